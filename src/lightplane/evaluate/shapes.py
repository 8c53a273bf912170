"""Shapes fitted to measured points, and comparisons against a known truth.

What a measurement is checked with: a sphere's radius and centre (:func:`fit_sphere`),
a plane's flatness (:func:`fit_plane`), the height of a step between two parallel faces
(:func:`step_height`), the best rigid alignment of two point sets (:func:`rigid_align`)
and the errors of an estimated (camera, light plane) against the truth in the working
volume (:func:`plane_accuracy`).  All lengths in mm.

Robust fits select inliers by the residuals' median absolute deviation
(:func:`scipy.stats.median_abs_deviation`, scaled to a Gaussian sigma): points within
``max(k · MAD, min_tol_mm)`` of the shape are kept, and the fit is redone on them.  The
geometric sphere fit is :func:`scipy.optimize.least_squares`; the rigid alignment is
:meth:`scipy.spatial.transform.Rotation.align_vectors` (Kabsch, a proper rotation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lightplane.core.errors import LightplaneError
from lightplane.plane.triangulate import triangulate
from lightplane.plane.uncertainty import WorkingVolume, point_sigma_mm, volume_sigma, working_volume_grid

__all__ = ["SphereFit", "PlaneFit", "StepFit", "Alignment", "fit_sphere", "fit_plane", "step_height",
           "rigid_align", "plane_accuracy"]


def _points(points, name: str, n_min: int) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise LightplaneError(f"{name}: points must be (N, 3), got shape {p.shape}")
    p = p[np.all(np.isfinite(p), axis=1)]
    if len(p) < n_min:
        raise LightplaneError(f"{name}: need at least {n_min} finite points, got {len(p)}")
    return p


def _mad_sigma(r: np.ndarray) -> float:
    """Gaussian-scaled median absolute deviation (about the median) of ``r``."""
    from scipy.stats import median_abs_deviation

    return float(median_abs_deviation(r, scale="normal"))


def _rank_tol(q: np.ndarray) -> np.ndarray:
    """Singular values of the centred points, relative to the largest (1 when all points coincide: 0s)."""
    s = np.linalg.svd(q - q.mean(axis=0), compute_uv=False)
    return s / s[0] if s[0] > 0 else np.zeros_like(s)


# ----------------------------------------------------------------------------- sphere
@dataclass(frozen=True)
class SphereFit:
    """A sphere fitted to points: ``center_mm`` (3,), ``radius_mm``, ``rms_mm`` (of the inliers'
    distances to the surface), ``inliers`` (bool per finite input point), ``n_points``."""

    center_mm: np.ndarray
    radius_mm: float
    rms_mm: float
    inliers: np.ndarray
    n_points: int

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))

    def to_dict(self) -> dict:
        return {"center_mm": [float(v) for v in self.center_mm], "radius_mm": float(self.radius_mm),
                "rms_mm": float(self.rms_mm), "n_inliers": self.n_inliers, "n_points": int(self.n_points)}


def _sphere_algebraic(q: np.ndarray) -> tuple[np.ndarray, float]:
    """Linear sphere ``|p|² = 2 c·p + (r² − |c|²)`` through ``q`` (least squares)."""
    A = np.column_stack([2 * q, np.ones(len(q))])
    sol, *_ = np.linalg.lstsq(A, np.sum(q**2, axis=1), rcond=None)
    return sol[:3], float(np.sqrt(max(sol[3] + sol[:3] @ sol[:3], 0.0)))


def _sphere_geometric(q: np.ndarray, c: np.ndarray, r: float) -> tuple[np.ndarray, float]:
    """Geometric least squares (distances to the surface) from ``(c, r)``."""
    from scipy.optimize import least_squares

    def res(x):
        return np.linalg.norm(q - x[:3], axis=1) - x[3]

    def jac(x):
        dv = q - x[:3]
        dist = np.linalg.norm(dv, axis=1)
        return np.column_stack([-dv / dist[:, None], -np.ones(len(q))])

    sol = least_squares(res, np.append(c, r), jac=jac, method="lm", xtol=1e-12, ftol=1e-12, gtol=1e-12)
    return sol.x[:3], float(sol.x[3])


def fit_sphere(points: np.ndarray, *, ransac_tol_mm: float = 0.5, iterations: int = 4, k: float = 4.0,
               min_tol_mm: float = 0.05, ransac_trials: int = 300, seed: int = 0) -> SphereFit:
    """Robust least-squares sphere through ``points`` (N, 3) mm (non-finite rows dropped).

    RANSAC on 4-point algebraic spheres (inliers within ``ransac_tol_mm``; ``ransac_trials``
    samples, reproducible from ``seed``), then the geometric fit on the inliers, re-selected
    ``iterations`` times as the points within ``max(k · MAD, min_tol_mm)`` of the surface.
    Raises :class:`LightplaneError` for fewer than 4 points or points on one plane or line.
    """
    p = _points(points, "fit_sphere", 4)
    origin = np.median(p, axis=0)  # conditioning: fit in coordinates near the points
    p = p - origin
    if _rank_tol(p)[2] < 1e-9:
        raise LightplaneError("fit_sphere: the points lie on one plane (or line): no unique sphere")
    rng = np.random.default_rng(seed)
    best, best_n = None, -1
    for _ in range(ransac_trials):
        idx = rng.choice(len(p), 4, replace=False)
        try:
            c, r = _sphere_algebraic(p[idx])
        except np.linalg.LinAlgError:
            continue
        if not np.isfinite(r) or r <= 0:
            continue
        n_in = int(np.count_nonzero(np.abs(np.linalg.norm(p - c, axis=1) - r) <= ransac_tol_mm))
        if n_in > best_n:
            best, best_n = (c, r), n_in
    c, r = best if best is not None else _sphere_algebraic(p)
    keep = np.abs(np.linalg.norm(p - c, axis=1) - r) <= ransac_tol_mm
    if np.count_nonzero(keep) < 4:
        keep = np.ones(len(p), bool)
    for _ in range(iterations):
        c, r = _sphere_geometric(p[keep], c, r)
        res = np.linalg.norm(p - c, axis=1) - r
        new = np.abs(res) <= max(k * _mad_sigma(res[keep]), min_tol_mm)
        if np.count_nonzero(new) < 4:
            break
        keep = new
    res = np.linalg.norm(p[keep] - c, axis=1) - r
    return SphereFit(c + origin, float(r), float(np.sqrt(np.mean(res**2))), keep, len(p))


# ----------------------------------------------------------------------------- plane
@dataclass(frozen=True)
class PlaneFit:
    """A plane ``normal · x + d = 0`` (unit ``normal``) fitted to points: ``rms_mm`` (flatness:
    RMS distance of the inliers), ``peak_to_valley_mm`` (inliers), ``inliers``, ``n_points``."""

    normal: np.ndarray
    d: float
    rms_mm: float
    peak_to_valley_mm: float
    inliers: np.ndarray
    n_points: int

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))

    def distances(self, points: np.ndarray) -> np.ndarray:
        """Signed distances (mm) of ``points`` (N, 3) to the plane."""
        return np.asarray(points, dtype=np.float64) @ self.normal + self.d

    def to_dict(self) -> dict:
        return {"normal": [float(v) for v in self.normal], "d": float(self.d), "rms_mm": float(self.rms_mm),
                "peak_to_valley_mm": float(self.peak_to_valley_mm), "n_inliers": self.n_inliers,
                "n_points": int(self.n_points)}


def _plane_tls(q: np.ndarray) -> tuple[np.ndarray, float]:
    m = q.mean(axis=0)
    n = np.linalg.svd(q - m, full_matrices=False)[2][2]
    if n[2] < 0 or (n[2] == 0 and (n[1] < 0 or (n[1] == 0 and n[0] < 0))):
        n = -n  # a fixed sign: normal towards +z (the camera's optical axis) where it can
    return n, float(-n @ m)


def fit_plane(points: np.ndarray, *, iterations: int = 5, k: float = 4.0, min_tol_mm: float = 0.0) -> PlaneFit:
    """Robust total-least-squares plane through ``points`` (N, 3) mm (non-finite rows dropped).

    The plane through all points, then ``iterations`` times the plane through the points
    within ``max(k · MAD, min_tol_mm)`` of it (stops when the selection no longer changes).
    Raises :class:`LightplaneError` for fewer than 3 points or points on one line.
    """
    p = _points(points, "fit_plane", 3)
    if _rank_tol(p)[1] < 1e-9:
        raise LightplaneError("fit_plane: the points lie on one line (or coincide): no unique plane")
    keep = np.ones(len(p), bool)
    n, d = _plane_tls(p)
    for _ in range(iterations):
        e = p @ n + d
        tol = max(k * _mad_sigma(e[keep]), min_tol_mm)
        new = np.abs(e) <= tol
        if np.count_nonzero(new) < 3 or _rank_tol(p[new])[1] < 1e-9 or np.array_equal(new, keep):
            break
        keep = new
        n, d = _plane_tls(p[keep])
    e = p[keep] @ n + d
    return PlaneFit(n, d, float(np.sqrt(np.mean(e**2))), float(e.max() - e.min()), keep, len(p))


# ----------------------------------------------------------------------------- step
@dataclass(frozen=True)
class StepFit:
    """Two parallel faces: ``height_mm`` (their separation along the common normal),
    ``normal`` (unit, from both faces), ``parallel_deg`` (angle between the faces fitted
    alone), ``base`` and ``top`` (each face's :class:`PlaneFit`)."""

    height_mm: float
    normal: np.ndarray
    parallel_deg: float
    base: PlaneFit
    top: PlaneFit

    def to_dict(self) -> dict:
        return {"height_mm": float(self.height_mm), "normal": [float(v) for v in self.normal],
                "parallel_deg": float(self.parallel_deg), "base": self.base.to_dict(), "top": self.top.to_dict()}


def step_height(base_points: np.ndarray, top_points: np.ndarray, **fit_options) -> StepFit:
    """Height of a step from the points of its two faces (each (N, 3) mm, segmented by the caller).

    Each face is fitted robustly (:func:`fit_plane`, ``fit_options``); the common normal is
    the total-least-squares normal of both faces' inliers, each centred on itself, and the
    height is the distance between the two centroids along it.
    """
    pb = _points(base_points, "step_height (base)", 3)
    pt = _points(top_points, "step_height (top)", 3)
    fb, ft = fit_plane(pb, **fit_options), fit_plane(pt, **fit_options)
    qb, qt = pb[fb.inliers], pt[ft.inliers]
    n = np.linalg.svd(np.vstack([qb - qb.mean(0), qt - qt.mean(0)]), full_matrices=False)[2][2]
    h = float(n @ (qt.mean(0) - qb.mean(0)))
    if h < 0:
        n, h = -n, -h
    par = float(np.degrees(np.arccos(min(1.0, abs(float(fb.normal @ ft.normal))))))
    return StepFit(h, n, par, fb, ft)


# ----------------------------------------------------------------------------- alignment
@dataclass(frozen=True)
class Alignment:
    """Rigid motion ``b ≈ a @ rotation.T + translation`` (``rotation`` 3x3 proper, ``translation`` mm)
    and ``rms_mm``, the RMS distance after it."""

    rotation: np.ndarray
    translation: np.ndarray
    rms_mm: float

    def apply(self, points: np.ndarray) -> np.ndarray:
        return np.asarray(points, dtype=np.float64) @ self.rotation.T + self.translation


def rigid_align(a: np.ndarray, b: np.ndarray) -> Alignment:
    """The rigid motion (rotation and translation, no reflection, no scale) that moves
    ``a`` (N, 3) onto ``b`` (N, 3) (matched rows) with the least squared distances.

    Rows with a non-finite coordinate in either set are ignored.  Raises
    :class:`LightplaneError` for different shapes or fewer than 3 usable pairs.
    """
    from scipy.spatial.transform import Rotation

    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 3:
        raise LightplaneError(f"rigid_align: need two (N, 3) arrays of the same shape, got {a.shape} and {b.shape}")
    ok = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1)
    a, b = a[ok], b[ok]
    if len(a) < 3:
        raise LightplaneError(f"rigid_align: need at least 3 finite point pairs, got {len(a)}")
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    import warnings

    with warnings.catch_warnings():  # collinear points: the rotation about their line is arbitrary, still optimal
        warnings.simplefilter("ignore", UserWarning)
        rot, _ = Rotation.align_vectors(b - mb, a - ma)
    R = rot.as_matrix()
    t = mb - R @ ma
    e = np.linalg.norm(a @ R.T + t - b, axis=1)
    return Alignment(R, t, float(np.sqrt(np.mean(e**2))))


# ----------------------------------------------------------------------------- plane vs truth
def plane_accuracy(plane_est, camera_est, plane_true, camera_true, *,
                   distance_mm: tuple[float, float] = (380.0, 520.0)) -> dict:
    """Errors of an estimated (camera, plane) against the truth, in the user's units.

    ``angle_deg``: angle between the normals; ``offset_mm``: signed distance of the
    estimated plane at the true plane's crossing of the optical axis; over the pixels
    whose true rays meet the true plane at ``distance_mm`` from the camera (the working
    volume): ``tri_rms_mm``, the RMS distance between the points triangulated with the
    estimate and with the truth (camera frame), and ``tri_rms_aligned_mm``, the same after
    the best rigid alignment of the two point sets (:func:`rigid_align`: an error of the
    principal point rotates the whole camera frame: no shape or distance error, but
    camera-frame coordinates move); ``point_sigma_rms_mm``: the RMS predicted sigma there
    (camera frame, with the camera's share when ``camera_est`` has a covariance and the
    plane records its dependence on it), ``shape_sigma_rms_mm`` the predicted sigma after
    the best rigid motion, ``plane_only_sigma_rms_mm`` the plane's image noise alone, and
    ``camera_share_included`` (sigmas None / absent without a plane covariance).
    """

    vol = working_volume_grid(camera_true, plane_true, distance_mm=distance_mm)
    a = triangulate(camera_est, plane_est, vol.uv)
    b = vol.points
    ok = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1)
    a, b = a[ok], b[ok]
    e = np.linalg.norm(a - b, axis=1)
    out = {
        "angle_deg": float(np.degrees(plane_est.angle_to(plane_true))),
        "offset_mm": float(plane_est.signed_distance(plane_true.point_on_axis()[None])[0]),
        "tri_rms_mm": float(np.sqrt(np.mean(e**2))),
        "tri_rms_aligned_mm": rigid_align(a, b).rms_mm,
        "point_sigma_rms_mm": None,
    }
    if plane_est.covariance is not None:
        s = point_sigma_mm(camera_est, plane_est, vol.uv[ok])
        out["point_sigma_rms_mm"] = float(np.sqrt(np.nanmean(s**2)))
        vs = volume_sigma(camera_est, plane_est, WorkingVolume(vol.uv[ok], b, vol.distance_mm, vol.step_px))
        out["shape_sigma_rms_mm"] = vs.shape_mm
        out["plane_only_sigma_rms_mm"] = vs.plane_only_mm
        out["camera_share_included"] = vs.camera_included
    return out
