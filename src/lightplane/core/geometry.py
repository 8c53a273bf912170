"""Low-level geometry primitives shared by the whole package (numpy only).

One implementation each of the small fits and distances that the calibration,
measurement, baselines and ellipse code all need:

- :func:`robust_sigma` — the normal-consistent MAD, ``1.4826 · median|x − median x|``
  (or about zero, for residuals known to be centred);
- :func:`tls_line` — total-least-squares 2-D line; :func:`robust_line` — the same,
  refitted on the points within ``k_mad`` robust sigmas;
- :func:`fit_plane_tls` — orthogonal (weighted) least-squares plane in 3-D;
- :func:`ray_plane` — rays from the camera centre meeting a plane;
- :func:`fit_conic` / :func:`fit_conics` — Halir–Flusser direct least-squares ellipse fit
  (one point set, or many with the eigen-steps vectorised);
- :func:`sampson_distance` — first-order geometric distance of 2-D points to a conic.

Failure convention: a primitive that can fail returns its result, or a
:class:`Failure` — falsy, carrying its ``reason`` — so that inner loops need no
exceptions; callers that raise build their message from the reason.  Results that
are arrays have no truth value, so test ``isinstance(r, Failure)`` there.  Bad shapes (a programming error, not bad data) raise
:class:`ValueError`.

(The simulator's scene geometry is :mod:`lightplane.simulate.scene`, unrelated.)
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Failure", "MAD_TO_SIGMA", "robust_sigma", "tls_line", "robust_line", "plane_scatter", "fit_plane_tls", "ray_plane",
           "sampson_distance", "fit_conic", "fit_conics", "default_workers"]

#: 1 / Φ⁻¹(3/4) to the precision the package has always used: MAD → σ for normal data.
MAD_TO_SIGMA = 1.4826


@dataclass(frozen=True)
class Failure:
    """A failed primitive: falsy, with the reason (a short phrase, for messages)."""

    reason: str

    def __bool__(self) -> bool:
        return False


def _points(p, dim: int, name: str) -> np.ndarray:
    a = np.asarray(p, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != dim:
        raise ValueError(f"{name} must be an (N, {dim}) array, got shape {a.shape}")
    return a


def robust_sigma(x, *, center: bool = True, upper_median: bool = False) -> float:
    """Normal-consistent robust scale of ``x`` (any shape): ``1.4826 · median|x − median(x)|``.

    ``center=False`` takes the deviations about zero instead (residuals that are
    centred by construction, or already absolute distances): ``1.4826 · median|x|``.
    ``upper_median=True`` (with ``center=False``) takes the upper middle order statistic
    instead of the median (one ``np.partition``, no sort; equal for odd sizes).
    NaN for an empty ``x`` (numpy's median of nothing); NaNs in ``x`` propagate.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.size == 0:
        return float("nan")
    if upper_median:
        if center:
            raise ValueError("upper_median=True needs center=False")
        a = np.abs(x).ravel()
        return float(MAD_TO_SIGMA * np.partition(a, a.size // 2)[a.size // 2])
    if center:
        return float(MAD_TO_SIGMA * np.median(np.abs(x - np.median(x))))
    return float(MAD_TO_SIGMA * np.median(np.abs(x)))


def tls_line(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Total-least-squares line through (K, 2) points: ``(centroid (2,), unit direction (2,), unit normal (2,))``.

    Direction and normal are the right singular vectors of the centred points (largest
    and smallest spread); their signs are LAPACK's.  ValueError for a bad shape or fewer
    than 2 points.
    """
    if p.ndim != 2 or p.shape[1] != 2 or len(p) < 2:
        raise ValueError(f"tls_line needs an (N >= 2, 2) array, got shape {np.shape(p)}")
    m = p.mean(axis=0)
    vt = np.linalg.svd(p - m, full_matrices=False)[2]
    return m, vt[0], vt[1]


def robust_line(p: np.ndarray, *, refits: int = 4, k_mad: float = 4.0, min_tol: float = 0.0,
                rel_tol: float = 0.0, center: bool = False, upper_median: bool = False,
                min_points: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Total-least-squares line through (K, 2) points with MAD rejection.

    Up to ``refits`` times: :func:`tls_line` on the inliers, then the new inliers are the
    points within ``max(k_mad · σ, min_tol, rel_tol · (1 + max|centroid|))`` of it, σ the
    :func:`robust_sigma` of the inliers' distances (signed and ``center``-ed, or absolute
    about zero; ``upper_median`` as there).  Stops early when the inliers no longer change
    or would be fewer than ``min_points`` (then the previous inliers stay).  Starts from the
    finite points.  Returns ``(centroid, direction, normal, inliers (K,) bool)``; the line
    is the last one fitted, on the inliers before the last update.  ValueError for a bad
    shape or fewer than 2 finite points.
    """
    p = _points(p, 2, "points")
    inl = np.all(np.isfinite(p), axis=1)
    m = d = n = None
    for _ in range(max(int(refits), 1)):
        m, d, n = tls_line(p[inl])
        r = (p - m) @ n
        ri = r[inl]
        s = robust_sigma(ri, center=True) if center else robust_sigma(np.abs(ri), center=False,
                                                                        upper_median=upper_median)
        new = np.abs(r) <= max(k_mad * s, min_tol, rel_tol * (1.0 + np.abs(m).max()))
        if new.sum() < min_points or np.array_equal(new, inl):
            break
        inl = new
    assert m is not None and d is not None and n is not None  # the loop runs at least once
    return m, d, n, inl


def plane_scatter(p: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eigen-decomposition of the centred (weighted) scatter matrix of (N, 3) points.

    Returns ``(centroid (3,), eigenvalues (3,) ascending, eigenvectors (3, 3) as
    columns)``: column 0 is the total-least-squares plane's normal, its eigenvalue the
    weighted sum of squared distances (the other two give the normal's covariance).
    ValueError for a bad shape or fewer than 3 points.
    """
    p = _points(p, 3, "points")
    if len(p) < 3:
        raise ValueError(f"a plane fit needs at least 3 points, got {len(p)}")
    w = np.ones(len(p)) if weights is None else np.asarray(weights, dtype=np.float64)
    c = (w @ p) / w.sum()
    q = p - c
    S = (q * w[:, None]).T @ q
    lam, V = np.linalg.eigh(S)
    return c, lam, V


def fit_plane_tls(p: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, float, float]:
    """Orthogonal (weighted) least-squares plane through (N, 3) points.

    Returns ``(normal (3,), d, smallest eigenvalue of the weighted scatter)``: the
    normal is the eigenvector of the smallest eigenvalue of the centred scatter
    matrix (:func:`plane_scatter`); the eigenvalue is the weighted sum of squared
    distances.  ValueError for a bad shape or fewer than 3 points.
    """
    c, lam, V = plane_scatter(p, weights)
    n = V[:, 0]
    return n, -float(n @ c), float(max(lam[0], 0.0))


def ray_plane(xy: np.ndarray, normal: np.ndarray, point: np.ndarray) -> np.ndarray:
    """Intersect rays ``(x, y, 1)`` (normalised, (K, 2)) with the plane through ``point`` with ``normal``.

    Returns (K, 3) points in the camera frame; NaN for rays (nearly) parallel to the
    plane (``|ray · normal| < 1e-9``) or meeting it behind the camera.
    """
    xy = _points(xy, 2, "xy")
    xh = np.column_stack([xy, np.ones(len(xy))])
    den = xh @ normal
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (normal @ point) / den
    s[~(s > 0) | (np.abs(den) < 1e-9)] = np.nan
    return xh * s[:, None]


def sampson_distance(C: np.ndarray, uv: np.ndarray, *, signed: bool = True) -> np.ndarray:
    """Sampson (first-order geometric) distance (N,) of points ``uv`` (N, 2) to the conic ``C`` (3, 3).

    ``xᵀ C x / (2 ‖(C x)[:2]‖)`` — exact to first order for points near the curve; in
    the units of ``uv``.  Signed (the sign of the conic's value; negative inside for a
    conic that is negative inside) unless ``signed=False``.  Where the gradient
    vanishes (a centre) the distance is ``value / 1e-300``: huge, or 0 on the curve.
    """
    uv = _points(uv, 2, "uv")
    if np.shape(C) != (3, 3):
        raise ValueError(f"the conic must be a (3, 3) array, got shape {np.shape(C)}")
    return sampson_distance_unchecked(C, uv, signed)


def sampson_distance_unchecked(C: np.ndarray, uv: np.ndarray, signed: bool = True) -> np.ndarray:
    """:func:`sampson_distance` without the input checks: ``C`` a (3, 3) and ``uv`` an (N, 2)
    float64 array (internal hot loops that built them)."""
    X = np.column_stack([uv, np.ones(len(uv))])
    CX = X @ C
    alg = CX[:, 0] * uv[:, 0] + CX[:, 1] * uv[:, 1] + CX[:, 2]  # xᵀ C x, summed in np.sum's order
    g = 2 * np.hypot(CX[:, 0], CX[:, 1])
    d = alg / np.maximum(g, 1e-300)
    return d if signed else np.abs(d)


# ------------------------------------------------------------------ conics
def ellipse_problems(E: np.ndarray) -> list[str | None]:
    """For (n, 3, 3) symmetric conics (well scaled, Frobenius norm 1): per item None if a real,
    non-degenerate ellipse, else the reason (str).

    Ellipse: the 2x2 block is definite; non-degenerate: ``|det| >= 1e-13`` (for norm 1,
    ``|det| = |λ1 λ2 λ3| <= min |λ|``); real: the value at the centre
    (``det / det₂ = E33 - bᵀ A⁻¹ b``) has the opposite sign of the block's trace.  ``E``
    must be well scaled (normalised camera coordinates, or :func:`fit_conic`'s
    conditioned frame).
    """
    A = E[:, :2, :2]
    det2 = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
    det3 = np.linalg.det(E)
    tr = A[:, 0, 0] + A[:, 1, 1]
    not_ellipse = ~(det2 > 1e-12 * np.add.reduce(A * A, axis=(1, 2)))
    degenerate = ~(np.abs(det3) >= 1e-13)
    with np.errstate(divide="ignore", invalid="ignore"):
        imaginary = (det3 / det2) * tr >= 0
    if not (not_ellipse | degenerate | imaginary).any():
        return [None] * len(E)
    out: list[str | None] = []
    for k in range(len(E)):
        if not_ellipse[k]:
            out.append(f"is not an ellipse (a parabola or hyperbola: det of its 2x2 block is {det2[k]:.3g})")
        elif degenerate[k]:
            out.append(f"is a degenerate conic (det {det3[k]:.3g})")
        elif imaginary[k]:
            out.append("is an imaginary ellipse (no real points)")
        else:
            out.append(None)
    return out


def fit_conic(uv: np.ndarray, weights: np.ndarray | None = None) -> "np.ndarray | Failure":
    """Direct least-squares ellipse fit (Halir & Flusser 1998) to ``(N, 2)`` points.

    Points are centred and scaled to unit RMS radius first (conditioning), then the
    fit is mapped back.  Returns the conic ``(3, 3)`` in the points' coordinates,
    symmetric, Frobenius norm 1, negative inside (positive trace of the 2x2 block), or a
    :class:`Failure` for fewer than 5 or non-finite points, or when no real ellipse fits
    (collinear points...).  ``weights`` (N,), optional, weigh the squared algebraic
    residuals.  The fit is ellipse-specific: points on some other curve still get an
    ellipse, so check :func:`sampson_distance` against the expected noise.
    ValueError for a bad shape.

    Reference: R. Halir, J. Flusser, "Numerically stable direct least squares fitting of
    ellipses", WSCG 1998 (the constraint 4AC - B^2 = 1 of Fitzgibbon et al.).
    """
    p = _points(uv, 2, "uv")
    if weights is not None:
        weights = np.asarray(weights, dtype=np.float64)
        if weights.shape != (len(p),):
            raise ValueError(f"weights must be ({len(p)},), got shape {weights.shape}")
    conics, problems = fit_conics([p], None if weights is None else [weights])
    return Failure(problems[0]) if problems[0] is not None else conics[0]


# C1⁻¹ M of Halir & Flusser as a row gather and scale; the conic matrix from its six coefficients
_C1_INV_ROWS = np.array([2, 1, 0])
_C1_INV_SCALE = np.array([0.5, -1.0, 0.5])[:, None]
_CONIC_FROM_COEFFS = np.array([[0, 1, 3], [1, 2, 4], [3, 4, 5]])
_CONIC_COEFF_SCALE = np.array([[1.0, 0.5, 0.5], [0.5, 1.0, 0.5], [0.5, 0.5, 1.0]])


def fit_conics(point_sets, weights=None) -> tuple[np.ndarray, list]:
    """:func:`fit_conic` for several point sets at once (the eigen-steps vectorised).

    ``point_sets``: sequence of (N_i, 2) float arrays; ``weights``: None or a sequence of
    (N_i,) non-negative weights (of each point's squared algebraic residual).  Returns
    ``conics (n, 3, 3)`` (NaN where the fit failed) and a list of n problems (None, or why not).
    """
    n = len(point_sets)
    S_all, Tn_all, problems = _conditioned_scatters(point_sets, weights)
    good_idx = [k for k in range(n) if problems[k] is None]
    conics = np.full((n, 3, 3), np.nan)
    if not good_idx:
        return conics, problems
    if len(good_idx) == n:
        S, Tn = S_all, Tn_all
    else:
        S, Tn = S_all[good_idx], Tn_all[good_idx]
    Cm, ok3, fitted = _direct_ellipse_fits(S, Tn)
    for j, k in enumerate(good_idx):
        if not ok3[j]:
            problems[k] = "degenerate point set (collinear?)"
        elif not fitted[j]:
            problems[k] = "the points do not lie on an ellipse"
        else:
            conics[k] = Cm[j]
    return conics, problems


def _conditioned_scatters(point_sets, weights) -> tuple[np.ndarray, np.ndarray, list]:
    """Per point set: the scatter matrix ``Dᵀ D`` (6, 6) of Halir & Flusser's design matrix in the
    conditioned frame (centred, unit RMS radius), the conditioning transform (3, 3) and the
    problem (None, or why the set cannot be fitted: too few, non-finite, coincident or
    collinear points); zero rows where there is a problem."""
    n = len(point_sets)
    problems: list = [None] * n
    S_all = np.zeros((n, 6, 6))
    Tn_all = np.zeros((n, 3, 3))
    Tn_all[:, 2, 2] = 1.0
    for k, p in enumerate(point_sets):
        if p.shape[0] < 5:
            problems[k] = f"need at least 5 points to fit an ellipse, got {p.shape[0]}"
            continue
        if not np.isfinite(p).all():
            problems[k] = "contains NaN or infinite coordinates"
            continue
        m = (np.ones(len(p)) @ p) / len(p)  # the centroid (a strided mean(axis=0) is slower)
        q = p - m
        (sxx, sxy), (_, syy) = (q.T @ q).tolist()  # the scatter
        s = math.sqrt((sxx + syy) / len(q))  # RMS radius
        if not s > 0:
            problems[k] = "all points coincide"
            continue
        # the scatter's eigenvalues, ascending, in closed form (the ratio does not depend on the scale)
        half_gap = math.hypot(0.5 * (sxx - syy), sxy)
        if 0.5 * (sxx + syy) - half_gap < 1e-6 * (0.5 * (sxx + syy) + half_gap):
            problems[k] = "the points are (nearly) collinear, not an ellipse"
            continue
        q = q / s
        x, y = q[:, 0], q[:, 1]
        D = np.empty((len(q), 6))
        np.multiply(x, x, out=D[:, 0])
        np.multiply(x, y, out=D[:, 1])
        np.multiply(y, y, out=D[:, 2])
        D[:, 3:5] = q
        D[:, 5] = 1.0
        if weights is None or weights[k] is None:
            S_all[k] = D.T @ D  # one product gives S1, S2, S3 of Halir & Flusser
        else:
            S_all[k] = (D * np.asarray(weights[k], dtype=np.float64)[:, None]).T @ D
        m0, m1 = m.tolist()
        Tn_all[k, 0, 0] = Tn_all[k, 1, 1] = 1 / s
        Tn_all[k, 0, 2] = -m0 / s
        Tn_all[k, 1, 2] = -m1 / s
    return S_all, Tn_all, problems


def _direct_ellipse_fits(S: np.ndarray, Tn: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Halir & Flusser's eigen-step for g scatter matrices ``S`` (g, 6, 6) of conditioned frames ``Tn``
    (g, 3, 3): the conics (g, 3, 3) mapped back to the points' frame (Frobenius norm 1, positive
    trace of the 2x2 block), whether ``S3`` was invertible (g,) and whether a real ellipse was
    found (g,)."""
    g = len(S)
    S1, S2, S3 = S[:, :3, :3], S[:, :3, 3:], S[:, 3:, 3:]
    det3 = np.linalg.det(S3)
    ok3 = np.abs(det3) > 1e-12 * np.abs(S3).reshape(g, 9).max(axis=1) ** 3
    if not ok3.all():
        S3 = np.where(ok3[:, None, None], S3, np.eye(3))
    T = -np.linalg.solve(S3, S2.transpose(0, 2, 1))
    M = S1 + S2 @ T
    M = M[:, _C1_INV_ROWS] * _C1_INV_SCALE  # C1⁻¹ M, C1 = [[0,0,2],[0,-1,0],[2,0,0]]
    w, v = np.linalg.eig(M)
    v = np.real(v)
    cond = 4.0 * v[:, 0] * v[:, 2] - v[:, 1] ** 2
    if np.iscomplexobj(w):
        valid = (cond > 0) & (np.abs(np.imag(w)) < 1e-9 * (1 + np.abs(np.real(w))))
        w = np.real(w)
    else:  # all eigenvalues real (eig raises on non-finite input)
        valid = cond > 0
    score = np.where(valid, np.abs(w), np.inf)
    pick = np.argmin(score, axis=1)
    rows = np.arange(g)
    a1 = v[rows, :, pick]
    a2 = np.einsum("nij,nj->ni", T, a1)
    # [[A, B/2, D/2], [B/2, C, E/2], [D/2, E/2, F]] from a1 = (A, B, C), a2 = (D, E, F)
    Cn = np.concatenate([a1, a2], axis=1)[:, _CONIC_FROM_COEFFS] * _CONIC_COEFF_SCALE
    with np.errstate(divide="ignore", invalid="ignore"):
        Cn = Cn / np.sqrt(np.add.reduce(Cn * Cn, axis=(1, 2)))[:, None, None]  # Frobenius norm
        fin = np.isfinite(Cn).all(axis=(1, 2))
        Cn_safe = Cn if fin.all() else np.where(fin[:, None, None], Cn, np.eye(3))
        shape_problems = ellipse_problems(Cn_safe)  # in the conditioned frame
        Cm = Tn.transpose(0, 2, 1) @ Cn @ Tn
        Cm = 0.5 * (Cm + Cm.transpose(0, 2, 1))
        Cm = Cm / np.sqrt(np.add.reduce(Cm * Cm, axis=(1, 2)))[:, None, None]
    np.negative(Cm, out=Cm, where=(Cm[:, 0, 0] + Cm[:, 1, 1] < 0)[:, None, None])  # positive trace of the block
    picked = score[rows, pick]
    fitted = np.array([bool(np.isfinite(picked[j]) and fin[j]) and shape_problems[j] is None for j in range(g)])
    return Cm, ok3, fitted


# ------------------------------------------------------------------ misc
def default_workers() -> int:
    """Worker processes used by default: the cores this process may run on."""
    import os

    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover (not Linux)
        return max(1, os.cpu_count() or 1)
