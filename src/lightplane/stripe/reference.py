"""Pure-numpy implementation of the profile kernels in :mod:`lightplane.stripe.kernels`.

Same algorithm, same clamped borders, same tie-breaking; vectorised over lines.
Used by ``extract_profile`` with ``StripeOptions(backend="numpy")`` and to check the numba kernels.
"""

from __future__ import annotations

import numpy as np

from lightplane.stripe import kernels as K


def candidates_numpy(A: np.ndarray, sep: int):
    """:func:`_stripe_kernels.profile_candidates` in numpy (same definition of p2)."""
    S, L = A.shape
    B = K.BLOCK
    nb = (S + B - 1) // B
    ln = np.arange(L)
    Af = A.astype(np.float64)
    p1 = np.argmax(Af, axis=0).astype(np.int64)
    v1 = Af[p1, ln]
    pad = np.full((nb * B, L), -np.inf)
    pad[:S] = Af
    bm = pad.reshape(nb, B, L).max(axis=1)                       # (nb, L)
    s0 = np.arange(nb)[:, None] * B
    s1 = np.minimum(S, s0 + B)
    far = (s1 - 1 < p1[None, :] - sep) | (s0 > p1[None, :] + sep)
    bmf = np.where(far, bm, -np.inf)
    b2 = np.argmax(bmf, axis=0)
    has = far.any(axis=0)
    v2 = np.where(has, bmf[b2, ln], -np.inf)
    blk = pad.reshape(nb, B, L)[b2, :, ln]                         # (L, B)
    p2 = b2 * B + np.argmax(blk == v2[:, None], axis=1)
    p2 = np.where(has, p2, -1).astype(np.int64)
    return p1, v1, p2, v2


def choose_numpy(A, p1, v1, p2, v2, min_peak, half_window, tol):
    """:func:`lightplane.stripe.kernels.choose_consistent` in numpy."""
    S, L = A.shape
    out = p1.copy()
    ref_src = np.where(v1 >= min_peak, p1.astype(float), np.nan)
    pad = np.concatenate([np.full(half_window, np.nan), ref_src, np.full(half_window, np.nan)])
    win = np.lib.stride_tricks.sliding_window_view(pad, 2 * half_window + 1).copy()
    win[:, half_window] = np.nan
    cnt = np.sum(np.isfinite(win), axis=1)
    cand = cnt >= 2
    if not cand.any():
        return out
    ref = np.full(L, np.nan)
    ref[cand] = np.nanmedian(win[cand], axis=1)
    off = cand & (np.abs(p1 - ref) > tol)
    second = off & (p2 >= 0) & (v2 >= min_peak) & (np.abs(p2 - ref) <= tol)
    out[second] = p2[second]
    # the rest: the highest sample within tol of the median, a local maximum of at least K.NEAR_MEDIAN_SHARE of p1's
    for line in np.flatnonzero(off & ~second):
        s0 = max(1, int(np.ceil(ref[line] - tol)))
        s1 = min(S - 2, int(np.floor(ref[line] + tol)))
        if s1 < s0:
            continue
        seg = A[s0:s1 + 1, line].astype(np.float64)
        q = s0 + int(np.argmax(seg))
        best = float(A[q, line])
        if best >= min_peak and best >= K.NEAR_MEDIAN_SHARE * v1[line] and best >= A[q - 1, line] \
                and best >= A[q + 1, line]:
            out[line] = q
    return out


def _take(A, rows, lines):
    S, L = A.shape
    return A[np.clip(rows, 0, S - 1), lines].astype(np.float64)


def fwhm_numpy(A, c, half):
    """Vectorised :func:`_stripe_kernels._fwhm_line` (min_peak = 0): fwhm, best, bg, left, right."""
    S, L = A.shape
    ln = np.arange(L)
    cands = np.stack([_take(A, c, ln), _take(A, c - 1, ln), _take(A, c + 1, ln)])
    j = np.argmax(cands, axis=0)
    best = cands[j, ln]
    k0 = c + np.array([0, -1, 1])[j]
    offs = np.arange(-half, half + 1)
    bg = np.min(_take(A, c[:, None] + offs[None, :], ln[:, None]), axis=1)
    bg = np.minimum(bg, best)
    level = bg + 0.5 * (best - bg)
    steps = np.arange(1, half + 1)
    res = []
    for sgn in (1, -1):
        ks = k0[:, None] + sgn * steps[None, :]
        vals = _take(A, ks, ln[:, None])
        below = vals < level[:, None]
        found = below.any(axis=1)
        first = np.argmax(below, axis=1)
        x = vals[ln, first]
        prev = np.where(first == 0, best, vals[ln, np.maximum(first - 1, 0)])
        kk = ks[ln, first]
        with np.errstate(divide="ignore", invalid="ignore"):
            pos = (kk - sgn) + sgn * (prev - level) / (prev - x)
        res.append(np.where(found, pos, np.nan))
    right, left = res
    return right - left, best, bg, left, right


def _hermite_root_np(g0, d0, g1, d1):
    """Vectorised :func:`_stripe_kernels._hermite_root` (same steps)."""
    lo = np.zeros_like(g0)
    hi = np.ones_like(g0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = g0 / (g0 - g1)
        pos0 = g0 > 0.0
        active = np.ones(np.shape(t), dtype=bool)
        for _ in range(K.HERMITE_ITER):
            t2 = t * t
            t3 = t2 * t
            h = (2.0 * t3 - 3.0 * t2 + 1.0) * g0 + (t3 - 2.0 * t2 + t) * d0 + (-2.0 * t3 + 3.0 * t2) * g1 + (t3 - t2) * d1
            dh = (6.0 * t2 - 6.0 * t) * (g0 - g1) + (3.0 * t2 - 4.0 * t + 1.0) * d0 + (3.0 * t2 - 2.0 * t) * d1
            same = (h > 0.0) == pos0
            lo = np.where(same, t, lo)
            hi = np.where(same, hi, t)
            tn = np.where(dh != 0.0, t - h / dh, 0.5 * (lo + hi))
            tn = np.where((lo <= tn) & (tn <= hi), tn, 0.5 * (lo + hi))
            done = np.abs(tn - t) <= K.HERMITE_TOL
            t = np.where(active, tn, t)
            active &= ~done
            if not active.any():
                break
    t = np.where(g1 == 0.0, 1.0, t)
    return np.where(g0 == 0.0, 0.0, t)


def _ridge_normal_np(ruu, ruv, rvv):
    half_tr = 0.5 * (ruu + rvv)
    half_df = 0.5 * (ruu - rvv)
    root = np.sqrt(half_df * half_df + ruv * ruv)
    lam = half_tr - root
    pos = half_df > 0.0
    nu = np.where(pos, ruv, half_df - root)
    nv = np.where(pos, -half_df - root, ruv)
    nrm = np.sqrt(nu * nu + nv * nv)
    zero = nrm == 0.0
    with np.errstate(divide="ignore", invalid="ignore"):
        nu = np.where(zero, 1.0, nu / nrm)
        nv = np.where(zero, 0.0, nv / nrm)
    flip = (nv < 0.0) | ((nv == 0.0) & (nu < 0.0))
    return lam, np.where(flip, -nu, nu), np.where(flip, -nv, nv)


def centres_numpy(A, pos, w0, w1, w2, params):
    """Vectorised :func:`_stripe_kernels.profile_centres`: the centre of each line of ``A`` near
    its peak ``pos`` (-1: none), with the scales and limits of ``params`` (``xw``, ``qpeak``,
    ``half``, ``min_peak``, ``max_width``, ``min_cos``)."""
    xw, qpeak, half = params["xw"], params["qpeak"], params["half"]
    min_peak, max_width, min_cos = params["min_peak"], params["max_width"], params["min_cos"]
    S, L = A.shape
    R = (w0.size - 1) // 2
    has = pos >= 0
    p = np.where(has, pos, 0)
    # 1. midpoint of the half-level crossings around the highest sample
    fw, best, bg, left, right = fwhm_numpy(A, p, half)
    with np.errstate(invalid="ignore"):
        cm = np.floor(0.5 * (left + right) + 0.5)
        use = np.isfinite(fw) & (np.abs(cm - p) <= qpeak)
    c = np.where(use, cm, p).astype(np.int64)
    edge = (c - 1 - R < 0) | (c + 1 + R > S - 1)
    # 2. derivatives at c-1, c, c+1 from the local patch
    RX = (xw.shape[2] - 1) // 2
    ln = np.arange(L)
    re = np.minimum(np.minimum(ln, L - 1 - ln), RX)
    rs, rss, rl, rll, rls, intensity = _patch_derivatives(A, c, w0, w1, w2, xw, re)
    lam, nl, ns = _ridge_normal_np(rll[:, 1], rls[:, 1], rss[:, 1])
    # 3. zero crossing
    cc, crossing = _zero_crossing(c, nl[:, None] * rl + ns[:, None] * rs, nl[:, None] * rls + ns[:, None] * rss)
    width = fw * ns
    # clipped (flat) tops where Steger's ridge test fails: midpoint of the smoothed
    # half-level crossings (as in _stripe_kernels._line_finish)
    steger_fail = (lam >= 0.0) | (np.abs(ns) < min_cos) | ~crossing
    flat = flat_numpy(A, p, fw, best, bg, half) & has & ~edge & (best - bg >= min_peak) & steger_fail
    cc_flat = np.full(L, np.nan)
    if flat.any():
        f = np.flatnonzero(flat)
        cc_flat[f] = flat_centre_numpy(A, f, p[f], c[f], xw, re[f], qpeak, half)
    no_normal = flat & ((lam >= 0.0) | (np.abs(ns) < min_cos))
    nl = np.where(no_normal, 0.0, nl)
    ns = np.where(no_normal, 1.0, ns)
    width = np.where(flat, fw * ns, width)
    too_wide = ~np.isfinite(fw) | (width > max_width)
    cc = np.where(flat, cc_flat, cc)
    # lines whose contrast is below min_peak stop before their derivatives (the kernels' _line_hopeless)
    hopeless = has & ~edge & (best - bg < min_peak)
    status = np.select(
        [~has, edge, best - bg < min_peak, flat & ~np.isfinite(cc_flat), flat & too_wide, flat,
         lam >= 0.0, np.abs(ns) < min_cos, ~crossing, too_wide],
        [K.NO_PEAK, K.EDGE, K.NO_PEAK, K.TOO_WIDE, K.TOO_WIDE, K.OK,
         K.NOT_RIDGE, K.ALONG_LINE, K.NO_CROSSING, K.TOO_WIDE],
        K.OK,
    ).astype(np.uint8)
    ok = status == K.OK
    centre = np.where(ok, cc, np.nan)
    normal = np.column_stack([nl, ns])
    strength = -lam
    # mirror what the numba kernel leaves in lines it gives up on
    gone = ~has | edge | hopeless
    width = np.where((ok | (status == K.TOO_WIDE)) & ~gone, width, np.nan)
    for arr in (intensity, strength):
        arr[gone] = np.nan
    normal[gone] = np.nan
    return centre, normal, strength, intensity, width, status


def _patch_derivatives(A, c, w0, w1, w2, xw, re):
    """Derivatives ``r_s, r_ss, r_l, r_ll, r_ls`` (L, 3) at samples ``c - 1, c, c + 1`` of each line
    (``s`` along, ``l`` across the lines) and the smoothed value at ``c`` (L,), from the patch
    ``P[l, j, m, i]`` around each centre (``re``: each line's kernel set across the lines)."""
    S, L = A.shape
    R = (w0.size - 1) // 2
    RX = (xw.shape[2] - 1) // 2
    ln = np.arange(L)
    ii = np.arange(-R, R + 1)
    jj = np.arange(-RX, RX + 1)
    lines = np.clip(ln[:, None] + jj[None, :], 0, L - 1)                     # (L, 2RX+1)
    x0, x1, x2 = xw[re, 0], xw[re, 1], xw[re, 2]                               # (L, 2RX+1) each
    rows = c[:, None, None] + np.arange(-1, 2)[None, :, None] + ii[None, None, :]  # (L, 3, 2R+1)
    P = A[np.clip(rows, 0, S - 1)[:, None, :, :], lines[:, :, None, None]].astype(np.float64)
    b0 = P @ w0
    b1 = P @ w1
    b2 = P @ w2                                                               # (L, 2RX+1, 3)
    rs = np.einsum("lj,ljm->lm", x0, b1)
    rss = np.einsum("lj,ljm->lm", x0, b2)
    rl = np.einsum("lj,ljm->lm", x1, b0)
    rll = np.einsum("lj,ljm->lm", x2, b0)
    rls = np.einsum("lj,ljm->lm", x1, b1)
    intensity = np.einsum("lj,lj->l", x0, b0[:, :, 1])
    return rs, rss, rl, rll, rls, intensity


def _zero_crossing(c, g, d):
    """The zero of ``g`` (L, 3) at samples ``c - 1, c, c + 1`` (slopes ``d``) next to ``c``:
    the cubic Hermite root in the bracketing cell (the nearer one when both bracket), and
    whether there is one."""
    g0, g1, g2 = g.T
    d0, d1, d2 = d.T
    lo_ok = ((g0 > 0.0) != (g1 > 0.0)) | (g0 == 0.0)
    hi_ok = ((g1 > 0.0) != (g2 > 0.0)) | (g2 == 0.0)
    t_lo = _hermite_root_np(g0, d0, g1, d1)
    t_hi = _hermite_root_np(g1, d1, g2, d2)
    cc_lo = c - 1 + t_lo
    cc_hi = c + t_hi
    cc = np.where(lo_ok & hi_ok, np.where((1.0 - t_lo) < t_hi, cc_lo, cc_hi), np.where(lo_ok, cc_lo, cc_hi))
    cc = np.where(g1 == 0.0, c.astype(float), cc)
    crossing = (g1 == 0.0) | lo_ok | hi_ok
    return cc, crossing


def flat_numpy(A, p, fw, best, bg, half):
    """Vectorised :func:`_stripe_kernels._is_flat`."""
    S, L = A.shape
    ln = np.arange(L)
    thr = best - K.FLAT_TOL * (best - bg)
    ks = np.arange(1, 2 * half + 1)
    n = np.ones(L)
    for sgn in (1, -1):
        kk = p[:, None] + sgn * ks[None, :]
        inside = (kk >= 0) & (kk < S)
        ge = inside & (_take(A, kk, ln[:, None]) >= thr[:, None])
        n += np.cumprod(ge, axis=1).sum(axis=1)
    with np.errstate(invalid="ignore"):
        return np.isfinite(fw) & (best - bg > 0.0) & (n >= 3) & (n > K.FLAT_RUN_PER_FWHM * fw + 1.5)


def flat_centre_numpy(A, lines, p, c, xw, re, qpeak, half):
    """Vectorised :func:`_stripe_kernels._flat_centre` for the given ``lines``."""
    S, L = A.shape
    RX = (xw.shape[2] - 1) // 2
    H2 = half + qpeak + 2
    jj = np.arange(-RX, RX + 1)
    cols = np.clip(lines[:, None] + jj[None, :], 0, L - 1)                     # (n, 2RX+1)
    rows = np.clip(c[:, None] + np.arange(-H2, H2 + 1)[None, :], 0, S - 1)   # (n, M)
    P = A[rows[:, :, None], cols[:, None, :]].astype(np.float64)              # (n, M, 2RX+1)
    Y = np.einsum("nmj,nj->nm", P, xw[re, 0])
    fw, _, _, left, right = fwhm_numpy(np.ascontiguousarray(Y.T), p - c + H2, half)
    return c - H2 + 0.5 * (left + right)


def profile_numpy(A, w0, w1, w2, params):
    p1, v1, p2, v2 = candidates_numpy(A, params["sep"])
    pos = choose_numpy(A, p1, v1, p2, v2, params["min_peak"], 5, params["tol"]) if params["continuity"] else p1
    return centres_numpy(A, pos, w0, w1, w2, params)
