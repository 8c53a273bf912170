"""The compiled corner kernels (:mod:`lightplane.camera._corner_kernels`) against the numpy loops they replace.

The saddle fit's Levenberg–Marquardt and Förstner's iteration were batched numpy loops; the kernels
run them a corner at a time with the same model, weights, damping and stopping rules.  Here the
numpy model and loops (kept below as references) run on the very inputs the kernels get inside
:func:`fit_corners` (cold and warm starts, with and without a lens frame) and
:func:`refine_corners`, on the noisy affine board of ``test_intrinsics_corners``: the corners agree
to rounding (measured 6e-14 px for the saddle fit, 3e-13 px for Förstner's; the bar 1e-9 px is far
below the fit's noise, 0.012 px).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import lightplane.camera._corner_kernels as ck
import lightplane.camera.corners as corners_module
from lightplane.camera.model import Camera
from lightplane.camera.corners import _fit_corners, refine_corners
from test_intrinsics_corners import BOARD, SHAPE, affine_board, truth_corners

SAME_PX = 1e-9


def _saddle_model(P: np.ndarray, ux: np.ndarray, uy: np.ndarray, jacobian: bool):
    """The blurred saddle of :func:`lightplane.camera.corners.fit_corners` at offsets ``(ux, uy)`` (N, K) from the
    corners; ``P`` (N, 13) = qx, qy, φ1, φ2, s, a, b, gx, gy, hx, hy, κ1, κ2 (the edges' bends, held).
    Returns the model (N, K) and, if asked, its Jacobian (N, 11, K) in the free parameters."""
    from scipy.special import erf

    c1, s1 = np.cos(P[:, 2:3]), np.sin(P[:, 2:3])
    c2, s2 = np.cos(P[:, 3:4]), np.sin(P[:, 3:4])
    s = P[:, 4:5]
    k1, k2 = P[:, 11:12], P[:, 12:13]
    n1, n2 = c1 * ux + s1 * uy, c2 * ux + s2 * uy
    t1, t2 = c1 * uy - s1 * ux, c2 * uy - s2 * ux  # along the edges
    d1 = n1 + k1 * t1**2
    d2 = n2 + k2 * t2**2
    e1 = erf(d1 / (np.sqrt(2.0) * s))
    e2 = erf(d2 / (np.sqrt(2.0) * s))
    ee = e1 * e2
    amp = P[:, 6:7] + P[:, 9:10] * ux + P[:, 10:11] * uy
    model = P[:, 5:6] + P[:, 7:8] * ux + P[:, 8:9] * uy + amp * ee
    if not jacobian:
        return model, None
    k = np.sqrt(2.0 / np.pi) / s
    b1 = amp * (k * np.exp(-0.5 * (d1 / s) ** 2)) * e2  # amp · E'(d1) E(d2)
    b2 = amp * e1 * (k * np.exp(-0.5 * (d2 / s) ** 2))
    J = np.empty((P.shape[0], 11, ux.shape[1]))
    J[:, 0] = -P[:, 7:8] - P[:, 9:10] * ee - b1 * (c1 - 2 * k1 * t1 * s1) - b2 * (c2 - 2 * k2 * t2 * s2)
    J[:, 1] = -P[:, 8:9] - P[:, 10:11] * ee - b1 * (s1 + 2 * k1 * t1 * c1) - b2 * (s2 + 2 * k2 * t2 * c2)
    J[:, 2] = b1 * t1 * (1 - 2 * k1 * n1)
    J[:, 3] = b2 * t2 * (1 - 2 * k2 * n2)
    J[:, 4] = -(b1 * d1 + b2 * d2) / s
    J[:, 5] = 1.0
    J[:, 6] = ee
    J[:, 7] = ux
    J[:, 8] = uy
    J[:, 9] = ux * ee
    J[:, 10] = uy * ee
    return model, J


def _solve_each(A, b):
    try:
        with np.errstate(all="ignore"):
            return np.linalg.solve(A, b[..., None])[..., 0]
    except np.linalg.LinAlgError:
        x = np.full(b.shape, np.nan)
        for i in range(len(A)):
            try:
                x[i] = np.linalg.solve(A[i], b[i])
            except np.linalg.LinAlgError:
                pass
        return x


def numpy_fit_saddles(px, py, img, w0, radius, taper, P, warm, max_iter, tol):
    """The batched numpy Levenberg–Marquardt that :func:`ck.fit_saddles` replaces (lightplane 7a27c47; with
    the edges' bends ``P[:, 11:13]`` held)."""
    def weight(q):
        ux, uy = px - q[:, :1], py - q[:, 1:]
        t = np.clip((radius[:, None] - np.hypot(ux, uy)) / taper, 0.0, 1.0)
        return ux, uy, w0 * np.sin(0.5 * np.pi * t) ** 2

    n = len(P)
    P = P.copy()
    if not warm:
        ux, uy, W = weight(P[:, :2])
        _, J = _saddle_model(P, ux, uy, True)
        lin = [5, 6, 7, 8, 9, 10]
        Jl = J[:, lin]
        A = (Jl * W[:, None]) @ Jl.transpose(0, 2, 1)
        rhs = ((Jl * W[:, None]) @ img[..., None])[..., 0]
        sol = _solve_each(A + 1e-9 * np.trace(A, axis1=1, axis2=2)[:, None, None] * np.eye(6), rhs)
        P[:, lin] = np.where(np.isfinite(sol), sol, 0.0)
    eye = np.eye(11)
    lam = np.full(n, 1e-3)
    best_cost = np.full(n, np.inf)
    best_P = P.copy()
    A_best = np.zeros((n, 11, 11))
    g_best = np.zeros((n, 11))
    for _ in range(max_iter + 1):
        ux, uy, W = weight(P[:, :2])
        M, J = _saddle_model(P, ux, uy, True)
        res = img - M
        cost = np.einsum("nk,nk->n", W, res * res) / np.maximum(W.sum(1), 1e-300)
        better = np.isfinite(cost) & (cost <= best_cost)
        if np.any(better):
            sw = np.sqrt(W)
            J *= sw[:, None]
            A_best[better] = (J @ J.transpose(0, 2, 1))[better]
            g_best[better] = (J @ (sw * res)[..., None])[..., 0][better]
            best_P[better], best_cost[better] = P[better], cost[better]
        lam = np.clip(np.where(better, 0.3 * lam, 10.0 * lam), 1e-9, 1e9)
        diag = np.einsum("nii->ni", A_best)
        step = _solve_each(A_best + (lam[:, None] * diag)[:, :, None] * eye, g_best)
        step[~np.all(np.isfinite(step), axis=1)] = 0.0
        P = best_P.copy()
        P[:, :11] += step
        if np.all(better) and np.abs(step[:, :2]).max(initial=0.0) < tol:
            break
    return best_P, best_cost


def numpy_forstner(gx, gy, q0, radius, sigma, max_iter, tol):
    """The batched numpy iteration of :func:`refine_corners` that :func:`ck.forstner` replaces."""
    h, w = gx.shape
    r = int(np.ceil(radius))
    oy, ox = np.mgrid[-r:r + 1, -r:r + 1]
    ox, oy = ox.ravel(), oy.ravel()
    q = q0.copy()
    for _ in range(max_iter):
        base = np.round(q).astype(int)
        px = np.clip(base[:, :1] + ox, 0, w - 1)
        py = np.clip(base[:, 1:] + oy, 0, h - 1)
        d2 = (px - q[:, :1]) ** 2 + (py - q[:, 1:]) ** 2
        wt = np.exp(-d2 / (2.0 * sigma**2)) * (d2 <= radius**2)
        a, b = gx[py, px], gy[py, px]
        axx, axy, ayy = (wt * a * a).sum(1), (wt * a * b).sum(1), (wt * b * b).sum(1)
        bx = (wt * (a * a * px + a * b * py)).sum(1)
        by = (wt * (a * b * px + b * b * py)).sum(1)
        det = axx * ayy - axy**2
        ok = det > 1e-12 * np.maximum(axx * ayy, 1e-300)
        with np.errstate(divide="ignore", invalid="ignore"):
            qn = np.column_stack([(ayy * bx - axy * by) / det, (axx * by - axy * bx) / det])
        qn[~ok] = q[~ok]
        step = np.abs(qn - q).max() if len(q) else 0.0
        q = qn
        if step < tol:
            break
    return q


@pytest.fixture(scope="module")
def noisy_board():
    rng = np.random.default_rng(11)
    origin = np.array([55.4, 0.3])
    img = affine_board(origin, 0.9) + rng.normal(0.0, 2.0, SHAPE)
    t = truth_corners(origin)
    return img, t, t + rng.uniform(-0.2, 0.2, t.shape)


def _recorded_fits(monkeypatch, run):
    """The kernel's inputs and outputs in each call made by ``run()``."""
    calls = []
    kernel = ck.fit_saddles

    def record(px, py, img, w0, radius, taper, P, warm, max_iter, tol, best_P, best_cost, sens):
        start = P.copy()
        kernel(px, py, img, w0, radius, taper, P, warm, max_iter, tol, best_P, best_cost, sens)
        calls.append(((px, py, img, w0, radius, taper, start, warm, max_iter, tol), best_P.copy(), best_cost.copy(),
                      sens.copy()))

    monkeypatch.setattr(corners_module, "fit_saddles", record)  # where the corner fit looks it up
    out = run()
    monkeypatch.undo()
    return calls, out


def test_saddle_fit_is_the_numpy_loop(monkeypatch, noisy_board):
    """Cold fit, warm refit in a lens frame (barrel distortion: every window bent), and the corners."""
    img, t, start = noisy_board
    cam = Camera(np.array([[300.0, 0, 110.0], [0, 300.0, 75.0], [0, 0, 1]]), np.array([-0.3, 0.1, 0, 0, 0]),
                 SHAPE[1], SHAPE[0])
    cold, (q1, _, ok1, P1) = _recorded_fits(monkeypatch, lambda: _fit_corners(img, start, BOARD))
    warm, (q2, _, ok2, _) = _recorded_fits(monkeypatch, lambda: _fit_corners(img, q1, BOARD, camera=cam, start=P1))
    # two chunks each (the cold fit's calls after them: its corners fitted again with the bends of their
    # fitted grid, a warm start)
    assert ok1.all() and ok2.all() and len(warm) == 2 and [c[0][7] for c in cold[:2]] == [False, False]
    assert all(c[0][7] for c in cold[2:]) and warm[0][0][7]  # the cold start solves the linear parameters, the warm one not
    for args, best_P, best_cost, _ in cold + warm:
        ref_P, ref_cost = numpy_fit_saddles(*args)
        assert np.abs(best_P[:, :2] - ref_P[:, :2]).max() < SAME_PX
        assert np.allclose(best_P, ref_P, rtol=1e-9, atol=1e-9)
        assert np.allclose(best_cost, ref_cost, rtol=1e-9)
    # and the fit is the fit: 0.0117 px RMS from the truth here; the bar is test_noise_8bit's (1.5x its 0.012 px)
    assert np.sqrt(np.mean(np.sum((q1 - t) ** 2, axis=1))) < 0.018
    assert np.abs(q2 - q1).max() > 1e-3  # the lens frame moved them (0.025 px): the warm path did run


def test_bend_sensitivity_is_the_fits(monkeypatch, noisy_board):
    """The kernel's ``sens``, how a fitted corner moves with the bends it holds (what the corner fit moves
    its corners by when the bends measured on the fitted grid differ from the start's), against the
    fit itself with each bend changed by ±0.02 px across the window: within 10 % of the largest (measured
    3 %: ``sens`` is taken after the first step, the corner fit needs it to a few per cent)."""
    img, _, start = noisy_board
    cold, _ = _recorded_fits(monkeypatch, lambda: _fit_corners(img, start, BOARD))
    (px, py, im, w0, radius, taper, P0, warm, _, _), best_P, _, sens = cold[0]
    assert sens.shape == (len(P0), 2, 2) and np.all(np.isfinite(sens))
    fd = np.empty_like(sens)
    for c in range(2):
        q = []
        for sign in (1.0, -1.0):
            P = best_P.copy()  # from the fit: warm, the bends moved, to convergence
            P[:, 11 + c] += sign * 0.02 / radius**2
            out, cost, s2 = np.empty_like(P), np.empty(len(P)), np.empty((len(P), 2, 2))
            ck.fit_saddles(px, py, im, w0, radius, taper, P, True, 50, 1e-10, out, cost, s2)
            q.append(out[:, :2])
        fd[:, :, c] = (q[0] - q[1]) / (2 * 0.02 / radius[:, None] ** 2)
    assert np.abs(fd).max() > 1.0  # px per 1/px: the bends do move the corners
    assert np.abs(sens - fd).max() < 0.1 * np.abs(fd).max(), np.abs(sens - fd).max() / np.abs(fd).max()


def test_forstner_is_the_numpy_loop(noisy_board):
    img, t, start = noisy_board
    spacing = 20.0
    q = refine_corners(img, start, spacing)
    g = img.astype(np.float64)
    gx = cv2.Scharr(g, cv2.CV_64F, 1, 0) / 32.0
    gy = cv2.Scharr(g, cv2.CV_64F, 0, 1) / 32.0
    radius = max(2.0, min(0.6 * spacing, 30.0))
    ref = numpy_forstner(gx, gy, start, radius, 0.2 * spacing, 30, 1e-5)
    bad = ~np.all(np.isfinite(ref), axis=1) | (np.linalg.norm(ref - start, axis=1) > 0.25 * spacing)
    ref[bad] = start[bad]
    assert not bad.any()
    assert np.abs(q - ref).max() < SAME_PX
