"""Zhou's planar-target light-plane calibration (paper ref. [14]; docs/method.md §Zhou baseline), the baseline.

Per image, a planar target (chessboard, circle grid or ChArUco: :mod:`lightplane.camera.targets`)
with the laser stripe across it: the board pose ``T_cam_board`` comes from its points
(found in the image, in a laser-off frame or in a separate lit pattern frame of the
same pose, then a distortion-aware ``cv2.solvePnP``); stripe centres inside the board are
back-projected and intersected with the board plane, which gives 3D points of
the light plane.  With two or more board poses the points span the plane, and
one plane is fitted to all of them by total least squares.

The plane's covariance is a leave-one-pose-out jackknife when there are four or
more poses: the board-pose errors, shared by all points of one image, dominate
and the residual scatter cannot see them.  With two or three poses only the
least-squares covariance from the residual scatter is available (optimistic).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import numpy as np

from lightplane.camera.board_pose import BoardPose, find_board_pose, pose_from_corners
from lightplane.camera.model import Camera, as_points, camera_record
from lightplane.core.errors import LightplaneError
from lightplane.core.geometry import plane_scatter, ray_plane, robust_sigma, tls_line
from lightplane.plane.calibrate import propagate_camera
from lightplane.plane.model import CameraDependence, LightPlane
from lightplane.plane.quality import (PlaneQuality, check_plane_quality, plane_geometry, plane_quality, stripe_image,
                                      working_volume)
from lightplane.camera.targets import as_target
from lightplane.core.io import to_gray_float, too_few_images_message
from lightplane.stripe.difference import laser_difference
from lightplane.stripe.extract import REFLECTANCE_SPREAD_MAX, extract_stripe, on_even_reflectance, sigma_for_width
from lightplane.stripe.options import StripePointsOptions
from lightplane.core.threads import with_blas_limited

__all__ = [
    "corners_clear_of_stripe",
    "board_polygon_mask",
    "board_area_mask",
    "stripe_points_on_board",
    "fit_plane",
    "ZhouCalibration",
    "plane_from_board_stripes",
    "board_views_and_stripes",
    "BoardViews",
    "BoardFrames",
    "BoardPlaneOptions",
    "find_board_views",
    "calibrate_plane_boards",
    "straight_stripe_inliers",
    "laser_light",
    "even_reflectance",
    "calibrate_plane_board",
]


def corners_clear_of_stripe(camera: Camera, pose: BoardPose, stripe_uv: np.ndarray, *,
                            clearance_px: float) -> np.ndarray:
    """(N,) bool: corners farther than ``clearance_px`` (undistorted px) from the stripe's line.

    A bright stripe across a corner pulls its sub-pixel position (the refinement
    window sees the stripe's edges); such corners are left out when the board
    had to be found in the laser-on image.
    """
    uv = camera.undistort_points(as_points(stripe_uv, 2, "stripe_uv"))
    m, _, nrm = tls_line(uv)
    c = camera.undistort_points(pose.corners_uv)
    return np.abs((c - m) @ nrm) > clearance_px


def board_polygon_mask(camera: Camera, pose: BoardPose, board, square_mm: float | None = None, *,
                       margin_squares: float | None = None, samples_per_edge: int = 20) -> np.ndarray:
    """uint8 mask (H, W) of the board area where stripe points are taken.

    The rectangle is :meth:`lightplane.camera.targets.Target.outline_mm` (chessboard: the
    inner-corner rectangle grown by 0.9 square — the outer squares reach one square
    beyond the inner corners, so it keeps to the printed squares; ``margin_squares``
    overrides the 0.9).  The outline is sampled along each edge and projected with
    distortion, so it follows curved edges.
    """
    import cv2

    target = as_target(board, square_mm)
    x0, x1, y0, y1 = target.outline_mm()
    if margin_squares is not None and target.kind == "chessboard":
        m, s_ = margin_squares * target.square_mm, target.square_mm
        x0, x1, y0, y1 = -m, (target.cols - 1) * s_ + m, -m, (target.rows - 1) * s_ + m
    t = np.linspace(0.0, 1.0, samples_per_edge, endpoint=False)
    edges = [np.column_stack([x0 + (x1 - x0) * t, np.full_like(t, y0)]),
             np.column_stack([np.full_like(t, x1), y0 + (y1 - y0) * t]),
             np.column_stack([x1 - (x1 - x0) * t, np.full_like(t, y1)]),
             np.column_stack([np.full_like(t, x0), y1 - (y1 - y0) * t])]
    xy = np.vstack(edges)
    p_cam = np.column_stack([xy, np.zeros(len(xy))]) @ pose.R_cam_board.T + pose.t_cam_board
    uv = camera.project(p_cam)
    mask = np.zeros((camera.height, camera.width), np.uint8)
    if np.all(np.isfinite(uv)):
        cv2.fillPoly(mask, [np.round(uv).astype(np.int32).reshape(-1, 1, 2)], 255)
    return mask


def _printed_rect(target) -> tuple[float, float, float, float]:
    """``(x0, x1, y0, y1)`` mm: the printed pattern's rectangle in board coordinates (chessboard: the
    outer squares, one square beyond the inner corners; other targets: their outline)."""
    x0, x1, y0, y1 = target.outline_mm()
    g = 0.1 * target.square_mm if target.kind == "chessboard" else 0.0
    return x0 - g, x1 + g, y0 - g, y1 + g


def _beyond_pattern(camera: Camera, pose: BoardPose, rect, shape: tuple[int, int], f: int) -> np.ndarray:
    """For every pixel of the image shrunk ``f`` times, ``shape = (h, w)``: how far (mm, board plane)
    it lies beyond each side of the rectangle ``rect`` (``(h, w, 4)``: x0, x1, y0, y1; negative
    inside; NaN off the plane)."""
    h, w = shape
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    uv = np.column_stack([(jj.ravel() + 0.5) * f - 0.5, (ii.ravel() + 0.5) * f - 0.5])
    X = ray_plane(camera.undistort_points(uv, normalized=True), pose.normal_cam, pose.t_cam_board)
    q = (X - pose.t_cam_board) @ pose.R_cam_board
    x0, x1, y0, y1 = rect
    return np.column_stack([x0 - q[:, 0], q[:, 0] - x1, y0 - q[:, 1], q[:, 1] - y1]).reshape(h, w, 4)


def _margin_widths(region: np.ndarray, excess: np.ndarray, start_mm: float, step_mm: float,
                   extent_mm: float) -> np.ndarray:
    """Per side of the pattern, how far (mm) the board reaches: across the strip straight beyond that
    side, the distance up to which the grown ``region`` keeps >= 80 % of the pixels seen (the board is a
    rectangle; a leak into a background as light as the board covers only part of the strip)."""
    widths = np.zeros(4)
    for k in range(4):
        others = [j for j in range(4) if j != k and j // 2 != k // 2]
        lateral = np.all(excess[..., others] <= 0, axis=-1) & (excess[..., k] > 0)
        d = excess[..., k][lateral]
        inr = region[lateral]
        w = 0.0
        for lo in np.arange(start_mm, extent_mm, step_mm):
            sel = (d > lo) & (d <= lo + step_mm)
            if np.count_nonzero(sel) < 3:
                if lo > w + 2 * step_mm:
                    break
                continue
            if np.mean(inr[sel]) < 0.8:
                break
            w = lo + step_mm
        widths[k] = w
    return widths


def _grown_margin(small: np.ndarray, excess: np.ndarray, ring: tuple[float, float], extent_mm: float) -> np.ndarray:
    """bool mask: the board's flat, evenly lit margin, grown from a ring just outside the pattern.

    Per side of the pattern, the ring's median level ``m`` and robust spread ``s`` (a side whose ring
    is not at the white level of the pattern's light parts, or not even, has no margin seen: it is
    the background or the board's edge); from the ring the region grows over pixels within
    ``max(4 s, 0.05 m)`` of ``m`` whose gradient stays that of the ring's, never beyond ``extent_mm``.
    """
    import cv2

    out = np.max(excess, axis=2)
    side = np.argmax(np.nan_to_num(excess, nan=-np.inf), axis=2)
    white = float(np.percentile(small[out < 0], 90)) if np.any(out < 0) else 0.0
    g = cv2.GaussianBlur(small, (0, 0), 1.0)
    gy, gx = np.gradient(g)
    grad = np.hypot(gx, gy)
    inside = np.isfinite(out) & (out > 0) & (out <= extent_mm)
    region = np.zeros(small.shape, bool)
    for k in range(4):
        seed = inside & (side == k) & (out > ring[0]) & (out <= ring[1])
        if np.count_nonzero(seed) < 8:
            continue
        m, s = float(np.median(g[seed])), robust_sigma(g[seed])
        if not (m > 0.5 * white and s < 0.15 * m):
            continue
        tol = max(4.0 * s, 0.05 * m)
        gtol = min(max(float(np.median(grad[seed])) + 6.0 * robust_sigma(grad[seed]), 0.1 * tol), 0.5 * tol)
        cand = inside & (np.abs(g - m) <= tol) & (grad <= gtol)
        _, lab = cv2.connectedComponents(cand.astype(np.uint8), connectivity=4)
        ids = np.unique(lab[seed & cand])
        region |= np.isin(lab, ids[ids > 0])
    return region


def board_area_mask(camera: Camera, pose: BoardPose, board, square_mm: float | None = None, *,
                    image: np.ndarray | None = None, channel: str | None = None,
                    margin_mm: float | None = None) -> np.ndarray:
    """uint8 mask (H, W): the printed pattern (:func:`board_polygon_mask`) and the flat board around it.

    The board plane extends beyond its pattern: in ``image`` (the lit board; a thin bright
    stripe in it is opened away) the white margin is grown outward from a ring just outside the
    printed pattern while it keeps the ring's level and smoothness (:func:`_grown_margin`,
    computed on the image shrunk to ~480 px), so it stops at the board's edges and never takes the
    background.  The growth stays within ``margin_mm`` of the printed pattern in board coordinates
    (None: the pattern's larger side); ``margin_mm=0`` or no ``image``: the pattern only.
    """
    import cv2

    target = as_target(board, square_mm)
    pattern = board_polygon_mask(camera, pose, target)
    if image is None or (margin_mm is not None and margin_mm <= 0):
        return pattern
    rect = _printed_rect(target)
    extent = float(margin_mm) if margin_mm is not None else max(rect[1] - rect[0], rect[3] - rect[2])
    gray = to_gray_float(image, channel)
    H, W = gray.shape
    f = max(1, int(np.ceil(max(H, W) / 480)))
    h, w = H // f, W // f
    small = cv2.resize(np.ascontiguousarray(gray[:h * f, :w * f]), (w, h), interpolation=cv2.INTER_AREA)
    small = cv2.morphologyEx(small, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5)))
    excess = _beyond_pattern(camera, pose, rect, (h, w), f)
    out = np.max(excess, axis=2)
    mm_px = target.square_mm * f / _corner_spacing_px(pose.corners_uv)  # mm per shrunk pixel
    d1 = max(0.15 * target.square_mm, 1.5 * mm_px)
    region = _grown_margin(small, excess, (d1, d1 + max(0.35 * target.square_mm, 3.0 * mm_px)), extent)
    ell = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    region = cv2.morphologyEx((region | (out <= 0)).astype(np.uint8), cv2.MORPH_CLOSE, ell) > 0
    widths = _margin_widths(region, excess, d1, mm_px, extent)
    region &= np.all(np.nan_to_num(excess, nan=np.inf) <= widths, axis=2)  # the board: a rectangle
    region = cv2.erode(region.astype(np.uint8), np.ones((3, 3), np.uint8))
    full = np.zeros((H, W), np.uint8)
    full[:h * f, :w * f] = cv2.resize(region * 255, (w * f, h * f), interpolation=cv2.INTER_NEAREST)
    return np.maximum(full, pattern)


def stripe_points_on_board(camera: Camera, pose: BoardPose, stripe_uv: np.ndarray) -> np.ndarray:
    """Back-project stripe centres (distorted px, ``(N, 2)``) onto the board plane → ``(N, 3)`` mm, camera frame.

    The board plane is ``n·X = n·t`` with ``n`` the board z axis and ``t`` its
    origin; the ray ``s (x, y, 1)`` meets it at ``s = n·t / n·(x, y, 1)``.
    """
    uv = as_points(stripe_uv, 2, "stripe_uv")
    xy = camera.undistort_points(uv, normalized=True)
    return ray_plane(xy, pose.normal_cam, pose.t_cam_board)


def fit_plane(points_mm: np.ndarray, *, meta: dict | None = None) -> LightPlane:
    """Total-least-squares plane through ``(N, 3)`` points (mm) with its 4x4 covariance.

    The normal is the scatter matrix's smallest eigenvector.  With residual
    variance ``σ² = Σr² / (N − 3)`` and the other eigenpairs ``(λ_k, e_k)``,
    first-order perturbation gives ``Cov(n) = σ² Σ_k e_k e_kᵀ / λ_k``; with the
    centroid ``c``, ``d = −n·c`` so ``Cov(n, d) = −Cov(n) c`` and
    ``Var(d) = cᵀ Cov(n) c + σ² / N``.

    >>> rng = np.random.default_rng(1)
    >>> p = np.column_stack([rng.uniform(-50, 50, (100, 2)), np.full(100, 300.0)])
    >>> fit_plane(p)
    LightPlane(+0.000000 x +0.000000 y +1.000000 z -300.0000 = 0)
    """
    p = as_points(points_mm, 3, "points_mm")
    p = p[np.all(np.isfinite(p), axis=1)]
    if len(p) < 3:
        raise LightplaneError(f"a plane fit needs at least 3 points, got {len(p)}")
    c, lam, V = plane_scatter(p)  # eigenvalues ascending
    if lam[1] <= 1e-12 * max(lam[2], 1e-300):
        raise LightplaneError("the points are collinear: they do not determine a plane (need two or more board poses)")
    n = V[:, 0]
    d = -float(n @ c)
    r = (p - c) @ n
    dof = max(len(p) - 3, 1)
    sigma2 = float(r @ r) / dof
    cov_n = sigma2 * (np.outer(V[:, 2], V[:, 2]) / lam[2] + np.outer(V[:, 1], V[:, 1]) / lam[1])
    cov = np.zeros((4, 4))
    cov[:3, :3] = cov_n
    cov[:3, 3] = cov[3, :3] = -cov_n @ c
    cov[3, 3] = float(c @ cov_n @ c) + sigma2 / len(p)
    info = {"n_points": int(len(p)), "residual_rms_mm": float(np.sqrt(np.mean(r**2)))}
    return LightPlane(n, d, cov, meta={**info, **(meta or {})})


@dataclass(frozen=True)
class ZhouCalibration:
    """Result of Zhou's planar-target calibration.

    Attributes
    ----------
    plane : LightPlane with covariance; ``meta`` holds method "zhou" and per-image diagnostics.
    points_cam_mm : (N, 3) the stripe points on the boards, camera frame.
    view_index : (N,) int, which pose each point comes from.
    poses : tuple of BoardPose.
    residual_mm : (N,) signed distance of each point from the fitted plane.
    """

    plane: LightPlane
    points_cam_mm: np.ndarray
    view_index: np.ndarray
    poses: tuple
    residual_mm: np.ndarray = field(repr=False)
    quality: PlaneQuality | None = field(default=None, repr=False)

    @property
    def residual_rms_mm(self) -> float:
        return float(np.sqrt(np.mean(self.residual_mm**2)))

    def assess(self, camera: Camera, scale_mm: float) -> PlaneQuality:
        """Each pose's stripe points against the plane and their stripe noise
        (:func:`lightplane.plane.quality.plane_quality`; ``scale_mm``: the board's square or pitch)."""
        imgs = [stripe_image(camera, pose.name or f"pose {k}", self.points_cam_mm[self.view_index == k],
                             pose.normal_cam, pose.t_cam_board) for k, pose in enumerate(self.poses)]
        return plane_quality(camera, self.plane.normal, self.plane.d, imgs, scale_mm)


def plane_from_board_stripes(camera: Camera, poses: Sequence[BoardPose], stripes_uv: Sequence[np.ndarray], *,
                             min_points_per_view: int = 10, jackknife_min_views: int = 4,
                             meta: dict | None = None) -> ZhouCalibration:
    """Zhou's method from board poses and stripe centres (distorted px, on each board).

    The plane's covariance: with ``jackknife_min_views`` or more poses, the
    leave-one-pose-out jackknife (it sees the board-pose errors, shared by all
    points of a pose); with fewer, the least-squares covariance from the residual
    scatter (:func:`fit_plane`), which does not and is optimistic.
    ``plane.meta["covariance_method"]`` says which.

    Raises LightplaneError with fewer than two usable poses (one board plane
    only gives a line of the light plane) or when the points are collinear.
    """
    if len(poses) != len(stripes_uv):
        raise LightplaneError(f"{len(poses)} board poses but {len(stripes_uv)} stripe point sets")
    pts, idx, diag = [], [], []
    for k, (pose, uv) in enumerate(zip(poses, stripes_uv)):
        p = stripe_points_on_board(camera, pose, uv) if len(uv) else np.zeros((0, 3))
        p = p[np.all(np.isfinite(p), axis=1)]
        used = len(p) >= min_points_per_view
        diag.append({**pose.to_dict(), "n_stripe_points": int(len(p)), "used": bool(used)})
        if used:
            pts.append(p)
            idx.append(np.full(len(p), k))
    if len(pts) < 2:
        raise LightplaneError(f"Zhou's method needs the stripe on at least 2 board poses, got {len(pts)} "
                              f"(of {len(poses)} images with a board; each needs ≥ {min_points_per_view} stripe points)")
    P, I = np.vstack(pts), np.concatenate(idx)
    plane = fit_plane(P)
    res = plane.signed_distance(P)
    cov_fit = plane.covariance
    assert cov_fit is not None  # fit_plane gives its covariance
    cov, cov_method = cov_fit, "fit residuals (optimistic: ignores board-pose errors)"
    if len(pts) >= jackknife_min_views:
        # leave-one-pose-out jackknife: each pose's error moves all its points together,
        # which the residual scatter cannot see
        theta = np.array([fit_plane(np.vstack(pts[:k] + pts[k + 1:])).coefficients for k in range(len(pts))])
        dev = theta - theta.mean(axis=0)
        cov = (len(pts) - 1) / len(pts) * dev.T @ dev
        cov_method = f"jackknife over {len(pts)} board poses"
    for k, dg in enumerate(diag):
        sel = I == k
        dg["residual_rms_mm"] = float(np.sqrt(np.mean(res[sel] ** 2))) if sel.any() else None
    m = {**plane.meta, "method": "zhou", "covariance_method": cov_method,
         "covariance_fit": cov_fit.tolist(), "images": diag, "camera": camera_record(camera), **(meta or {})}
    plane = LightPlane(plane.normal, plane.d, cov, meta=m)
    return ZhouCalibration(plane, P, I, tuple(poses), res)


def straight_stripe_inliers(uv_undist: np.ndarray, *, tol_px: float = 1.0, min_tol_px: float = 0.05,
                            iterations: int = 300, rng: np.random.Generator | None = None) -> np.ndarray:
    """Which stripe points lie on the dominant straight line (RANSAC), ``(N,)`` bool.

    The light plane meets a flat board in a 3D line, whose image in *undistorted*
    pixels is straight; points off it (Steger responses at square edges, glints)
    are dropped; so are points biased where the stripe crosses a reflectance edge
    (a square's border), by tightening the band to three robust standard
    deviations of the inliers' residuals (never below ``min_tol_px``).
    ``tol_px``: RANSAC band, distance from the line, undistorted px.
    """
    uv = as_points(uv_undist, 2, "uv_undist")
    n = len(uv)
    if n < 2:
        return np.zeros(n, bool)
    rng = np.random.default_rng(0) if rng is None else rng
    i = rng.integers(0, n, iterations)
    j = rng.integers(0, n, iterations)
    d = uv[j] - uv[i]
    ln = np.linalg.norm(d, axis=1)
    ok = ln > 1e-6
    if not ok.any():
        return np.zeros(n, bool)
    nrm = np.column_stack([-d[ok, 1], d[ok, 0]]) / ln[ok, None]
    dist = np.abs(nrm @ uv.T - np.sum(nrm * uv[i[ok]], axis=1)[:, None])  # (K, N)
    best = np.argmax((dist < tol_px).sum(axis=1))
    inl = dist[best] < tol_px
    for it in range(5):  # refine on the inliers (total least squares), then tighten to 3 robust sigma
        if inl.sum() < 3:
            break
        m, _, nrm = tls_line(uv[inl])
        r = np.abs((uv - m) @ nrm)
        tol = tol_px if it == 0 else min(tol_px, max(3.0 * robust_sigma(r[inl], center=False), min_tol_px))
        new = r < tol
        if np.array_equal(new, inl):
            break
        inl = new
    return inl


#: Stripe centres are kept where the board's level (the lit frame over its white) is at least
#: ``EVEN_LEVEL_MIN`` and its max over min within the stripe's reach stays under ``EVEN_SPREAD_MAX``
#: (:func:`even_reflectance`).
EVEN_LEVEL_MIN = 0.5
EVEN_SPREAD_MAX = REFLECTANCE_SPREAD_MAX


def laser_light(image: np.ndarray, lit: np.ndarray, mask: np.ndarray,
                channel: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The laser's light alone and the board's reflectance: ``(stripe, level)``, float images.

    ``lit``: the same board pose lit, laser off (a pattern frame or a laser-off frame).  The laser
    image's ambient part is ``lit`` times the frames' exposure ratio (the median of ``image / lit``
    over the light board pixels of ``mask``: 1 for a laser-off frame of the same exposure, ~0.03
    for a dark laser frame), which is subtracted.  ``level``: ``lit`` over the board's white (its
    90th percentile in ``mask``), the printed reflectance under the stripe (:func:`even_reflectance`).
    """
    g = to_gray_float(image, channel)
    p = to_gray_float(lit, channel)
    m = (mask > 0) & (p > 0)
    white = float(np.percentile(p[m], 90)) if np.any(m) else 0.0
    if not white > 0:
        return np.clip(g - p, 0, None), np.ones_like(p)
    bright = m & (p > 0.5 * white)
    k = float(np.median(g[bright] / p[bright])) if np.any(bright) else 1.0
    return np.clip(g - k * p, 0, None), p / white


def even_reflectance(level: np.ndarray, uv: np.ndarray, width_px: float, normals: np.ndarray) -> np.ndarray:
    """(N,) bool: the stripe centres ``uv`` (N, 2, px) that lie on light, even print.

    A stripe on paper is the laser's irradiance times the paper's reflectance; where a printed
    edge (a square's or a marker's border) runs within the stripe's reach, the product's peak
    moves towards the lighter side, by a good part of a pixel when the edge runs along the stripe,
    and every centre along it moves alike (no number of centres averages it out).  Dividing by
    the lit frame does not undo it: the blur spreads the edge over both frames differently.  Kept:
    the centres whose ``level`` (:func:`laser_light`: the lit board over its white) is at least
    :data:`EVEN_LEVEL_MIN` (not on ink: the stripe there is dim and next to the edges) and, on every
    line across the stripe (``normals``) within its reach, varies by less than :data:`EVEN_SPREAD_MAX`
    (max over min): :func:`lightplane.stripe.extract.on_even_reflectance`.
    """
    return on_even_reflectance(level, uv, normals, float(width_px), sigma_for_width(float(width_px)),
                               full_scale=1.0, min_level=EVEN_LEVEL_MIN)


def _stripe_in_mask(camera: Camera, image: np.ndarray, mask: np.ndarray, background: np.ndarray | None,
                    width_px: float | None, channel: str | None, corners_uv: np.ndarray | None = None,
                    pattern_mask: np.ndarray | None = None, lit: np.ndarray | None = None) -> tuple[np.ndarray, str]:
    """Stripe centres (distorted px) inside ``mask`` and on one straight line (undistorted), after
    subtracting the laser-off frame in the channels that carry the stripe
    (:func:`lightplane.stripe.difference.laser_difference`; ``pattern_mask``: the printed pattern, whose white
    level a stripe must exceed without one; default ``mask``), and a note on the channels ("" if none).
    ``lit``: the lit board of the same pose (laser off): its ambient part is subtracted
    (:func:`laser_light`) and only centres on light, even print are kept (:func:`even_reflectance`)."""

    import cv2

    grid = None if corners_uv is None else corners_uv.reshape(-1, 2)
    spacing = None if grid is None else _corner_spacing_px(grid)
    if lit is not None:
        if lit.shape[:2] != image.shape[:2]:
            raise LightplaneError(f"lit board frame shape {lit.shape} differs from image shape {image.shape}")
        img, level = laser_light(image, lit, mask if pattern_mask is None else pattern_mask, channel)
        note = ""
        background = lit  # what follows treats the frame as background-subtracted
    elif background is not None:
        if background.shape != image.shape:
            raise LightplaneError(f"background image shape {background.shape} differs from image shape {image.shape}")
        diff = laser_difference(image, background, channel, region=mask)
        img, note = diff.image, diff.note
    else:
        # No laser-off frame: the white squares, touching corner to corner, are bright
        # ridges too.  A white top-hat narrower than a square removes them and keeps
        # the (much narrower) stripe.
        img, note = to_gray_float(image, channel), ""
        raw = img
        if spacing is not None:
            k = int(max(5, round(0.35 * spacing))) | 1
            img = cv2.morphologyEx(img, cv2.MORPH_TOPHAT, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    channel = None
    # no along-stripe smoothing: on a board the stripe crosses reflectance edges every square,
    # and smoothing spreads their bias along it; the plane fit (and the cross-ratio line fit)
    # average hundreds of centres anyway (clean renders: residual 0.0042 vs 0.0072 mm)
    sp = extract_stripe(img, StripePointsOptions(width_px=width_px, channel=channel, sigma_along_px=0.0), mask=mask > 0)
    uv = np.asarray(sp.uv, dtype=np.float64).reshape(-1, 2)
    if len(uv):
        ij = np.clip(np.round(uv).astype(int), 0, [mask.shape[1] - 1, mask.shape[0] - 1])
        keep = mask[ij[:, 1], ij[:, 0]] > 0
        if background is None:
            # without a laser-off frame, trust only centres brighter than the white squares
            # (the 90th percentile of the board area): square corners survive the top-hat, and
            # centres on dark squares sit next to reflectance edges that bias them
            pm = mask if pattern_mask is None else pattern_mask
            white = float(np.percentile(raw[pm > 0], 90))
            keep &= raw[ij[:, 1], ij[:, 0]] > white * 1.05 + 2.0
        if lit is not None:
            fwhm = np.asarray(sp.width, float).ravel()
            w = width_px if width_px is not None else (float(np.nanmedian(fwhm)) if np.any(np.isfinite(fwhm)) else 3.0)
            keep &= even_reflectance(level, uv, w, np.asarray(sp.normals, float).reshape(-1, 2))
        uv = uv[keep]
    if len(uv) and grid is not None and spacing is not None:
        # X-junction responses at the corners line up along the corner rows: drop them
        d2 = ((uv[:, None, :] - grid[None, :, :]) ** 2).sum(axis=2).min(axis=1)
        uv = uv[d2 > (0.2 * spacing) ** 2]
    if len(uv):
        uv = uv[straight_stripe_inliers(camera.undistort_points(uv))]
    # a stripe across the board gives about one centre per pixel over several squares;
    # fewer than one square's worth of points on a line is clutter, not the laser
    if spacing is not None and len(uv) < spacing:
        uv = uv[:0]
    return uv, note


@dataclass(frozen=True)
class BoardViews:
    """Per image: the board pose and the stripe centres on it, or why the image was skipped.

    poses, stripes, names : the usable images (same order as given); skipped : image name → reason;
    notes : image name → how its stripe was taken, where that differs from the request (colour channels
    clipped in the laser-off frame, :func:`lightplane.stripe.difference.laser_difference`).
    """

    poses: list
    stripes: list
    names: list
    skipped: dict
    notes: dict = field(default_factory=dict)


@dataclass(frozen=True)
class BoardFrames:
    """The laser images of a board calibration (:func:`calibrate_plane_board`, :func:`find_board_views`)
    and the frames that go with them.

    - ``images``: laser images (gray or BGR arrays; None for one that could not be read), the board in
      a different pose in each (or several laser frames per pose with ``pattern_images``).
    - ``pattern_images``: per laser image, the lit board frame (laser off) of its pose, in which the
      board is found (the laser frames may be dark, low-exposure ones); the same frame object given
      for several images is searched once.
    - ``background_images``: laser-off frames, one per image (same pose; also used to find the board)
      or one for all; subtracted before stripe extraction.
    - ``names``: the images' names (default ``image 0``, ``image 1``...).
    - ``skipped``: name → reason of images already skipped by the caller (unreadable files), for
      :func:`calibrate_plane_board`'s message and result.
    """

    images: Sequence
    pattern_images: Sequence | None = None
    background_images: Sequence | None = None
    names: Sequence[str] | None = None
    skipped: dict | None = None


@dataclass(frozen=True)
class BoardPlaneOptions:
    """Options of Zhou's board calibration (:func:`calibrate_plane_board`; the first three also of
    :func:`find_board_views`).  Checked on construction.

    - ``stripe_width_px``, ``channel``: passed to :func:`lightplane.stripe.extract.extract_stripe`.
    - ``region_px``: ``(x0, y0, x1, y1)`` px: stripe centres only with ``x0 <= u < x1``, ``y0 <= v < y1``
      (one laser's stripe among several, told apart by where it is in the image).
    - ``min_points_per_view``: fewer stripe points on a board skip the image.
    - ``min_views``: fewer usable images raise LightplaneError, saying why the others were skipped.
    - ``keep_suspect``: keep a plane whose stripe points contradict their stripe noise
      (:mod:`lightplane.plane.quality`), marked in ``meta["quality"]``, instead of raising.
    - ``board_margin_mm``: stripe points are taken on the board around its printed pattern too
      (:func:`board_area_mask`: the white margin the lit board shows, grown from the pattern); None:
      as far as the image shows it (up to the pattern's larger side); a value: at most that far
      beyond the printed pattern (mm, every side), still only where the image shows board; 0: the
      pattern only.
    - ``reflectance``: where a lit frame of the pose is given (a pattern frame, or a laser-off frame
      per image), keep the stripe centres only on light, even print (:func:`even_reflectance`: the
      printed edges under the stripe do not move the centres kept).  None (default): for ChArUco
      boards, whose markers put edges under every stripe (on renders the per-pose offset of the
      centres drops from 0.072 to ~0.02 px RMS, benchmarks/bench_board_stripe.py); True: for every
      board; False: never (the laser-off frame only subtracted, every centre kept).  Chessboards
      and circle grids gain nothing measurable on renders, and on real dark laser frames whose
      stripe saturates on the white squares (FabScan) the filter drops the centres that remain.
    """

    stripe_width_px: float | None = None
    channel: str | None = None
    region_px: tuple[float, float, float, float] | None = None
    min_points_per_view: int = 10
    min_views: int = 2
    keep_suspect: bool = False
    board_margin_mm: float | None = None
    reflectance: bool | None = None

    def __post_init__(self):
        if self.board_margin_mm is not None and not (np.isfinite(self.board_margin_mm) and self.board_margin_mm >= 0):
            raise LightplaneError(f"board_margin_mm (--board-margin) must be finite and >= 0 mm, got {self.board_margin_mm}")
        if self.region_px is not None and len(self.region_px) != 4:
            raise LightplaneError(f"region_px must be (x0, y0, x1, y1), got {self.region_px}")
        if int(self.min_points_per_view) < 0:
            raise LightplaneError(f"min_points_per_view must be >= 0, got {self.min_points_per_view}")


def _frames(frames: "BoardFrames | Sequence") -> BoardFrames:
    return frames if isinstance(frames, BoardFrames) else BoardFrames(frames)


def find_board_views(frames: "BoardFrames | Sequence", camera: Camera, board, square_mm: float | None = None,
                     options: BoardPlaneOptions | None = None, *, min_stripe_points: int = 0, skip: bool = True,
                     progress: Callable[[int], None] | None = None, pose_cache: dict | None = None) -> BoardViews:
    """Board pose and on-board stripe centres for each image.

    ``frames``: :class:`BoardFrames` (or just the laser images).  ``board``: a
    :class:`lightplane.camera.targets.Target` or ``(cols, rows)`` chessboard with ``square_mm``.
    Where the board is looked for: in ``pattern_images[k]`` (the lit board, laser off, of
    image ``k``'s pose; the laser image may then be a dark frame in which the board
    cannot be seen), else in the laser-off ``background_images[k]`` (one per image,
    also subtracted before stripe extraction; a single one is only subtracted), else
    in the image itself (corners the stripe runs over are then left out of the pose).
    ``images[k]`` may be None (unreadable: pass its reason in a skipped entry upstream).
    ``options``: :class:`BoardPlaneOptions` (its ``stripe_width_px``, ``channel``, ``region_px``).

    With ``skip`` an image whose board is not found, or with fewer than
    ``min_stripe_points`` stripe centres on the board, is skipped with its reason;
    without it the first such image raises LightplaneError.
    ``pose_cache``: a dict shared between calls on the same pattern frame objects (several
    lasers' frames of the same poses): each pattern frame's board is searched once.
    """
    fr = _frames(frames)
    opts = BoardPlaneOptions() if options is None else options
    target = as_target(board, square_mm)
    images = fr.images
    names = list(fr.names) if fr.names is not None else [f"image {i}" for i in range(len(images))]
    if len(names) != len(images):
        raise LightplaneError(f"{len(images)} images but {len(names)} names")
    if fr.background_images is not None and len(fr.background_images) not in (1, len(images)):
        raise LightplaneError(f"give one background image, or one per image ({len(images)}); "
                              f"got {len(fr.background_images)}")
    if fr.pattern_images is not None and len(fr.pattern_images) != len(images):
        raise LightplaneError(f"give one pattern frame per laser image ({len(images)}); got {len(fr.pattern_images)}")
    out = BoardViews([], [], [], {})
    pattern_poses: dict[int, BoardPose | str] = {} if pose_cache is None else pose_cache
    for k, img in enumerate(images):
        try:
            if img is None:
                raise LightplaneError(f"{names[k]}: not a readable image")
            pose, stripe = _board_view(camera, target, fr, k, names[k], opts, pattern_poses, out.notes)
            if len(stripe) < min_stripe_points:
                raise LightplaneError(f"{names[k]}: " + (f"only {len(stripe)} stripe points on the board"
                                                         if len(stripe) else "no stripe on the board"))
        except LightplaneError as e:
            if not skip:
                raise
            out.skipped[names[k]] = str(e).removeprefix(f"{names[k]}: ")
        else:
            out.stripes.append(stripe)
            out.poses.append(pose)
            out.names.append(names[k])
        if progress is not None:
            progress(k)
    return out


def _board_view(camera: Camera, target, fr: BoardFrames, k: int, name: str, opts: BoardPlaneOptions,
                pattern_poses: dict, notes: dict | None = None) -> tuple[BoardPose, np.ndarray]:
    """Image ``k``'s board pose and the stripe centres on the board (:func:`find_board_views`); ``notes``
    receives the image's note on the colour channels the stripe was taken from, if any."""
    img = fr.images[k]
    bgs, pats = fr.background_images, fr.pattern_images
    bg = None
    if bgs is not None:
        bg = bgs[k if len(bgs) > 1 else 0]
    per_image = bgs is not None and bg is not None and len(bgs) == len(fr.images)
    pat = None
    if pats is not None:
        pat = pats[k]
        pose = _pattern_pose(camera, target, pat, name, opts.channel, pattern_poses)
        camera.check_image(img, name)
        pose = replace(pose, name=name)
    else:
        pose = find_board_pose(bg if per_image and bg is not None else img, camera, target, name=name,
                               channel=opts.channel)
    pattern_mask = board_polygon_mask(camera, pose, target)
    lit = pat if pat is not None else (bg if per_image else img)
    mask = board_area_mask(camera, pose, target, image=lit, channel=opts.channel, margin_mm=opts.board_margin_mm)
    if opts.region_px is not None:
        x0, y0, x1, y1 = opts.region_px
        u, v = np.arange(mask.shape[1]), np.arange(mask.shape[0])
        inside = ((v >= y0) & (v < y1))[:, None] & ((u >= x0) & (u < x1))[None, :]
        mask = np.where(inside, mask, 0).astype(mask.dtype)
    if pat is not None and bg is None and _same_exposure(img, pat, pattern_mask, opts.channel):
        bg = pat  # a lit laser frame and its pattern frame: subtract it as the laser-off frame
    lit_frame = pat if pat is not None else (bg if per_image else None)
    stripe, note = _stripe_in_mask(camera, img, mask, bg, opts.stripe_width_px, opts.channel, pose.corners_uv,
                                   pattern_mask, lit=lit_frame if _even_print(opts, target) else None)
    if note and notes is not None:
        notes[name] = note
    if pats is None and not per_image and len(stripe) >= 2:
        # corners found in the laser-on image: leave out those the stripe runs over
        clear = corners_clear_of_stripe(camera, pose, stripe, clearance_px=0.35 * _corner_spacing_px(pose.corners_uv))
        if not clear.all() and np.count_nonzero(clear) >= 6:
            pose = pose_from_corners(camera, pose.corners_uv, target, name=name, corner_ok=clear, ids=pose.ids)
    return pose, stripe


def _even_print(opts: BoardPlaneOptions, target) -> bool:
    """Whether the stripe centres are kept only on even print (``opts.reflectance``; None: ChArUco boards)."""
    return target.kind == "charuco" if opts.reflectance is None else bool(opts.reflectance)


def _pattern_pose(camera: Camera, target, pat, name: str, channel: str | None, pattern_poses: dict) -> BoardPose:
    """The board pose of pattern frame ``pat``, found once per frame object (``pattern_poses``: its pose or why not)."""
    if pat is None:
        raise LightplaneError(f"{name}: no usable pattern frame for this laser frame")
    if id(pat) not in pattern_poses:
        try:
            pattern_poses[id(pat)] = find_board_pose(pat, camera, target, name=name, channel=channel)
        except LightplaneError as e:
            pattern_poses[id(pat)] = str(e).removeprefix(f"{name}: ")
    pose = pattern_poses[id(pat)]
    if isinstance(pose, str):
        raise LightplaneError(f"{name}: pattern frame: {pose}")
    return pose


def _corner_spacing_px(corners_uv: np.ndarray) -> float:
    """Typical distance (px) between consecutive detected points: the board's scale in the image."""
    return float(np.median(np.linalg.norm(np.diff(corners_uv.reshape(-1, 2), axis=0), axis=1)))


def _same_exposure(image: np.ndarray, pattern: np.ndarray, mask: np.ndarray, channel: str | None) -> bool:
    """Whether a laser frame was taken at the pattern frame's exposure (the board's median level
    within a factor 2), so the pattern frame can be subtracted; dark laser frames are not."""
    m = mask > 0
    a = float(np.median(to_gray_float(image, channel)[m]))
    b = float(np.median(to_gray_float(pattern, channel)[m]))
    return b > 0 and 0.5 < a / b < 2.0


def board_views_and_stripes(images: Sequence[np.ndarray], camera: Camera, *, board, square_mm: float | None = None,
                            background_images: Sequence[np.ndarray] | None = None,
                            image_names: Sequence[str] | None = None, stripe_width_px: float | None = None,
                            channel: str | None = None, progress: Callable[[int], None] | None = None):
    """Board pose and on-board stripe centres for each image → (poses, stripes_uv, names).

    :func:`find_board_views` without skipping: raises LightplaneError naming the
    first image where the board is not found.
    """
    v = find_board_views(BoardFrames(images, background_images=background_images, names=image_names), camera, board,
                         square_mm, BoardPlaneOptions(stripe_width_px=stripe_width_px, channel=channel), skip=False,
                         progress=progress)
    return v.poses, v.stripes, v.names


@with_blas_limited
def calibrate_plane_board(frames: "BoardFrames | Sequence", camera: Camera, board, square_mm: float | None = None,
                          options: BoardPlaneOptions | None = None, *,
                          progress: Callable[[int], None] | None = None,
                          pose_cache: dict | None = None) -> ZhouCalibration:
    """Zhou's planar-target light-plane calibration from images of a board with the stripe.

    Parameters
    ----------
    frames : :class:`BoardFrames` (the laser images with their pattern or laser-off frames, names and
        the images skipped before), or just the laser images.
    camera : the calibrated camera.
    board : a :class:`lightplane.camera.targets.Target` (chessboard, circle grid, ChArUco), or
        ``(cols, rows)`` chessboard inner corners with ``square_mm`` (mm).
    options : :class:`BoardPlaneOptions` (stripe width and channel, image region, fewest stripe points
        per board and fewest usable images; defaults when omitted).
    progress : ``progress(k)`` after image ``k``.
    pose_cache : see :func:`find_board_views` (the board of each pattern frame found once for all lasers).

    Returns
    -------
    ZhouCalibration; its ``plane`` has the covariance and ``meta["images"]`` per-image
    diagnostics (pose, stripe points used, residual RMS), ``meta["skipped"]`` the
    images not used with their reason.
    """

    fr = _frames(frames)
    opts = BoardPlaneOptions() if options is None else options
    target = as_target(board, square_mm)
    pre = dict(fr.skipped or {})
    v = find_board_views(fr, camera, target, options=opts, min_stripe_points=opts.min_points_per_view, skip=True,
                         progress=progress, pose_cache=pose_cache)
    why = {**pre, **v.skipped}
    n_min = max(2, opts.min_views)
    if len(v.poses) < n_min:
        raise LightplaneError("Zhou's method: " + too_few_images_message("images", len(v.poses), n_min, why.items()))
    z = plane_from_board_stripes(camera, v.poses, v.stripes, min_points_per_view=opts.min_points_per_view,
                                 meta={"board": [target.cols, target.rows], "square_mm": float(target.square_mm),
                                       "target": target.to_dict(), "skipped": why,
                                       "board_margin_mm": opts.board_margin_mm,
                                       "stripe_channels": _channel_summary(v.notes),
                                       "laser_frames": "pattern frames" if fr.pattern_images is not None else
                                       ("background-subtracted" if fr.background_images is not None
                                        else "laser-on only")})
    q = z.assess(camera, float(target.square_mm))
    per_image_bg = fr.background_images is not None and len(fr.background_images) > 1
    rec = check_plane_quality(q, keep=opts.keep_suspect, background_per_image=per_image_bg)
    geometry = plane_geometry(z.points_cam_mm, z.view_index, z.plane.normal, z.plane.d, z.plane.covariance)
    if geometry["refusal"] and not opts.keep_suspect:
        raise LightplaneError(geometry["refusal"] + "; or keep the plane as it is with --keep-suspect")
    meta = {**z.plane.meta, "quality": rec, "working_volume": working_volume(z.points_cam_mm), "geometry": geometry}
    if camera.covariance is not None:
        meta[CameraDependence.KEY] = _camera_dependence(camera, target, v, z.plane, opts).to_dict()
    plane = LightPlane(z.plane.normal, z.plane.d, z.plane.covariance, meta=meta)
    return replace(z, plane=plane, quality=q)


def _camera_dependence(camera: Camera, target, views: BoardViews, plane: LightPlane,
                       opts: BoardPlaneOptions) -> CameraDependence:
    """The plane's dependence on the intrinsics (:func:`lightplane.plane.calibrate.propagate_camera`): the
    board poses solved again from the same corners and the same stripe centres put on them, with
    other intrinsics."""
    def solve(cam: Camera) -> LightPlane:
        poses = [pose_from_corners(cam, p.corners_uv, target, name=p.name, corner_ok=p.corner_ok, ids=p.ids)
                 for p in views.poses]
        return plane_from_board_stripes(cam, poses, views.stripes, min_points_per_view=opts.min_points_per_view,
                                        jackknife_min_views=len(poses) + 1).plane

    return propagate_camera(solve, camera, plane)


def _channel_summary(notes: dict) -> str | None:
    """One line for the plane file: how many images had their stripe from other channels, and the first note."""
    if not notes:
        return None
    first = next(iter(notes.values()))
    return first if len(notes) == 1 else f"{len(notes)} images: {first} (and alike)"


def calibrate_plane_boards(frames: BoardFrames, camera: Camera, board, lasers: dict,
                           options: BoardPlaneOptions | None = None, *,
                           progress: Callable[[str, int, int], None] | None = None) -> dict:
    """Zhou's calibration of one plane per laser from the same board poses (``lightplane calibrate-plane-board``).

    ``lasers``: laser name (None for one laser) → ``(indices of its images in frames, its
    :class:`lightplane.stripe.lasers.LaserSelector` or None)``; a laser's selector gives its channel and
    image region (else ``options``').  Images named in ``frames.skipped`` are left out (and listed).  Each
    pattern frame's board is found once for all lasers.  ``progress(label, done, total)`` after each image.
    Returns ``{name: ZhouCalibration}``; a laser's error names it.
    """
    opts = BoardPlaneOptions() if options is None else options
    names = [f"image {i}" for i in range(len(frames.images))] if frames.names is None else list(frames.names)
    skipped = frames.skipped or {}
    pose_cache: dict = {}  # each pattern frame's board found once for all lasers
    bgs, pats = frames.background_images, frames.pattern_images
    results = {}
    for lname, (idx, sel) in lasers.items():
        keep = [k for k in idx if names[k] not in skipped]
        label = "board poses and stripes" + ("" if lname is None else f", laser {lname}")
        fr = BoardFrames([frames.images[k] for k in keep],
                         pattern_images=None if pats is None else [pats[k] for k in keep],
                         background_images=None if bgs is None else (bgs if len(bgs) == 1 else [bgs[k] for k in keep]),
                         names=[names[k] for k in keep],
                         skipped={names[k]: skipped[names[k]] for k in idx if names[k] in skipped})
        laser_opts = opts if sel is None else replace(opts, channel=sel.channel, region_px=sel.region)
        step = None if progress is None else (lambda i, label=label, n=len(keep): progress(label, i + 1, n))
        try:
            results[lname] = calibrate_plane_board(fr, camera, board, options=laser_opts, progress=step,
                                                   pose_cache=pose_cache)
        except LightplaneError as e:
            if sel is None:
                raise
            raise LightplaneError(f"laser {sel.describe()}: {e}") from None
    return results
