"""Frame sources: replays (frames in memory, an image folder, a video file) and UVC/V4L2 cameras, all
through OpenCV, and :func:`open_source`, which opens a source from a spec string.

A replay runs at a fixed frame rate: frame ``k`` is "exposed" at ``t0 + k / fps``.  A consumer that falls
behind does not slow the replay down: when it asks for the next frame, the frames whose time has passed
(all but the newest) are skipped and counted in ``dropped``, and the frame counter jumps by as many, as
with a camera whose buffer overflows.  Like a camera's driver, a replay keeps a queue of ``queue`` frames
(:data:`REPLAY_QUEUE`, the four buffers a V4L2 capture queues by default): a reader that is late by fewer
frames gets them all, oldest first, each with its own exposure time (the latency shows the delay).  Without a frame rate (``fps=None``) every frame is delivered, as fast
as it is asked for.

Specs (:func:`open_source`): ``sim:KIND`` (the simulated sensor, :mod:`lightplane.live.simulated`),
``uvc:N`` or ``/dev/videoN`` (a camera), a folder of images, a video file.  Further schemes are added to
:data:`SCHEMES` (``name -> factory(rest_of_spec, **kw)``).
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from lightplane.core.errors import LightplaneError
from lightplane.core.io import expand_inputs, try_read_image
from lightplane.live.pacing import Pacer
from lightplane.live.simulated import SimulatedSensor
from lightplane.live.aravis import open_aravis
from lightplane.live.genicam import open_genicam
from lightplane.live.source import Control, Frame, Source
from lightplane.measure.scan import VIDEO_SUFFIXES

__all__ = ["ReplaySource", "ArraySource", "FolderSource", "VideoSource", "UVCSource", "open_source", "SCHEMES",
           "register_scheme", "parse_options", "REPLAY_QUEUE"]


#: frames a replay keeps for a late reader (a V4L2 capture's default number of buffers)
REPLAY_QUEUE = 4


class ReplaySource:
    """Frames of a finite sequence replayed at ``fps`` (None: as fast as asked), looped or once, with a
    queue of ``queue`` frames for a late reader (1: only the newest frame waits).

    Subclasses give ``_count()`` and ``_load(i)``; ``_skip(i)`` for a frame not delivered (a video decodes
    it anyway).  ``read`` returns None after the last frame of a replay that does not loop."""

    nominal_fps: float | None

    def __init__(self, name: str, fps: float | None = 30.0, loop: bool = True, queue: int = REPLAY_QUEUE) -> None:
        self.name = name
        self.queue = queue
        self._pacer = Pacer(fps, queue)
        self.nominal_fps = self._pacer.fps
        self.loop = bool(loop)
        self.dropped = 0
        self.frames = 0

    def _count(self) -> int:  # pragma: no cover - interface
        raise NotImplementedError

    def _load(self, i: int) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError

    def _skip(self, i: int) -> None:
        pass

    def start(self) -> None:
        self._pacer.start()
        self.dropped = 0
        self.frames = 0

    def read(self, timeout: float | None = None) -> Frame | None:
        n = self._count()
        k, t, skipped = self._pacer.take(timeout)
        if not self.loop and k >= n:
            self.dropped += max(0, n - (k - skipped))  # frames of the sequence it never delivered
            return None
        for j in range(k - skipped, k):
            self._skip(j % n)
        self.dropped += skipped
        img = self._load(k % n)
        self.frames += 1
        return Frame(img, k, t, time.monotonic(), {"replay_index": k % n})

    def stop(self) -> None:
        pass

    def controls(self) -> dict[str, Control]:
        return {"fps": Control("fps", self.nominal_fps, "1/s", 0.0, None)}

    def set_control(self, name: str, value: Any) -> None:
        if name != "fps":
            raise LightplaneError(f"{self.name}: no control {name!r} (it has: fps)")
        self._pacer = Pacer(None if value is None else float(value), self.queue)
        self.nominal_fps = self._pacer.fps


class ArraySource(ReplaySource):
    """Frames in memory (a sequence of arrays or an (F, H, W[, 3]) array) replayed at ``fps``."""

    def __init__(self, frames: Sequence[np.ndarray] | np.ndarray, fps: float | None = 30.0, loop: bool = True,
                 name: str = "frames in memory", queue: int = REPLAY_QUEUE) -> None:
        if len(frames) == 0:
            raise LightplaneError("no frames to replay")
        super().__init__(f"{name} ({len(frames)} frames)", fps, loop, queue)
        self._frames = frames

    def _count(self) -> int:
        return len(self._frames)

    def _load(self, i: int) -> np.ndarray:
        return np.asarray(self._frames[i])


class FolderSource(ReplaySource):
    """The images of a folder (or files / globs), in natural order, replayed at ``fps``; an unreadable
    file raises :class:`LightplaneError` when its turn comes."""

    def __init__(self, inputs: str | os.PathLike | Sequence[str | os.PathLike], fps: float | None = 30.0,
                 loop: bool = True, queue: int = REPLAY_QUEUE) -> None:
        items = [inputs] if isinstance(inputs, (str, os.PathLike)) else list(inputs)
        self.paths = expand_inputs(items)
        if not self.paths:
            raise LightplaneError(f"no images found in {', '.join(map(str, items))}")
        super().__init__(f"{items[0]} ({len(self.paths)} images)", fps, loop, queue)

    def _count(self) -> int:
        return len(self.paths)

    def _load(self, i: int) -> np.ndarray:
        img, why = try_read_image(self.paths[i])
        if img is None:
            raise LightplaneError(f"{self.paths[i]}: {why}")
        return img


class VideoSource(ReplaySource):
    """A video file decoded with ``cv2.VideoCapture``, replayed at ``fps`` (None: the file's own rate)."""

    def __init__(self, path: str | os.PathLike, fps: float | None = None, loop: bool = True,
                 queue: int = REPLAY_QUEUE) -> None:
        import cv2

        self.path = Path(path)
        if not self.path.is_file():
            raise LightplaneError(f"{self.path}: no such video file")
        self._cap = cv2.VideoCapture(str(self.path))
        if not self._cap.isOpened():
            raise LightplaneError(f"{self.path}: cannot be opened as a video")
        own = float(self._cap.get(cv2.CAP_PROP_FPS))
        self._n = int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT))
        if self._n <= 0:
            raise LightplaneError(f"{self.path}: the video does not say how many frames it has")
        rate = fps if fps is not None else (own if own > 0 else 30.0)
        super().__init__(f"video {self.path.name} ({self._n} frames)", rate, loop, queue)
        self._pos = 0

    def _count(self) -> int:
        return self._n

    def _seek(self, i: int) -> None:
        import cv2

        if i != self._pos:
            if i < self._pos:
                self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
                self._pos = 0
            while self._pos < i:
                self._cap.grab()
                self._pos += 1

    def _skip(self, i: int) -> None:
        self._seek(i)
        self._cap.grab()
        self._pos += 1

    def _load(self, i: int) -> np.ndarray:
        self._seek(i)
        ok, img = self._cap.read()
        self._pos += 1
        if not ok or img is None:
            raise LightplaneError(f"{self.path}: frame {i} cannot be decoded")
        return img

    def start(self) -> None:
        import cv2

        if not self._cap.isOpened():  # stopped before: open it again
            self._cap = cv2.VideoCapture(str(self.path))
        self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
        self._pos = 0
        super().start()

    def stop(self) -> None:
        self._cap.release()


#: the camera controls :class:`UVCSource` exposes, by OpenCV property name (unit, what it sets)
_UVC_PROPS = {"exposure": ("CAP_PROP_EXPOSURE", "driver units"), "gain": ("CAP_PROP_GAIN", "driver units"),
              "fps": ("CAP_PROP_FPS", "1/s"), "width": ("CAP_PROP_FRAME_WIDTH", "px"),
              "height": ("CAP_PROP_FRAME_HEIGHT", "px"), "auto_exposure": ("CAP_PROP_AUTO_EXPOSURE", "driver units")}


class UVCSource:
    """A UVC camera through V4L2 (``cv2.VideoCapture(N, cv2.CAP_V4L2)`` or a ``/dev/videoN`` path).

    A grabbing thread is not used: ``read`` takes the driver's next frame.  Times: ``t_received`` when
    OpenCV hands the frame over; ``t_exposure`` the driver's buffer time stamp when OpenCV gives one on the
    monotonic clock, else ``t_received`` minus one frame period.  Frames the driver lost are counted from
    the gaps between time stamps (more than 1.5 periods).  Controls: exposure, gain, fps, width, height,
    auto_exposure as the driver understands them (``CAP_PROP_*``; a value the driver refuses raises);
    a region of interest is the frame's width and height (the driver's crop is not reachable through OpenCV).
    """

    def __init__(self, device: int | str, *, width: int | None = None, height: int | None = None,
                 fps: float | None = None, exposure: float | None = None, gain: float | None = None) -> None:
        import cv2

        self.name = f"uvc:{device}"
        self._cap = cv2.VideoCapture(device, cv2.CAP_V4L2)
        if not self._cap.isOpened():
            self._cap.release()
            raise LightplaneError(f"{self.name}: no camera there (cannot be opened through V4L2)")
        for key, value in (("width", width), ("height", height), ("fps", fps), ("exposure", exposure),
                           ("gain", gain)):
            if value is not None:
                self.set_control(key, value)
        got = float(self._cap.get(cv2.CAP_PROP_FPS))
        self.nominal_fps = got if got > 0 else None
        self.dropped = 0
        self._index = 0
        self._last: float | None = None

    def start(self) -> None:
        self._index = 0
        self._last = None

    def read(self, timeout: float | None = None) -> Frame | None:
        import cv2

        ok, img = self._cap.read()
        t_rx = time.monotonic()
        if not ok or img is None:
            raise TimeoutError(f"{self.name}: no frame from the camera")
        stamp = float(self._cap.get(cv2.CAP_PROP_POS_MSEC)) / 1000.0
        period = 1.0 / self.nominal_fps if self.nominal_fps else 0.0
        t_exp = stamp if 0.0 < t_rx - stamp < 1.0 else t_rx - period
        if self._last is not None and period > 0:
            gap = int(round((t_exp - self._last) / period)) - 1
            if (t_exp - self._last) > 1.5 * period and gap > 0:
                self.dropped += gap
                self._index += gap
        self._last = t_exp
        frame = Frame(img, self._index, t_exp, t_rx, {})
        self._index += 1
        return frame

    def stop(self) -> None:
        self._cap.release()

    def controls(self) -> dict[str, Control]:
        import cv2

        return {k: Control(k, float(self._cap.get(getattr(cv2, prop))), unit) for k, (prop, unit) in _UVC_PROPS.items()}

    def set_control(self, name: str, value: Any) -> None:
        import cv2

        if name not in _UVC_PROPS:
            raise LightplaneError(f"{self.name}: no control {name!r} (it has: {', '.join(_UVC_PROPS)})")
        if not self._cap.set(getattr(cv2, _UVC_PROPS[name][0]), float(value)):
            raise LightplaneError(f"{self.name}: the camera refuses {name} = {value!r}")
        if name == "fps":
            self.nominal_fps = float(value)


# ----------------------------------------------------------------------------- specs
def parse_options(text: str) -> dict[str, Any]:
    """``key=value,key=value`` → dict (numbers as int/float, true/false as bool)."""
    out: dict[str, Any] = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        key, sep, value = part.partition("=")
        if not sep or not key.strip():
            raise LightplaneError(f"source option {part!r}: write key=value")
        v: Any = value.strip()
        low = v.lower()
        if low in ("true", "false"):
            v = low == "true"
        else:
            for conv in (int, float):
                try:
                    v = conv(v)
                    break
                except ValueError:
                    pass
        out[key.strip()] = v
    return out


def _open_uvc(rest: str, **kw) -> Source:
    device: int | str
    try:
        device = int(rest)
    except ValueError:
        device = rest
    return UVCSource(device, **kw)


def _open_sim(rest: str, **kw) -> Source:
    kind, _, opts = rest.partition(",")
    return SimulatedSensor(kind or "turntable", **{**parse_options(opts), **kw})


def _open_path(rest: str, **kw) -> Source:
    p = Path(rest)
    if p.is_dir() or any(ch in rest for ch in "*?["):
        return FolderSource(rest, **kw)
    if p.suffix.lower() in VIDEO_SUFFIXES:
        return VideoSource(p, **kw)
    if not p.exists():
        raise LightplaneError(f"{rest}: no such folder or video file")
    raise LightplaneError(f"{rest}: not a folder of images or a video file ({', '.join(VIDEO_SUFFIXES)})")


#: source schemes: ``SCHEME:REST`` → ``factory(REST, **kw)``; ``file`` also serves plain paths
SCHEMES: dict[str, Callable[..., Source]] = {"sim": _open_sim, "uvc": _open_uvc, "file": _open_path,
                                             "aravis": open_aravis, "genicam": open_genicam}


def register_scheme(name: str, factory: Callable[..., Source]) -> None:
    """Add a source scheme (``name:...`` specs go to ``factory(rest, **kw)``)."""
    if not name.isidentifier():
        raise LightplaneError(f"a source scheme must be a name, got {name!r}")
    SCHEMES[name] = factory


def open_source(spec: str, **kw) -> Source:
    """The source a spec names: ``sim:KIND[,key=value...]``, ``uvc:N``, ``/dev/videoN``, a folder of
    images or a video file (replayed at ``fps``, looped unless ``loop=False``), or ``SCHEME:...`` of
    :data:`SCHEMES`.  Keyword arguments go to the source (they override options in the spec)."""
    spec = str(spec).strip()
    if not spec:
        raise LightplaneError("no source given (sim:turntable, uvc:0, a folder or a video file)")
    if spec.startswith("/dev/video"):
        return _open_uvc(spec, **kw)
    scheme, sep, rest = spec.partition(":")
    if sep and scheme in SCHEMES and not (len(scheme) == 1 and os.name == "nt"):
        return SCHEMES[scheme](rest, **kw)
    if sep and scheme.isidentifier() and not Path(spec).exists():
        raise LightplaneError(f"source {spec!r}: unknown scheme {scheme!r} (known: {', '.join(sorted(SCHEMES))}; "
                              "or a folder or a video file)")
    return _open_path(spec, **kw)
