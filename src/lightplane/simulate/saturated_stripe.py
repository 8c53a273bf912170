"""Synthetic saturated (clipped) laser stripes with an exact centre line.

Used by tests/test_stripe_saturation.py and benchmarks/bench_stripe_saturation.py.
A straight Gaussian stripe (FWHM ``width_px``, direction angle ``theta``: the
sub-pixel position of the centre changes along it) of amplitude ``amplitude``
times the clipping level (a number, or a function of the column ``u`` for a hot
spot), optionally with a blooming halo (a wide, low Gaussian pedestal, possibly
off-centre) and a secondary reflection (a weaker copy a few widths away), on a
smoothly varying background; optical blur (Gaussian, before the sensor), sensor
noise, then clipping at ``clip`` and rounding to ``dtype``.  With ``subtract``
a laser-off frame (same background, its own noise) is subtracted
(``cv2.subtract``), so the clipped level of the difference image varies with the
background.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np


@dataclass(frozen=True)
class SaturatedStripe:
    """A synthetic saturated stripe (:func:`render_saturated`).

    ``shape``: image ``(H, W)``; ``width_px``: the stripe's FWHM; ``amplitude``: times ``clip``
    (a number, or a function of the column ``u``: :func:`hot_spot`); ``clip``, ``dtype``: the
    clipping level and the image type; ``theta``: the centre line's direction angle, ``v0``:
    its row at the middle column; ``blur_px``: optical blur (Gaussian σ); ``noise``,
    ``background``: fractions of ``clip``; ``halo = (height, fwhm_px, offset_px)``, height a
    fraction of ``clip``, centred ``offset_px`` off the centre line along its normal;
    ``secondary = (height, distance_px)``, height a fraction of ``clip``; ``subtract``: a
    laser-off frame subtracted; ``ss``: ``ss x ss`` samples per pixel.
    """

    shape: tuple[int, int] = (80, 400)
    width_px: float = 5.0
    amplitude: float | Callable = 2.0
    clip: float = 255.0
    dtype: type = np.uint8
    theta: float = 0.06
    v0: float = 40.3
    blur_px: float = 0.7
    noise: float = 0.01
    background: float = 0.05
    halo: tuple[float, float, float] | None = None
    secondary: tuple[float, float] | None = None
    subtract: bool = False
    ss: int = 4


def render_saturated(stripe: SaturatedStripe = SaturatedStripe(), rng: np.random.Generator | None = None):
    """Image and ``truth(u)``: the row where the centre line crosses column ``u`` (``stripe``:
    :class:`SaturatedStripe`; ``rng`` for the noise, default seeded 0)."""
    import cv2

    rng = np.random.default_rng(0) if rng is None else rng
    shape, width_px, amplitude, clip, dtype = stripe.shape, stripe.width_px, stripe.amplitude, stripe.clip, stripe.dtype
    theta, v0, blur_px, noise, background = stripe.theta, stripe.v0, stripe.blur_px, stripe.noise, stripe.background
    halo, secondary, subtract, ss = stripe.halo, stripe.secondary, stripe.subtract, stripe.ss
    H, W = shape
    n = np.array([-np.sin(theta), np.cos(theta)])
    o = (np.arange(ss) + 0.5) / ss - 0.5
    v, u = np.mgrid[0:H, 0:W].astype(float)
    s = width_px / 2.3548
    acc = np.zeros((H, W))
    amp = amplitude(u) if callable(amplitude) else amplitude
    for dy in o:
        for dx in o:
            d = (u + dx - W / 2) * n[0] + (v + dy - v0) * n[1]
            acc += amp * np.exp(-0.5 * (d / s) ** 2)
            if halo is not None:
                ha, hw, hoff = halo
                acc += ha * np.exp(-0.5 * ((d - hoff) / (hw / 2.3548)) ** 2)
            if secondary is not None:
                sa, sd = secondary
                acc += sa * np.exp(-0.5 * ((d - sd) / s) ** 2)
    img: np.ndarray = clip * acc / ss**2
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    bg = background * clip * (1.0 + 0.5 * np.sin(u / 37.0 + v / 23.0))
    out = np.round(np.clip(img + bg + rng.normal(0.0, noise * clip, (H, W)), 0, clip)).astype(dtype)
    if subtract:
        off = np.round(np.clip(bg + rng.normal(0.0, noise * clip, (H, W)), 0, clip)).astype(dtype)
        out = cv2.subtract(out, off)

    def truth(uu):
        return v0 + (np.asarray(uu, float) - W / 2) * np.tan(theta)

    return out, truth


def hot_spot(peak: float, base: float = 0.7, centre_u: float = 200.0, fwhm_u: float = 120.0):
    """Amplitude along the stripe: ``base`` with a Gaussian hot spot of ``peak`` (times the clip level)."""
    s = fwhm_u / 2.3548
    return lambda u: base + (peak - base) * np.exp(-0.5 * ((u - centre_u) / s) ** 2)
