"""Uncertainty of triangulated points from the light plane's covariance (docs/method.md §Point uncertainty).

A stripe pixel with undistorted normalised ray ``x̃ = (x, y, 1)`` triangulates to
``X = −d x̃ / (n·x̃)`` (paper Eq. 2/4).  To first order an error ``δ(a, b, c, d)`` of
the plane moves it by ``J δ`` with

    ∂X/∂n = d x̃ x̃ᵀ / (n·x̃)²,   ∂X/∂d = −x̃ / (n·x̃),

so ``Cov(X) = J Σ Jᵀ`` (Σ: the plane's 4x4 covariance).  ``point_sigma_mm`` is
``sqrt(trace Cov(X))``: the RMS length of the 3D error vector (mm).

What it does NOT cover: the stripe centre's own image noise (a per-point effect that
averages out along a profile), errors of the camera intrinsics and distortion, and
model errors (a curved or thick light sheet); it is the part due to the plane
calibration only, i.e. the systematic error shared by all points of a scan.

>>> import numpy as np
>>> from lightplane import Camera, LightPlane
>>> cam = Camera([[1000., 0, 640], [0, 1000, 480], [0, 0, 1]], np.zeros(5), 1280, 960)
>>> pl = LightPlane([0, 0, 1], -500, covariance=np.diag([0, 0, 0, 0.01]))
>>> point_sigma_mm(cam, pl, np.array([[640., 480.]]))   # only d uncertain: 0.1 mm along z
array([0.1])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import Camera, as_points
from .errors import LightplaneError
from .measure import GRAZING_COS, points_sigma_mm, triangulate_normalized
from .plane import LightPlane

__all__ = ["point_covariance", "point_sigma_mm", "WorkingVolume", "working_volume_grid", "rms_point_sigma_mm",
           "rms_triangulation_error_mm", "camera_param_names", "camera_params", "camera_with_params", "camera_steps",
           "ray_sigma_rad"]


def _plane_cov(plane: LightPlane, covariance: np.ndarray | None) -> np.ndarray:
    cov = plane.covariance if covariance is None else np.asarray(covariance, float)
    if cov is None:
        raise LightplaneError("the light plane has no covariance (calibrate it with method 'ml')")
    if cov.shape != (4, 4) or not np.all(np.isfinite(cov)):
        raise LightplaneError(f"plane covariance must be a finite 4x4 matrix, got shape {cov.shape}")
    return cov


def _point_jacobian(plane: LightPlane, xy: np.ndarray) -> np.ndarray:
    """(N, 3, 4) ``∂X/∂(a, b, c, d)`` at normalised rays ``xy`` (N, 2); NaN for grazing rays."""
    xt = np.column_stack([xy, np.ones(len(xy))])
    den = xt @ plane.normal
    bad = ~(np.abs(den) >= GRAZING_COS * np.linalg.norm(xt, axis=1))
    den = np.where(bad, np.nan, den)
    J = np.empty((len(xy), 3, 4))
    J[:, :, :3] = plane.d * xt[:, :, None] * xt[:, None, :] / (den**2)[:, None, None]
    J[:, :, 3] = -xt / den[:, None]
    return J


def point_covariance(camera: Camera, plane: LightPlane, uv: np.ndarray, *,
                     covariance: np.ndarray | None = None) -> np.ndarray:
    """(N, 3, 3) covariance (mm²) of points triangulated from distorted pixels ``uv`` (N, 2).

    From the plane's covariance only (or ``covariance``, a 4x4 of ``(a, b, c, d)``,
    e.g. a Cramér–Rao bound); NaN for rays nearly parallel to the plane.
    """
    uv = as_points(uv, 2, "uv")
    cov = _plane_cov(plane, covariance)
    J = _point_jacobian(plane, camera.undistort_points(uv, normalized=True))
    return J @ cov @ np.swapaxes(J, 1, 2)


def point_sigma_mm(camera: Camera, plane: LightPlane, uv: np.ndarray, *,
                   covariance: np.ndarray | None = None) -> np.ndarray:
    """(N,) sigma (mm) of points triangulated from distorted pixels ``uv`` (N, 2).

    ``sqrt(trace Cov(X))``: the RMS length of the 3D error due to the plane's
    uncertainty (first-order propagation, module docstring).  NaN for grazing rays.
    Raises when there is no covariance.  Computed by
    :func:`lightplane.measure.points_sigma_mm` from the undistorted rays.
    """
    uv = as_points(uv, 2, "uv")
    cov = _plane_cov(plane, covariance)
    return points_sigma_mm(plane, camera.undistort_points(uv, normalized=True), covariance=cov)


@dataclass(frozen=True)
class WorkingVolume:
    """Image samples of the stripe region: pixels whose ray meets the plane in range.

    ``uv`` (N, 2) distorted px on a regular grid, ``points`` (N, 3) mm on the plane,
    ``distance_mm`` the range of distances from the camera centre used, ``step_px``.
    """

    uv: np.ndarray
    points: np.ndarray
    distance_mm: tuple[float, float]
    step_px: float


def working_volume_grid(camera: Camera, plane: LightPlane, *, distance_mm: tuple[float, float] = (380.0, 520.0),
                        step_px: float = 16.0, margin_px: float = 0.0) -> WorkingVolume:
    """Sample the image on a grid and keep pixels whose ray meets the plane at a distance in ``distance_mm``.

    That is the region where the stripe can be seen on objects in the working volume
    (docs/conventions.md §Default sensor: 380–520 mm).  Raises if no pixel qualifies.
    """
    if step_px <= 0:
        raise LightplaneError(f"step_px must be positive, got {step_px}")
    lo, hi = float(distance_mm[0]), float(distance_mm[1])
    if not (0 < lo < hi):
        raise LightplaneError(f"distance_mm must be (near, far) with 0 < near < far, got {distance_mm}")
    us = np.arange(margin_px, camera.width - margin_px, step_px)
    vs = np.arange(margin_px, camera.height - margin_px, step_px)
    U, V = np.meshgrid(us, vs)
    uv = np.column_stack([U.ravel(), V.ravel()])
    pts = triangulate_normalized(plane, camera.undistort_points(uv, normalized=True)).points
    dist = np.linalg.norm(pts, axis=1)
    keep = np.isfinite(dist) & (dist >= lo) & (dist <= hi)
    if not np.any(keep):
        raise LightplaneError(f"the light plane is not in view at distances {lo:g}–{hi:g} mm")
    return WorkingVolume(uv[keep], pts[keep], (lo, hi), float(step_px))


def rms_point_sigma_mm(camera: Camera, plane: LightPlane, volume: WorkingVolume, *,
                       covariance: np.ndarray | None = None) -> float:
    """RMS over the working volume of :func:`point_sigma_mm` (mm)."""
    s = point_sigma_mm(camera, plane, volume.uv, covariance=covariance)
    return float(np.sqrt(np.nanmean(s**2)))


def rms_triangulation_error_mm(camera: Camera, plane_est: LightPlane, plane_true: LightPlane,
                               volume: WorkingVolume) -> float:
    """RMS over the working volume of the distance (mm) between points triangulated with
    ``plane_est`` and with ``plane_true`` (the same pixels)."""
    xy = camera.undistort_points(volume.uv, normalized=True)
    a = triangulate_normalized(plane_est, xy).points
    b = triangulate_normalized(plane_true, xy).points
    e = np.linalg.norm(a - b, axis=1)
    return float(np.sqrt(np.nanmean(e**2)))


# ------------------------------------------------------------------ the camera's share
def camera_param_names(camera: Camera) -> tuple[str, ...]:
    """The intrinsic parameters in the order of a camera covariance: ``fx, fy, cx, cy`` then ``dist``'s."""
    from .lens import coeff_names

    return ("fx", "fy", "cx", "cy") + coeff_names(camera.model)


def camera_params(camera: Camera) -> np.ndarray:
    """The vector of :func:`camera_param_names`."""
    return np.concatenate([[camera.fx, camera.fy, camera.cx, camera.cy], camera.dist])


def camera_with_params(camera: Camera, p: np.ndarray) -> Camera:
    """``camera`` with the intrinsic vector ``p`` (order of :func:`camera_param_names`; no covariance)."""
    p = np.asarray(p, np.float64)
    K = camera.K.copy()
    K[0, 0], K[1, 1], K[0, 2], K[1, 2] = p[:4]
    return Camera(K, p[4:], camera.width, camera.height, model=camera.model)


def camera_steps(camera: Camera) -> np.ndarray:
    """(r, P) one-sigma steps of the intrinsics along the principal axes of the camera's
    covariance (their outer products sum to it; axes of zero variance dropped); (0, P)
    when the camera has no covariance.  Raises when the covariance names other
    parameters than the camera's model has."""
    names = camera_param_names(camera)
    if camera.covariance is None:
        return np.zeros((0, len(names)))
    if tuple(camera.covariance_params) != names:
        raise LightplaneError(f"the camera's covariance is of ({', '.join(camera.covariance_params)}) but its model "
                              f"has ({', '.join(names)}): a camera file from another model?")
    w, V = np.linalg.eigh(camera.covariance)
    keep = w > 1e-12 * max(w.max(initial=0.0), 1e-300)
    return (V[:, keep] * np.sqrt(w[keep])).T


def ray_sigma_rad(camera: Camera, uv: np.ndarray) -> np.ndarray:
    """(N,) sigma (rad) of the direction of the rays through distorted pixels ``uv`` due to
    the camera's covariance (first order, central differences along :func:`camera_steps`);
    NaN without a covariance."""
    uv = as_points(uv, 2, "uv")
    steps = camera_steps(camera)
    if len(steps) == 0:
        return np.full(len(uv), np.nan)
    p0 = camera_params(camera)
    var = np.zeros(len(uv))
    for s in steps:
        a = camera_with_params(camera, p0 + s).rays(uv, unit=True)
        b = camera_with_params(camera, p0 - s).rays(uv, unit=True)
        var += np.sum((0.5 * (a - b)) ** 2, axis=1)
    return np.sqrt(var)


def image_grid(camera: Camera, step_px: float = 32.0) -> np.ndarray:
    """(N, 2) pixel centres of a regular grid over the whole image."""
    us = np.arange(step_px / 2, camera.width, step_px)
    vs = np.arange(step_px / 2, camera.height, step_px)
    U, V = np.meshgrid(us, vs)
    return np.column_stack([U.ravel(), V.ravel()])


#: What the camera's share covers (one sentence, printed and stored with every figure that includes it).
CAMERA_SHARE_COVERS = ("the intrinsics' and distortion's covariance from the camera calibration (corner noise "
                       "estimated from its residuals, board poses marginalised)")
#: Said wherever a figure lacks the camera's share.
CAMERA_SHARE_MISSING = "the camera's share is not included (the camera file has no covariance)"


def camera_uncertainty_summary(camera: Camera, distance_mm: float, step_px: float = 32.0) -> dict:
    """What the camera's covariance means at ``distance_mm``: the sigma of a ray's direction
    (deg; RMS over the image and its maximum) and the same as a displacement across the
    ray at that distance (mm).  ``{"included": False, "note": ...}`` without a covariance."""
    if camera.covariance is None:
        return {"included": False, "note": CAMERA_SHARE_MISSING}
    if not distance_mm > 0:
        raise LightplaneError(f"the working distance must be positive, got {distance_mm} mm")
    s = ray_sigma_rad(camera, image_grid(camera, step_px))
    rms, mx = float(np.sqrt(np.mean(s**2))), float(np.max(s))
    return {"included": True, "distance_mm": float(distance_mm),
            "ray_sigma_deg_rms": float(np.degrees(rms)), "ray_sigma_deg_max": float(np.degrees(mx)),
            "ray_sigma_mm_rms": rms * float(distance_mm), "ray_sigma_mm_max": mx * float(distance_mm),
            "covers": CAMERA_SHARE_COVERS}
