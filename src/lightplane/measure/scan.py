"""Scans: a stream of stripe frames with known motion → one point cloud (docs/method.md §Scans).

The object moves through the light sheet (conveyor, linear stage); every frame gives
one profile (:class:`lightplane.measure.profile.ProfileMeasurer`), and the known motion maps
each frame's points back to where the object was at frame 0:

    p_object = p_camera − (offset_i − offset_0)

with ``offset_i`` the object's displacement at frame ``i`` (camera frame, mm):
``i · step · direction`` for a constant step (:meth:`Motion.linear`), or read from an
encoder log (:meth:`Motion.load_positions`).  Without motion the points stay in the
camera frame.

Streaming: frames are read one at a time (image files, a folder, a glob, a video
file via ``cv2.VideoCapture``, or arrays in memory), processed by a pool of worker
processes (each with its own measurer and lookup tables; numba kept to one thread per
worker), a bounded number in flight, results consumed in frame order; points go to a
:class:`lightplane.measure.pointcloud.PointSpool` on disk and are copied into the output at
the end.  Memory therefore does not grow with the number of frames.  A frame that
cannot be read is skipped and reported; a frame whose size differs from the camera's
stops the scan (wrong camera file) and nothing is written.
"""

from __future__ import annotations

import os
import time
from collections import deque
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.core.geometry import default_workers
from lightplane.measure.options import CloudOutput, MeasureOptions
from lightplane.measure.profile import DROP_REASONS, ProfileMeasurer
from lightplane.plane.triangulate import profile_axis
from lightplane.motion.model import Motion, unit_direction  # noqa: F401  (re-exported: lightplane.measure.scan.Motion)
from lightplane.plane.model import LightPlane
from lightplane.measure.pointcloud import POINT_DTYPE, PointSpool, write_cloud
from lightplane.core.io import (MAX_PIXELS_ENV, expand_inputs, max_pixels, provenance, rotation_code,
                                 too_few_images_message, try_read_image)
from lightplane.core.threads import enter_serial, frames_across_threads, serial_kernels
from lightplane.stripe import kernels as K
from lightplane.stripe.extract import estimate_width
from lightplane.core.threads import with_blas_limited

__all__ = [
    "Motion",
    "FrameSource",
    "ImageFiles",
    "VideoFrames",
    "ArrayFrames",
    "open_frames",
    "PairedPath",
    "LaserOnly",
    "FrameProcessor",
    "FrameResult",
    "iter_scan",
    "kernels_release_gil",
    "ScanSummary",
    "Dropped",
    "measure_scan",
    "scan_points",
    "VIDEO_SUFFIXES",
]

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".mjpeg", ".mjpg")


# ----------------------------------------------------------------------------- motion
# Motion (one rigid transform per frame) lives in lightplane.motion.model; imported here so
# that ``lightplane.measure.scan.Motion`` keeps working.


# ----------------------------------------------------------------------------- frame sources
class FrameSource:
    """Frames in order: ``items()`` yields ``(index, name, payload)``; payload is an image
    array or a path that :func:`load_frame` reads (in the worker)."""

    n_frames: int | None = None
    description: str = ""
    #: whether ``n_frames`` is exact (a video container's count may not be: checked at the end)
    exact_count: bool = True

    def items(self) -> Iterator[tuple[int, str, object]]:  # pragma: no cover - interface
        raise NotImplementedError

    def close(self) -> None:
        pass


def load_frame(payload) -> np.ndarray:
    """An image array as is, or read from a path (raises LightplaneError if unreadable)."""
    img, reason = try_load_frame(payload)
    if img is None:
        raise LightplaneError(f"{payload}: {reason}")
    return img


def try_load_frame(payload) -> tuple[np.ndarray | None, str]:
    """``(image, "")``, or ``(None, reason)`` for a file that cannot be read (truncated,
    corrupt, not an image...: :func:`lightplane.core.io.try_read_image`)."""
    if isinstance(payload, np.ndarray):
        return payload, ""

    if isinstance(payload, PairedPath):
        return payload.read()
    if isinstance(payload, RotatedPath):
        return try_read_image(payload.path, rotate_deg=payload.rotate_deg)
    return try_read_image(payload)


@dataclass(frozen=True)
class RotatedPath:
    """An image file read rotated clockwise by ``rotate_deg`` (0/90/180/270), e.g. a
    sensor whose software rotates every frame before use (FabScan)."""

    path: str
    rotate_deg: int

    def __str__(self) -> str:
        return self.path


@dataclass(frozen=True)
class PairedPath:
    """A laser frame read less its laser-off frame (both rotated clockwise by ``rotate_deg``):
    ``laser - background`` per pixel and channel, clipped at 0, in the frames' own type."""

    path: str
    background: str
    rotate_deg: int = 0

    def __str__(self) -> str:
        return self.path

    def read(self) -> tuple[np.ndarray | None, str]:
        import cv2

        img, reason = try_read_image(self.path, rotate_deg=self.rotate_deg)
        if img is None:
            return None, reason
        bg, reason = try_read_image(self.background, rotate_deg=self.rotate_deg)
        if bg is None:
            return None, f"laser-off frame {self.background}: {reason}"
        if bg.shape != img.shape or bg.dtype != img.dtype:
            return None, (f"laser-off frame {self.background} is {_describe(bg)}, the frame {_describe(img)}")
        return LaserOnly.of(cv2.subtract(img, bg), bg), ""


class LaserOnly(np.ndarray):
    """A laser frame less its laser-off frame, which it carries as ``lit`` (the scene's reflectance
    times its ambient light): :class:`~lightplane.measure.profile.ProfileMeasurer` drops the centres
    on uneven reflectance with it.  Anything else reads it as the plain difference image."""

    lit: np.ndarray | None

    @classmethod
    def of(cls, diff: np.ndarray, lit: np.ndarray) -> "LaserOnly":
        out = np.asarray(diff).view(cls)
        out.lit = lit
        return out

    def __array_finalize__(self, obj) -> None:
        self.lit = getattr(obj, "lit", None)


def _describe(img: np.ndarray) -> str:
    return f"{img.shape[1]}x{img.shape[0]} {img.dtype}" + (f" x{img.shape[2]}" if img.ndim == 3 else "")


class ImageFiles(FrameSource):
    """Image files in the given order (use :func:`lightplane.core.io.expand_inputs` for folders/globs).

    ``backgrounds``: laser-off frames, one for all frames or one per frame (same order); each frame is
    then read less its laser-off frame (:class:`PairedPath`)."""

    def __init__(self, paths: Sequence[str | os.PathLike], rotate_deg: int = 0,
                 backgrounds: Sequence[str | os.PathLike] | None = None) -> None:
        rotation_code(rotate_deg)  # 0, 90, 180 or 270
        self.rotate_deg = int(rotate_deg)
        self.paths = [Path(p) for p in paths]
        if not self.paths:
            raise LightplaneError("no input images")
        missing = [str(p) for p in self.paths if not p.exists()]
        if missing:
            raise LightplaneError(f"{missing[0]}: no such file" + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""))
        self.n_frames = len(self.paths)
        self.description = f"{len(self.paths)} image files"
        self.backgrounds: list[Path] | None = None
        if backgrounds is not None:
            bgs = [Path(p) for p in backgrounds]
            if len(bgs) not in (1, len(self.paths)):
                raise LightplaneError(f"{len(bgs)} laser-off frames for {len(self.paths)} frames: give one for all "
                                      "frames or one per frame")
            gone = [str(p) for p in bgs if not p.exists()]
            if gone:
                raise LightplaneError(f"{gone[0]}: no such file")
            same = {p.resolve() for p in bgs} & {p.resolve() for p in self.paths}
            if same:
                raise LightplaneError(f"{sorted(same)[0]} is given both as a frame and as a laser-off frame")
            self.backgrounds = bgs if len(bgs) > 1 else bgs * len(self.paths)
            self.description += (f" less {len(bgs)} laser-off frame" + ("s" if len(bgs) > 1 else ""))

    def items(self):
        for i, p in enumerate(self.paths):
            if self.backgrounds is not None:
                yield i, str(p), PairedPath(str(p), str(self.backgrounds[i]), self.rotate_deg)
            else:
                yield i, str(p), (RotatedPath(str(p), self.rotate_deg) if self.rotate_deg else str(p))


class ArrayFrames(FrameSource):
    """Frames already in memory: a sequence of (H, W[, 3]) arrays or an (F, H, W[, 3]) array."""

    def __init__(self, frames, names: Sequence[str] | None = None) -> None:
        self.frames = frames
        self.n_frames = len(frames)
        self.names = names
        self.description = f"{self.n_frames} frames in memory"

    def items(self):
        for i in range(self.n_frames):
            yield i, (self.names[i] if self.names is not None else f"frame {i}"), self.frames[i]


class _quiet_stderr:
    """Silence native libraries writing to file descriptor 2 inside the block (our errors are one line)."""

    def __enter__(self):
        import sys

        try:
            sys.stderr.flush()
            self.saved = os.dup(2)
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 2)
            os.close(devnull)
        except OSError:  # pragma: no cover - no fd 2
            self.saved = None
        return self

    def __exit__(self, *exc):
        if self.saved is not None:
            os.dup2(self.saved, 2)
            os.close(self.saved)


class VideoFrames(FrameSource):
    """Frames of a video file, decoded sequentially with ``cv2.VideoCapture``.

    Raises :class:`LightplaneError` if the file cannot be opened.  ``n_frames`` is the
    container's frame count (may be approximate; the scan counts the frames it reads).
    """

    def __init__(self, path: str | os.PathLike) -> None:
        import cv2

        self.path = Path(path)
        if not self.path.is_file():
            raise LightplaneError(f"{self.path}: no such video file")
        with _quiet_stderr():  # FFmpeg prints its own complaints ("moov atom not found") to fd 2
            cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            cap.release()
            raise LightplaneError(f"{self.path}: cannot be opened as a video")
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        limit = max_pixels()
        if w * h > limit:  # the container's frame size, checked before any frame is decoded
            cap.release()
            raise LightplaneError(f"{self.path}: frames of {w}x{h} px ({w * h / 1e6:.3g} megapixels) in its header, "
                                  f"above the limit of {limit / 1e6:g} megapixels (--max-pixels or "
                                  f"{MAX_PIXELS_ENV} raises it)")
        self.cap = cap
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        self.n_frames = n if n > 0 else None
        self.description = f"video {self.path.name}" + (f" ({n} frames)" if n > 0 else "")
        self.exact_count = False
        self.frames_read = 0

    def items(self):
        i = 0
        while True:
            ok, frame = self.cap.read()
            if not ok or frame is None:
                break
            yield i, f"{self.path.name}#{i}", frame
            i += 1
            self.frames_read = i

    def close(self) -> None:
        self.cap.release()


def open_frames(inputs: Sequence[str | os.PathLike], rotate_deg: int = 0,
                background: Sequence[str | os.PathLike] | None = None) -> FrameSource:
    """A frame source for CLI-style inputs: one video file, or image files / folders / globs
    (image files read rotated clockwise by ``rotate_deg``; videos are not rotated).  ``background``:
    laser-off frames (files / folders / globs; one for all frames or one per frame, in name order),
    subtracted from the image files' frames."""
    items = [str(x) for x in inputs]
    if not items:
        raise LightplaneError("no input given (image files, a folder, a glob or a video file)")
    videos = [s for s in items if Path(s).suffix.lower() in VIDEO_SUFFIXES]
    if videos:
        if len(items) > 1:
            raise LightplaneError("give either one video file or image files, not both / several videos")
        if rotate_deg:
            raise LightplaneError("frames of a video are not rotated; give image files with a rotation")
        if background is not None:
            raise LightplaneError("laser-off frames go with image files, not with a video")
        return VideoFrames(videos[0])
    paths = expand_inputs(items)
    if not paths:
        raise LightplaneError(f"no images found in {', '.join(items)}")
    bgs = None
    if background is not None:
        bg_items = [str(x) for x in background]
        bgs = expand_inputs(bg_items)
        if not bgs:
            raise LightplaneError(f"no laser-off frames found in {', '.join(bg_items)}")
    return ImageFiles(paths, rotate_deg, backgrounds=bgs)


# ----------------------------------------------------------------------------- processing
@dataclass(frozen=True)
class FrameResult:
    """One frame's outcome: ``records`` (:data:`POINT_DTYPE`, valid points only, placed by
    the motion) or ``error`` (why it was skipped); ``dropped``: reason → points the screen dropped
    (:meth:`lightplane.measure.profile.ProfileMeasurer.screen`)."""

    index: int
    name: str
    records: np.ndarray | None
    error: str | None = None
    dropped: dict = field(default_factory=dict)


class FrameProcessor:
    """Frame → placed point records; picklable (sent once to each worker process)."""

    def __init__(self, camera: Camera, plane: LightPlane, motion: Motion | None = None,
                 options: MeasureOptions = MeasureOptions()) -> None:
        self.measurer = ProfileMeasurer(camera, plane, options)
        self.motion = Motion.none() if motion is None else motion

    @property
    def camera(self) -> Camera:
        return self.measurer.camera

    def process(self, index: int, image: np.ndarray) -> np.ndarray:
        return self._records(index, self.measurer(image))

    def _records(self, index: int, prof) -> np.ndarray:
        ok = prof.valid
        n = int(np.count_nonzero(ok))
        rec = np.empty(n, POINT_DTYPE)
        p = self.motion.apply(index, prof.points[ok])
        rec["x"], rec["y"], rec["z"] = p[:, 0], p[:, 1], p[:, 2]
        rec["frame"] = index
        rec["intensity"] = prof.intensity[ok]
        rec["sigma_mm"] = prof.sigma_mm[ok]
        rec["u"], rec["v"] = prof.uv[ok, 0], prof.uv[ok, 1]
        return rec

    def run(self, index: int, name: str, payload) -> FrameResult:
        """Read (if a path) and process one frame; an unreadable frame gives ``error``.

        A frame of the wrong size raises (a camera mismatch is not a bad frame).
        """
        image, reason = try_load_frame(payload)
        if image is None:
            return FrameResult(index, name, None, reason)
        prof = self.measurer(image)
        return FrameResult(index, name, self._records(index, prof), dropped=prof.dropped)

    def run_batch(self, batch: list) -> list[FrameResult]:
        """:meth:`run` of each ``(index, name, payload)``; regions of interest of few rows
        (:meth:`ProfileMeasurer.batches`) are profiled in one call for the whole batch."""
        if len(batch) < 2 or not self.measurer.batches:
            return [self.run(*item) for item in batch]
        return self.run_loaded([(i, name, *try_load_frame(p)) for i, name, p in batch])

    def run_loaded(self, loaded: list) -> list[FrameResult]:
        """:meth:`run_batch` of frames already read: ``(index, name, image or None, reason)``."""
        images = [im for _, _, im, _ in loaded if im is not None]
        profs = iter(self.measurer.measure_many(images))
        out = []
        for i, name, im, why in loaded:
            if im is None:
                out.append(FrameResult(i, name, None, why))
            else:
                prof = next(profs)
                out.append(FrameResult(i, name, self._records(i, prof), dropped=prof.dropped))
        return out


_WORKER: FrameProcessor | None = None


def _worker_init(processor: FrameProcessor) -> None:
    global _WORKER
    import cv2

    enter_serial()          # one core per worker: numba's own threads would oversubscribe
    cv2.setNumThreads(1)    # and so would OpenCV's (this process is the worker's own)
    processor.measurer.build_lookup()  # each worker builds its own tables once (they are not pickled)
    _WORKER = processor


_SHM: dict = {}


class _ShmFrame:
    """A frame in the shared-memory ring: ``name`` of the block, byte ``offset``, ``shape``, ``dtype``."""

    __slots__ = ("name", "offset", "shape", "dtype")

    def __init__(self, name: str, offset: int, shape: tuple, dtype: str) -> None:
        self.name, self.offset, self.shape, self.dtype = name, offset, shape, dtype

    def view(self) -> np.ndarray:
        shm = _SHM.get(self.name)
        if shm is None:
            from multiprocessing import shared_memory

            # the parent owns and unlinks the block (spawned workers share its resource tracker)
            shm = shared_memory.SharedMemory(name=self.name)
            _SHM[self.name] = shm
        return np.ndarray(self.shape, np.dtype(self.dtype), buffer=shm.buf, offset=self.offset)


def _worker_batch(batch: list) -> list[FrameResult]:
    assert _WORKER is not None
    return _WORKER.run_batch([(i, name, p.view() if isinstance(p, _ShmFrame) else p) for i, name, p in batch])


class _FrameRing:
    """Shared-memory slots for frames sent to worker processes (a copy instead of pickling).

    Created at the first array frame, sized for ``n_slots`` frames of its size; frames
    of another size (or non-arrays) are sent as they are.
    """

    def __init__(self, n_slots: int) -> None:
        self.n_slots = n_slots
        self.shm = None
        self.free: deque = deque()

    def put(self, payload):
        if not isinstance(payload, np.ndarray):
            return payload, None
        if self.shm is None:
            from multiprocessing import shared_memory

            self.nbytes, self.shape, self.dtype = payload.nbytes, payload.shape, payload.dtype
            self.shm = shared_memory.SharedMemory(create=True, size=max(1, self.nbytes * self.n_slots))
            self.free.extend(range(self.n_slots))
        if payload.shape != self.shape or payload.dtype != self.dtype or not self.free:
            return payload, None
        slot = self.free.popleft()
        off = slot * self.nbytes
        np.ndarray(self.shape, self.dtype, buffer=self.shm.buf, offset=off)[...] = payload
        return _ShmFrame(self.shm.name, off, self.shape, self.dtype.str), slot

    def release(self, slots) -> None:
        self.free.extend(s for s in slots if s is not None)

    def close(self) -> None:
        if self.shm is not None:
            self.shm.close()
            self.shm.unlink()
            self.shm = None


def _batches(items: Iterator, size: int) -> Iterator[list]:
    batch = []
    for it in items:
        batch.append(it)
        if len(batch) >= size:
            yield batch
            batch = []
    if batch:
        yield batch


def kernels_release_gil() -> bool:
    """True when the stripe profile's numba kernels are compiled with ``nogil=True``
    (then threads can share one process: one copy of the tables, no frame copies)."""
    names = ("profile_frame", "profiles_batch_serial", "fwhm_median", "frames_points_serial")
    return all(bool(getattr(getattr(K, n, None), "targetoptions", {}).get("nogil")) for n in names)


def _iter_threads(source: FrameSource, processor: FrameProcessor, workers: int, batch: int,
                  limit: int) -> Iterator[FrameResult]:
    from concurrent.futures import ThreadPoolExecutor

    # one level of parallelism: frames across these threads, serial kernels in each
    with frames_across_threads(), ThreadPoolExecutor(workers, initializer=enter_serial) as ex:
        pending: deque = deque()
        try:
            for b in _batches(source.items(), batch):
                while len(pending) >= limit:
                    yield from pending.popleft().result()
                pending.append(ex.submit(processor.run_batch, b))
            while pending:
                yield from pending.popleft().result()
        finally:
            for f in pending:
                f.cancel()


def iter_scan(source: FrameSource, processor: FrameProcessor, *, workers: int | None = None,
              batch: int = 8, in_flight: int | None = None, executor: str = "auto") -> Iterator[FrameResult]:
    """Process every frame of ``source``; yield :class:`FrameResult` in frame order.

    ``workers`` processes or threads (default: the CPUs this process may use; 1: in
    this process, no pool); one level of parallelism: frames across the workers, each
    running the serial kernels (:mod:`lightplane.core.threads`); frames in memory (arrays, video frames) are copied into a
    shared-memory ring (pickling 1.2 MB frames through a pipe costs more than
    measuring them), file paths are read by the workers themselves; frames go to
    them in batches of ``batch``, at most
    ``in_flight`` batches at a time (default ``2 · workers``), so memory stays bounded
    however long the source.  ``executor``: ``"process"`` (worker processes),
    ``"thread"`` (one process; useful only when the stripe kernels release the GIL) or
    ``"auto"`` (threads when :func:`kernels_release_gil`, else processes).
    """
    workers = default_workers() if workers is None else int(workers)
    if workers < 1:
        raise LightplaneError(f"workers must be >= 1, got {workers}")
    if executor not in ("auto", "process", "thread"):
        raise LightplaneError(f"executor must be auto, process or thread, got {executor!r}")
    if workers == 1:
        with serial_kernels():
            if not processor.measurer.batches:
                for item in source.items():
                    yield processor.run(*item)
                return
            # a short roi: profiles a batch at a time; each frame is read as it comes (a source's
            # payload, e.g. a temporary copy of a remote file, may not outlive the next item)
            loaded = ((i, name, *try_load_frame(p)) for i, name, p in source.items())
            for b in _batches(loaded, max(1, int(batch))):
                yield from processor.run_loaded(b)
        return
    limit = 2 * workers if in_flight is None else max(1, int(in_flight))
    batch = max(1, int(batch))
    if executor == "thread" or (executor == "auto" and kernels_release_gil()):
        yield from _iter_threads(source, processor, workers, batch, limit)
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    # spawn: workers must not inherit OpenMP/numba thread state (not fork-safe)
    ctx = mp.get_context("spawn")
    ring = _FrameRing(limit * batch)
    with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_worker_init, initargs=(processor,)) as ex:
        pending: deque = deque()
        try:
            for b in _batches(source.items(), batch):
                while len(pending) >= limit:
                    fut, slots = pending.popleft()
                    res = fut.result()
                    ring.release(slots)
                    yield from res
                items, slots = [], []
                for i, name, payload in b:
                    sent, slot = ring.put(payload)
                    items.append((i, name, sent))
                    slots.append(slot)
                pending.append((ex.submit(_worker_batch, items), slots))
            while pending:
                fut, slots = pending.popleft()
                res = fut.result()
                ring.release(slots)
                yield from res
        finally:
            for fut, _ in pending:
                fut.cancel()
            if pending:  # workers may still read the ring: wait for them before unlinking it
                ex.shutdown(wait=True, cancel_futures=True)
            ring.close()


# ----------------------------------------------------------------------------- scan → file
@dataclass(frozen=True)
class ScanSummary:
    """What a scan did.  ``skipped``: ``(index, name, reason)`` of frames that could not be read;
    ``dropped``: :class:`Dropped`, the points the screen dropped (frames without a stripe, outliers)."""

    path: Path | None
    format: str | None
    n_frames: int
    n_frames_used: int
    n_points: int
    skipped: tuple = ()
    frames_without_points: int = 0
    axis: str = ""
    width_px: float = float("nan")
    motion: dict = field(default_factory=dict)
    seconds: float = float("nan")
    warnings: tuple = ()
    dropped: "Dropped" = field(default_factory=lambda: Dropped())

    @property
    def n_skipped(self) -> int:
        return len(self.skipped)


@dataclass
class Dropped:
    """What a scan's screen dropped (:meth:`lightplane.measure.profile.ProfileMeasurer.screen`):
    ``totals`` reason → points, ``frames`` ``(index, name, {reason: points})`` of each frame with any."""

    totals: dict = field(default_factory=dict)
    frames: list = field(default_factory=list)
    #: frames without a stripe when ``frames`` is not the whole list (a batch's summary keeps only the first ones)
    n_frames_without_stripe: int | None = None

    def add(self, r: FrameResult) -> None:
        if r.dropped:
            self.frames.append((r.index, r.name, dict(r.dropped)))
            for k, v in r.dropped.items():
                self.totals[k] = self.totals.get(k, 0) + int(v)

    @property
    def frames_without_stripe(self) -> int:
        if self.n_frames_without_stripe is not None:
            return self.n_frames_without_stripe
        return sum("no stripe" in d for _, _, d in self.frames)

    def summary(self) -> str:
        """One line: points dropped per reason and frames without a stripe ("" when nothing was dropped)."""
        if not self.totals:
            return ""
        parts = [f"{n} points {why}" if why != "no stripe" else f"{self.frames_without_stripe} frames without a stripe "
                 f"({n} points)" for why, n in sorted(self.totals.items(), key=lambda kv: DROP_REASONS.index(kv[0]))]
        return "dropped: " + ", ".join(parts)

    def comments(self, limit: int = 1000) -> list[str]:
        """The cloud file's lines: the summary, then one per frame with dropped points (at most ``limit``)."""
        if not self.totals:
            return []
        lines = [self.summary()]
        for i, name, d in self.frames[:limit]:
            lines.append(f"frame {i} ({Path(name).name}): dropped " + ", ".join(f"{n} {why}" for why, n in d.items()))
        if len(self.frames) > limit:
            lines.append(f"... and {len(self.frames) - limit} more frames with dropped points")
        return lines


def _first_frame(source: FrameSource) -> tuple[np.ndarray, FrameSource]:
    """The first readable frame (for checks) and a source that still yields every frame."""
    if isinstance(source, VideoFrames):
        it = source.items()
        try:
            first = next(it)
        except StopIteration:
            raise LightplaneError(f"{source.path}: the video has no readable frames") from None

        class _Replay(FrameSource):
            def items(self_inner):
                yield first
                yield from it

        rep = _Replay()
        rep.n_frames = source.n_frames
        rep.description = source.description
        rep.exact_count = False
        return first[2], rep

    skipped = []
    for _, name, payload in source.items():  # nothing usable is fatal: say why for each frame
        img, reason = try_load_frame(payload)
        if img is not None:
            return np.asarray(img), source   # a LaserOnly frame as its plain difference
        skipped.append((name, reason))
    raise LightplaneError(too_few_images_message("frames", 0, 1, skipped))


def _prepare(source, camera, plane, motion, options: MeasureOptions):
    """A scan's checks before any frame is measured; the source (still yielding every frame), the
    motion, and the options with the profile axis and the stripe width resolved (``width_px``
    None: estimated on the first frame, None again when it shows no stripe)."""
    if not isinstance(camera, Camera):
        raise LightplaneError(f"camera must be a Camera, got {type(camera).__name__}")
    if not isinstance(plane, LightPlane):
        raise LightplaneError(f"plane must be a LightPlane, got {type(plane).__name__}")
    motion = Motion.none() if motion is None else motion
    exact = getattr(source, "exact_count", True)  # a video's container count may be approximate: checked at the end
    if exact and motion.n_frames is not None and source.n_frames is not None and motion.n_frames != source.n_frames:
        raise LightplaneError(f"the {motion.what} give {motion.n_frames} frames but the input has {source.n_frames}")
    first, source = _first_frame(source)
    camera.check_image(first, "the first frame")
    axis = profile_axis(plane) if options.axis == "auto" else options.axis
    width_px = options.stripe.width_px
    if width_px is None:
        w = estimate_width(first, channel=options.stripe.channel, axis=axis)
        width_px = float(w) if np.isfinite(w) else None
    return source, motion, replace(options, axis=axis, stripe=replace(options.stripe, width_px=width_px))


@with_blas_limited
def scan_points(source: FrameSource, camera: Camera, plane: LightPlane, options: MeasureOptions = MeasureOptions(),
                *, motion: Motion | None = None, workers: int | None = 1,
                executor: str = "auto",
                progress: Callable[[int, int | None], None] | None = None) -> tuple[np.ndarray, ScanSummary]:
    """In-memory scan: all points as one :data:`POINT_DTYPE` array, and the summary.

    For long scans use :func:`measure_scan` (streams to a file).  ``options``:
    :class:`~lightplane.measure.options.MeasureOptions` (a stripe ``width_px`` of None is
    estimated once on the first frame and used for all frames); ``workers``, ``executor``:
    :func:`iter_scan`; ``progress(done, total)`` after each frame (``total`` None when unknown).
    """
    t0 = time.perf_counter()
    source, motion, opts = _prepare(source, camera, plane, motion, options)
    proc = FrameProcessor(camera, plane, motion, opts)
    parts, skipped, n, empty, dropped = [], [], 0, 0, Dropped()
    for r in iter_scan(source, proc, workers=workers, executor=executor):
        n += 1
        if progress is not None:
            progress(n, source.n_frames)
        if r.error is not None:
            skipped.append((r.index, r.name, r.error))
            continue
        assert r.records is not None  # a frame without an error has its records
        empty += r.records.size == 0
        dropped.add(r)
        parts.append(r.records)
    recs = np.concatenate(parts) if parts else np.empty(0, POINT_DTYPE)
    width_px = opts.stripe.width_px
    summ = ScanSummary(None, None, n, n - len(skipped), int(recs.size), tuple(skipped), int(empty), opts.axis,
                       float("nan") if width_px is None else width_px, motion.to_dict(), time.perf_counter() - t0,
                       dropped=dropped)
    return recs, summ


@with_blas_limited
def measure_scan(source: FrameSource, camera: Camera, plane: LightPlane, out_path: str | os.PathLike,
                 options: MeasureOptions = MeasureOptions(), *, motion: Motion | None = None,
                 output: CloudOutput = CloudOutput(), workers: int | None = None, executor: str = "auto",
                 progress: Callable[[int, int | None], None] | None = None) -> ScanSummary:
    """Scan ``source`` into a point-cloud file (PLY/CSV/NPY, :func:`lightplane.measure.pointcloud.write_cloud`).

    ``options``: :class:`~lightplane.measure.options.MeasureOptions` (as :func:`scan_points`);
    ``output``: :class:`~lightplane.measure.options.CloudOutput` (format, ASCII PLY, overwrite,
    extra comment lines).  Streams: frames are processed by ``workers`` processes and the points
    spooled to a temporary file beside ``out_path``; the output is written (atomically) only when
    every frame has been processed, so a failure leaves nothing behind.

    Errors (:class:`LightplaneError`, nothing written): output exists without
    ``force``; a frame's size differs from the camera's; ``motion`` has positions for a
    different number of frames than the input holds; no frame readable.  Unreadable
    frames are skipped and listed in the summary.  ``progress(done, total)`` is called
    after each frame (``total`` None when unknown).
    """
    t0 = time.perf_counter()
    original = source
    out, fmt = output.target(out_path)
    try:
        source, motion, opts = _prepare(source, camera, plane, motion, options)
        proc = FrameProcessor(camera, plane, motion, opts)
        if workers is None and source.n_frames is not None and source.n_frames < 64:
            workers = 1  # starting a pool costs more than it saves
        with PointSpool(out.parent if str(out.parent) else None) as spool:
            n, skipped, empty, dropped = _spool_scan(iter_scan(source, proc, workers=workers, executor=executor),
                                                     spool, progress, source.n_frames)
            if motion.n_frames is not None and motion.n_frames != n:
                raise LightplaneError(f"the {motion.what} give {motion.n_frames} frames but the input has {n}")
            if n == len(skipped):
                raise LightplaneError(too_few_images_message("frames", 0, 1, [(nm, why) for _, nm, why in skipped]))
            if spool.count == 0:
                raise LightplaneError(no_points_message(n - len(skipped), dropped))
            lines = _scan_comments(source, plane, motion, opts, n, skipped) + dropped.comments() + list(output.comments)
            write_cloud(out, spool, fmt=fmt, ascii=output.ascii, force=output.force, comments=lines)
            n_points = spool.count
    finally:
        original.close()
    warnings = []
    if isinstance(original, VideoFrames) and original.n_frames is not None and n < original.n_frames:
        warnings.append(f"{original.path.name}: the video announces {original.n_frames} frames but only {n} "
                        f"could be decoded (a damaged frame ends a video stream)")
    width_px = opts.stripe.width_px
    return ScanSummary(out, fmt, n, n - len(skipped), n_points, tuple(skipped), int(empty), opts.axis,
                       float("nan") if width_px is None else float(width_px), motion.to_dict(),
                       time.perf_counter() - t0, tuple(warnings), dropped)


def no_points_message(n_readable: int, dropped: "Dropped") -> str:
    """Why a scan has no point at all (one sentence)."""
    if not dropped.totals:
        return (f"no stripe found in any of the {n_readable} readable frames (laser off, wrong --channel or --roi?); "
                "nothing written")
    if set(dropped.totals) == {"no stripe"}:
        return (f"no laser stripe in any of the {n_readable} readable frames (their centres form no line: laser off, "
                "wrong --channel or --roi, or frames of the calibration target?); nothing written")
    return (f"no stripe point left in any of the {n_readable} readable frames ({dropped.summary()}; --keep-outliers "
            "keeps the outliers); nothing written")


def _spool_scan(results: Iterator[FrameResult], spool: PointSpool, progress, total) -> tuple[int, list, int, Dropped]:
    """The frames' points into ``spool``; the number of frames, the skipped ones ``(index, name,
    reason)``, how many frames had no point and what the screen dropped.  ``progress(done, total)``
    after each frame."""
    skipped, n, empty, dropped = [], 0, 0, Dropped()
    for r in results:
        n += 1
        if r.error is not None:
            skipped.append((r.index, r.name, r.error))
        else:
            assert r.records is not None  # a frame without an error has its records
            empty += r.records.size == 0
            dropped.add(r)
            spool.append(r.records)
        if progress is not None:
            progress(n, total)
    return n, skipped, int(empty), dropped


def _scan_comments(source, plane, motion, opts: MeasureOptions, n: int, skipped: list) -> list[str]:
    """A scanned cloud's comment lines: frame, plane, provenance, options, skipped frames."""
    record = {"axis": opts.axis, "roi": opts.roi, "width_px": opts.stripe.width_px, "channel": opts.stripe.channel,
              "motion": motion.to_dict(), "frames": n, "skipped": len(skipped),
              "stripe_evidence": opts.stripe_evidence, "keep_outliers": opts.keep_outliers}
    prov = provenance([getattr(source, "description", "")], record)
    return [f"lightplane point cloud: x y z in mm ({motion.frame_description})",
            f"plane: {plane!r}", f"created: {prov['created_utc']}", f"command: {prov['command']}",
            f"versions: {' '.join(f'{k}={v}' for k, v in prov['versions'].items())}",
            f"options: {record}",
            *(f"skipped frame {i} ({Path(nm).name}): {why}" for i, nm, why in skipped)]
