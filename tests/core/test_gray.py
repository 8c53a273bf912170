"""The one gray conversion (lightplane.core.io.to_gray_float) and the one 8-bit stretch (to_gray8)."""

import numpy as np
import pytest

from lightplane.core.errors import LightplaneError
from lightplane.core.io import to_gray8, to_gray_float


def _bgr(dtype, hi):
    rng = np.random.default_rng(3)
    return rng.integers(0, hi, (20, 30, 3)).astype(dtype)


@pytest.mark.parametrize("dtype,hi", [(np.uint8, 256), (np.uint16, 65536), (np.float32, 1000), (np.float64, 1000),
                                      (np.int32, 1000)])
def test_gray_is_the_weighted_sum_for_every_dtype(dtype, hi):
    img = _bgr(dtype, hi)
    f = img.astype(np.float64)
    want = 0.114 * f[:, :, 0] + 0.587 * f[:, :, 1] + 0.299 * f[:, :, 2]
    g = to_gray_float(img)
    assert g.dtype == np.float32 and g.shape == (20, 30)
    # OpenCV: integer outputs rounded to a level, its weights in 14-bit fixed point; floats to float32 precision
    tol = 0.5 + hi * 2.0**-14 if dtype in (np.uint8, np.uint16) else 1e-5 * hi
    assert np.max(np.abs(g - want)) <= tol
    bgra = np.concatenate([img, img[:, :, :1]], axis=2)
    assert np.array_equal(to_gray_float(bgra), g)  # alpha ignored


def test_channels_native_types_and_sum():
    img = _bgr(np.uint8, 256)
    for name, k in (("blue", 0), ("green", 1), ("red", 2)):
        assert np.array_equal(to_gray_float(img, name), img[:, :, k].astype(np.float32))
        nat = to_gray_float(img, name, native=True)
        assert nat.dtype == np.uint8 and np.array_equal(nat, img[:, :, k])
    s = to_gray_float(img, "sum", native=True)
    assert s.dtype == np.uint16 and np.array_equal(s, img.astype(np.uint16).sum(axis=2))
    assert to_gray_float(img[:, :, 0], native=True).dtype == np.uint8
    assert to_gray_float(img[:, :, :1]).shape == (20, 30)  # (H, W, 1)
    b = to_gray_float(np.eye(4, dtype=bool))
    assert b.max() == 255.0 and b.min() == 0.0


def test_bad_images_are_one_clear_error():
    img = _bgr(np.float32, 10)
    img[3, 4, 1] = np.nan
    with pytest.raises(LightplaneError, match="frame.png contains NaN or infinite"):
        to_gray_float(img, name="frame.png")
    with pytest.raises(LightplaneError, match="single-channel"):
        to_gray_float(np.zeros((5, 5)), "red")
    with pytest.raises(LightplaneError, match="channel must be"):
        to_gray_float(np.zeros((5, 5, 3)), "purple")
    with pytest.raises(LightplaneError, match=r"\(H, W\)"):
        to_gray_float(np.zeros((5, 5, 2)))
    with pytest.raises(LightplaneError, match="dtype"):
        to_gray_float(np.zeros((5, 5), complex))


def test_gray8_keeps_8bit_data_and_stretches_the_rest():
    img = _bgr(np.uint8, 256)[:, :, 0]
    assert to_gray8(img) is img or np.array_equal(to_gray8(img), img)
    assert np.array_equal(to_gray8(img.astype(np.float32)), img)  # a float copy of 8-bit data stays
    ramp = np.tile(np.linspace(0, 4000, 1001), (8, 1)).astype(np.uint16)  # 16-bit: stretched
    g8 = to_gray8(ramp, percentiles=(10.0, 90.0))
    lo, hi = np.percentile(ramp.astype(np.float64), [10, 90])
    want = np.clip((ramp - lo) * 255.0 / (hi - lo), 0, 255).astype(np.uint8)
    assert np.max(np.abs(g8.astype(int) - want.astype(int))) <= 1
    assert (g8 == 0).mean() == pytest.approx(0.1, abs=0.01) and (g8 == 255).mean() == pytest.approx(0.1, abs=0.01)
    flat = np.full((10, 10), 700, np.uint16)
    assert not to_gray8(flat).any()
    small = (img // 64).astype(np.uint8)  # dim 8-bit data: kept by default, stretched for pictures
    assert np.array_equal(to_gray8(small), small) and to_gray8(small, keep_8bit=False).max() == 255
