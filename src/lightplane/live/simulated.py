"""The simulated sensor: a live source whose frames show what a :class:`~lightplane.live.source.SimulatedHardware`
says (lasers on or off, the turntable's angle, the linear stage's position), with exact truth.

Scenes (``kind``):

- ``turntable``: a sphere resting on the turntable, off its axis (:func:`lightplane.simulate.views.render_turntable_view`);
- ``linear``: an object (``object``: sphere, step or plane) on a linear stage that moves it across the
  light sheet (:func:`lightplane.simulate.views.render_stage_view`); stage position 0 puts the object's
  reference point on the sheet;
- ``target``: a circle target moved through ``placements`` random placements, each held ``hold_s``
  seconds (or chosen with :meth:`SimulatedSensor.set_placement`).

The renderer is not real time (a 1280x960 view takes ~0.25 s): every state's frame is rendered once and
kept (``cache`` views, least recently used dropped), so a state's frames are one image, noise included.
Frames come at ``fps``; a state first seen stalls the stream while it renders (the stall is the
simulator's, not the reader's: no frame is counted as dropped; the frame's exposure time is when its
state was read, before the render).  ``frame.meta["truth"]``: the view's truth (camera frame, mm) and ``"planes"``, the true
light planes; ``meta["laser"]``, ``["angle_deg"]``, ``["position_mm"]``, ``["placement"]``: the state.

:attr:`SimulatedSensor.sensor` is the sensor a user would have calibrated: the true camera and
turntable, and light planes fitted to noisy points of the true ones (:func:`calibrated_plane`), so
they are off the truth by about their own covariance.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from lightplane.camera.model import Camera, camera_record
from lightplane.core.errors import LightplaneError
from lightplane.core.geometry import fit_plane_tls
from lightplane.live.source import Control, Frame, SimulatedHardware
from lightplane.live.pacing import Pacer
from lightplane.measure.sensor import Sensor
from lightplane.plane.model import LightPlane
from lightplane.simulate.render import SCAN_KINDS, RenderOptions
from lightplane.simulate.scene import default_camera, default_plane, sample_placements
from lightplane.simulate.turntable import default_turntable, mirrored_plane
from lightplane.simulate.views import render_stage_view, render_target_view, render_turntable_view

__all__ = ["SimulatedSensor", "SimulatedOptions", "SIM_KINDS", "calibrated_plane", "scaled_camera"]

SIM_KINDS = ("turntable", "linear", "target")


def scaled_camera(camera: Camera, scale: float) -> Camera:
    """``camera`` with its image ``scale`` times as large (pixel centres kept: ``c' = (c + 0.5) s - 0.5``)."""
    if not (np.isfinite(scale) and 0.1 <= scale <= 4):
        raise LightplaneError(f"scale must be between 0.1 and 4, got {scale!r}")
    if scale == 1:
        return camera
    K = camera.K.copy()
    K[:2, :2] *= scale
    K[:2, 2] = (K[:2, 2] + 0.5) * scale - 0.5
    return Camera(K, camera.dist, int(round(camera.width * scale)), int(round(camera.height * scale)),
                  meta={"source": f"default camera scaled by {scale}"})


def calibrated_plane(plane: LightPlane, rng: np.random.Generator, *, sigma_mm: float = 0.03, n_points: int = 300,
                     depth_mm: tuple[float, float] = (400.0, 540.0), half_width_mm: float = 60.0,
                     camera: Camera | None = None) -> LightPlane:
    """A plane as a calibration would give it: fitted (orthogonal least squares) to ``n_points`` points of
    ``plane`` over the working area, each off the plane by Gaussian noise of ``sigma_mm``; with the fit's
    covariance of ``(a, b, c, d)`` for that noise; ``camera``: the camera it belongs to (recorded)."""
    n = plane.normal
    e1 = np.cross(n, [0.0, 1.0, 0.0])
    e1 = e1 / np.linalg.norm(e1) if np.linalg.norm(e1) > 1e-6 else np.array([1.0, 0, 0])
    e2 = np.cross(n, e1)
    z = rng.uniform(*depth_mm, n_points)
    s = rng.uniform(-half_width_mm, half_width_mm, n_points)
    foot = -plane.d * n  # the plane's point nearest the camera
    p = foot + s[:, None] * e2
    # move along e1 within the plane until the depth is z
    t = (z - p[:, 2]) / e1[2] if abs(e1[2]) > 1e-6 else z
    p = p + t[:, None] * e1 + rng.normal(0.0, sigma_mm, n_points)[:, None] * n
    normal, d, _ = fit_plane_tls(p)
    c = p.mean(axis=0)
    q = p - c
    lam, V = np.linalg.eigh(q.T @ q)  # ascending: V[:, 0] the normal, V[:, 1:] in the plane
    J = np.zeros((4, 3))
    for k in (1, 2):
        J[:3, k - 1] = V[:, k]
        J[3, k - 1] = -V[:, k] @ c
    J[3, 2] = -1.0
    cov = J @ np.diag([sigma_mm**2 / lam[1], sigma_mm**2 / lam[2], sigma_mm**2 / n_points]) @ J.T
    sign = 1.0 if normal @ n > 0 else -1.0
    meta: dict[str, Any] = {"method": "simulated calibration", "noise_mm": sigma_mm, "points": n_points}
    if camera is not None:
        meta["camera"] = camera_record(camera)
    return LightPlane(sign * normal, sign * d, cov, meta=meta)


@dataclass(frozen=True)
class SimulatedOptions:
    """The simulated sensor's scene and image formation (checked on construction).

    ``lasers`` 1 or 2 (the second the first's mirror image about the turntable's axis); ``object`` on the
    linear stage: sphere, step or plane; ``difficulty``, ``noise``, ``samples``: the image formation
    (:class:`lightplane.simulate.render.RenderOptions`); ``scale``: the image size relative to the
    default camera's 1280x960; ``seed``: the scene's and the calibration's random draws; ``placements``,
    ``hold_s``: the target scene's placements and how long each is held; ``cache``: views kept.
    """

    lasers: int = 1
    object: str = "sphere"
    difficulty: str = "clean"
    noise: bool = True
    samples: int = 4
    scale: float = 1.0
    seed: int = 0
    placements: int = 6
    hold_s: float = 2.0
    cache: int = 256

    def __post_init__(self) -> None:
        if self.lasers not in (1, 2) or isinstance(self.lasers, bool):
            raise LightplaneError(f"lasers must be 1 or 2, got {self.lasers!r}")
        if self.object not in SCAN_KINDS:
            raise LightplaneError(f"object must be one of {', '.join(SCAN_KINDS)}, got {self.object!r}")
        RenderOptions(difficulty=self.difficulty, noise=bool(self.noise), samples=self.samples)  # checks them
        if not (isinstance(self.scale, (int, float)) and 0.1 <= self.scale <= 4):
            raise LightplaneError(f"scale must be between 0.1 and 4, got {self.scale!r}")
        for name in ("seed", "placements", "cache"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < (0 if name == "seed" else 1):
                raise LightplaneError(f"{name} must be an integer >= {0 if name == 'seed' else 1}, got {v!r}")
        if not (isinstance(self.hold_s, (int, float)) and self.hold_s > 0):
            raise LightplaneError(f"hold_s must be a positive number of seconds, got {self.hold_s!r}")


class SimulatedSensor:
    """A simulated camera with lasers and a turntable or linear stage (module docstring).

    ``hardware``: the :class:`SimulatedHardware` whose state the frames show (default: one made here with
    ``options.lasers`` lasers, the first one on, a turntable for ``kind="turntable"``, a stage for
    ``"linear"``); ``fps``: the frame rate (None: a frame whenever one is asked for); ``options``:
    :class:`SimulatedOptions`, which keyword arguments change (``SimulatedSensor("linear", scale=0.5)``, as a
    spec's options ``sim:linear,scale=0.5`` do).
    """

    def __init__(self, kind: str = "turntable", *, hardware: SimulatedHardware | None = None, fps: float | None = 30.0,
                 options: SimulatedOptions | None = None, **changes: Any) -> None:
        if kind not in SIM_KINDS:
            raise LightplaneError(f"simulated sensor kind must be one of {', '.join(SIM_KINDS)}, got {kind!r}")
        o = SimulatedOptions() if options is None else options
        if changes:
            names = {f.name for f in fields(SimulatedOptions)}
            bad = sorted(set(changes) - names)
            if bad:
                raise LightplaneError(f"simulated sensor: no option {bad[0]!r} (options: fps, {', '.join(sorted(names))})")
            o = replace(o, **changes)
        lasers = o.lasers
        if kind == "target" and lasers != 1:
            raise LightplaneError(f"the target scene has one laser, got lasers={lasers!r}")
        self.kind, self.options, self.object, self.seed, self.hold_s = kind, o, o.object, o.seed, o.hold_s
        self.render_options = RenderOptions(difficulty=o.difficulty, noise=o.noise, samples=o.samples)
        self.camera = scaled_camera(default_camera(), o.scale)
        plane = default_plane()
        self.table = replace(default_turntable(plane), camera=self.camera.to_dict())
        self.true_planes = [plane, mirrored_plane(plane, self.table.point_mm)][:lasers]
        self.direction = self._stage_direction(plane)
        if hardware is None:
            hardware = SimulatedHardware(lasers, has_turntable=kind == "turntable",
                                         stage_direction=tuple(self.direction) if kind == "linear" else None)
            hardware.set_laser(0, True)
        if hardware.n_lasers != lasers:
            raise LightplaneError(f"the hardware has {hardware.n_lasers} lasers, the scene {lasers}")
        self.hardware = hardware
        rng = np.random.default_rng([self.seed, 99])
        planes = {f"laser{i}": calibrated_plane(p, rng, camera=self.camera) for i, p in enumerate(self.true_planes)}
        self.sensor = Sensor(self.camera, planes, self.table if kind == "turntable" else None)
        self.placements = sample_placements(o.placements, np.random.default_rng([self.seed, 7]),
                                            camera=self.camera, plane=plane) if kind == "target" else []
        self._placement: int | None = None
        self.name = f"sim:{kind}" + (f" ({o.object})" if kind == "linear" else "")
        self._pacer = Pacer(fps)
        self.nominal_fps = self._pacer.fps
        self.dropped = 0
        self._cache: OrderedDict = OrderedDict()
        self._cache_size = o.cache
        self._lock = threading.Lock()
        self._t_start = time.monotonic()
        self.renders = 0

    @staticmethod
    def _stage_direction(plane: LightPlane) -> np.ndarray:
        """Across the sheet: the plane's normal projected on the image plane (as the scan data sets)."""
        d = np.array([plane.normal[0], plane.normal[1], 0.0])
        return d / np.linalg.norm(d) if np.linalg.norm(d) > 1e-9 else np.array([1.0, 0.0, 0.0])

    # ------------------------------------------------------------------ state and views
    def set_placement(self, index: int | None) -> None:
        """Show target placement ``index`` (None: cycle through them every ``hold_s`` seconds)."""
        if index is not None and not 0 <= int(index) < len(self.placements):
            raise LightplaneError(f"placement must be 0..{len(self.placements) - 1}, got {index!r}")
        self._placement = None if index is None else int(index)

    def state(self) -> tuple:
        """The state a frame taken now shows: ``(lasers on, angle_deg or position_mm or placement)``."""
        lasers = tuple(bool(v) for v in self.hardware.laser_states())
        if self.kind == "turntable":
            return lasers, round(float(self.hardware.angle_deg), 9)
        if self.kind == "linear":
            return lasers, round(float(getattr(self.hardware, "position_mm", 0.0)), 9)
        k = self._placement
        if k is None:
            k = int((time.monotonic() - self._t_start) / self.hold_s) % len(self.placements)
        return lasers, k

    def view(self, state: tuple) -> tuple[np.ndarray, dict]:
        """The image and truth of ``state`` (rendered once, then kept)."""
        with self._lock:
            hit = self._cache.get(state)
            if hit is not None:
                self._cache.move_to_end(state)
                return hit
        hit = self._render(state)
        with self._lock:
            self._cache[state] = hit
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        return hit

    def _render(self, state: tuple) -> tuple[np.ndarray, dict]:
        lasers, value = state
        kw: dict[str, Any] = {"options": self.render_options, "seed": self.seed}
        if self.kind == "turntable":
            img, truth = render_turntable_view(self.camera, self.true_planes, self.table, value, lasers, **kw)
        elif self.kind == "linear":
            img, truth = render_stage_view(self.camera, self.true_planes, self.object, self._offset(value), lasers,
                                           **kw)
        else:
            img, truth = render_target_view(self.camera, self.true_planes[0], self.placements[value], lasers[0],
                                            index=value, **kw)
        self.renders += 1
        img.setflags(write=False)
        truth["planes"] = [p.to_dict() for p in self.true_planes]
        return img, truth

    def _offset(self, position_mm: float) -> np.ndarray:
        """The object's displacement (camera frame) at stage position ``position_mm``: at 0 its reference
        point (sphere centre, the step's base point, the plane's point) lies on the first light sheet."""
        ref = {"sphere": np.array([0.0, 0.0, 470.0]), "step": np.array([0.0, 0.0, 480.0]),
               "plane": np.array([0.0, 0.0, 470.0])}[self.object]
        pl = self.true_planes[0]
        rate = float(pl.normal @ self.direction)
        shift = -float(pl.signed_distance(ref)[0]) / rate
        return (shift + float(position_mm)) * self.direction

    # ------------------------------------------------------------------ Source
    def start(self) -> None:
        self._pacer.start()
        self.dropped = 0

    def read(self, timeout: float | None = None) -> Frame | None:
        k, t, skipped = self._pacer.take(timeout)
        self.dropped += skipped
        t_state = time.monotonic()
        state = self.state()
        with self._lock:
            cached = state in self._cache
        img, truth = self.view(state)
        if not cached:  # the simulator stalled to render: not the reader's fault
            t = t_state  # the frame shows the state as it was then, not as it is after the render
            self._pacer.rebase()
        lasers, value = state
        meta: dict[str, Any] = {"laser": lasers, "truth": truth, "state": state}
        key = {"turntable": "angle_deg", "linear": "position_mm", "target": "placement"}[self.kind]
        meta[key] = value
        return Frame(img, k, t, time.monotonic(), meta)

    def stop(self) -> None:
        pass

    def controls(self) -> dict[str, Control]:
        return {"fps": Control("fps", self.nominal_fps, "1/s", 0.0, None)}

    def set_control(self, name: str, value: Any) -> None:
        if name != "fps":
            raise LightplaneError(f"{self.name}: no control {name!r} (it has: fps)")
        self._pacer = Pacer(None if value is None else float(value))
        self.nominal_fps = self._pacer.fps
