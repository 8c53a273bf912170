"""Numba kernels behind :meth:`lightplane.camera.model.Camera.undistort_points` (and its variant from a
close start, ``Camera._undistort_near``): Newton's undistortion of each point on the exact lens
model (:func:`lightplane.camera.lens.distort_jac`, compiled on scalars as the renderer does), a point at
a time.  The numpy version iterated all points until the slowest converged, ~40 array operations
per step: 6000 points took ~2 ms, this ~0.5 ms.  The values are the same to an ulp or two (a point
stops at its own convergence instead of the slowest one's), and a point's value no longer depends
on which points are undistorted with it.
"""

from __future__ import annotations

import math

from lightplane.core.jit import njit_cached

from lightplane.camera.lens import distort_jac, undistort_guess  # noqa: E402

distort_jac_kernel = njit_cached(nogil=True, inline="always", error_model="numpy")(distort_jac)
_undistort_guess = njit_cached(nogil=True, inline="always", error_model="numpy")(undistort_guess)


@njit_cached(nogil=True, inline="always", error_model="numpy")
def newton_step_kernel(x, y, tx, ty, lens):  # pragma: no cover - compiled
    """One Newton step towards the undistorted point whose distortion is ``(tx, ty)``, from ``(x, y)``:
    the new point, the step taken ``(dx, dy)`` and the distortion's Jacobian at ``(x, y)``."""
    xd, yd, j11, j12, j21, j22 = distort_jac_kernel(x, y, lens)
    f0 = xd - tx
    f1 = yd - ty
    det = j11 * j22 - j12 * j21
    dx = (j22 * f0 - j12 * f1) / det
    dy = (-j21 * f0 + j11 * f1) / det
    return x - dx, y - dy, dx, dy, j11, j12, j21, j22


@njit_cached(nogil=True, error_model="numpy")
def newton_undistort(tx, ty, lens, K, u, v, iters, xy, err):  # pragma: no cover - compiled
    """For each point ``k``: the normalised undistorted ``xy[k]`` whose distortion is the normalised
    distorted ``(tx[k], ty[k])`` (K⁻¹ of the pixel ``(u[k], v[k])``), by Newton from
    :func:`undistort_guess` until the step is at most 1e-16 (``iters`` steps at most), and ``err[k]``
    the distance (px) between its projection and the pixel (NaN / inf where it failed)."""
    for k in range(tx.shape[0]):
        x, y = _undistort_guess(tx[k], ty[k], lens)
        for _ in range(iters):
            x, y, dx, dy, _, _, _, _ = newton_step_kernel(x, y, tx[k], ty[k], lens)
            if not max(abs(dx), abs(dy)) > 1e-16:
                break
        xy[k, 0] = x
        xy[k, 1] = y
        xd, yd, _, _, _, _ = distort_jac_kernel(x, y, lens)
        du = K[0, 0] * xd + K[0, 1] * yd + K[0, 2] - u[k]
        dv = K[1, 1] * yd + K[1, 2] - v[k]
        err[k] = math.sqrt(du * du + dv * dv)


@njit_cached(nogil=True, error_model="numpy")
def newton_undistort_from(tx, ty, sx, sy, lens, tol, iters, xy, jac, done):  # pragma: no cover - compiled
    """:meth:`lightplane.camera.model.Camera._undistort_near`'s Newton, a point at a time: from the start
    ``(sx[k], sy[k])`` until a step is below ``tol`` (normalised; ``iters`` steps at most), ``xy[k]``
    the result, ``jac[:, k]`` the distortion's Jacobian (j11, j12, j21, j22) at the last step's start,
    ``done[k]`` whether it got there (False: not converged, or not finite)."""
    for k in range(tx.shape[0]):
        x, y = sx[k], sy[k]
        ok = False
        for _ in range(iters):
            x, y, dx, dy, j11, j12, j21, j22 = newton_step_kernel(x, y, tx[k], ty[k], lens)
            jac[0, k] = j11
            jac[1, k] = j12
            jac[2, k] = j21
            jac[3, k] = j22
            if max(abs(dx), abs(dy)) < tol:
                ok = True
                break
        xy[k, 0] = x
        xy[k, 1] = y
        done[k] = ok and math.isfinite(x) and math.isfinite(y)
