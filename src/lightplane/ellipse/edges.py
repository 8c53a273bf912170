"""Image preparation, gradients and sub-pixel edge sampling along an ellipse's normals.

Shared by detection (verification, final refit) and :func:`refine_ellipse`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lightplane.ellipse.model import Ellipse
from lightplane.core.io import to_gray8, to_gray_float

__all__ = ["prepare_gray", "Gradients", "gradients", "normal_edge_points", "normal_edge_samples", "NormalEdgeSamples",
           "edge_peaks_along_normals"]


def prepare_gray(image: np.ndarray, name: str = "image") -> np.ndarray:
    """Gray float32 image (H, W), C-contiguous: :func:`lightplane.core.io.to_gray_float`."""
    return np.ascontiguousarray(to_gray_float(image, name=name))


def to_uint8(gray: np.ndarray) -> np.ndarray:
    """8-bit version of a gray image for the segment detector: :func:`lightplane.core.io.to_gray8`
    (8-bit-scale data kept, others stretched between the 0.1 and 99.9 percentiles)."""
    return to_gray8(gray, percentiles=(0.1, 99.9))


@dataclass(frozen=True)
class Gradients:
    """Smoothed image gradients (float32 (H, W) each), derivative per pixel (central difference)."""

    gx: np.ndarray
    gy: np.ndarray
    mag: np.ndarray | None


def gradients(gray: np.ndarray, sigma_px: float = 1.0, *, with_magnitude: bool = True) -> Gradients:
    """Gaussian pre-smoothing (``sigma_px``, 0 for none) then central-difference gradients."""
    import cv2

    g = gray
    if sigma_px > 0:
        g = cv2.GaussianBlur(gray, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)
    kx = np.array([[-0.5, 0.0, 0.5]], np.float32)
    gx = cv2.filter2D(g, cv2.CV_32F, kx, borderType=cv2.BORDER_REFLECT)
    gy = cv2.filter2D(g, cv2.CV_32F, kx.T, borderType=cv2.BORDER_REFLECT)
    return Gradients(gx, gy, cv2.magnitude(gx, gy) if with_magnitude else None)


def _remap(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``img`` at (u, v) (any equal shapes), 0 outside the image."""
    import cv2

    shp = np.shape(u)
    mu = np.asarray(u, dtype=np.float32).ravel()
    mv = np.asarray(v, dtype=np.float32).ravel()
    m = mu.size
    if m == 0:
        return np.zeros(shp, np.float32)
    cols = 1024
    rows = -(-m // cols)
    pad = rows * cols - m
    map_u = np.concatenate([mu, np.full(pad, -10.0, np.float32)]).reshape(rows, cols)
    map_v = np.concatenate([mv, np.full(pad, -10.0, np.float32)]).reshape(rows, cols)
    out = cv2.remap(img, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out.ravel()[:m].reshape(shp)


def edge_peaks_along_normals(grad: Gradients, p: np.ndarray, nrm: np.ndarray, polarity: np.ndarray, *,
                             band_px: np.ndarray | float, step_px: float = 0.5, min_mag: float = 0.0,
                             max_angle_rad: float = math.radians(30), return_width: bool = False):
    """Sub-pixel gradient peaks along given normals (vectorised over samples).

    ``p`` (N, 2) px sample points, ``nrm`` (N, 2) outward unit normals, ``polarity`` (N,)
    of +1 (interior brighter) or -1 (darker), ``band_px`` scalar or (N,).  The gradient
    (bilinear, ``cv2.remap``) is sampled along the normal every ``step_px`` within the band;
    its component along the normal, signed by polarity, is maximised and the peak located
    by a Gaussian (log-parabola) fit through the three samples around it (parabola when a
    sample is not positive).  Returns ``(uv (N, 2), ok (N,), peak (N,))``: a sample is not
    ok when its peak is on the band's border, weaker than ``min_mag`` or its gradient
    direction is more than ``max_angle_rad`` off the normal.

    ``return_width``: also return ``width_sq (N,)`` px², the squared Gaussian width of
    the gradient profile across the edge: least-squares parabola through the logarithm
    of the five samples within +-1 px of the peak sample (``sigma^2 = -1 / (2 c2)``);
    NaN where a sample is missing or not positive or the log-profile is not concave.
    It measures the total blur across the edge (optics, pixel, pre-smoothing, the
    derivative's difference kernel and the bilinear sampling): see
    :func:`lightplane.ellipse.refine.edge_blur_sigma`.
    """
    n = len(p)
    band = np.broadcast_to(np.asarray(band_px, dtype=np.float64), (n,))
    k = int(math.ceil(float(np.max(band)) / step_px)) if n else 1
    offs = np.arange(-k, k + 1) * step_px
    U = p[:, 0:1] + offs[None, :] * nrm[:, 0:1]
    V = p[:, 1:2] + offs[None, :] * nrm[:, 1:2]
    gx = _remap(grad.gx, U, V)
    gy = _remap(grad.gy, U, V)
    pol = np.asarray(polarity, dtype=np.float64).reshape(-1, 1)
    prof = -pol * (gx * nrm[:, 0:1] + gy * nrm[:, 1:2])  # positive peak expected
    prof = np.where(np.abs(offs)[None, :] <= band[:, None] + 1e-9, prof, -np.inf)
    j = np.argmax(prof, axis=1)
    rows = np.arange(n)
    jj = np.clip(j, 1, len(offs) - 2)
    y0, y1, y2 = prof[rows, jj - 1], prof[rows, jj], prof[rows, jj + 1]
    ok = (j > 0) & (j < len(offs) - 1) & np.isfinite(y0) & np.isfinite(y2)
    ok &= (y1 > min_mag) & (y1 > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        tiny = 1e-6 * np.maximum(y1, 1e-12)
        l0, l1, l2 = np.log(np.maximum(y0, tiny)), np.log(np.maximum(y1, tiny)), np.log(np.maximum(y2, tiny))
        den = l0 - 2 * l1 + l2
        dg = 0.5 * (l0 - l2) / den
        dp = 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2)
    use_g = (y0 > 0) & (y2 > 0) & (den < 0)
    delta = np.where(use_g, dg, dp)
    ok &= np.isfinite(delta) & (np.abs(delta) <= 0.5 + 1e-9)
    gxx, gyy = gx[rows, jj], gy[rows, jj]
    gm = np.hypot(gxx, gyy)
    cosang = -pol[:, 0] * (gxx * nrm[:, 0] + gyy * nrm[:, 1]) / np.maximum(gm, 1e-12)
    ok &= cosang >= math.cos(max_angle_rad)
    off = offs[jj] + np.where(np.isfinite(delta), delta, 0.0) * step_px
    uv = p + off[:, None] * nrm
    if not return_width:
        return uv, ok, y1
    width_sq = _log_profile_width_sq(prof, j, step_px)
    return uv, ok, y1, width_sq


def _log_profile_width_sq(prof: np.ndarray, j: np.ndarray, step_px: float) -> np.ndarray:
    """Squared Gaussian width (px²) of each profile row around its peak index ``j``
    (log-parabola least squares over the samples within +-1 px; NaN where not possible)."""
    n, m = prof.shape
    h = max(1, int(round(1.0 / step_px)))
    x = np.arange(-h, h + 1) * step_px
    idx = j[:, None] + np.arange(-h, h + 1)[None, :]
    inside = np.all((idx >= 0) & (idx < m), axis=1)
    vals = prof[np.arange(n)[:, None], np.clip(idx, 0, m - 1)]
    good = inside & np.all(np.isfinite(vals) & (vals > 0), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        lv = np.log(np.where(good[:, None], vals, 1.0))
        xc = x * x - np.mean(x * x)
        c2 = (lv @ xc) / float(xc @ xc)  # quadratic coefficient (x and x² are orthogonal on a symmetric grid)
        w2 = -0.5 / c2
    return np.where(good & (c2 < 0), w2, np.nan)


@dataclass(frozen=True)
class NormalEdgeSamples:
    """Edge points found along an ellipse's normals (:func:`normal_edge_samples`).

    uv (M, 2) px; t (M,) parametric angles of the samples (rad); peak (M,) gradient
    magnitude at the peak; normal (M, 2) outward unit normals searched along;
    width_sq (M,) px² squared Gaussian width of the gradient profile (NaN where not
    measured); polarity: +1 interior brighter, -1 darker.
    """

    uv: np.ndarray
    t: np.ndarray
    peak: np.ndarray
    normal: np.ndarray
    width_sq: np.ndarray
    polarity: int


def normal_edge_samples(grad: Gradients, ellipse: Ellipse, *, n: int, band_px: float, step_px: float = 0.5,
                        polarity: int = 0, min_mag: float = 0.0, max_angle_rad: float = math.radians(30),
                        ) -> NormalEdgeSamples:
    """As :func:`normal_edge_points`, with the normals and the profile widths."""
    t, p, nrm, polarity = _normals_setup(grad, ellipse, n, band_px, step_px, polarity)
    uv, ok, pk, w2 = edge_peaks_along_normals(grad, p, nrm, np.full(len(t), float(polarity)), band_px=band_px,
                                              step_px=step_px, min_mag=min_mag, max_angle_rad=max_angle_rad,
                                              return_width=True)
    return NormalEdgeSamples(uv[ok], t[ok], pk[ok], nrm[ok], w2[ok], int(polarity))


def _normals_setup(grad: Gradients, ellipse: Ellipse, n: int, band_px: float, step_px: float, polarity: int):
    """``n`` (at least 8) equally spaced parametric angles, their points and outward
    normals, and the polarity (0: the sign with the stronger total response)."""
    n = int(max(n, 8))
    t = np.linspace(0.0, 2 * math.pi, n, endpoint=False)
    p = ellipse.points_at(t)
    nrm = ellipse.normals_at(t)  # outward
    if polarity == 0:
        polarity = _stronger_polarity(grad, p, nrm, band_px, step_px)
    return t, p, nrm, polarity


def _stronger_polarity(grad: Gradients, p: np.ndarray, nrm: np.ndarray, band_px: float, step_px: float) -> int:
    n = len(p)
    _, ok_d, pk_d = edge_peaks_along_normals(grad, p, nrm, np.full(n, -1.0), band_px=band_px, step_px=step_px)
    _, ok_l, pk_l = edge_peaks_along_normals(grad, p, nrm, np.full(n, 1.0), band_px=band_px, step_px=step_px)
    return -1 if np.sum(pk_d[ok_d]) >= np.sum(pk_l[ok_l]) else 1


def normal_edge_points(grad: Gradients, ellipse: Ellipse, *, n: int, band_px: float, step_px: float = 0.5,
                       polarity: int = 0, min_mag: float = 0.0, max_angle_rad: float = math.radians(30),
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Sub-pixel edge points along the normals of ``ellipse`` at ``n`` equally spaced
    parametric angles (see :func:`edge_peaks_along_normals`); ``polarity`` 0 picks the
    sign with the stronger total response.

    Returns ``(uv (M, 2) px, t (M,) parametric angles rad, peak (M,) gradient magnitude,
    polarity used)``.
    """
    t, p, nrm, polarity = _normals_setup(grad, ellipse, n, band_px, step_px, polarity)
    uv, ok, pk = edge_peaks_along_normals(grad, p, nrm, np.full(len(t), float(polarity)), band_px=band_px,
                                          step_px=step_px, min_mag=min_mag, max_angle_rad=max_angle_rad)
    return uv[ok], t[ok], pk[ok], int(polarity)
