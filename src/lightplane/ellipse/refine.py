"""Sub-pixel refinement of a detected ellipse for metrology (SPEC §5.1).

Edge points are found along the ellipse's normals (gradient-magnitude peak, Gaussian
fit through three samples), outliers are rejected with the median absolute deviation
of their distances to a first fit, and the conic is fitted by Halir–Flusser's direct
method (Hartley-normalised coordinates) followed by a geometric (Sampson-distance)
Levenberg–Marquardt refinement.  With a camera the edge points are undistorted first
and the conic is in *undistorted* pixels, the input of ``circle_poses`` (SPEC §6).
The conic's centre is not the image of the circle's centre under perspective: use
the pose solution for that.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import LightplaneError
from .edges import gradients, normal_edge_points, prepare_gray
from .model import Ellipse, fit_ellipse_direct, fit_ellipse_geometric, sampson_distance

__all__ = ["RefinedEllipse", "refine_ellipse", "fit_conic_robust"]


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
    """

    conic: np.ndarray = field(repr=False)
    ellipse: Ellipse
    image_ellipse: Ellipse
    edge_points_px: np.ndarray = field(repr=False)
    edge_points_undistorted: np.ndarray = field(repr=False)
    residual_rms_px: float
    n_inliers: int
    n_samples: int


def fit_conic_robust(uv: np.ndarray, *, mad_k: float = 3.5, min_sigma_px: float = 0.05,
                     iterations: int = 2, geometric: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Direct (Halir–Flusser) then geometric conic fit with MAD outlier rejection.

    ``uv`` (N, 2) px.  Points farther than ``mad_k`` robust sigmas (1.4826 MAD, at least
    ``min_sigma_px``) from the current fit are dropped, ``iterations`` times; then (if
    ``geometric``) a Levenberg–Marquardt fit of the Sampson distances, one more
    rejection and a final geometric fit.
    Returns ``(conic (3, 3), inlier mask (N,), residuals of the inliers (M,) px)`` or None.
    """
    uv = np.asarray(uv, dtype=np.float64)
    keep = np.all(np.isfinite(uv), axis=1)
    C = fit_ellipse_direct(uv[keep])
    if C is None:
        return None
    for _ in range(iterations):
        r = sampson_distance(C, uv)
        r[~np.isfinite(r)] = np.inf
        med = np.median(r[keep])
        sig = max(1.4826 * np.median(np.abs(r[keep] - med)), min_sigma_px)
        keep = np.abs(r - med) <= mad_k * sig
        if keep.sum() < 6:
            return None
        C2 = fit_ellipse_direct(uv[keep])
        if C2 is None:
            return None
        C = C2
    if not geometric:
        return C, keep, sampson_distance(C, uv[keep])
    g = fit_ellipse_geometric(uv[keep], C)
    if g is None:
        return None
    C, res = g
    # a last rejection on the geometric residuals, then the final geometric fit
    med = np.median(res)
    sig = max(1.4826 * np.median(np.abs(res - med)), min_sigma_px)
    r_all = sampson_distance(C, uv)
    keep2 = keep & (np.abs(r_all - med) <= mad_k * sig)
    if keep2.sum() >= 6 and keep2.sum() < keep.sum():
        g2 = fit_ellipse_geometric(uv[keep2], C)
        if g2 is not None:
            C, res = g2
            keep = keep2
    return C, keep, res


def refine_ellipse(image: np.ndarray, ellipse: Ellipse, camera=None, *, band_px: float | None = None,
                   sigma_px: float = 0.8, polarity: str | int | None = None, iterations: int = 3,
                   min_inliers: int = 20) -> RefinedEllipse:
    """Refine ``ellipse`` on ``image`` to sub-pixel accuracy (SPEC §5.1).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array, any dtype (8/16-bit, float).
    ellipse : approximate ellipse (image pixels), e.g. from :func:`detect_ellipses`.
    camera : optional :class:`lightplane.camera.Camera`; then the edge points are
        undistorted (``camera.undistort_points``) and the returned conic is in
        undistorted pixels.
    band_px : half-width of the search band along the normals for the first pass
        (default ``clip(0.1 b, 3, 8)`` px); later passes use 2 px around the new fit.
    sigma_px : Gaussian pre-smoothing before the gradient (px).
    polarity : ``"dark"``/``"light"`` interior, or None: the ellipse's own polarity if
        known, else the stronger response.

    Raises LightplaneError when too few edge points are found (< ``min_inliers``).

    >>> import numpy as np
    >>> img = np.full((120, 160), 200.0)
    >>> vv, uu = np.mgrid[0:120, 0:160]
    >>> img[((uu - 80.3) / 40) ** 2 + ((vv - 60.2) / 25) ** 2 <= 1] = 40.0
    >>> r = refine_ellipse(img, Ellipse.from_params((80, 60), 39, 26, 0.0))
    >>> bool(np.hypot(*(r.ellipse.centre - (80.3, 60.2))) < 0.1)
    True
    """
    if not isinstance(ellipse, Ellipse):
        raise LightplaneError(f"ellipse must be an Ellipse, got {type(ellipse).__name__}")
    from .detect import _POLARITY

    if polarity not in _POLARITY:
        raise LightplaneError(f"polarity must be None, 'dark' or 'light', got {polarity!r}")
    pol = _POLARITY[polarity] or int(ellipse.polarity)
    gray = prepare_gray(image)
    if camera is not None:
        camera.check_image(gray)
    h, w = gray.shape
    if band_px is None:
        band_px = float(np.clip(0.1 * ellipse.b, 3.0, 8.0))
    # work on a crop around the ellipse (gradients of the whole image are not needed)
    m = int(math.ceil(band_px + 4 * sigma_px + 4))
    u0, v0, u1, v1 = ellipse.bbox()
    cu0, cv0 = max(int(math.floor(u0)) - m, 0), max(int(math.floor(v0)) - m, 0)
    cu1, cv1 = min(int(math.ceil(u1)) + m, w - 1), min(int(math.ceil(v1)) + m, h - 1)
    if cu1 - cu0 < 4 or cv1 - cv0 < 4:
        raise LightplaneError("ellipse lies outside the image")
    grad = gradients(np.ascontiguousarray(gray[cv0:cv1 + 1, cu0:cu1 + 1]), sigma_px)
    off = np.array([cu0, cv0], dtype=np.float64)
    local = Ellipse.from_params(ellipse.centre - off, ellipse.a, ellipse.b, ellipse.angle)
    n = int(np.clip(round(ellipse.perimeter), 64, 4000))
    # weak-edge floor: a fraction of the strongest gradient in the crop
    min_mag = 0.05 * float(np.percentile(grad.mag, 99.5))
    band = band_px
    uv = None
    keep = None
    for it in range(max(1, iterations)):
        pts, _, _, pol = normal_edge_points(grad, local, n=n, band_px=band, step_px=0.5, polarity=pol,
                                            min_mag=min_mag, max_angle_rad=math.radians(30))
        if len(pts) < min_inliers:
            raise LightplaneError(f"refine_ellipse: only {len(pts)} edge points found near the ellipse")
        last = it == max(1, iterations) - 1
        fit = fit_conic_robust(pts, geometric=last and camera is None)
        if fit is None:
            raise LightplaneError("refine_ellipse: no ellipse fits the edge points")
        C, keep, _ = fit
        try:
            new_local = Ellipse.from_conic(C)
        except LightplaneError as exc:
            raise LightplaneError(f"refine_ellipse: {exc}") from exc
        if np.hypot(*(new_local.centre - local.centre)) > max(band, 0.5 * ellipse.b):
            raise LightplaneError("refine_ellipse: the fit moved away from the given ellipse")
        local = new_local
        uv = pts
        band = 2.0
    uv_px = uv[keep] + off
    if int(keep.sum()) < min_inliers:
        raise LightplaneError(f"refine_ellipse: only {int(keep.sum())} inlier edge points")
    image_ellipse = Ellipse.from_params(local.centre + off, local.a, local.b, local.angle,
                                        polarity=pol or ellipse.polarity, score=ellipse.score,
                                        inlier_ratio=ellipse.inlier_ratio, coverage=ellipse.coverage)
    if camera is None:
        conic = image_ellipse.conic
        und = uv_px.copy()
        res = sampson_distance(conic, und)
    else:
        und = camera.undistort_points(uv_px)
        fit = fit_conic_robust(und, iterations=1)
        if fit is None:
            raise LightplaneError("refine_ellipse: no ellipse fits the undistorted edge points")
        conic, k2, res = fit
        uv_px, und = uv_px[k2], und[k2]
    out_ellipse = Ellipse.from_conic(conic, polarity=image_ellipse.polarity, score=ellipse.score,
                                     inlier_ratio=ellipse.inlier_ratio, coverage=ellipse.coverage)
    uv_px.flags.writeable = False
    und.flags.writeable = False
    return RefinedEllipse(conic=out_ellipse.conic, ellipse=out_ellipse, image_ellipse=image_ellipse,
                          edge_points_px=uv_px, edge_points_undistorted=und,
                          residual_rms_px=float(np.sqrt(np.mean(res ** 2))), n_inliers=len(uv_px), n_samples=n)
