"""Lens distortion models: OpenCV's plumb bob, rational, thin prism, tilted sensor, and fisheye.

One implementation of every model (docs/conventions.md §Lens model), used by :class:`lightplane.Camera`
(on NumPy arrays) and by the renderer (compiled by numba on scalars): :func:`distort_jac` is
written with arithmetic and ``np.sqrt`` / ``np.arctan`` only, so the same source runs both ways.

Models (the distortion vector as OpenCV orders it):

============  ===  ==========================================================
name          n    coefficients
============  ===  ==========================================================
plumb_bob     5    k1 k2 p1 p2 k3 (a 4-vector is read with k3 = 0)
rational      8    k1 k2 p1 p2 k3 k4 k5 k6
thin_prism    12   ... s1 s2 s3 s4
tilted        14   ... tauX tauY (radians; the sensor tilted against the lens, Scheimpflug)
fisheye       4    k1 k2 k3 k4 (``cv2.fisheye``: equidistant, θ_d = θ (1 + k1 θ² + ... + k4 θ⁸))
============  ===  ==========================================================

For normalised undistorted ``(x, y)`` (the ray ``(x, y, 1)``), ``r² = x² + y²``, the standard
models give::

    x'' = x (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶) + 2 p1 x y + p2 (r² + 2 x²) + s1 r² + s2 r⁴
    y'' = y (...)/(...) + p1 (r² + 2 y²) + 2 p2 x y + s3 r² + s4 r⁴
    [x_d, y_d, 1] ∝ T(tauX, tauY) [x'', y'', 1]      (identity T unless tilted)

and fisheye ``x_d = x θ_d / r`` with ``θ = atan r``.  Pixels are then ``K [x_d, y_d, 1]``
(with K's skew ``K[0, 1]``, which OpenCV's own projection ignores).
"""

from __future__ import annotations

import numpy as np

from lightplane.core.errors import LightplaneError

__all__ = ["MODELS", "ROS_MODELS", "COEFF_NAMES", "coeff_names", "undistort_guess", "lens_params", "model_for", "distort_jac", "tilt_matrix", "N_PARAMS"]

#: model name -> number of coefficients
MODELS = {"plumb_bob": 5, "rational": 8, "thin_prism": 12, "tilted": 14, "fisheye": 4}
_CODES = {"plumb_bob": 0.0, "rational": 1.0, "thin_prism": 2.0, "tilted": 3.0, "fisheye": 4.0}
#: our model -> ROS camera_info ``distortion_model``
ROS_MODELS = {"plumb_bob": "plumb_bob", "rational": "rational_polynomial", "thin_prism": "rational_polynomial",
              "tilted": "rational_polynomial", "fisheye": "equidistant"}
#: names of the coefficients of the standard models, in OpenCV's order (a model uses the first n)
COEFF_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4", "taux", "tauy")


def coeff_names(model: str) -> tuple[str, ...]:
    """The names of a model's distortion coefficients, in their order."""
    return ("k1", "k2", "k3", "k4") if model == "fisheye" else COEFF_NAMES[:MODELS[model]]


#: the parameters packed for :func:`distort_jac`: model code, 12 coefficients, the 3x3 tilt matrix
N_PARAMS = 22
_BY_LENGTH = {4: "plumb_bob", 5: "plumb_bob", 8: "rational", 12: "thin_prism", 14: "tilted"}


def model_for(dist: np.ndarray, model: str | None) -> tuple[str, np.ndarray]:
    """Check a distortion vector against its model (inferred from the length when None): ``(model, dist)``
    with a plumb-bob 4-vector padded to 5.  A wrong length or an unknown model raises, in one line."""
    d = np.asarray(dist, dtype=np.float64).ravel()
    if model is None:
        if d.size not in _BY_LENGTH:
            raise LightplaneError(f"dist must hold 4, 5, 8, 12 or 14 coefficients (OpenCV's models), got {d.size}")
        model = _BY_LENGTH[d.size]
    if model not in MODELS:
        raise LightplaneError(f"unknown lens model {model!r} (known: {', '.join(MODELS)})")
    n = MODELS[model]
    if model == "plumb_bob" and d.size == 4:
        d = np.append(d, 0.0)
    if d.size != n:
        raise LightplaneError(f"lens model {model} needs {n} distortion coefficients, got {d.size}")
    if not np.all(np.isfinite(d)):
        raise LightplaneError(f"dist: coefficients must be finite, got {d.tolist()}")
    return model, d


def tilt_matrix(tau_x: float, tau_y: float) -> np.ndarray:
    """OpenCV's tilted-sensor matrix (computeTiltProjectionMatrix): ``[x_d, y_d, 1] ∝ T [x'', y'', 1]``."""
    cx, sx, cy, sy = np.cos(tau_x), np.sin(tau_x), np.cos(tau_y), np.sin(tau_y)
    rx = np.array([[1, 0, 0], [0, cx, sx], [0, -sx, cx]])
    ry = np.array([[cy, 0, -sy], [0, 1, 0], [sy, 0, cy]])
    r = ry @ rx
    proj = np.array([[r[2, 2], 0, -r[0, 2]], [0, r[2, 2], -r[1, 2]], [0, 0, 1]])
    return proj @ r


def lens_params(model: str, dist: np.ndarray) -> np.ndarray:
    """The packed ``(N_PARAMS,)`` parameters :func:`distort_jac` takes."""
    p = np.zeros(N_PARAMS)
    p[0] = _CODES[model]
    d = np.asarray(dist, dtype=np.float64).ravel()
    if model == "fisheye":
        p[1:5] = d
    else:
        p[1:1 + min(d.size, 12)] = d[:12]
    t = tilt_matrix(d[12], d[13]) if model == "tilted" else np.eye(3)
    p[13:22] = t.ravel()
    return p


def distort_jac(x, y, p):
    """Distorted normalised ``(x_d, y_d)`` of undistorted ``(x, y)`` and the Jacobian
    ``(j11, j12, j21, j22) = ∂(x_d, y_d)/∂(x, y)``; ``p`` from :func:`lens_params`.

    ``x``, ``y``: NumPy arrays or (compiled by numba) floats."""
    r2 = x * x + y * y
    if p[0] == 4.0:  # fisheye (equidistant)
        small = r2 < 1e-16  # r < 1e-8: the limit r -> 0 (scale 1, no radial derivative)
        rs = np.sqrt(r2) + small
        th = np.arctan(rs)
        t2 = th * th
        k1, k2, k3, k4 = p[1], p[2], p[3], p[4]
        poly = 1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))
        dpoly = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))  # d(θ poly)/dθ
        thd = th * poly
        c = thd / rs
        c = c + small * (1.0 - c)
        g = (dpoly / (1.0 + rs * rs) * rs - thd) / (rs * rs * rs) * (1.0 - small)  # (dc/dr) / r
        xd = x * c
        yd = y * c
        j12 = g * x * y
        return xd, yd, c + g * x * x, j12, j12, c + g * y * y
    k1, k2, p1, p2, k3, k4, k5, k6 = p[1], p[2], p[3], p[4], p[5], p[6], p[7], p[8]
    s1, s2, s3, s4 = p[9], p[10], p[11], p[12]
    num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dnum = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    # The rational and thin-prism terms are skipped where their coefficients are all zero (every
    # plumb-bob camera): the values are the same to the bit (a denominator of exactly 1, terms of
    # exactly 0 added last), and the renderer's sampler, which calls this for every sub-pixel
    # sample, saves its two divisions.
    if k4 == 0.0 and k5 == 0.0 and k6 == 0.0:
        rad = num
        drad = dnum
    else:
        den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
        dden = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2)
        rad = num / den
        drad = (dnum * den - num * dden) / (den * den)  # d rad / d r²
    a = x * rad + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    b = y * rad + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    a11 = rad + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x
    a12 = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
    a21 = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
    a22 = rad + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x
    if s1 != 0.0 or s2 != 0.0 or s3 != 0.0 or s4 != 0.0:
        dpx = s1 + 2.0 * s2 * r2  # d(prism x) / d r²
        dpy = s3 + 2.0 * s4 * r2
        a = a + r2 * (s1 + s2 * r2)
        b = b + r2 * (s3 + s4 * r2)
        a11 = a11 + 2.0 * x * dpx
        a12 = a12 + 2.0 * y * dpx
        a21 = a21 + 2.0 * x * dpy
        a22 = a22 + 2.0 * y * dpy
    if p[0] != 3.0:
        return a, b, a11, a12, a21, a22
    m0, m1, m2, m3, m4, m5, m6, m7, m8 = p[13], p[14], p[15], p[16], p[17], p[18], p[19], p[20], p[21]
    w = m6 * a + m7 * b + m8
    xd = (m0 * a + m1 * b + m2) / w
    yd = (m3 * a + m4 * b + m5) / w
    t11 = (m0 - xd * m6) / w
    t12 = (m1 - xd * m7) / w
    t21 = (m3 - yd * m6) / w
    t22 = (m4 - yd * m7) / w
    return (xd, yd, t11 * a11 + t12 * a21, t11 * a12 + t12 * a22, t21 * a11 + t22 * a21, t21 * a12 + t22 * a22)


def undistort_guess(xd, yd, p):
    """A start for Newton's undistortion: the distorted point itself, or for fisheye the
    equidistant inverse ``r = tan θ_d`` (θ_d capped at 1.4 rad); arrays or (numba) floats."""
    if p[0] == 4.0:
        r2 = xd * xd + yd * yd
        small = r2 < 1e-16
        rd = np.sqrt(r2) + small
        rc = rd - (rd > 1.4) * (rd - 1.4)
        s = np.tan(rc) / rd
        s = s + small * (1.0 - s)
        return xd * s, yd * s
    return xd + 0.0, yd + 0.0
