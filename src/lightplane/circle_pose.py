"""The two poses of a circle of known radius from its image ellipse (paper §2.2.2, Eq. 7–15; SPEC §6).

The ellipse conic ``E`` (undistorted pixels, ``[u v 1] E [u v 1]ᵀ = 0``) and the
camera matrix ``K`` give the oblique elliptical cone through the optical centre
``W = Kᵀ E K`` (Eq. 7–9).  Diagonalising it, ``W = R Λ Rᵀ`` (Eq. 10–12), puts the
cone in a standard frame where a plane cuts it in a circle of radius ``r`` in
exactly two ways (Eq. 13–15); one of them is the target.

Also here: :func:`fit_conic`, the Halir–Flusser direct least-squares ellipse fit,
for rim points that are already undistorted.

>>> import numpy as np
>>> from lightplane.simulate.geometry import TargetPlacement, default_camera
>>> cam = default_camera(distortion=False)
>>> tp = TargetPlacement([20.0, -10.0, 450.0], [0.3, 0.2, -0.93], 50.0)
>>> a, b = circle_poses(tp.conic(cam), cam.K, 25.0)
>>> bool(min(np.linalg.norm(a.center - tp.center), np.linalg.norm(b.center - tp.center)) < 1e-9)
True
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import as_points
from .errors import LightplaneError

__all__ = ["CirclePose", "circle_poses", "fit_conic", "conic_residuals_px"]


@dataclass(frozen=True, eq=False)
class CirclePose:
    """A circle in the camera frame.

    Attributes
    ----------
    center : (3,) float64, mm.
    normal : (3,) float64, unit, towards the camera (``normal · center < 0``).
    radius_mm : float.
    """

    center: np.ndarray
    normal: np.ndarray
    radius_mm: float

    @property
    def d(self) -> float:
        """Offset of the target plane ``normal · X + d = 0`` (mm); ``d > 0`` with the normal towards the camera."""
        return -float(self.normal @ self.center)

    def to_dict(self) -> dict:
        return {"center_mm": self.center.tolist(), "normal": self.normal.tolist(), "radius_mm": self.radius_mm}


def _check_conic(conic: np.ndarray, name: str = "conic") -> np.ndarray:
    E = np.asarray(conic, dtype=np.float64)
    if E.shape != (3, 3) or not np.all(np.isfinite(E)):
        raise LightplaneError(f"{name} must be a finite 3x3 matrix, got shape {np.shape(conic)}")
    E = 0.5 * (E + E.T)
    nrm = np.linalg.norm(E)
    if nrm == 0:
        raise LightplaneError(f"{name} is zero")
    return E / nrm


def _ellipse_check(E: np.ndarray, name: str) -> None:
    """Raise unless the symmetric conic ``E`` is a real, non-degenerate ellipse.

    ``E`` must be well scaled (coordinates of order 1: normalised camera
    coordinates, or the conditioned frame of :func:`fit_conic`), normalised to
    Frobenius norm 1.  Ellipse: the 2x2 block is definite; real: the value at the
    centre has the opposite sign of the block's trace; non-degenerate: the three
    eigenvalues are not tiny (``|det| >= 1e-13``).
    """
    A = E[:2, :2]
    det2 = float(np.linalg.det(A))
    if det2 <= 1e-12 * float(np.sum(A * A)):
        raise LightplaneError(f"{name} is not an ellipse (a parabola or hyperbola: det of its 2x2 block is {det2:.3g})")
    det3 = float(np.linalg.det(E))
    # |det| = |λ1 λ2 λ3| <= min |λ| for Frobenius norm 1: a tiny det flags a (near) zero eigenvalue
    if abs(det3) < 1e-13:
        raise LightplaneError(f"{name} is a degenerate conic (det {det3:.3g})")
    centre_val = det3 / det2  # E33 - bᵀ A⁻¹ b
    if centre_val * np.trace(A) >= 0:
        raise LightplaneError(f"{name} is an imaginary ellipse (no real points)")


def circle_poses(conic: np.ndarray, K: np.ndarray, radius_mm: float) -> tuple[CirclePose, CirclePose]:
    """The two circle poses compatible with an image ellipse (paper Eq. 7–15, SPEC §6).

    Parameters
    ----------
    conic : (3, 3)
        Ellipse conic in UNDISTORTED pixels, ``[u v 1] E [u v 1]ᵀ = 0`` (any scale and sign).
    K : (3, 3)
        Camera matrix (pixels).
    radius_mm : float
        Circle radius (mm), > 0.

    Returns
    -------
    (CirclePose, CirclePose)
        Centres (mm) and unit normals towards the camera.  Exactly one is the true
        pose; with exact data it matches to ~1e-12 mm.  Seen face-on
        (``|λ1| ≈ |λ2|``) the two coincide.

    Method: ``W = Kᵀ E K`` (the cone, Eq. 9); ``W = R Λ Rᵀ`` with λ1, λ2 of one sign,
    ``|λ1| ≥ |λ2|``, λ3 of the other, ``R`` right-handed (Eq. 10–12); in that frame

        centre' = (±r sqrt(|λ3|(|λ1|-|λ2|) / (|λ1|(|λ1|+|λ3|))), 0, r sqrt(|λ1|(|λ2|+|λ3|) / (|λ3|(|λ1|+|λ3|))))
        normal' = (±sqrt((|λ1|-|λ2|) / (|λ1|+|λ3|)), 0, -sqrt((|λ2|+|λ3|) / (|λ1|+|λ3|)))

    (Eq. 13–15, same sign in both); ``C = R centre'``, ``N = R normal'``; both negated
    if ``C_z < 0``; ``N`` then oriented towards the camera.
    """
    E = _check_conic(conic)
    Km = np.asarray(K, dtype=np.float64)
    if Km.shape != (3, 3) or not np.all(np.isfinite(Km)) or abs(np.linalg.det(Km)) < 1e-12:
        raise LightplaneError(f"K must be a finite invertible 3x3 matrix, got shape {np.shape(K)}")
    try:
        r = float(radius_mm)
    except (TypeError, ValueError):
        raise LightplaneError(f"radius_mm must be a number, got {radius_mm!r}") from None
    if not (np.isfinite(r) and r > 0):
        raise LightplaneError(f"radius_mm must be positive, got {radius_mm}")
    W = Km.T @ E @ Km
    W = 0.5 * (W + W.T)
    W /= np.linalg.norm(W)
    # checked on the cone W (normalised camera coordinates: well scaled); for zero
    # skew its 2x2 block is diag(fx, fy) E₂ diag(fx, fy), so ellipse-ness is the same
    _ellipse_check(W, "conic")
    lam, V = np.linalg.eigh(W)
    pos = lam > 0
    if pos.sum() == 2:
        i3 = int(np.flatnonzero(~pos)[0])
    elif pos.sum() == 1:
        i3 = int(np.flatnonzero(pos)[0])
    else:
        raise LightplaneError("conic: the cone through the optical centre has no real points (eigenvalues of one sign)")
    i12 = [i for i in range(3) if i != i3]
    i1, i2 = sorted(i12, key=lambda i: -abs(lam[i]))
    l1, l2, l3 = abs(lam[i1]), abs(lam[i2]), abs(lam[i3])
    if min(l1, l2, l3) < 1e-14:
        raise LightplaneError("conic: degenerate cone (a zero eigenvalue)")
    R = np.column_stack([V[:, i1], V[:, i2], V[:, i3]])
    if np.linalg.det(R) < 0:
        R[:, 2] = -R[:, 2]
    dl = max(l1 - l2, 0.0)  # ≥ 0 by the ordering; clip rounding
    cx = r * np.sqrt(l3 * dl / (l1 * (l1 + l3)))
    cz = r * np.sqrt(l1 * (l2 + l3) / (l3 * (l1 + l3)))
    nx = np.sqrt(dl / (l1 + l3))
    nz = -np.sqrt((l2 + l3) / (l1 + l3))
    out = []
    for s in (1.0, -1.0):
        C = R @ np.array([s * cx, 0.0, cz])
        N = R @ np.array([s * nx, 0.0, nz])
        if C[2] < 0:
            C, N = -C, -N
        if N @ C > 0:
            N = -N
        N = N / np.linalg.norm(N)
        C.setflags(write=False)
        N.setflags(write=False)
        out.append(CirclePose(C, N, r))
    return out[0], out[1]


def fit_conic(uv: np.ndarray, *, name: str = "rim points") -> np.ndarray:
    """Direct least-squares ellipse fit (Halir & Flusser 1998) to ``(N, 2)`` points.

    Points are centred and scaled to unit RMS radius first (conditioning), then the
    fit is mapped back.  Returns the conic ``(3, 3)`` in the points' coordinates
    (for :func:`circle_poses`: undistorted pixels), symmetric, Frobenius norm 1,
    negative inside.  Raises LightplaneError (naming ``name``) for fewer than 5 or
    non-finite points, or when no ellipse fits (collinear points...).  The fit is
    ellipse-specific: points on some other curve still get an ellipse, so check
    :func:`conic_residuals_px` against the expected noise.
    """
    p = as_points(uv, 2, name)
    if p.shape[0] < 5:
        raise LightplaneError(f"{name}: need at least 5 points to fit an ellipse, got {p.shape[0]}")
    if not np.all(np.isfinite(p)):
        raise LightplaneError(f"{name}: contains NaN or infinite coordinates")
    m = p.mean(axis=0)
    q = p - m
    s = np.sqrt(np.mean(np.sum(q * q, axis=1)))
    if not s > 0:
        raise LightplaneError(f"{name}: all points coincide")
    q = q / s
    ev = np.linalg.eigvalsh(q.T @ q)  # squared singular values, ascending
    if ev[0] < 1e-6 * ev[1]:
        raise LightplaneError(f"{name}: the points are (nearly) collinear, not an ellipse")
    x, y = q[:, 0], q[:, 1]
    D = np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)])
    S = D.T @ D  # one product gives S1, S2, S3 of Halir & Flusser
    S1, S2, S3 = S[:3, :3], S[:3, 3:], S[3:, 3:]
    try:
        T = -np.linalg.solve(S3, S2.T)
    except np.linalg.LinAlgError:
        raise LightplaneError(f"{name}: degenerate point set (collinear?)") from None
    M = S1 + S2 @ T
    M = np.array([M[2] / 2.0, -M[1], M[0] / 2.0])  # C1⁻¹ M with C1 = [[0,0,2],[0,-1,0],[2,0,0]]
    w, v = np.linalg.eig(M)
    v = np.real(v)
    cond = 4.0 * v[0] * v[2] - v[1] ** 2
    ok = np.flatnonzero((cond > 0) & (np.abs(np.imag(w)) < 1e-9 * (1 + np.abs(np.real(w)))))
    if ok.size == 0:
        raise LightplaneError(f"{name}: the points do not lie on an ellipse")
    a1 = v[:, ok[np.argmin(np.abs(np.real(w[ok])))]]
    a2 = T @ a1
    A, B, C = a1
    D, E_, F = a2
    Cn = np.array([[A, B / 2, D / 2], [B / 2, C, E_ / 2], [D / 2, E_ / 2, F]])
    Cn /= np.linalg.norm(Cn)
    if not np.all(np.isfinite(Cn)):
        raise LightplaneError(f"{name}: ellipse fit failed")
    try:
        _ellipse_check(Cn, name)  # in the conditioned frame
    except LightplaneError:
        raise LightplaneError(f"{name}: the points do not lie on an ellipse") from None
    Tn = np.array([[1 / s, 0, -m[0] / s], [0, 1 / s, -m[1] / s], [0, 0, 1.0]])
    Cm = Tn.T @ Cn @ Tn
    Cm = 0.5 * (Cm + Cm.T)
    Cm /= np.linalg.norm(Cm)
    if Cm[0, 0] + Cm[1, 1] < 0:
        Cm = -Cm
    return Cm


def conic_residuals_px(conic: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Approximate geometric distances (px) of ``(N, 2)`` points to a conic (Sampson distance).

    ``|xᵀ C x| / (2 ‖(C x)[:2]‖)``; exact to first order for points near the curve.
    """
    C = _check_conic(conic)
    p = as_points(uv, 2, "uv")
    xh = np.column_stack([p, np.ones(len(p))])
    Cx = xh @ C
    val = np.sum(Cx * xh, axis=1)
    g = 2.0 * np.linalg.norm(Cx[:, :2], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.abs(val) / g
