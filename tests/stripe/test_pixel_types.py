"""The stripe kernels run on two pixel types: 8-bit as given, everything else as float32.

A 16-bit frame that is an 8-bit frame scaled (x 257: the full scale's ratio; x 16: 12-bit data in
a 16-bit container, whose full scale is 4095) and a float frame (/ 255) give the 8-bit frame's
centres: the thresholds follow the full scale, every sum is linear in the pixel values, so only
the rounding of the scaled sums differs (~1e-13 px; 1e-9 px allowed)."""

from __future__ import annotations

import numpy as np
import pytest

from lightplane.stripe import kernels as K
from lightplane.stripe.extract import KERNEL_PIXEL_TYPES, extract_profile, extract_profiles, extract_stripe, kernel_pixels


def _frame(seed: int = 3, H: int = 150, W: int = 220) -> np.ndarray:
    """A curved, tilted Gaussian stripe (FWHM 5 px), noise 2 grey levels, 8-bit."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    centre = 0.45 * H + 0.08 * (u - W / 2) + 12.0 * np.sin(u / W * np.pi)
    img = 12.0 + 190.0 * np.exp(-0.5 * ((v - centre) / (5.0 / 2.3548)) ** 2) + rng.normal(0.0, 2.0, (H, W))
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


#: frame type -> (the 8-bit frame scaled into it, the centres' tolerance, px)
SCALED = {
    "16-bit": (lambda a: a.astype(np.uint16) * 257, 1e-9),
    "12-bit in 16": (lambda a: a.astype(np.uint16) * 16, 1e-9),
    "float32 0..255": (lambda a: a.astype(np.float32), 1e-9),
    "float64 0..255": (lambda a: a.astype(np.float64), 1e-9),
    # a / 255 is rounded to float32 (6e-8 of the value): the centres move by ~1e-8 px
    "float32 0..1": (lambda a: (a / np.float32(255.0)).astype(np.float32), 1e-6),
}


def _same_profile(a, b, atol: float) -> None:
    np.testing.assert_array_equal(a.status, b.status)
    np.testing.assert_array_equal(a.valid, b.valid)
    assert a.valid.sum() > 100
    np.testing.assert_allclose(b.uv[b.valid], a.uv[a.valid], rtol=0, atol=atol)
    assert b.width_px == pytest.approx(a.width_px, abs=atol)


@pytest.mark.parametrize("kind", list(SCALED))
def test_scaled_frames_give_the_8bit_centres(kind):
    img8 = _frame()
    scale, atol = SCALED[kind]
    img = scale(img8)
    for axis, a8, a in (("columns", img8, img), ("rows", img8.T.copy(), img.T.copy())):   # rows: the stripe upright
        _same_profile(extract_profile(a8, axis=axis, parallel=False), extract_profile(a, axis=axis, parallel=False), atol)
        roi = (10, 15, 120, 180) if axis == "rows" else (15, 10, 180, 120)   # rows: the width from A's copy
        _same_profile(extract_profile(a8, axis=axis, roi=roi), extract_profile(a, axis=axis, roi=roi), atol)
    stack8 = np.stack([img8, img8[::-1].copy()])
    for a, b in zip(extract_profiles(stack8, parallel=False), extract_profiles(np.stack([img, img[::-1].copy()]),
                                                                                parallel=False)):
        _same_profile(a, b, atol)


def test_scaled_frames_give_the_8bit_stripe_points():
    img8 = _frame()
    a = extract_stripe(img8)
    b = extract_stripe(SCALED["16-bit"][0](img8))
    # the derivative images are float32 (OpenCV): the scaled image's are rounded differently, ~1e-7 relative
    assert len(a) == len(b) > 150
    np.testing.assert_allclose(b.uv, a.uv, rtol=0, atol=1e-4)


def test_the_kernels_see_two_pixel_types_only():
    img8 = _frame()
    for f, _ in SCALED.values():
        extract_profile(f(img8), parallel=False)
        extract_profiles(np.stack([f(img8)] * 2), parallel=False)
    assert kernel_pixels(img8) is img8
    allowed = {np.dtype(t).name for t in KERNEL_PIXEL_TYPES}
    assert allowed == {"uint8", "float32"}
    for k in (K.profile_frame, K.profiles_batch_serial, K.fwhm_median):
        pixel_types = {str(sig[0].dtype) for sig in k.signatures}   # the image argument's, numba's names
        assert pixel_types and pixel_types <= allowed, (k, pixel_types)
