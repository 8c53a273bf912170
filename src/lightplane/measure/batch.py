"""Batch measurement of many scans on a Dask cluster (``lightplane measure-batch``).

A *manifest* (CSV with a header) names the scans: ``id,input,camera,plane`` and the
optional ``step,direction,positions,background`` (direction written ``x;y;z``), with the meaning
they have in ``lightplane measure``.  Relative paths are taken relative to the
manifest's folder.  Each scan's frames are listed on the client (a folder listing, no
image is read there) and cut into *chunks* of consecutive frames; one Dask task per
chunk reads its own frames (paths on a filesystem the workers share, or fsspec URLs
such as ``s3://bucket/scan/*.png``, copied to a local temporary file and read as a local
file is; a video is one chunk, decoded from its start) and measures them
with the very code ``measure`` runs (:class:`lightplane.measure.scan.FrameProcessor`, one frame
at a time), so the points are bitwise those of ``measure`` whatever the number of
workers and the chunking:

- the only quantity ``measure`` takes from more than one frame, the stripe width
  estimated on the first readable frame (when not given), is estimated once per scan by
  a small *prepare* task (the same function ``measure`` calls) and handed to every
  chunk of that scan;
- the motion places frame ``i`` by its global index ``i``, known from the chunk's start.

Output (``OUT_DIR``)::

    points/scan=<id>/part-<k>.parquet   chunk k of scan <id>: columns x,y,z,frame,
                                        intensity,sigma_mm,u,v (as measure's CSV) and
                                        scan (the id, a string)
    ply/<id>.ply                        optional, one cloud per scan
    manifest.json                       status ("in progress", then "ok" or "failed"),
                                        what was written, failures, provenance
    set-aside/                          partitions (and PLY files) of scans that failed or
                                        left the manifest, moved out of the dataset
    .lightplane-batch.lock              while a run writes here: its pid, host, start

One run at a time: a run holds ``.lightplane-batch.lock`` (created with ``O_CREAT|O_EXCL``)
from its start to its end; a second run refuses, naming the holder; a lock left by a
process of this host that is no longer running is taken over; a lock from another host
is broken only when asked (``BatchOptions(break_lock=True)``, ``--break-lock``).

Faults and resume: a partition is (scan, chunk); its name is deterministic and it is
written to a hidden temporary name then renamed, so a task retried after a worker died
rewrites the same file and a reader never sees half a partition.  Each partition
carries in its Parquet metadata the fingerprint of what produced it (its frames' names,
sizes and modification times, the SHA-256 of the camera, plane and positions files, the
motion, the options, the layout and the code's versions) and the chunk's own summary
(unreadable frames...); a re-run keeps the partitions whose fingerprint is the current
one and measures the rest (a partition with another fingerprint is removed before its
chunk is measured again).  ``manifest.json`` says "in progress" from a run's start and
"ok" or "failed" only at its end, once the partitions of failed or dropped scans are set
aside, so that the dataset read with :func:`scan_partitioning` holds exactly the points
of the scans the manifest lists as ok.  An unreadable frame is skipped and recorded for
its scan; a scan whose input, camera or plane cannot be used fails alone; the others go on.
"""

from __future__ import annotations

import codecs
import contextlib
import csv
import datetime as _dt
import hashlib
import io
import json
import os
import re
import shutil
import socket
import time
import uuid
import warnings
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np

from lightplane.core.errors import LightplaneError
from lightplane.measure.options import MeasureOptions
from lightplane.measure.pointcloud import FIELD_UNITS, POINT_DTYPE, POINT_FIELDS
from lightplane.measure.scan import FrameSource
from lightplane.camera.model import Camera
from lightplane.core.io import IMAGE_SUFFIXES, atomic_write, expand_inputs, provenance, versions, write_json
from lightplane.measure.pointcloud import PointSpool, write_cloud
from lightplane.measure.scan import (Dropped, FrameProcessor, ImageFiles, PairedPath, VIDEO_SUFFIXES, VideoFrames, _prepare,
                                     iter_scan)
from lightplane.motion.model import Motion
from lightplane.plane.model import LightPlane, check_camera
from lightplane.core.threads import frames_across_threads, with_blas_limited

__all__ = ["BatchScan", "BatchOptions", "read_manifest", "plan_chunks", "measure_batch", "BatchResult", "read_points",
           "open_dataset", "scan_partitioning", "DATASET_READ", "DEFAULT_CHUNK_FRAMES", "LOCK_NAME", "SET_ASIDE",
           "local_cluster", "require_extra"]

DEFAULT_CHUNK_FRAMES = 200
REQUIRED_COLUMNS = ("id", "input", "camera", "plane")
OPTIONAL_COLUMNS = ("step", "direction", "positions", "background")
_ID_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")
_META_KEY = b"lightplane"
#: bump when the partition layout or the meaning of its metadata changes
_LAYOUT = 2
#: the lock file a run holds in its output folder
LOCK_NAME = ".lightplane-batch.lock"
#: frames listed with their dropped points in a scan's manifest entry (the totals count every frame)
MAX_DROPPED_FRAMES = 1000
#: the folder (in the output folder, beside points/) that receives the partitions of failed or dropped scans
SET_ASIDE = "set-aside"


# ----------------------------------------------------------------------------- manifest
@dataclass(frozen=True)
class BatchScan:
    """One row of the manifest (paths resolved against the manifest's folder; cells as written)."""

    id: str
    input: str
    camera: str
    plane: str
    step: str = ""
    direction: str = ""
    positions: str = ""
    row: int = 0
    background: str = ""


def _resolve(cell: str, base: Path) -> str:
    if not cell or "://" in cell or os.path.isabs(cell):
        return cell
    return str(base / cell)


def _manifest_text(p: Path) -> str:
    """The manifest's text: UTF-8 (with or without a byte-order mark) or UTF-16 with its byte-order mark."""
    try:
        raw = p.read_bytes()
    except OSError as e:
        raise LightplaneError(f"{p}: cannot be read ({e.strerror or type(e).__name__})") from None
    if raw.startswith((codecs.BOM_UTF32_LE, codecs.BOM_UTF32_BE)):
        raise LightplaneError(f"{p}: the manifest is UTF-32 text; save it as UTF-8 (or UTF-16)")
    encoding = "utf-16" if raw.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)) else "utf-8-sig"
    if encoding == "utf-8-sig" and b"\x00" in raw:
        raise LightplaneError(f"{p}: the manifest holds NUL bytes, not UTF-8 text (UTF-16 text needs its "
                              "byte-order mark); save it as UTF-8")
    try:
        text = raw.decode(encoding)
    except UnicodeDecodeError as e:
        what = "UTF-16" if encoding == "utf-16" else "UTF-8"
        raise LightplaneError(f"{p}: the manifest is not {what} text (byte {e.start} cannot be decoded); "
                              "save it as UTF-8") from None
    if "\x00" in text:
        raise LightplaneError(f"{p}: the manifest holds NUL characters, not CSV text; save it as UTF-8")
    return text


def _manifest_rows(p: Path) -> list[list[str]]:
    """The manifest's rows, blank lines and ``#`` comments left out."""
    try:
        rows = list(csv.reader(io.StringIO(_manifest_text(p), newline="")))
    except csv.Error as e:
        raise LightplaneError(f"{p}: not a valid CSV manifest ({e})") from None
    return [r for r in rows if r and not (len(r) == 1 and not r[0].strip()) and not r[0].lstrip().startswith("#")]


def read_manifest(path: str | os.PathLike) -> list[BatchScan]:
    """The scans of a manifest CSV (UTF-8, with or without a byte-order mark, or UTF-16 with
    one); raises :class:`LightplaneError` for a malformed manifest (other bytes, no header,
    a required column missing, an unknown column, an empty or duplicate id, an id unusable
    as a folder name).  Values are checked per scan when it runs."""
    p = Path(path)
    if not p.is_file():
        raise LightplaneError(f"{p}: no such manifest file")
    base = p.resolve().parent
    rows = _manifest_rows(p)
    if not rows:
        raise LightplaneError(f"{p}: manifest is empty (expected a header id,input,camera,plane)")
    header = [h.strip().lower() for h in rows[0]]
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise LightplaneError(f"{p}: the header must name the columns id,input,camera,plane "
                              f"(missing: {','.join(missing)}; got {','.join(header)!r})")
    unknown = [c for c in header if c not in REQUIRED_COLUMNS + OPTIONAL_COLUMNS]
    if unknown:
        raise LightplaneError(f"{p}: unknown column(s) {','.join(unknown)!r} (known: "
                              f"{','.join(REQUIRED_COLUMNS + OPTIONAL_COLUMNS)})")
    scans, seen = [], set()
    for n, r in enumerate(rows[1:], start=2):
        if len(r) > len(header):
            raise LightplaneError(f"{p}: row {n} has {len(r)} cells but the header names {len(header)} "
                                  "(quote a cell that holds a comma)")
        cells = {h: (r[i].strip() if i < len(r) else "") for i, h in enumerate(header)}
        sid = cells["id"]
        if not sid:
            raise LightplaneError(f"{p}: row {n} has no id")
        if not _ID_RE.fullmatch(sid):
            raise LightplaneError(f"{p}: row {n}: id {sid!r} must be letters, digits, '.', '_' or '-' "
                                  "(it names a folder)")
        if sid in seen:
            raise LightplaneError(f"{p}: row {n}: id {sid!r} appears twice")
        seen.add(sid)
        for c in ("input", "camera", "plane"):
            if not cells[c]:
                raise LightplaneError(f"{p}: row {n} (scan {sid}) has no {c}")
        scans.append(BatchScan(sid, _resolve(cells["input"], base), _resolve(cells["camera"], base),
                               _resolve(cells["plane"], base), cells.get("step", ""), cells.get("direction", ""),
                               _resolve(cells.get("positions", ""), base), n,
                               _resolve(cells.get("background", ""), base)))
    if not scans:
        raise LightplaneError(f"{p}: manifest has a header but no scans")
    return scans


def _motion_of(scan: BatchScan):
    dvec = None
    if scan.direction:
        try:
            dvec = tuple(float(t) for t in re.split(r"[;,\s]+", scan.direction.strip()) if t)
        except ValueError:
            dvec = ()
        if len(dvec) != 3:
            raise LightplaneError(f"direction must be x;y;z (three numbers), got {scan.direction!r}")
    if scan.step and scan.positions:
        raise LightplaneError("give either step (with direction) or positions, not both")
    if scan.step:
        try:
            step = float(scan.step)
        except ValueError:
            raise LightplaneError(f"step must be a number of mm, got {scan.step!r}") from None
        if dvec is None:
            raise LightplaneError("step needs a direction x;y;z")
        return Motion.linear(step, dvec)
    if scan.positions:
        return Motion.load_positions(scan.positions, dvec)
    if dvec is not None:
        raise LightplaneError("direction needs step or a single-column positions file")
    return Motion.none()


# ----------------------------------------------------------------------------- planning
@dataclass
class _Plan:
    """A scan ready to run: calibration, frames, chunks (filled on the client)."""

    scan: BatchScan
    camera: Camera | None = None
    plane: LightPlane | None = None
    motion: Motion | None = None
    frames: list = field(default_factory=list)  # frame paths (images) or [video path]
    video: bool = False
    chunks: list = field(default_factory=list)  # [(k, start, stop)]; stop None: to the end (video)
    tokens: dict = field(default_factory=dict)  # k -> hash of the partition's fingerprint
    fingerprint: dict = field(default_factory=dict)  # the scan's (every partition's, but its chunk)
    scan_token: str = ""
    stats: list | None = None  # remote frames: (size, modification stamp) from the listing
    backgrounds: list | None = None  # laser-off frame paths, one per frame (``background`` column)
    error: str | None = None


def plan_chunks(n_frames: int, chunk_frames: int) -> list[tuple[int, int, int]]:
    """``[(k, start, stop)]``: consecutive chunks of at most ``chunk_frames`` frames."""
    c = int(chunk_frames)
    if c < 1:
        raise LightplaneError(f"chunk_frames must be >= 1, got {chunk_frames}")
    return [(k, s, min(s + c, n_frames)) for k, s in enumerate(range(0, n_frames, c))]


def _plan(scan: BatchScan, chunk_frames: int, record: dict) -> _Plan:

    pl = _Plan(scan)
    try:
        pl.motion = _motion_of(scan)
        pl.camera = Camera.load(scan.camera)
        pl.plane = LightPlane.load(scan.plane)
        check_camera(pl.plane, pl.camera, plane_file=scan.plane, camera_file=scan.camera)  # another camera's: failed
        if _is_url(scan.input):
            if Path(scan.input).suffix.lower() in VIDEO_SUFFIXES:
                raise LightplaneError(f"{scan.input}: a video must be a local (shared) path, not a URL")
            if scan.background:
                raise LightplaneError("laser-off frames (background) go with local image files, not with a URL")
            pl.frames, pl.stats = _list_url_frames(scan.input)
            pl.chunks = plan_chunks(len(pl.frames), chunk_frames)
        elif Path(scan.input).suffix.lower() in VIDEO_SUFFIXES:
            if not Path(scan.input).is_file():
                raise LightplaneError(f"{scan.input}: no such video file")
            if scan.background:
                raise LightplaneError("laser-off frames (background) go with image files, not with a video")
            pl.video, pl.frames, pl.chunks = True, [scan.input], [(0, 0, None)]  # a video is decoded in one task
        else:
            paths = expand_inputs([scan.input])
            if not paths:
                raise LightplaneError(f"no images found in {scan.input}")
            bgs = None
            if scan.background:
                bgs = expand_inputs([scan.background]) if not _is_url(scan.background) else []
                if not bgs:
                    raise LightplaneError(f"no laser-off frames found in {scan.background} (local image files)")
            # every listed file exists, the laser-off frames paired, as measure checks and pairs them
            files = ImageFiles(paths, backgrounds=bgs)
            if files.backgrounds is not None:
                pl.backgrounds = [str(q) for q in files.backgrounds]
            pl.frames = [str(q) for q in paths]
            pl.chunks = plan_chunks(len(pl.frames), chunk_frames)
    except LightplaneError as e:
        pl.error = str(e)
        return pl
    except (OSError, ValueError) as e:
        pl.error = f"{type(e).__name__}: {e}"
        return pl
    assert pl.motion is not None  # read above, or returned
    fingerprint = _scan_fingerprint(pl, record)
    pl.fingerprint = fingerprint
    pl.scan_token = _sha256_json(fingerprint)
    for k, a, b in pl.chunks:
        pl.tokens[k] = _sha256_json({**fingerprint, "chunk": [k, a, b]})
    return pl


def _sha256_json(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def _file_sha256(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _scan_fingerprint(pl: _Plan, record: dict) -> dict:
    """What a scan's partitions depend on (JSON): its frames (each one's name, size and
    modification time: the stripe width comes from the first readable frame of the scan), the
    SHA-256 of the camera, plane and positions files, the motion, the options and the code."""
    assert pl.motion is not None  # only a planned scan has a fingerprint
    stats = pl.stats if pl.stats is not None else [_stat(q) for q in pl.frames]
    motion = pl.motion.to_dict()
    if pl.motion.positions_mm is not None:
        motion["positions_sha256"] = hashlib.sha256(np.ascontiguousarray(pl.motion.positions_mm).tobytes()).hexdigest()
    s = pl.scan
    files = {"camera": _file_sha256(s.camera), "plane": _file_sha256(s.plane)}
    if s.positions:
        files["positions"] = _file_sha256(s.positions)
    out = {"layout": _LAYOUT, "frames": {"count": len(pl.frames), "sha256": _sha256_json([pl.frames, stats])},
           "calibration_sha256": files, "motion": motion, "options": record, "code": _code_versions()}
    if pl.backgrounds:
        out["laser_off_frames"] = {"count": len(set(pl.backgrounds)),
                                   "sha256": _sha256_json([pl.backgrounds, [_stat(q) for q in pl.backgrounds]])}
    return out


def _is_url(text: str) -> bool:
    """An fsspec URL (``s3://``, ``gs://``, ``file://``...) rather than a path."""
    return "://" in str(text)


def _natural(text: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", text)]


def _list_url_frames(url: str) -> tuple[list[str], list]:
    """The image files of an fsspec URL (a folder, a glob or one file), in natural order, with their stamps."""
    try:
        import fsspec
    except ImportError:  # pragma: no cover - fsspec comes with dask
        raise LightplaneError(f"{url}: reading URLs needs fsspec (pip install fsspec)") from None

    try:
        fs, path = fsspec.core.url_to_fs(url)
        if any(ch in path for ch in "*?["):
            infos = fs.glob(path, detail=True)
        elif fs.isdir(path):
            infos = {i["name"]: i for i in fs.ls(path, detail=True)
                     if i.get("type") != "directory" and Path(i["name"]).suffix.lower() in IMAGE_SUFFIXES}
        elif fs.exists(path):
            infos = {path: fs.info(path)}
        else:
            raise LightplaneError(f"{url}: no such file or folder")
    except LightplaneError:
        raise
    except Exception as e:  # the filesystem's own errors (no credentials, no network...)
        raise LightplaneError(f"{url}: cannot be listed ({type(e).__name__}: {e})") from None
    names = sorted(infos, key=_natural)
    if not names:
        raise LightplaneError(f"no images found in {url}")
    stamps = [[infos[n].get("size"), str(infos[n].get("mtime") or infos[n].get("LastModified")
                                          or infos[n].get("ETag") or "")] for n in names]
    return [fs.unstrip_protocol(n) for n in names], stamps


class _RemoteFrames(FrameSource):
    """Frames named by fsspec URLs: each is copied to a local temporary file and read there
    exactly as a local file is (:func:`lightplane.core.io.try_read_image`), then removed."""

    def __init__(self, urls: Sequence[str], start: int = 0) -> None:
        self.urls, self.start = list(urls), int(start)
        self.n_frames = len(self.urls)
        self.errors: dict = {}

    def items(self):
        import tempfile

        import fsspec

        for i, url in enumerate(self.urls):
            fd, tmp = tempfile.mkstemp(prefix=".lightplane-frame-", suffix=Path(url).suffix)
            os.close(fd)
            try:
                try:
                    with fsspec.open(url, "rb") as src, open(tmp, "wb") as dst:
                        while True:
                            block = src.read(1 << 22)
                            if not block:
                                break
                            dst.write(block)
                except FileNotFoundError:
                    os.unlink(tmp)  # read as "no such file"
                except Exception as e:
                    self.errors[self.start + i] = f"cannot be read ({type(e).__name__}: {e})"
                yield self.start + i, url, tmp
            finally:
                if os.path.exists(tmp):
                    os.unlink(tmp)

    def close(self) -> None:
        pass


def _stat(path: str):
    try:
        st = os.stat(path)
        return [st.st_size, st.st_mtime_ns]
    except OSError:
        return None


def _code_versions() -> dict:
    """The versions that shape the points: lightplane, Python, numpy, scipy, OpenCV."""
    return versions()


# ----------------------------------------------------------------------------- worker side
class _ChunkFrames(FrameSource):
    """Frames ``start..stop`` of a scan's image list, with their global indices (each read less its
    laser-off frame where ``backgrounds`` gives them, one per frame)."""

    def __init__(self, paths: Sequence[str], start: int, backgrounds: Sequence[str] | None = None) -> None:
        self.paths, self.start = list(paths), int(start)
        self.backgrounds = None if not backgrounds else list(backgrounds)
        self.n_frames = len(self.paths)

    def items(self):
        for i, p in enumerate(self.paths):
            yield self.start + i, p, (p if self.backgrounds is None else PairedPath(p, self.backgrounds[i]))

    def close(self) -> None:
        pass


class _VideoChunk(FrameSource):
    """All frames of a video (one chunk)."""

    def __init__(self, path: str) -> None:
        self.src = VideoFrames(path)
        self.n_frames = self.src.n_frames

    def items(self):
        yield from self.src.items()

    def close(self) -> None:
        self.src.close()


def _prepare_task(frames: list, video: bool, camera, plane, motion, options: MeasureOptions,
                  backgrounds: list | None = None) -> dict:
    """Per scan, on a worker: the first readable frame checked against the camera, the
    profile axis and the stripe width, exactly as ``measure`` prepares a scan."""
    src = None
    try:  # a worker that does not see the files says so here, for the scan
        src = VideoFrames(frames[0]) if video else _RemoteFrames(frames) if _is_url(frames[0]) else \
            ImageFiles(frames, backgrounds=backgrounds)
        _, _, opts = _prepare(src, camera, plane, motion, options)
    except LightplaneError as e:
        return {"error": str(e)}
    finally:
        if src is not None:
            src.close()
    return {"axis": opts.axis, "width_px": opts.stripe.width_px}


_PROCESSORS: "OrderedDict[str, object]" = OrderedDict()  # per worker process: processors with built tables


def _processor(key: str, camera, plane, motion, axis: str, width_px, options: MeasureOptions):
    proc = _PROCESSORS.get(key)
    if proc is None:
        proc = FrameProcessor(camera, plane, motion,
                              replace(options, axis=axis, stripe=replace(options.stripe, width_px=width_px)))
        _PROCESSORS[key] = proc
        while len(_PROCESSORS) > 4:  # lookup tables are ~30 MB each
            _PROCESSORS.popitem(last=False)
    else:
        _PROCESSORS.move_to_end(key)
    return proc


def _table(records: np.ndarray, meta: dict, frame: str = ""):
    """The partition's table: the points' columns (each field's metadata ``unit``:
    :data:`~lightplane.measure.pointcloud.FIELD_UNITS`) and ``scan`` (the id, a string: a reader that
    infers the partition key as an integer fails on it instead of merging ``1`` and ``01``); the
    schema's metadata: the chunk's record, ``units`` (field -> unit) and ``frame`` (the coordinate frame)."""
    import pyarrow as pa

    arrays = [pa.array(np.ascontiguousarray(records[name])) for name in POINT_FIELDS]
    fields = [pa.field(name, a.type, metadata={b"unit": FIELD_UNITS[name].encode()})
              for name, a in zip(POINT_FIELDS, arrays)]
    arrays.append(pa.repeat(pa.scalar(str(meta["scan"]), pa.string()), records.size))
    fields.append(pa.field("scan", pa.string()))
    units = {name: FIELD_UNITS[name] for name in POINT_FIELDS}
    return pa.Table.from_arrays(arrays, schema=pa.schema(fields, metadata={
        _META_KEY: json.dumps(meta).encode(), b"units": json.dumps(units).encode(),
        b"frame": (frame or "x y z in mm").encode()}))


def _chunk_task(spec: dict, camera, plane, motion, prep: dict, options: MeasureOptions) -> dict:
    """Measure one chunk and write its partition atomically; returns the chunk's summary."""
    import pyarrow.parquet as pq


    k, start, stop = spec["chunk"]
    if "error" in prep:
        return {"chunk": k, "error": prep["error"]}
    key = f"{spec['proc_key']}:{prep['axis']}:{prep['width_px']!r}"
    proc = _processor(key, camera, plane, motion, prep["axis"], prep["width_px"], options)
    src: FrameSource
    if spec["video"]:
        src = _VideoChunk(spec["frames"][0])
    elif _is_url(spec["frames"][0]):
        src = _RemoteFrames(spec["frames"], start)
    else:
        src = _ChunkFrames(spec["frames"], start, spec.get("backgrounds"))

    # remote frames that could not be fetched (filled while the frames are read)
    fetch_errors: dict = src.errors if isinstance(src, _RemoteFrames) else {}
    parts, skipped, n, empty, dropped = [], [], 0, 0, Dropped()
    try:
        with frames_across_threads():  # the parallelism is across Dask's workers: serial kernels, one OpenCV thread
            scan = list(iter_scan(src, proc, workers=1))  # in this process, serial: measure's own path
        for r in scan:
            n += 1
            if r.index in fetch_errors:
                skipped.append([r.index, r.name, fetch_errors[r.index]])
            elif r.error is not None:
                skipped.append([r.index, r.name, r.error])
            else:
                assert r.records is not None  # a frame without an error has its records
                empty += r.records.size == 0
                parts.append(r.records)
                dropped.add(r)
    except LightplaneError as e:  # a frame of the wrong size, positions too short: the scan's fault
        return {"chunk": k, "error": str(e)}
    finally:
        src.close()
    recs = np.concatenate(parts) if parts else np.empty(0, POINT_DTYPE)
    summary = {"chunk": k, "frames": [start, start + n], "n_frames": n, "n_points": int(recs.size),
               "skipped": skipped, "frames_without_points": int(empty), "axis": prep["axis"],
               "width_px": prep["width_px"], "dropped": dict(dropped.totals),
               "frames_dropped": [[i, name, d] for i, name, d in dropped.frames[:MAX_DROPPED_FRAMES]],
               "n_frames_dropped": len(dropped.frames), "frames_without_stripe": dropped.frames_without_stripe}
    meta = {"token": spec["token"], "scan": spec["scan"], "fingerprint": spec["fingerprint"], **summary}
    if _lock_token(Path(spec["lock"][0])) != spec["lock"][1]:  # the run that asked for it has ended
        return {"chunk": k, "error": "the run that submitted this chunk no longer holds the output folder's lock"}
    table = _table(recs, meta, f"x y z in mm ({motion.frame_description if motion is not None else 'camera frame'})")
    atomic_write(spec["path"], lambda tmp: pq.write_table(table, tmp), force=True)
    return {**summary, "written": True}


def _read_partition_meta(path: Path) -> dict | None:
    import pyarrow.parquet as pq

    try:
        md = pq.read_schema(path).metadata or {}
        return json.loads(md[_META_KEY])
    except Exception:  # unreadable, foreign or truncated file: not complete
        return None


# ----------------------------------------------------------------------------- client
def require_extra() -> None:
    """Raise :class:`LightplaneError` naming the optional extra when dask.distributed or pyarrow is missing."""
    import importlib.util

    missing = [m for m in ("distributed", "pyarrow") if importlib.util.find_spec(m) is None]
    if missing:
        raise LightplaneError(f"batch measurement needs {' and '.join(missing)}: "
                              "pip install 'lightplane[distributed]'")


@dataclass
class BatchResult:
    """What :func:`measure_batch` did; ``scans``: one dict per manifest row (as in manifest.json);
    ``set_aside``: what lies in ``set-aside/`` (path, reason); ``notes``: what the run reported
    on the way (a stale lock taken over...)."""

    out_dir: Path
    scans: list
    seconds: float
    dashboard: str | None = None
    set_aside: list = field(default_factory=list)
    notes: list = field(default_factory=list)

    @property
    def status(self) -> str:
        """``ok`` when every scan was measured, else ``failed`` (as manifest.json says)."""
        return "failed" if self.failed else "ok"

    @property
    def failed(self) -> list:
        return [s for s in self.scans if s["status"] == "failed"]

    @property
    def n_points(self) -> int:
        return sum(s.get("n_points", 0) for s in self.scans)

    @property
    def n_frames(self) -> int:
        return sum(s.get("n_frames", 0) for s in self.scans)

    @property
    def partitions_written(self) -> int:
        return sum(s.get("partitions_written", 0) for s in self.scans)

    @property
    def partitions_reused(self) -> int:
        return sum(s.get("partitions_reused", 0) for s in self.scans)


def local_cluster(n_workers: int, **kwargs):
    """A LocalCluster of ``n_workers`` single-threaded worker processes (no dashboard without bokeh)."""
    from distributed import LocalCluster

    opts = dict(n_workers=int(n_workers), threads_per_worker=1, processes=True, dashboard_address=":0")
    opts.update(kwargs)
    return LocalCluster(**opts)


def _partition_path(out_dir: Path, sid: str, k: int) -> Path:
    return out_dir / "points" / f"scan={sid}" / f"part-{k}.parquet"


@dataclass(frozen=True)
class BatchOptions:
    """How :func:`measure_batch` runs: ``chunk_frames`` frames per task, ``ply`` (also one PLY per
    scan, ``ply/<id>.ply``), ``retries`` of a failed task (a worker that died), ``break_lock``
    (take the output folder's lock whoever holds it: only when its holder is known to be gone)."""

    chunk_frames: int = DEFAULT_CHUNK_FRAMES
    ply: bool = False
    retries: int = 2
    break_lock: bool = False

    def __post_init__(self) -> None:
        plan_chunks(1, self.chunk_frames)  # checks chunk_frames
        if not isinstance(self.retries, int) or self.retries < 0:
            raise LightplaneError(f"retries must be an integer >= 0, got {self.retries!r}")


def _options_record(options: MeasureOptions) -> dict:
    """The measurement options as a batch records them (JSON; the partitions' fingerprint)."""
    roi, width = options.roi, options.stripe.width_px
    return {"axis": options.axis, "roi": None if roi is None else [int(v) for v in roi],
            "width_px": None if width is None else float(width), "channel": options.stripe.channel,
            "stripe": options.changed()}


# ----------------------------------------------------------------------------- the output folder's lock
def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _process_state(pid: int) -> tuple[str, str] | None:
    """(state, start time in clock ticks) of process ``pid`` from /proc (Linux); None elsewhere or when gone."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
        return fields[0].decode(), fields[19].decode()
    except (OSError, IndexError, UnicodeDecodeError):
        return None


def _pid_alive(pid: int, process_start: str | None) -> bool:
    """Whether process ``pid`` of this host still runs (and is the one that started at ``process_start``)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # another user's process: it exists
    state = _process_state(pid)
    if state is not None and (state[0] in ("Z", "X") or (process_start is not None and state[1] != process_start)):
        return False  # a zombie, or the pid was reused by another process
    return True


def _lock_holder(raw: bytes) -> dict | None:
    """The holder a lock file names (pid, host, started...), or None when it is not a lock file's content."""
    try:
        d = json.loads(raw.decode())
    except (ValueError, RecursionError):
        return None
    ok = (isinstance(d, dict) and isinstance(d.get("pid"), int) and not isinstance(d.get("pid"), bool)
          and d["pid"] > 0 and isinstance(d.get("host"), str))
    return d if ok else None


def _lock_token(path: Path) -> str | None:
    """The token of the run holding the lock file at ``path`` (None: no lock, or not readable)."""
    try:
        holder = _lock_holder(path.read_bytes())
    except OSError:
        return None
    return None if holder is None else holder.get("token")


def _age(seconds: float) -> str:
    s = max(0, int(seconds))
    if s < 120:
        return f"{s} s"
    if s < 7200:
        return f"{s // 60} min"
    if s < 2 * 86400:
        return f"{s // 3600} h {s % 3600 // 60} min"
    return f"{s // 86400} days"


def _describe_holder(holder: dict | None, path: Path) -> str:
    try:
        mtime = path.stat().st_mtime
    except OSError:
        mtime = time.time()
    if holder is None:
        return f"an unreadable lock file {path}, last written {_age(time.time() - mtime)} ago"
    started = holder.get("started_unix")
    age = _age(time.time() - (started if isinstance(started, (int, float)) else mtime))
    return f"pid {holder['pid']} on host {holder['host']}, started {holder.get('started_utc', '?')}, {age} ago"


def _remove_lock(path: Path, seen: bytes) -> None:
    """Remove the lock file if it still holds ``seen``; one another run wrote meanwhile is put back."""
    aside = path.with_name(f"{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}")
    try:
        os.rename(path, aside)
    except FileNotFoundError:
        return
    try:
        if aside.read_bytes() != seen:  # a new holder's lock: back where it was (unless a third run has one)
            try:
                os.link(aside, path)
            except FileExistsError:
                pass
            except OSError:  # no hard links on this file system
                os.rename(aside, path)
    finally:
        aside.unlink(missing_ok=True)


def _clear_lock(path: Path, break_lock: bool, notice: Callable[[str], None]) -> None:
    """Remove a lock that may be taken over (stale, or ``break_lock``); else raise naming its holder."""
    try:
        seen = path.read_bytes()
    except FileNotFoundError:
        return  # released meanwhile
    except OSError:
        seen = b""
    holder = _lock_holder(seen)
    who = _describe_holder(holder, path)
    out = path.parent
    if break_lock:
        _remove_lock(path, seen)
        notice(f"{out}: broke the lock of {who}, as --break-lock asks")
        return
    if holder is None:
        raise LightplaneError(f"{out}: locked by {who}; if no other measure-batch run writes there, "
                              "run again with --break-lock")
    if holder["host"] != socket.gethostname():
        raise LightplaneError(f"{out}: a measure-batch run on another host holds the lock ({who}); "
                              "if it is no longer running, run again with --break-lock")
    if _pid_alive(holder["pid"], holder.get("process_start")):
        raise LightplaneError(f"{out}: another measure-batch run writes there ({who}); wait for it to end")
    _remove_lock(path, seen)
    notice(f"{out}: took over the stale lock of {who} (that process is no longer running)")


@contextlib.contextmanager
def _output_lock(out: Path, break_lock: bool, notice: Callable[[str], None]) -> Iterator[dict]:
    """Hold ``out/.lightplane-batch.lock`` (created with O_CREAT|O_EXCL) for the block; removed at its end."""
    path = out / LOCK_NAME
    pid = os.getpid()
    state = _process_state(pid)
    me = {"pid": pid, "host": socket.gethostname(), "started_utc": _utc_now(), "started_unix": time.time(),
          "process_start": None if state is None else state[1], "token": uuid.uuid4().hex}
    for _ in range(5):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            _clear_lock(path, break_lock, notice)
            continue
        with os.fdopen(fd, "w") as f:
            f.write(json.dumps(me))
        break
    else:
        raise LightplaneError(f"{out}: could not take the lock {path}: other runs keep taking it")
    try:
        yield me
    finally:
        if _lock_token(path) == me["token"]:
            path.unlink(missing_ok=True)


# ----------------------------------------------------------------------------- the run
@dataclass
class _Run:
    """One run of :func:`measure_batch`: its output folder, scans, settings, lock and what it set aside."""

    out: Path
    scans: list
    record: dict
    batch: BatchOptions
    notes: list = field(default_factory=list)
    on_notice: Callable[[str], None] | None = None
    lock: dict = field(default_factory=dict)
    moved: dict = field(default_factory=dict)  # set-aside path -> reason, this run
    earlier: dict = field(default_factory=dict)  # set-aside path -> reason, from the last manifest.json
    t0: float = field(default_factory=time.perf_counter)

    def notice(self, message: str) -> None:
        self.notes.append(message)
        if self.on_notice is not None:
            self.on_notice(message)
        else:
            warnings.warn(message, RuntimeWarning, stacklevel=4)


def _output_folder(out_dir: str | os.PathLike) -> Path:
    out = Path(out_dir)
    if not out.resolve().parent.exists():
        raise LightplaneError(f"{out.parent}: output folder's parent does not exist")
    if out.exists() and not out.is_dir():
        raise LightplaneError(f"{out}: exists and is not a folder")
    return out


@with_blas_limited
def measure_batch(manifest: str | os.PathLike | Sequence[BatchScan], out_dir: str | os.PathLike,
                  options: MeasureOptions = MeasureOptions(), batch: BatchOptions = BatchOptions(), *,
                  client=None, scheduler: str | None = None, local_workers: int | None = None,
                  progress: Callable[[str, int, int], None] | None = None,
                  on_dashboard: Callable[[str | None], None] | None = None,
                  on_notice: Callable[[str], None] | None = None) -> BatchResult:
    """Measure every scan of ``manifest`` into a hive-partitioned Parquet dataset under ``out_dir``.

    The cluster: an existing ``client`` (``distributed.Client``), a ``scheduler`` address
    (``tcp://host:port``), or ``local_workers`` worker processes started here (a
    LocalCluster, closed at the end).  ``options``
    (:class:`~lightplane.measure.options.MeasureOptions`) apply to every scan, as in
    ``measure``; ``batch``: :class:`BatchOptions` (frames per task, PLY files, retries,
    breaking a lock).  ``progress(scan_id, chunks_done, chunks_total)`` after each chunk;
    ``on_notice(line)`` for what the run reports on the way (default: a ``RuntimeWarning``).

    One run at a time per output folder (its lock file; a second run raises
    :class:`LightplaneError` naming the holder).  ``manifest.json`` says ``in progress`` from
    the start and ``ok`` or ``failed`` at the end.  Partitions whose fingerprint is the
    current one are kept (resume), the others measured again; the partitions of failed scans
    and of folders not in the manifest are moved to ``set-aside/``.  Returns a
    :class:`BatchResult`.  Raises :class:`LightplaneError` only for a bad manifest, a bad or
    locked output folder; a scan's own failure is recorded in its entry.
    """
    require_extra()
    scans = list(manifest) if not isinstance(manifest, (str, os.PathLike)) else read_manifest(manifest)
    out = _output_folder(out_dir)
    if sum(x is not None for x in (client, scheduler, local_workers)) != 1:
        raise LightplaneError("give exactly one of a client, a scheduler address or a number of local workers")
    if local_workers is not None and int(local_workers) < 1:
        raise LightplaneError(f"local workers must be >= 1, got {local_workers}")
    run = _Run(out, scans, _options_record(options), batch, on_notice=on_notice)
    out.mkdir(exist_ok=True)
    with _output_lock(out, batch.break_lock, run.notice) as lock:
        run.lock = lock
        run.earlier = _earlier_set_aside(out)
        _write_manifest_in_progress(run)
        try:
            return _measure_locked(run, options, (client, scheduler, local_workers), progress, on_dashboard)
        except BaseException as exc:
            _write_manifest_stopped(run, exc)
            raise


def _measure_locked(run: _Run, options: MeasureOptions, cluster: tuple, progress, on_dashboard) -> BatchResult:
    """The run, once it holds the lock: plan, set aside what is not the manifest's, measure, set aside failures."""
    out = run.out
    (out / "points").mkdir(exist_ok=True)
    plans = [_plan(s, run.batch.chunk_frames, run.record) for s in run.scans]
    _set_aside_foreign(run)
    entries, dashboard = _on_cluster(run, plans, options, cluster, progress, on_dashboard)
    for e in entries:
        if e["status"] == "failed":
            _set_aside_scan(run, e)
    written = set()
    if run.batch.ply:
        for e, pl in zip(entries, plans):
            if e["status"] != "failed" and e["n_points"]:
                e["ply"] = str(_write_ply(out, e, pl))
                written.add(Path(e["ply"]).name)
    _set_aside_ply(run, written)
    result = BatchResult(out, entries, time.perf_counter() - run.t0, dashboard, _set_aside_listing(run), run.notes)
    _write_manifest(run, result)
    return result


def _on_cluster(run: _Run, plans: list, options: MeasureOptions, cluster: tuple, progress, on_dashboard):
    """``(entries, dashboard)``: the plans measured on the given client, scheduler or a local cluster."""
    client, scheduler, local_workers = cluster
    own_cluster = own_client = None
    try:
        if client is None:
            from distributed import Client

            if scheduler is not None:
                client = own_client = Client(scheduler)
            else:
                assert local_workers is not None  # exactly one of the three was checked
                own_cluster = local_cluster(local_workers)
                client = own_client = Client(own_cluster)
        dashboard = getattr(client, "dashboard_link", None)
        if on_dashboard is not None:
            on_dashboard(dashboard)
        lock = (str(run.out / LOCK_NAME), run.lock["token"])
        return _run(client, plans, run.out, options, (run.batch.retries, lock), progress), dashboard
    finally:
        if own_client is not None:
            own_client.close()
        if own_cluster is not None:
            own_cluster.close()


def _run(client, plans: list, out: Path, options: MeasureOptions, settings: tuple, progress) -> list:
    """Submit every chunk not yet complete, collect the chunks' summaries; one entry per scan.
    ``settings``: (retries, (lock path, lock token))."""
    # keys unique to this run: a key the scheduler still remembers from an earlier run would
    # give that run's result without running the task (and without rewriting a deleted partition)
    run = uuid.uuid4().hex[:8]
    entries, futs, chunk_meta = [], {}, {}
    try:
        for i, pl in enumerate(plans):
            e = _entry(pl)
            entries.append(e)
            if pl.error is not None:
                continue
            done, todo = _partitions_done(out, pl)
            chunk_meta[i] = done
            e["partitions_reused"] = len(done)
            if todo:
                futs[i] = _submit_scan(client, pl, todo, out, options, settings, run)
            if progress is not None:
                progress(pl.scan.id, len(done), len(pl.chunks))
        errors = _collect(futs, plans, entries, chunk_meta, progress)
    except BaseException:  # stopped: no task of this run may write once the lock is gone
        with contextlib.suppress(Exception):
            client.cancel([f for fs in futs.values() for f in fs])
        raise
    for i, (pl, e) in enumerate(zip(plans, entries)):
        if pl.error is None:
            _summarize(e, pl, chunk_meta[i], out, errors.get(i))
    return entries


def _entry(pl: _Plan) -> dict:
    """A scan's entry in manifest.json before its chunks are collected (failed already when it could not be planned)."""
    s = pl.scan
    e: dict = {"id": s.id, "input": s.input, "camera": s.camera, "plane": s.plane, "status": "ok", "error": None,
               "motion": None if pl.motion is None else pl.motion.to_dict(), "partitions": [], "n_frames": 0,
               "n_points": 0, "skipped": [], "frames_without_points": 0, "dropped": {}, "frames_dropped": [],
               "n_frames_dropped": 0, "frames_without_stripe": 0, "partitions_written": 0,
               "partitions_reused": 0}
    if pl.error is not None:
        e["status"], e["error"] = "failed", pl.error
    else:
        e["fingerprint"] = {"scan": pl.fingerprint, "sha256": pl.scan_token}
    return e


def _partitions_done(out: Path, pl: _Plan) -> tuple[dict, list]:
    """A scan's partitions complete and with the current fingerprint (chunk -> its summary), taken back
    from ``set-aside/`` when one lies there, and the chunks to measure.  Every other file the scan's
    folder holds (a partition with another fingerprint, of another chunking, a dead run's temporary
    file) is removed."""
    s = pl.scan
    folder = out / "points" / f"scan={s.id}"
    folder.mkdir(parents=True, exist_ok=True)
    wanted = {_partition_path(out, s.id, k).name for k, _, _ in pl.chunks}
    for q in folder.iterdir():
        if q.is_file() and q.name not in wanted:
            q.unlink()
    todo, done = [], {}
    for k, a, b in pl.chunks:
        path = _partition_path(out, s.id, k)
        meta = _read_partition_meta(path) if path.exists() else None
        if meta is None or meta.get("token") != pl.tokens[k]:
            aside = out / SET_ASIDE / path.relative_to(out)
            meta = _read_partition_meta(aside) if aside.is_file() else None
            if meta is not None and meta.get("token") == pl.tokens[k]:
                os.replace(aside, path)
        if meta is not None and meta.get("token") == pl.tokens[k]:
            done[k] = meta
        else:
            path.unlink(missing_ok=True)  # never kept: a reader of a stopped run sees no partition of another
            todo.append((k, a, b))
    return done, todo


def _submit_scan(client, pl: _Plan, todo: list, out: Path, options: MeasureOptions, settings: tuple,
                 run: str) -> list:
    """The scan's prepare task and one task per chunk of ``todo``: their futures, the prepare's first."""
    retries, lock = settings
    s = pl.scan
    common = (pl.camera, pl.plane, pl.motion)
    prep = client.submit(_prepare_task, pl.frames, pl.video, *common, options, pl.backgrounds, retries=retries,
                         pure=False,
                         key=f"prepare-{s.id}-{pl.scan_token[:12]}-{run}")
    futs = [prep]
    for k, a, b in todo:
        spec = {"scan": s.id, "chunk": (k, a, b), "video": pl.video,
                "frames": pl.frames if pl.video else pl.frames[a:b], "token": pl.tokens[k],
                "backgrounds": None if pl.backgrounds is None else pl.backgrounds[a:b],
                "fingerprint": {**pl.fingerprint, "chunk": [k, a, b]}, "lock": lock,
                "proc_key": pl.scan_token, "path": str(_partition_path(out, s.id, k))}
        futs.append(client.submit(_chunk_task, spec, *common, prep, options, retries=retries, pure=False,
                                  key=f"chunk-{s.id}-{k}-{pl.tokens[k][:12]}-{run}"))
    return futs


def _collect(futs: dict, plans: list, entries: list, chunk_meta: dict, progress) -> dict[int, list]:
    """Every chunk's result as it completes into ``chunk_meta``; the chunks' errors per scan."""
    from distributed import as_completed

    owner = {f.key: i for i, fs in futs.items() for f in fs[1:]}
    all_chunks = [f for fs in futs.values() for f in fs[1:]]
    errors: dict[int, list] = {}
    for fut in as_completed(all_chunks):
        i = owner[fut.key]
        try:
            res = fut.result()
        except Exception as exc:  # retries exhausted (worker deaths, bugs): the scan fails, the others go on
            res = {"chunk": None, "error": f"task {fut.key} failed: {type(exc).__name__}: {exc}"}
        if "error" in res:
            errors.setdefault(i, []).append((res["chunk"] if res["chunk"] is not None else -1, res["error"]))
        else:
            chunk_meta[i][res["chunk"]] = res
            entries[i]["partitions_written"] += 1
        if progress is not None:
            progress(plans[i].scan.id, len(chunk_meta[i]), len(plans[i].chunks))
        fut.release()
    for fs in futs.values():
        fs[0].release()
    return errors


def _summarize(e: dict, pl: _Plan, metas_by_chunk: dict, out: Path, errors: list | None) -> None:
    """A scan's entry from its chunks' summaries (in chunk order) and errors: totals and status."""
    assert pl.motion is not None  # only planned scans get this far
    metas = [metas_by_chunk[k] for k, _, _ in pl.chunks if k in metas_by_chunk]
    for m in metas:
        e["partitions"].append({"path": str(_partition_path(out, pl.scan.id, m["chunk"]).relative_to(out)),
                                "chunk": m["chunk"], "frames": m["frames"], "n_points": m["n_points"]})
        e["n_frames"] += m["n_frames"]
        e["n_points"] += m["n_points"]
        e["skipped"].extend(m["skipped"])
        e["frames_without_points"] += m["frames_without_points"]
        for why, count in m.get("dropped", {}).items():
            e["dropped"][why] = e["dropped"].get(why, 0) + count
        room = MAX_DROPPED_FRAMES - len(e["frames_dropped"])
        e["frames_dropped"].extend(m.get("frames_dropped", [])[:max(room, 0)])
        e["n_frames_dropped"] += m.get("n_frames_dropped", 0)
        e["frames_without_stripe"] += m.get("frames_without_stripe", 0)
        e["axis"], e["width_px"] = m["axis"], m["width_px"]
    e["n_frames_used"] = e["n_frames"] - len(e["skipped"])
    if errors:
        e["status"], e["error"] = "failed", min(errors)[1]  # the first failing chunk's reason
    elif pl.motion.n_frames is not None and pl.motion.n_frames != e["n_frames"]:
        e["status"], e["error"] = "failed", (f"the positions give {pl.motion.n_frames} frames but the input "
                                             f"has {e['n_frames']}")
    elif e["n_frames"] and e["n_frames"] == len(e["skipped"]):
        e["status"], e["error"] = "failed", f"none of the {e['n_frames']} frames could be read"
    elif e["n_points"] == 0:
        e["status"], e["error"] = "failed", (f"no stripe found in any of the {e['n_frames_used']} readable "
                                             "frames (laser off, wrong --channel or --roi?)")


# ----------------------------------------------------------------------------- set aside
def _set_aside(run: _Run, src: Path, reason: str) -> None:
    """Move ``src`` (under the output folder) to the same place under ``set-aside/``, replacing what lay there."""
    out = run.out
    dest = out / SET_ASIDE / src.relative_to(out)
    dest.parent.mkdir(parents=True, exist_ok=True)
    if dest.is_dir() and not dest.is_symlink():
        shutil.rmtree(dest)
    elif dest.exists() or dest.is_symlink():
        dest.unlink()
    os.replace(src, dest)
    run.moved[str(dest.relative_to(out))] = reason


def _set_aside_foreign(run: _Run) -> None:
    """Set aside what ``points/`` holds besides the manifest's scans (names starting with ``.`` or
    ``_`` stay: pyarrow's dataset discovery skips them)."""
    ids = {f"scan={s.id}" for s in run.scans}
    for q in sorted((run.out / "points").iterdir()):
        if q.name.startswith((".", "_")) or (q.name in ids and q.is_dir()):
            continue
        _set_aside(run, q, "not a scan of the manifest")


def _set_aside_scan(run: _Run, e: dict) -> None:
    """A failed scan's folder out of ``points/``: set aside when it holds partitions, else removed."""
    folder = run.out / "points" / f"scan={e['id']}"
    e["partitions"] = []
    if not folder.is_dir():
        return
    if any(q.name.endswith(".parquet") and not q.name.startswith(".") for q in folder.iterdir()):
        _set_aside(run, folder, f"the scan failed: {e['error']}")
        e["set_aside"] = f"{SET_ASIDE}/points/scan={e['id']}"
    else:
        shutil.rmtree(folder)


def _set_aside_ply(run: _Run, written: set) -> None:
    """Set aside the PLY files this run did not write (of failed or dropped scans, or of an earlier
    run when this one wrote none)."""
    folder = run.out / "ply"
    if not folder.is_dir():
        return
    for q in sorted(folder.iterdir()):
        if q.is_file() and q.suffix == ".ply" and q.name not in written:
            _set_aside(run, q, "not written by the last run (its scan failed, left the manifest, or --ply was off)")


def _earlier_set_aside(out: Path) -> dict:
    """The reasons the last manifest.json gives for what lies in ``set-aside/`` (path -> reason)."""
    try:
        doc = json.loads((out / "manifest.json").read_text(encoding="utf-8"))
        return {str(d["path"]): str(d["reason"]) for d in doc.get("set_aside", [])}
    except (OSError, ValueError, TypeError, KeyError, AttributeError):
        return {}


def _set_aside_listing(run: _Run) -> list:
    """What lies in ``set-aside/`` now: ``{"path", "reason"}`` each (empty folders removed)."""
    root = run.out / SET_ASIDE
    items = []
    for sub in ("points", "ply"):
        folder = root / sub
        if not folder.is_dir():
            continue
        for q in sorted(folder.iterdir()):
            if q.is_dir() and not any(q.iterdir()):
                q.rmdir()  # all its partitions were taken back
                continue
            rel = str(q.relative_to(run.out))
            items.append({"path": rel, "reason": run.moved.get(rel) or run.earlier.get(rel)
                          or "set aside by an earlier run"})
    return items


# ----------------------------------------------------------------------------- reading
def scan_partitioning():
    """The dataset's partitioning: hive, with the ``scan`` key a string (ids ``1`` and ``01`` stay
    apart; inferred, a key whose values all look like integers would become int32)."""
    import pyarrow as pa
    import pyarrow.dataset as pds

    return pds.partitioning(pa.schema([("scan", pa.string())]), flavor="hive")


def open_dataset(out_dir: str | os.PathLike):
    """The points of a measure-batch output as one ``pyarrow.dataset.Dataset`` (columns x, y, z, frame,
    intensity, sigma_mm, u, v, scan): ``pyarrow.dataset.dataset(out_dir/points, format="parquet",
    partitioning=scan_partitioning())``.  Its points are those of the scans ``manifest.json`` lists
    as ok when it says ``ok`` or ``failed`` (not while it says ``in progress``)."""
    import pyarrow.dataset as pds

    folder = Path(out_dir) / "points"
    if not folder.is_dir():
        raise LightplaneError(f"{folder}: no such folder (not a measure-batch output?)")
    return pds.dataset(folder, format="parquet", partitioning=scan_partitioning())


def read_points(out_dir: str | os.PathLike, scan_id: str) -> np.ndarray:
    """A scan's points (:data:`lightplane.measure.pointcloud.POINT_DTYPE`) in frame order, from its
    partitions in :func:`open_dataset` (empty when the scan has none)."""
    import pyarrow.dataset as pds

    if not (Path(out_dir) / "points").is_dir():
        return np.empty(0, POINT_DTYPE)
    frags = open_dataset(out_dir).get_fragments(filter=pds.field("scan") == str(scan_id))
    arrays = []
    for frag in sorted(frags, key=lambda f: _natural(Path(f.path).name)):
        t = frag.to_table(columns=list(POINT_FIELDS))
        rec = np.empty(t.num_rows, POINT_DTYPE)
        for name in POINT_FIELDS:
            rec[name] = t.column(name).to_numpy()
        arrays.append(rec)
    return np.concatenate(arrays) if arrays else np.empty(0, POINT_DTYPE)


def _write_ply(out: Path, e: dict, pl: _Plan) -> Path:
    import pyarrow.parquet as pq

    assert pl.motion is not None  # only planned scans get this far
    (out / "ply").mkdir(exist_ok=True)
    dest = out / "ply" / f"{pl.scan.id}.ply"
    with PointSpool(out / "ply") as spool:
        for part in e["partitions"]:
            t = pq.read_table(out / part["path"], columns=list(POINT_FIELDS))
            rec = np.empty(t.num_rows, POINT_DTYPE)
            for name in POINT_FIELDS:
                rec[name] = t.column(name).to_numpy()
            spool.append(rec)
        lines = ["lightplane point cloud: x y z in mm (camera frame"
                 + (", object at frame 0" if pl.motion.kind != "none" else "") + ")",
                 f"plane: {pl.plane!r}", f"scan: {pl.scan.id} ({pl.scan.input})", f"frames: {e['n_frames']}",
                 f"skipped: {len(e['skipped'])}"]
        write_cloud(dest, spool, fmt="ply", force=True, comments=lines)
    return dest


# ----------------------------------------------------------------------------- manifest.json
#: how the dataset is read (as documented in docs/batch.md and manifest.json)
DATASET_READ = ('pyarrow.dataset.dataset("points", format="parquet", partitioning=pyarrow.dataset.partitioning('
                'pyarrow.schema([("scan", pyarrow.string())]), flavor="hive"))')


def _manifest_head(run: _Run, status: str) -> dict:
    """manifest.json's common part: format, status, the run (pid, host, start), provenance, the dataset."""
    prov = provenance([s.input for s in run.scans], {**run.record, "chunk_frames": int(run.batch.chunk_frames)})
    lock = run.lock
    return {"format": "lightplane batch", "layout": _LAYOUT, "status": status,
            "run": {"pid": lock.get("pid"), "host": lock.get("host"), "started_utc": lock.get("started_utc")},
            "provenance": prov,
            "dataset": {"path": "points", "format": "parquet", "partitioning": "hive", "partition_key": "scan",
                        "partition_schema": {"scan": "string"}, "columns": [*POINT_FIELDS, "scan"],
                        "read": DATASET_READ}}


def _write_manifest_in_progress(run: _Run) -> None:
    doc = _manifest_head(run, "in progress")
    doc["summary"] = {"scans": len(run.scans)}
    doc["scans"] = [{"id": s.id, "status": "in progress"} for s in run.scans]
    doc["set_aside"] = [{"path": p, "reason": r} for p, r in sorted(run.earlier.items())]
    write_json(run.out / "manifest.json", doc, force=True)


def _write_manifest_stopped(run: _Run, exc: BaseException) -> None:
    """manifest.json of a run stopped by an exception: failed, why, and that the dataset may be mixed."""
    doc = _manifest_head(run, "failed")
    doc["run"]["finished_utc"] = _utc_now()
    doc["error"] = (f"the run stopped before its end ({type(exc).__name__}: {exc}); the dataset may hold "
                    "partitions of this run and of an earlier one: run it again")
    doc["scans"] = [{"id": s.id, "status": "unknown"} for s in run.scans]
    doc["set_aside"] = _set_aside_listing(run) if (run.out / SET_ASIDE).is_dir() else []
    with contextlib.suppress(Exception):  # the exception that stopped the run is the one to see
        write_json(run.out / "manifest.json", doc, force=True)


def _write_manifest(run: _Run, result: BatchResult) -> None:
    doc = _manifest_head(run, result.status)
    doc["run"]["finished_utc"] = _utc_now()
    ok = [s for s in result.scans if s["status"] == "ok"]
    doc["summary"] = {"scans": len(result.scans), "ok": len(ok), "failed": len(result.failed),
                      "frames": result.n_frames, "points": result.n_points,
                      "partitions_written": result.partitions_written,
                      "partitions_reused": result.partitions_reused, "set_aside": len(result.set_aside),
                      "seconds": round(result.seconds, 3)}
    doc["scans"] = result.scans
    doc["set_aside"] = result.set_aside
    doc["notes"] = result.notes
    write_json(run.out / "manifest.json", doc, force=True)
