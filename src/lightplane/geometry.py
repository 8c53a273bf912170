"""Low-level geometry primitives shared by the whole package (numpy only).

One implementation each of the small fits and distances that the calibration,
measurement, baselines and ellipse code all need:

- :func:`robust_sigma` — the normal-consistent MAD, ``1.4826 · median|x − median x|``
  (or about zero, for residuals known to be centred);
- :func:`tls_line` — total-least-squares 2-D line;
- :func:`fit_plane_tls` — orthogonal (weighted) least-squares plane in 3-D;
- :func:`ray_plane` — rays from the camera centre meeting a plane;
- :func:`sampson_distance` — first-order geometric distance of 2-D points to a conic.

Failure convention: a primitive that can fail returns its result, or a
:class:`Failure` — falsy, carrying its ``reason`` — so that ``if not r: ...
r.reason`` works without exceptions in inner loops; callers that raise build their
message from the reason.  Bad shapes (a programming error, not bad data) raise
:class:`ValueError`.

(The simulator's scene geometry is :mod:`lightplane.simulate.geometry`, unrelated.)
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Failure", "MAD_TO_SIGMA", "robust_sigma", "tls_line", "fit_plane_tls", "ray_plane",
           "sampson_distance", "default_workers"]

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


def fit_plane_tls(p: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, float, float]:
    """Orthogonal (weighted) least-squares plane through (N, 3) points.

    Returns ``(normal (3,), d, smallest eigenvalue of the weighted scatter)``: the
    normal is the eigenvector of the smallest eigenvalue of the centred scatter
    matrix; the eigenvalue is the weighted sum of squared distances.  ValueError for a
    bad shape or fewer than 3 points.
    """
    p = _points(p, 3, "points")
    if len(p) < 3:
        raise ValueError(f"a plane fit needs at least 3 points, got {len(p)}")
    w = np.ones(len(p)) if weights is None else np.asarray(weights, dtype=np.float64)
    c = (w @ p) / w.sum()
    q = p - c
    S = (q * w[:, None]).T @ q
    lam, V = np.linalg.eigh(S)
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
    X = np.column_stack([uv, np.ones(len(uv))])
    CX = X @ C
    alg = np.sum(CX * X, axis=1)
    g = 2 * np.hypot(CX[:, 0], CX[:, 1])
    d = alg / np.maximum(g, 1e-300)
    return d if signed else np.abs(d)


def default_workers() -> int:
    """Worker processes used by default: the cores this process may run on."""
    import os

    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover (not Linux)
        return max(1, os.cpu_count() or 1)
