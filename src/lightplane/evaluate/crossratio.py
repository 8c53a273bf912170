"""Accuracy evaluation by cross-ratio invariance (docs/method.md §Cross-ratio check, paper §4.3, Eq. 16, Tables 1–2).

A chessboard stands in the measuring volume with the laser stripe across it.
On a line ``l`` of corners (a row, or a column) the corners A, B, C have known
board coordinates; the stripe crosses ``l`` at D.  A line-to-line central
projection preserves the cross-ratio (paper Eq. 16)::

    CR = ((u_a − u_c)(u_b − u_d)) / ((u_b − u_c)(u_a − u_d))
       = ((X_A − X_C)(X_B − X_D)) / ((X_B − X_C)(X_A − X_D))

so D's board coordinate follows from its image position: the *ideal* point.
Image positions are taken along the fitted line's direction in *undistorted*
pixels (the paper's v-version of Eq. 16 has typos, and distorted pixels do not
lie on a line).  Distances between ideal points of one board pose are the
reference ``dt``; the same crossings triangulated with a calibrated light plane
give ``dm``; ``Δ = dt − dm`` per pair and its RMS are the paper's Table 2.

Distances are frame-independent, so ideal points stay in the board frame
(mm, z = 0) while measured points are camera-frame.

>>> ideal = np.array([[45.715, 20, 0], [44.284, 30, 0]])           # paper Table 1, No. 1–2
>>> zhou = np.array([[3.262, 12.453, 447.108], [13.011, 13.432, 445.060]])
>>> e = distance_errors(ideal, zhou, [(0, 1)])
>>> round(float(e.dt_mm[0]), 3), round(float(e.dm_mm[0]), 3)
(10.102, 10.01)
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from lightplane.camera.model import Camera, as_points
from lightplane.core.errors import LightplaneError
from lightplane.plane.triangulate import triangulate_normalized
from lightplane.core.geometry import robust_sigma, tls_line
from lightplane.plane.model import LightPlane
from lightplane.camera.targets import as_target
from lightplane.core.io import too_few_images_message
from lightplane.plane.zhou import BoardFrames, BoardPlaneOptions, find_board_views

__all__ = [
    "DistanceErrors",
    "distance_errors",
    "cross_ratio",
    "point_from_cross_ratio",
    "CrossRatioOptions",
    "EvaluateOptions",
    "CrossRatioPoints",
    "cross_ratio_points",
    "first_point_pairs",
    "Evaluation",
    "evaluate_views",
    "evaluate_images",
]


# ------------------------------------------------------------------ distances
@dataclass(frozen=True)
class DistanceErrors:
    """Reference vs measured distances between pairs of points (paper Table 2).

    Attributes
    ----------
    pairs : (K, 2) int
        Indices into the point arrays.
    dt_mm : (K,) float
        Reference ("ideal", true) distances, mm.
    dm_mm : (K,) float
        Measured distances, mm.
    delta_mm : (K,) float
        ``dt − dm``, mm.
    rms_mm : float
        ``sqrt(mean(delta²))``, mm.
    """

    pairs: np.ndarray
    dt_mm: np.ndarray
    dm_mm: np.ndarray
    delta_mm: np.ndarray
    rms_mm: float

    @property
    def max_abs_mm(self) -> float:
        return float(np.max(np.abs(self.delta_mm))) if self.delta_mm.size else float("nan")

    def to_dict(self) -> dict:
        return {
            "pairs": [
                {"pair": [int(i), int(j)], "dt_mm": float(t), "dm_mm": float(m), "delta_mm": float(e)}
                for (i, j), t, m, e in zip(self.pairs, self.dt_mm, self.dm_mm, self.delta_mm)
            ],
            "rms_mm": self.rms_mm,
        }


def _as_pairs(pairs, n: int) -> np.ndarray:
    p = np.asarray(pairs)
    if p.size == 0:
        raise LightplaneError("pairs must hold at least one (i, j) pair")
    if p.ndim != 2 or p.shape[1] != 2 or not np.issubdtype(p.dtype, np.integer):
        raise LightplaneError(f"pairs must be (K, 2) integer indices, got shape {p.shape} dtype {p.dtype}")
    if np.any(p < 0) or np.any(p >= n):
        raise LightplaneError(f"pairs index out of range for {n} points")
    if np.any(p[:, 0] == p[:, 1]):
        raise LightplaneError("pairs must join two different points")
    return p.astype(np.intp)


def distance_errors(ideal_mm: np.ndarray, measured_mm: np.ndarray, pairs) -> DistanceErrors:
    """Distance errors between point pairs (paper Table 2).

    Parameters
    ----------
    ideal_mm : (N, 3) or (N, 2) reference points, mm, any frame (e.g. board coordinates).
    measured_mm : (N, 3) measured points, mm, any frame (e.g. camera) — distances
        are frame-independent, so the two arrays need not share a frame.
    pairs : (K, 2) int, the point pairs ``(i, j)``.

    Returns
    -------
    DistanceErrors with ``dt = |ideal_i − ideal_j|``, ``dm = |measured_i − measured_j|``,
    ``delta = dt − dm`` and ``rms = sqrt(mean(delta²))``.  A pair with a non-finite
    measured point (e.g. a grazing ray) raises: an RMS silently over fewer pairs
    would not be comparable.
    """
    ideal = np.asarray(ideal_mm, dtype=np.float64)
    if ideal.ndim == 2 and ideal.shape[1] == 2:
        ideal = np.column_stack([ideal, np.zeros(len(ideal))])
    ideal = as_points(ideal, 3, "ideal_mm")
    meas = as_points(measured_mm, 3, "measured_mm")
    if len(ideal) != len(meas):
        raise LightplaneError(f"ideal_mm and measured_mm must have the same length, got {len(ideal)} and {len(meas)}")
    p = _as_pairs(pairs, len(ideal))
    dt = np.linalg.norm(ideal[p[:, 0]] - ideal[p[:, 1]], axis=1)
    dm = np.linalg.norm(meas[p[:, 0]] - meas[p[:, 1]], axis=1)
    if not (np.all(np.isfinite(dt)) and np.all(np.isfinite(dm))):
        raise LightplaneError("distance_errors: a pair involves a non-finite point")
    delta = dt - dm
    return DistanceErrors(p, dt, dm, delta, float(np.sqrt(np.mean(delta**2))))


# ------------------------------------------------------------------ cross-ratio
def cross_ratio(a, b, c, d):
    """Cross-ratio ``((a − c)(b − d)) / ((b − c)(a − d))`` of four collinear coordinates (paper Eq. 16)."""
    a, b, c, d = (np.asarray(x, dtype=np.float64) for x in (a, b, c, d))
    return ((a - c) * (b - d)) / ((b - c) * (a - d))


def point_from_cross_ratio(cr, A, B, C):
    """The coordinate D with ``cross_ratio(A, B, C, D) == cr`` (paper Eq. 16 solved for D).

    With ``k = cr (B − C) / (A − C)``: ``B − D = k (A − D)``, so ``D = (k A − B) / (k − 1)``.

    >>> round(float(point_from_cross_ratio(cross_ratio(0.0, 1.0, 3.0, 1.7), 0.0, 1.0, 3.0)), 12)
    1.7
    """
    cr, A, B, C = (np.asarray(x, dtype=np.float64) for x in (cr, A, B, C))
    k = cr * (B - C) / (A - C)
    return (k * A - B) / (k - 1.0)


def _line_map(X: np.ndarray, s: np.ndarray) -> tuple[float, float, float]:
    """1D homography ``s = (p X + q) / (r X + 1)`` fitted to corners (least squares, algebraic).

    Three corners determine it exactly, which is the cross-ratio construction;
    more corners average the corner noise.
    """
    A = np.column_stack([X, np.ones_like(X), -X * s])
    sol, *_ = np.linalg.lstsq(A, s, rcond=None)
    return float(sol[0]), float(sol[1]), float(sol[2])


@dataclass(frozen=True)
class CrossRatioOptions:
    """How the stripe's crossings with the target's lines of points are found (:func:`cross_ratio_points`).

    ``lines``: ``"rows"``, ``"columns"`` or ``"auto"`` (the family the stripe crosses more
    often; ties go to the steeper crossing).  ``corners_used``: ``"three"`` — the paper's
    construction with A, B, C = first, middle and last corner of the line; ``"all"`` — a
    least-squares 1D homography through every corner of the line (the same map, less
    sensitive to corner noise).  ``window_px``: half-width of the band around a corner line
    in which stripe points are used; default: all of them.  The stripe on a flat board is
    straight in undistorted pixels, so one line through all its centres is both the most
    precise and the only choice that always bridges the dark squares on either side of a
    corner line, where the stripe is faint or missing.  Give a band (e.g. 1.5 square
    spacings) for a board that is not flat.  ``min_angle_deg``: crossings flatter than this
    are skipped (ill-conditioned).  ``min_stripe_points``: fewest stripe points for one crossing.
    """

    lines: str = "auto"
    corners_used: str = "all"
    window_px: float | None = None
    min_angle_deg: float = 15.0
    min_stripe_points: int = 4

    def __post_init__(self) -> None:
        if self.lines not in ("rows", "columns", "auto"):
            raise LightplaneError(f"lines must be 'rows', 'columns' or 'auto', got {self.lines!r}")
        if self.corners_used not in ("three", "all"):
            raise LightplaneError(f"corners_used must be 'three' or 'all', got {self.corners_used!r}")


@dataclass(frozen=True)
class EvaluateOptions(CrossRatioOptions):
    """:class:`CrossRatioOptions` and the stripe extraction of :func:`evaluate_images`:
    ``stripe_width_px`` (None: estimated) and the laser's colour ``channel`` (None: gray)."""

    stripe_width_px: float | None = None
    channel: str | None = None


@dataclass(frozen=True)
class CrossRatioPoints:
    """Ideal points where the stripe crosses lines of chessboard corners.

    Attributes
    ----------
    p_board_mm : (M, 3) float, ideal points in board coordinates (mm, z = 0).
    uv_undist : (M, 2) float, the stripe's crossing of each corner line, undistorted pixels.
    line_index : (M,) int, index of the corner row (``family == "rows"``) or column.
    family : "rows" or "columns".
    crossing_angle_deg : (M,) float, angle between stripe and corner line in the image.
    n_stripe_points : (M,) int, stripe points used for each crossing.
    """

    p_board_mm: np.ndarray
    uv_undist: np.ndarray
    line_index: np.ndarray
    family: str
    crossing_angle_deg: np.ndarray
    n_stripe_points: np.ndarray

    def __len__(self) -> int:
        return len(self.p_board_mm)


def _crossings(grid: np.ndarray, okg: np.ndarray, origin_mm: np.ndarray, stripe: np.ndarray, square_mm: float,
               family: str, options: CrossRatioOptions) -> CrossRatioPoints:
    """Crossings of the stripe with the lattice lines: ``grid`` (ny, nx, 2) points (undistorted px),
    ``okg`` (ny, nx) which of them exist and are usable, lattice point (x, y) at
    ``origin_mm + (x, y)·square_mm`` on the board."""
    rows, cols = okg.shape
    if family == "rows":
        lines = [(grid[j], okg[j]) for j in range(rows)]
    else:
        lines = [(grid[:, i], okg[:, i]) for i in range(cols)]
    window_px, min_stripe_points = options.window_px, options.min_stripe_points
    half_window = np.inf if window_px is None else float(window_px)
    pts, uvs, idx, angles, counts = [], [], [], [], []
    for li, (full_line, line_ok) in enumerate(lines):
        if np.count_nonzero(line_ok) < 3:
            continue
        X = np.flatnonzero(line_ok).astype(np.float64)  # board coordinate in squares
        line = full_line[line_ok]
        m, t, _ = tls_line(line)
        if (line[-1] - line[0]) @ t < 0:
            t = -t  # along increasing board coordinate
        nrm = np.array([-t[1], t[0]])
        s_c = (line - m) @ t
        step = float(np.median(np.diff(s_c) / np.diff(X)))
        rel = stripe - m
        s, h = rel @ t, rel @ nrm
        near = np.abs(h) < half_window
        if np.isfinite(half_window):
            near &= (s > s_c[0] - step * (X[0] + 1)) & (s < s_c[-1] + step * (len(full_line) - X[-1]))
        if np.count_nonzero(near) < min_stripe_points or not (h[near].min() < 0 < h[near].max()):
            continue
        q = np.column_stack([s[near], h[near]])
        for _ in range(4):  # fit the (locally straight) stripe, drop points beyond 3 robust sigma
            qm, qd, _ = tls_line(q)
            res = np.abs((q - qm) @ np.array([-qd[1], qd[0]]))
            keep = res <= max(3.0 * robust_sigma(res, center=False), 0.05)
            if keep.all() or np.count_nonzero(keep) < min_stripe_points:
                break
            q = q[keep]
        angle = float(np.degrees(np.arctan2(abs(qd[1]), abs(qd[0]))))
        if angle < options.min_angle_deg:
            continue
        s_d = qm[0] - qm[1] * qd[0] / qd[1]  # where the stripe line meets h = 0
        s_lo, s_hi = s_c[0] - step * X[0], s_c[-1] + step * (len(full_line) - 1 - X[-1])  # the full line
        if not (s_lo - step <= s_d <= s_hi + step):
            continue
        if options.corners_used == "three":
            ia, ib, ic = 0, (len(line) - 1) // 2, len(line) - 1
            x_d = float(point_from_cross_ratio(cross_ratio(s_c[ia], s_c[ib], s_c[ic], s_d), X[ia], X[ib], X[ic]))
        else:
            x0 = X[0]  # condition the algebraic fit: both coordinates in squares from the first corner
            p_, q_, r_ = _line_map(X - x0, (s_c - s_c[0]) / step)
            sd = (s_d - s_c[0]) / step
            x_d = x0 + (sd - q_) / (p_ - r_ * sd)
        along, fixed = x_d * square_mm, li * square_mm
        pts.append([along + origin_mm[0], fixed + origin_mm[1], 0.0] if family == "rows"
                   else [fixed + origin_mm[0], along + origin_mm[1], 0.0])
        uvs.append(m + s_d * t)
        idx.append(li)
        angles.append(angle)
        counts.append(len(q))
    return CrossRatioPoints(
        np.asarray(pts, dtype=np.float64).reshape(-1, 3),
        np.asarray(uvs, dtype=np.float64).reshape(-1, 2),
        np.asarray(idx, dtype=np.intp),
        family,
        np.asarray(angles, dtype=np.float64),
        np.asarray(counts, dtype=np.intp),
    )


def cross_ratio_points(corners_uv_undist: np.ndarray, board, stripe_uv_undist: np.ndarray, *,
                       square_mm: float | None = None, options: CrossRatioOptions = CrossRatioOptions(),
                       corner_ok: np.ndarray | None = None, ids=None) -> CrossRatioPoints:
    """Ideal points where the stripe crosses the target's lines of points (paper §4.3, Eq. 16).

    The lines are the rows and columns of the target's lattice
    (:meth:`lightplane.camera.targets.Target.lattice_index`): chessboard and ChArUco corners,
    the dots of circle grids (an asymmetric grid's rows hold every other lattice point,
    its columns every other row).

    Parameters
    ----------
    corners_uv_undist : (N, 2) float
        The target's points in *undistorted* pixels, in the order of ``ids`` (default: all
        points in id order; for a chessboard OpenCV's order, row by row, ``cols`` per row,
        corner ``k`` at board coordinates ``((k % cols)·square, (k // cols)·square, 0)``).
    board : a :class:`lightplane.camera.targets.Target`, or (cols, rows) chessboard inner corners.
    ids : (N,) the target's ids of the points (partial ChArUco views).
    stripe_uv_undist : (N, 2) float
        Stripe centre points in undistorted pixels, on the board only (mask first).
    square_mm : float, the square size (with a (cols, rows) board).
    options : :class:`CrossRatioOptions` (the line family, the corners used, the stripe
        band, the flattest crossing, the fewest stripe points).
    corner_ok : (N,) bool, points to use (e.g. not those the stripe runs over);
        a line needs three usable points.  Default: all.

    Returns
    -------
    CrossRatioPoints (possibly empty: the caller decides whether that is an error).
    """
    if square_mm is not None and not (np.isfinite(square_mm) and square_mm > 0):
        raise LightplaneError(f"square_mm must be positive, got {square_mm}")
    target = as_target(board, square_mm)  # checks the board
    nx, ny = target.lattice_shape
    if nx < 3 or ny < 2:
        raise LightplaneError(f"board needs at least 3 points per row and 2 rows, got {nx}x{ny}")
    corners = as_points(corners_uv_undist, 2, "corners_uv_undist")
    ids_ = np.arange(target.n_points) if ids is None else np.asarray(ids, dtype=np.intp).ravel()
    if len(corners) != len(ids_):
        raise LightplaneError(f"corners_uv_undist has {len(corners)} points, "
                              f"{'the ids say' if ids is not None else target.describe() + ' needs'} {len(ids_)}")
    stripe = as_points(stripe_uv_undist, 2, "stripe_uv_undist")
    stripe = stripe[np.all(np.isfinite(stripe), axis=1)]
    if corner_ok is None:
        ok = np.ones(len(corners), bool)
    else:
        ok = np.asarray(corner_ok, bool).ravel()
        if ok.shape != (len(corners),):
            raise LightplaneError(f"corner_ok must have {len(corners)} entries, got {np.shape(corner_ok)}")
    lat = target.lattice_index(ids_)
    grid = np.full((ny, nx, 2), np.nan)
    okg = np.zeros((ny, nx), bool)
    grid[lat[:, 1], lat[:, 0]] = corners
    okg[lat[:, 1], lat[:, 0]] = ok & np.all(np.isfinite(corners), axis=1)
    def crossings(family: str) -> CrossRatioPoints:
        return _crossings(grid, okg, target.lattice_origin_mm, stripe, float(target.square_mm), family, options)

    lines = options.lines
    if lines != "auto":
        if lines == "columns" and ny < 3:
            raise LightplaneError("lines='columns' needs at least 3 rows of corners")
        return crossings(lines)
    cand = [crossings("rows")]
    if ny >= 3:
        cand.append(crossings("columns"))
    return max(cand, key=lambda c: (len(c), float(np.mean(c.crossing_angle_deg)) if len(c) else 0.0))


def first_point_pairs(groups: np.ndarray) -> np.ndarray:
    """Pairs ``(first, k)`` inside each group of points (the paper's Table 2 layout).

    ``groups`` (M,) labels (e.g. the image index); points of one group are paired
    with the group's first point, as the paper pairs test point 1 with 2–5 and 6 with 7–10.
    """
    g = np.asarray(groups).ravel()
    out: list[tuple[int, int]] = []
    for lab in dict.fromkeys(g.tolist()):
        members = np.flatnonzero(g == lab)
        out.extend((int(members[0]), int(k)) for k in members[1:])
    return np.asarray(out, dtype=np.intp).reshape(-1, 2)


# ------------------------------------------------------------------ pipeline
@dataclass(frozen=True)
class Evaluation:
    """Cross-ratio evaluation of one or more light planes on board views.

    Attributes
    ----------
    ideal_board_mm : (M, 3) ideal points, board frame of their own view (mm).
    ideal_cam_mm : (M, 3) the same points in the camera frame through the board pose (mm).
    uv_undist : (M, 2) stripe crossings, undistorted pixels.
    view_index : (M,) int, which view each point comes from.
    line_index : (M,) int, corner row/column of each point.
    pairs : (K, 2) int, point pairs (inside one view).
    measured_mm : tuple of (M, 3), per plane, the crossings triangulated on that plane (camera frame).
    errors : tuple of DistanceErrors, per plane.
    point_error_mm : tuple of (M,), per plane, |measured − ideal_cam| (depends on the pose too).
    labels : tuple of str, a name per plane.
    views : per view, its diagnostics; view_names : the views' names (``view_index`` indexes them);
    skipped : image name → reason, for the images not used (:func:`evaluate_images`).
    """

    ideal_board_mm: np.ndarray
    ideal_cam_mm: np.ndarray
    uv_undist: np.ndarray
    view_index: np.ndarray
    line_index: np.ndarray
    pairs: np.ndarray
    measured_mm: tuple
    errors: tuple
    point_error_mm: tuple
    labels: tuple
    views: tuple = field(default=(), repr=False)
    skipped: dict = field(default_factory=dict)
    view_names: tuple = ()

    def to_dict(self) -> dict:
        return {
            "points": [
                {"view": int(v), "line": int(li), "uv_undist_px": uv.tolist(), "ideal_board_mm": pb.tolist(),
                 "ideal_cam_mm": pc.tolist(),
                 "measured_mm": {lab: m[k].tolist() for lab, m in zip(self.labels, self.measured_mm)}}
                for k, (v, li, uv, pb, pc) in enumerate(zip(self.view_index, self.line_index, self.uv_undist,
                                                           self.ideal_board_mm, self.ideal_cam_mm))
            ],
            "planes": {lab: e.to_dict() for lab, e in zip(self.labels, self.errors)},
            "views": list(self.views),
            "view_names": list(self.view_names),
            "skipped": dict(self.skipped),
        }


def evaluate_views(camera: Camera, planes: Sequence[LightPlane], views: Sequence, stripes: Sequence[np.ndarray], *,
                   board, square_mm: float | None = None, labels: Sequence[str] | None = None,
                   options: CrossRatioOptions = CrossRatioOptions(), view_names: Sequence[str] | None = None
                   ) -> Evaluation:
    """Cross-ratio evaluation from detected boards and stripe points (paper §4.3).

    Parameters
    ----------
    camera : Camera.
    planes : light planes to evaluate (camera frame).
    views : per view, a board detection with ``corners_uv`` (distorted px, OpenCV order),
        ``R_cam_board`` (3, 3) and ``t_cam_board`` (3,) mm (see
        :func:`lightplane.plane.zhou.find_board`).
    stripes : per view, (N, 2) stripe centres in distorted pixels, on the board.
    board : a :class:`lightplane.camera.targets.Target`, or (cols, rows) chessboard inner corners with ``square_mm``.
    options : :class:`CrossRatioOptions`, how the crossings are found.

    Raises LightplaneError when the stripe crosses no corner line in any view, or
    when no view gives two points (no pair to measure).
    """
    planes = list(planes)
    if not planes:
        raise LightplaneError("at least one light plane is needed")
    labels = tuple(labels) if labels is not None else tuple(f"plane{i + 1}" for i in range(len(planes)))
    names = list(view_names) if view_names is not None else [f"view {i}" for i in range(len(views))]
    if len(stripes) != len(views):
        raise LightplaneError(f"{len(views)} views but {len(stripes)} stripe point sets")
    ideal_b_l: list[np.ndarray] = []
    ideal_c_l: list[np.ndarray] = []
    uvs_l: list[np.ndarray] = []
    vidx_l: list[np.ndarray] = []
    lidx_l: list[np.ndarray] = []
    diag: list[dict] = []
    for k, (view, stripe) in enumerate(zip(views, stripes)):
        corners_u = camera.undistort_points(view.corners_uv)
        stripe_u = camera.undistort_points(as_points(stripe, 2, "stripe")) if len(stripe) else np.zeros((0, 2))
        cr = cross_ratio_points(corners_u, board, stripe_u, square_mm=square_mm, options=options,
                                corner_ok=getattr(view, "corner_ok", None), ids=getattr(view, "ids", None))
        diag.append({"view": names[k], "n_points": len(cr), "family": cr.family,
                     "lines": cr.line_index.tolist()})
        if len(cr) == 0:
            continue
        ideal_b_l.append(cr.p_board_mm)
        ideal_c_l.append(cr.p_board_mm @ np.asarray(view.R_cam_board).T + np.asarray(view.t_cam_board))
        uvs_l.append(cr.uv_undist)
        vidx_l.append(np.full(len(cr), k))
        lidx_l.append(cr.line_index)
    if not ideal_b_l:
        raise LightplaneError("the stripe crosses no corner row or column in any image "
                              "(is the laser on the board, and not parallel to the rows?)")
    ideal_b, ideal_c, uvs = np.vstack(ideal_b_l), np.vstack(ideal_c_l), np.vstack(uvs_l)
    vidx, lidx = np.concatenate(vidx_l), np.concatenate(lidx_l)
    pairs = first_point_pairs(vidx)
    if len(pairs) == 0:
        raise LightplaneError("no image gives two stripe crossings: nothing to compare (need the stripe across "
                              "at least two corner rows of one board)")
    xy = camera.pixels_to_normalized_linear(uvs)
    measured, errors, perr = [], [], []
    for plane, lab in zip(planes, labels):
        t = triangulate_normalized(plane, xy)
        if not np.all(t.valid):
            raise LightplaneError(f"{lab}: {np.count_nonzero(~t.valid)} stripe crossings cannot be triangulated "
                                  "(ray parallel to the plane or plane behind the camera)")
        measured.append(t.points)
        errors.append(distance_errors(ideal_b, t.points, pairs))
        perr.append(np.linalg.norm(t.points - ideal_c, axis=1))
    return Evaluation(ideal_b, ideal_c, uvs, vidx, lidx, pairs, tuple(measured), tuple(errors), tuple(perr),
                      labels, tuple(diag))


def evaluate_images(images: Sequence, camera: Camera, planes: Sequence[LightPlane], *,
                    board, square_mm: float | None = None, options: EvaluateOptions = EvaluateOptions(),
                    background_images: Sequence[np.ndarray] | None = None, labels: Sequence[str] | None = None,
                    image_names: Sequence[str] | None = None, skipped: dict | None = None,
                    progress=None) -> Evaluation:
    """Cross-ratio evaluation from images of a board with the stripe (paper §4.3).

    Per image: the board (a :class:`lightplane.camera.targets.Target`, or (cols, rows) chessboard
    inner corners with ``square_mm``) is found and its pose solved, stripe centres are
    extracted inside the board (after subtracting the laser-off ``background_images``
    when given: :func:`lightplane.plane.zhou.find_board_views`; ``options.stripe_width_px`` and
    ``options.channel``), then :func:`evaluate_views` (with ``options``: :class:`EvaluateOptions`).  Images where the board is not found or the stripe is
    missing are skipped with their reason (``Evaluation.skipped``, with the caller's
    ``skipped``); fewer than one usable image raises LightplaneError saying why.
    ``progress(i)`` is called after each image.
    """

    target = as_target(board, square_mm)
    v = find_board_views(BoardFrames(images, background_images=background_images, names=image_names), camera, target,
                         options=BoardPlaneOptions(stripe_width_px=options.stripe_width_px, channel=options.channel),
                         min_stripe_points=2, skip=True, progress=progress)
    why = {**(skipped or {}), **v.skipped}
    if not v.poses:
        raise LightplaneError(too_few_images_message("images", 0, 1, why.items()))
    ev = evaluate_views(camera, planes, v.poses, v.stripes, board=target, labels=labels, options=options,
                        view_names=v.names)
    return replace(ev, skipped=why, view_names=tuple(v.names))
