"""Stripes whose width changes along the line (scattering materials, defocus, grazing angles) are measured at
their own width (``StripeOptions.local_width``, :func:`lightplane.stripe.extract._local_widths`).

Truth: Gaussian stripes drawn in closed form with white noise.  The bound on a centre's scatter is the
Cramér–Rao bound of one line's profile, ``sigma_noise / A * sqrt(2 s / sqrt(pi))`` (amplitude ``A``, Gaussian
sigma ``s`` of the profile); smoothing along the stripe averages neighbouring lines, so a line's error may
be below it, and 1.5x it bounds the RMS."""

from __future__ import annotations

import numpy as np

from lightplane import Camera, LightPlane
from lightplane.measure.options import MeasureOptions
from lightplane.measure.profile import measure_profile
from lightplane.stripe.extract import extract_profile, extract_profiles
from lightplane.stripe.options import StripeOptions

NOISE = 2.0


def _stripe(centre, fwhm, amp, shape, seed, background=15.0):
    H, W = shape
    v = np.arange(H, dtype=float)[:, None]
    img = background + amp * np.exp(-0.5 * ((v - centre) / (fwhm / 2.3548)) ** 2)
    return np.clip(np.rint(img + np.random.default_rng(seed).normal(0, NOISE, img.shape)), 0, 255).astype(np.uint8)


def _crlb(fwhm, amp):
    s = np.asarray(fwhm) / 2.3548
    return NOISE / amp * np.sqrt(2 * s / np.sqrt(np.pi))


def test_a_stripe_from_4_to_40_px_wide():
    W = 1280
    u = np.arange(W)
    fwhm = np.interp(u, [0, W - 1], [4.0, 40.0])
    centre = 200 + 30 * np.sin(u / 300.0)
    img = _stripe(centre, fwhm, 180.0, (400, W), seed=1)
    p = extract_profile(img)
    assert p.valid.mean() >= 0.95, p.valid.mean()
    err = p.uv[:, 1] - centre
    for a in range(0, W, 320):
        s = slice(a, a + 320)
        e = err[s][p.valid[s]]
        assert abs(e.mean()) < 0.03, (a, e.mean())
        assert np.sqrt(np.mean(e**2)) < 1.5 * _crlb(fwhm[s], 180.0).max(), (a, np.sqrt(np.mean(e**2)))


def _steps(amp_top=150.0, seed=2):
    """A bed (stripe 6 px wide) and a printed step's top (32 px: the print scatters the light), 30 px apart."""
    W = 640
    u = np.arange(W)
    top = (u > 200) & (u < 400)
    fwhm = np.where(top, 32.0, 6.0)
    centre = 240 + 20 * np.sin(u / 100.0) - np.where(top, 30, 0)
    amp = np.where(top, amp_top, 200.0)
    return _stripe(centre, fwhm, amp, (480, W), seed), top, centre, fwhm


def test_a_scattering_step_top_is_kept_by_measure():
    img, top, centre, fwhm = _steps()
    cam = Camera([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]], [0, 0, 0, 0, 0], 640, 480)
    n = np.array([0.0, 0.8, -0.6])
    plane = LightPlane(n, 0.6 * 400.0)
    inner = top.copy()
    inner[np.flatnonzero(top)[:6]] = inner[np.flatnonzero(top)[-6:]] = False  # the lines at the step's edges
    local = measure_profile(img, cam, plane)
    single = measure_profile(img, cam, plane, MeasureOptions(StripeOptions(local_width=False)))
    assert local.valid[inner].mean() >= 0.95, local.valid[inner].mean()
    assert single.valid[inner].mean() < 0.1  # one width for the frame: the wide stripe was dropped
    e = (local.uv[:, 1] - centre)[inner & local.valid]
    assert np.sqrt(np.mean(e**2)) < 1.5 * _crlb(32.0, 150.0) and abs(e.mean()) < 0.03
    # the bed, away from the top, is measured as before, bit for bit
    far = np.ones(640, bool)
    far[150:450] = False
    assert np.array_equal(local.uv[far], single.uv[far], equal_nan=True)
    assert local.line_width_px is not None and np.allclose(local.line_width_px[inner & local.valid], 32.0, rtol=0.1)


def test_batches_equal_single_frames():
    frames = np.stack([_steps(amp_top=a, seed=s)[0][180:308] for a, s in ((150.0, 3), (90.0, 4), (200.0, 5))])
    opts = StripeOptions(width_px=6.2)
    batch = extract_profiles(frames, options=opts)
    for f, b in zip(frames, batch):
        one = extract_profile(f, options=opts)
        assert np.array_equal(one.uv, b.uv, equal_nan=True) and np.array_equal(one.status, b.status)
        assert b.line_width_px is not None and np.array_equal(one.line_width_px, b.line_width_px)
