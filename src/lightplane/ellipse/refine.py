"""Sub-pixel refinement of a detected ellipse for metrology (docs/method.md §Ellipse).

Edge points are found along the ellipse's normals (gradient-magnitude peak, Gaussian
fit through three samples), outliers are rejected with the median absolute deviation
of their distances to a first fit, and the conic is fitted by Halir–Flusser's direct
method (Hartley-normalised coordinates) followed by a geometric (Sampson-distance)
Levenberg–Marquardt refinement.

Curvature bias.  On a curved edge the gradient-magnitude peak of the blurred image lies
*inside* the true edge, towards the centre of curvature, by ``kappa sigma_t^2 / 2`` to
first order (``kappa = 1/R`` the local curvature in px^-1, ``sigma_t^2`` the variance
of the total blur along the edge: optics and pixel, the Gaussian pre-smoothing, the
difference kernel and the bilinear sampling of the gradient) — the same effect that
Steger corrects on curved stripes.  With the PSF sigma 0.9 px of a realistic render
and R ~ 150 px it is ~0.006 px: small, but the same sign all around the rim, so it
shrinks the ellipse and biases the circle's pose (depth).  ``refine_ellipse``
(``EllipseRefinementOptions.correct_curvature``, on by default) estimates the optical
blur from the width of the gradient profiles across the rim (:func:`edge_blur_sigma`), shifts each edge point
outward along its normal by the predicted bias and refits.

With a camera the edge points are undistorted first
and the conic is in *undistorted* pixels, the input of ``circle_poses`` (docs/method.md §Circle pose).
The conic's centre is not the image of the circle's centre under perspective: use
the pose solution for that.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lightplane.core.errors import LightplaneError
from lightplane.core.geometry import Failure, robust_sigma, sampson_distance_unchecked
from lightplane.ellipse.edges import Gradients, NormalEdgeSamples, gradients, normal_edge_samples, prepare_gray
from lightplane.ellipse.model import Ellipse, fit_ellipse_direct, fit_ellipse_geometric, sampson_distance
from lightplane.ellipse.detect import _POLARITY

__all__ = ["RefinedEllipse", "EllipseRefinementOptions", "refine_ellipse", "fit_conic_robust", "edge_blur_sigma", "curvature_bias_px",
           "ellipse_curvature"]

# Variance (px²) that the 5-sample log-parabola width of a bilinearly sampled gradient
# profile adds to the blur across the edge, beyond the pre-smoothing and the difference
# kernel (measured on exactly blurred synthetic discs, sigma 0.4-2 px: 0.19-0.21; the
# linear-interpolation average alone is 1/6).
_WIDTH_SAMPLING_VAR = 0.20
# Variance that the sampling adds along the edge, beyond the pre-smoothing and the
# difference kernel: the phase average of bilinear interpolation alone is 1/6 px²; the
# 1/3 px² used fits the measured bias of exactly blurred synthetic discs (sigma
# 0.6-1.3 px, R 15-240 px: residual after correction within +-0.0012 px, except
# +0.003 px at sigma 1.3, R 15) where 1/6 left -0.07/R px.
_TANGENT_SAMPLING_VAR = 1.0 / 3.0


@dataclass(frozen=True, eq=False)
class RefinedEllipse:
    """Result of :func:`refine_ellipse`.

    Attributes
    ----------
    conic : (3, 3) normalised conic, in undistorted pixels when a camera was given
        (else in image pixels).
    ellipse : :class:`Ellipse` of ``conic`` (same frame).
    image_ellipse : :class:`Ellipse` fitted to the distorted edge points (image frame;
        use it for masks in the image).
    edge_points_px : (N, 2) inlier edge points, distorted image pixels.
    edge_points_undistorted : (N, 2) the same points undistorted (equal to
        ``edge_points_px`` without a camera).
    residual_rms_px : RMS geometric (Sampson) distance of the inliers to the conic, px.
    n_inliers, n_samples : inlier edge points / samples taken along the normals.
    blur_sigma_px : estimated optical blur of the rim (Gaussian sigma, px, image frame;
        includes the pixel's own footprint), from :func:`edge_blur_sigma`; NaN when
        not estimated.
    curvature_shift_px : mean outward shift applied to the edge points for the
        curvature bias (0 with ``correct_curvature=False``).
    """

    conic: np.ndarray = field(repr=False)
    ellipse: Ellipse
    image_ellipse: Ellipse
    edge_points_px: np.ndarray = field(repr=False)
    edge_points_undistorted: np.ndarray = field(repr=False)
    residual_rms_px: float
    n_inliers: int
    n_samples: int
    blur_sigma_px: float = float("nan")
    curvature_shift_px: float = 0.0


def _normal_angle_terms(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(cos^4 + sin^4, sin^2(2 theta))`` of the normals' angle theta (each (N,))."""
    c2 = normals[:, 0] ** 2 / np.maximum(np.sum(normals ** 2, axis=1), 1e-300)
    s2 = 1.0 - c2
    return c2 * c2 + s2 * s2, 4.0 * c2 * s2


def edge_blur_sigma(width_sq_px2: np.ndarray, normals: np.ndarray, sigma_px: float) -> float:
    """Optical blur (Gaussian sigma, px) of an edge from its gradient-profile widths.

    ``width_sq_px2`` (N,) squared widths across the edge from
    :func:`lightplane.ellipse.edges.normal_edge_samples` (gradients of ``sigma_px``
    pre-smoothing, central differences, bilinear samples), ``normals`` (N, 2) the
    directions they were measured along.  Across an edge of normal angle theta the
    width is ``sigma_o^2 + sigma_px^2 + (cos^4 + sin^4)/3 + 0.20`` (the central
    difference is a box of variance 1/3 along each axis; 0.20 px² from the sampling,
    measured on exactly blurred synthetic discs); the median over the points of the
    solved ``sigma_o^2`` is returned as a sigma (0 when negative, NaN with fewer than
    8 finite widths).
    """
    w2 = np.asarray(width_sq_px2, dtype=np.float64)
    q, _ = _normal_angle_terms(np.asarray(normals, dtype=np.float64).reshape(-1, 2))
    est = w2 - sigma_px ** 2 - q / 3.0 - _WIDTH_SAMPLING_VAR
    est = est[np.isfinite(est)]
    if len(est) < 8:
        return float("nan")
    return math.sqrt(max(float(np.median(est)), 0.0))


def ellipse_curvature(ellipse: Ellipse, t: np.ndarray) -> np.ndarray:
    """Curvature (px^-1) of ``ellipse`` at parametric angles ``t`` (rad):
    ``a b / (a^2 sin^2 t + b^2 cos^2 t)^(3/2)``."""
    t = np.asarray(t, dtype=np.float64)
    a, b = ellipse.a, ellipse.b
    return a * b / (a * a * np.sin(t) ** 2 + b * b * np.cos(t) ** 2) ** 1.5


def curvature_bias_px(curvature_px: np.ndarray, normals: np.ndarray, blur_sigma_px: float,
                      sigma_px: float) -> np.ndarray:
    """Predicted inward offset (px, >= 0) of the gradient-magnitude peak of a curved edge.

    ``kappa sigma_t^2 / 2`` per point: ``curvature_px`` (N,) px^-1, ``normals`` (N, 2),
    ``sigma_t^2 = blur_sigma_px^2 + sigma_px^2 + 1/3 + sin^2(2 theta)/6`` the blur's
    variance along the edge (optics, pre-smoothing, the sampling — 1/3 px², measured,
    see ``_TANGENT_SAMPLING_VAR`` — and the central difference's box seen along the
    edge: ``2 cos^2 sin^2 / 3``).  For a disc of radius R blurred by a Gaussian sigma,
    the gradient-magnitude profile is ``exp(-(r^2 + R^2) / 2 sigma^2) I1(r R / sigma^2)``
    whose maximum is at ``r = R - sigma^2 / (2 R) + O(sigma^4 / R^3)``; for a general
    smooth curve, a kernel of variance ``sigma_t^2`` along the edge moves the apparent
    edge inward by ``kappa sigma_t^2 / 2``.  Calibrated for the default pre-smoothing
    (0.8 px) and blur 0.6-1.3 px; with ``sigma_px`` 0-0.5 px and a sharp image (blur
    0.6 px) about 0.2 px² is missing (residual ~ -0.1/R px).
    """
    _, s2t = _normal_angle_terms(np.asarray(normals, dtype=np.float64).reshape(-1, 2))
    var_t = blur_sigma_px ** 2 + sigma_px ** 2 + _TANGENT_SAMPLING_VAR + s2t / 6.0
    return 0.5 * np.asarray(curvature_px, dtype=np.float64) * var_t


def fit_conic_robust(uv: np.ndarray, *, mad_k: float = 3.5, min_sigma_px: float = 0.05,
                     iterations: int = 2, geometric: bool = True) -> "tuple[np.ndarray, np.ndarray, np.ndarray] | Failure":
    """Direct (Halir–Flusser) then geometric conic fit with MAD outlier rejection.

    ``uv`` (N, 2) px.  Points farther than ``mad_k`` robust sigmas (1.4826 MAD, at least
    ``min_sigma_px``) from the current fit are dropped, ``iterations`` times; then (if
    ``geometric``) a Levenberg–Marquardt fit of the Sampson distances, one more
    rejection and a final geometric fit.
    Returns ``(conic (3, 3), inlier mask (N,), residuals of the inliers (M,) px)`` or a
    :class:`~lightplane.core.geometry.Failure` with the reason.
    """
    uv = np.asarray(uv, dtype=np.float64)
    keep = np.all(np.isfinite(uv), axis=1)
    C = fit_ellipse_direct(uv[keep])
    if isinstance(C, Failure):
        return C
    for _ in range(iterations):
        r = sampson_distance_unchecked(C, uv)
        r[~np.isfinite(r)] = np.inf
        rk = r[keep]
        med = np.median(rk)
        sig = max(robust_sigma(rk - med, center=False), min_sigma_px)  # robust_sigma(rk), its median not recomputed
        keep = np.abs(r - med) <= mad_k * sig
        if keep.sum() < 6:
            return Failure(f"only {int(keep.sum())} points left after the outlier rejection")
        C2 = fit_ellipse_direct(uv[keep])
        if isinstance(C2, Failure):
            return C2
        C = C2
    if not geometric:
        return C, keep, sampson_distance_unchecked(C, uv[keep])
    g = fit_ellipse_geometric(uv[keep], C)
    if isinstance(g, Failure):
        return g
    C, res = g
    # a last rejection on the geometric residuals, then the final geometric fit
    med = np.median(res)
    sig = max(robust_sigma(res - med, center=False), min_sigma_px)
    r_all = sampson_distance_unchecked(C, uv)
    keep2 = keep & (np.abs(r_all - med) <= mad_k * sig)
    if keep2.sum() >= 6 and keep2.sum() < keep.sum():
        g2 = fit_ellipse_geometric(uv[keep2], C)
        if not isinstance(g2, Failure):
            C, res = g2
            keep = keep2
    return C, keep, res


def _fit_edge_points(uv: np.ndarray, geometric: bool, what: str):
    """Robust conic fit of edge points -> ``(conic, inlier mask, Ellipse)``; LightplaneError if none fits."""
    fit = fit_conic_robust(uv, geometric=geometric)
    if isinstance(fit, Failure):
        raise LightplaneError(f"refine_ellipse: no ellipse fits {what}")
    C, keep, _ = fit
    try:
        return C, keep, Ellipse.from_conic(C)
    except LightplaneError as exc:
        raise LightplaneError(f"refine_ellipse: {exc}") from exc


@dataclass(frozen=True)
class EllipseRefinementOptions:
    """Options of :func:`refine_ellipse` (checked on construction).

    band_px : half-width of the search band along the normals for the first pass
        (None: ``clip(0.1 b, 3, 8)`` px of the ellipse); later passes use 2 px around the new fit.
    sigma_px : Gaussian pre-smoothing before the gradient (px).
    polarity : ``"dark"``/``"light"`` interior, or None: the ellipse's own polarity if
        known, else the stronger response.
    iterations : passes of edge sampling and fitting (at least one is made).
    min_inliers : fewer edge points (found, or inliers of the fit) raise LightplaneError.
    correct_curvature : estimate the rim's blur (:func:`edge_blur_sigma`) and move each
        edge point outward along its normal by the curvature bias of the gradient peak
        (:func:`curvature_bias_px`, with the curvature of the current fit), then refit.
        The blur estimate is returned (``blur_sigma_px``) either way.
    """

    band_px: float | None = None
    sigma_px: float = 0.8
    polarity: str | int | None = None
    iterations: int = 3
    min_inliers: int = 20
    correct_curvature: bool = True

    def __post_init__(self) -> None:
        if self.polarity not in _POLARITY:
            raise LightplaneError(f"polarity must be None, 'dark' or 'light', got {self.polarity!r}")


@dataclass
class _EdgeFit:
    """The state of :func:`refine_ellipse` after its passes: the edge samples of the last pass
    (crop coordinates), their points (moved by the curvature correction, if any), the inlier
    mask and fit (crop coordinates), the ellipse the samples were taken on and the polarity."""

    samples: NormalEdgeSamples
    uv: np.ndarray
    keep: np.ndarray
    conic: np.ndarray
    local: Ellipse
    sampled_on: Ellipse
    pol: int


def refine_ellipse(image: np.ndarray, ellipse: Ellipse, camera=None,
                   options: EllipseRefinementOptions | None = None) -> RefinedEllipse:
    """Refine ``ellipse`` on ``image`` to sub-pixel accuracy (docs/method.md §Ellipse).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array, any dtype (8/16-bit, float).
    ellipse : approximate ellipse (image pixels), e.g. from :func:`detect_ellipses`.
    camera : optional :class:`lightplane.camera.model.Camera`; then the edge points are
        undistorted (``camera.undistort_points``) and the returned conic is in
        undistorted pixels.
    options : :class:`EllipseRefinementOptions` (None: the defaults): the search band, the
        pre-smoothing, the polarity, the passes, the fewest inliers and the curvature correction.

    Raises LightplaneError when too few edge points are found (< ``options.min_inliers``).

    >>> import numpy as np
    >>> img = np.full((120, 160), 200.0)
    >>> vv, uu = np.mgrid[0:120, 0:160]
    >>> img[((uu - 80.3) / 40) ** 2 + ((vv - 60.2) / 25) ** 2 <= 1] = 40.0
    >>> r = refine_ellipse(img, Ellipse.from_params((80, 60), 39, 26, 0.0))
    >>> bool(np.hypot(*(r.ellipse.centre - (80.3, 60.2))) < 0.1)
    True
    """
    opts = EllipseRefinementOptions() if options is None else options
    if not isinstance(ellipse, Ellipse):
        raise LightplaneError(f"ellipse must be an Ellipse, got {type(ellipse).__name__}")
    pol = _POLARITY[opts.polarity] or int(ellipse.polarity)
    gray = prepare_gray(image)
    if camera is not None:
        camera.check_image(gray)
    band_px = opts.band_px if opts.band_px is not None else float(np.clip(0.1 * ellipse.b, 3.0, 8.0))
    grad, off = _gradients_about(gray, ellipse, band_px, opts.sigma_px)
    local = Ellipse.from_params(ellipse.centre - off, ellipse.a, ellipse.b, ellipse.angle)
    n = int(np.clip(round(ellipse.perimeter), 64, 4000))
    fit = _edge_passes(grad, ellipse, local, n, band_px, pol, opts, camera is None)
    blur = edge_blur_sigma(fit.samples.width_sq[fit.keep], fit.samples.normal[fit.keep], opts.sigma_px)
    shift_mean = 0.0
    if opts.correct_curvature and np.isfinite(blur):
        shift_mean = _correct_curvature(fit, blur, opts.sigma_px, camera is None)
    uv_px = fit.uv[fit.keep] + off
    if int(fit.keep.sum()) < opts.min_inliers:
        raise LightplaneError(f"refine_ellipse: only {int(fit.keep.sum())} inlier edge points")
    local = fit.local
    image_ellipse = Ellipse.from_params(local.centre + off, local.a, local.b, local.angle,
                                        polarity=fit.pol or ellipse.polarity, score=ellipse.score,
                                        inlier_ratio=ellipse.inlier_ratio, coverage=ellipse.coverage)
    conic, uv_px, und, res = _final_conic(image_ellipse, uv_px, camera)
    out_ellipse = Ellipse.from_conic(conic, polarity=image_ellipse.polarity, score=ellipse.score,
                                     inlier_ratio=ellipse.inlier_ratio, coverage=ellipse.coverage)
    uv_px.flags.writeable = False
    und.flags.writeable = False
    return RefinedEllipse(conic=out_ellipse.conic, ellipse=out_ellipse, image_ellipse=image_ellipse,
                          edge_points_px=uv_px, edge_points_undistorted=und,
                          residual_rms_px=float(np.sqrt(np.mean(res ** 2))), n_inliers=len(uv_px), n_samples=n,
                          blur_sigma_px=blur, curvature_shift_px=shift_mean)


def _gradients_about(gray: np.ndarray, ellipse: Ellipse, band_px: float, sigma_px: float):
    """The gradients of a crop of ``gray`` around ``ellipse`` (the gradients of the whole image
    are not needed) and the crop's offset ``(u0, v0)`` (2,) px; LightplaneError when the
    ellipse lies outside the image."""
    h, w = gray.shape
    m = int(math.ceil(band_px + 4 * sigma_px + 4))
    u0, v0, u1, v1 = ellipse.bbox()
    cu0, cv0 = max(int(math.floor(u0)) - m, 0), max(int(math.floor(v0)) - m, 0)
    cu1, cv1 = min(int(math.ceil(u1)) + m, w - 1), min(int(math.ceil(v1)) + m, h - 1)
    if cu1 - cu0 < 4 or cv1 - cv0 < 4:
        raise LightplaneError("ellipse lies outside the image")
    grad = gradients(np.ascontiguousarray(gray[cv0:cv1 + 1, cu0:cu1 + 1]), sigma_px)
    return grad, np.array([cu0, cv0], dtype=np.float64)


def _edge_passes(grad: Gradients, ellipse: Ellipse, local: Ellipse, n: int, band_px: float, pol: int,
                 opts: EllipseRefinementOptions, geometric_last: bool) -> _EdgeFit:
    """:func:`refine_ellipse`'s passes: edge points along the normals of the current fit (``n``
    samples, a band of ``band_px`` first, then 2 px), each pass refitted (geometrically on the
    last pass when ``geometric_last``); ``local`` the starting ellipse in crop coordinates."""
    # weak-edge floor: a fraction of the strongest gradient in the crop
    assert grad.mag is not None  # gradients() computes the magnitude by default
    min_mag = 0.05 * float(np.percentile(grad.mag, 99.5))
    band = band_px
    fit = None
    passes = max(1, opts.iterations)
    for it in range(passes):
        samples = normal_edge_samples(grad, local, n=n, band_px=band, step_px=0.5, polarity=pol,
                                      min_mag=min_mag, max_angle_rad=math.radians(30))
        pts, pol = samples.uv, samples.polarity
        sampled_on = local
        if len(pts) < opts.min_inliers:
            raise LightplaneError(f"refine_ellipse: only {len(pts)} edge points found near the ellipse")
        C, keep, new_local = _fit_edge_points(pts, it == passes - 1 and geometric_last, "the edge points")
        if np.hypot(*(new_local.centre - local.centre)) > max(band, 0.5 * ellipse.b):
            raise LightplaneError("refine_ellipse: the fit moved away from the given ellipse")
        local = new_local
        fit = _EdgeFit(samples, pts, keep, C, local, sampled_on, pol)
        band = 2.0
    assert fit is not None  # the loop runs at least once
    return fit


def _correct_curvature(fit: _EdgeFit, blur: float, sigma_px: float, geometric: bool) -> float:
    """Move ``fit``'s edge points outward by the curvature bias of the gradient peak and refit
    (``fit`` updated in place); the mean shift of the inliers (px)."""
    samples = fit.samples
    # the points lie on the normals of the ellipse they were sampled on: its curvature
    # there (the final fit differs by a few hundredths of a px)
    kappa = ellipse_curvature(fit.sampled_on, samples.t)
    shift = curvature_bias_px(kappa, samples.normal, blur, sigma_px)
    fit.uv = fit.uv + shift[:, None] * samples.normal
    fit.conic, fit.keep, fit.local = _fit_edge_points(fit.uv, geometric, "the curvature-corrected edge points")
    return float(np.mean(shift[fit.keep]))


def _final_conic(image_ellipse: Ellipse, uv_px: np.ndarray, camera):
    """The refined conic, the inlier edge points (distorted px), the same undistorted and their
    residuals: without a camera the image ellipse's; with one, fitted again to the undistorted points."""
    if camera is None:
        conic = image_ellipse.conic
        und = uv_px.copy()
        return conic, uv_px, und, sampson_distance(conic, und)
    und = camera.undistort_points(uv_px)
    fit = fit_conic_robust(und, iterations=1)
    if isinstance(fit, Failure):
        raise LightplaneError("refine_ellipse: no ellipse fits the undistorted edge points")
    conic, k2, res = fit
    return conic, uv_px[k2], und[k2], res
