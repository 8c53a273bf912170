"""Numba kernel behind :meth:`lightplane.measure.profile.ProfileMeasurer.normalized`: the undistortion
lookup of one frame's stripe centres in one pass (the numpy version took ~20 array operations
and four gathers from the 30 MB tables, ~0.4 ms a 1280x960 frame; this ~0.05 ms).

It computes what the numpy expressions did, in the same order of operations (no fast-math, no
contraction into fused multiply-adds), so the numbers are the same bit for bit
(``tests/test_measure.py`` compares the two).
"""

from __future__ import annotations

import math

import numpy as np

from lightplane.core.jit import njit_cached

#: :func:`hermite_lookup`'s status of each point
NOT_FINITE, DONE, OFF_GRID, NOT_BUILT = 0, 1, 2, 3


@njit_cached(nogil=True)
def hermite_lookup(tab_xy, tab_dxy, built, block_lines, block_samples, line, t, out, status):  # pragma: no cover
    """For each point ``k`` at line ``line[k]`` (an integer, as a float, off the grid otherwise) and
    sample ``t[k]`` of the tables (roi-relative): the cubic Hermite interpolation of ``tab_xy``
    (L, S, 2) with the derivatives ``tab_dxy`` (L, S, 2, float32) between the samples bracketing
    ``t[k]``, written to ``out[k]`` (status DONE); NOT_FINITE (out NaN) where ``line`` or ``t`` is not
    finite, OFF_GRID where the line is not an integer inside the tables, NOT_BUILT where a table block
    it needs (``built`` (lines / block_lines, samples / block_samples)) is not built yet (out left)."""
    L = tab_xy.shape[0]
    S = tab_xy.shape[1]
    for k in range(line.shape[0]):
        lk, tk = line[k], t[k]
        if not (math.isfinite(lk) and math.isfinite(tk)):
            out[k, 0] = np.nan
            out[k, 1] = np.nan
            status[k] = NOT_FINITE
            continue
        lr = np.rint(lk)
        if not (abs(lk - lr) < 1e-9 and lr >= 0 and lr < L):
            status[k] = OFF_GRID
            continue
        li = int(lr)
        fl = math.floor(tk)
        i0 = int(min(max(fl, 0.0), S - 2.0))
        lb = li // block_lines
        if not (built[lb, i0 // block_samples] and built[lb, (i0 + 1) // block_samples]):
            status[k] = NOT_BUILT
            continue
        f = tk - i0
        f2 = f * f
        f3 = f * f * f
        h00 = 2.0 * f3 - 3.0 * f2 + 1.0
        h10 = f3 - 2.0 * f2 + f
        h01 = -2.0 * f3 + 3.0 * f2
        h11 = f3 - f2
        for c in range(2):
            p0 = tab_xy[li, i0, c]
            p1 = tab_xy[li, i0 + 1, c]
            m0 = np.float64(tab_dxy[li, i0, c])
            m1 = np.float64(tab_dxy[li, i0 + 1, c])
            out[k, c] = h00 * p0 + h10 * m0 + h01 * p1 + h11 * m1
        status[k] = DONE


@njit_cached(nogil=True)
def median_where(w, mask):  # pragma: no cover
    """``(np.median(w[mask & isfinite(w)]), count)``; ``(NaN, 0)`` when none (numpy's median, bit for
    bit: the middle value, or the two middle ones' sum halved)."""
    buf = np.empty(w.shape[0], np.float64)
    n = 0
    for k in range(w.shape[0]):
        if mask[k] and math.isfinite(w[k]):
            buf[n] = w[k]
            n += 1
    if n == 0:
        return np.nan, 0
    return np.median(buf[:n]), n
