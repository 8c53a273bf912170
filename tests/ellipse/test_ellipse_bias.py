"""Curvature bias of the refined rim edge points.

On a curved edge blurred by a Gaussian of sigma, the gradient-magnitude peak lies
inside the true edge by ``sigma_t^2 / (2 R)`` (``sigma_t^2`` = optical blur² + the
derivative filter's variance, R the radius of curvature, px).  The images here are
exact: a disc of radius R convolved with an isotropic Gaussian and point-sampled at
the pixel centres is ``P(|X| <= R)`` with ``X ~ N(pixel - centre, sigma^2 I)``, the
non-central chi-square CDF ``chndtr(R²/sigma², 2, r²/sigma²)``.  Ellipses are
rendered 8x supersampled, blurred at that resolution and point-sampled (the
indicator's 1/8 px steps average out along the rim).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import chndtr

from lightplane.ellipse import Ellipse, EllipseRefinementOptions, refine_ellipse
from lightplane.ellipse.refine import edge_blur_sigma

SIGMA_FILTER = 0.8  # refine_ellipse's default pre-smoothing (px)


def _blurred_disc(size: int, centre: np.ndarray, radius_px: float, sigma_px: float, inside: float,
                  outside: float) -> np.ndarray:
    vv, uu = np.mgrid[0:size, 0:size].astype(np.float64)
    r = np.hypot(uu - centre[0], vv - centre[1])
    frac = np.zeros_like(r)
    near = r <= radius_px + 10 * sigma_px
    frac[near] = chndtr((radius_px / sigma_px) ** 2, 2, (r[near] / sigma_px) ** 2)
    return outside + (inside - outside) * frac


def _blurred_ellipse(shape: tuple[int, int], e: Ellipse, sigma_px: float, inside: float, outside: float,
                     factor: int = 8) -> np.ndarray:
    import cv2

    h, w = shape
    # sub-pixel k of pixel i sits at i + (k + 0.5) / factor - 0.5; the centre sample of
    # each block (k = factor / 2) is the pixel centre when factor is even -> offset 1/(2f)
    vv, uu = np.mgrid[0:h * factor, 0:w * factor].astype(np.float64)
    uu = (uu + 0.5) / factor - 0.5
    vv = (vv + 0.5) / factor - 0.5
    ind = (e.algebraic(np.column_stack([uu.ravel(), vv.ravel()])) <= 0).reshape(uu.shape).astype(np.float32)
    big = cv2.GaussianBlur(ind, (0, 0), sigma_px * factor, borderType=cv2.BORDER_REFLECT)
    # point-sample halfway between the two central sub-pixels of each block: average them
    k = factor // 2
    s = 0.25 * (big[k - 1::factor, k - 1::factor] + big[k::factor, k - 1::factor]
                + big[k - 1::factor, k::factor] + big[k::factor, k::factor])
    return outside + (inside - outside) * s.astype(np.float64)


def _signed_distance_to_circle(uv: np.ndarray, centre: np.ndarray, radius_px: float) -> np.ndarray:
    return np.hypot(uv[:, 0] - centre[0], uv[:, 1] - centre[1]) - radius_px


def _signed_distance_to_ellipse(uv: np.ndarray, e: Ellipse) -> np.ndarray:
    C = e.conic  # interior negative
    h = np.column_stack([uv, np.ones(len(uv))])
    f = np.einsum("ni,ij,nj->n", h, C, h)
    g = 2.0 * (h @ C[:, :2])
    return f / np.linalg.norm(g, axis=1)


@pytest.mark.parametrize("radius_px,sigma_px,polarity", [
    (20.0, 0.6, "dark"), (40.0, 0.9, "light"), (80.0, 1.3, "dark"), (120.0, 0.9, "light"),
])
def test_curvature_bias_removed_on_exact_blurred_discs(radius_px, sigma_px, polarity):
    # The sub-pixel peak estimator has a pixel-locking error that depends on the disc's
    # position on the pixel grid (the mean over one image's rim scatters by ~0.003 px at
    # R 40 px, without any noise): the bias is a mean over a 3 x 3 grid of sub-pixel
    # centres, which averages that zero-mean part out.
    size = int(2 * radius_px + 40)
    inside, outside = (40.0, 200.0) if polarity == "dark" else (210.0, 30.0)
    before, after, blur = [], [], []
    for du in (1 / 6, 1 / 2, 5 / 6):
        for dv in (1 / 6, 1 / 2, 5 / 6):
            centre = np.array([size // 2 + du, size // 2 + dv])
            img = _blurred_disc(size, centre, radius_px, sigma_px, inside, outside)
            init = Ellipse.from_params(centre + (0.4, -0.3), 1.02 * radius_px, 0.98 * radius_px, 0.4)
            r0 = refine_ellipse(img, init, options=EllipseRefinementOptions(correct_curvature=False))
            r1 = refine_ellipse(img, init)
            before.append(np.mean(_signed_distance_to_circle(r0.edge_points_px, centre, radius_px)))
            after.append(np.mean(_signed_distance_to_circle(r1.edge_points_px, centre, radius_px)))
            blur.append(r1.blur_sigma_px)
            assert r1.curvature_shift_px > 0
            assert math.isfinite(r0.blur_sigma_px) and r0.curvature_shift_px == 0.0
    # lower bound of the prediction: optical blur and pre-smoothing only (the difference
    # kernel and the bilinear sampling add ~0.4 px²)
    pred = (sigma_px ** 2 + SIGMA_FILTER ** 2) / (2 * radius_px)
    assert np.mean(before) < -0.9 * pred  # inside, as predicted
    assert np.mean(before) > -2.0 * pred
    assert abs(np.mean(after)) <= 0.002
    assert abs(np.mean(blur) / sigma_px - 1.0) <= 0.15


def test_curvature_bias_removed_on_blurred_ellipse():
    # curvature radius from b²/a = 18 px to a²/b = 89 px along the rim
    e = Ellipse.from_params((80.3, 70.6), 60.0, 40.0, 0.5)
    sigma_px = 1.0
    img = _blurred_ellipse((141, 161), e, sigma_px, 30.0, 190.0)
    init = Ellipse.from_params((80.0, 71.0), 61.0, 39.0, 0.45)
    r0 = refine_ellipse(img, init, options=EllipseRefinementOptions(correct_curvature=False))
    r1 = refine_ellipse(img, init)
    d0 = _signed_distance_to_ellipse(r0.edge_points_px, e)
    d1 = _signed_distance_to_ellipse(r1.edge_points_px, e)
    # mean curvature along the rim (by arc length) is 2 pi / perimeter
    pred = (sigma_px ** 2 + SIGMA_FILTER ** 2) * (2 * math.pi / e.perimeter) / 2
    assert np.mean(d0) < -0.9 * pred
    assert abs(np.mean(d1)) <= 0.002
    # semi-axes: ~pred short before; after within the pixel-locking scatter of one image
    assert e.a - r0.ellipse.a > 0.5 * pred and e.b - r0.ellipse.b > 0.5 * pred
    assert abs(r1.ellipse.a - e.a) <= 0.005 and abs(r1.ellipse.b - e.b) <= 0.005
    assert abs(r1.blur_sigma_px / sigma_px - 1.0) <= 0.15


def test_edge_blur_sigma_inverts_the_width_model():
    rng = np.random.default_rng(3)
    th = rng.uniform(0, 2 * math.pi, 200)
    nrm = np.column_stack([np.cos(th), np.sin(th)])
    q = np.cos(th) ** 4 + np.sin(th) ** 4
    w2 = 0.7 ** 2 + 0.8 ** 2 + q / 3 + 0.20
    assert edge_blur_sigma(w2, nrm, 0.8) == pytest.approx(0.7, abs=1e-12)
    assert math.isnan(edge_blur_sigma(w2[:5], nrm[:5], 0.8))
