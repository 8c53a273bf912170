"""Turntable scenes with exact truth: a scan of a sphere on a rotating table (one or two
lasers), and a board standing on the table at several angles (for ``calibrate-turntable``).

The default turntable (:func:`default_turntable`) sits in front of lightplane's default
sensor: its axis tipped 15° towards the camera (a camera looking down on the table),
through a point of the first light plane 470 mm away, so both lasers always cut the
object.  The second laser (:func:`mirrored_plane`) is the first one's mirror image
about the vertical plane through the axis point, its source on the other side of the
camera, as on two-laser desktop scanners.  Angles are right-handed about the axis
direction (up), as in :mod:`lightplane.motion.model`; the object frame of the truth is the
turntable frame of :meth:`lightplane.motion.model.Turntable.basis`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.motion.model import Turntable, rotation_about
from lightplane.plane.model import LightPlane
from lightplane.simulate import render_core as rc
from lightplane.simulate.scene import default_camera, default_plane
from lightplane.simulate.render import (_IMAGING, DIFFICULTIES, Dataset, RenderOptions, _check_choice, _check_n, _finish,
                                        _laser_row, laser_source)
from lightplane.simulate.render import _charuco_layout, _target_patch, target_object_points, target_spec

__all__ = ["default_turntable", "mirrored_plane", "TurntableScanOptions", "render_turntable_scan", "render_turntable_board"]

TABLE_RADIUS_MM = 70.0


def default_turntable(plane: LightPlane | None = None, *, tilt_deg: float = 15.0, height_mm: float = 25.0,
                      distance_mm: float = 470.0) -> Turntable:
    """The axis: direction up, tipped ``tilt_deg`` towards the camera; its point on the table's
    top ``height_mm`` below the optical axis (camera y), ``distance_mm`` away, on ``plane``."""
    plane = default_plane() if plane is None else plane
    a = np.deg2rad(tilt_deg)
    up = np.array([0.0, -np.cos(a), -np.sin(a)])
    n = plane.normal
    if abs(n[0]) < 1e-6:
        raise LightplaneError("the light plane must not contain the camera's x axis direction")
    x0 = -(n[1] * height_mm + n[2] * distance_mm + plane.d) / n[0]
    return Turntable.from_axis([x0, height_mm, distance_mm], up)


def mirrored_plane(plane: LightPlane, point_mm) -> LightPlane:
    """``plane`` mirrored about the plane x = point_x (through ``point_mm``): the second laser."""
    n = plane.normal * np.array([-1.0, 1.0, 1.0])
    p = np.asarray(point_mm, dtype=np.float64)
    return LightPlane(n, -float(n @ p))


def _table_patch(table: Turntable) -> np.ndarray:
    o, B = table.basis()
    return rc.make_patch(o, B[:, 0], B[:, 1], shape=rc.SHAPE_ELLIPSE, region=(TABLE_RADIUS_MM, TABLE_RADIUS_MM, 0, 0),
                         albedo=0.5)


def _angles(n: int, step_deg: float | None, start_deg: float) -> tuple[float, np.ndarray]:
    step = 360.0 / n if step_deg is None else float(step_deg)
    if not (np.isfinite(step) and step != 0):
        raise LightplaneError(f"step_deg must be a finite non-zero number of degrees, got {step_deg}")
    return step, start_deg + step * np.arange(n)


@dataclass(frozen=True)
class TurntableScanOptions(RenderOptions):
    """A turntable scan (:func:`render_turntable_scan`) and its image formation.

    ``step_deg``: degrees per frame (None: one turn over the frames), frame ``k`` at
    ``start_deg + k · step_deg``; ``lasers``: 1 or 2 (each laser has its own frames);
    ``radius_mm``: the sphere, resting on the table's top, its centre ``offset_mm`` from the axis.
    """

    difficulty: str = "clean"
    step_deg: float | None = None
    start_deg: float = 0.0
    lasers: int = 2
    radius_mm: float = 20.0
    offset_mm: float = 12.0

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.lasers not in (1, 2):
            raise LightplaneError(f"lasers must be 1 or 2, got {self.lasers}")


def _turntable_scan_truth(table: Turntable, planes: list[LightPlane], n_frames: int, step: float,
                          angles: np.ndarray, seed: int, options: TurntableScanOptions, frames: list[dict]) -> dict:
    o = options
    q = np.array([o.offset_mm, 0.0, o.radius_mm])
    return {
        "scene": "turntable_scan",
        "units": "mm; degrees; pixels (OpenCV convention)",
        "frame": "camera; the object in the turntable frame (lightplane.motion.model.Turntable.basis)",
        "turntable": table.to_dict(),
        "lasers": {f"laser{i}": {"plane": p.to_dict(), "source_mm": laser_source(p),
                                 "files": [f"laser{i}_{k:03d}.png" for k in range(n_frames)]}
                   for i, p in enumerate(planes)},
        "step_deg": step, "start_deg": float(o.start_deg), "angles_deg": angles,
        "sphere": {"radius_mm": o.radius_mm, "center_turntable_mm": q},
        "table_radius_mm": TABLE_RADIUS_MM,
        "difficulty": o.difficulty, "imaging": o.imaging.__dict__, "seed": seed,
        "options": {"n_frames": n_frames, "step_deg": step, "start_deg": o.start_deg, "lasers": o.lasers,
                    "radius_mm": o.radius_mm, "offset_mm": o.offset_mm, "seed": seed, "difficulty": o.difficulty},
        "frames": frames,
    }


def render_turntable_scan(n_frames: int = 24, seed: int = 0, options: TurntableScanOptions = TurntableScanOptions(),
                          *, camera: Camera | None = None, plane: LightPlane | None = None,
                          table: Turntable | None = None, progress=None) -> Dataset:
    """A sphere on a turntable, one frame per angle and laser (``laser0_000.png``, ``laser1_000.png``...).

    ``options`` (:class:`TurntableScanOptions`): the sphere (``radius_mm``) rests on the
    table's top, its centre ``offset_mm`` from the axis (so every frame sees a different
    slice); frame ``k`` is at ``start_deg + k · step_deg`` (default step: one turn over
    ``n_frames``).  ``lasers`` 1 or 2: each laser has its own frames (one laser on at a
    time).  Truth: the axis (``turntable``), the angle of every frame, each laser's plane,
    the sphere's centre in the turntable frame and per frame in the camera frame.
    """
    n_frames = _check_n(n_frames, "n_frames")
    camera = default_camera() if camera is None else camera
    plane = default_plane() if plane is None else plane
    table = default_turntable(plane) if table is None else table
    planes = [plane, mirrored_plane(plane, table.point_mm)][:options.lasers]
    step, angles = _angles(n_frames, options.step_deg, options.start_deg)
    o, B = table.basis()
    q = np.array([options.offset_mm, 0.0, options.radius_mm])  # sphere centre, turntable frame
    imaging = options.imaging
    patches = np.array([_table_patch(table)])
    images, names, frames = [], [], []
    for li, pl in enumerate(planes):
        for k, ang in enumerate(angles):
            rng = np.random.default_rng([seed, li, k])
            c = o + B @ (rotation_about([0, 0, 1.0], np.deg2rad(ang)) @ q)
            spheres = np.array([rc.make_sphere(c, options.radius_mm, 0.7)])
            laser = _laser_row(pl, imaging, 220.0, rng)
            rad = rc.render_radiance(camera, patches, spheres, laser, 4.0, samples=options.samples,
                                     edge_samples=options.edge_samples, salt=int(rng.integers(0, 2**31 - 1)))
            images.append(_finish(rad, camera, imaging, rng, noise=options.noise))
            names.append(f"laser{li}_{k:03d}.png")
            if li == 0:
                frames.append({"angle_deg": float(ang), "sphere_center_cam_mm": c})
            if progress is not None:
                progress(len(images), n_frames * len(planes))
    truth = _turntable_scan_truth(table, planes, n_frames, step, angles, seed, options, frames)
    return Dataset(images, names, camera, truth)


def render_turntable_board(target=None, angles_deg=(-40, -25, -10, 5, 20, 35), seed: int = 0, *,
                           difficulty: str = "clean", camera: Camera | None = None, table: Turntable | None = None,
                           height_mm: float = 12.0, radial_mm: float = 10.0, noise: bool = True,
                           edge_samples: int = 16) -> Dataset:
    """A board standing on the turntable, one lit image per table angle (laser off).

    ``target``: as :func:`lightplane.simulate.render.target_spec` (default a 9x6 chessboard,
    8 mm squares).  At angle 0 the board faces the camera, upright (its y axis down the
    axis), its first row of points ``height_mm`` above the table and its plane
    ``radial_mm`` in front of the axis.  Truth per view: ``T_cam_board`` and the angle.
    """
    _check_choice(difficulty, DIFFICULTIES, "difficulty")
    camera = default_camera() if camera is None else camera
    table = default_turntable() if table is None else table
    spec = target_spec(("chessboard", 9, 6, 8.0) if target is None else target)
    obj = target_object_points(spec)
    layout = _charuco_layout(spec) if spec.kind == "charuco" else None
    o, B = table.basis()
    x_t, y_t, z_t = B[:, 0], B[:, 1], B[:, 2]
    # board at angle 0: x along y_t (left to right as the camera sees it), y down the axis, z away from the camera
    R0 = np.column_stack([y_t, -z_t, -x_t])
    width = obj[:, 0].max() - obj[:, 0].min()
    top = obj[:, 1].max()
    t0 = o + radial_mm * x_t + (height_mm + top) * z_t - (width / 2) * y_t
    imaging = _IMAGING[difficulty]
    dark = rc.make_laser([1.0, 0, 0], -1e4, [1e4, 0, 0], power=0.0, sigma_mm=0.2)
    images, names, views = [], [], []
    for k, ang in enumerate(np.asarray(angles_deg, dtype=np.float64)):
        rng = np.random.default_rng([seed, k])
        Rt = rotation_about(z_t, np.deg2rad(ang))
        R, t = Rt @ R0, o + Rt @ (t0 - o)
        bg = rc.make_patch(o - 200.0 * x_t, y_t, z_t, albedo=0.25)
        patches = np.array([_target_patch(spec, R, t, layout), _table_patch(table), bg])
        rad = rc.render_radiance(camera, patches, np.zeros((0, rc.SPHERE_COLS)), dark, 150.0,
                                 salt=int(rng.integers(0, 2**31 - 1)), edge_samples=edge_samples,
                                 texels=None if layout is None else layout["texels"])
        images.append(_finish(rad, camera, imaging, rng, noise=noise))
        names.append(f"board_{k:03d}.png")
        views.append({"file": names[-1], "angle_deg": float(ang), "T_cam_board": {"R": R, "t": t},
                      "points_px": camera.project(obj @ R.T + t)})
    truth = {"scene": "turntable_board", "units": "mm; degrees; pixels", "frame": "camera",
             "turntable": table.to_dict(), "target": spec.to_dict(), "difficulty": difficulty, "seed": seed,
             "options": {"angles_deg": list(map(float, angles_deg)), "seed": seed, "difficulty": difficulty,
                         "height_mm": height_mm, "radial_mm": radial_mm},
             "views": views}
    return Dataset(images, names, camera, truth)
