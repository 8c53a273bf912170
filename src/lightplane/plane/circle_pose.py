"""The two poses of a circle of known radius from its image ellipse (paper §2.2.2, Eq. 7–15; docs/method.md §Circle pose).

The ellipse conic ``E`` (undistorted pixels, ``[u v 1] E [u v 1]ᵀ = 0``) and the
camera matrix ``K`` give the oblique elliptical cone through the optical centre
``W = Kᵀ E K`` (Eq. 7–9).  Diagonalising it, ``W = R Λ Rᵀ`` (Eq. 10–12), puts the
cone in a standard frame where a plane cuts it in a circle of radius ``r`` in
exactly two ways (Eq. 13–15); one of them is the target.

Also here: :func:`fit_rim_conic`, the Halir–Flusser direct least-squares ellipse fit
(:func:`lightplane.core.geometry.fit_conic`) for rim points that are already undistorted,
raising :class:`LightplaneError` when no ellipse fits.

>>> import numpy as np
>>> from lightplane.simulate.scene import TargetPlacement, default_camera
>>> cam = default_camera(distortion=False)
>>> tp = TargetPlacement([20.0, -10.0, 450.0], [0.3, 0.2, -0.93], 50.0)
>>> a, b = circle_poses(tp.conic(cam), cam.K, 25.0)
>>> bool(min(np.linalg.norm(a.center - tp.center), np.linalg.norm(b.center - tp.center)) < 1e-9)
True
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lightplane.camera.model import as_points
from lightplane.core.errors import LightplaneError
from lightplane.core.geometry import Failure, ellipse_problems, fit_conic, sampson_distance

__all__ = ["CirclePose", "circle_poses", "circle_poses_batch", "fit_rim_conic", "conic_residuals_px"]


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
    """Raise unless the symmetric conic ``E`` (3, 3) is a real, non-degenerate ellipse (see
    :func:`ellipse_problems`)."""
    why = ellipse_problems(E[None])[0]
    if why is not None:
        raise LightplaneError(f"{name} {why}")


def circle_poses_batch(conics: np.ndarray, K: np.ndarray, radius_mm: float) -> tuple[np.ndarray, np.ndarray, list]:
    """:func:`circle_poses` for many conics at once (vectorised; for speed).

    ``conics`` (n, 3, 3) in undistorted pixels.  Returns ``centers (n, 2, 3)`` mm,
    ``normals (n, 2, 3)`` and a list of n problems (None, or why item k is no ellipse);
    rows with a problem are NaN.  ``K`` and ``radius_mm`` are assumed valid.
    """
    E = np.asarray(conics, dtype=np.float64)
    E = 0.5 * (E + np.swapaxes(E, 1, 2))
    W = K.T @ E @ K
    W = W / np.linalg.norm(W, axis=(1, 2))[:, None, None]
    problems = ellipse_problems(W)
    lam, V = np.linalg.eigh(W)  # ascending
    npos = np.sum(lam > 0, axis=1)
    # two positive: λ0 < 0 < λ1 <= λ2 -> (e1, e2, e3) = (v2, v1, v0);
    # one positive: λ0 <= λ1 < 0 < λ2 -> (v0, v1, v2)
    two = npos == 2
    order = np.where(two[:, None], [2, 1, 0], [0, 1, 2])
    al = np.abs(np.take_along_axis(lam, order, axis=1))
    R = np.take_along_axis(V, order[:, None, :], axis=2)
    flip = np.linalg.det(R) < 0
    R[flip, :, 2] *= -1.0
    l1, l2, l3 = al[:, 0], al[:, 1], al[:, 2]
    r = float(radius_mm)
    dl = np.maximum(l1 - l2, 0.0)  # >= 0 by the ordering; clip rounding
    with np.errstate(divide="ignore", invalid="ignore"):
        cx = r * np.sqrt(l3 * dl / (l1 * (l1 + l3)))
        cz = r * np.sqrt(l1 * (l2 + l3) / (l3 * (l1 + l3)))
        nx = np.sqrt(dl / (l1 + l3))
        nz = -np.sqrt((l2 + l3) / (l1 + l3))
    centers = np.empty((len(E), 2, 3))
    normals = np.empty((len(E), 2, 3))
    zero = np.zeros_like(cx)
    for j, sgn in enumerate((1.0, -1.0)):
        C = np.einsum("nij,nj->ni", R, np.column_stack([sgn * cx, zero, cz]))
        N = np.einsum("nij,nj->ni", R, np.column_stack([sgn * nx, zero, nz]))
        neg = C[:, 2] < 0  # eigenvector signs are arbitrary
        C[neg] *= -1.0
        N[neg] *= -1.0
        away = np.sum(N * C, axis=1) > 0  # docs/conventions.md §Target pose: towards the camera
        N[away] *= -1.0
        N /= np.linalg.norm(N, axis=1, keepdims=True)
        centers[:, j] = C
        normals[:, j] = N
    for k in range(len(E)):
        if problems[k] is None and not (npos[k] in (1, 2) and np.min(al[k]) > 1e-14):
            problems[k] = "has no real cone through the optical centre (eigenvalues of one sign or zero)"
        if problems[k] is not None:
            centers[k] = np.nan
            normals[k] = np.nan
    return centers, normals, problems


def circle_poses(conic: np.ndarray, K: np.ndarray, radius_mm: float) -> tuple[CirclePose, CirclePose]:
    """The two circle poses compatible with an image ellipse (paper Eq. 7–15, docs/method.md §Circle pose).

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
    centers, normals, problems = circle_poses_batch(E[None], Km, r)
    if problems[0] is not None:
        raise LightplaneError(f"conic {problems[0]}")
    out = []
    for j in range(2):
        C, N = centers[0, j].copy(), normals[0, j].copy()
        C.setflags(write=False)
        N.setflags(write=False)
        out.append(CirclePose(C, N, r))
    return out[0], out[1]


def fit_rim_conic(uv: np.ndarray, *, name: str = "rim points") -> np.ndarray:
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
    C = fit_conic(p)
    if isinstance(C, Failure):
        raise LightplaneError(f"{name}: {C.reason}")
    return C


def conic_residuals_px(conic: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Approximate geometric distances (px) of ``(N, 2)`` points to a conic (Sampson distance).

    ``|xᵀ C x| / (2 ‖(C x)[:2]‖)``; exact to first order for points near the curve
    (:func:`lightplane.core.geometry.sampson_distance`, unsigned, of the normalised conic).
    """
    return sampson_distance(_check_conic(conic), as_points(uv, 2, "uv"), signed=False)
