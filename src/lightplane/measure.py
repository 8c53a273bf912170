"""Measurement: pixels to 3D points on the light plane (SPEC §4, paper Eq. 2 and 4).

pixel → undistorted normalised ``(x, y)`` → ray ``X = s (x, y, 1)`` → on the
plane ``s = -d / (a x + b y + c)``.  Rays nearly parallel to the plane give NaN
(flagged), never huge numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import Camera, as_points
from .errors import LightplaneError
from .plane import LightPlane

__all__ = ["triangulate", "triangulate_normalized", "Triangulation", "GRAZING_COS"]

#: Rays whose direction makes |cos| with the plane normal below this are rejected
#: (about 0.06°: a 0.01 px error there moves the point by metres).
GRAZING_COS = 1e-3


@dataclass(frozen=True)
class Triangulation:
    """Triangulated points and which rays were rejected.

    ``points`` (N, 3) mm, NaN where ``grazing`` (ray nearly parallel to the plane)
    or ``behind`` (the plane is behind the camera along that ray).
    """

    points: np.ndarray
    grazing: np.ndarray
    behind: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        return ~(self.grazing | self.behind) & np.all(np.isfinite(self.points), axis=1)


def triangulate_normalized(plane: LightPlane, xy: np.ndarray, *, min_cos: float = GRAZING_COS) -> Triangulation:
    """Intersect rays ``(x, y, 1)`` (normalised, undistorted, ``(N, 2)``) with the plane."""
    xy = as_points(xy, 2, "xy")
    a, b, c = plane.normal
    den = a * xy[:, 0] + b * xy[:, 1] + c
    ray_norm = np.sqrt(xy[:, 0] ** 2 + xy[:, 1] ** 2 + 1.0)
    grazing = ~(np.abs(den) >= min_cos * ray_norm)  # |cos(ray, normal)| < min_cos, or NaN input
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -plane.d / den
    behind = ~grazing & ~(s > 0)
    s[grazing | behind] = np.nan
    pts = np.column_stack([xy[:, 0] * s, xy[:, 1] * s, s])
    return Triangulation(pts, grazing, behind)


def triangulate(camera: Camera, plane: LightPlane, uv: np.ndarray, *, min_cos: float = GRAZING_COS,
                return_flags: bool = False):
    """Triangulate distorted pixels ``uv`` ``(N, 2)`` on the light plane → ``(N, 3)`` mm, camera frame.

    Rays nearly parallel to the plane (|cos| between ray and plane normal below
    ``min_cos``) or meeting it behind the camera give NaN rows.  With
    ``return_flags=True`` returns a :class:`Triangulation` with the flags.

    >>> import numpy as np
    >>> cam = Camera(np.array([[1000., 0, 640], [0, 1000, 480], [0, 0, 1]]), np.zeros(5), 1280, 960)
    >>> pl = LightPlane([0, 0, 1], -500)
    >>> triangulate(cam, pl, np.array([[640., 480.]]))
    array([[  0.,   0., 500.]])
    """
    if not isinstance(camera, Camera):
        raise LightplaneError(f"camera must be a Camera, got {type(camera).__name__}")
    if not isinstance(plane, LightPlane):
        raise LightplaneError(f"plane must be a LightPlane, got {type(plane).__name__}")
    uv = as_points(uv, 2, "uv")
    t = triangulate_normalized(plane, camera.undistort_points(uv, normalized=True), min_cos=min_cos)
    return t if return_flags else t.points
