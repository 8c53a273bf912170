"""The profile's first pass on busy frames: the choice between candidates, lines that stop before
their derivatives, and the width estimate on a stripe that sits on a pedestal (docs/method.md,
§Stripe centres: the profile's first pass)."""

from __future__ import annotations

import numpy as np

from lightplane.stripe import kernels as K
from lightplane.stripe.extract import extract_profile
from lightplane.stripe.options import StripeOptions

FWHM = 5.0
SIGMA = FWHM / 2.3548


def _choose_by_median(p1, v1, p2, v2, min_peak, half_window, tol):
    """The rule written out with np.median (what the kernel must reproduce)."""
    out = p1.copy()
    L = p1.size
    for line in range(L):
        if p2[line] < 0 or v2[line] < min_peak:
            continue
        nb = [p1[k] for k in range(max(0, line - half_window), min(L, line + half_window + 1))
              if k != line and v1[k] >= min_peak]
        if len(nb) < 2:
            continue
        ref = np.median(np.array(nb, float))
        if abs(p1[line] - ref) > tol and abs(p2[line] - ref) <= tol:
            out[line] = p2[line]
    return out


def test_choose_consistent_is_the_median_rule():
    rng = np.random.default_rng(5)
    switched = 0
    for _ in range(200):
        L = int(rng.integers(1, 120))
        base = np.cumsum(rng.integers(-2, 3, L)) + 100
        p1 = np.where(rng.random(L) < 0.3, rng.integers(0, 200, L), base).astype(np.int64)
        p2 = np.where(rng.random(L) < 0.5, base + rng.integers(-3, 4, L), rng.integers(-1, 200, L)).astype(np.int64)
        v1, v2 = rng.uniform(0, 40, L), rng.uniform(0, 40, L)
        tol = float(rng.choice([0.5, 3.0, 5.5]))
        got = K.choose_consistent(p1, v1, p2, v2, 20.0, 5, tol)
        np.testing.assert_array_equal(got, _choose_by_median(p1, v1, p2, v2, 20.0, 5, tol))
        switched += int(np.sum(got != p1))
    assert switched > 50   # the second candidate is taken often enough for the rule to be exercised


def _stripe_column(H: int, v0: float, amp: float) -> np.ndarray:
    return amp * np.exp(-0.5 * ((np.arange(H) - v0) / SIGMA) ** 2)


def test_lines_without_contrast_stop_early():
    """Columns 0-39 hold the stripe; 40-59 a 10-level bump (below min_peak); 60-79 a ramp that never
    falls to its half level on one side.  The stripe's columns are valid, the others not; the bump's
    lines end as "no peak" with no derivative outputs; the numpy twin agrees."""
    H, W = 80, 80
    v = np.arange(H, dtype=float)[:, None]
    img = np.full((H, W), 20.0)
    img[:, :40] += _stripe_column(H, 40.3, 150.0)[:, None]
    img[:, 40:60] += _stripe_column(H, 40.0, 10.0)[:, None]
    img[:, 60:] += np.clip(4.0 * (v - 30.0), 0, 120)        # rises to a plateau at the bottom: no crossing below
    img = np.round(img).astype(np.uint8)
    opts = StripeOptions(width_px=FWHM)
    a = extract_profile(img, options=opts)
    b = extract_profile(img, options=StripeOptions(width_px=FWHM, backend="numpy"))
    assert a.valid[6:34].all()
    assert np.all(np.abs(a.uv[6:34, 1] - 40.3) < 0.05)
    assert not a.valid[40:].any()
    assert np.all(a.status[42:58] == K.NO_PEAK)
    assert np.all(np.isnan(a.strength[42:58])) and np.all(np.isnan(a.intensity[42:58]))
    np.testing.assert_array_equal(a.status, b.status)
    for f in ("uv", "intensity", "strength", "width", "normals"):
        np.testing.assert_allclose(getattr(a, f), getattr(b, f), rtol=1e-7, atol=1e-6, equal_nan=True, err_msg=f)
