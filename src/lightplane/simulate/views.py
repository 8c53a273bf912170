"""Single views of the scan scenes for a given state, with exact truth: the frames a live simulated
sensor shows (:mod:`lightplane.live.simulated`).

A *view* is one image of a scene in one state: a sphere on the turntable at an angle, an object on a
linear stage at a position, a circle target in a placement; each with any subset of the lasers on (none:
the laser-off frame of a capture cycle).  The scenes are those of :func:`lightplane.simulate.turntable.
render_turntable_scan`, :func:`lightplane.simulate.render.render_scan_dataset` and
:func:`lightplane.simulate.render.render_circle_image`; the image formation is given by a
:class:`lightplane.simulate.render.RenderOptions` (difficulty, noise, samples per pixel).  Random
draws (speckle, noise) are seeded by ``seed`` and the state, so a view of one state is the same image
every time.  Several lasers on at once add their light (one radiance per laser).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.motion.model import Turntable, rotation_about
from lightplane.plane.model import LightPlane
from lightplane.simulate import render_core as rc
from lightplane.simulate.render import (CircleOptions, RenderOptions, _check_choice, _finish, _laser_row, _scan_objects,
                                        render_circle_image, SCAN_KINDS)
from lightplane.simulate.scene import TargetPlacement
from lightplane.simulate.turntable import _table_patch

__all__ = ["render_turntable_view", "render_stage_view", "render_target_view", "VIEW_LASER_POWER"]

#: laser power of the scan views (grey levels at unit albedo), as in the scan data sets
VIEW_LASER_POWER = 220.0
#: the default image formation of the views: clean (the scan data sets' turntable default)
CLEAN = RenderOptions(difficulty="clean")
#: ambient light of the scan views (a dark scene: the stripe is what a scan sees)
VIEW_AMBIENT = 4.0


def _seed(seed: int, *parts: float) -> np.random.Generator:
    """A generator seeded by ``seed`` and the state (numbers rounded to 1e-6)."""
    return np.random.default_rng([int(seed)] + [int(round(float(p) * 1e6)) % (2**63) for p in parts])


def _lit(camera: Camera, planes: Sequence[LightPlane], lasers_on: Sequence[bool], patches: np.ndarray,
         spheres: np.ndarray, options: RenderOptions, rng: np.random.Generator) -> np.ndarray:
    """The image of a scene lit by the lasers that are on (ambient light once)."""
    imaging = options.imaging
    samples, edge = options.samples, options.edge_samples
    if len(lasers_on) != len(planes):
        raise LightplaneError(f"{len(lasers_on)} laser states for {len(planes)} lasers")
    rad = None
    ambient = VIEW_AMBIENT
    for pl, on in zip(planes, lasers_on):
        laser = _laser_row(pl, imaging, VIEW_LASER_POWER if on else 0.0, rng)
        if not on and rad is not None:
            continue
        r = rc.render_radiance(camera, patches, spheres, laser, ambient, samples=samples, edge_samples=edge,
                               salt=int(rng.integers(0, 2**31 - 1)))
        rad = r if rad is None else rad + r
        ambient = 0.0
    if rad is None:  # no laser at all
        off = rc.make_laser([1.0, 0, 0], -1e4, [1e4, 0, 0], power=0.0, sigma_mm=0.2)
        rad = rc.render_radiance(camera, patches, spheres, off, ambient, samples=samples, edge_samples=edge)
    return _finish(rad, camera, imaging, rng, noise=options.noise)


def render_turntable_view(camera: Camera, planes: Sequence[LightPlane], table: Turntable, angle_deg: float,
                          lasers_on: Sequence[bool], *, radius_mm: float = 20.0, offset_mm: float = 12.0,
                          options: RenderOptions = CLEAN, seed: int = 0) -> tuple[np.ndarray, dict]:
    """A sphere (``radius_mm``, its centre ``offset_mm`` from the axis) resting on the turntable, turned
    by ``angle_deg`` (right-handed about the axis, up), lit by the lasers that are on.

    Truth: ``angle_deg``, ``sphere`` (``center_mm`` in the camera frame, ``radius_mm``), ``table`` (its
    top: ``normal``, ``d`` in the camera frame, ``radius_mm``), ``lasers`` (each laser's true plane and
    whether it was on)."""
    o, B = table.basis()
    q = np.array([offset_mm, 0.0, radius_mm])
    c = o + B @ (rotation_about([0, 0, 1.0], np.deg2rad(float(angle_deg))) @ q)
    spheres = np.array([rc.make_sphere(c, radius_mm, 0.7)])
    patches = np.array([_table_patch(table)])
    rng = _seed(seed, 1.0, angle_deg, *map(float, lasers_on))
    img = _lit(camera, planes, lasers_on, patches, spheres, options, rng)
    n = B[:, 2]
    truth = {"scene": "turntable", "angle_deg": float(angle_deg),
             "sphere": {"center_mm": c, "radius_mm": float(radius_mm)},
             "table": {"normal": n, "d": float(-n @ o), "point_mm": o, "radius_mm": 70.0},
             "lasers": [{"plane": p.to_dict(), "on": bool(on)} for p, on in zip(planes, lasers_on)]}
    return img, truth


def render_stage_view(camera: Camera, planes: Sequence[LightPlane], kind: str, offset_mm: np.ndarray,
                      lasers_on: Sequence[bool], *, options: RenderOptions = CLEAN,
                      seed: int = 0) -> tuple[np.ndarray, dict]:
    """An object of :func:`lightplane.simulate.render.render_scan_dataset` (``kind``: sphere, step or
    plane) displaced by ``offset_mm`` (3,) in the camera frame, lit by the lasers that are on.

    Truth: ``offset_mm``, ``surfaces`` (as the scan data set's, camera frame), ``lasers``."""
    _check_choice(kind, SCAN_KINDS, "kind")
    off = np.asarray(offset_mm, dtype=np.float64).reshape(3)
    patches, spheres, surfaces = _scan_objects(kind, off, planes[0])
    rng = _seed(seed, 2.0, *off, *map(float, lasers_on))
    img = _lit(camera, planes, lasers_on, patches, spheres, options, rng)
    truth = {"scene": "stage", "kind": kind, "offset_mm": off, "surfaces": surfaces,
             "lasers": [{"plane": p.to_dict(), "on": bool(on)} for p, on in zip(planes, lasers_on)]}
    return img, truth


def render_target_view(camera: Camera, plane: LightPlane, placement: TargetPlacement, laser_on: bool, *,
                       options: RenderOptions = CLEAN, seed: int = 0, index: int = 0) -> tuple[np.ndarray, dict]:
    """A light circle target in ``placement`` in front of a dark background, the laser on or off
    (:func:`lightplane.simulate.render.render_circle_image`; the same scene either way).

    Truth: ``placement`` (``center_mm``, ``normal``, ``diameter_mm``), ``chord_mm`` (the stripe's true
    ends on the disc, or None), ``lasers``."""
    rng = np.random.default_rng([int(seed), 3, int(index)])
    img = render_circle_image(camera, plane, placement, rng, CircleOptions(
        difficulty=options.difficulty, noise=options.noise, samples=options.samples, edge_samples=options.edge_samples),
                              laser=bool(laser_on))
    chord = placement.chord(plane)
    truth = {"scene": "target", "placement": {"center_mm": placement.center, "normal": placement.normal,
                                               "diameter_mm": placement.diameter_mm},
             "chord_mm": None if chord is None else np.asarray(chord),
             "lasers": [{"plane": plane.to_dict(), "on": bool(laser_on)}]}
    return img, truth
