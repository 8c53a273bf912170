"""GigE Vision and USB3 Vision cameras through Aravis (the open-source GenICam library), as a ``live.source.Source``.

Aravis is reached through its GObject introspection data (Debian: ``gir1.2-aravis-0.8``) and PyGObject; only this
module imports ``gi``, inside the functions that need it, so that ``import lightplane`` works without them.

Frame counter: the frame's GVSP block id (GigE Vision; 16 bits, wrapping from 65535 to 1) or the USB3 Vision block
id, unwrapped to a counter that only grows; every id missing between two delivered frames is a dropped frame, and
so is every buffer Aravis delivers incomplete.  Aravis' own stream counters (completed buffers, failures,
underruns, missing packets) are in :meth:`AravisSource.statistics`.

Times: ``t_received`` is when the buffer left Aravis' queue.  ``t_exposure`` is, with ``timestamps="camera"``, the
camera's own frame timestamp moved onto ``time.monotonic()`` by the smallest (host arrival - camera timestamp) seen
so far: the camera clock's offset is taken from the fastest frame, so the time from exposure to arrival is
underestimated by that fastest frame's transfer time.  With ``timestamps="system"`` it is the host time at which
Aravis completed the buffer (an upper bound of the exposure's end).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any

from lightplane.core.errors import LightplaneError
from lightplane.live.pixelformats import PIXEL_FORMATS, FrameCounter, convert_pixels
from lightplane.live.source import Control, Frame
from lightplane.live.spec import parse_roi, split_spec

__all__ = ["AravisOptions", "AravisSource", "FrameCounter", "PIXEL_FORMATS", "aravis_devices", "convert_pixels",
           "open_aravis"]


@dataclass(frozen=True)
class AravisOptions:
    """Which camera and how to set it up.  ``device``: Aravis' device id (``Vendor-Model-Serial`` as
    ``arv-tool-0.8`` lists it, or the camera's IP address), ``None`` for the first camera found.  ``pixel_format``
    (a GenICam name such as ``Mono8``), ``exposure_us`` (µs), ``gain_db`` (dB), ``roi`` (x, y, width, height in px)
    and ``frame_rate_hz`` are set on the camera when given.  ``n_buffers`` buffers circulate between Aravis and
    lightplane.  ``timestamps``: ``"camera"`` or ``"system"`` (module doc).  ``packet_socket``: Aravis' faster
    GigE receiver (needs CAP_NET_RAW); ``None`` uses it except for cameras on the loopback address."""

    device: str | None = None
    pixel_format: str | None = None
    exposure_us: float | None = None
    gain_db: float | None = None
    roi: tuple[int, int, int, int] | None = None
    frame_rate_hz: float | None = None
    n_buffers: int = 8
    timestamps: str = "camera"
    packet_socket: bool | None = None

    def __post_init__(self) -> None:
        if self.exposure_us is not None and not self.exposure_us > 0:
            raise LightplaneError(f"exposure_us must be > 0, got {self.exposure_us}")
        if self.frame_rate_hz is not None and not self.frame_rate_hz > 0:
            raise LightplaneError(f"frame_rate_hz must be > 0, got {self.frame_rate_hz}")
        if self.roi is not None and (len(self.roi) != 4 or min(self.roi[2:]) <= 0 or min(self.roi[:2]) < 0):
            raise LightplaneError(f"roi must be x, y, width, height with width, height > 0, got {self.roi}")
        if not 2 <= self.n_buffers <= 256:
            raise LightplaneError(f"n_buffers must be 2 to 256, got {self.n_buffers}")
        if self.timestamps not in ("camera", "system"):
            raise LightplaneError(f"timestamps must be 'camera' or 'system', got {self.timestamps!r}")


def _aravis() -> tuple[Any, Any]:
    """(Aravis, GLib) from GObject introspection, or one LightplaneError that says what to install."""
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis, GLib
    except (ImportError, ValueError) as e:
        raise LightplaneError(
            f"Aravis is not available to Python ({e}): install Aravis' introspection data (Debian: "
            "gir1.2-aravis-0.8) and PyGObject (pip install 'lightplane[aravis]'); docs/live-hardware.md") from None
    return Aravis, GLib


def aravis_devices() -> list[str]:
    """The device ids of the cameras Aravis finds now."""
    Aravis, _ = _aravis()
    Aravis.update_device_list()
    return [Aravis.get_device_id(i) for i in range(Aravis.get_n_devices())]


class AravisSource:
    """A GenICam camera through Aravis (module doc for the counter and the times).  Exposure (µs), gain (dB),
    region of interest (x, y, w, h in px), frame rate (Hz) and pixel format are controls where the camera has
    them; changing the region or the pixel format restarts the stream."""

    def __init__(self, options: AravisOptions | None = None) -> None:
        self.options = options or AravisOptions()
        self.name = f"aravis:{self.options.device or ''}"
        self.nominal_fps: float | None = None
        self.dropped = 0
        self._cam: Any = None
        self._stream: Any = None
        self._counter = FrameCounter()
        self._clock_offset: float | None = None
        self._wall_minus_mono = 0.0
        self._address = ""
        self._lock = threading.RLock()

    # --- life cycle ----------------------------------------------------------------------------------------
    def start(self) -> None:
        Aravis, GLib = _aravis()
        o = self.options
        # the device list is read before the camera is opened: refreshing it while a stream runs disturbs the
        # stream's packet reception
        seen = aravis_devices()
        addresses = {Aravis.get_device_id(i): str(Aravis.get_device_address(i) or "") for i in range(len(seen))}
        self._address = addresses.get(o.device or (seen[0] if seen else ""), o.device or "")
        try:
            self._cam = Aravis.Camera.new(o.device)
        except GLib.Error as e:
            which = f"camera {o.device!r}" if o.device else "camera"
            raise LightplaneError(f"no Aravis {which} ({e.message}); cameras found: "
                                  f"{', '.join(seen) if seen else 'none'}") from None
        self.name = f"aravis:{o.device or self._cam.get_device_id()}"
        self._counter = FrameCounter(wrap=65535 if self._cam.is_gv_device() else None)
        self._configure()
        self._open_stream()

    def _configure(self) -> None:
        o = self.options
        if o.pixel_format is not None:
            self._set("pixel_format", o.pixel_format, restart=False)
        if o.roi is not None:
            self._set("roi", o.roi, restart=False)
        if o.exposure_us is not None:
            self._set("exposure_us", o.exposure_us, restart=False)
        if o.gain_db is not None:
            self._set("gain_db", o.gain_db, restart=False)
        if o.frame_rate_hz is not None:
            self._set("frame_rate_hz", o.frame_rate_hz, restart=False)

    def _open_stream(self) -> None:
        Aravis, GLib = _aravis()
        cam = self._cam
        try:
            if cam.is_gv_device():
                use_packet_socket = self.options.packet_socket
                if use_packet_socket is None:
                    use_packet_socket = not self._address.startswith("127.")
                if not use_packet_socket:
                    cam.gv_set_stream_options(Aravis.GvStreamOption.PACKET_SOCKET_DISABLED)
            stream = cam.create_stream(None, None)
            if cam.is_gv_device():
                stream.set_property("socket-buffer", Aravis.GvStreamSocketBuffer.AUTO)
            payload = cam.get_payload()
            for _ in range(self.options.n_buffers):
                stream.push_buffer(Aravis.Buffer.new_allocate(payload))
            self.nominal_fps = float(cam.get_frame_rate()) if cam.is_frame_rate_available() else None
            self._wall_minus_mono = time.time() - time.monotonic()
            cam.start_acquisition()
        except GLib.Error as e:
            raise LightplaneError(f"{self.name}: the stream did not start ({e.message})") from None
        self._stream = stream

    def _close_stream(self) -> None:
        if self._cam is not None and self._stream is not None:
            _, GLib = _aravis()
            try:
                self._cam.stop_acquisition()
            except GLib.Error:
                pass
        self._stream = None

    def stop(self) -> None:
        with self._lock:
            self._close_stream()
            self._cam = None

    # --- frames --------------------------------------------------------------------------------------------
    def read(self, timeout: float | None = None) -> Frame | None:
        Aravis, _ = _aravis()
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            left = 1.0 if deadline is None else deadline - time.monotonic()
            with self._lock:  # short waits under the lock: a control change from another thread gets its turn
                if self._stream is None:
                    raise LightplaneError(f"{self.name} is not started")
                wait_us = int(min(left, 0.1) * 1e6)
                buf = self._stream.timeout_pop_buffer(wait_us) if wait_us > 0 else self._stream.try_pop_buffer()
                if buf is not None:
                    frame = self._take(Aravis, buf)
                    if frame is not None:
                        return frame
                    continue
            if deadline is not None and time.monotonic() >= deadline:
                raise TimeoutError(f"{self.name}: no frame within {timeout:g} s")

    def _take(self, Aravis: Any, buf: Any) -> Frame | None:
        t_received = time.monotonic()
        try:
            if buf.get_status() != Aravis.BufferStatus.SUCCESS:
                self._counter.advance(buf.get_frame_id())
                self._counter.dropped += 1
                self.dropped = self._counter.dropped
                return None
            return self._frame(buf, t_received)
        finally:
            self._stream.push_buffer(buf)

    def _frame(self, buf: Any, t_received: float) -> Frame:
        image = convert_pixels(buf.get_image_data(), buf.get_image_width(), buf.get_image_height(),
                               buf.get_image_pixel_format())
        frame_id = int(buf.get_frame_id())
        index = self._counter.advance(frame_id)
        self.dropped = self._counter.dropped
        t_system_ns = int(buf.get_system_timestamp())
        t_system = t_system_ns * 1e-9 - self._wall_minus_mono if t_system_ns else t_received
        t_camera_ns = int(buf.get_timestamp())
        t_exposure = t_system
        if self.options.timestamps == "camera" and t_camera_ns:
            offset = t_system - t_camera_ns * 1e-9
            self._clock_offset = offset if self._clock_offset is None else min(self._clock_offset, offset)
            t_exposure = t_camera_ns * 1e-9 + self._clock_offset
        fmt = PIXEL_FORMATS[buf.get_image_pixel_format()][0]
        meta = {"frame_id": frame_id, "t_camera_ns": t_camera_ns, "pixel_format": fmt}
        # the host clock mapping is good to microseconds: an exposure never ends after its frame arrived
        return Frame(image=image, index=index, t_exposure=min(t_exposure, t_received), t_received=t_received,
                     meta=meta)

    def statistics(self) -> dict[str, int]:
        """Aravis' stream counters (``n_completed_buffers``, ``n_failures``, ``n_underruns``, ... as Aravis names
        them) and lightplane's ``dropped``."""
        out = {"dropped": self.dropped}
        if self._stream is not None:
            for i in range(self._stream.get_n_infos()):
                if self._stream.get_info_type(i).name == "guint64":
                    out[self._stream.get_info_name(i)] = int(self._stream.get_info_uint64(i))
        return out

    # --- controls ------------------------------------------------------------------------------------------
    def controls(self) -> dict[str, Control]:
        cam = self._require_camera()
        out: dict[str, Control] = {}
        if cam.is_exposure_time_available():
            lo, hi = cam.get_exposure_time_bounds()
            out["exposure_us"] = Control("exposure_us", float(cam.get_exposure_time()), "µs", lo, hi)
        if cam.is_gain_available():
            lo, hi = cam.get_gain_bounds()
            out["gain_db"] = Control("gain_db", float(cam.get_gain()), "dB", lo, hi)
        if cam.is_frame_rate_available():
            lo, hi = cam.get_frame_rate_bounds()
            out["frame_rate_hz"] = Control("frame_rate_hz", float(cam.get_frame_rate()), "Hz", lo, hi)
        x, y, w, h = cam.get_region()
        out["roi"] = Control("roi", (int(x), int(y), int(w), int(h)), "px")
        out["pixel_format"] = Control("pixel_format", cam.get_pixel_format_as_string())
        return out

    def set_control(self, name: str, value: Any) -> None:
        self._set(name, value, restart=True)

    def _require_camera(self) -> Any:
        if self._cam is None:
            raise LightplaneError(f"{self.name} is not started")
        return self._cam

    def _set(self, name: str, value: Any, restart: bool) -> None:
        with self._lock:
            self._set_locked(name, value, restart)

    def _set_locked(self, name: str, value: Any, restart: bool) -> None:
        cam = self._require_camera()
        _, GLib = _aravis()
        needs_restart = name in ("roi", "pixel_format") and restart and self._stream is not None
        if needs_restart:
            self._close_stream()
        try:
            _SETTERS[name](cam, value)
        except KeyError:
            raise LightplaneError(f"{self.name} has no control {name!r}: use {', '.join(_SETTERS)}") from None
        except (GLib.Error, TypeError, ValueError) as e:
            message = getattr(e, "message", str(e))
            raise LightplaneError(f"{self.name}: cannot set {name} to {value!r} ({message})") from None
        finally:
            if needs_restart:
                self._open_stream()
        if name == "frame_rate_hz":
            self.nominal_fps = float(cam.get_frame_rate())


def _set_exposure(cam: Any, value: Any) -> None:
    if not cam.is_exposure_time_available():
        raise ValueError("the camera has no exposure time")
    cam.set_exposure_time(float(value))


def _set_gain(cam: Any, value: Any) -> None:
    if not cam.is_gain_available():
        raise ValueError("the camera has no gain")
    cam.set_gain(float(value))


def _set_roi(cam: Any, value: Any) -> None:
    x, y, w, h = (int(v) for v in value)
    if w <= 0 or h <= 0 or x < 0 or y < 0:
        raise ValueError("x, y must be >= 0 and width, height > 0")
    cam.set_region(x, y, w, h)
    if tuple(int(v) for v in cam.get_region()) != (x, y, w, h):
        raise ValueError(f"the camera took {tuple(cam.get_region())} instead (its steps or limits)")


_SETTERS = {
    "exposure_us": _set_exposure,
    "gain_db": _set_gain,
    "frame_rate_hz": lambda cam, v: cam.set_frame_rate(float(v)),
    "roi": _set_roi,
    "pixel_format": lambda cam, v: cam.set_pixel_format_from_string(str(v)),
}

_SPEC_KEYS = {"pixel": "pixel_format", "exposure": "exposure_us", "gain": "gain_db", "roi": "roi",
              "fps": "frame_rate_hz", "buffers": "n_buffers", "timestamps": "timestamps",
              "packet_socket": "packet_socket"}


def _spec_value(key: str, value: Any) -> Any:
    field_name = _SPEC_KEYS.get(key, key)
    if not isinstance(value, str):
        return tuple(int(v) for v in value) if field_name == "roi" else value
    try:
        if field_name == "roi":
            return parse_roi(value)
        if field_name == "n_buffers":
            return int(value)
        if field_name == "packet_socket":
            return value.lower() in ("1", "true", "yes", "on")
        if field_name in ("pixel_format", "timestamps"):
            return value
        return float(value)
    except ValueError:
        raise LightplaneError(f"aravis option {key}={value!r} is not valid (roi is x,y,w,h in px)") from None


def open_aravis(spec: str, **kw: Any) -> AravisSource:
    """An Aravis camera from ``aravis[:DEVICE][?exposure=US&gain=DB&roi=X,Y,W,H&fps=HZ&pixel=Mono8&buffers=N&
    timestamps=camera|system&packet_socket=0|1]`` (or the same options after commas: ``aravis:DEVICE,exposure=US,
    roi=X:Y:W:H``); DEVICE is Aravis' device id or an IP address, none for the first camera.  The leading
    ``aravis:`` may be left out.  Keyword arguments (the short names above or ``AravisOptions``' fields) override
    the spec.  The source is returned unstarted."""
    device, pairs = split_spec(spec, "aravis")
    kwargs: dict[str, Any] = {"device": device or None}
    fields = set(_SPEC_KEYS.values())
    for key, value in [*pairs, *kw.items()]:
        if key not in _SPEC_KEYS and key not in fields:
            raise LightplaneError(f"unknown aravis option {key!r}: use {', '.join(_SPEC_KEYS)}")
        kwargs[_SPEC_KEYS.get(key, key)] = _spec_value(key, value)
    return AravisSource(AravisOptions(**kwargs))
