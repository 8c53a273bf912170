"""Zhang intrinsic calibration with OpenCV, and its diagnostics (SPEC §3).

Corners by ``cv2.findChessboardCornersSB`` (sub-pixel by construction), the
solve by ``cv2.calibrateCameraExtended`` (standard deviations of the intrinsics,
per-view RMS errors).  The result keeps every view's residuals so the report
can show where the model fits worst.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from .camera import Camera
from .errors import LightplaneError

__all__ = ["BoardView", "IntrinsicsCalibration", "find_board", "refine_corners", "board_points",
           "calibrate_camera", "plot_residuals", "INTRINSIC_NAMES"]

INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


def board_points(board: tuple[int, int], square_mm: float) -> np.ndarray:
    """Inner-corner coordinates ``(cols*rows, 3)`` in the board frame (mm, z = 0), row-major
    (x along a row, matching OpenCV's corner order)."""
    cols, rows = board
    if square_mm <= 0:
        raise LightplaneError(f"square size must be positive, got {square_mm} mm")
    xs, ys = np.meshgrid(np.arange(cols), np.arange(rows))
    return np.column_stack([xs.ravel() * square_mm, ys.ravel() * square_mm, np.zeros(cols * rows)])


def refine_corners(gray: np.ndarray, corners_uv: np.ndarray, spacing_px: float, *, sigma_frac: float = 0.2,
                   radius_frac: float = 0.6, max_radius_px: float = 30.0, max_iter: int = 30,
                   tol_px: float = 1e-5) -> np.ndarray:
    """Chessboard corners refined by gradient orthogonality on the pixel grid, ``(N, 2)`` px.

    Each corner ``q`` solves ``sum_p w(p - q) g_p g_p^T (q - p) = 0`` (Förstner's
    operator, as ``cv2.cornerSubPix``): the image gradient ``g_p`` (Scharr) at every
    pixel ``p`` near the corner is orthogonal to ``p - q`` on the two board edges through
    it.  Unlike ``cornerSubPix`` the sums run over the integer pixel grid (no bilinear
    resampling of the image at sub-pixel offsets, whose phase-dependent error is
    ~0.01 px) with a Gaussian weight ``w`` of σ = ``sigma_frac * spacing_px`` re-centred
    on ``q`` at each iteration, cut at ``radius_frac * spacing_px`` (< 1 spacing: only the
    two edges of this corner).  ``spacing_px`` is the smallest corner spacing on the
    board (foreshortened).  On rendered 13x9 boards tilted 30–60° (realistic noise) the
    error against the exact corners drops from 0.029 px RMS (cornerSubPix) to 0.019 px;
    noise-free from 0.020 to 0.011 px.  Corners whose solve is singular, or that move
    by more than a quarter of the spacing, keep their input position.
    """
    import cv2

    g = np.asarray(gray, dtype=np.float64)
    if g.ndim != 2:
        raise LightplaneError(f"refine_corners: gray must be a 2-D image, got shape {g.shape}")
    q0 = np.asarray(corners_uv, dtype=np.float64).reshape(-1, 2)
    if not spacing_px > 0:
        raise LightplaneError(f"refine_corners: spacing_px must be positive, got {spacing_px}")
    gx = cv2.Scharr(g, cv2.CV_64F, 1, 0) / 32.0
    gy = cv2.Scharr(g, cv2.CV_64F, 0, 1) / 32.0
    h, w = g.shape
    radius = max(2.0, min(radius_frac * spacing_px, max_radius_px))
    sigma = sigma_frac * spacing_px * radius / (radius_frac * spacing_px)
    r = int(np.ceil(radius))
    oy, ox = np.mgrid[-r:r + 1, -r:r + 1]
    ox, oy = ox.ravel(), oy.ravel()
    q = q0.copy()
    for _ in range(max_iter):
        base = np.round(q).astype(int)
        px = np.clip(base[:, :1] + ox, 0, w - 1)
        py = np.clip(base[:, 1:] + oy, 0, h - 1)
        dx, dy = px - q[:, :1], py - q[:, 1:]
        d2 = dx**2 + dy**2
        wt = np.exp(-d2 / (2.0 * sigma**2)) * (d2 <= radius**2)
        a, b = gx[py, px], gy[py, px]
        axx, axy, ayy = (wt * a * a).sum(1), (wt * a * b).sum(1), (wt * b * b).sum(1)
        bx = (wt * (a * a * px + a * b * py)).sum(1)
        by = (wt * (a * b * px + b * b * py)).sum(1)
        det = axx * ayy - axy**2
        ok = det > 1e-12 * np.maximum(axx * ayy, 1e-300)
        with np.errstate(divide="ignore", invalid="ignore"):
            qn = np.column_stack([(ayy * bx - axy * by) / det, (axx * by - axy * bx) / det])
        qn[~ok] = q[~ok]
        step = np.abs(qn - q).max() if len(q) else 0.0
        q = qn
        if step < tol_px:
            break
    bad = ~np.all(np.isfinite(q), axis=1) | (np.linalg.norm(q - q0, axis=1) > 0.25 * spacing_px)
    q[bad] = q0[bad]
    return q


def find_board(image: np.ndarray, board: tuple[int, int], *, subpix: bool = True,
               refine: bool = False) -> np.ndarray | None:
    """Chessboard inner corners ``(cols*rows, 2)`` (distorted px) or None if not found.

    ``cv2.findChessboardCornersSB`` finds the board robustly; ``cv2.cornerSubPix``
    then refines each corner with a half-window of 30 % of the local corner
    spacing (at most 11 px), as OpenCV's classic pipeline does.  That refinement
    reproduces the published Ciclop calibration to 0.01 px, where the SB
    detector's own sub-pixel estimate differs by up to 0.9 px in cy.  With ``refine``
    (and ``subpix``) :func:`refine_corners` then polishes them on the pixel grid with
    a wider window (0.6 spacing), which lowers the corner error by ~1.5x on rendered
    boards (see its docstring); off by default because the wider window also takes in
    a laser stripe crossing the board (Zhou's images): :func:`calibrate_camera`, whose
    boards carry no stripe, turns it on.
    """
    import cv2

    from .io import to_gray_float

    gray = image if image.ndim == 2 else to_gray_float(image)
    if gray.dtype != np.uint8:
        g = gray.astype(np.float64)
        lo, hi = np.percentile(g, [0.5, 99.5])
        gray = np.clip((g - lo) * (255.0 / max(hi - lo, 1e-9)), 0, 255).astype(np.uint8)
    flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE
    found, corners = cv2.findChessboardCornersSB(gray, tuple(board), flags=flags)
    if not found or corners is None:
        return None
    c = corners.reshape(-1, 2).astype(np.float32)
    if subpix:
        cols, rows = board
        grid = c.reshape(rows, cols, 2)
        spacing = min(np.linalg.norm(np.diff(grid, axis=1), axis=2).min(),
                      np.linalg.norm(np.diff(grid, axis=0), axis=2).min())
        half = int(np.clip(np.floor(0.3 * spacing), 2, 11))
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)
        c = cv2.cornerSubPix(gray, c.reshape(-1, 1, 2), (half, half), (-1, -1), crit).reshape(-1, 2)
        if refine and spacing >= 8:
            return refine_corners(gray, c, float(spacing))
    return c.astype(np.float64)


@dataclass(frozen=True)
class BoardView:
    """One image's board detection: ``corners_uv`` (N, 2) px or None when not found."""

    name: str
    corners_uv: np.ndarray | None
    image_size: tuple[int, int]  # (width, height)


@dataclass(frozen=True)
class IntrinsicsCalibration:
    """Result of :func:`calibrate_camera`.

    ``std`` holds the standard deviations of ``INTRINSIC_NAMES`` (px for fx..cy,
    unitless for the distortion); ``per_view_rms_px`` the RMS reprojection error of
    each used view (same order as ``used``); ``residuals_px`` per used view (N, 2).
    """

    camera: Camera
    rms_px: float
    std: dict[str, float]
    used: tuple[str, ...]
    not_found: tuple[str, ...]
    per_view_rms_px: np.ndarray
    residuals_px: tuple[np.ndarray, ...]
    corners_uv: tuple[np.ndarray, ...]
    rvecs: tuple[np.ndarray, ...]
    tvecs: tuple[np.ndarray, ...]
    board: tuple[int, int]
    square_mm: float
    flags: int
    options: dict = field(default_factory=dict)

    def ranked_views(self) -> list[tuple[str, float]]:
        """(view name, RMS px), worst first."""
        order = np.argsort(-self.per_view_rms_px)
        return [(self.used[i], float(self.per_view_rms_px[i])) for i in order]

    def T_cam_board(self, i: int) -> np.ndarray:
        """4x4 pose of the board in used view ``i`` (board points → camera frame)."""
        import cv2

        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(self.rvecs[i])[0]
        T[:3, 3] = self.tvecs[i].ravel()
        return T

    def to_dict(self) -> dict:
        return {
            "std": self.std,
            "per_view_rms_px": dict(zip(self.used, map(float, self.per_view_rms_px))),
            "views_used": list(self.used),
            "views_board_not_found": list(self.not_found),
            "board": {"cols": self.board[0], "rows": self.board[1], "square_mm": self.square_mm},
            "flags": self.flags,
        }


def calibrate_camera(
    images: Sequence,
    board: tuple[int, int],
    square_mm: float,
    *,
    names: Sequence[str] | None = None,
    flags: int = 0,
    rotate_deg: int = 0,
    min_views: int = 3,
    refine: bool = True,
    progress: Callable[[int, int], None] | None = None,
) -> IntrinsicsCalibration:
    """Zhang calibration from chessboard images (SPEC §3).

    Parameters
    ----------
    images : sequence of image arrays or paths
    board : (cols, rows) inner corners
    square_mm : square size, mm (sets the scale of the poses only)
    flags : ``cv2.CALIB_*`` flags for ``calibrateCameraExtended`` (0: 5 coefficients, as OpenCV's default)
    rotate_deg : clockwise rotation applied to path inputs on reading (0/90/180/270)
    min_views : fewer usable views raise :class:`LightplaneError`
    refine : polish the corners with :func:`refine_corners` (see :func:`find_board`); on
        rendered realistic boards it lowers OpenCV's std of cx, cy by ~1.6x; on the real
        Ciclop captures the RMS drops from 0.242 to 0.223 px and cx moves by 0.4 px

    All images must have one size.  Views where the board is not found are listed
    in ``not_found``.
    """
    import cv2

    from .io import read_image

    if len(images) == 0:
        raise LightplaneError("no images given")
    if names is None:
        names = [str(im) if isinstance(im, (str, Path)) else f"image {i}" for i, im in enumerate(images)]
    views: list[BoardView] = []
    size = None
    for i, (im, name) in enumerate(zip(images, names)):
        img = read_image(im, rotate_deg=rotate_deg) if isinstance(im, (str, Path)) else np.asarray(im)
        if img.ndim not in (2, 3):
            raise LightplaneError(f"{name}: not an image (shape {img.shape})")
        h, w = img.shape[:2]
        if size is None:
            size = (w, h)
        elif size != (w, h):
            raise LightplaneError(f"{name}: size {w}x{h} px differs from the first image's {size[0]}x{size[1]} px")
        views.append(BoardView(name, find_board(img, board, refine=refine), (w, h)))
        if progress:
            progress(i + 1, len(images))
    found = [v for v in views if v.corners_uv is not None]
    not_found = tuple(v.name for v in views if v.corners_uv is None)
    if not found:
        raise LightplaneError(f"the {board[0]}x{board[1]} board was found in none of the {len(views)} images")
    if len(found) < min_views:
        raise LightplaneError(
            f"the board was found in only {len(found)} image(s); at least {min_views} usable views are needed"
        )
    obj = board_points(board, square_mm).astype(np.float32)
    objpoints = [obj] * len(found)
    imgpoints = [v.corners_uv.astype(np.float32).reshape(-1, 1, 2) for v in found]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    rms, K, dist, rvecs, tvecs, std_int, _std_ext, per_view = cv2.calibrateCameraExtended(
        objpoints, imgpoints, size, None, None, flags=flags, criteria=crit
    )
    dist = np.asarray(dist, dtype=np.float64).ravel()
    if dist.size > 5 and np.allclose(dist[5:], 0):
        dist = dist[:5]
    camera = Camera(K, dist[:5], size[0], size[1], rms_px=float(rms))
    std_int = np.asarray(std_int).ravel()
    std = {n: float(s) for n, s in zip(INTRINSIC_NAMES, std_int)}
    residuals, corners = [], []
    for v, rv, tv in zip(found, rvecs, tvecs):
        proj, _ = cv2.projectPoints(obj.astype(np.float64), rv, tv, K, dist)
        residuals.append(v.corners_uv - proj.reshape(-1, 2))
        corners.append(v.corners_uv)
    return IntrinsicsCalibration(
        camera=camera,
        rms_px=float(rms),
        std=std,
        used=tuple(v.name for v in found),
        not_found=not_found,
        per_view_rms_px=np.asarray(per_view, dtype=np.float64).ravel(),
        residuals_px=tuple(residuals),
        corners_uv=tuple(corners),
        rvecs=tuple(np.asarray(r).ravel() for r in rvecs),
        tvecs=tuple(np.asarray(t).ravel() for t in tvecs),
        board=tuple(board),
        square_mm=float(square_mm),
        flags=int(flags),
        options={"rotate_deg": rotate_deg, "refine": refine},
    )


def plot_residuals(result: IntrinsicsCalibration, path: str) -> None:
    """Residual plot: all corner residuals (px) as a scatter and per-view RMS bars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .io import save_figure

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.5))
    for name, r in zip(result.used, result.residuals_px):
        ax1.plot(r[:, 0], r[:, 1], ".", ms=2, alpha=0.6)
    ax1.set_aspect("equal")
    ax1.set_xlabel("residual u (px)")
    ax1.set_ylabel("residual v (px)")
    ax1.set_title(f"Corner residuals, RMS {result.rms_px:.3f} px")
    ax1.grid(True, alpha=0.3)
    labels = [Path(n).name for n in result.used]
    ax2.bar(range(len(labels)), result.per_view_rms_px)
    ax2.set_xticks(range(len(labels)))
    ax2.set_xticklabels(labels, rotation=60, ha="right", fontsize=7)
    ax2.set_ylabel("per-view RMS (px)")
    ax2.set_title("Per-view reprojection error")
    fig.tight_layout()
    save_figure(fig, path, force=True, dpi=110)
