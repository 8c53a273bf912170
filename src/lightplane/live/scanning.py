"""A live scan: turn the table (or move the stage) step by step, capture the frames of each step's cycle,
write them where ``lightplane measure`` reads them, and measure them as they come.

One step: move (the controller returns when the table has settled), then with every laser off the
pattern frame, then with each laser on alone its laser frame; each capture takes the
``settle_frames``-th frame exposed after the lasers were switched.  The first step captures where the
table stands; every later one moves by ``step`` first.  The scan folder::

    pattern/0000.png ...        laser-off frame of each step (the capture cycle's P)
    laser0/0000.png ...         laser frames, one folder per laser (named as the sensor's planes)
    sensor.json                 the sensor the scan was measured with
    scan.json                   kind, steps, step, cycle, motion, and the measure command that gives the
                                same cloud from these files
    cloud.ply                   the measured cloud: every laser's points, placed by the motion

The cloud is what :func:`lightplane.measure.sensor.measure_lasers` makes of the laser folders with the
scan's motion (``lightplane measure --sensor sensor.json --laser laser0=laser0 ... --turntable-step STEP``
or ``--step STEP --direction=X,Y,Z``): the same frames, options and arithmetic, so the same points.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from lightplane.core.errors import LightplaneError
from lightplane.core.io import provenance, rotate_image, write_json
from lightplane.live.recording import prepare_folder, write_png
from lightplane.live.source import Frame, Hardware
from lightplane.measure.options import MeasureOptions
from lightplane.measure.pointcloud import POINT_FIELDS, write_cloud
from lightplane.measure.scan import FrameProcessor
from lightplane.measure.sensor import LASER_POINT_DTYPE, Sensor
from lightplane.motion.model import Motion
from lightplane.plane.triangulate import profile_axis
from lightplane.stripe.extract import estimate_width

__all__ = ["ScanJob", "ScanRequest", "SCAN_KINDS", "measure_command"]

SCAN_KINDS = ("turntable", "linear")


def measure_command(laser_names: list[str], kind: str, step: float, direction, options: MeasureOptions) -> str:
    """The ``lightplane measure`` command (run in the scan folder) that measures the scan's frames as the
    live scan did."""
    parts = ["lightplane measure --sensor sensor.json"] + [f"--laser {n}={n}" for n in laser_names]
    if kind == "turntable":
        parts.append(f"--turntable-step {step!r}")
    else:
        parts.append(f"--step {step!r} --direction={','.join(repr(float(v)) for v in direction)}")
    s = options.stripe
    if s.channel is not None:
        parts.append(f"--channel {s.channel}")
    if s.width_px is not None:
        parts.append(f"--stripe-width {s.width_px!r}")
    if s.sigma_along_px is not None:
        parts.append(f"--sigma-along {s.sigma_along_px!r}")
    if options.axis != "auto":
        parts.append(f"--axis {options.axis}")
    if options.roi is not None:
        x, y, w, h = options.roi
        parts.append(f"--roi {x},{y},{x + w},{y + h}")
    if options.smooth_lines:
        parts.append(f"--smooth {options.smooth_lines}")
    if options.keep_outliers:
        parts.append("--keep-outliers")
    return " ".join(parts + ["-o cloud.ply"])


@dataclass(frozen=True)
class ScanRequest:
    """What to scan (checked on construction): ``kind`` turntable or linear, ``steps`` (>= 1) of ``step``
    degrees or mm (finite, non-zero), into ``folder``; ``settle_frames``: each capture takes the n-th frame
    exposed after the lasers were switched."""

    kind: str
    steps: int
    step: float
    folder: Path
    settle_frames: int = 1

    def __post_init__(self) -> None:
        if self.kind not in SCAN_KINDS:
            raise LightplaneError(f"scan kind must be turntable or linear, got {self.kind!r}")
        try:
            steps, step, settle = int(self.steps), float(self.step), int(self.settle_frames)
        except (TypeError, ValueError):
            raise LightplaneError(f"steps and step must be numbers, got {self.steps!r} and {self.step!r}") from None
        if isinstance(self.steps, bool) or steps != self.steps or steps < 1:
            raise LightplaneError(f"steps must be an integer >= 1, got {self.steps!r}")
        if not (np.isfinite(step) and step != 0):
            raise LightplaneError(f"step must be a finite non-zero number "
                                  f"({'deg' if self.kind == 'turntable' else 'mm'}), got {self.step!r}")
        if settle < 1:
            raise LightplaneError(f"settle_frames must be >= 1, got {self.settle_frames!r}")
        object.__setattr__(self, "steps", steps)
        object.__setattr__(self, "step", step)
        object.__setattr__(self, "folder", Path(self.folder))
        object.__setattr__(self, "settle_frames", settle)


class ScanJob:
    """One scan (``request``) on its own thread (module docstring).  ``capture(after)`` returns the first
    frame exposed after the monotonic time ``after``; ``sensor`` None: the frames are written, no cloud;
    ``options``: how the laser frames are measured; ``source_name``: recorded in ``scan.json``."""

    def __init__(self, request: ScanRequest, *, hardware: Hardware | None, sensor: Sensor | None,
                 options: MeasureOptions, capture: Callable[[float], Frame], source_name: str = "") -> None:
        kind, step = request.kind, request.step
        self.direction = _check_hardware(kind, hardware, sensor)
        assert hardware is not None  # checked above
        self.kind, self.steps, self.step, self.hardware = kind, request.steps, step, hardware
        self.sensor, self.options, self.capture = sensor, options, capture
        self.settle_frames, self.source_name = request.settle_frames, source_name
        n = hardware.n_lasers if sensor is None else min(hardware.n_lasers, len(sensor.planes))
        self.names = [f"laser{i}" for i in range(n)] if sensor is None else list(sensor.planes)[:n]
        if n == 0:
            raise LightplaneError("the hardware has no laser to scan with")
        self.motion = Motion.none()
        if sensor is not None:
            self.motion = Motion.turntable(sensor.turntable, step) if sensor.turntable is not None and \
                kind == "turntable" else Motion.linear(step, self.direction)
        self.folder = prepare_folder(request.folder)
        self.state, self.done = "running", 0
        self.error: str | None = None
        self.files: dict[str, Path] = {}
        self._parts: list[list[np.ndarray]] = [[] for _ in self.names]
        self._preview: list[np.ndarray] = []
        self._lock = threading.Lock()
        self._cancel = threading.Event()
        self._thread = threading.Thread(target=self._run, name="lightplane-scan", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def cancel(self, wait: float = 5.0) -> None:
        self._cancel.set()
        if self._thread.is_alive():
            self._thread.join(wait)

    def status(self) -> dict:
        return {"state": self.state, "done": self.done, "total": self.steps, "folder": str(self.folder),
                "files": {k: str(v) for k, v in self.files.items()}, "error": self.error}

    def points(self, since: int = 0) -> np.ndarray:
        """(n, 3) points (mm, the scan's object frame) measured so far, from the ``since``-th on."""
        with self._lock:
            pts = np.concatenate(self._preview) if self._preview else np.empty((0, 3))
        return pts[max(0, int(since)):]

    # ------------------------------------------------------------------ the scan
    def _grab(self) -> Frame:
        """The ``settle_frames``-th frame exposed after now."""
        after = time.monotonic()
        frame = self.capture(after)
        for _ in range(self.settle_frames - 1):
            frame = self.capture(frame.t_exposure)
        return frame

    def _lasers(self, on: int | None) -> None:
        for i in range(self.hardware.n_lasers):
            self.hardware.set_laser(i, i == on)

    def _run(self) -> None:
        before = self.hardware.laser_states()
        dirs = [self.folder / "pattern"] + [self.folder / n for n in self.names]
        try:
            for d in dirs:
                d.mkdir()
            procs: list[FrameProcessor | None] = [None] * len(self.names)
            for k in range(self.steps):
                if self._cancel.is_set():
                    raise _Cancelled()
                if k:
                    self._move()
                self._lasers(None)
                write_png(dirs[0] / f"{k:04d}.png", self._grab().image)
                for li in range(len(self.names)):
                    self._lasers(li)
                    img = self._grab().image
                    write_png(dirs[li + 1] / f"{k:04d}.png", img)
                    procs[li] = self._measure(li, k, img, procs[li])
                self.done = k + 1
            self.files.update({"pattern": dirs[0], **{n: d for n, d in zip(self.names, dirs[1:])}})
            self._finish()
            self.state = "done"
        except _Cancelled:
            self.state = "stopped"
        except (LightplaneError, OSError, RuntimeError, TimeoutError) as e:
            self.state, self.error = "failed", str(e)
        finally:
            for i, on in enumerate(before):
                self.hardware.set_laser(i, on)

    def _move(self) -> None:
        if self.kind == "turntable":
            self.hardware.move_turntable(self.step)
        else:
            self.hardware.move_stage(self.step)  # type: ignore[attr-defined]  # a Stage, checked

    def _measure(self, li: int, k: int, image: np.ndarray, proc: FrameProcessor | None) -> FrameProcessor | None:
        """Laser ``li``'s frame ``k`` measured (its processor made on its first frame, as a scan's)."""
        if self.sensor is None:
            return None
        if self.sensor.rotate_deg:  # the files hold the frames as the camera gave them; measure rotates them
            image = rotate_image(image, self.sensor.rotate_deg)
        if proc is None:
            plane = self.sensor.planes[self.names[li]]
            self.sensor.camera.check_image(image, "the first laser frame")
            axis = profile_axis(plane) if self.options.axis == "auto" else self.options.axis
            width = self.options.stripe.width_px
            if width is None:
                w = estimate_width(image, channel=self.options.stripe.channel, axis=axis)
                width = float(w) if np.isfinite(w) else None
            opts = replace(self.options, axis=axis, stripe=replace(self.options.stripe, width_px=width))
            proc = FrameProcessor(self.sensor.camera, plane, self.motion, opts)
        rec = proc.process(k, image)
        self._parts[li].append(rec)
        with self._lock:
            self._preview.append(np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(np.float64))
        return proc

    def _finish(self) -> None:
        """sensor.json, scan.json and the cloud."""
        record = {"kind": self.kind, "steps": self.steps, "step": self.step,
                  "step_units": "deg" if self.kind == "turntable" else "mm",
                  "cycle": ["pattern", *self.names], "motion": self.motion.to_dict(),
                  "direction": None if self.direction is None else list(self.direction),
                  "source": self.source_name}
        if self.sensor is not None:
            self.files["sensor"] = self.sensor.save(self.folder / "sensor.json")
            record["measure"] = measure_command(self.names, self.kind, self.step, self.direction, self.options)
        self.files["scan"] = write_json(self.folder / "scan.json", {**record, "provenance": provenance([], record)})
        if self.sensor is None:
            return
        parts = []
        for li, recs in enumerate(self._parts):
            for r in recs:
                out = np.empty(r.size, LASER_POINT_DTYPE)
                for f in POINT_FIELDS:
                    out[f] = r[f]
                out["laser"] = li
                parts.append(out)
        cloud = np.concatenate(parts) if parts else np.empty(0, LASER_POINT_DTYPE)
        self.files["cloud"] = write_cloud(self.folder / "cloud.ply", cloud, comments=[
            f"lightplane point cloud: x y z in mm ({self.motion.frame_description}); laser = index below",
            *(f"laser {i}: {n}" for i, n in enumerate(self.names)), f"live scan: {record['measure']}",
            f"source: {self.source_name}"])


class _Cancelled(Exception):
    pass


def _check_hardware(kind: str, hardware: Hardware | None, sensor: Sensor | None):
    """The scan's hardware checked; the stage's direction for a linear scan (None for a turntable)."""
    if hardware is None:
        raise LightplaneError("a scan needs hardware (lasers and a turntable or a linear stage)")
    if kind == "turntable":
        if not hardware.has_turntable:
            raise LightplaneError("this hardware has no turntable")
        if sensor is not None and sensor.turntable is None:
            raise LightplaneError("the sensor has no turntable calibration (calibrate-turntable, then 'lightplane "
                                  "sensor')")
        return None
    if not getattr(hardware, "has_stage", False):
        raise LightplaneError("this hardware has no linear stage")
    direction = getattr(hardware, "stage_direction", None)
    if direction is None and sensor is not None:
        raise LightplaneError("the linear stage's direction in the camera frame is not known")
    return direction
