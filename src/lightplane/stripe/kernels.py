"""Numba kernels behind :mod:`lightplane.stripe.extract` (and their small numpy helpers).

Conventions used by every kernel here:

- Profile kernels work on a "sample-major" array ``A[s, l]``: ``l`` indexes the
  *lines* (one centre per line: image columns for ``axis="columns"``) and ``s``
  the samples along a line (rows).  ``axis="rows"`` is handled by the caller
  passing the transposed image, so the kernels scan memory in order.
- Derivative kernels are *correlation* kernels ``w[i]``, ``i = -R..R``, of the
  Gaussian integrated over each pixel (Steger 1998 §3.1 uses the same
  pixel-integrated kernels): ``r^(k)(x) = sum_i w_k[i] f[x + i]``.
- Indices outside the image are clamped (replicated border), identically in the
  numba and numpy code paths so both give the same numbers.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from numba import prange  # noqa: E402

from lightplane.core.jit import njit_cached

__all__ = ["gaussian_derivative_kernels"]

# status codes of a profile line (kept in StripeProfile.status)
OK = 0
NO_PEAK = 1       # nothing above min_peak
NOT_RIDGE = 2     # Hessian not negative across the line (no bright ridge)
NO_CROSSING = 3   # first derivative does not change sign near the peak
TOO_WIDE = 4      # FWHM above max_width (glare, blooming) or no half-level crossing
ALONG_LINE = 5    # the stripe runs along the scan line (normal nearly across it)
EDGE = 6          # centre closer than the kernel radius to the first/last sample
WHITISH = 7       # whitish pixels on the stripe (glare, sensor bloom); set by stripe.py

# Flat (clipped) tops.  A line's top is flat when the run of samples within
# FLAT_TOL of its contrast (peak - background) below the peak is at least 3 samples
# and longer than FLAT_RUN_PER_FWHM * FWHM + 1.5: an unclipped Gaussian keeps
# |d| <= s sqrt(2 FLAT_TOL) = 0.24 FWHM / 2 within that band, i.e. at most
# floor(0.24 FWHM) + 1 samples, so it never qualifies (noise aside).  Clipped at
# 1/a of its amplitude the run is 2 s sqrt(2 ln a) wide: detected from a ~ 1.2.
FLAT_TOL = 0.04
FLAT_RUN_PER_FWHM = 0.24


@lru_cache(maxsize=64)
def _kernels_cached(sigma_milli: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    sigma = sigma_milli / 1000.0
    R = int(math.ceil(3.0 * sigma))
    i = np.arange(-R, R + 1, dtype=np.float64)
    s2 = math.sqrt(2.0)
    erf = np.vectorize(math.erf)

    def Phi(x):
        return 0.5 * (1.0 + erf(x / (s2 * sigma)))

    def phi(x):
        return np.exp(-0.5 * (x / sigma) ** 2) / (math.sqrt(2.0 * math.pi) * sigma)

    def dphi(x):
        return -x / sigma**2 * phi(x)

    w0 = Phi(i + 0.5) - Phi(i - 0.5)
    w1 = phi(i - 0.5) - phi(i + 0.5)
    w2 = dphi(i + 0.5) - dphi(i - 0.5)
    # exactly (anti)symmetric, as they are mathematically (the profile kernels fold the taps
    # i and -i: _band_sums); the differences of Phi and phi above can be 1 ulp off it
    w0 = 0.5 * (w0 + w0[::-1])
    w1 = 0.5 * (w1 - w1[::-1])
    w2 = 0.5 * (w2 + w2[::-1])
    # Normalise the truncated kernels so that they are exact on polynomials:
    # sum w0 = 1, sum i w1 = 1, sum w2 = 0 and sum i^2 w2 / 2 = 1.
    w0 /= w0.sum()
    w1 /= np.sum(i * w1)
    w2 -= w2.mean()
    w2 /= np.sum(i * i * w2) / 2.0
    for w in (w0, w1, w2):
        w.setflags(write=False)
    return w0, w1, w2


def gaussian_derivative_kernels(sigma_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Correlation kernels (value, first, second derivative) of a pixel-integrated Gaussian.

    Returns three read-only float64 arrays of length ``2R + 1``, ``R = ceil(3 sigma)``;
    ``w1`` is odd (``sum i w1[i] = 1``), ``w2`` even (``sum i^2 w2[i] / 2 = 1``).
    ``sigma_px`` is rounded to 0.001 px (kernels are cached).
    """
    return _kernels_cached(int(round(float(sigma_px) * 1000.0)))


def edge_kernels(w0: np.ndarray, w1: np.ndarray, w2: np.ndarray) -> np.ndarray:
    """Kernels truncated symmetrically to radius k = 0..R, renormalised: (R+1, 3, 2R+1).

    Row k holds (value, first, second derivative) kernels non-zero on |i| <= k with
    the moment conditions of :func:`gaussian_derivative_kernels`; for k = 0 the
    derivative kernels are zero (no information across lines).
    """
    R = (w0.size - 1) // 2
    i = np.arange(-R, R + 1, dtype=np.float64)
    out = np.zeros((R + 1, 3, 2 * R + 1))
    for k in range(R + 1):
        m = np.abs(i) <= k
        a = np.where(m, w0, 0.0)
        out[k, 0] = a / a.sum()
        if k >= 1:
            b = np.where(m, w1, 0.0)
            out[k, 1] = b / np.sum(i * b)
            c = np.where(m, w2, 0.0)
            c[m] -= c[m].mean()
            out[k, 2] = c / (np.sum(i * i * c) / 2.0)
    return out


# ----------------------------------------------------------------------------------------
# small scalar helpers (shared by the 2-D and profile kernels)

HERMITE_ITER = 6    # safeguarded Newton steps (quadratic convergence: ~1e-15 px)
HERMITE_TOL = 1e-7   # ... or fewer: a root stops after the first step below this (samples); Newton converges
#                     quadratically, so the root is then within ~1e-14 samples (centres moved <= 2e-13 px from 1e-12)


@njit_cached(error_model="numpy")
def _hermite_root(g0, d0, g1, d1):
    """Root in [0, 1] of the cubic Hermite interpolant (values g, slopes d) with g0*g1 <= 0.

    Safeguarded Newton from the secant estimate, keeping a bracket (bisection
    when a step leaves it); at most :data:`HERMITE_ITER` steps, stopping after the
    first step shorter than :data:`HERMITE_TOL`, as the numpy version does (so that it
    reproduces the numbers exactly).
    """
    if g0 == 0.0:
        return 0.0
    if g1 == 0.0:
        return 1.0
    lo = 0.0
    hi = 1.0
    t = g0 / (g0 - g1)
    pos0 = g0 > 0.0
    for _ in range(HERMITE_ITER):
        t2 = t * t
        t3 = t2 * t
        h = (2.0 * t3 - 3.0 * t2 + 1.0) * g0 + (t3 - 2.0 * t2 + t) * d0 + (-2.0 * t3 + 3.0 * t2) * g1 + (t3 - t2) * d1
        dh = (6.0 * t2 - 6.0 * t) * (g0 - g1) + (3.0 * t2 - 4.0 * t + 1.0) * d0 + (3.0 * t2 - 2.0 * t) * d1
        if (h > 0.0) == pos0:
            lo = t
        else:
            hi = t
        tn = t - h / dh if dh != 0.0 else 0.5 * (lo + hi)
        if not (lo <= tn <= hi):
            tn = 0.5 * (lo + hi)
        done = abs(tn - t) <= HERMITE_TOL   # converged: the next step would be ~tol^2
        t = tn
        if done:
            break
    return t


@njit_cached(error_model="numpy")
def _ridge_normal(ruu, ruv, rvv):
    """Most negative Hessian eigenvalue and its unit eigenvector (n_u, n_v), n_v >= 0."""
    half_tr = 0.5 * (ruu + rvv)
    half_df = 0.5 * (ruu - rvv)
    root = math.sqrt(half_df * half_df + ruv * ruv)
    lam = half_tr - root
    # eigenvector of [[ruu, ruv], [ruv, rvv]] for lam, from the better-conditioned row
    if half_df > 0.0:
        nu = ruv
        nv = -half_df - root      # lam - ruu
    else:
        nu = half_df - root       # lam - rvv
        nv = ruv
    nrm = math.sqrt(nu * nu + nv * nv)
    if nrm == 0.0:
        return lam, 1.0, 0.0
    nu /= nrm
    nv /= nrm
    if nv < 0.0 or (nv == 0.0 and nu < 0.0):
        nu = -nu
        nv = -nv
    return lam, nu, nv


# ----------------------------------------------------------------------------------------
# profile kernels (A[s, l], lines = columns of A)

BLOCK = 16      # samples per block of the candidate search (at most 256: a block's argmax is kept as uint8)
# Lines per parallel task.  1280 lines in chunks of 256 made 5 tasks for 2 threads (one
# thread did 3): 128 gives 10 and balances them; the 1280x128 profile went from 0.36
# to 0.31 ms, the 1280x960 one from 0.47 to 0.39 ms (benchmarks/bench_stripe.py).
_CHUNK = 128


@njit_cached
def _candidates_chunk(A, sep, p1, v1, p2, v2, l0, l1):
    # numba's parfor lowering slows this body ~5x when it is inlined in prange:
    # keep it a separate serial function.  Every loop runs over the lines (contiguous: vectorised);
    # each of them costs a fixed overhead per row or block, so the serial frame kernel passes
    # the whole width at once
    S = A.shape[0]
    B = BLOCK
    nb = (S + B - 1) // B
    n = l1 - l0
    bm = np.empty((nb, n), dtype=A.dtype)
    ba = np.empty((nb, n), dtype=np.uint8)   # the sample within its block: as wide as 8-bit data (vectorised)
    for b in range(nb):
        s0 = b * B
        s1 = min(S, s0 + B)
        acc = bm[b]
        arg = ba[b]
        r0 = A[s0, l0:l1]
        for l in range(n):
            acc[l] = r0[l]
            arg[l] = 0
        for s in range(s0 + 1, s1):
            r = A[s, l0:l1]
            k = np.uint8(s - s0)
            for l in range(n):
                x = r[l]
                up = x > acc[l]
                acc[l] = x if up else acc[l]
                arg[l] = k if up else arg[l]
    # p1: the first block holding the line's maximum (blocks in order, strictly higher replaces)
    q1 = p1[l0:l1]
    m1 = v1[l0:l1]
    acc = bm[0]
    arg = ba[0]
    for l in range(n):
        m1[l] = np.float64(acc[l])
        q1[l] = np.int64(arg[l])
    for b in range(1, nb):
        acc = bm[b]
        arg = ba[b]
        s0 = b * B
        for l in range(n):
            x = np.float64(acc[l])
            m = m1[l]
            up = x > m
            m1[l] = x if up else m
            q1[l] = (s0 + np.int64(arg[l])) if up else q1[l]
    # p2: the same over the blocks entirely farther than sep from p1 (-1, -inf: none)
    q2 = p2[l0:l1]
    m2 = v2[l0:l1]
    for l in range(n):
        q2[l] = -1
        m2[l] = -np.inf
    for b in range(nb):
        acc = bm[b]
        arg = ba[b]
        s0 = b * B
        s1 = min(S, s0 + B)
        for l in range(n):
            q = q1[l]
            x = np.float64(acc[l])
            m = m2[l]
            p = q2[l]
            take = ((s1 - 1 < q - sep) | (s0 > q + sep)) & ((p < 0) | (x > m))
            m2[l] = x if take else m
            q2[l] = (s0 + np.int64(arg[l])) if take else p


@njit_cached(parallel=True, nogil=True)
def profile_candidates(A, sep, p1, v1, p2, v2):
    """Per line the highest sample (p1, v1) and a second, farther candidate (p2, v2).

    ``p1`` is the first sample holding the line's maximum (``argmax``).  ``p2`` is
    the first sample holding the maximum over the blocks of ``BLOCK`` samples
    (``s // BLOCK``) that lie entirely farther than ``sep`` from ``p1``; ``p2 = -1``
    and ``v2 = -inf`` where there is no such block.  One pass over ``A`` in memory
    order computes the block maxima (a max-reduction the compiler vectorises:
    reading the columns of a row-major image sample by sample would miss the
    cache at every sample); positions then cost at most ``2 BLOCK`` reads a line.
    """
    L = A.shape[1]
    nch = (L + _CHUNK - 1) // _CHUNK
    for ch in prange(nch):
        _candidates_chunk(A, sep, p1, v1, p2, v2, ch * _CHUNK, min(L, ch * _CHUNK + _CHUNK))


#: a line whose candidates both miss its neighbours' median takes its highest sample within ``tol`` of the
#: median instead, when that is a local maximum at least this fraction of the line's highest sample
NEAR_MEDIAN_SHARE = 0.5


@njit_cached(nogil=True)
def choose_consistent(A, p1, v1, p2, v2, min_peak, half_window, tol):
    """Per line pick p1, or p2 when p1 is off the neighbours' median and p2 is on it, or else the
    line's highest sample within ``tol`` of the median when that is a local maximum of at least
    :data:`NEAR_MEDIAN_SHARE` of p1's (and ``min_peak``): the stripe, dimmed by speckle on this line,
    under a brighter second line or reflection that is too close to be the far candidate ``p2``."""
    S = A.shape[0]
    L = p1.shape[0]
    out = p1.copy()
    buf = np.empty(2 * half_window + 1, dtype=np.int64)
    for l in range(L):
        n = 0
        lo = np.iinfo(np.int64).max
        hi = np.iinfo(np.int64).min
        for k in range(max(0, l - half_window), min(L, l + half_window + 1)):
            if k != l and v1[k] >= min_peak:
                x = p1[k]
                buf[n] = x
                n += 1
                lo = min(lo, x)
                hi = max(hi, x)
        if n < 2:
            continue
        # the median lies within [min, max] of the neighbours: where p1 is within tol of all of that
        # range the choice is p1 whatever the median (on a continuous stripe nearly every line; the
        # sort below is then skipped)
        a = p1[l]
        if hi - a <= tol and a - lo <= tol:
            continue
        # the median of the n neighbours (np.median's value): insertion sort of <= 2 half_window ints
        for i in range(1, n):
            x = buf[i]
            j = i - 1
            while j >= 0 and buf[j] > x:
                buf[j + 1] = buf[j]
                j -= 1
            buf[j + 1] = x
        h = n // 2
        ref = np.float64(buf[h]) if n % 2 == 1 else 0.5 * (np.float64(buf[h - 1]) + np.float64(buf[h]))
        if abs(a - ref) <= tol:
            continue
        b = p2[l]
        if b >= 0 and v2[l] >= min_peak and abs(b - ref) <= tol:
            out[l] = b
            continue
        # the highest sample within tol of the median (the first of equals), inside the line
        s0 = max(1, int(math.ceil(ref - tol)))
        s1 = min(S - 2, int(math.floor(ref + tol)))
        if s1 < s0:
            continue
        q = s0
        best = np.float64(A[s0, l])
        for s in range(s0 + 1, s1 + 1):
            x = np.float64(A[s, l])
            if x > best:
                best = x
                q = s
        if best >= min_peak and best >= NEAR_MEDIAN_SHARE * v1[l] and best >= np.float64(A[q - 1, l]) \
                and best >= np.float64(A[q + 1, l]):
            out[l] = q
    return out


@njit_cached(error_model="numpy")
def _clamp(i, n):
    if i < 0:
        return 0
    if i >= n:
        return n - 1
    return i


@njit_cached(inline="always")
def _fwhm_line(A, l, c, half, min_peak):
    """Raw full width at half level along line ``l`` around sample ``c``.

    Returns (fwhm_samples, left, right, peak, background); fwhm NaN when a side
    never drops below the half level within ``half`` samples or the contrast is
    below ``min_peak``.
    """
    S = A.shape[0]
    inside = c - half - 1 >= 0 and c + half + 1 <= S - 1   # no sample to clamp (the usual case)
    # centre index: the highest of c-1, c, c+1
    k0 = c
    best = np.float64(A[c if inside else _clamp(c, S), l])
    for k in (c - 1, c + 1):
        x = np.float64(A[k if inside else _clamp(k, S), l])
        if x > best:
            best = x
            k0 = k
    bg = best
    for k in range(c - half, c + half + 1):
        bg = min(bg, np.float64(A[k if inside else _clamp(k, S), l]))
    if best - bg < min_peak:
        return np.nan, np.nan, np.nan, best, bg
    level = bg + 0.5 * (best - bg)
    right = np.nan
    prev = best
    for k in range(k0 + 1, k0 + half + 1):
        x = np.float64(A[k if inside else _clamp(k, S), l])
        if x < level:
            right = (k - 1) + (prev - level) / (prev - x)
            break
        prev = x
    left = np.nan
    prev = best
    for k in range(k0 - 1, k0 - half - 1, -1):
        x = np.float64(A[k if inside else _clamp(k, S), l])
        if x < level:
            left = (k + 1) - (prev - level) / (prev - x)
            break
        prev = x
    return right - left, left, right, best, bg


@njit_cached(nogil=True)
def _peaks_across(A, every, n, p):
    """``p[j]`` = the first sample holding line ``j * every``'s maximum when the lines run
    across memory (``A`` row-major: a line is a column).  One pass over the rows in memory
    order takes the maxima of blocks of ``BLOCK`` samples of every column up to the last
    line (an element-wise max the compiler vectorises; gathering the few sampled columns
    sample by sample was ~4x slower); a line then reads its block maxima and at most one
    block."""
    S = A.shape[0]
    nb = (S + BLOCK - 1) // BLOCK
    L1 = (n - 1) * every + 1
    bm = np.empty((nb, L1), dtype=A.dtype)
    for b in range(nb):
        s0 = b * BLOCK
        s1 = min(S, s0 + BLOCK)
        acc = bm[b]
        r0 = A[s0]
        for l in range(L1):
            acc[l] = r0[l]
        s = s0 + 1
        while s + 3 < s1:   # four rows into acc at a time: a quarter of its loads and stores (0.029 -> 0.021 ms)
            r, q, u, v = A[s], A[s + 1], A[s + 2], A[s + 3]
            for l in range(L1):
                x = r[l] if r[l] > q[l] else q[l]
                y = u[l] if u[l] > v[l] else v[l]
                x = x if x > y else y
                acc[l] = x if x > acc[l] else acc[l]
            s += 4
        for s in range(s, s1):
            r = A[s]
            for l in range(L1):
                x = r[l]
                acc[l] = x if x > acc[l] else acc[l]
    for j in range(n):
        l = j * every
        bb = 0
        best = bm[0, l]
        for b in range(1, nb):
            if bm[b, l] > best:
                best = bm[b, l]
                bb = b
        s = bb * BLOCK
        while A[s, l] < best:   # the block holds it (no NaN: images are checked finite)
            s += 1
        p[j] = s


@njit_cached(nogil=True)
def _peaks_along(A, every, n, p):
    """:func:`_peaks_across` for lines that run along memory (``A`` the transposed view of a
    row-major image): per line the maxima of chunks of 128 samples, then the first sample
    of the first chunk holding the line's maximum.  Each chunk is a slice looped from 0:
    indexing the line from a running start keeps numba's negative-index check in the loop,
    which stops the vectoriser (7x slower); chunks of 64 are too short for its vector loop."""
    S = A.shape[0]
    for j in range(n):
        line = A[:, j * every]
        best = line[0]
        c = 0
        for c0 in range(0, S, 128):
            chunk = line[c0:c0 + 128]
            m = chunk[0]
            for i in range(chunk.size):
                x = chunk[i]
                m = x if x > m else m
            if m > best:
                best = m
                c = c0
        while line[c] < best:
            c += 1
        p[j] = c


@njit_cached(nogil=True)
def fwhm_median(A, every, half, min_peak):
    """Median raw FWHM (samples) at the highest sample (first ``argmax``, the peak the
    candidates kernel finds) of every ``every``-th line of ``A[s, l]``, and the number of
    lines with one (:func:`_fwhm_line`); NaN, 0 when none.  One call, serial: ~160 lines
    are too little work to split over threads.  ``A`` row-major or the transposed view of
    a row-major image (the lines are then its rows: no transpose needed)."""
    L = A.shape[1]
    n = (L + every - 1) // every
    p = np.empty(n, np.int64)
    if A.strides[0] >= A.strides[1]:
        _peaks_across(A, every, n, p)
    else:
        _peaks_along(A, every, n, p)
    out = np.empty(n, np.float64)
    m = 0
    for j in range(n):
        fw = _fwhm_line(A, j * every, p[j], half, min_peak)[0]
        if np.isfinite(fw):
            out[m] = fw
            m += 1
    if m == 0:
        return np.nan, 0
    return np.median(out[:m]), m


@njit_cached(inline="always")
def _is_wide(st, wd, thr):
    """A line the local-width pass looks at again: too wide for the frame's scale, or a stripe wider than
    ``thr`` px."""
    return st == TOO_WIDE or (st == OK and wd > thr)


@njit_cached(nogil=True)
def wide_line_counts(status, width, thr):
    """Per frame of a batch (``status``, ``width``: (N, L)): how many lines are wide (:func:`_is_wide`)."""
    N, L = status.shape
    out = np.zeros(N, np.int64)
    for f in range(N):
        c = 0
        for l in range(L):
            c += _is_wide(status[f, l], width[f, l], thr)
        out[f] = c
    return out


@njit_cached(nogil=True)
def wide_line_flags(status, width, thr):
    """One frame's wide lines (:func:`_is_wide`) and how many."""
    L = status.size
    flag = np.zeros(L, np.bool_)
    n = 0
    for l in range(L):
        flag[l] = _is_wide(status[l], width[l], thr)
        n += flag[l]
    return flag, n


@njit_cached(nogil=True)
def merge_local_width(centre, normal, strength, intensity, width, status, c2, n2, s2, i2, w2, st2, s0, redo, a, b,
                      a0, wl, scale):
    """Take a wide block's second pass (``c2`` ... ``st2``: lines ``a0 ..`` of it, centres ``s0`` samples into the
    frame) into the frame's outputs: lines ``[a, b)`` marked ``redo`` take all of a centre found at width ``wl``;
    where none is found, a line that had a centre keeps it and one that had none takes the second pass's
    reason.  Nothing changes when no ``redo`` line found a centre."""
    found_any = False
    for l in range(a, b):
        if redo[l] and st2[l - a0] == OK:
            found_any = True
            break
    if not found_any:
        return
    for l in range(a, b):
        if not redo[l]:
            continue
        k = l - a0
        if st2[k] == OK:
            centre[l] = c2[k] + s0
            normal[l, 0] = n2[k, 0]
            normal[l, 1] = n2[k, 1]
            strength[l] = s2[k]
            intensity[l] = i2[k]
            width[l] = w2[k]
            status[l] = st2[k]
            scale[l] = wl
        elif status[l] != OK:
            status[l] = st2[k]
            scale[l] = wl


@njit_cached(inline="always")
def _next_run(mask, i):
    """The first run of True in ``mask`` at or after ``i``: ``(a, b)``, ``mask[a:b]`` all True; ``(n, n)`` when
    there is none."""
    n = mask.size
    while i < n and not mask[i]:
        i += 1
    a = i
    while i < n and mask[i]:
        i += 1
    return a, i


@njit_cached(nogil=True)
def wide_blocks(flag, gap, min_lines, block_lines):
    """The local-width pass's blocks: ``flag`` with every gap of at most ``gap`` unflagged lines between
    flagged ones filled in (``bridged``), and ``(a, b, run_a, run_b)`` per block (K, 4): the bridged runs
    ``[run_a, run_b)`` of at least ``min_lines`` lines, each cut into ``ceil(len / block_lines)``
    near-equal blocks ``[a, b)`` (the cuts rounded half to even, as ``np.linspace(...).round()``)."""
    L = flag.size
    bridged = flag.copy()
    last = -1
    for i in range(L):
        if flag[i]:
            if last >= 0 and 1 < i - last <= gap + 1:
                for j in range(last + 1, i):
                    bridged[j] = True
            last = i
    out = np.empty((L, 4), np.int64)
    k = 0
    b = 0
    while True:
        a, b = _next_run(bridged, b)
        if a >= L:
            break
        if b - a < min_lines:
            continue
        m = -(-(b - a) // block_lines)
        step = float(b - a) / m
        prev = a
        for j in range(1, m + 1):
            c = b if j == m else round(j * step + a)   # half to even, as np.round
            out[k, 0] = prev
            out[k, 1] = c
            out[k, 2] = a
            out[k, 3] = b
            k += 1
            prev = c
    return out[:k], bridged


@njit_cached(nogil=True)
def block_peak_spread(B):
    """For a block ``B[s, l]`` (row-major) of a wide run: the lines' peak samples (first maximum), their median
    ``mid``, ``off = |peak - mid|`` and the 75th percentile of ``off`` (linear interpolation, as
    ``np.percentile``): whether the block's peaks line up (a stripe) or scatter (texture)."""
    n = B.shape[1]
    p = np.empty(n, np.int64)
    _peaks_across(B, 1, n, p)
    q = np.sort(p)
    h = n // 2
    mid = float(q[h]) if n % 2 == 1 else (float(q[h - 1]) + float(q[h])) / 2.0
    off = np.empty(n, np.float64)
    for j in range(n):
        off[j] = abs(p[j] - mid)
    o = np.sort(off)
    vi = (n - 1) * 0.75
    lo = int(math.floor(vi))
    hi = min(lo + 1, n - 1)
    g = vi - lo
    d = o[hi] - o[lo]
    spread = o[hi] - d * (1.0 - g) if g >= 0.5 else o[lo] + d * g
    return mid, spread, off


@njit_cached(error_model="numpy")
def _is_flat(A, l, p, fw, best, bg, half):
    """Whether line ``l`` has a flat (clipped) top at sample ``p`` (see FLAT_TOL)."""
    if not (fw == fw) or best - bg <= 0.0:
        return False
    S = A.shape[0]
    thr = best - FLAT_TOL * (best - bg)
    # a run of >= 3 needs a neighbour of p in it (the usual case: a peak, no plateau)
    if not ((p + 1 < S and float(A[p + 1, l]) >= thr) or (p >= 1 and float(A[p - 1, l]) >= thr)):
        return False
    n = 1
    k = p + 1
    while k < S and k <= p + 2 * half and float(A[k, l]) >= thr:
        n += 1
        k += 1
    k = p - 1
    while k >= 0 and k >= p - 2 * half and float(A[k, l]) >= thr:
        n += 1
        k -= 1
    return n >= 3 and n > FLAT_RUN_PER_FWHM * fw + 1.5


@njit_cached
def _flat_centre(A, l, p, c, xw, re, qpeak, half, Y):
    """Midpoint of the half-level crossings of line ``l`` smoothed across the lines
    (kernel ``xw[re, 0]``), around sample ``p``; NaN where a flank is missing."""
    S, L = A.shape
    RX = (xw.shape[2] - 1) // 2
    H2 = half + qpeak + 2
    k0 = xw[re, 0]
    for m in range(2 * H2 + 1):
        row = A[_clamp(c - H2 + m, S)]
        a0 = 0.0
        for jj in range(2 * re + 1):
            a0 += k0[RX - re + jj] * float(row[l - re + jj])
        Y[m, 0] = a0
    fw, left, right, best, bg = _fwhm_line(Y[:2 * H2 + 1], 0, p - c + H2, half, 0.0)
    if not (fw == fw):
        return np.nan
    return c - H2 + 0.5 * (left + right)


# Lines per band (the along-line sums and the line ends vectorised over them): BAND_LINES where
# their highest samples span at most BAND_SPAN samples or scatter rather than drift (see
# _centres_range), else half as many.  Each vectorised loop
# over a band costs a fixed overhead, so a wide band is cheaper per line; but the sums run over
# the rows of every middle in the band, and a steep stripe's middles spread over more rows in a
# wider band (64 / 32 lines: the serial 1280x64 ROI batch 160 -> 147 ns/line, the 1280x960 frame
# 0.354 -> 0.379 ms with 64 lines everywhere)
BAND_LINES = 64
BAND_SPAN = 4
BAND_DRIFT = 8      # lines whose centre is within this many samples of the band's median share it
N_SUMS = 6          # derivative sums per row: r_s, r_ss, r_l, r_ls, r_ll, r (see _band_sums)


@njit_cached(inline="always")
def _band_sums(A, d0, nd, l0, n, RX, w0, w1, w2, k0, k1, k2, Fb, C, D):
    """The derivative sums at the rows ``d0 .. d0 + nd - 1`` of the lines ``l0 .. l0 + n - 1``:
    ``D[k, r, j]`` for row ``d0 + r`` of line ``l0 + j``, k = r_s, r_ss, r_l, r_ls, r_ll, r;
    r_ll and r (needed at a line's middle c only) at the rows 1 .. nd - 2 (the middles).

    Along the lines first: ``C[k, r, m]`` = sum_i w_k[i] A[d0 + r - R + i, l0 - RX + m] for
    the band's columns and their RX neighbours on each side (rows converted to float64 once,
    in ``Fb``), then across the lines with the across-line kernels ``k0, k1, k2``
    (r_s = k0 * C1, r_ss = k0 * C2, r_l = k1 * C0, r_ls = k1 * C1, r_ll = k2 * C0, r = k0 * C0).

    Folded: the kernels are symmetric (w0, w2, k0, k2) or antisymmetric with a zero middle
    (w1, k1), exactly (:func:`gaussian_derivative_kernels`), so each sum pairs the taps
    i and 2R - i: ``sum_{i<R} w[i] (x[i] +- x[2R-i]) (+ w[R] x[R])``, a third fewer
    operations.  Every sum starts from its first pair's product and adds the pairs in
    order, then the middle tap, as :func:`_line_sums` does for a line alone, so a line
    gets the same numbers either way.  Every loop innermost over the lines (contiguous:
    vectorised).  Along first needs half the products of across first.
    """
    R = (w0.shape[0] - 1) // 2
    m = n + 2 * RX
    for r in range(nd + 2 * R):
        src = A[d0 - R + r, l0 - RX:l0 - RX + m]
        f = Fb[r]
        for j in range(m):
            f[j] = np.float64(src[j])
    # along: C0 = w0 * x, C1 = w1 * x, C2 = w2 * x, over the pairs (i, 2R - i), two a pass
    for r in range(nd):
        c0 = C[0, r]
        c1 = C[1, r]
        c2 = C[2, r]
        a = w0[0]
        b = w1[0]
        g = w2[0]
        x = Fb[r]
        y = Fb[r + 2 * R]
        if R >= 2:
            a2 = w0[1]
            b2 = w1[1]
            g2 = w2[1]
            x2 = Fb[r + 1]
            y2 = Fb[r + 2 * R - 1]
            for j in range(m):
                s = x[j] + y[j]
                d = x[j] - y[j]
                s2 = x2[j] + y2[j]
                dd = x2[j] - y2[j]
                c0[j] = a * s + a2 * s2
                c1[j] = b * d + b2 * dd
                c2[j] = g * s + g2 * s2
            i = 2
        else:
            for j in range(m):
                s = x[j] + y[j]
                c0[j] = a * s
                c1[j] = b * (x[j] - y[j])
                c2[j] = g * s
            i = 1
        while i + 1 < R:
            a = w0[i]
            b = w1[i]
            g = w2[i]
            a2 = w0[i + 1]
            b2 = w1[i + 1]
            g2 = w2[i + 1]
            x = Fb[r + i]
            y = Fb[r + 2 * R - i]
            x2 = Fb[r + i + 1]
            y2 = Fb[r + 2 * R - i - 1]
            for j in range(m):
                s = x[j] + y[j]
                d = x[j] - y[j]
                s2 = x2[j] + y2[j]
                dd = x2[j] - y2[j]
                c0[j] = (c0[j] + a * s) + a2 * s2
                c1[j] = (c1[j] + b * d) + b2 * dd
                c2[j] = (c2[j] + g * s) + g2 * s2
            i += 2
        a = w0[R]
        g = w2[R]
        z = Fb[r + R]
        if i < R:   # the last pair and the middle tap
            a2 = w0[i]
            b2 = w1[i]
            g2 = w2[i]
            x = Fb[r + i]
            y = Fb[r + 2 * R - i]
            for j in range(m):
                s = x[j] + y[j]
                zj = z[j]
                c0[j] = (c0[j] + a2 * s) + a * zj
                c1[j] = c1[j] + b2 * (x[j] - y[j])
                c2[j] = (c2[j] + g2 * s) + g * zj
        else:       # the middle tap (w1's is 0)
            for j in range(m):
                zj = z[j]
                c0[j] = c0[j] + a * zj
                c2[j] = c2[j] + g * zj
    # across: the pairs of columns (jj, 2RX - jj), one a pass, then the middle column (k1's is 0)
    for r in range(nd):
        Ds = D[0, r]
        Dss = D[1, r]
        Dl = D[2, r]
        Dls = D[3, r]
        for jj in range(RX):
            u = k0[jj]
            v = k1[jj]
            X0 = C[0, r, jj:jj + n]
            X1 = C[1, r, jj:jj + n]
            X2 = C[2, r, jj:jj + n]
            Z0 = C[0, r, 2 * RX - jj:2 * RX - jj + n]
            Z1 = C[1, r, 2 * RX - jj:2 * RX - jj + n]
            Z2 = C[2, r, 2 * RX - jj:2 * RX - jj + n]
            if jj == 0:
                for j in range(n):
                    Ds[j] = u * (X1[j] + Z1[j])
                    Dss[j] = u * (X2[j] + Z2[j])
                    Dl[j] = v * (X0[j] - Z0[j])
                    Dls[j] = v * (X1[j] - Z1[j])
            else:
                for j in range(n):
                    Ds[j] += u * (X1[j] + Z1[j])
                    Dss[j] += u * (X2[j] + Z2[j])
                    Dl[j] += v * (X0[j] - Z0[j])
                    Dls[j] += v * (X1[j] - Z1[j])
        u = k0[RX]
        X1 = C[1, r, RX:RX + n]
        X2 = C[2, r, RX:RX + n]
        for j in range(n):
            Ds[j] += u * X1[j]
            Dss[j] += u * X2[j]
    # r_ll and r at the middles only (rows 1 .. nd - 2: the first and last row are c -+ 1 only), in
    # passes of their own: fewer arrays a loop than with the four above (~2 % faster, serial ROI batch)
    for r in range(1, nd - 1):
        Dll = D[4, r]
        D0 = D[5, r]
        for jj in range(RX):
            u = k0[jj]
            q = k2[jj]
            X0 = C[0, r, jj:jj + n]
            Z0 = C[0, r, 2 * RX - jj:2 * RX - jj + n]
            if jj == 0:
                for j in range(n):
                    s0 = X0[j] + Z0[j]
                    Dll[j] = q * s0
                    D0[j] = u * s0
            else:
                for j in range(n):
                    s0 = X0[j] + Z0[j]
                    Dll[j] += q * s0
                    D0[j] += u * s0
        u = k0[RX]
        q = k2[RX]
        X0 = C[0, r, RX:RX + n]
        for j in range(n):
            x0 = X0[j]
            Dll[j] += q * x0
            D0[j] += u * x0


@njit_cached(error_model="numpy")
def _line_sums(A, l, c, re, RX, w0, w1, w2, xw, T, sm):
    """The derivative sums of line ``l`` alone at the rows c-1, c, c+1 (:func:`_band_sums`'s
    numbers, by the same operations: the same pairs of taps in the same order; the
    across-line kernels truncated to radius ``re`` near the first and last lines):
    ``sm`` = r_s(3), r_ss(3), r_l(3), r_ls(3), r_ll, r at c."""
    R = (w0.shape[0] - 1) // 2
    o = RX - re
    k0 = xw[re, 0]
    k1 = xw[re, 1]
    k2 = xw[re, 2]
    for m in range(3):
        for jj in range(2 * re + 1):
            col = l - re + jj
            b0 = c - 1 + m - R
            x = np.float64(A[b0, col])
            y = np.float64(A[b0 + 2 * R, col])
            s = x + y
            a0 = w0[0] * s
            a1 = w1[0] * (x - y)
            a2 = w2[0] * s
            for i in range(1, R):
                x = np.float64(A[b0 + i, col])
                y = np.float64(A[b0 + 2 * R - i, col])
                s = x + y
                a0 += w0[i] * s
                a1 += w1[i] * (x - y)
                a2 += w2[i] * s
            z = np.float64(A[b0 + R, col])
            a0 += w0[R] * z
            a2 += w2[R] * z
            T[0, m, jj] = a0
            T[1, m, jj] = a1
            T[2, m, jj] = a2
    for m in range(3):
        s_ = 0.0
        ss = 0.0
        sl = 0.0
        sls = 0.0
        sll = 0.0
        s0 = 0.0
        for jj in range(re):
            u = k0[o + jj]
            v = k1[o + jj]
            q = k2[o + jj]
            e = 2 * re - jj
            p0 = T[0, m, jj] + T[0, m, e]
            t1 = u * (T[1, m, jj] + T[1, m, e])
            t2 = u * (T[2, m, jj] + T[2, m, e])
            t3 = v * (T[0, m, jj] - T[0, m, e])
            t4 = v * (T[1, m, jj] - T[1, m, e])
            t5 = q * p0
            t6 = u * p0
            if jj == 0:
                s_ = t1
                ss = t2
                sl = t3
                sls = t4
                sll = t5
                s0 = t6
            else:
                s_ += t1
                ss += t2
                sl += t3
                sls += t4
                sll += t5
                s0 += t6
        u = k0[RX]
        q = k2[RX]
        s_ += u * T[1, m, re]
        ss += u * T[2, m, re]
        sll += q * T[0, m, re]
        s0 += u * T[0, m, re]
        sm[m] = s_
        sm[3 + m] = ss
        sm[6 + m] = sl
        sm[9 + m] = sls
        if m == 1:
            sm[12] = sll
            sm[13] = s0


@njit_cached(error_model="numpy")
def _nan_outputs(l, centre, normal, strength, intensity, width):
    """Line ``l``'s centre, normal, strength, intensity and width set to NaN (a line that ends early)."""
    centre[l] = np.nan
    normal[l, 0] = np.nan
    normal[l, 1] = np.nan
    strength[l] = np.nan
    intensity[l] = np.nan
    width[l] = np.nan


@njit_cached(error_model="numpy")
def _line_start(A, l, p, half, qpeak, R, min_peak, centre, normal, strength, intensity, width, status):
    """The first steps of a profile line: its outputs set to NaN, the stripe's middle ``c``.

    Returns ``(c, fw, best, bg, flat)``; ``c = -1`` where the line ends here (status set): no
    candidate, too close to the ends (``EDGE``), or a contrast below ``min_peak``
    (:func:`_line_hopeless`), before its derivatives are computed.
    """
    S = A.shape[0]
    _nan_outputs(l, centre, normal, strength, intensity, width)
    if p < 0:
        status[l] = NO_PEAK
        return -1, np.nan, 0.0, 0.0, False
    # the stripe's middle: midpoint of the raw half-level crossings around the highest
    # sample (robust to a flat, saturated top and to one hot pixel)
    fw, left, right, best, bg = _fwhm_line(A, l, p, half, 0.0)
    c = p
    if fw == fw:
        cm = np.int64(math.floor(0.5 * (left + right) + 0.5))
        if abs(cm - p) <= qpeak:
            c = cm
    if c - 1 - R < 0 or c + 1 + R > S - 1:
        status[l] = EDGE
        return -1, fw, best, bg, False
    st = _line_hopeless(fw, best, bg, min_peak)
    if st != OK:
        status[l] = st
        return -1, fw, best, bg, False
    return c, fw, best, bg, _is_flat(A, l, p, fw, best, bg, half)


@njit_cached(inline="always")
def _line_hopeless(fw, best, bg, min_peak):
    """``NO_PEAK`` where the line's contrast is below ``min_peak``, else ``OK``: such a line can only
    end with that status (the contrast is checked after the derivatives), so its derivatives are
    not computed.  On busy frames these are many of the lines whose highest sample is dark
    texture or clutter, not the stripe.  (A line without a half-level crossing is left to the
    later steps: its status, whatever the Hessian says, decides whether a second pass measures
    it at a wider scale.)"""
    if best - bg < min_peak:
        return NO_PEAK
    return OK


@njit_cached(inline="always")
def _band_start(A, pos, l0, n, half, qpeak, R, min_peak, centre, normal, strength, intensity, width, status,
                cs, fws, bests, bgs, flats, srt, P, K0, BG, LV, KR, KL, M, vec):
    """:func:`_line_start` of the band's lines ``l0 .. l0 + n - 1``: the same numbers, bit for bit,
    with the window scans of :func:`_fwhm_line` vectorised over the lines.

    The lines whose window ``p - half - 1 .. p + half + 1`` is inside ``A`` and whose ``p`` is
    within :data:`BAND_DRIFT` of the band's median ``p`` (all of them when the ``p`` span at
    most ``2 BAND_DRIFT``) share one sweep over the rows their windows cover (converted to
    float64 once, in ``F``): the background (the window's minimum, as a select per lane)
    and then the half-level crossings (the first sample below the level after the highest
    one, the last before it: a min / max of the row index per lane); the crossings' sub-pixel
    positions, the middle and the flat-top test per line from them.  The other lines go
    through :func:`_line_start`.
    """
    S = A.shape[0]
    k = 0
    pmin = S
    pmax = -1
    for j in range(n):
        p = pos[l0 + j]
        ok = p - half - 1 >= 0 and p + half + 1 <= S - 1
        vec[j] = ok
        if ok:
            srt[k] = p
            k += 1
            pmin = min(pmin, p)
            pmax = max(pmax, p)
    if pmax - pmin > 2 * BAND_DRIFT:
        srt[:k].sort()
        med = srt[k // 2]
        pmin = med
        pmax = med
        for j in range(n):
            p = pos[l0 + j]
            ok = vec[j] and abs(p - med) <= BAND_DRIFT
            vec[j] = ok
            if ok:
                pmin = min(pmin, p)
                pmax = max(pmax, p)
    nv = 0
    for j in range(n):
        q = l0 + j
        if not vec[j]:
            P[j] = -S - 2 * half - 8   # no row of the sweeps falls in its window
            K0[j] = P[j]
            c, fw, best, bg, flat = _line_start(A, q, pos[q], half, qpeak, R, min_peak, centre, normal, strength,
                                                intensity, width, status)
            cs[j] = c
            fws[j] = fw
            bests[j] = best
            bgs[j] = bg
            flats[j] = flat
            continue
        nv += 1
        p = pos[q]
        P[j] = p
        # the highest of p-1, p, p+1 (as _fwhm_line: p first)
        k0 = p
        best = np.float64(A[p, q])
        x = np.float64(A[p - 1, q])
        if x > best:
            best = x
            k0 = p - 1
        x = np.float64(A[p + 1, q])
        if x > best:
            best = x
            k0 = p + 1
        K0[j] = k0
        bests[j] = best
        BG[j] = best
    if nv == 0:
        return
    # the background: min over p - half .. p + half; the rows in every window first, in A's type
    # (exact: the minimum is one of the samples), then the others masked per line
    ca = pmax - half
    cb = pmin + half
    if ca <= cb:
        row = A[ca, l0:l0 + n]
        for j in range(n):
            M[j] = row[j]
        for s in range(ca + 1, cb + 1):
            row = A[s, l0:l0 + n]
            for j in range(n):
                x = row[j]
                m = M[j]
                M[j] = x if x < m else m
        for j in range(n):
            x = np.float64(M[j])
            b = BG[j]
            BG[j] = x if x < b else b
    for s in range(pmin - half, pmax + half + 1):
        if ca <= s <= cb:
            continue
        row = A[s, l0:l0 + n]
        for j in range(n):
            d = s - P[j]
            x = np.float64(row[j])
            b = BG[j]
            BG[j] = x if (x < b) & (d >= -half) & (d <= half) else b
    big = S + 1
    for j in range(n):
        b = BG[j]
        LV[j] = b + 0.5 * (bests[j] - b)
        KR[j] = big if vec[j] else -big
        KL[j] = -big if vec[j] else big
    # the crossings: the first sample below the level in k0 + 1 .. k0 + half (rows upwards until
    # every line has its own), the last one in k0 - half .. k0 - 1 (rows downwards)
    kmin = pmin - 1
    kmax = pmax + 1
    for s in range(kmin + 1, kmax + half + 1):
        row = A[s, l0:l0 + n]
        pend = 0
        for j in range(n):
            d = s - K0[j]
            kr = KR[j]
            hit = (np.float64(row[j]) < LV[j]) & (d >= 1) & (d <= half) & (kr == big)
            KR[j] = s if hit else kr
            pend += (KR[j] == big) & (d < half)
        if pend == 0:
            break
    for s in range(kmax - 1, kmin - half - 1, -1):
        row = A[s, l0:l0 + n]
        pend = 0
        for j in range(n):
            d = K0[j] - s
            kl = KL[j]
            hit = (np.float64(row[j]) < LV[j]) & (d >= 1) & (d <= half) & (kl == -big)
            KL[j] = s if hit else kl
            pend += (KL[j] == -big) & (d < half)
        if pend == 0:
            break
    for j in range(n):
        if not vec[j]:
            continue
        q = l0 + j
        p = P[j]
        level = LV[j]
        right = np.nan
        kk = KR[j]
        if kk < big:
            prev = np.float64(A[kk - 1, q])
            x = np.float64(A[kk, q])
            right = (kk - 1) + (prev - level) / (prev - x)
        left = np.nan
        kk = KL[j]
        if kk > -big:
            prev = np.float64(A[kk + 1, q])
            x = np.float64(A[kk, q])
            left = (kk + 1) - (prev - level) / (prev - x)
        fw = right - left
        best = bests[j]
        bg = BG[j]
        bgs[j] = bg
        fws[j] = fw
        c = p
        if fw == fw:
            cm = np.int64(math.floor(0.5 * (left + right) + 0.5))
            if abs(cm - p) <= qpeak:
                c = cm
        st = EDGE if (c - 1 - R < 0 or c + 1 + R > S - 1) else _line_hopeless(fw, best, bg, min_peak)
        if st != OK:
            status[q] = st
            _nan_outputs(q, centre, normal, strength, intensity, width)
            cs[j] = -1
            flats[j] = False
            continue
        cs[j] = c
        # a flat top's run of >= 3 samples holds p and two of p-2 .. p+2 (inside A: half >= 2); the
        # test without a branch first: a Gaussian top fails it (a branch on the neighbours is
        # mispredicted on about every other line)
        thr = best - FLAT_TOL * (best - bg)
        a1 = np.float64(A[p + 1, q]) >= thr
        a2 = np.float64(A[p + 2, q]) >= thr
        b1 = np.float64(A[p - 1, q]) >= thr
        b2 = np.float64(A[p - 2, q]) >= thr
        run3 = (a1 & a2) | (b1 & b2) | (a1 & b1)
        flats[j] = _is_flat(A, q, p, fw, best, bg, half) if run3 else False


@njit_cached(error_model="numpy")
def _line_finish(A, l, p, c, fw, best, bg, flat, sm, xw, re, qpeak, half, min_peak, max_width, min_cos, tmp,
                 centre, normal, strength, intensity, width, status):
    """The rest of a profile line from its derivative sums ``sm`` (:func:`_line_sums`):
    the ridge's normal, the zero crossing of the derivative across the stripe, the width."""
    intensity[l] = sm[13]
    lam, nl, ns = _ridge_normal(sm[12], sm[10], sm[4])
    normal[l, 0] = nl
    normal[l, 1] = ns
    strength[l] = -lam
    if best - bg < min_peak:
        status[l] = NO_PEAK
        return
    # zero crossing of g = n . grad r along the line
    st = OK
    cc = np.nan
    if lam >= 0.0:
        st = NOT_RIDGE
    elif abs(ns) < min_cos:
        st = ALONG_LINE
    else:
        g0 = nl * sm[6] + ns * sm[0]
        g1 = nl * sm[7] + ns * sm[1]
        g2 = nl * sm[8] + ns * sm[2]
        d0 = nl * sm[9] + ns * sm[3]
        d1 = nl * sm[10] + ns * sm[4]
        d2 = nl * sm[11] + ns * sm[5]
        if g1 == 0.0:
            cc = float(c)
        else:
            lo_ok = (g0 > 0.0) != (g1 > 0.0) or g0 == 0.0
            hi_ok = (g1 > 0.0) != (g2 > 0.0) or g2 == 0.0
            if lo_ok and hi_ok:
                # both sides bracket a root (should not happen on a ridge): take the nearer
                t_lo = _hermite_root(g0, d0, g1, d1)
                t_hi = _hermite_root(g1, d1, g2, d2)
                cc = (c - 1 + t_lo) if (1.0 - t_lo) < t_hi else (c + t_hi)
            elif lo_ok:
                cc = c - 1 + _hermite_root(g0, d0, g1, d1)
            elif hi_ok:
                cc = c + _hermite_root(g1, d1, g2, d2)
            else:
                st = NO_CROSSING
    if st != OK:
        if not flat:
            status[l] = st
            return
        # clipped (flat) top too wide for the scale: the Hessian is ~0 on the plateau.
        # Centre = midpoint of the half-level crossings of the flanks, smoothed across
        # the lines (along the stripe)
        cc = _flat_centre(A, l, p, c, xw, re, qpeak, half, tmp[3:4].T)
        if not (cc == cc):
            status[l] = TOO_WIDE
            return
        if st == NOT_RIDGE or st == ALONG_LINE:
            normal[l, 0] = 0.0
            normal[l, 1] = 1.0
            ns = 1.0
    # width across the stripe
    width[l] = fw * ns
    if not (fw == fw) or fw * ns > max_width:
        status[l] = TOO_WIDE
        return
    centre[l] = cc
    status[l] = OK


@njit_cached(error_model="numpy")
def _line_alone(A, l, p, c, fw, best, bg, flat, w0, w1, w2, xw, qpeak, half, min_peak, max_width, min_cos, tmp,
                T, sm, Fb, C, D, centre, normal, strength, intensity, width, status):
    """A profile line from ``c`` on (after :func:`_line_start`), its sums computed alone: an interior
    line as a band of one (:func:`_band_sums`: its loops run along the rows of ``A``, over the line's
    across-line neighbours, which the compiler vectorises; ~2x faster than :func:`_line_sums`'s loops
    down the columns, the same numbers); a line nearer the first or last line than the across-line
    kernel's radius with :func:`_line_sums` (the kernel truncated there)."""
    L = A.shape[1]
    RX = (xw.shape[2] - 1) // 2
    re = min(RX, l, L - 1 - l)
    if re == RX:
        _band_sums(A, c - 1, 3, l, 1, RX, w0, w1, w2, xw[RX, 0], xw[RX, 1], xw[RX, 2], Fb, C, D)
        for k in range(4):
            for o in range(3):
                sm[3 * k + o] = D[k, o, 0]
        sm[12] = D[4, 1, 0]
        sm[13] = D[5, 1, 0]
    else:
        _line_sums(A, l, c, re, RX, w0, w1, w2, xw, T, sm)
    _line_finish(A, l, p, c, fw, best, bg, flat, sm, xw, re, qpeak, half, min_peak, max_width, min_cos, tmp,
                 centre, normal, strength, intensity, width, status)


# rows of the band's scratch array V (see _band_finish)
_V_LAM, _V_NL, _V_NS, _V_G0, _V_D0, _V_G1, _V_D1, _V_T, _V_LO, _V_HI = 0, 1, 2, 3, 4, 5, 6, 7, 8, 9
_V_ROWS = 10


@njit_cached(inline="always")
def _band_finish(A, pos, l0, n, lo, hi, cs, fws, bests, bgs, flats, D, E, V, act, xw, RX, qpeak, half, min_peak,
                 max_width, min_cos, tmp, sm, centre, normal, strength, intensity, width, status):
    """:func:`_line_finish` of the band's lines whose middle ``c`` is in ``lo .. hi``, from
    the derivative sums ``D`` (:func:`_band_sums`), vectorised over the lines: the
    ridge's normal, the derivative across the stripe at c-1, c, c+1, and the zero
    crossing (:func:`_hermite_root`'s safeguarded Newton steps, all lanes at once, each
    lane stopping where the scalar root stops).  The same numbers as :func:`_line_finish`,
    bit for bit; the rare lines whose derivative brackets a root on both sides, and the
    flat tops, go through the scalar code."""
    lam = V[_V_LAM]
    nlv = V[_V_NL]
    nsv = V[_V_NS]
    G0 = V[_V_G0]
    D0v = V[_V_D0]
    G1 = V[_V_G1]
    D1v = V[_V_D1]
    T = V[_V_T]
    LO = V[_V_LO]
    HI = V[_V_HI]
    # each line's sums at its c-1, c, c+1, side by side (E[k, o, j] = D[k, c - lo + o, j]), so
    # that the next loop reads every lane alike (vectorised)
    for j in range(n):
        c = cs[j]
        inb = lo <= c <= hi
        r = (c - lo) if inb else 0
        act[j] = inb
        for k in range(4):
            for o in range(3):
                E[k, o, j] = D[k, r + o, j]
        E[4, 1, j] = D[4, r + 1, j]
    nact = 0
    for j in range(n):
        inb = act[j]
        ruu = E[4, 1, j]
        ruv = E[3, 1, j]
        rvv = E[1, 1, j]
        # _ridge_normal, branch-free
        half_tr = 0.5 * (ruu + rvv)
        half_df = 0.5 * (ruu - rvv)
        root = math.sqrt(half_df * half_df + ruv * ruv)
        lm = half_tr - root
        pos_df = half_df > 0.0
        nu = ruv if pos_df else half_df - root
        nvv = (-half_df - root) if pos_df else ruv
        nrm = math.sqrt(nu * nu + nvv * nvv)
        zero = nrm == 0.0
        nu = 1.0 if zero else nu / nrm
        nvv = 0.0 if zero else nvv / nrm
        flip = (nvv < 0.0) | ((nvv == 0.0) & (nu < 0.0))
        nu = -nu if flip else nu
        nvv = -nvv if flip else nvv
        lam[j] = lm
        nlv[j] = nu
        nsv[j] = nvv
        g0 = nu * E[2, 0, j] + nvv * E[0, 0, j]
        g1 = nu * E[2, 1, j] + nvv * E[0, 1, j]
        g2 = nu * E[2, 2, j] + nvv * E[0, 2, j]
        d0 = nu * E[3, 0, j] + nvv * E[1, 0, j]
        d1 = nu * E[3, 1, j] + nvv * E[1, 1, j]
        d2 = nu * E[3, 2, j] + nvv * E[1, 2, j]
        lo_ok = ((g0 > 0.0) != (g1 > 0.0)) | (g0 == 0.0)
        hi_ok = ((g1 > 0.0) != (g2 > 0.0)) | (g2 == 0.0)
        # the one bracket's cubic (the lower one's values when both or neither), in the
        # order of the pair as _hermite_root is called: (g0, d0, g1, d1) or (g1, d1, g2, d2)
        up = hi_ok & (not lo_ok)
        a = g1 if up else g0
        b = g2 if up else g1
        da = d1 if up else d0
        db = d2 if up else d1
        G0[j] = a
        G1[j] = b
        D0v[j] = da
        D1v[j] = db
        go = inb & (lm < 0.0) & (abs(nvv) >= min_cos) & (g1 != 0.0) & (lo_ok != hi_ok) & (a != 0.0) & (b != 0.0)
        act[j] = go
        nact += go
        T[j] = a / (a - b) if go else 0.0
        LO[j] = 0.0
        HI[j] = 1.0
    it = 0
    while nact > 0 and it < HERMITE_ITER:
        nact = 0
        for j in range(n):   # every lane, branch-free (vectorised); the inactive ones keep their values
            on = act[j]
            g0 = G0[j]
            g1 = G1[j]
            d0 = D0v[j]
            d1 = D1v[j]
            t = T[j]
            t2 = t * t
            t3 = t2 * t
            h = (2.0 * t3 - 3.0 * t2 + 1.0) * g0 + (t3 - 2.0 * t2 + t) * d0 + (-2.0 * t3 + 3.0 * t2) * g1 \
                + (t3 - t2) * d1
            dh = (6.0 * t2 - 6.0 * t) * (g0 - g1) + (3.0 * t2 - 4.0 * t + 1.0) * d0 + (3.0 * t2 - 2.0 * t) * d1
            same = (h > 0.0) == (g0 > 0.0)
            lo0 = LO[j]
            hi0 = HI[j]
            lo_ = t if same else lo0
            hi_ = hi0 if same else t
            mid = 0.5 * (lo_ + hi_)
            tn = (t - h / dh) if dh != 0.0 else mid
            tn = tn if (lo_ <= tn) & (tn <= hi_) else mid
            T[j] = tn if on else t
            LO[j] = lo_ if on else lo0
            HI[j] = hi_ if on else hi0
            still = on & (not (abs(tn - t) <= HERMITE_TOL))
            act[j] = still
            nact += still
        it += 1
    for j in range(n):
        q = l0 + j
        c = cs[j]
        if not (lo <= c <= hi):
            continue
        r = c - lo
        intensity[q] = D[5, r + 1, j]
        nl = nlv[j]
        ns = nsv[j]
        normal[q, 0] = nl
        normal[q, 1] = ns
        strength[q] = -lam[j]
        fw = fws[j]
        if bests[j] - bgs[j] < min_peak:
            status[q] = NO_PEAK
            width[q] = np.nan
            centre[q] = np.nan
            continue
        st = OK
        cc = np.nan
        if lam[j] >= 0.0:
            st = NOT_RIDGE
        elif abs(ns) < min_cos:
            st = ALONG_LINE
        else:
            g0 = nl * D[2, r, j] + ns * D[0, r, j]
            g1 = nl * D[2, r + 1, j] + ns * D[0, r + 1, j]
            g2 = nl * D[2, r + 2, j] + ns * D[0, r + 2, j]
            if g1 == 0.0:
                cc = float(c)
            else:
                lo_ok = (g0 > 0.0) != (g1 > 0.0) or g0 == 0.0
                hi_ok = (g1 > 0.0) != (g2 > 0.0) or g2 == 0.0
                if lo_ok and hi_ok:
                    d0 = nl * D[3, r, j] + ns * D[1, r, j]
                    d1 = nl * D[3, r + 1, j] + ns * D[1, r + 1, j]
                    d2 = nl * D[3, r + 2, j] + ns * D[1, r + 2, j]
                    t_lo = _hermite_root(g0, d0, g1, d1)
                    t_hi = _hermite_root(g1, d1, g2, d2)
                    cc = (c - 1 + t_lo) if (1.0 - t_lo) < t_hi else (c + t_hi)
                elif lo_ok:
                    t = 0.0 if g0 == 0.0 else T[j]
                    cc = c - 1 + t
                elif hi_ok:
                    t = 1.0 if g2 == 0.0 else T[j]
                    cc = c + t
                else:
                    st = NO_CROSSING
        # the end of _line_finish, written out again: sharing it through an inlined helper made
        # the serial ROI kernel ~20 % slower (same-process A/B, thread time)
        if st != OK:
            if not flats[j]:
                status[q] = st
                width[q] = np.nan
                centre[q] = np.nan
                continue
            cc = _flat_centre(A, q, pos[q], c, xw, RX, qpeak, half, tmp[3:4].T)
            if not (cc == cc):
                status[q] = TOO_WIDE
                width[q] = np.nan
                centre[q] = np.nan
                continue
            if st == NOT_RIDGE or st == ALONG_LINE:
                normal[q, 0] = 0.0
                normal[q, 1] = 1.0
                ns = 1.0
        width[q] = fw * ns
        if not (fw == fw) or fw * ns > max_width:
            status[q] = TOO_WIDE
            centre[q] = np.nan
            continue
        centre[q] = cc
        status[q] = OK


@njit_cached(error_model="numpy")
def _centres_range(A, pos, w0, w1, w2, xw, qpeak, half, min_peak, max_width, min_cos,
                   centre, normal, strength, intensity, width, status, la, lb):
    """The profile of lines ``la .. lb - 1`` (see :func:`profile_centres`).

    Interior lines go in bands of :data:`BAND_LINES` (half as many where their highest samples
    span more than :data:`BAND_SPAN`): first each line's middle ``c``
    (:func:`_band_start`, vectorised over the lines; :func:`_line_start` for the lines it
    leaves), then for the lines whose ``c`` is within :data:`BAND_DRIFT`
    of the band's median the derivative sums at the rows c-1 .. c+1 of every such c
    (:func:`_band_sums`) and the lines' ends (:func:`_band_finish`), both vectorised
    over the lines.  The other lines are computed alone (:func:`_line_alone`).  The
    numbers are the same either way, bit for bit, so they do not depend on how the
    lines are split into bands or tasks.
    """
    S, L = A.shape
    R = (w0.shape[0] - 1) // 2
    RX = (xw.shape[2] - 1) // 2
    tmp = np.empty((4, 2 * (half + qpeak + 2) + 1))   # row 3: the flat centre's Y
    sm = np.empty(14)
    ndmax = 2 * BAND_DRIFT + 3
    Fb = np.empty((ndmax + 2 * R, BAND_LINES + 2 * RX))
    C = np.empty((3, ndmax, BAND_LINES + 2 * RX))
    D = np.empty((N_SUMS, ndmax, BAND_LINES))
    E = np.empty((5, 3, BAND_LINES))
    T = np.empty((3, 3, 2 * RX + 1))
    cs = np.empty(BAND_LINES, np.int64)
    fws = np.empty(BAND_LINES)
    bests = np.empty(BAND_LINES)
    bgs = np.empty(BAND_LINES)
    flats = np.empty(BAND_LINES, np.bool_)
    srt = np.empty(BAND_LINES, np.int64)
    V = np.empty((_V_ROWS, BAND_LINES))
    act = np.empty(BAND_LINES, np.bool_)
    P = np.empty(BAND_LINES, np.int64)      # _band_start's scratch
    K0 = np.empty(BAND_LINES, np.int64)
    KR = np.empty(BAND_LINES, np.int64)
    KL = np.empty(BAND_LINES, np.int64)
    BG = np.empty(BAND_LINES)
    LV = np.empty(BAND_LINES)
    M = np.empty(BAND_LINES, A.dtype)
    vec = np.empty(BAND_LINES, np.bool_)
    l = la
    while l < lb:
        l0 = max(l, RX)
        l1 = min(l0 + BAND_LINES, lb, L - RX)
        if l1 - l0 > BAND_LINES // 2:
            h = l0 + BAND_LINES // 2
            amin = S
            amax = -1
            for q in range(l0, h):
                amin = min(amin, pos[q])
                amax = max(amax, pos[q])
            bmin = S
            bmax = -1
            for q in range(h, l1):
                bmin = min(bmin, pos[q])
                bmax = max(bmax, pos[q])
            span = max(amax, bmax) - min(amin, bmin)
            # halved where the peaks drift across the band (a steep stripe: each half spans fewer
            # rows), not where they only scatter (speckle, texture on the stripe: each half spans
            # as many rows, and a narrower band pays its fixed costs twice)
            if span > BAND_SPAN and 4 * max(amax - amin, bmax - bmin) <= 3 * span:
                l1 = h
        if l == l0 and l1 - l0 >= 8:
            n = l1 - l0
            _band_start(A, pos, l0, n, half, qpeak, R, min_peak, centre, normal, strength, intensity, width, status,
                        cs, fws, bests, bgs, flats, srt, P, K0, BG, LV, KR, KL, M, vec)
            k = 0
            lo = S
            hi = -1
            for j in range(n):
                c = cs[j]
                if c >= 0:
                    srt[k] = c
                    k += 1
                    lo = min(lo, c)
                    hi = max(hi, c)
            if k > 0 and hi - lo > BAND_DRIFT:   # else every c is within BAND_DRIFT of the median
                srt[:k].sort()
                med = srt[k // 2]
                lo = med
                hi = med
                for j in range(k):
                    if abs(srt[j] - med) <= BAND_DRIFT:
                        lo = min(lo, srt[j])
                        hi = max(hi, srt[j])
            if k > 0:
                # the rows c-1 .. c+1 of every c in lo..hi (their windows inside A: _line_start checked)
                _band_sums(A, lo - 1, hi - lo + 3, l0, n, RX, w0, w1, w2, xw[RX, 0], xw[RX, 1], xw[RX, 2], Fb, C, D)
                _band_finish(A, pos, l0, n, lo, hi, cs, fws, bests, bgs, flats, D, E, V, act, xw, RX, qpeak, half,
                             min_peak, max_width, min_cos, tmp, sm, centre, normal, strength, intensity, width,
                             status)
            for j in range(n):
                q = l0 + j
                c = cs[j]
                if c >= 0 and not (lo <= c <= hi):
                    centre[q] = np.nan   # (_band_start leaves its lines' outputs to the end of each line)
                    width[q] = np.nan
                    _line_alone(A, q, pos[q], c, fws[j], bests[j], bgs[j], flats[j], w0, w1, w2, xw, qpeak, half,
                                min_peak, max_width, min_cos, tmp, T, sm, Fb, C, D, centre, normal, strength, intensity,
                                width, status)
            l = l1
        else:   # an edge line (or a short remainder): alone
            c, fw, best, bg, flat = _line_start(A, l, pos[l], half, qpeak, R, min_peak, centre, normal, strength,
                                                intensity, width, status)
            if c >= 0:
                _line_alone(A, l, pos[l], c, fw, best, bg, flat, w0, w1, w2, xw, qpeak, half, min_peak, max_width,
                            min_cos, tmp, T, sm, Fb, C, D, centre, normal, strength, intensity, width, status)
            l += 1


@njit_cached(parallel=True, nogil=True)
def profile_centres(A, pos, w0, w1, w2, xw, qpeak, half, min_peak, max_width, min_cos,
                    centre, normal, strength, intensity, width, status):
    """Sub-pixel ridge centre per line at the candidate sample ``pos[l]``.

    1. the stripe's middle sample: midpoint of the raw half-level crossings around
       ``pos`` (kept within ``pos ± qpeak``);
    2. the five Gaussian derivatives at that sample and its two neighbours, from
       a local (2RX+1) x (2R+3) patch (no full-image filtering), across the
       lines first (contiguous rows), then along the line;
    3. normal ``n`` = Hessian eigenvector of the most negative eigenvalue at the
       peak (Steger); ``g = n . grad r`` at the three samples, its slope along the
       line ``n . (H e_s)``; the zero crossing of ``g`` bracketed next to the peak
       is found on the cubic Hermite interpolant (exact to O(h^4), unlike
       Steger's one-step Newton ``t`` whose error grows like t^3);
    4. the raw FWHM of step 1 times ``|n_s|`` (width across the stripe).

    ``xw`` (RX+1, 3, 2RX+1): across-line kernels (their own scale, possibly
    larger than along the line) truncated symmetrically to radius ``k`` (row
    ``k``; see :func:`edge_kernels`), used for the lines within RX of the
    first/last line so the smoothing stays symmetric about the line.

    Outputs per line: ``centre`` (sample coordinate, NaN if invalid), ``normal``
    (L, 2) as (n_l, n_s), ``strength`` = -lambda, ``intensity`` = smoothed value
    at the peak, ``width`` (px across the stripe), ``status`` (codes above).
    """
    L = A.shape[1]
    nch = (L + _CHUNK - 1) // _CHUNK
    for ch in prange(nch):
        _centres_range(A, pos, w0, w1, w2, xw, qpeak, half, min_peak, max_width, min_cos,
                       centre, normal, strength, intensity, width, status, ch * _CHUNK, min(L, ch * _CHUNK + _CHUNK))


# ----------------------------------------------------------------------------------------
# 2-D kernels (full derivative images)

@njit_cached
def _ridge_row(ru, rv, ruu, ruv, rvv, low, su, sv, sn_u, sn_v, sstr, v, lam_row, u0, v0):
    """One row of :func:`ridge_points` (serial: see :func:`_centres_range`)."""
    H, W = ru.shape
    # vectorisable pass: most negative Hessian eigenvalue of every pixel of the row
    a_row = ruu[v]
    b_row = ruv[v]
    c_row = rvv[v]
    s_row = sstr[v]
    half = np.float32(0.5)
    quarter = np.float32(0.25)
    for u in range(W):      # float32 throughout so that it vectorises
        a = a_row[u]
        b = b_row[u]
        cq = c_row[u]
        d = a - cq
        lam_row[u] = half * (a + cq) - np.sqrt(quarter * d * d + b * b)
        s_row[u] = 0.0
    neg_low = np.float32(-low)
    for u in range(W):
        if lam_row[u] > neg_low:
            continue
        a = float(ruu[v, u])
        b = float(ruv[v, u])
        cq = float(rvv[v, u])
        lam, nu, nv = _ridge_normal(a, b, cq)
        vert = abs(nv) >= abs(nu)
        if vert:
            if v == 0 or v == H - 1:
                continue
            gm = nu * ru[v - 1, u] + nv * rv[v - 1, u]
            g0 = nu * ru[v, u] + nv * rv[v, u]
            gp = nu * ru[v + 1, u] + nv * rv[v + 1, u]
            dm = nu * ruv[v - 1, u] + nv * rvv[v - 1, u]
            d0 = nu * b + nv * cq
            dp = nu * ruv[v + 1, u] + nv * rvv[v + 1, u]
        else:
            if u == 0 or u == W - 1:
                continue
            gm = nu * ru[v, u - 1] + nv * rv[v, u - 1]
            g0 = nu * ru[v, u] + nv * rv[v, u]
            gp = nu * ru[v, u + 1] + nv * rv[v, u + 1]
            dm = nu * ruu[v, u - 1] + nv * ruv[v, u - 1]
            d0 = nu * a + nv * b
            dp = nu * ruu[v, u + 1] + nv * ruv[v, u + 1]
        t = 2.0
        if g0 == 0.0:
            t = 0.0
        elif (g0 > 0.0) != (gp > 0.0):
            t = _hermite_root(g0, d0, gp, dp)
            if t >= 0.5:
                t = 2.0
        if t == 2.0 and (gm > 0.0) != (g0 > 0.0):
            t = _hermite_root(gm, dm, g0, d0) - 1.0
            if t < -0.5:
                t = 2.0
        if t == 2.0:
            continue
        if vert:
            su[v, u] = u + u0
            sv[v, u] = v + v0 + t
        else:
            su[v, u] = u + u0 + t
            sv[v, u] = v + v0
        sn_u[v, u] = nu
        sn_v[v, u] = nv
        sstr[v, u] = -lam


@njit_cached(parallel=True)
def ridge_points(ru, rv, ruu, ruv, rvv, low, su, sv, sn_u, sn_v, sstr, u0, v0, u1, v1):
    """Steger points of bright lines from the five derivative images (H, W).

    For every pixel p with ridge strength ``-lambda >= low``: normal n from the
    Hessian; ``g = n . grad r`` sampled at p and its neighbours p ± e along the
    image axis closer to n (column if |n_v| >= |n_u|, else row); the zero of ``g``
    on the cubic Hermite interpolant of (g, dg/de) is the centre, kept by the
    pixel whose half-open cell [-0.5, 0.5) along e contains it, so each crossing
    of a grid line by the centre line gives exactly one point.  Only the region
    ``u0 <= u < u1``, ``v0 <= v < v1`` of the (H, W) arrays is read and written (as that
    region's own image: its border is its edge), positions in full-image pixels; the
    arrays are whole and C-contiguous, so that the kernel compiles once whatever the
    region (a view of a region would be another array layout).  Outputs: sub-pixel
    (u, v) in ``su, sv``, normal in ``sn_u, sn_v``, strength in ``sstr`` (0 where no
    point).
    """
    r_u = ru[v0:v1, u0:u1]
    r_v = rv[v0:v1, u0:u1]
    r_uu = ruu[v0:v1, u0:u1]
    r_uv = ruv[v0:v1, u0:u1]
    r_vv = rvv[v0:v1, u0:u1]
    o_u = su[v0:v1, u0:u1]
    o_v = sv[v0:v1, u0:u1]
    o_nu = sn_u[v0:v1, u0:u1]
    o_nv = sn_v[v0:v1, u0:u1]
    o_s = sstr[v0:v1, u0:u1]
    H, W = r_u.shape
    nch = (H + 31) // 32
    for ch in prange(nch):
        lam_row = np.empty(W, dtype=np.float32)
        for v in range(ch * 32, min(H, ch * 32 + 32)):
            _ridge_row(r_u, r_v, r_uu, r_uv, r_vv, low, o_u, o_v, o_nu, o_nv, o_s, v, lam_row, u0, v0)


@njit_cached
def _bilinear(img, x, y):
    H, W = img.shape
    if x < 0.0:
        x = 0.0
    if y < 0.0:
        y = 0.0
    if x > W - 1:
        x = W - 1.0
    if y > H - 1:
        y = H - 1.0
    x0 = min(int(x), W - 2) if W > 1 else 0
    y0 = min(int(y), H - 2) if H > 1 else 0
    fx = x - x0
    fy = y - y0
    x1 = min(x0 + 1, W - 1)
    y1 = min(y0 + 1, H - 1)
    return ((1 - fx) * (1 - fy) * img[y0, x0] + fx * (1 - fy) * img[y0, x1]
            + (1 - fx) * fy * img[y1, x0] + fx * fy * img[y1, x1])


@njit_cached(parallel=True)
def normal_profiles(img, uv, nrm, reach, step, out_width, out_bg):
    """FWHM (px) across the stripe at each point, sampling ``img`` bilinearly along the normal.

    ``out_bg[:, 0]`` / ``[:, 1]``: background (minimum) on the ``-n`` / ``+n`` side
    within ``reach`` px, ``out_bg[:, 2]`` the image at the point; ``out_width`` NaN
    when a side never falls to half level.
    """
    N = uv.shape[0]
    nstep = int(reach / step)
    for k in prange(N):
        x = uv[k, 0]
        y = uv[k, 1]
        nx = nrm[k, 0]
        ny = nrm[k, 1]
        peak = _bilinear(img, x, y)
        bgs = np.empty(2)
        for side in range(2):
            sg = 1.0 if side == 1 else -1.0
            bg = peak
            for j in range(1, nstep + 1):
                val = _bilinear(img, x + sg * j * step * nx, y + sg * j * step * ny)
                if val < bg:
                    bg = val
            bgs[side] = bg
        out_bg[k, 0] = bgs[0]
        out_bg[k, 1] = bgs[1]
        out_bg[k, 2] = peak
        tot = 0.0
        ok = True
        for side in range(2):
            sg = 1.0 if side == 1 else -1.0
            level = bgs[side] + 0.5 * (peak - bgs[side])
            prev = peak
            found = False
            for j in range(1, nstep + 1):
                val = _bilinear(img, x + sg * j * step * nx, y + sg * j * step * ny)
                if val < level:
                    tot += step * (j - 1) + step * (prev - level) / (prev - val)
                    found = True
                    break
                prev = val
            if not found:
                ok = False
        out_width[k] = tot if ok else np.nan


@njit_cached
def link_points(index_map, pu, pv, su, sv, order, curve, max_gap):
    """Order points into chains; index_map (H, W) holds point ids (-1: none), pu/pv their pixels.

    Chains start at end points (at most one 8-neighbour) and walk to the nearest
    unvisited 8-neighbour (sub-pixel distance); whatever remains (closed loops)
    starts anywhere.  Writes the visiting order into ``order`` and a chain id per
    point into ``curve`` (indexed by point id); returns the number of chains.
    """
    H, W = index_map.shape
    N = order.shape[0]
    visited = np.zeros(N, dtype=np.bool_)
    nnb = np.zeros(N, dtype=np.int64)
    for k in range(N):
        u = pu[k]
        v = pv[k]
        for dv in range(-1, 2):
            for du in range(-1, 2):
                if du == 0 and dv == 0:
                    continue
                uu = u + du
                vv = v + dv
                if 0 <= uu < W and 0 <= vv < H and index_map[vv, uu] >= 0:
                    nnb[k] += 1
    n_out = 0
    n_curves = 0
    for pass_ in range(2):
        for k0 in range(N):
            if visited[k0]:
                continue
            if pass_ == 0 and nnb[k0] > 1:
                continue
            k = k0
            while True:
                visited[k] = True
                order[n_out] = k
                curve[k] = n_curves
                n_out += 1
                best = -1
                bestd = max_gap * max_gap
                u = pu[k]
                v = pv[k]
                # 8-neighbours first; bridge one missing pixel (5 x 5) only when none
                for rad in range(1, 3):
                    for dv in range(-rad, rad + 1):
                        for du in range(-rad, rad + 1):
                            if max(abs(du), abs(dv)) != rad:
                                continue
                            uu = u + du
                            vv = v + dv
                            if 0 <= uu < W and 0 <= vv < H:
                                j = index_map[vv, uu]
                                if j >= 0 and not visited[j]:
                                    ddu = su[vv, uu] - su[v, u]
                                    ddv = sv[vv, uu] - sv[v, u]
                                    d = ddu * ddu + ddv * ddv
                                    if d <= bestd:
                                        bestd = d
                                        best = j
                    if best >= 0:
                        break
                if best < 0:
                    break
                k = best
            n_curves += 1
    return n_curves


@lru_cache(maxsize=64)
def _edge_cached(sigma_milli: int) -> np.ndarray:
    out = edge_kernels(*_kernels_cached(sigma_milli))
    out.setflags(write=False)
    return out


def edge_kernels_cached(sigma_px: float) -> np.ndarray:
    """:func:`edge_kernels` of :func:`gaussian_derivative_kernels` (cached)."""
    return _edge_cached(int(round(float(sigma_px) * 1000.0)))


@njit_cached(nogil=True)
def profile_curvature(uv, nrm, valid, c2, m, k):
    """Numba version of ``stripe._profile_curvature`` (same arithmetic), in place on ``uv``."""
    L = uv.shape[0]
    if L < 2 * m + 1:
        return
    shift = np.zeros(L)
    for i in range(m, L - m):
        if not (valid[i] and valid[i - m] and valid[i + m]):
            continue
        ax = uv[i - m, 0]
        ay = uv[i - m, 1]
        cx = uv[i + m, 0]
        cy = uv[i + m, 1]
        L2 = (cx - ax) ** 2 + (cy - ay) ** 2
        kn = (8.0 * (0.5 * (ax + cx) - uv[i, 0]) * nrm[i, 0] + 8.0 * (0.5 * (ay + cy) - uv[i, 1]) * nrm[i, 1]) / L2
        if kn == kn and abs(kn) < np.inf:
            shift[i] = 0.5 * c2 * kn / nrm[i, k]
    for i in range(m, L - m):
        uv[i, k] -= shift[i]


@njit_cached(nogil=True)
def profile_frame(A, sep, min_peak, continuity, tol, w0, w1, w2, xw, qpeak, half, max_width, min_cos,
                  centre, normal, strength, intensity, width, status):
    """The whole profile of one frame on the calling thread: candidates, the choice
    between them (``continuity``), the centres; the same numbers as the parallel
    kernels :func:`profile_candidates` and :func:`profile_centres`."""
    L = A.shape[1]
    p1 = np.empty(L, np.int64)
    p2 = np.empty(L, np.int64)
    v1 = np.empty(L, np.float64)
    v2 = np.empty(L, np.float64)
    # the serial kernels called directly (a wrapper kernel between would compile the code under it
    # once more); np.int64(0), not 0: a literal argument would compile a variant of its own
    _candidates_chunk(A, sep, p1, v1, p2, v2, np.int64(0), L)
    if continuity:
        pos = choose_consistent(A, p1, v1, p2, v2, min_peak, 5, tol)
    else:
        pos = p1
    _centres_range(A, pos, w0, w1, w2, xw, qpeak, half, min_peak, max_width, min_cos,
                   centre, normal, strength, intensity, width, status, np.int64(0), L)


@njit_cached(parallel=True, nogil=True)
def profiles_batch(A3, sep, min_peak, continuity, tol, w0, w1, w2, xw, qpeak, half, max_width, min_cos,
                   centre, normal, strength, intensity, width, status):
    """:func:`profile_frame` of every frame of a stack (N, S, L), frames across numba's
    threads (one level: each frame serial); ``min_peak`` (N,); outputs (N, L[, 2])."""
    for f in prange(A3.shape[0]):
        profile_frame(A3[f], sep, min_peak[f], continuity, tol, w0, w1, w2, xw, qpeak, half, max_width, min_cos,
                      centre[f], normal[f], strength[f], intensity[f], width[f], status[f])


@njit_cached(nogil=True)
def profiles_batch_serial(A3, sep, min_peak, continuity, tol, w0, w1, w2, xw, qpeak, half, max_width, min_cos,
                          centre, normal, strength, intensity, width, status):
    """:func:`profiles_batch` on the calling thread only."""
    for f in range(A3.shape[0]):
        profile_frame(A3[f], sep, min_peak[f], continuity, tol, w0, w1, w2, xw, qpeak, half, max_width, min_cos,
                      centre[f], normal[f], strength[f], intensity[f], width[f], status[f])


@njit_cached(nogil=True, inline="always")
def _frame_points(centre, normal, status, lines, sample0, columns, curv, c2, m, uv, nrm, valid):
    """A frame's profile in image coordinates (as ``stripe._profile_finish`` makes them):
    ``uv`` (NaN off the valid lines), ``nrm`` (u, v), ``valid``; the curvature correction
    when ``curv``.  ``nrm`` may be ``normal`` itself (each line's two values are read
    before either is written)."""
    L = centre.shape[0]
    iu = 0 if columns else 1
    for i in range(L):
        ok = status[i] == OK
        valid[i] = ok
        uv[i, iu] = np.float64(lines[i]) if ok else np.nan
        uv[i, 1 - iu] = centre[i] + sample0
        n0 = normal[i, 0]
        n1 = normal[i, 1]
        nrm[i, iu] = n0
        nrm[i, 1 - iu] = n1
    if curv:
        profile_curvature(uv, nrm, valid, c2, m, 1 - iu)


@njit_cached(parallel=True, nogil=True)
def frames_points(centre, normal, status, lines, sample0, columns, curv, c2, m, uv, nrm, valid):
    """:func:`_frame_points` of every frame of a batch, frames across numba's threads."""
    for f in prange(centre.shape[0]):
        _frame_points(centre[f], normal[f], status[f], lines, sample0, columns, curv, c2, m, uv[f], nrm[f], valid[f])


@njit_cached(nogil=True)
def frames_points_serial(centre, normal, status, lines, sample0, columns, curv, c2, m, uv, nrm, valid):
    """:func:`frames_points` on the calling thread only."""
    for f in range(centre.shape[0]):
        _frame_points(centre[f], normal[f], status[f], lines, sample0, columns, curv, c2, m, uv[f], nrm[f], valid[f])


@njit_cached
def saturated_core_runs(bgr, ch, min_chroma, bright_sum, bright_max, laser_min, max_len, reach, out_c, out_len):
    """Whitish (saturated) stripe cores down each column of a BGR image.

    A whitish pixel: B + G + R >= ``bright_sum``, max channel >= ``bright_max`` and
    colour saturation ``(max - min) / max < min_chroma``.  A laser pixel: channel ``ch``
    the largest, >= ``laser_min``, saturation >= ``min_chroma``.  A run of whitish pixels
    down a column, at most ``max_len`` long, with a laser pixel within ``reach`` px
    beyond each end (only non-whitish pixels between), is a core: its midpoint (ends
    refined where the saturation crosses ``min_chroma``) is written to ``out_c`` at the
    midpoint's pixel (row) and its length to ``out_len``; elsewhere both stay as given.
    """
    H, W = bgr.shape[0], bgr.shape[1]
    chroma = np.empty(H)
    white = np.zeros(H, np.bool_)
    laser = np.zeros(H, np.bool_)
    for u in range(W):
        for v in range(H):
            b = float(bgr[v, u, 0])
            g = float(bgr[v, u, 1])
            r = float(bgr[v, u, 2])
            hi = max(b, max(g, r))
            lo = min(b, min(g, r))
            c = (hi - lo) / hi if hi > 0 else 0.0
            chroma[v] = c
            white[v] = (b + g + r >= bright_sum) and (hi >= bright_max) and (c < min_chroma)
            x = float(bgr[v, u, ch])
            laser[v] = (x >= hi) and (x >= laser_min) and (c >= min_chroma)
        v = 0
        while True:
            a, v = _next_run(white, v)
            if a >= H:
                break
            e = v - 1
            n = e - a + 1
            if n > max_len or a == 0 or e == H - 1:
                continue
            up = False
            for t in range(a - 1, max(-1, a - 1 - reach), -1):
                if white[t]:
                    break
                if laser[t]:
                    up = True
                    break
            dn = False
            for t in range(e + 1, min(H, e + 1 + reach)):
                if white[t]:
                    break
                if laser[t]:
                    dn = True
                    break
            if not (up and dn):
                continue
            ca, cp = chroma[a], chroma[a - 1]
            ea = a - 0.5 if cp == ca else a - (min_chroma - ca) / (cp - ca)
            ea = min(max(ea, a - 1.0), float(a))
            ce, cn = chroma[e], chroma[e + 1]
            eb = e + 0.5 if cn == ce else e + (min_chroma - ce) / (cn - ce)
            eb = min(max(eb, float(e)), e + 1.0)
            mid = 0.5 * (ea + eb)
            p = int(math.floor(mid + 0.5))
            out_c[p, u] = mid
            out_len[p, u] = eb - ea


@njit_cached
def smooth_along_quadratic(uv, nrm, first, last, sig, rmax, rad, side):
    """Intercepts of local quadratic fits along ordered curves (see ``stripe._smooth_along``).

    For point ``i`` (its curve spans ``first[i]..last[i]``), the neighbours ``i ± k``,
    ``k <= min(i - first, last - i, rmax, ceil(3 sig_i))``, give ``t = (p - p_i)·tau_i`` and
    ``h = (p - p_i)·n_i``; ``h = a + b u + c u^2`` (``u = t / sig_i``) is fitted with weights
    ``exp(-k^2 / (2 sig_i^2))``, and the same fit to the circle ``side_i (r - sqrt(r^2 - t^2))``
    of radius ``rad_i``; returns ``a - a_circle`` (0 where fewer than 2 neighbours a side).
    """
    n = uv.shape[0]
    out = np.zeros(n)
    for i in range(n):
        half = min(i - first[i], last[i] - i, rmax, int(math.ceil(3.0 * sig[i])))
        if half < 2:
            continue
        tx, ty = -nrm[i, 1], nrm[i, 0]
        s0 = 1.0
        s1 = s2 = s3 = s4 = 0.0
        h0 = h1 = h2 = 0.0
        c0 = c1 = c2 = 0.0
        inv = 1.0 / sig[i]
        r = rad[i]
        for k in range(1, half + 1):
            g = math.exp(-0.5 * (k * inv) ** 2)
            for j in (i - k, i + k):
                dx = uv[j, 0] - uv[i, 0]
                dy = uv[j, 1] - uv[i, 1]
                t = dx * tx + dy * ty
                h = dx * nrm[i, 0] + dy * nrm[i, 1]
                u = t * inv
                u2 = u * u
                s0 += g
                s1 += g * u
                s2 += g * u2
                s3 += g * u2 * u
                s4 += g * u2 * u2
                h0 += g * h
                h1 += g * h * u
                h2 += g * h * u2
                q = r * r - t * t
                hc = side[i] * (r - math.sqrt(q if q > 0.0 else 0.0))
                c0 += g * hc
                c1 += g * hc * u
                c2 += g * hc * u2
        # Cramer's rule for the intercept of [[s0 s1 s2] [s1 s2 s3] [s2 s3 s4]] x = rhs
        det = s0 * (s2 * s4 - s3 * s3) - s1 * (s1 * s4 - s3 * s2) + s2 * (s1 * s3 - s2 * s2)
        if abs(det) < 1e-12:
            continue
        m0 = s2 * s4 - s3 * s3
        a = (h0 - c0) * m0 - s1 * ((h1 - c1) * s4 - s3 * (h2 - c2)) + s2 * ((h1 - c1) * s3 - s2 * (h2 - c2))
        out[i] = a / det
    return out
