"""The live loop: frames from a source, a stripe profile of each, the latest profile and a preview image
for a page, profile events for subscribers, recording and scans.

Two threads: one reads the source into a short queue (:data:`INBOX_FRAMES`), one profiles the frames in
order.  The queue absorbs a moment's delay of the processing (another process taking the core); when it
is full the oldest frame waiting is dropped and counted (with the frames the source itself dropped), so
the latency stays bounded when the processing falls behind for longer.
With a sensor (:class:`lightplane.measure.sensor.Sensor`) a profile is in mm
(:class:`lightplane.measure.profile.ProfileMeasurer`: the camera and one of the sensor's light planes),
else the stripe's centres in px (:func:`lightplane.stripe.extract.extract_profile`).  A sensor whose frames
are rotated (``Sensor.rotate_deg``, e.g. FabScan's) has every frame rotated so before it is measured, as
``lightplane measure`` rotates its image files; the preview shows the rotated frame.

A profile in mm is given in the light plane's own coordinates: ``z`` the distance from the camera along
the plane (the camera's optical axis projected into the plane), ``x`` across, along the laser line (see
:func:`plane_axes`); the points themselves in the camera frame are :meth:`LiveEngine.latest_points`.
"""

from __future__ import annotations

import queue
import threading
import time
from collections import deque
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from lightplane.core.errors import LightplaneError
from lightplane.core.io import CHANNELS, rotate_image
from lightplane.ellipse.detect import EllipseDetectionOptions, detect_ellipses
from lightplane.ellipse.target import select_target
from lightplane.live.recording import Recorder
from lightplane.live.scanning import ScanJob, ScanRequest
from lightplane.live.source import Frame, Hardware, Source
from lightplane.measure.options import MeasureOptions
from lightplane.measure.pointcloud import POINT_DTYPE
from lightplane.measure.profile import ProfileMeasurer
from lightplane.measure.sensor import Sensor
from lightplane.plane.model import LightPlane
from lightplane.plane.triangulate import profile_axis
from lightplane.stripe.extract import estimate_width, extract_profile
from lightplane.stripe.options import StripeOptions

__all__ = ["LiveEngine", "LiveSettings", "plane_axes"]

#: profiles the latency and rate statistics are taken over
STATS_WINDOW = 600
#: events a subscriber's queue holds before its oldest are dropped
SUBSCRIBER_QUEUE = 16
#: frames waiting for the profiling thread before the oldest is dropped
INBOX_FRAMES = 3
#: the circle target is looked for in a preview's frame at most this often (s)
TARGET_EVERY_S = 0.5
#: stripe centres drawn on a preview at most
PREVIEW_POINTS = 2000


@dataclass(frozen=True)
class LiveSettings:
    """The stripe settings of the live profile (checked on construction; a bad value raises
    :class:`LightplaneError`).  The measuring ones are those of ``lightplane measure``: ``channel``
    (red, green, blue, gray, sum or None: weighted grey), ``width_px`` (stripe FWHM; None: estimated on
    the first frame after each change), ``sigma_along_px``, ``axis`` (auto, columns, rows; auto without a
    sensor: columns), ``roi`` (x, y, width, height px), ``smooth_lines``, ``keep_outliers``.  Live only:
    ``laser`` (the sensor plane the live profile uses; None: the plane of the one laser that is on, else the
    sensor's first), ``settle_frames`` (a scan takes the
    n-th frame exposed after each switch of the lasers), ``jpeg_quality`` (preview, 10..100), ``target``
    (find the circle target for the preview, at most every :data:`TARGET_EVERY_S`)."""

    channel: str | None = None
    width_px: float | None = None
    sigma_along_px: float | None = None
    axis: str = "auto"
    roi: tuple[int, int, int, int] | None = None
    smooth_lines: int = 0
    keep_outliers: bool = False
    laser: str | None = None
    settle_frames: int = 1
    jpeg_quality: int = 80
    target: bool = False

    def __post_init__(self) -> None:
        if self.roi is not None:
            try:
                roi = tuple(int(v) for v in self.roi)
            except (TypeError, ValueError):
                raise LightplaneError(f"roi must be x, y, width, height (integer px), got {self.roi!r}") from None
            if len(roi) != 4 or roi[2] < 3 or roi[3] < 3 or roi[0] < 0 or roi[1] < 0:
                raise LightplaneError(f"roi must be x, y, width, height with width, height >= 3, got {self.roi!r}")
            object.__setattr__(self, "roi", roi)
        for name, lo, hi in (("settle_frames", 1, 100), ("jpeg_quality", 10, 100)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                raise LightplaneError(f"{name} must be an integer {lo}..{hi}, got {v!r}")
        if self.channel is not None and self.channel not in CHANNELS:
            raise LightplaneError(f"channel must be one of {', '.join(CHANNELS)} or None, got {self.channel!r}")
        if self.laser is not None and not isinstance(self.laser, str):
            raise LightplaneError(f"laser must be a plane name, got {self.laser!r}")
        self.measure_options()  # the measuring options check themselves

    def measure_options(self) -> MeasureOptions:
        """The settings as :class:`MeasureOptions` (what a scan and ``lightplane measure`` use)."""
        stripe = StripeOptions(width_px=self.width_px, channel=self.channel, sigma_along_px=self.sigma_along_px)
        return MeasureOptions(stripe, axis=self.axis, roi=self.roi, smooth_lines=self.smooth_lines,
                              keep_outliers=bool(self.keep_outliers))

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}


def plane_axes(plane: LightPlane) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The light plane's profile coordinates: ``(origin, e_x, e_z)`` in the camera frame.  ``origin``:
    the plane's point nearest the camera; ``e_z``: the camera's optical axis projected into the plane;
    ``e_x = e_z × normal``, signed so that its largest component is positive."""
    n = plane.normal
    ez = np.array([0.0, 0.0, 1.0]) - n[2] * n
    if np.linalg.norm(ez) < 1e-9:  # the plane faces the camera: depth along camera y instead
        ez = np.array([0.0, 1.0, 0.0]) - n[1] * n
    ez /= np.linalg.norm(ez)
    ex = np.cross(ez, n)
    ex /= np.linalg.norm(ex)
    if ex[np.argmax(np.abs(ex))] < 0:
        ex = -ex
    return -plane.d * n, ex, ez


class _Latest:
    """One profiled frame: the frame, its profile's valid points and where they came from."""

    __slots__ = ("frame", "image", "uv", "xyz", "sigma", "records", "t_done", "units", "plane")

    def __init__(self, frame: Frame, image: np.ndarray, uv: np.ndarray, xyz: np.ndarray | None,
                 sigma: np.ndarray | None, records: np.ndarray | None, t_done: float, units: str,
                 plane: str | None) -> None:
        self.frame, self.image, self.uv, self.xyz, self.sigma = frame, image, uv, xyz, sigma
        self.records, self.t_done, self.units, self.plane = records, t_done, units, plane


class LiveEngine:
    """The live loop over ``source`` (module docstring).

    ``sensor``: profiles in mm (None: the source's own sensor when it has one, as the simulated sensor
    does, else px); ``hardware``: lasers and turntable or stage (None: the source's own hardware when it
    has one); ``settings``: :class:`LiveSettings`.
    """

    def __init__(self, source: Source, *, sensor: Sensor | None = None, hardware: Hardware | None = None,
                 settings: LiveSettings | None = None) -> None:
        self.source = source
        self.sensor = sensor if sensor is not None else getattr(source, "sensor", None)
        self.hardware = hardware if hardware is not None else getattr(source, "hardware", None)
        self._settings = LiveSettings() if settings is None else settings
        if not isinstance(self._settings, LiveSettings):
            raise LightplaneError(f"settings must be LiveSettings, got {type(self._settings).__name__}")
        self.units: Literal["mm", "px"] = "mm" if self.sensor is not None else "px"
        self._check_laser(self._settings.laser)
        self._axes = {} if self.sensor is None else {n: plane_axes(p) for n, p in self.sensor.planes.items()}
        self._proc_lock = threading.Lock()
        self._measurers: dict[str, ProfileMeasurer] = {}  # per plane, for the current settings
        self._stripe: tuple[str, StripeOptions] | None = None  # px: axis and resolved options
        self._cond = threading.Condition()
        self._inbox: deque[Frame] = deque()
        self._grabbed: Frame | None = None
        self._latest: _Latest | None = None
        self._running = False
        self._ended = False
        self._busy = False
        self._error: str | None = None
        self._threads: list[threading.Thread] = []
        self._skipped = 0
        self._frames = 0
        self._lat: deque = deque(maxlen=STATS_WINDOW)
        self._done_t: deque = deque(maxlen=STATS_WINDOW)
        self._subs: list[queue.Queue] = []
        self._subs_lock = threading.Lock()
        self._recorder: Recorder | None = None
        self._scan: ScanJob | None = None
        self._preview_cache: tuple[int, int, tuple[bytes, dict]] | None = None
        self._target: tuple[float, dict | None] = (-np.inf, None)  # when it was looked for, what was found

    # ------------------------------------------------------------------ set-up
    def _check_laser(self, laser: str | None) -> None:
        if laser is None:
            return
        if self.sensor is None:
            raise LightplaneError("settings.laser names a sensor plane, but there is no sensor")
        self.sensor.plane(laser)  # raises for a name the sensor lacks

    def _plane_name(self, frame: Frame) -> str:
        """The sensor plane a frame is measured on: ``settings.laser``, else the plane of the one laser
        that is on (the frame's ``meta["laser"]``, else the hardware's state), else the first."""
        assert self.sensor is not None
        names = list(self.sensor.planes)
        if self._settings.laser is not None:
            return self._settings.laser
        states = frame.meta.get("laser")
        if states is None and self.hardware is not None:
            states = self.hardware.laser_states()
        on = [i for i, v in enumerate(states or ()) if v and i < len(names)]
        return names[on[0]] if len(on) == 1 else names[0]

    def settings(self) -> LiveSettings:
        return self._settings

    def update_settings(self, **changes: Any) -> LiveSettings:
        """New settings (unknown names and bad values raise :class:`LightplaneError`; nothing changes then)."""
        names = {f.name for f in fields(LiveSettings)}
        bad = sorted(set(changes) - names)
        if bad:
            raise LightplaneError(f"no stripe setting {bad[0]!r} (settings: {', '.join(sorted(names))})")
        new = replace(self._settings, **changes)
        self._check_laser(new.laser)
        self._target = (-np.inf, None)
        with self._proc_lock:
            self._settings = new
            self._measurers, self._stripe = {}, None  # rebuilt on the next frame
        return new

    # ------------------------------------------------------------------ threads
    def start(self) -> None:
        """Start reading and profiling (background threads)."""
        if self._running:
            return
        self._running, self._ended, self._error = True, False, None
        self._inbox.clear()
        self._grabbed = None
        self.source.start()
        self._threads = [threading.Thread(target=self._grab_loop, name="lightplane-grab", daemon=True),
                         threading.Thread(target=self._process_loop, name="lightplane-profile", daemon=True)]
        for t in self._threads:
            t.start()

    def stop(self) -> None:
        """Stop the scan, the recording and the threads, and the source."""
        if self._scan is not None and self._scan.state == "running":
            self._scan.cancel()
        if self._recorder is not None:
            self.stop_recording()
        with self._cond:
            self._running = False
            self._cond.notify_all()
        for t in self._threads:
            t.join(5.0)
        self._threads = []
        self.source.stop()

    def _grab_loop(self) -> None:
        while self._running:
            try:
                frame = self.source.read(timeout=0.5)
            except TimeoutError:
                continue
            except Exception as e:  # a source's own failure: shown in the status, the loop ends
                self._error = f"{self.source.name}: {e}"
                frame = None
            with self._cond:
                if frame is None:
                    self._ended = True
                    self._cond.notify_all()
                    return
                if len(self._inbox) >= INBOX_FRAMES:
                    self._inbox.popleft()
                    self._skipped += 1
                self._inbox.append(frame)
                self._grabbed = frame
                self._cond.notify_all()

    def _process_loop(self) -> None:
        while True:
            with self._cond:
                while self._running and not self._inbox and not self._ended:
                    self._cond.wait(0.5)
                if not self._running or (not self._inbox and self._ended):
                    return
                frame = self._inbox.popleft()
                self._busy = True
            try:
                self._process(frame)
            except LightplaneError as e:  # e.g. a frame of another size than the sensor's camera
                self._error = str(e)
            except Exception as e:  # noqa: BLE001 - the loop goes on with the next frame; the status says why
                self._error = f"frame {frame.index}: {type(e).__name__}: {e}"
            finally:
                self._busy = False

    def _process(self, frame: Frame) -> None:
        with self._proc_lock:
            latest = self._profile(frame)
        self._latest = latest
        self._frames += 1
        self._lat.append(latest.t_done - frame.t_exposure)
        self._done_t.append(latest.t_done)
        rec = self._recorder
        if self._subs or rec is not None:
            event = self._event(latest)
            self._publish(event)
            if rec is not None:
                rec.add(frame, {"frame": event["frame"], "t_exposure": event["t_exposure"],
                                "t_received": frame.t_received, **{k: event.get(k) for k in ("x", "z", "sigma_mm",
                                                                                              "u", "v")}},
                        latest.records)

    def _profile(self, frame: Frame) -> _Latest:
        """The frame's profile with the current settings (the measurer built on the first frame after a change)."""
        img = frame.image
        if self.sensor is not None and self.sensor.rotate_deg:
            img = rotate_image(img, self.sensor.rotate_deg)  # as the sensor's frames are read from files
        s = self._settings
        if self.sensor is not None:
            name = self._plane_name(frame)
            m = self._measurers.get(name)
            if m is None:
                plane, opts = self.sensor.planes[name], s.measure_options()
                axis = profile_axis(plane) if opts.axis == "auto" else opts.axis
                w = opts.stripe.width_px
                if w is None:
                    we = estimate_width(img, channel=opts.stripe.channel, axis=axis)
                    w = float(we) if np.isfinite(we) else None
                m = self._measurers[name] = ProfileMeasurer(self.sensor.camera, plane, replace(
                    opts, axis=axis, stripe=replace(opts.stripe, width_px=w)))
            prof = m(img)
            ok = prof.valid
            rec = np.empty(int(ok.sum()), POINT_DTYPE)
            p = prof.points[ok]
            rec["x"], rec["y"], rec["z"] = p[:, 0], p[:, 1], p[:, 2]
            rec["frame"] = frame.index
            rec["intensity"], rec["sigma_mm"] = prof.intensity[ok], prof.sigma_mm[ok]
            rec["u"], rec["v"] = prof.uv[ok, 0], prof.uv[ok, 1]
            return _Latest(frame, img, prof.uv[ok], p, prof.sigma_mm[ok], rec, time.monotonic(), "mm", name)
        if self._stripe is None:
            opts = s.measure_options()
            axis = "columns" if opts.axis == "auto" else opts.axis
            w = opts.stripe.width_px
            if w is None:
                we = estimate_width(img, channel=opts.stripe.channel, axis=axis)
                w = float(we) if np.isfinite(we) else None
            self._stripe = (axis, replace(opts.stripe, width_px=w))
        axis, stripe = self._stripe
        sp = extract_profile(img, axis, stripe, roi=s.roi)
        return _Latest(frame, img, sp.uv[sp.valid], None, None, None, time.monotonic(), "px", None)

    # ------------------------------------------------------------------ what a page reads
    def status(self) -> dict:
        lat = np.array(self._lat) * 1000.0
        t = np.array(self._done_t)
        fps = float((len(t) - 1) / (t[-1] - t[0])) if len(t) > 1 and t[-1] > t[0] else 0.0
        latest = self._latest
        scan = None if self._scan is None else self._scan.status()
        out = {"source": self.source.name, "fps": fps,
               "latency_ms": {"median": float(np.median(lat)) if lat.size else float("nan"),
                              "p99": float(np.percentile(lat, 99)) if lat.size else float("nan")},
               "dropped": int(self.source.dropped) + self._skipped, "frames": self._frames,
               "points": 0 if latest is None else int(len(latest.uv)), "units": self.units,
               "recording": self._recorder is not None, "scan": scan}
        # ended: the source has no more frames and every frame read has been measured
        out["running"], out["error"] = self._running, self._error
        with self._cond:
            out["ended"] = self._ended and not self._inbox and not self._busy
        return out

    def _event(self, latest: _Latest) -> dict:
        f = latest.frame
        ev: dict[str, Any] = {"frame": int(f.index), "t_exposure": float(f.t_exposure), "units": latest.units}
        if latest.units == "mm" and latest.xyz is not None and latest.plane is not None:
            ev["laser"] = latest.plane
            o, ex, ez = self._axes[latest.plane]
            q = latest.xyz - o
            ev["x"], ev["z"] = (q @ ex).tolist(), (q @ ez).tolist()
            sig = latest.sigma
            ev["sigma_mm"] = None if sig is None or not np.isfinite(sig).all() else sig.tolist()
        else:
            ev["u"], ev["v"] = latest.uv[:, 0].tolist(), latest.uv[:, 1].tolist()
            ev["sigma_mm"] = None
        return ev

    def latest_profile(self) -> dict | None:
        latest = self._latest
        return None if latest is None else self._event(latest)

    def latest_points(self) -> tuple[Frame, np.ndarray, np.ndarray | None] | None:
        """The latest profiled frame, its valid points (n, 3) in the camera frame (mm; px mode: (n, 2) stripe
        centres) and their σ (mm; None in px mode)."""
        latest = self._latest
        if latest is None:
            return None
        return latest.frame, (latest.xyz if latest.xyz is not None else latest.uv), latest.sigma

    def latest_preview(self, max_width: int = 640) -> tuple[bytes, dict] | None:
        """A JPEG of the latest profiled frame at most ``max_width`` px wide and ``{"scale": preview px per
        image px, "stripe_uv": the stripe centres in preview px, "target": None, "frame": its counter}``."""
        import cv2

        latest = self._latest
        if latest is None:
            return None
        key = (latest.frame.index, int(max_width))
        cached = self._preview_cache
        if cached is not None and cached[:2] == key:
            return cached[2]
        img = latest.image
        h, w = img.shape[:2]
        scale = min(1.0, max(16, int(max_width)) / w)
        small = cv2.resize(img, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA) \
            if scale < 1 else img
        if small.dtype != np.uint8:
            small = cv2.convertScaleAbs(small, alpha=255.0 / max(float(small.max()), 1.0))
        ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, self._settings.jpeg_quality])
        if not ok:
            return None
        uv = latest.uv
        if len(uv) > PREVIEW_POINTS:
            uv = uv[np.linspace(0, len(uv) - 1, PREVIEW_POINTS).astype(int)]
        target = self._find_target(latest) if self._settings.target else None
        if target is not None:
            target = {**target, "centre": [v * scale for v in target["centre"]],
                      "axes": [v * scale for v in target["axes"]]}
        out = (buf.tobytes(), {"scale": scale, "stripe_uv": np.round(uv * scale, 2).tolist(), "target": target,
                               "frame": int(latest.frame.index)})
        self._preview_cache = (key[0], key[1], out)
        return out

    def _find_target(self, latest: _Latest) -> dict | None:
        """The circle target crossed by the stripe in the latest frame (image px: ``centre``, semi-axes
        ``axes``, ``angle_deg``, ``score``, ``frame``), looked for at most every :data:`TARGET_EVERY_S`."""
        t_last, found = self._target
        now = time.monotonic()
        if now - t_last < TARGET_EVERY_S:
            return found
        img = latest.image
        ellipses = detect_ellipses(img, EllipseDetectionOptions(min_axis_px=max(5.0, img.shape[1] / 100), max_count=8))
        hint = latest.uv if len(latest.uv) >= 10 else None
        e = select_target(img, ellipses, hint).ellipse if ellipses else None
        found = None if e is None else {"centre": [float(e.centre[0]), float(e.centre[1])], "axes": [float(e.a), float(e.b)],
                                        "angle_deg": float(np.degrees(e.angle)), "score": float(e.score),
                                        "frame": int(latest.frame.index)}
        self._target = (now, found)
        return found

    # ------------------------------------------------------------------ subscribers
    def subscribe(self) -> "queue.Queue[dict]":
        """A queue of profile events (:meth:`latest_profile`'s dicts); when it is full its oldest event is
        dropped: a slow subscriber loses its own events and never stalls the loop."""
        q: queue.Queue = queue.Queue(SUBSCRIBER_QUEUE)
        with self._subs_lock:
            self._subs = self._subs + [q]
        return q

    def unsubscribe(self, q: "queue.Queue[dict]") -> None:
        with self._subs_lock:
            self._subs = [s for s in self._subs if s is not q]

    def _publish(self, event: dict) -> None:
        for q in self._subs:
            while True:
                try:
                    q.put_nowait(event)
                    break
                except queue.Full:
                    try:
                        q.get_nowait()
                    except queue.Empty:
                        pass

    # ------------------------------------------------------------------ recording
    def start_recording(self, folder: Path) -> None:
        """Record every profiled frame into ``folder`` (new or empty): ``frames/``, then at
        :meth:`stop_recording` ``profiles.parquet`` and (with a sensor) ``cloud.ply``."""
        if self._recorder is not None:
            raise LightplaneError("already recording")
        meta = {"source": self.source.name, "settings": self._settings.to_dict(), "units": self.units,
                "frame": "x, z: the light plane's coordinates (lightplane.live.engine.plane_axes), mm"
                if self.units == "mm" else "u, v: image pixels"}
        self._recorder = Recorder(folder, self.units, meta)

    def stop_recording(self) -> dict[str, Path]:
        rec, self._recorder = self._recorder, None
        if rec is None:
            raise LightplaneError("not recording")
        return rec.finish()

    # ------------------------------------------------------------------ scans
    def capture(self, after: float, timeout: float = 10.0) -> Frame:
        """The first frame read whose exposure time is after the monotonic time ``after``."""
        end = time.monotonic() + timeout
        with self._cond:
            while True:
                g = self._grabbed
                if g is not None and g.t_exposure > after:
                    return g
                if self._ended or not self._running:
                    raise LightplaneError("the source is not running (it ended or was stopped)")
                left = end - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"no frame from {self.source.name} within {timeout:g} s")
                self._cond.wait(left)

    def start_scan(self, kind: Literal["turntable", "linear"], steps: int, step: float, folder: Path) -> None:
        """Scan into ``folder`` (new or empty; :mod:`lightplane.live.scanning`): ``steps`` steps of ``step``
        degrees (turntable) or mm (linear stage)."""
        if self._scan is not None and self._scan.state == "running":
            raise LightplaneError("a scan is already running")
        if not self._running:
            raise LightplaneError("start the engine before scanning")
        request = ScanRequest(kind, steps, step, Path(folder), self._settings.settle_frames)
        job = ScanJob(request, hardware=self.hardware, sensor=self.sensor, options=self._settings.measure_options(),
                      capture=self.capture, source_name=self.source.name)
        self._scan = job
        job.start()

    def scan_status(self) -> dict:
        if self._scan is None:
            return {"state": "idle", "done": 0, "total": 0, "folder": None, "files": {}, "error": None}
        return self._scan.status()

    def scan_points(self, since: int = 0) -> np.ndarray:
        return np.empty((0, 3)) if self._scan is None else self._scan.points(since)
