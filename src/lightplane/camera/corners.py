"""Calibration boards in images: OpenCV's chessboard detection, the corners refined by gradient orthogonality
(Förstner) or by the blurred-saddle fit, its edges bent as the lens bends the board's lines (or fitted in
a known lens's own frame; docs/method.md §Camera calibration, docs/lens-models.md).  The board's point layout is
:func:`lightplane.camera.targets.board_object_points`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lightplane.camera._corner_kernels import fit_saddles, forstner, line_bends, window_pixels
from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.core.io import to_gray_float

__all__ = ["MIN_BOARD_BLUR_PX", "CornerFitOptions", "corner_noise", "find_board", "fit_corners", "lens_bend",
           "refine_corners"]

#: Boards (in :func:`calibrate_camera`: captures) whose edges are sharper than this (median
#: fitted blur, px) keep Förstner's corners: the saddle model needs an image smooth on the
#: pixel scale (see :func:`fit_corners`); sharpened camera images (halos) are not.
MIN_BOARD_BLUR_PX = 0.55

#: The saddle fit's corners are fitted again where the bends of their edges (:func:`_grid_bends`) measured
#: on the fitted corners differ from those it held by more than this across the window (px); the others
#: are moved to first order (a corner moves by ~0.27 of a bend, linear within 1.4 % up to 0.05 px: within
#: this, less than 1e-5 px is left).
BEND_REFIT_PX = 0.005


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
    by more than a quarter of the spacing, keep their input position.  The iteration is
    compiled (:func:`lightplane.camera._corner_kernels.forstner`; all corners step until the largest
    step is below ``tol_px``).
    """
    import cv2

    g = np.asarray(gray)
    if g.ndim != 2:
        raise LightplaneError(f"refine_corners: gray must be a 2-D image, got shape {g.shape}")
    q0 = np.asarray(corners_uv, dtype=np.float64).reshape(-1, 2)
    if not spacing_px > 0:
        raise LightplaneError(f"refine_corners: spacing_px must be positive, got {spacing_px}")
    if g.dtype == np.uint8:  # Scharr's sums are integers (|.| <= 4080): exact in int16, scaled in the kernel
        gx, gy, unit = cv2.Scharr(g, cv2.CV_16S, 1, 0), cv2.Scharr(g, cv2.CV_16S, 0, 1), 1.0 / 32.0
    else:
        g = g.astype(np.float64, copy=False)
        gx, gy, unit = cv2.Scharr(g, cv2.CV_64F, 1, 0, scale=1 / 32), cv2.Scharr(g, cv2.CV_64F, 0, 1, scale=1 / 32), 1.0
    radius = max(2.0, min(radius_frac * spacing_px, max_radius_px))
    sigma = sigma_frac * spacing_px * radius / (radius_frac * spacing_px)
    q = np.empty_like(q0)
    forstner(np.ascontiguousarray(gx), np.ascontiguousarray(gy), float(unit), np.ascontiguousarray(q0), float(radius),
             float(2.0 * sigma**2), int(max_iter), float(tol_px), q)
    bad = ~np.all(np.isfinite(q), axis=1) | (np.linalg.norm(q - q0, axis=1) > 0.25 * spacing_px)
    q[bad] = q0[bad]
    return q


def _grid_geometry(corners_uv: np.ndarray, board: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per corner of a ``(cols, rows)`` grid: the distance to the nearest parallel grid line
    (px, the smaller of the row and column line spacings), and the row and column
    directions (central differences of the neighbouring corners, one-sided at the border)."""
    cols, rows = board
    g = corners_uv.reshape(rows, cols, 2)
    e_row = np.gradient(g, axis=1)  # along a row: the edge line between two rows of squares
    e_col = np.gradient(g, axis=0)
    u_row = e_row / np.linalg.norm(e_row, axis=2, keepdims=True)
    u_col = e_col / np.linalg.norm(e_col, axis=2, keepdims=True)
    # perpendicular distance to the next row line (step along a column ⨯ row direction), and vice versa
    cross = lambda a, b: np.abs(a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0])  # noqa: E731
    dv = np.diff(g, axis=0)
    du = np.diff(g, axis=1)
    gap = np.full((rows, cols), np.inf)
    d_rowline = cross(dv, u_row[1:])  # from corner (j+1, i) back to row j's line, ~ the same from j
    d_rowline = np.minimum(d_rowline, cross(dv, u_row[:-1]))
    gap[1:] = np.minimum(gap[1:], d_rowline)
    gap[:-1] = np.minimum(gap[:-1], d_rowline)
    d_colline = np.minimum(cross(du, u_col[:, 1:]), cross(du, u_col[:, :-1]))
    gap[:, 1:] = np.minimum(gap[:, 1:], d_colline)
    gap[:, :-1] = np.minimum(gap[:, :-1], d_colline)
    return gap.ravel(), e_row.reshape(-1, 2), e_col.reshape(-1, 2)


class _LensFrame:
    """Locally rectified coordinates about corners ``q0`` (n, 2) distorted px of ``camera``.

    ``p -> q0 + J0 (x(p) - x(q0))`` with ``x`` the normalised undistorted coordinates and
    ``J0 = ∂(u, v)/∂(x, y)`` at ``q0``: the identity to first order at each corner (pixel
    scale, the same edge angles and blur), with the lens's bending of straight lines
    (second and higher orders) taken out.  A straight board edge is straight in it."""

    def __init__(self, camera: Camera, q0: np.ndarray) -> None:
        self.camera = camera
        self.q0 = np.asarray(q0, np.float64)
        self.x0 = camera.undistort_points(self.q0, normalized=True)
        self.J0 = camera.pixel_jacobian(self.x0)  # (n, 2, 2)

    def forward(self, px: np.ndarray, py: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixel centres (n, K) -> their rectified coordinates (n, K) each, and the area element
        ``|det ∂(rectified)/∂(pixel)|`` (n, K) by which a pixel sum becomes the integral there."""
        n, k = px.shape
        J0 = self.J0
        # Newton's start: the lens linearised about the corner (within the window's bend of the root)
        Ji = np.linalg.inv(J0)
        du, dv = px - self.q0[:, :1], py - self.q0[:, 1:]
        start = np.stack([self.x0[:, None, 0] + Ji[:, None, 0, 0] * du + Ji[:, None, 0, 1] * dv,
                          self.x0[:, None, 1] + Ji[:, None, 1, 0] * du + Ji[:, None, 1, 1] * dv], axis=-1)
        x, (j11, j12, j21, j22) = self.camera._undistort_near(np.column_stack([px.ravel(), py.ravel()]),
                                                               start.reshape(-1, 2))
        d = x.reshape(n, k, 2) - self.x0[:, None, :]
        X = self.q0[:, :1] + J0[:, None, 0, 0] * d[..., 0] + J0[:, None, 0, 1] * d[..., 1]
        Y = self.q0[:, 1:] + J0[:, None, 1, 0] * d[..., 0] + J0[:, None, 1, 1] * d[..., 1]
        # |det ∂(u, v)/∂(x, y)| = fx fy |det ∂(x_d, y_d)/∂(x, y)| (K upper triangular)
        det_p = (self.camera.K[0, 0] * self.camera.K[1, 1]) * (j11 * j22 - j12 * j21).reshape(n, k)
        det0 = J0[:, 0, 0] * J0[:, 1, 1] - J0[:, 0, 1] * J0[:, 1, 0]
        area = np.abs(det0)[:, None] / np.abs(det_p)
        return X, Y, area

    def back(self, q: np.ndarray) -> np.ndarray:
        """Rectified coordinates (n, 2) -> distorted px (n, 2) (the exact inverse of :meth:`forward`)."""
        d = np.linalg.solve(self.J0, (q - self.q0)[..., None])[..., 0]
        return self.camera.normalized_to_pixels(self.x0 + d)


def _fit_saddles(g: np.ndarray, P: np.ndarray, radius: np.ndarray, taper_px: float, max_iter: int,
                 tol_px: float, camera: Camera | None = None, warm: bool = False,
                 bent: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Levenberg–Marquardt fit of the blurred saddle of :func:`fit_corners` to ``g`` for corners with starting
    parameters ``P`` (n, 13) and window radii ``radius`` (n,) px: the fitted parameters, the weighted
    mean squared residual (n,) and, with ``bent``, the corners' derivatives in the bends (n, 2, 2) (the
    kernel's ``sens``; else NaN).  With ``camera``, the model is fitted in
    the :class:`_LensFrame` about the starting corners (the corners returned in distorted px).
    ``warm``: ``P`` is a whole fitted parameter set (else only the corner, edge angles and blur:
    the linear parameters are solved for first).  The iteration is :func:`_corner_kernels.fit_saddles`
    (the pixel centres, image values and lens frame prepared here)."""
    q0 = P[:, :2].copy()
    r = int(np.ceil(radius.max())) + 1
    oy, ox = np.mgrid[-r:r + 1, -r:r + 1]
    keep = ox**2 + oy**2 <= r**2
    ox, oy = ox[keep].astype(np.float64), oy[keep].astype(np.float64)
    n, k = len(q0), ox.size
    px, py, img, w0 = np.empty((n, k)), np.empty((n, k)), np.empty((n, k)), np.empty((n, k))
    # (n, K) pixel centres about the rounded corners (fixed), the image there, 1 inside the image else 0
    window_pixels(g, np.round(q0), ox, oy, px, py, img, w0)
    frame = None if camera is None or not camera.has_distortion else _LensFrame(camera, q0)
    if frame is not None:
        px, py, area = frame.forward(px, py)
        ok = np.isfinite(px) & np.isfinite(py) & np.isfinite(area)
        px, py, area = np.where(ok, px, 0.0), np.where(ok, py, 0.0), np.where(ok, area, 0.0)
        w0 = w0 * area
    P = np.array(P, dtype=np.float64, order="C")
    best_P = np.empty_like(P)
    best_cost = np.empty(len(P))
    sens = np.empty((len(P) if bent and frame is None else 0, 2, 2))  # the lens frame's edges are straight
    fit_saddles(np.ascontiguousarray(px, dtype=np.float64), np.ascontiguousarray(py, dtype=np.float64), img,
                np.ascontiguousarray(w0, dtype=np.float64), np.ascontiguousarray(radius, dtype=np.float64),
                float(taper_px), P, bool(warm), int(max_iter), float(tol_px), best_P, best_cost, sens)
    if frame is not None:
        best_P[:, :2] = frame.back(best_P[:, :2])
    return best_P, best_cost, sens if len(sens) else np.full((len(P), 2, 2), np.nan)


@dataclass(frozen=True)
class CornerFitOptions:
    """Options of the blurred-saddle corner fit (:func:`fit_corners`; checked on construction).

    radius_frac : the window's radius as a fraction of the distance to the nearest parallel grid line.
    max_radius_px : the largest window radius (px).
    taper_px : the width over which the window's weight falls to 0 (px).
    max_iter, tol_px : Levenberg–Marquardt steps at most, and the corner step (px) that ends them.
    min_blur_px : corners whose fitted blur ``|s|`` is below this keep their input.
    chunk_size : corners fitted together (bounded memory).
    bent_edges : the model's edges bent as the board's grid lines are at each corner (the lens's
        distortion, :func:`fit_corners`); False: straight edges.
    """

    radius_frac: float = 0.75
    max_radius_px: float = 40.0
    taper_px: float = 3.0
    max_iter: int = 12
    tol_px: float = 1e-4
    min_blur_px: float = 0.4
    chunk_size: int = 24
    bent_edges: bool = True

    def __post_init__(self) -> None:
        for name in ("radius_frac", "max_radius_px", "tol_px"):
            if not getattr(self, name) > 0:
                raise LightplaneError(f"{name} must be positive, got {getattr(self, name)}")
        for name in ("taper_px", "min_blur_px"):
            if not getattr(self, name) >= 0:
                raise LightplaneError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("max_iter", "chunk_size"):
            if not int(getattr(self, name)) >= 1:
                raise LightplaneError(f"{name} must be >= 1, got {getattr(self, name)}")


def fit_corners(gray: np.ndarray, corners_uv: np.ndarray, board: tuple[int, int],
                options: CornerFitOptions | None = None, *, camera: Camera | None = None) -> np.ndarray:
    """Chessboard corners by fitting a blurred-saddle model to the image, ``(N, 2)`` px.

    Around each corner ``q`` the image is modelled as

        I(p) = a + g·(p - q) + (b + h·(p - q)) · E(d1 / s) · E(d2 / s),   E(t) = erf(t / √2),

    with ``d_i = n_i·(p - q) + κ_i (t_i·(p - q))²`` the signed distances (px) to the two board edges
    through the corner (normal angles φ1, φ2 free: in perspective the edges are not
    perpendicular; ``t_i`` along the edge, ``κ_i`` its bend, below), ``s`` the blur (Gaussian
    PSF ⊗ pixel box ≈ Gaussian of ``s² = σ_psf² + 1/12``), ``a, b`` the mean and half-contrast, ``g, h`` their
    gradients (vignetting and shading; the multiplicative ``h`` term matters because,
    being odd about ``q``, it would otherwise pull the corner).  All 11 parameters but the
    bends are fitted per corner by Levenberg–Marquardt (compiled, :mod:`lightplane.camera._corner_kernels`;
    the corners of a chunk step together until all are done), over the pixel centres within a
    disc about the *current* ``q`` (radius ``radius_frac`` × the distance to the nearest parallel
    grid line, at most ``max_radius_px``; the weight falls smoothly to 0 over its last
    ``taper_px``; near the image border the radius shrinks so that the disc stays inside the
    image); the options are :class:`CornerFitOptions`.

    Why it is unbiased: the blurred ideal saddle is point-symmetric about ``q``, so is
    the model, so is the weight; the residual of any symmetric misfit (the erf product is
    exact only for perpendicular edges, the pixel box is not Gaussian) is then even about
    ``q`` while the model's derivative in ``q`` is odd, and the two are orthogonal: no
    pull on ``q``.  Everything being smooth on the pixel scale, the pixel-grid sums
    equal the integrals, so there is no sub-pixel-phase error either — the error of
    gradient operators (:func:`refine_corners`, ``cv2.cornerSubPix``) that dominates
    on rendered boards.  On exact images of a chessboard with edges at 69° the error is
    2e-5 px at a blur (PSF) of 0.9 px and 3e-4 px at 0.6 px, where the sampling starts
    to alias; on sharper images (s < ``min_blur_px``, e.g. in-camera sharpening) the fit
    is refused.  What remains is image noise: on the rendered calibration capture
    (realistic imaging, 30 views of 15x11 corners) the error against the exact corners
    is 0.006 px RMS (noise-free renders: 0.004 px, 8-bit quantisation and the renderer's
    sampling), against 0.019 px for :func:`refine_corners` and 0.031 px for
    ``cornerSubPix``; ~0.1 s of CPU per view of 165 corners (0.4 s as the numpy loop it was).

    Lens distortion bends the board edges across the disc, which breaks the symmetry: with straight
    edges the fit pulls the corners towards the image centre (a rendered wide 6 mm lens, ~0.06 px of
    bend per window: -0.003 px at r < 200 px, -0.010 px at 400–600 px, enough to bias the focal
    length by 10 σ; a 2.6 mm fisheye -0.013 to -0.023 px).  So the model's edges are bent as the
    board's own lines are (``bent_edges``): a board line stays straight in perspective, the lens
    alone bends it, and its bend at a corner is that of the corners on it (a cubic through the
    corner and its neighbours on the line, :func:`_grid_bends`; ``κ_i`` held in the fit).  The bend's
    quadratic part is what breaks the symmetry (a cubic one is point-symmetric about ``q``), so the
    pull is gone.  The bends are measured on the start corners for the fit, then again on the fitted
    corners, which are moved by their derivatives in the bends (the fit's, to first order) until the
    two agree: the corners are those of the bends of their own grid, whatever the start
    (:func:`_rebent`; a noisy start, ~0.1 px, bends its neighbours' lines).  On 10 realistic renders
    of each lens: wide 6 mm lens +0.0003 / +0.0002 / +0.0000 px at r < 200 / 200–400 / 400–600 px,
    0.0070 px RMS (straight edges 0.0101 px); fisheye within ±0.0008 px, 0.0104 px RMS (0.0232 px);
    the default 16 mm lens 0.0060 px RMS either way; ~1.2x the straight fit's time.  With ``camera``
    (a lens known, e.g. from a calibration) the straight model is fitted in the lens frame about each
    corner instead (:class:`_LensFrame`: the pixel centres mapped through the undistortion and back
    by the local Jacobian, so the first-order geometry is unchanged and only the bending removed;
    each pixel weighted by the area element so the sums stay integrals): the same corners to the
    noise (+0.0003 px on the wide lens), at ~1.4x the straight fit's time.

    Parameters
    ----------
    gray : (H, W) image, any real dtype (used as float, no rescaling)
    corners_uv : (cols*rows, 2) starting corners, px, row-major as :func:`find_board`
        (e.g. from ``cv2.cornerSubPix``); within ~0.3 px of the truth
    board : (cols, rows) inner corners; the grid gives the edge directions and the
        local spacing of every corner

    options : :class:`CornerFitOptions` (None: the defaults)
    camera : the lens (any model): fit in its lens frame with straight edges (the corners returned in
        distorted px)

    Corners whose fit fails (singular, not finite, blur outside ``options.min_blur_px`` … half
    the radius, contrast below 5x the residual noise, edge directions turned by more
    than 20° from the grid's) or that move by more than a quarter of the local spacing
    keep their input position.
    """
    return _fit_corners(gray, corners_uv, board, options, camera=camera)[0]


def _fit_corners(gray: np.ndarray, corners_uv: np.ndarray, board: tuple[int, int],
                 options: CornerFitOptions | None = None, *, camera: Camera | None = None,
                 min_bend_px: float = 0.0, start: np.ndarray | None = None,
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`fit_corners`, also returning the fitted blur ``s`` (N,) px, which corners were fitted (N,) bool
    and the fitted parameters (N, 13) (qx, qy, φ1, φ2, s, a, b, gx, gy, hx, hy, κ1, κ2 of
    :func:`fit_corners`'s model, the bends κ held; NaN rows where not fitted).
    With ``camera`` only the corners whose window the lens bends by more than ``min_bend_px``
    (:func:`lens_bend`) are fitted; the others keep their input (blur NaN, not fitted).
    ``start``: (N, 13) parameters of an earlier fit about ``corners_uv`` to start from (its corners
    ``corners_uv``; NaN rows: the corners it did not fit, which start afresh), e.g. the fit without
    ``camera`` for the refit in the lens frame (which, to first order, changes nothing about the
    corner): the Levenberg–Marquardt then converges in one or two steps instead of three or four."""
    opts = CornerFitOptions() if options is None else options
    g, q0, cols, rows = _checked_corner_input(gray, corners_uv, board)
    gap, e_row, e_col = _grid_geometry(q0, (cols, rows))
    # the window stays inside the image (a cut window would not be symmetric about q)
    h, w = g.shape
    border = np.min(np.column_stack([q0, w - 1 - q0[:, 0], h - 1 - q0[:, 1]]), axis=1) - 0.5
    radius = np.clip(np.minimum(opts.radius_frac * gap, border), 2.0, opts.max_radius_px)
    n = len(q0)
    sel = np.ones(n, bool)
    if camera is not None and min_bend_px > 0:
        sel = lens_bend(camera, q0, radius) > min_bend_px
    P, warm = _start_parameters(q0, e_row, e_col, start)
    bent = opts.bent_edges and (camera is None or not camera.has_distortion)
    if bent:
        P[~warm, 11:13] = _clipped_bends(q0, (cols, rows), radius, np.ones(n, bool))[~warm]
    else:  # straight edges (in the lens frame the lens's bending is taken out)
        P[:, 11:13] = 0.0
    P, cost, sens = _fit_groups(g, P, radius, [sel & ~warm, sel & warm], opts, camera, bent)
    geometry = (q0, gap, radius, e_row, e_col)
    bad = _failed(P, cost, geometry, opts) | ~sel
    if bent:
        P, bad = _rebent(g, P, cost, sens, bad, (cols, rows), geometry, opts)
    q = np.where(bad[:, None], q0, P[:, :2])
    blur = np.abs(P[:, 4])  # the model is even in s (with b): only |s| means something
    blur[~sel] = np.nan
    P[bad] = np.nan
    return q, blur, ~bad, P


def corner_noise(gray: np.ndarray, corners_uv: np.ndarray, board: tuple[int, int], params: np.ndarray,
                 options: CornerFitOptions | None = None) -> tuple[np.ndarray, np.ndarray]:
    """How precisely the saddle fit placed each corner, from the image alone: the covariance (N, 2, 2)
    px² of each fitted corner and the image noise (N,) (grey levels) its fit residual shows.

    ``params``: the fitted parameters (N, 13) of :func:`_fit_corners` about the start corners
    ``corners_uv`` (NaN rows: not fitted, NaN out).  Per corner, the image noise is the fit's weighted
    residual RMS over its window (``σ_I² = Σ w r² / (Σ w − 11)``) and the covariance the least-squares
    one of the 11 fitted parameters, ``σ_I² A⁻¹ B A⁻¹`` with ``A = Σ w J Jᵀ``, ``B = Σ w² J Jᵀ`` (the
    model's Jacobian ``J`` at the fit, the window's weights ``w``), its corner block.  For white image
    noise this is the corner's Cramér–Rao bound; nothing in it comes from a calibration, so a
    calibration's residuals can be judged against it.  Model misfit (a sharpened or aliased image)
    raises ``σ_I`` with it: the estimate errs towards larger noise.
    """
    opts = CornerFitOptions() if options is None else options
    g, q0, cols, rows = _checked_corner_input(gray, corners_uv, board)
    P = np.asarray(params, np.float64).reshape(-1, 13)
    gap, _, _ = _grid_geometry(q0, (cols, rows))
    h, w = g.shape
    border = np.min(np.column_stack([q0, w - 1 - q0[:, 0], h - 1 - q0[:, 1]]), axis=1) - 0.5
    radius = np.clip(np.minimum(opts.radius_frac * gap, border), 2.0, opts.max_radius_px)
    cov = np.full((len(P), 2, 2), np.nan)
    noise = np.full(len(P), np.nan)
    ok = np.flatnonzero(np.all(np.isfinite(P[:, :11]), axis=1))
    ok = ok[np.argsort(radius[ok])]  # chunks of similar windows: few padded pixels
    for chunk in np.array_split(ok, max(1, int(np.ceil(ok.size / opts.chunk_size)))):
        if chunk.size:
            cov[chunk], noise[chunk] = _chunk_noise(g, P[chunk], radius[chunk], opts.taper_px)
    return cov, noise


def _chunk_noise(g: np.ndarray, P: np.ndarray, radius: np.ndarray, taper: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`corner_noise` of the corners with fitted parameters ``P`` (n, 13) and window radii ``radius``."""
    r = int(np.ceil(radius.max())) + 1
    oy, ox = np.mgrid[-r:r + 1, -r:r + 1]
    keep = ox**2 + oy**2 <= r**2
    ox, oy = ox[keep].astype(np.float64), oy[keep].astype(np.float64)
    n, k = len(P), ox.size
    px, py, img, w0 = np.empty((n, k)), np.empty((n, k)), np.empty((n, k)), np.empty((n, k))
    window_pixels(g, np.round(P[:, :2]), ox, oy, px, py, img, w0)
    x, y = px - P[:, :1], py - P[:, 1:2]
    t = np.clip((radius[:, None] - np.hypot(x, y)) / max(taper, 1e-12), 0.0, 1.0)
    wt = w0 * np.sin(0.5 * np.pi * t) ** 2
    c1, s1, c2, s2 = np.cos(P[:, 2:3]), np.sin(P[:, 2:3]), np.cos(P[:, 3:4]), np.sin(P[:, 3:4])
    s, k1, k2 = P[:, 4:5], P[:, 11:12], P[:, 12:13]
    n1, n2 = c1 * x + s1 * y, c2 * x + s2 * y
    t1, t2 = c1 * y - s1 * x, c2 * y - s2 * x
    d1, d2 = n1 + k1 * t1**2, n2 + k2 * t2**2
    from scipy.special import erf

    e1, e2 = erf(d1 / (np.sqrt(2.0) * s)), erf(d2 / (np.sqrt(2.0) * s))
    ee = e1 * e2
    amp = P[:, 6:7] + P[:, 9:10] * x + P[:, 10:11] * y
    res = img - (P[:, 5:6] + P[:, 7:8] * x + P[:, 8:9] * y + amp * ee)
    kk = np.sqrt(2.0 / np.pi) / s
    b1 = amp * kk * np.exp(-0.5 * (d1 / s) ** 2) * e2
    b2 = amp * e1 * kk * np.exp(-0.5 * (d2 / s) ** 2)
    a1, a2 = 2.0 * k1 * t1, 2.0 * k2 * t2
    J = np.stack([-P[:, 7:8] - P[:, 9:10] * ee - b1 * (c1 - a1 * s1) - b2 * (c2 - a2 * s2),
                  -P[:, 8:9] - P[:, 10:11] * ee - b1 * (s1 + a1 * c1) - b2 * (s2 + a2 * c2),
                  b1 * t1 * (1.0 - 2.0 * k1 * n1), b2 * t2 * (1.0 - 2.0 * k2 * n2), -(b1 * d1 + b2 * d2) / s,
                  np.ones_like(x), ee, x, y, x * ee, y * ee], axis=1)  # (n, 11, K)
    Jw = J * np.sqrt(wt)[:, None, :]
    Jww = J * wt[:, None, :]
    A = Jw @ Jw.transpose(0, 2, 1)
    B = Jww @ Jww.transpose(0, 2, 1)
    sw = wt.sum(axis=1)
    var = np.einsum("nk,nk->n", wt, res**2) / np.maximum(sw - 11.0, 1.0)
    with np.errstate(all="ignore"):
        Ai = np.linalg.pinv(A)
    C = var[:, None, None] * (Ai @ B @ Ai)[:, :2, :2]
    return C, np.sqrt(var)


def _rebent(g: np.ndarray, P: np.ndarray, cost: np.ndarray, sens: np.ndarray, bad: np.ndarray,
            board: tuple[int, int], geometry: tuple, opts: CornerFitOptions) -> tuple[np.ndarray, np.ndarray]:
    """The fitted corners with the bends of the fitted grid instead of the start's (its noise, ~0.02 px
    from Förstner's step, bends its neighbours' lines by ~0.15 of it): each corner moved by its derivative
    in the bends (``sens`` (N, 2, 2)) times their change, the bends measured again on the moved corners
    until they stop moving (to first order the corners are then those of a fit with the final bends,
    whatever the start); where a bend changed by more than :data:`BEND_REFIT_PX` across the window (a
    misplaced start corner) the corner is fitted again with it first.  The parameters (N, 13) (corners
    and bends replaced) and which fits failed (N,)."""
    q0, radius = geometry[0], geometry[2]
    P, cost, sens = P.copy(), cost.copy(), sens.copy()
    q = P[:, :2].copy()
    for _ in range(4):
        bends = _clipped_bends(np.where(bad[:, None], q0, q), board, radius, ~bad)
        change = bends - P[:, 11:13]
        refit = ~bad & ((np.max(np.abs(change), axis=1) * radius**2 > BEND_REFIT_PX)
                        | ~np.all(np.isfinite(sens), axis=(1, 2)))
        if refit.any():
            P[refit, 11:13] = bends[refit]
            P2, cost2, sens2 = _fit_groups(g, P, radius, [np.zeros(len(P), bool), refit], opts, None, True)
            P[refit], cost[refit], sens[refit] = P2[refit], cost2[refit], sens2[refit]
            bad[refit] = _failed(P, cost, geometry, opts)[refit]
            change[refit] = 0.0
        moved = P[:, :2] + np.einsum("nij,nj->ni", np.nan_to_num(sens), change)
        step = np.max(np.abs(moved - q)[~bad], initial=0.0)
        q = moved
        if step < 1e-6 and not refit.any():
            break
    P[:, :2] = np.where(bad[:, None], P[:, :2], q)
    P[:, 11:13] = np.where(bad[:, None], P[:, 11:13], bends)
    return P, bad


def _failed(P: np.ndarray, cost: np.ndarray, geometry: tuple, opts: CornerFitOptions) -> np.ndarray:
    """The saddle fits (parameters ``P`` (N, 13), costs (N,)) that failed (N,) bool: not finite, the corner
    moved by more than a quarter of the gap, blur out of range, contrast below 5x the residual noise,
    an edge turned by more than 20° from the grid's direction.  ``geometry``: the start corners, their
    gaps, window radii and grid directions (:func:`_grid_geometry`)."""
    q0, gap, radius, e_row, e_col = geometry

    def turned(phi, e):  # angle between the fitted edge and the grid direction
        return np.abs(np.cos(phi) * e[:, 0] + np.sin(phi) * e[:, 1]) / np.linalg.norm(e, axis=1)

    noise = np.sqrt(np.maximum(cost, 0.0))
    blur = np.abs(P[:, 4])
    max_turn = np.sin(np.radians(20.0))
    with np.errstate(invalid="ignore"):
        return (~np.all(np.isfinite(P), axis=1) | ~(np.linalg.norm(P[:, :2] - q0, axis=1) <= 0.25 * gap)
                | ~(blur >= opts.min_blur_px) | ~(blur < 0.5 * radius) | ~(np.abs(P[:, 6]) > 5.0 * noise)
                | (turned(P[:, 2], e_row) > max_turn) | (turned(P[:, 3], e_col) > max_turn))


def _fit_groups(g: np.ndarray, P: np.ndarray, radius: np.ndarray, groups: list, opts: CornerFitOptions,
                camera: Camera | None, bent: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The saddle fits of the corners of ``groups`` ([cold, warm] (N,) bool: started from their geometry
    alone, or from a whole parameter set), in chunks of similar radius (bounded memory, few padded
    pixels): the parameters (N, 13) (the others as they were), costs (N,) (inf where not fitted) and,
    with ``bent``, the corners' derivatives in the bends (N, 2, 2) (NaN where not fitted or not ``bent``)."""
    P = P.copy()
    cost = np.full(len(P), np.inf)
    sens = np.full((len(P), 2, 2), np.nan)
    for group, is_warm in zip(groups, (False, True)):
        order = np.flatnonzero(group)[np.argsort(radius[group])]
        for chunk in np.array_split(order, max(1, int(np.ceil(order.size / opts.chunk_size)))):
            if chunk.size == 0:
                continue
            P[chunk], cost[chunk], sens[chunk] = _fit_saddles(g, P[chunk], radius[chunk], opts.taper_px, opts.max_iter,
                                                              opts.tol_px, camera, warm=is_warm, bent=bent)
    return P, cost, sens


def _clipped_bends(q: np.ndarray, board: tuple[int, int], radius: np.ndarray, use: np.ndarray) -> np.ndarray:
    """:func:`_grid_bends` of the corners ``q`` (N, 2) (those of ``use`` (N,) bool) as (N, 2), each at most
    1 px across its window (radius ``radius`` (N,)): a misplaced corner bends its neighbours' lines."""
    _, e_row, e_col = _grid_geometry(q, board)
    top = (1.0 / radius**2)[:, None]
    return np.clip(np.column_stack(_grid_bends(q, board, e_row, e_col, use)), -top, top)


def _checked_corner_input(gray: np.ndarray, corners_uv: np.ndarray,
                          board: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, int, int]:
    """:func:`fit_corners`' image (C-contiguous float64, the kernels' layout, once for all chunks),
    corners (N, 2) and board ``cols, rows``, checked."""
    g = np.asarray(gray)
    if g.ndim != 2 or not np.issubdtype(g.dtype, np.number):
        raise LightplaneError(f"fit_corners: gray must be a 2-D numeric image, got shape {g.shape}")
    g = np.ascontiguousarray(g, dtype=np.float64)
    q0 = np.asarray(corners_uv, dtype=np.float64)
    cols, rows = (int(v) for v in board)
    if cols < 2 or rows < 2:
        raise LightplaneError(f"fit_corners: board needs at least 2x2 inner corners, got {board}")
    if q0.shape != (cols * rows, 2):
        raise LightplaneError(f"fit_corners: corners_uv must have shape ({cols * rows}, 2) for a {cols}x{rows} "
                              f"board, got {q0.shape}")
    if not np.all(np.isfinite(q0)):
        raise LightplaneError("fit_corners: corners_uv holds non-finite values")
    return g, q0, cols, rows


def _grid_bends(q0: np.ndarray, board: tuple[int, int], e_row: np.ndarray, e_col: np.ndarray,
                use: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How the lens bends the two board edges through each corner (N,) each, 1/px: ``κ`` of the edge
    along the row and of the edge along the column, as :func:`fit_corners`' model has them
    (``d = n·u + κ (t·u)²``, ``n`` the edge's normal of the grid direction, ``t`` along it), from the
    grid itself: a board line stays straight in perspective, what bends it is the lens, so the
    line's bend at a corner is that of the corners on it (:func:`_line_bends`; only the corners
    ``use`` (N,) bool)."""
    cols, rows = board
    g = q0.reshape(rows, cols, 2)
    ok = use.reshape(rows, cols)
    k_row = _line_bends(g, e_row.reshape(rows, cols, 2), ok)
    k_col = _line_bends(g.transpose(1, 0, 2), e_col.reshape(rows, cols, 2).transpose(1, 0, 2), ok.T).T
    # the bend changes smoothly from a line to the next: (1, 2, 1) / 4 across the lines halves its noise
    # (from the start corners; the fit refits fewer corners) and moves it by a quarter of its second
    # difference across the lines (nothing on the lenses measured)
    k_row[1:-1] = 0.25 * k_row[:-2] + 0.5 * k_row[1:-1] + 0.25 * k_row[2:]
    k_col[:, 1:-1] = 0.25 * k_col[:, :-2] + 0.5 * k_col[:, 1:-1] + 0.25 * k_col[:, 2:]
    return k_row.ravel(), k_col.ravel()


def _line_bends(g: np.ndarray, e: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """The bend ``κ`` (lines, m) of grid lines of corners ``g`` (lines, m, 2) at each corner, whose line
    direction there is ``e`` (lines, m, 2): the corner's neighbours on the line (9, centred where the
    line allows, shifted in at its ends; all of a shorter line; those of ``ok`` (lines, m) only) in the
    frame of the corner and ``e`` (``t`` along, ``y`` across), and ``y = a + b t + c t² + d t³`` fitted
    to them (a parabola through 4 or 5): the edge through the corner lies at ``y = c t²``, ``κ = -c``
    (:func:`lightplane.camera._corner_kernels.line_bends`).  The cubic term keeps the bend's change
    along the line out of ``c`` at the ends; 9 corners (not 5) halve the start corners' noise in ``κ``.
    0 through fewer than 4 corners."""
    kappa = np.zeros(ok.shape)
    if ok.shape[1] >= 4:
        line_bends(np.ascontiguousarray(g, np.float64), np.ascontiguousarray(e, np.float64),
                   np.ascontiguousarray(ok), min(9, ok.shape[1]), kappa)
    return kappa


def _start_parameters(q0: np.ndarray, e_row: np.ndarray, e_col: np.ndarray,
                      start: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """The saddle fit's starting parameters (N, 13): the corners ``q0``, the edge normals of the grid's
    row and column directions, unit blur, straight edges; or, where ``start`` holds a whole fit about
    the same corner, that fit (``warm``, (N,) bool)."""
    n = len(q0)
    P = np.zeros((n, 13))
    P[:, :2] = q0
    P[:, 2] = np.arctan2(e_row[:, 0], -e_row[:, 1])  # normal of the edge along the row
    P[:, 3] = np.arctan2(e_col[:, 0], -e_col[:, 1])
    P[:, 4] = 1.0
    warm = np.zeros(n, bool)
    if start is not None:
        start = np.asarray(start, np.float64)
        if start.shape != (n, 13):
            raise LightplaneError(f"fit_corners: start must have shape ({n}, 13), got {start.shape}")
        warm = np.all(np.isfinite(start), axis=1) & np.all(start[:, :2] == q0, axis=1)
        P[warm] = start[warm]
    return P, warm


def lens_bend(camera: Camera, corners_uv: np.ndarray, radius_px: np.ndarray | float) -> np.ndarray:
    """How far ``camera``'s lens bends the corner windows of :func:`fit_corners` (N,) px: the
    largest distance, over the rim of each window (radius ``radius_px`` about each corner of
    ``corners_uv`` (N, 2), distorted px), between a pixel and its place in the
    :class:`_LensFrame` about the corner: the part of the lens mapping that is not affine
    across the window (straight board edges curved by up to about this much)."""
    q = np.asarray(corners_uv, np.float64).reshape(-1, 2)
    r = np.broadcast_to(np.asarray(radius_px, np.float64), (len(q),))[:, None]
    if not camera.has_distortion or len(q) == 0:
        return np.zeros(len(q))
    a = np.linspace(0.0, 2.0 * np.pi, 16, endpoint=False)
    px, py = q[:, :1] + r * np.cos(a), q[:, 1:] + r * np.sin(a)
    X, Y, _ = _LensFrame(camera, q).forward(px, py)
    bend = np.hypot(X - px, Y - py).max(axis=1)
    return np.where(np.isfinite(bend), bend, np.inf)


def find_board(image: np.ndarray, board: tuple[int, int], *, subpix: bool = True,
               refine: bool | str = False) -> np.ndarray | None:
    """Chessboard inner corners ``(cols*rows, 2)`` (distorted px) or None if not found.

    ``cv2.findChessboardCornersSB`` finds the board robustly; ``cv2.cornerSubPix``
    then refines each corner with a half-window of 30 % of the local corner
    spacing (at most 11 px), as OpenCV's classic pipeline does.  That refinement
    reproduces the published Ciclop calibration to 0.01 px, where the SB
    detector's own sub-pixel estimate differs by up to 0.9 px in cy.  With ``refine``
    (and ``subpix``, and a corner spacing of at least 8 px) the corners are then polished
    with a wider window (0.6–0.75 of the spacing): ``"saddle"`` (or True) fits the blurred
    saddle of :func:`fit_corners` to the image (0.006 px RMS on rendered boards, ~5x
    below cornerSubPix), ``"forstner"`` runs :func:`refine_corners` (0.019 px).  Off by
    default because the wider window also takes in a laser stripe crossing the board
    (Zhou's images): :func:`calibrate_camera`, whose boards carry no stripe, turns it on.
    Colour images are reduced to gray by :func:`lightplane.core.io.to_gray_float`; the saddle
    fit runs on that float image (not on the 8-bit copy the detector gets).  The saddle
    fit starts from Förstner's corners; corners it cannot fit keep them, and so does the
    whole board when its edges are sharper than ``MIN_BOARD_BLUR_PX`` (median fitted blur).
    """
    method = _refine_method(refine)
    c, saddle, blur, _ = _detect_board(image, board, subpix, method)
    if saddle is not None and blur.size and np.median(blur) >= MIN_BOARD_BLUR_PX:
        return saddle
    return c


def _refine_method(refine) -> str | None:
    method = {False: None, True: "saddle", "saddle": "saddle", "forstner": "forstner"}.get(refine, "?") \
        if isinstance(refine, (bool, str)) else "?"
    if method == "?":
        raise LightplaneError(f"refine must be False, True, 'saddle' or 'forstner', got {refine!r}")
    return method


def _detect_board(image: np.ndarray, board: tuple[int, int], subpix: bool,
                  method: str | None) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray, np.ndarray | None]:
    """:func:`find_board`'s steps: the corners up to Förstner's refinement (or None when
    the board is not found), the saddle fit's corners (None unless ``method`` is
    ``"saddle"``; unfitted corners keep Förstner's), the blur (px) of the fitted ones and the
    fit's parameters (N, 11), NaN rows where not fitted (None without the fit)."""
    import cv2

    none = (None, None, np.zeros(0), None)
    gray = image if image.ndim == 2 else to_gray_float(image)
    gray_in = gray
    if gray.dtype != np.uint8:
        g = gray.astype(np.float64)
        lo, hi = np.percentile(g, [0.5, 99.5])
        gray = np.clip((g - lo) * (255.0 / max(hi - lo, 1e-9)), 0, 255).astype(np.uint8)
    flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE
    found, corners = cv2.findChessboardCornersSB(gray, tuple(board), flags=flags)
    if not found or corners is None:
        return none
    c32 = corners.reshape(-1, 2).astype(np.float32)
    if not subpix:
        return c32.astype(np.float64), None, np.zeros(0), None
    cols, rows = board
    grid = c32.reshape(rows, cols, 2)
    spacing = min(np.linalg.norm(np.diff(grid, axis=1), axis=2).min(),
                  np.linalg.norm(np.diff(grid, axis=0), axis=2).min())
    half = int(np.clip(np.floor(0.3 * spacing), 2, 11))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)
    c = cv2.cornerSubPix(gray, c32.reshape(-1, 1, 2), (half, half), (-1, -1), crit).reshape(-1, 2)
    c = c.astype(np.float64)
    if method is None or spacing < 8:
        return c, None, np.zeros(0), None
    c = refine_corners(gray, c, float(spacing))
    if method != "saddle":
        return c, None, np.zeros(0), None
    q, blur, ok, params = _fit_corners(gray_in, c, (cols, rows))  # corners it cannot fit keep Förstner's position
    return c, q, blur[ok], params
