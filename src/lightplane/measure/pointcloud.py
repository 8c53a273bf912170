"""Point clouds: one record per measured point, written and read as PLY, CSV or NPY (docs/conventions.md §Point clouds).

A cloud is a numpy structured array of :data:`POINT_DTYPE` records (32 bytes each):

=============  =======  ==================================================================
field          type     meaning
=============  =======  ==================================================================
x, y, z        float32  mm; camera frame, or the object's frame-0 position after motion
frame          uint32   index of the source frame (0-based, in input order)
intensity      float32  smoothed image value at the stripe's peak (grey levels)
sigma_mm       float32  camera-frame σ: plane calibration (+ camera's share if carried)
u, v           float32  the stripe centre in the source frame, distorted pixels
=============  =======  ==================================================================

float32 holds 500 mm to 3e-5 mm and 1280 px to 1e-4 px: far below the measurement noise.

A cloud of several lasers (``measure --sensor``, :func:`lightplane.measure.sensor.measure_lasers`)
adds ``laser`` (uint8, the laser's index; the names are in the file's comments):
:data:`lightplane.measure.sensor.LASER_POINT_DTYPE`.

Formats (by :func:`write_cloud`'s ``fmt`` or the file suffix):

- PLY (``.ply``), binary little-endian by default, ASCII with ``ascii=True``: one
  ``vertex`` element with the fields above as properties (``float``/``uint``), the
  provenance as ``comment`` lines, the first naming each field's unit (:data:`FIELD_UNITS`).  The header comes from ``plyfile``; files are read
  with ``plyfile``.
- CSV (``.csv``): ``#`` comment lines (the fields' units, the coordinate frame, the provenance: the
  PLY's comments), a header row naming the columns (``x,y,z,frame,intensity,sigma_mm,u,v``), then one
  row per point; floats with 9 significant digits (float32 round-trips exactly).  Readers: numpy's
  ``loadtxt`` skips ``#`` lines by default, pandas with ``comment="#"``.
- NPY (``.npy``): the structured array itself (``numpy.load``).

Writing streams: :class:`PointSpool` collects records in an append-only temporary file
and :func:`write_cloud` copies it into the output in chunks, so memory does not grow
with the number of points.  Every output is written atomically
(:func:`lightplane.core.io.atomic_write`): a temporary file in the destination folder,
renamed when complete; an existing file is replaced only with ``force``.

>>> import numpy as np, tempfile, os
>>> rec = make_records(np.array([[1.0, 2.0, 450.0]]), frame=3, intensity=[120.0], sigma_mm=[0.01],
...                    uv=np.array([[640.0, 480.5]]))
>>> d = tempfile.mkdtemp()
>>> _ = write_cloud(os.path.join(d, "c.ply"), rec)
>>> back = read_cloud(os.path.join(d, "c.ply"))
>>> bool(np.array_equal(back, rec)), back["frame"].tolist()
(True, [3])
"""

from __future__ import annotations

import os
import re
import socket
import sys
import tempfile
import time
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from lightplane.core.errors import LightplaneError
from lightplane.core.io import atomic_write

__all__ = ["POINT_DTYPE", "POINT_FIELDS", "FORMATS", "FIELD_UNITS", "units_line", "cloud_comments", "make_records", "PointSpool", "write_cloud", "read_cloud", "cloud_format",
           "remove_stale_spools", "SPOOL_PREFIX", "STALE_SPOOL_S"]

POINT_DTYPE = np.dtype([
    ("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
    ("frame", "<u4"), ("intensity", "<f4"), ("sigma_mm", "<f4"),
    ("u", "<f4"), ("v", "<f4"),
])



def record_fields(dtype: np.dtype) -> tuple[str, ...]:
    """The field names of a structured dtype of point records, in order."""
    if dtype.names is None:
        raise LightplaneError(f"point records need a structured dtype, got {dtype}")
    return dtype.names


#: the fields of :data:`POINT_DTYPE`, in order
POINT_FIELDS = record_fields(POINT_DTYPE)

FORMATS = ("ply", "csv", "npy")

#: the unit of each field of the point records, stated by every written cloud (PLY comment, CSV ``#`` line,
#: Parquet field metadata)
FIELD_UNITS = {"x": "mm", "y": "mm", "z": "mm", "frame": "index (0-based)", "intensity": "grey level",
               "sigma_mm": "mm", "u": "px", "v": "px", "laser": "index (names in the comments)"}


def units_line(dtype: np.dtype) -> str:
    """The comment line naming each field's unit, e.g. ``units: x mm, y mm, ...``."""
    return "units: " + ", ".join(f"{n} {FIELD_UNITS.get(n, '-')}" for n in record_fields(dtype))

#: records per chunk when streaming (8 MB of binary records)
CHUNK_RECORDS = 262_144


def make_records(points: np.ndarray, frame, intensity=None, sigma_mm=None, uv=None) -> np.ndarray:
    """Records (:data:`POINT_DTYPE`) for ``points`` (N, 3) mm; ``frame`` scalar or (N,).

    ``intensity``, ``sigma_mm`` (N,) and ``uv`` (N, 2) default to NaN.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise LightplaneError(f"points must have shape (N, 3), got {p.shape}")
    n = p.shape[0]
    rec = np.empty(n, POINT_DTYPE)
    rec["x"], rec["y"], rec["z"] = p[:, 0], p[:, 1], p[:, 2]
    fr = np.asarray(frame)
    if fr.ndim and fr.shape != (n,):
        raise LightplaneError(f"frame must be a scalar or have shape ({n},), got {fr.shape}")
    if np.any(fr < 0):
        raise LightplaneError("frame indices must be >= 0")
    rec["frame"] = fr
    for name, val in (("intensity", intensity), ("sigma_mm", sigma_mm)):
        rec[name] = np.nan if val is None else np.asarray(val, dtype=np.float64)
    if uv is None:
        rec["u"] = rec["v"] = np.nan
    else:
        uv = np.asarray(uv, dtype=np.float64)
        if uv.shape != (n, 2):
            raise LightplaneError(f"uv must have shape ({n}, 2), got {uv.shape}")
        rec["u"], rec["v"] = uv[:, 0], uv[:, 1]
    return rec


def cloud_format(path: str | os.PathLike, fmt: str | None = None) -> str:
    """The format for ``path``: from the suffix (.ply, .csv, .npy); ``fmt``, when given, must agree
    with it (``csv`` for ``cloud.ply`` is refused), and names the format of a file with another
    suffix (``points.txt``)."""
    suffix = Path(path).suffix.lower().lstrip(".")
    if fmt is not None:
        fmt = fmt.lower()
        if fmt not in FORMATS:
            raise LightplaneError(f"format must be one of {', '.join(FORMATS)}; got {fmt!r}")
        if suffix in FORMATS and suffix != fmt:
            raise LightplaneError(f"{path}: the format {fmt} does not match the file's suffix .{suffix} (name the "
                                  f"file .{fmt}, or leave the format out)")
        return fmt
    if suffix not in FORMATS:
        raise LightplaneError(f"{path}: cannot tell the point-cloud format from the suffix "
                              f"(use .ply, .csv or .npy, or give the format)")
    return suffix


#: the start of a spool file's name: ``.lightplane-spool-<host>-<pid>-<random>.bin``
SPOOL_PREFIX = ".lightplane-spool-"
_SPOOL_SUFFIX = ".bin"
#: a spool file whose process cannot be checked (another machine, an older name) is left over from a
#: killed run once it has not been written for this long, s
STALE_SPOOL_S = 6 * 3600.0


def _host() -> str:
    return re.sub(r"[^A-Za-z0-9.]", "_", socket.gethostname()) or "host"


def _pid_alive(pid: int) -> bool:
    """Whether process ``pid`` of this machine exists (POSIX; elsewhere: assumed alive)."""
    if sys.platform.startswith("win"):   # os.kill(pid, 0) would send CTRL_C_EVENT there
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:   # someone else's process
        return True
    return True


def remove_stale_spools(directory: str | os.PathLike | None = None, *, max_age_s: float = STALE_SPOOL_S) -> list[Path]:
    """Remove the spool files (:class:`PointSpool`) that killed runs left in ``directory`` (None: the
    temporary folder): those of a process of this machine that no longer runs, and any other not
    written for ``max_age_s``.  Returns the files removed; the files of running processes stay."""
    folder = Path(tempfile.gettempdir() if directory is None else directory)
    removed: list[Path] = []
    try:
        names = [n for n in os.listdir(folder) if n.startswith(SPOOL_PREFIX) and n.endswith(_SPOOL_SUFFIX)]
    except OSError:
        return removed
    host, now = _host(), time.time()
    for name in names:
        parts = name[len(SPOOL_PREFIX):-len(_SPOOL_SUFFIX)].rsplit("-", 2)
        path = folder / name
        try:
            if len(parts) == 3 and parts[0] == host and parts[1].isdigit():
                pid = int(parts[1])
                stale = pid != os.getpid() and not _pid_alive(pid)
            else:
                stale = now - path.stat().st_mtime > max_age_s
            if stale:
                path.unlink()
                removed.append(path)
        except OSError:   # removed meanwhile, or not ours to remove
            continue
    return removed


class PointSpool:
    """Append-only temporary file of :data:`POINT_DTYPE` records (streaming accumulation).

    ``append`` writes records straight to disk; ``chunks`` reads them back in order,
    a bounded number at a time.  Use as a context manager: the file is removed on exit,
    whatever ends the block (an error, an interrupt; the command line turns SIGTERM into an
    exit too).  A run killed outright leaves its file behind: the file's name carries the
    host and process id, and the next spool made in that folder removes the files of
    processes that are gone (:func:`remove_stale_spools`).
    """

    def __init__(self, directory: str | os.PathLike | None = None, dtype: np.dtype = POINT_DTYPE) -> None:
        self.dtype = np.dtype(dtype)
        remove_stale_spools(directory)
        fd, self.path = tempfile.mkstemp(prefix=f"{SPOOL_PREFIX}{_host()}-{os.getpid()}-", suffix=_SPOOL_SUFFIX,
                                         dir=None if directory is None else str(directory))
        self._f = os.fdopen(fd, "wb")
        self.count = 0

    def append(self, records: np.ndarray) -> None:
        if records.dtype != self.dtype:
            raise LightplaneError(f"spool records must have dtype {self.dtype}, got {records.dtype}")
        if records.size:
            self._f.write(np.ascontiguousarray(records).tobytes())
            self.count += int(records.size)

    def chunks(self, n: int = CHUNK_RECORDS) -> Iterator[np.ndarray]:
        self._f.flush()
        with open(self.path, "rb") as f:
            left = self.count
            while left > 0:
                k = min(n, left)
                a = np.fromfile(f, dtype=self.dtype, count=k)
                if a.size != k:
                    raise LightplaneError(f"{self.path}: spool file is truncated")
                left -= k
                yield a

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()
        if os.path.exists(self.path):
            os.unlink(self.path)

    def __enter__(self) -> "PointSpool":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _chunks_of(data, n: int = CHUNK_RECORDS) -> tuple[int, np.dtype, Iterable[np.ndarray]]:
    if isinstance(data, PointSpool):
        return data.count, data.dtype, data.chunks(n)
    if not isinstance(data, np.ndarray) or data.dtype.names is None or data.ndim != 1:
        raise LightplaneError("cloud data must be a 1-D structured array (POINT_DTYPE) or a PointSpool")
    return data.size, data.dtype, (data[i:i + n] for i in range(0, data.size, n))


def _ply_header(dtype: np.dtype, count: int, ascii: bool, comments: Iterable[str]) -> bytes:
    from plyfile import PlyData, PlyElement

    le = np.dtype([(name, dtype[name].newbyteorder("<")) for name in record_fields(dtype)])
    props = PlyElement.describe(np.empty(0, le), "vertex").properties
    element = PlyElement("vertex", props, count)
    ply = PlyData([element], text=ascii, byte_order="<", comments=[c.replace("\n", " ") for c in comments])
    return (ply.header + "\n").encode("ascii")


def _text_format(dtype: np.dtype, sep: str) -> str:
    parts = []
    for name in record_fields(dtype):
        kind = dtype[name].kind
        parts.append("%d" if kind in "iu" else "%.9g" if dtype[name].itemsize <= 4 else "%.17g")
    return sep.join(parts)


def _write_text_rows(f, chunk: np.ndarray, fmt: str) -> None:
    # one formatting per row; float32 fields go through float() so "%.9g" sees the exact value
    cols = [chunk[name].tolist() for name in record_fields(chunk.dtype)]
    f.write("".join((fmt % row) + "\n" for row in zip(*cols)))


def write_cloud(path: str | os.PathLike, data, *, fmt: str | None = None, ascii: bool = False,
                force: bool = False, comments: Iterable[str] = ()) -> Path:
    """Write a point cloud atomically as PLY (binary unless ``ascii``), CSV or NPY.

    ``data``: a structured array (e.g. :data:`POINT_DTYPE` records) or a
    :class:`PointSpool` (streamed in chunks).  ``fmt`` defaults to the suffix;
    ``comments`` (PLY comments, CSV ``#`` lines; NPY has none) e.g. provenance lines, after the units line
    (:func:`units_line`).  Refuses to overwrite without
    ``force``.  Returns the path.
    """
    fmt = cloud_format(path, fmt)
    if ascii and fmt != "ply":
        raise LightplaneError("ascii applies to PLY only (CSV is text, NPY is binary)")
    count, dtype, chunks = _chunks_of(data)
    comments = [c.replace("\n", " ") for c in comments]
    if not any(c.startswith("units:") for c in comments):
        comments.insert(0, units_line(dtype))

    def writer(tmp: str) -> None:
        if fmt == "ply":
            with open(tmp, "wb") as f:
                f.write(_ply_header(dtype, count, ascii, comments))
                if ascii:
                    text = _text_format(dtype, " ")
                    import io as _io

                    for c in chunks:
                        buf = _io.StringIO()
                        _write_text_rows(buf, c, text)
                        f.write(buf.getvalue().encode("ascii"))
                else:
                    le = dtype.newbyteorder("<") if dtype.byteorder == ">" else dtype
                    for c in chunks:
                        f.write(np.ascontiguousarray(c.astype(le, copy=False)).tobytes())
        elif fmt == "csv":
            text = _text_format(dtype, ",")
            with open(tmp, "w", newline="") as f:
                f.write("".join(f"# {c}\n" for c in comments))  # units, frame, provenance: '#' lines first
                f.write(",".join(record_fields(dtype)) + "\n")
                for c in chunks:
                    _write_text_rows(f, c, text)
        else:
            with open(tmp, "wb") as f:
                header = {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False, "shape": (count,)}
                np.lib.format.write_array_header_2_0(f, header)
                for c in chunks:
                    f.write(np.ascontiguousarray(c).tobytes())

    return atomic_write(path, writer, force=force)


def cloud_comments(path: str | os.PathLike) -> list[str]:
    """The comment lines of a cloud file (PLY ``comment`` lines, CSV ``#`` lines; none for NPY):
    the units, the coordinate frame, the provenance."""
    p = Path(path)
    fmt = cloud_format(p)
    if fmt == "npy" or not p.is_file():
        return []
    out = []
    if fmt == "ply":
        with open(p, "rb") as fb:
            for raw in fb:  # the header is ASCII lines up to end_header, in every PLY format
                line = raw.decode("ascii", "replace").rstrip("\r\n")
                if line == "end_header":
                    break
                if line.startswith("comment "):
                    out.append(line[len("comment "):])
        return out
    with open(p, newline="") as f:
        for line in f:
            if not line.startswith("#"):
                break
            out.append(line[1:].strip())
    return out


def read_cloud(path: str | os.PathLike, fmt: str | None = None) -> np.ndarray:
    """Read a point cloud written by :func:`write_cloud` (or any PLY with a ``vertex`` element,
    any CSV with a header row, any 1-D structured NPY) as a structured array.

    Fields named like :data:`POINT_DTYPE`'s get its types; other CSV columns are float64.
    A missing or malformed file raises :class:`LightplaneError` naming it.
    """
    p = Path(path)
    if not p.is_file():
        raise LightplaneError(f"{p}: no such point-cloud file")
    fmt = cloud_format(p, fmt)
    if fmt == "ply":
        from plyfile import PlyData

        try:
            ply = PlyData.read(str(p))
            vertex = ply["vertex"]
        except KeyError:
            raise LightplaneError(f"{p}: PLY file has no 'vertex' element") from None
        except Exception as e:  # plyfile raises its own PlyParseError / ValueError
            raise LightplaneError(f"{p}: not a readable PLY file ({e})") from None
        data = vertex.data
        native = np.dtype([(n, data.dtype[n].newbyteorder("<")) for n in data.dtype.names])
        return np.array(data, dtype=native)
    if fmt == "npy":
        try:
            a = np.load(p, allow_pickle=False)
        except (ValueError, OSError) as e:
            raise LightplaneError(f"{p}: not a readable NPY file ({e})") from None
        if a.dtype.names is None or a.ndim != 1:
            raise LightplaneError(f"{p}: expected a 1-D structured array, got dtype {a.dtype} shape {a.shape}")
        return a
    with open(p, newline="") as f:
        header = f.readline()
        while header.startswith("#"):  # comment lines (units, frame, provenance) before the header row
            header = f.readline()
        header = header.strip()
        names = [h.strip() for h in header.split(",")]
        if not header or any(not n or n[0].isdigit() or n[0] in "+-." for n in names):
            raise LightplaneError(f"{p}: first row must name the columns (x,y,z,...), got {header!r}")
        dtype = np.dtype([(n, POINT_DTYPE[n] if n in POINT_FIELDS else "<f8") for n in names])
        import warnings

        try:
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", message="loadtxt: input contained no data")
                a = np.loadtxt(f, delimiter=",", dtype=dtype, ndmin=1)
        except ValueError as e:
            raise LightplaneError(f"{p}: malformed CSV row ({e})") from None
    return a
