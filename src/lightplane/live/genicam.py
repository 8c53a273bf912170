"""GenICam cameras through a GenTL producer (the camera vendor's ``.cti`` file) and ``harvesters``, as a
``live.source.Source``.  Only this module imports ``harvesters``, inside the functions that need it.

Frame counter: the GenTL buffer's frame id (64 bits), unwrapped by ``live.pixelformats.FrameCounter``; missing ids
are dropped frames, and so are incomplete buffers.  Times: ``t_exposure`` is the buffer's GenTL timestamp moved
onto ``time.monotonic()`` by the smallest (arrival - timestamp) seen so far (as ``live.aravis`` does), or the
arrival time when the producer gives no timestamp (``meta["timestamp"]`` says which).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from lightplane.core.errors import LightplaneError
from lightplane.live.pixelformats import PIXEL_FORMAT_CODES, FrameCounter, convert_pixels
from lightplane.live.source import Control, Frame
from lightplane.live.spec import parse_roi, split_spec

#: lightplane's control -> the GenICam SFNC feature names that carry it, first found wins
_FEATURES = {
    "exposure_us": ("ExposureTime", "ExposureTimeAbs"),
    "gain_db": ("Gain",),
    "frame_rate_hz": ("AcquisitionFrameRate", "AcquisitionFrameRateAbs"),
    "pixel_format": ("PixelFormat",),
}
_UNITS = {"exposure_us": "µs", "gain_db": "dB", "frame_rate_hz": "Hz", "pixel_format": ""}


@dataclass(frozen=True)
class GenICamOptions:
    """The GenTL producer (``cti``: path of the ``.cti`` file), which camera (``serial``: its serial number, or
    ``index`` in the producer's device list) and the settings to apply (as in ``live.aravis.AravisOptions``)."""

    cti: str
    serial: str | None = None
    index: int = 0
    pixel_format: str | None = None
    exposure_us: float | None = None
    gain_db: float | None = None
    roi: tuple[int, int, int, int] | None = None
    frame_rate_hz: float | None = None
    n_buffers: int = 8

    def __post_init__(self) -> None:
        if not self.cti:
            raise LightplaneError("a GenICam source needs the GenTL producer's .cti file: genicam:/path/to/x.cti")
        if self.index < 0:
            raise LightplaneError(f"index must be >= 0, got {self.index}")
        if self.exposure_us is not None and not self.exposure_us > 0:
            raise LightplaneError(f"exposure_us must be > 0, got {self.exposure_us}")
        if self.roi is not None and (len(self.roi) != 4 or min(self.roi[2:]) <= 0 or min(self.roi[:2]) < 0):
            raise LightplaneError(f"roi must be x, y, width, height with width, height > 0, got {self.roi}")
        if not 1 <= self.n_buffers <= 256:
            raise LightplaneError(f"n_buffers must be 1 to 256, got {self.n_buffers}")


def _harvester() -> Any:
    try:
        from harvesters.core import Harvester
    except ImportError as e:
        raise LightplaneError(f"harvesters is not installed ({e}): pip install 'lightplane[genicam]'") from None
    return Harvester


class GenICamSource:
    """A GenICam camera through its GenTL producer.  Exposure (µs), gain (dB), frame rate (Hz), pixel format and
    region of interest (x, y, w, h in px) are controls where the camera's node map has the SFNC features."""

    def __init__(self, options: GenICamOptions) -> None:
        self.options = options
        self.name = f"genicam:{Path(options.cti).name}"
        self.nominal_fps: float | None = None
        self.dropped = 0
        self._h: Any = None
        self._ia: Any = None
        self._counter = FrameCounter(wrap=None)
        self._clock_offset: float | None = None
        self._lock = threading.RLock()

    def start(self) -> None:
        o = self.options
        if not Path(o.cti).is_file():
            raise LightplaneError(f"GenTL producer {o.cti} does not exist")
        h = _harvester()()
        try:
            h.add_file(o.cti, check_existence=True)
            h.update()
        except Exception as e:  # the producer's own exception types
            h.reset()
            raise LightplaneError(f"the GenTL producer {o.cti} could not be loaded ({e})") from None
        devices = [f"{d.model} #{d.serial_number}" for d in h.device_info_list]
        key: Any = {"serial_number": o.serial} if o.serial is not None else o.index
        if (o.serial is not None and not any(d.serial_number == o.serial for d in h.device_info_list)) \
                or (o.serial is None and o.index >= len(devices)):
            h.reset()
            which = f"serial {o.serial!r}" if o.serial is not None else f"index {o.index}"
            raise LightplaneError(f"no camera with {which} behind {Path(o.cti).name}; cameras found: "
                                  f"{', '.join(devices) if devices else 'none (is it a GenTL producer for your camera?)'}")
        try:
            self._ia = h.create(key)
        except Exception as e:
            h.reset()
            raise LightplaneError(f"cannot open the camera {key!r} of {Path(o.cti).name} ({e})") from None
        self._h = h
        d = self._ia.remote_device.node_map
        self.name = f"genicam:{Path(o.cti).name}:{self._ia.device.node_map.DeviceSerialNumber.value}" \
            if hasattr(self._ia.device.node_map, "DeviceSerialNumber") else self.name
        for name, value in (("pixel_format", o.pixel_format), ("roi", o.roi), ("exposure_us", o.exposure_us),
                            ("gain_db", o.gain_db), ("frame_rate_hz", o.frame_rate_hz)):
            if value is not None:
                self.set_control(name, value)
        self._ia.num_buffers = max(o.n_buffers, getattr(self._ia, "min_num_buffers", 1))
        self.nominal_fps = self._float_feature(d, "frame_rate_hz")
        self._ia.start()

    def stop(self) -> None:
        with self._lock:
            self._stop()

    def _stop(self) -> None:
        if self._ia is not None:
            try:
                self._ia.stop()
                self._ia.destroy()
            finally:
                self._ia = None
        if self._h is not None:
            self._h.reset()
            self._h = None

    def read(self, timeout: float | None = None) -> Frame | None:
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            left = 1.0 if deadline is None else deadline - time.monotonic()
            with self._lock:  # short waits under the lock: a control change from another thread gets its turn
                if self._ia is None:
                    raise LightplaneError(f"{self.name} is not started")
                buf = self._ia.try_fetch(timeout=min(left, 0.1)) if left > 0 else None
                if buf is not None:
                    t_received = time.monotonic()
                    try:
                        frame = self._frame(buf, t_received)
                    finally:
                        buf.queue()
                    if frame is not None:
                        return frame
                    continue
            if deadline is not None and time.monotonic() >= deadline:
                raise TimeoutError(f"{self.name}: no frame within {timeout:g} s")

    def _frame(self, buf: Any, t_received: float) -> Frame | None:
        frame_id = int(buf.frame_id)
        if getattr(buf, "is_complete", lambda: True)() is False or not buf.payload.components:
            self._counter.advance(frame_id)
            self._counter.dropped += 1
            self.dropped = self._counter.dropped
            return None
        c = buf.payload.components[0]
        fmt = str(c.data_format)
        if fmt not in PIXEL_FORMAT_CODES:
            raise LightplaneError(f"{self.name}: pixel format {fmt} is not supported: choose Mono8, Mono16, an "
                                  "unpacked Bayer format, RGB8 or BGR8")
        image = convert_pixels(c.data.tobytes(), int(c.width), int(c.height), PIXEL_FORMAT_CODES[fmt])
        index = self._counter.advance(frame_id)
        self.dropped = self._counter.dropped
        try:
            t_cam_ns = int(buf.timestamp_ns)
        except Exception:  # producers without timestamps raise NotAvailable
            t_cam_ns = 0
        t_exposure, source = t_received, "arrival"
        if t_cam_ns:
            offset = t_received - t_cam_ns * 1e-9
            self._clock_offset = offset if self._clock_offset is None else min(self._clock_offset, offset)
            t_exposure, source = t_cam_ns * 1e-9 + self._clock_offset, "camera"
        meta = {"frame_id": frame_id, "pixel_format": fmt, "timestamp": source, "t_camera_ns": t_cam_ns}
        return Frame(image=image, index=index, t_exposure=t_exposure, t_received=t_received, meta=meta)

    # --- controls ------------------------------------------------------------------------------------------
    def _node_map(self) -> Any:
        if self._ia is None:
            raise LightplaneError(f"{self.name} is not started")
        return self._ia.remote_device.node_map

    @staticmethod
    def _feature(nm: Any, name: str) -> Any:
        for feature in _FEATURES[name]:
            if nm.has_node(feature):
                return getattr(nm, feature)
        return None

    def _float_feature(self, nm: Any, name: str) -> float | None:
        node = self._feature(nm, name)
        return None if node is None else float(node.value)

    def controls(self) -> dict[str, Control]:
        nm = self._node_map()
        out: dict[str, Control] = {}
        for name in _FEATURES:
            node = self._feature(nm, name)
            if node is None:
                continue
            lo = float(node.min) if hasattr(node, "min") and name != "pixel_format" else None
            hi = float(node.max) if hasattr(node, "max") and name != "pixel_format" else None
            value = str(node.value) if name == "pixel_format" else float(node.value)
            out[name] = Control(name, value, _UNITS[name], lo, hi)
        x = int(nm.OffsetX.value) if nm.has_node("OffsetX") else 0
        y = int(nm.OffsetY.value) if nm.has_node("OffsetY") else 0
        out["roi"] = Control("roi", (x, y, int(nm.Width.value), int(nm.Height.value)), "px")
        return out

    def set_control(self, name: str, value: Any) -> None:
        with self._lock:
            self._set_control(name, value)

    def _set_control(self, name: str, value: Any) -> None:
        nm = self._node_map()
        was_acquiring = bool(self._ia.is_acquiring()) if name in ("roi", "pixel_format") else False
        if was_acquiring:
            self._ia.stop()
        try:
            if name == "roi":
                self._set_roi(nm, value)
            elif name in _FEATURES:
                node = self._feature(nm, name)
                if node is None:
                    raise LightplaneError(f"{self.name} has no {name} (none of {', '.join(_FEATURES[name])})")
                node.value = str(value) if name == "pixel_format" else float(value)
            else:
                raise LightplaneError(f"{self.name} has no control {name!r}: use {', '.join([*_FEATURES, 'roi'])}")
        except LightplaneError:
            raise
        except Exception as e:  # GenApi's own exception types (out of range, not writable)
            raise LightplaneError(f"{self.name}: cannot set {name} to {value!r} ({e})") from None
        finally:
            if was_acquiring:
                self._ia.start()
        if name == "frame_rate_hz":
            self.nominal_fps = self._float_feature(nm, "frame_rate_hz")

    def _set_roi(self, nm: Any, value: Any) -> None:
        x, y, w, h = (int(v) for v in value)
        if (x or y) and not (nm.has_node("OffsetX") and nm.has_node("OffsetY")):
            raise LightplaneError(f"{self.name} has no OffsetX/OffsetY: its region of interest starts at 0, 0")
        if nm.has_node("OffsetX"):
            nm.OffsetX.value, nm.OffsetY.value = 0, 0
        nm.Width.value, nm.Height.value = w, h
        if nm.has_node("OffsetX"):
            nm.OffsetX.value, nm.OffsetY.value = x, y


_SPEC_KEYS = {"serial": "serial", "index": "index", "pixel": "pixel_format", "exposure": "exposure_us",
              "gain": "gain_db", "roi": "roi", "fps": "frame_rate_hz", "buffers": "n_buffers"}


def open_genicam(spec: str, **kw: Any) -> GenICamSource:
    """A GenICam camera from ``genicam:/path/to/producer.cti[?serial=S|index=N&exposure=US&gain=DB&roi=X,Y,W,H&
    fps=HZ&pixel=Mono8&buffers=N]`` (or the options after commas, ``roi=X:Y:W:H``); the first camera of the
    producer by default; the leading ``genicam:`` may be left out.  Keyword arguments (short names or
    ``GenICamOptions``' fields) override the spec.  Returned unstarted."""
    cti, pairs = split_spec(spec, "genicam")
    kwargs: dict[str, Any] = {"cti": cti}
    fields = set(_SPEC_KEYS.values())
    for key, value in [*pairs, *kw.items()]:
        if key not in _SPEC_KEYS and key not in fields:
            raise LightplaneError(f"unknown genicam option {key!r}: use {', '.join(_SPEC_KEYS)}")
        field = _SPEC_KEYS.get(key, key)
        if not isinstance(value, str):
            kwargs[field] = tuple(int(v) for v in value) if field == "roi" else value
            continue
        try:
            if field == "roi":
                kwargs[field] = parse_roi(value)
            elif field in ("index", "n_buffers"):
                kwargs[field] = int(value)
            elif field in ("serial", "pixel_format"):
                kwargs[field] = value
            else:
                kwargs[field] = float(value)
        except ValueError:
            raise LightplaneError(f"genicam option {key}={value!r} is not valid (roi is x,y,w,h in px)") from None
    return GenICamSource(GenICamOptions(**kwargs))
