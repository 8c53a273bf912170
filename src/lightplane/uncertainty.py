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
           "rms_triangulation_error_mm"]


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
