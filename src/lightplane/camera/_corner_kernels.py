"""Numba kernels behind :func:`lightplane.camera.corners.fit_corners` (the blurred-saddle fit) and
:func:`lightplane.camera.corners.refine_corners` (Förstner's step).

:func:`fit_saddles` is the Levenberg–Marquardt of ``intrinsics._fit_saddles`` a corner at a time:
the same model (:func:`lightplane.camera.corners.fit_corners`'s blurred saddle), weights, damping and stopping rule
(the corners of a chunk step together until all of them are done, as the batched numpy loop did),
with the model's ``erf`` and the normal equations evaluated only where the weight is not zero and
the Jacobian only at accepted steps; the cold start's ``erf`` serve the first iteration too.  On the
30-view calibration capture (165 corners a view, windows of ~3300 pixels, three iterations) a pixel
and iteration costs ~5 ns window, 12 ns ``erf``, 2 ns residual, 11 ns Jacobian and 10 ns normal
equations.  :func:`forstner` is :func:`refine_corners`' iteration (all corners together until the
largest step is below the tolerance).  Both give the numpy versions' values to rounding (sums in
another order, ``math.erf`` instead of scipy's; corners within 1.1e-13 px on the capture,
``tests/test_corner_kernels.py`` holds the numpy loops).
"""

from __future__ import annotations

import math

import numpy as np

from lightplane.core.jit import njit_cached

_SQRT2 = math.sqrt(2.0)
_SQRT_2_PI = math.sqrt(2.0 / math.pi)


@njit_cached(nogil=True, error_model="numpy")
def _solve(A, b, x):  # pragma: no cover - compiled
    """``x`` = the solution of ``A x = b`` (m, m) by Gaussian elimination with partial pivoting (as
    LAPACK's ``gesv``), NaN where a pivot is exactly zero.  ``A`` and ``b`` are overwritten."""
    m = b.shape[0]
    for c in range(m):
        p = c
        big = abs(A[c, c])
        for r in range(c + 1, m):
            if abs(A[r, c]) > big:
                big = abs(A[r, c])
                p = r
        if big == 0.0 or not math.isfinite(big):
            x[:] = np.nan
            return
        if p != c:
            for j in range(m):
                A[c, j], A[p, j] = A[p, j], A[c, j]
            b[c], b[p] = b[p], b[c]
        piv = A[c, c]
        for r in range(c + 1, m):
            f = A[r, c] / piv
            if f != 0.0:
                for j in range(c + 1, m):
                    A[r, j] -= f * A[c, j]
                b[r] -= f * b[c]
    for r in range(m - 1, -1, -1):
        s = b[r]
        for j in range(r + 1, m):
            s -= A[r, j] * x[j]
        x[r] = s / A[r, r]


@njit_cached(nogil=True, error_model="numpy", fastmath={"reassoc", "contract"})
def _normal_equations(J, res, m, A, g, n):  # pragma: no cover - compiled
    """``A = J Jᵀ``, ``g = J res`` over the first ``n`` rows and ``m`` columns of ``J`` (into ``A[:n, :n]``,
    ``g[:n]``; the sums reassociated so that they vectorise; four products per load of a row of ``J``)."""
    for a in range(n):
        ja = J[a]
        s0 = 0.0
        for k in range(m):
            s0 += ja[k] * res[k]
        g[a] = s0
        b = a
        while b + 4 <= n:
            j0, j1, j2, j3 = J[b], J[b + 1], J[b + 2], J[b + 3]
            s0 = s1 = s2 = s3 = 0.0
            for k in range(m):
                x = ja[k]
                s0 += x * j0[k]
                s1 += x * j1[k]
                s2 += x * j2[k]
                s3 += x * j3[k]
            A[a, b], A[a, b + 1], A[a, b + 2], A[a, b + 3] = s0, s1, s2, s3
            b += 4
        while b < n:
            jb = J[b]
            s0 = 0.0
            for k in range(m):
                s0 += ja[k] * jb[k]
            A[a, b] = s0
            b += 1
        for b in range(a, n):
            A[b, a] = A[a, b]


@njit_cached(nogil=True, error_model="numpy")
def _window(px, py, w0, i, qx, qy, radius, taper, ux, uy, W, idx):  # pragma: no cover - compiled
    """The weight of ``intrinsics._fit_saddles`` about ``(qx, qy)`` for corner ``i``: the pixels
    where it is not zero (their offsets ``ux, uy``, weights ``W`` and indices ``idx``), how many."""
    m = 0
    # squared distances safely inside the taper (weight w0: t >= 1, sin(π/2)² = 1 exactly) or outside
    # the disc (weight 0) need no hypot; the ones in between are computed as numpy did
    r_in = (radius - taper) * (1.0 - 1e-9) if radius > taper else 0.0
    r_in2 = r_in * r_in
    r_out2 = radius * radius * (1.0 + 1e-9)
    for k in range(px.shape[1]):
        if w0[i, k] == 0.0:
            continue
        dx = px[i, k] - qx
        dy = py[i, k] - qy
        d2 = dx * dx + dy * dy
        if d2 < r_in2:
            wk = w0[i, k]
        elif d2 > r_out2:
            continue
        else:
            t = (radius - math.hypot(dx, dy)) / taper
            if not t > 0.0:
                continue
            if t > 1.0:
                t = 1.0
            s = math.sin(0.5 * math.pi * t)
            wk = w0[i, k] * (s * s)
        ux[m] = dx
        uy[m] = dy
        W[m] = wk
        idx[m] = k
        m += 1
    return m


@njit_cached(nogil=True, inline="always", error_model="numpy")
def _erf(x):  # pragma: no cover - compiled
    """``math.erf``, its saturated tails (|x| >= 6: ±1 to the last bit, in libm as in scipy) without the call."""
    if x >= 6.0:
        return 1.0
    if x <= -6.0:
        return -1.0
    return math.erf(x)


@njit_cached(nogil=True, error_model="numpy")
def _erfs(p, ux, uy, m, e1, e2):  # pragma: no cover - compiled
    """The saddle model's ``erf`` factors ``e1``, ``e2`` for parameters ``p`` (13,) at the ``m`` offsets (the
    edges' signed distances ``d_i = n_i·u + κ_i t_i²``, ``t_i`` along the edge, ``κ_i = p[11 + i]``)."""
    c1, s1 = math.cos(p[2]), math.sin(p[2])
    c2, s2 = math.cos(p[3]), math.sin(p[3])
    k1, k2 = p[11], p[12]
    den = _SQRT2 * p[4]
    if k1 == 0.0 and k2 == 0.0:  # straight edges: the bends' terms left out (a tenth of the time)
        for k in range(m):
            x, y = ux[k], uy[k]
            e1[k] = _erf((c1 * x + s1 * y) / den)
            e2[k] = _erf((c2 * x + s2 * y) / den)
        return
    for k in range(m):
        x, y = ux[k], uy[k]
        t1 = c1 * y - s1 * x
        t2 = c2 * y - s2 * x
        e1[k] = _erf((c1 * x + s1 * y + k1 * (t1 * t1)) / den)
        e2[k] = _erf((c2 * x + s2 * y + k2 * (t2 * t2)) / den)


@njit_cached(nogil=True, error_model="numpy")
def _residual(p, img, i, ux, uy, idx, m, e1, e2, res):  # pragma: no cover - compiled
    """The residuals ``res`` (image - model) of the saddle model with parameters ``p`` and ``erf``
    factors ``e1``, ``e2`` at the ``m`` offsets."""
    for k in range(m):
        x, y = ux[k], uy[k]
        amp = p[6] + p[9] * x + p[10] * y
        res[k] = img[i, idx[k]] - (p[5] + p[7] * x + p[8] * y + amp * (e1[k] * e2[k]))


@njit_cached(nogil=True, error_model="numpy")
def _linear(p, img, i, ux, uy, W, idx, m, e1, e2, J, res, A6, g6, x6):  # pragma: no cover - compiled
    """The linear parameters (a, b, g, h) of ``p`` solved for its geometry (corner, edges, blur; the
    ``erf`` factors ``e1``, ``e2``), weights ``W``: written into ``p[5:11]`` (0 where not finite)."""
    for k in range(m):
        sw = math.sqrt(W[k])
        ee = e1[k] * e2[k]
        J[0, k] = sw
        J[1, k] = sw * ee
        J[2, k] = sw * ux[k]
        J[3, k] = sw * uy[k]
        J[4, k] = sw * (ux[k] * ee)
        J[5, k] = sw * (uy[k] * ee)
        res[k] = sw * img[i, idx[k]]
    _normal_equations(J, res, m, A6, g6, 6)
    tr = 0.0
    for a in range(6):
        tr += A6[a, a]
    for a in range(6):
        A6[a, a] += 1e-9 * tr
    _solve(A6, g6, x6)
    for a in range(6):
        p[5 + a] = x6[a] if math.isfinite(x6[a]) else 0.0


@njit_cached(nogil=True, error_model="numpy")
def _jacobian_straight(p, ux, uy, W, m, e1, e2, J, res):  # pragma: no cover - compiled
    """:func:`_jacobian` of straight edges (both bends 0) in the 11 free parameters."""
    c1, s1 = math.cos(p[2]), math.sin(p[2])
    c2, s2 = math.cos(p[3]), math.sin(p[3])
    s = p[4]
    kk = _SQRT_2_PI / s
    for k in range(m):
        xk, yk = ux[k], uy[k]
        d1 = c1 * xk + s1 * yk
        d2 = c2 * xk + s2 * yk
        ee = e1[k] * e2[k]
        amp = p[6] + p[9] * xk + p[10] * yk
        t1 = d1 / s
        t2 = d2 / s
        b1 = amp * (kk * math.exp(-0.5 * (t1 * t1))) * e2[k]
        b2 = amp * e1[k] * (kk * math.exp(-0.5 * (t2 * t2)))
        sw = math.sqrt(W[k])
        J[0, k] = sw * (-p[7] - p[9] * ee - b1 * c1 - b2 * c2)
        J[1, k] = sw * (-p[8] - p[10] * ee - b1 * s1 - b2 * s2)
        J[2, k] = sw * (b1 * (c1 * yk - s1 * xk))
        J[3, k] = sw * (b2 * (c2 * yk - s2 * xk))
        J[4, k] = sw * (-(b1 * d1 + b2 * d2) / s)
        J[5, k] = sw
        J[6, k] = sw * ee
        J[7, k] = sw * xk
        J[8, k] = sw * yk
        J[9, k] = sw * (xk * ee)
        J[10, k] = sw * (yk * ee)
        res[k] = sw * res[k]


@njit_cached(nogil=True, error_model="numpy")
def _jacobian(p, ux, uy, W, m, e1, e2, J, res, rows):  # pragma: no cover - compiled
    """The saddle model's Jacobian in its first ``rows`` (11 or 13) parameters (qx, qy, φ1, φ2, s, a, b,
    gx, gy, hx, hy, and the edges' bends κ1, κ2, which the fit holds) at the ``m`` offsets, times the
    square root of the weight, into ``J`` (13, K); the residuals ``res`` scaled alike."""
    c1, s1 = math.cos(p[2]), math.sin(p[2])
    c2, s2 = math.cos(p[3]), math.sin(p[3])
    k1, k2 = p[11], p[12]
    s = p[4]
    kk = _SQRT_2_PI / s
    if k1 == 0.0 and k2 == 0.0 and rows == 11:
        _jacobian_straight(p, ux, uy, W, m, e1, e2, J, res)
        return
    for k in range(m):
        xk, yk = ux[k], uy[k]
        n1 = c1 * xk + s1 * yk
        n2 = c2 * xk + s2 * yk
        t1 = c1 * yk - s1 * xk  # along the edges: d_i = n_i·u + κ_i t_i²
        t2 = c2 * yk - s2 * xk
        d1 = n1 + k1 * (t1 * t1)
        d2 = n2 + k2 * (t2 * t2)
        ee = e1[k] * e2[k]
        amp = p[6] + p[9] * xk + p[10] * yk
        r1 = d1 / s
        r2 = d2 / s
        b1 = amp * (kk * math.exp(-0.5 * (r1 * r1))) * e2[k]
        b2 = amp * e1[k] * (kk * math.exp(-0.5 * (r2 * r2)))
        sw = math.sqrt(W[k])
        # ∂d_i/∂u = n_i + 2 κ_i t_i (-sin φ_i, cos φ_i);  ∂d_i/∂φ_i = t_i (1 - 2 κ_i n_i·u)
        a1 = 2.0 * k1 * t1
        a2 = 2.0 * k2 * t2
        J[0, k] = sw * (-p[7] - p[9] * ee - b1 * (c1 - a1 * s1) - b2 * (c2 - a2 * s2))
        J[1, k] = sw * (-p[8] - p[10] * ee - b1 * (s1 + a1 * c1) - b2 * (s2 + a2 * c2))
        J[2, k] = sw * (b1 * t1 * (1.0 - 2.0 * k1 * n1))
        J[3, k] = sw * (b2 * t2 * (1.0 - 2.0 * k2 * n2))
        J[4, k] = sw * (-(b1 * d1 + b2 * d2) / s)
        J[5, k] = sw
        J[6, k] = sw * ee
        J[7, k] = sw * xk
        J[8, k] = sw * yk
        J[9, k] = sw * (xk * ee)
        J[10, k] = sw * (yk * ee)
        if rows > 11:
            J[11, k] = sw * (b1 * (t1 * t1))
            J[12, k] = sw * (b2 * (t2 * t2))
        res[k] = sw * res[k]


@njit_cached(nogil=True, error_model="numpy")
def window_pixels(g, base, ox, oy, px, py, img, w0):  # pragma: no cover - compiled
    """The pixel centres ``base[i] + (ox[k], oy[k])`` (``px, py``, (n, K)) about integer-valued corners
    ``base`` (n, 2), the image ``g`` there (``img``; outside the image: its nearest border pixel) and
    ``w0`` 1 inside the image, else 0."""
    h, w = g.shape
    for i in range(base.shape[0]):
        for k in range(ox.shape[0]):
            x = base[i, 0] + ox[k]
            y = base[i, 1] + oy[k]
            px[i, k] = x
            py[i, k] = y
            w0[i, k] = 1.0 if (x >= 0 and x <= w - 1 and y >= 0 and y <= h - 1) else 0.0
            img[i, k] = g[int(min(max(y, 0.0), h - 1.0)), int(min(max(x, 0.0), w - 1.0))]


@njit_cached(nogil=True, error_model="numpy")
def fit_saddles(px, py, img, w0, radius, taper, P, warm, max_iter, tol, best_P, best_cost, sens):  # pragma: no cover
    """``intrinsics._fit_saddles``' Levenberg–Marquardt for the corners of one chunk: pixel centres
    ``px, py`` (n, K) (lens-frame coordinates with a camera), image values ``img`` (n, K), the weight's
    fixed factor ``w0`` (n, K) (inside the image times the area element), window radii ``radius`` (n,);
    ``P`` (n, 13) the start (overwritten; its edge bends ``P[:, 11:13]`` held), ``warm``: whole parameter
    sets (else the linear parameters are solved for first).  Writes the best parameters ``best_P`` (n, 13),
    their weighted mean squared residual ``best_cost`` (n,) and, where ``sens`` is given ((n, 2, 2); else
    (0, 2, 2)), how the fitted corner moves with the bends held, ``∂(qx, qy)/∂(κ1, κ2)`` (Gauss–Newton:
    ``-(J_fᵀJ_f)⁻¹ J_fᵀ J_κ`` of the free parameters ``f``, at the last accepted step after a cold start's
    first; NaN where singular or where there was none)."""
    n, K = px.shape
    ux = np.empty(K)
    uy = np.empty(K)
    W = np.empty(K)
    idx = np.empty(K, np.int64)
    e1 = np.empty(K)
    e2 = np.empty(K)
    res = np.empty(K)
    J = np.empty((13, K))
    A = np.empty((11, 11))
    g = np.empty(11)
    step = np.empty(11)
    A6 = np.empty((6, 6))
    g6 = np.empty(6)
    x6 = np.empty(6)
    lam = np.full(n, 1e-3)
    best_cost[:] = np.inf
    best_P[:] = P
    A_best = np.zeros((n, 13, 13))  # with the bends' rows and columns (for sens)
    g_best = np.zeros((n, 13))
    want = sens.shape[0] == n
    has = np.zeros(n, np.bool_)
    for it in range(max_iter + 1):
        all_better = True
        big_step = 0.0
        for i in range(n):
            p = P[i]
            m = _window(px, py, w0, i, p[0], p[1], radius[i], taper, ux, uy, W, idx)
            _erfs(p, ux, uy, m, e1, e2)
            if it == 0 and not warm:  # the linear parameters for the starting geometry (the same erf)
                _linear(p, img, i, ux, uy, W, idx, m, e1, e2, J, res, A6, g6, x6)
                best_P[i] = p
            _residual(p, img, i, ux, uy, idx, m, e1, e2, res)
            num = 0.0
            den = 0.0
            for k in range(m):
                num += W[k] * (res[k] * res[k])
                den += W[k]
            cost = num / max(den, 1e-300)
            better = math.isfinite(cost) and cost <= best_cost[i]
            if better:
                # the bends' columns once, near the solution (after a cold start's first step): sens needs
                # them to a few per cent
                rows = 13 if want and not has[i] and (it > 0 or warm) else 11
                _jacobian(p, ux, uy, W, m, e1, e2, J, res, rows)
                _normal_equations(J, res, m, A_best[i], g_best[i], rows)
                has[i] = has[i] or rows == 13
                best_P[i] = p
                best_cost[i] = cost
                lam[i] = max(min(0.3 * lam[i], 1e9), 1e-9)
            else:
                all_better = False
                lam[i] = max(min(10.0 * lam[i], 1e9), 1e-9)
            for a in range(11):
                g[a] = g_best[i, a]
                for b in range(11):
                    A[a, b] = A_best[i, a, b]
                A[a, a] += lam[i] * A_best[i, a, a]
            _solve(A, g, step)
            finite = True
            for a in range(11):
                if not math.isfinite(step[a]):
                    finite = False
            for a in range(11):
                P[i, a] = best_P[i, a] + (step[a] if finite else 0.0)
            if finite:
                big_step = max(big_step, abs(step[0]), abs(step[1]))
        if all_better and big_step < tol:
            break
    for i in range(n if want else 0):
        if not has[i]:
            sens[i] = np.nan
            continue
        for c in range(2):
            for a in range(11):
                g[a] = A_best[i, a, 11 + c]
                for b in range(11):
                    A[a, b] = A_best[i, a, b]
            _solve(A, g, step)
            sens[i, 0, c] = -step[0]
            sens[i, 1, c] = -step[1]


@njit_cached(nogil=True, error_model="numpy")
def line_bends(g, e, ok, width, kappa):  # pragma: no cover - compiled
    """:func:`lightplane.camera.corners._line_bends`: for each corner of the grid lines ``g`` (lines, m, 2)
    (line directions ``e`` (lines, m, 2), usable corners ``ok`` (lines, m)), the polynomial
    ``y = a + b t + c t² (+ d t³)`` by least squares through the usable corners among the ``width``
    nearest on its line (centred, shifted in at the ends), in the frame of the corner and ``e``;
    ``kappa`` (lines, m) ``= -c`` (a parabola through 4 or 5 corners, the cubic through 6 or more;
    0 through fewer)."""
    n_lines, m = ok.shape
    A = np.empty((4, 4))
    b = np.empty(4)
    x = np.empty(4)
    for i in range(n_lines):
        for j in range(m):
            first = min(max(j - width // 2, 0), m - width)
            ux, uy = e[i, j, 0], e[i, j, 1]
            nrm = math.sqrt(ux * ux + uy * uy)
            ux /= nrm
            uy /= nrm
            count = 0
            scale = 1e-9
            for k in range(first, first + width):
                if ok[i, k]:
                    count += 1
                    scale = max(scale, abs((g[i, k, 0] - g[i, j, 0]) * ux + (g[i, k, 1] - g[i, j, 1]) * uy))
            kappa[i, j] = 0.0
            if count < 4:
                continue
            deg = 3 if count >= 6 else 2
            A[:] = 0.0
            b[:] = 0.0
            for k in range(first, first + width):
                if not ok[i, k]:
                    continue
                dx = g[i, k, 0] - g[i, j, 0]
                dy = g[i, k, 1] - g[i, j, 1]
                t = (dx * ux + dy * uy) / scale
                y = dy * ux - dx * uy  # along n = (-u_y, u_x), the saddle model's edge normal
                p = 1.0
                for r in range(deg + 1):
                    q = p * p  # t^(r + c)
                    for c in range(r, deg + 1):
                        A[r, c] += q
                        q *= t
                    b[r] += p * y
                    p *= t
            for r in range(deg + 1):
                for c in range(r):
                    A[r, c] = A[c, r]
            _solve(A[:deg + 1, :deg + 1], b[:deg + 1], x[:deg + 1])
            if math.isfinite(x[2]):
                kappa[i, j] = -x[2] / (scale * scale)


@njit_cached(nogil=True, error_model="numpy")
def forstner(gx, gy, unit, q0, radius, two_sigma2, max_iter, tol, q):  # pragma: no cover - compiled
    """:func:`lightplane.camera.corners.refine_corners`' iteration: each corner of ``q0`` (n, 2) moved to the
    point its gradients (``unit`` times ``gx, gy``, the Scharr images) are orthogonal to, over the pixels within
    ``radius`` of the integer pixel nearest to it weighted by ``exp(-d² / two_sigma2)`` (d from the
    corner); all corners step together until the largest step is below ``tol`` (``max_iter`` steps at
    most).  The result in ``q`` (n, 2); a corner whose system is singular keeps its place."""
    h, w = gx.shape
    n = q0.shape[0]
    r = int(math.ceil(radius))
    r2 = radius * radius
    for i in range(n):
        q[i, 0] = q0[i, 0]
        q[i, 1] = q0[i, 1]
    qn = np.empty((n, 2))
    for _ in range(max_iter):
        step = 0.0
        nan = False
        for i in range(n):
            qx, qy = q[i, 0], q[i, 1]
            bx0 = int(np.round(qx))
            by0 = int(np.round(qy))
            axx = axy = ayy = sx = sy = 0.0
            for oy in range(-r, r + 1):
                py = min(max(by0 + oy, 0), h - 1)
                dy = py - qy
                for ox in range(-r, r + 1):
                    px = min(max(bx0 + ox, 0), w - 1)
                    dx = px - qx
                    d2 = dx * dx + dy * dy
                    if not d2 <= r2:
                        continue
                    wt = math.exp(-d2 / two_sigma2)
                    a = gx[py, px] * unit
                    b = gy[py, px] * unit
                    axx += wt * a * a
                    axy += wt * a * b
                    ayy += wt * b * b
                    sx += wt * (a * a * px + a * b * py)
                    sy += wt * (a * b * px + b * b * py)
            det = axx * ayy - axy * axy
            if det > 1e-12 * max(axx * ayy, 1e-300):
                qn[i, 0] = (ayy * sx - axy * sy) / det
                qn[i, 1] = (axx * sy - axy * sx) / det
            else:
                qn[i, 0] = qx
                qn[i, 1] = qy
            dqx = abs(qn[i, 0] - qx)
            dqy = abs(qn[i, 1] - qy)
            if not (dqx == dqx and dqy == dqy):
                nan = True
            else:
                step = max(step, dqx, dqy)
        for i in range(n):
            q[i, 0] = qn[i, 0]
            q[i, 1] = qn[i, 1]
        if step < tol and not nan:
            break
