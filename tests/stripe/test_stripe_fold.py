"""The profile kernels' folded sums (``_band_sums``, ``_line_sums``).

Both pair the taps i and 2R - i of the derivative kernels, which is exact only when the
kernels are exactly (anti)symmetric; and a line's sums must be the same numbers, bit for
bit, whether computed in a band or alone (the split of lines into bands depends on the
threads and on the neighbouring lines).
"""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit

from lightplane.stripe import kernels as K
from lightplane.stripe.extract import sigma_for_width


@pytest.mark.parametrize("sigma", [0.3, 0.7, 1.0, 1.2345, 1.4434, 2.6, 4.0415, 7.777])
def test_kernels_exactly_symmetric(sigma):
    w0, w1, w2 = K.gaussian_derivative_kernels(sigma)
    R = (w0.size - 1) // 2
    np.testing.assert_array_equal(w0, w0[::-1])
    np.testing.assert_array_equal(w1, -w1[::-1])
    np.testing.assert_array_equal(w2, w2[::-1])
    assert w1[R] == 0.0
    xw = K.edge_kernels_cached(sigma)
    for k in range(R + 1):
        np.testing.assert_array_equal(xw[k, 0], xw[k, 0, ::-1])
        np.testing.assert_array_equal(xw[k, 1], -xw[k, 1, ::-1])
        np.testing.assert_array_equal(xw[k, 2], xw[k, 2, ::-1])
        assert xw[k, 1, R] == 0.0


@njit(cache=False)
def _band_and_alone(A, d0, nd, l0, n, w0, w1, w2, xw):
    R = (w0.shape[0] - 1) // 2
    RX = (xw.shape[2] - 1) // 2
    Fb = np.empty((nd + 2 * R, n + 2 * RX))
    C = np.empty((3, nd, n + 2 * RX))
    D = np.empty((K.N_SUMS, nd, n))
    K._band_sums(A, d0, nd, l0, n, RX, w0, w1, w2, xw[RX, 0], xw[RX, 1], xw[RX, 2], Fb, C, D)
    T = np.empty((3, 3, 2 * RX + 1))
    sm = np.empty(14)
    band = np.empty((nd - 2, n, 14))
    alone = np.empty((nd - 2, n, 14))
    for r in range(1, nd - 1):
        for j in range(n):
            for k in range(4):
                for o in range(3):
                    band[r - 1, j, 3 * k + o] = D[k, r - 1 + o, j]
            band[r - 1, j, 12] = D[4, r, j]
            band[r - 1, j, 13] = D[5, r, j]
            K._line_sums(A, l0 + j, d0 + r, RX, RX, w0, w1, w2, xw, T, sm)
            alone[r - 1, j] = sm
    return band, alone


@pytest.mark.parametrize("width_px", [2.5, 5.0, 9.0, 14.0])
def test_band_sums_equal_line_sums(width_px):
    sigma = sigma_for_width(width_px)
    w0, w1, w2 = K.gaussian_derivative_kernels(sigma)
    xw = K.edge_kernels_cached(sigma)
    R = (w0.size - 1) // 2
    rng = np.random.default_rng(int(width_px * 10))
    A = rng.integers(0, 256, (2 * R + 12, 64 + 2 * R + 5), dtype=np.uint8)
    band, alone = _band_and_alone(A, R + 2, 6, R + 2, 64, w0, w1, w2, xw)
    np.testing.assert_array_equal(band, alone)
    # and they are the sums of the kernels (unfolded, in float64)
    Af = A.astype(np.float64)
    l, c = R + 2 + 17, R + 2 + 2
    win = Af[c - R:c + R + 1, l - R:l + R + 1]     # rows: along the line (samples), columns: across (lines)
    ref_s = xw[R, 0] @ (w1 @ win)                    # r_s = k0 * (w1 * x)
    ref_l = xw[R, 1] @ (w0 @ win)
    ref = xw[R, 0] @ (w0 @ win)
    got = band[1, 17]
    np.testing.assert_allclose([got[1], got[7], got[13]], [ref_s, ref_l, ref], rtol=1e-12, atol=1e-9)
