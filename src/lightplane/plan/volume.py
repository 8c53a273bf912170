"""The working volume a calibration plan is judged over: where measurements will be made.

Two ways to state it, both giving a :class:`lightplane.plane.uncertainty.WorkingVolume`
(image samples and their points on the light plane):

- a box in the camera frame (mm): the part of the light plane inside it (:func:`box_volume`);
- a region of the image (px) and a range of distances from the camera (mm): the stripe's
  pixels there whose rays meet the plane in range (:func:`region_volume`).

:func:`parse_working_volume` reads the command line's form of either.

>>> from lightplane.simulate.scene import default_camera, default_plane
>>> vol = box_volume(default_camera(), default_plane(), (-40, -40, 400), (40, 40, 500), step_mm=10)
>>> bool(vol.points[:, 2].min() >= 400 and vol.points[:, 2].max() <= 500)
True
"""

from __future__ import annotations

import numpy as np

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.plane.model import LightPlane
from lightplane.plane.uncertainty import WorkingVolume, working_volume_grid

__all__ = ["box_volume", "region_volume", "parse_working_volume", "describe_volume"]


def _plane_basis(n: np.ndarray) -> np.ndarray:
    ref = np.eye(3)[int(np.argmin(np.abs(n)))]
    e1 = np.cross(n, ref)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(n, e1)])


#: the most steps along a box's diagonal that :func:`box_volume` samples (a grid of about (2 x this)² points)
MAX_BOX_STEPS = 500


def box_volume(camera: Camera, plane: LightPlane, lo_mm, hi_mm, *, step_mm: float | None = None) -> WorkingVolume:
    """The light plane's part inside the camera-frame box ``lo_mm``..``hi_mm`` (mm, each (x, y, z)), seen in the image.

    Sampled on a square grid of ``step_mm`` on the plane (default: 1/20 of the box's
    diagonal).  Raises :class:`LightplaneError` for an empty box or one the plane misses.
    """
    lo, hi = np.asarray(lo_mm, float).ravel(), np.asarray(hi_mm, float).ravel()
    if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo) & np.isfinite(hi)) or np.any(hi <= lo):
        raise LightplaneError(f"the box needs 3 finite lower and 3 larger upper bounds (mm), got {lo_mm} and {hi_mm}")
    if lo[2] <= 0:
        raise LightplaneError(f"the box must lie in front of the camera (z > 0 mm), got z from {lo[2]:g} mm")
    with np.errstate(over="ignore"):
        diag = float(np.linalg.norm(hi - lo))
    if not np.isfinite(diag):
        raise LightplaneError(f"the box {lo.tolist()}..{hi.tolist()} mm is too large to sample (its diagonal overflows)")
    step = diag / 20.0 if step_mm is None else float(step_mm)
    if not step > 0:
        raise LightplaneError(f"step_mm must be positive, got {step_mm}")
    if diag / step > MAX_BOX_STEPS:
        raise LightplaneError(f"the box's diagonal ({diag:.6g} mm) is over {MAX_BOX_STEPS} steps of {step:g} mm: "
                              "give a larger step or a smaller box")
    centre = 0.5 * (lo + hi)
    foot = centre - plane.signed_distance(centre[None])[0] * plane.normal
    B = _plane_basis(plane.normal)
    k = np.arange(-np.ceil(diag / step), np.ceil(diag / step) + 1) * step
    A, C = np.meshgrid(k, k)
    pts = foot + A.ravel()[:, None] * B[0] + C.ravel()[:, None] * B[1]
    pts = pts[np.all((pts >= lo) & (pts <= hi), axis=1)]
    uv = camera.project(pts) if len(pts) else np.zeros((0, 2))
    keep = np.all(np.isfinite(uv), axis=1) & camera.in_image(uv) if len(pts) else np.zeros(0, bool)
    if np.count_nonzero(keep) < 3:
        raise LightplaneError(f"the light plane crosses the box {lo.tolist()}..{hi.tolist()} mm in fewer than 3 "
                              "points seen in the image")
    d = np.linalg.norm(pts[keep], axis=1)
    px = step * camera.fx / float(np.median(pts[keep][:, 2]))
    return WorkingVolume(uv[keep], pts[keep], (float(d.min()), float(d.max())), float(px))


def region_volume(camera: Camera, plane: LightPlane, region_px=None, *, distance_mm=(380.0, 520.0),
                  step_px: float = 16.0) -> WorkingVolume:
    """The stripe's pixels in the image rectangle ``region_px`` (u0, v0, u1, v1; None: the whole image) whose rays
    meet the plane at a distance in ``distance_mm`` (:func:`lightplane.plane.uncertainty.working_volume_grid`)."""
    vol = working_volume_grid(camera, plane, distance_mm=tuple(distance_mm), step_px=step_px)
    if region_px is None:
        return vol
    r = np.asarray(region_px, float).ravel()
    if r.shape != (4,) or not np.all(np.isfinite(r)) or r[2] <= r[0] or r[3] <= r[1]:
        raise LightplaneError(f"the image region must be u0, v0, u1, v1 (px) with u1 > u0 and v1 > v0, got {region_px}")
    keep = (vol.uv[:, 0] >= r[0]) & (vol.uv[:, 0] <= r[2]) & (vol.uv[:, 1] >= r[1]) & (vol.uv[:, 1] <= r[3])
    if np.count_nonzero(keep) < 3:
        raise LightplaneError(f"the stripe crosses the image region {r.tolist()} px in fewer than 3 samples "
                              f"at {distance_mm[0]:g}–{distance_mm[1]:g} mm")
    return WorkingVolume(vol.uv[keep], vol.points[keep], vol.distance_mm, vol.step_px)


def _numbers(text: str, n: int, what: str) -> list[float]:
    try:
        v = [float(x) for x in text.replace(" ", "").split(",")]
    except ValueError:
        v = []
    if len(v) != n:
        raise LightplaneError(f"{what} needs {n} comma-separated numbers, got {text!r}")
    return v


def parse_working_volume(text: str, camera: Camera, plane: LightPlane) -> WorkingVolume:
    """The working volume from its text form.

    ``box:X0,Y0,Z0,X1,Y1,Z1`` (camera frame, mm); ``image:U0,V0,U1,V1[@NEAR,FAR]`` (an image
    region in px, and distances in mm, default 380,520); ``distance:NEAR,FAR`` (the whole
    image, distances in mm).
    """
    kind, _, rest = str(text).partition(":")
    kind = kind.strip().lower()
    if kind == "box":
        v = _numbers(rest, 6, "box:X0,Y0,Z0,X1,Y1,Z1")
        return box_volume(camera, plane, v[:3], v[3:])
    if kind == "image":
        region, _, dist = rest.partition("@")
        dm = _numbers(dist, 2, "@NEAR,FAR") if dist else [380.0, 520.0]
        return region_volume(camera, plane, _numbers(region, 4, "image:U0,V0,U1,V1"), distance_mm=dm)
    if kind == "distance":
        return region_volume(camera, plane, None, distance_mm=_numbers(rest, 2, "distance:NEAR,FAR"))
    raise LightplaneError(f"the working volume must be box:..., image:... or distance:..., got {text!r}")


def describe_volume(volume: WorkingVolume) -> str:
    """One line: the volume's extent on the light plane (camera frame, mm) and its samples."""
    p = volume.points
    return (f"{len(p)} samples on the light plane, x {p[:, 0].min():.0f}..{p[:, 0].max():.0f} mm, "
            f"y {p[:, 1].min():.0f}..{p[:, 1].max():.0f} mm, z {p[:, 2].min():.0f}..{p[:, 2].max():.0f} mm "
            f"(camera frame), distances {volume.distance_mm[0]:.0f}–{volume.distance_mm[1]:.0f} mm")
