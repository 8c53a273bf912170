"""Writing what the live sensor sees: frames as lossless PNG files, profiles as a Parquet table, points
as a point cloud.

A recording folder::

    frames/000123.png     every recorded frame, named by the source's frame counter (lossless)
    profiles.parquet      one row per frame: frame, t_exposure, t_received (s, monotonic clock), then
                          x, z, sigma_mm (mm, lists) with a sensor, or u, v (px, lists) without;
                          the file's metadata: units, frame (what x and z are), source, settings
    cloud.ply             with a sensor: every recorded profile's points, camera frame (mm)

Frames are written by a thread of their own through a bounded queue: when the disk cannot keep up,
frames are left out and counted (``frames_dropped``), never silently lost.
"""

from __future__ import annotations

import json
import queue
import threading
from pathlib import Path
from typing import Any

import numpy as np

from lightplane.core.errors import LightplaneError
from lightplane.core.io import atomic_write, provenance
from lightplane.measure.pointcloud import POINT_DTYPE, write_cloud

__all__ = ["write_png", "write_profiles", "Recorder", "prepare_folder"]

#: frames waiting for the disk before new ones are left out
QUEUE_FRAMES = 64


def prepare_folder(folder: str | Path) -> Path:
    """``folder`` created (it must be new or empty: nothing is overwritten)."""
    p = Path(folder)
    if p.exists() and (not p.is_dir() or any(p.iterdir())):
        raise LightplaneError(f"{p}: already exists and is not an empty folder (nothing is overwritten)")
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise LightplaneError(f"{p}: cannot create the folder ({e.strerror})") from None
    return p


def write_png(path: Path, image: np.ndarray) -> Path:
    """``image`` as a lossless PNG (written atomically; fast compression)."""
    import cv2

    def writer(tmp: str) -> None:
        if not cv2.imwrite(tmp, np.ascontiguousarray(image), [cv2.IMWRITE_PNG_COMPRESSION, 1]):
            raise LightplaneError(f"{path}: the image could not be written")

    return atomic_write(path, writer)


def write_profiles(path: Path, rows: list[dict], units: str, meta: dict[str, Any]) -> Path:
    """Profiles as a Parquet table (one row per frame; list columns), ``units`` and ``meta`` in its metadata."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    names = ["x", "z", "sigma_mm"] if units == "mm" else ["u", "v"]
    cols: dict[str, Any] = {
        "frame": pa.array([r["frame"] for r in rows], pa.int64()),
        "t_exposure": pa.array([r["t_exposure"] for r in rows], pa.float64()),
        "t_received": pa.array([r["t_received"] for r in rows], pa.float64()),
    }
    for n in names:
        cols[n] = pa.array([r.get(n) or [] for r in rows], pa.list_(pa.float64()))
    table = pa.table(cols)
    md = {"units": units, "lightplane": json.dumps(meta, default=str)}
    table = table.replace_schema_metadata({k.encode(): v.encode() for k, v in md.items()})
    return atomic_write(path, lambda tmp: pq.write_table(table, tmp))


class Recorder:
    """One recording: frames to ``folder/frames`` on a writer thread, profile rows and points kept in
    memory until :meth:`finish` writes ``profiles.parquet`` and ``cloud.ply``."""

    def __init__(self, folder: str | Path, units: str, meta: dict[str, Any]) -> None:
        import importlib.util

        if importlib.util.find_spec("pyarrow") is None:  # checked before anything is written
            raise LightplaneError("recording writes profiles as Parquet, which needs pyarrow (pip install "
                                  "'lightplane[live]')")
        self.folder = prepare_folder(folder)
        self.frames_dir = self.folder / "frames"
        self.frames_dir.mkdir()
        self.units, self.meta = units, meta
        self.rows: list[dict] = []
        self.points: list[np.ndarray] = []
        self.frames_written = 0
        self.frames_dropped = 0
        self.error: str | None = None
        self._closed = False
        self._lock = threading.Lock()
        self._q: queue.Queue = queue.Queue(QUEUE_FRAMES)
        self._thread = threading.Thread(target=self._write_loop, name="lightplane-recorder", daemon=True)
        self._thread.start()

    def add(self, frame, row: dict, records: np.ndarray | None) -> None:
        """One frame: its image queued for the disk (left out and counted when the queue is full), its
        profile row and point records kept.  Nothing is added once :meth:`finish` has begun."""
        with self._lock:
            if self._closed:
                return
            self.rows.append(row)
            if records is not None and records.size:
                self.points.append(records)
            try:
                self._q.put_nowait((frame.index, frame.image))
            except queue.Full:
                self.frames_dropped += 1

    def _write_loop(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            index, image = item
            try:
                write_png(self.frames_dir / f"{index:06d}.png", image)
                self.frames_written += 1
            except (LightplaneError, OSError) as e:
                self.error = str(e)
                self.frames_dropped += 1

    def finish(self) -> dict[str, Path]:
        """Wait for the frames, write the profiles and the cloud; the files written, by name."""
        with self._lock:
            self._closed = True
        self._q.put(None)
        self._thread.join()
        meta = {**self.meta, "frames_written": self.frames_written, "frames_dropped": self.frames_dropped,
                "provenance": provenance([self.meta.get("source", "")])}
        out = {"frames": self.frames_dir,
               "profiles": write_profiles(self.folder / "profiles.parquet", self.rows, self.units, meta)}
        if self.units == "mm":
            pts = np.concatenate(self.points) if self.points else np.empty(0, POINT_DTYPE)
            out["cloud"] = write_cloud(self.folder / "cloud.ply", pts, comments=[
                "lightplane live recording: x y z in mm (camera frame); frame = the source's frame counter",
                f"source: {self.meta.get('source', '')}", f"frames: {len(self.rows)}",
                f"created: {meta['provenance']['created_utc']}"])
        return out
