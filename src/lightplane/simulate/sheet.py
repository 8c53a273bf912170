"""Stripe points of a curved light sheet by the exact observation model (no images).

The sheet is the cone of :func:`lightplane.simulate.render.curved_sheet` (a tilted fan lens;
the plane for a tilt of 0).  Each circle-target placement (:func:`lightplane.simulate.scene.sample_placements`)
is cut by the sheet along a curve; its points are seen one per pixel along the stripe, each
moved across the stripe by Gaussian noise of ``noise_px`` (the stripe centre's error), and
put back on the target's plane *as the calibration knows it*: the true plane turned by a
Gaussian ``pose_tilt_deg`` about a random in-plane axis through the disc's centre and moved
along its normal by a Gaussian ``pose_offset_mm`` (the pose's error, shared by every point of
an image).  :func:`sheet_field_points` gives points on the true sheet over the field, to
score a triangulation against.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.core.geometry import ray_plane
from lightplane.plane.model import LightPlane
from lightplane.simulate.render import curved_sheet, laser_source
from lightplane.simulate.scene import PlacementOptions, default_camera, default_plane, sample_placements

__all__ = ["SheetObservation", "sheet_distance", "onto_sheet", "sheet_stripe_points", "sheet_field_points"]


@dataclass(frozen=True)
class SheetObservation:
    """The observation model's noise: ``noise_px`` across the stripe per point, the pose's
    ``pose_tilt_deg`` and ``pose_offset_mm`` per image (standard deviations)."""

    noise_px: float = 0.1
    pose_tilt_deg: float = 0.01
    pose_offset_mm: float = 0.01

    def __post_init__(self) -> None:
        for k in ("noise_px", "pose_tilt_deg", "pose_offset_mm"):
            v = getattr(self, k)
            if not (np.isfinite(v) and v >= 0):
                raise LightplaneError(f"SheetObservation.{k} must be >= 0, got {v!r}")


def _cone(plane: LightPlane, tilt_deg: float) -> tuple[np.ndarray, np.ndarray, float]:
    truth = curved_sheet(plane, tilt_deg)
    if truth is None:
        return laser_source(plane), plane.normal, 0.0
    return np.asarray(truth["apex_mm"]), np.asarray(truth["axis"]), float(truth["tilt_rad"])


def sheet_distance(plane: LightPlane, tilt_deg: float, points: np.ndarray) -> np.ndarray:
    """Signed distance (mm) of (N, 3) points to the sheet (the renderer's: ``(v·a) cos τ - |v x a| sin τ``)."""
    apex, axis, tau = _cone(plane, tilt_deg)
    v = np.asarray(points, float) - apex
    va = v @ axis
    return va * np.cos(tau) - np.sqrt(np.maximum(np.einsum("ij,ij->i", v, v) - va**2, 0.0)) * np.sin(tau)


def onto_sheet(plane: LightPlane, tilt_deg: float, points: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Points moved along ``direction`` (unit, (3,) or (N, 3)) onto the sheet (Newton, to 1e-12 mm)."""
    p = np.array(points, float)
    g = np.broadcast_to(np.asarray(direction, float), p.shape)
    for _ in range(20):
        f = sheet_distance(plane, tilt_deg, p)
        df = (sheet_distance(plane, tilt_deg, p + 1e-3 * g) - f) / 1e-3
        p = p - (f / df)[:, None] * g
        if np.max(np.abs(f)) < 1e-12:
            break
    return p


def sheet_stripe_points(n: int, rng: np.random.Generator, tilt_deg: float, obs: SheetObservation = SheetObservation(),
                        *, camera: Camera | None = None, plane: LightPlane | None = None) -> list[np.ndarray]:
    """Each of ``n`` placements' stripe points (camera frame, mm) as the calibration sees them."""
    camera = default_camera() if camera is None else camera
    plane = default_plane() if plane is None else plane
    out = []
    for tp in sample_placements(n, rng, PlacementOptions(), camera=camera, plane=plane):
        chord = tp.chord(plane)
        if chord is None:
            continue
        npx = int(np.linalg.norm(np.diff(camera.project(chord), axis=0)))
        s = np.linspace(0.02, 0.98, max(npx, 8))[:, None]
        flat = chord[0] + s * (chord[1] - chord[0])
        along = (chord[1] - chord[0]) / np.linalg.norm(chord[1] - chord[0])
        truth = onto_sheet(plane, tilt_deg, flat, np.cross(tp.normal, along))
        xy = truth[:, :2] / truth[:, 2:3]
        # the stripe centre's error, across the stripe in the image
        d_img = np.diff(xy[[0, -1]], axis=0)[0]
        across = np.array([-d_img[1], d_img[0]]) / np.linalg.norm(d_img)
        xy = xy + rng.normal(0.0, obs.noise_px, (len(xy), 1)) / camera.fx * across
        axis = np.cross(tp.normal, rng.normal(size=3))
        axis /= np.linalg.norm(axis)
        ang = np.radians(rng.normal(0.0, obs.pose_tilt_deg))
        n_est = tp.normal * np.cos(ang) + np.cross(axis, tp.normal) * np.sin(ang)
        c_est = tp.center + rng.normal(0.0, obs.pose_offset_mm) * tp.normal
        out.append(ray_plane(xy, n_est, c_est))
    return out


def sheet_field_points(tilt_deg: float, *, camera: Camera | None = None, plane: LightPlane | None = None,
                       distance_mm: tuple[float, float] = (380.0, 520.0), n: int = 25) -> np.ndarray:
    """Points (M, 3) mm on the true sheet over the field: an ``n x n`` grid of the plane's in-plane
    coordinates, moved onto the sheet along the normal, kept where the camera sees them at a depth in ``distance_mm``."""
    camera = default_camera() if camera is None else camera
    plane = default_plane() if plane is None else plane
    src = laser_source(plane)
    centre = plane.point_on_axis()
    ex = (centre - src) / np.linalg.norm(centre - src)
    ey = np.cross(plane.normal, ex)
    x = np.linspace(np.linalg.norm(centre - src) - 200, np.linalg.norm(centre - src) + 200, n)
    y = np.linspace(-80, 80, n)
    X, Y = np.meshgrid(x, y)
    p = src + X.reshape(-1, 1) * ex + Y.reshape(-1, 1) * ey
    p = onto_sheet(plane, tilt_deg, p, plane.normal)
    uv = camera.project(p)
    keep = ((p[:, 2] >= distance_mm[0]) & (p[:, 2] <= distance_mm[1]) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0)
            & (uv[:, 0] <= camera.width - 1) & (uv[:, 1] <= camera.height - 1))
    return p[keep]
