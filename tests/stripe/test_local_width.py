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


def _numpy_blocks(flag, gap=3, min_lines=8, block_lines=48):
    """The local-width pass's blocks stated with numpy (gaps bridged, runs cut by np.linspace)."""
    idx = np.flatnonzero(flag)
    bridged = flag.copy()
    for i in np.flatnonzero((np.diff(idx) > 1) & (np.diff(idx) <= gap + 1)):
        bridged[idx[i] + 1:idx[i + 1]] = True
    edges = np.flatnonzero(np.diff(np.concatenate([[0], bridged.view(np.int8), [0]])))
    out = []
    for a, b in zip(edges[::2], edges[1::2]):
        if b - a >= min_lines:
            cuts = np.linspace(a, b, -(-(b - a) // block_lines) + 1).round().astype(int).tolist()
            out += [(c0, c1, int(a), int(b)) for c0, c1 in zip(cuts[:-1], cuts[1:])]
    return out, bridged


def test_the_compiled_screen_equals_its_numpy_statement():
    """The local-width screen's kernels (``wide_line_counts``, ``wide_blocks``, ``block_peak_spread``) give what
    numpy's count_nonzero, linspace().round(), argmax, median and percentile give, exactly (random cases,
    runs whose cuts fall on halves included)."""
    import lightplane.stripe.kernels as K

    rng = np.random.default_rng(3)
    for _ in range(2000):
        flag = rng.random(int(rng.integers(1, 400))) < rng.random()
        blocks, bridged = K.wide_blocks(flag, 3, 8, 48)
        ref, ref_bridged = _numpy_blocks(flag)
        assert [tuple(b) for b in blocks.tolist()] == ref and np.array_equal(bridged, ref_bridged)
    half = np.zeros(60, bool)
    half[5:54] = True  # a run of 49 lines: two blocks cut at 5 + 24.5, rounded to even
    assert K.wide_blocks(half, 3, 8, 48)[0].tolist() == [[5, 30, 5, 54], [30, 54, 5, 54]]
    for _ in range(2000):
        B = rng.integers(0, 6, (int(rng.integers(5, 120)), int(rng.integers(1, 60)))).astype(np.float32)
        mid, spread, off = K.block_peak_spread(B)
        peaks = np.argmax(B, axis=0)
        assert mid == float(np.median(peaks)) and np.array_equal(off, np.abs(peaks - mid))
        assert spread == float(np.percentile(off, 75))
    status = rng.integers(0, 7, (40, 300)).astype(np.uint8)
    width = rng.random((40, 300)) * 10
    width[rng.random(width.shape) < 0.1] = np.nan
    flag = (status == K.TOO_WIDE) | ((status == K.OK) & (width > 5.0))
    assert np.array_equal(K.wide_line_counts(status, width, 5.0), np.count_nonzero(flag, axis=1))
