"""Range images of linear scans: the cloud resampled on a regular grid, one row per frame (docs/range-images.md).

A linear scan moves the object through the light sheet; each frame gives one profile.  The range
image is the grid that line-scan software processes (SICK's rectified range image, HALCON's X, Y,
Z images):

- **rows** are the frames, in order (row ``i`` is frame ``frame0 + i``; a frame without points is
  a row of missing values);
- **columns** are a regular grid of the *across* coordinate (``x`` or ``y`` of the cloud, mm):
  column ``j`` is at ``across = origin_mm + j * step_mm``;
- each pixel holds the point of that frame at that column, linearly interpolated between the
  frame's two nearest points along the profile (never across a gap wider than ``max_gap_steps``
  times the larger of the column spacing and the median point spacing: there the pixel is missing).

Stored as

- the **float arrays** ``X``, ``Y``, ``Z`` (rows x columns, float32 mm, NaN where missing; the
  across coordinate's array is the column grid itself), HALCON's three images, in an ``.npz``
  with the metadata (:func:`write_range_image`);
- a **16-bit image** (PNG or TIFF) of the *height* coordinate (``z`` by default), SICK's
  convention: ``0`` is missing data, else ``height = offset_mm + value * scale_mm``; the scale,
  offset, column grid and frames are in the image's metadata (PNG text chunk / TIFF
  ImageDescription, key ``lightplane.range_image``, JSON).  The default scale is the finest of
  1, 2, 5 x 10^k µm that spans the heights in 65535 levels: the quantisation error is at most
  half of it.

The cloud's frame (the object at frame 0, camera axes, mm) carries over: the metadata says so.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lightplane.core.checks import MAX_DISTANCE_MM
from lightplane.core.errors import LightplaneError
from lightplane.core.io import atomic_write

__all__ = ["RangeImageOptions", "RangeImage", "range_image", "write_range_image", "read_range_image", "META_KEY"]

#: the metadata key of the 16-bit image (PNG text chunk, TIFF ImageDescription as ``KEY=JSON``)
META_KEY = "lightplane.range_image"
_AXES = ("x", "y", "z")


@dataclass(frozen=True)
class RangeImageOptions:
    """How a cloud becomes a range image (checked on construction).

    across : the cloud coordinate of the columns, ``x`` or ``y``; ``auto``: the one the profiles
        extend along most (their median extent within a frame)
    height : the coordinate of the 16-bit image's values (``z``: the depth along the camera's axis)
    step_mm : the column spacing; None: the median spacing of neighbouring points along the profiles
    scale_mm : the 16-bit image's height quantum; None: see the module's notes
    max_gap_steps : no interpolation between points further apart than this many times the larger of the
        column spacing and the profiles' median point spacing
    """

    across: str = "auto"
    height: str = "z"
    step_mm: float | None = None
    scale_mm: float | None = None
    max_gap_steps: float = 2.0

    def __post_init__(self) -> None:
        if self.across not in ("auto", "x", "y", "z"):
            raise LightplaneError(f"across must be x, y, z or auto, got {self.across!r}")
        if self.height not in _AXES:
            raise LightplaneError(f"height must be x, y or z, got {self.height!r}")
        if self.across == self.height:
            raise LightplaneError(f"the columns and the height must be different coordinates, both {self.height}")
        for name in ("step_mm", "scale_mm"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and 0 < v <= MAX_DISTANCE_MM):
                raise LightplaneError(f"{name} must be a positive number of mm up to {MAX_DISTANCE_MM:g}, got {v}")
        if not (math.isfinite(self.max_gap_steps) and self.max_gap_steps >= 1):
            raise LightplaneError(f"max_gap_steps must be >= 1, got {self.max_gap_steps}")


@dataclass(frozen=True)
class RangeImage:
    """A range image (see the module's notes): ``xyz`` (3, rows, columns) float32 mm, NaN where missing."""

    xyz: np.ndarray
    across: str
    height: str
    origin_mm: float
    step_mm: float
    frame0: int
    scale_mm: float
    offset_mm: float
    frame_description: str = "the cloud's frame"
    meta: dict = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.xyz.shape[1]), int(self.xyz.shape[2])

    @property
    def heights(self) -> np.ndarray:
        """(rows, columns) float32 mm of the height coordinate, NaN where missing."""
        return self.xyz[_AXES.index(self.height)]

    def values(self) -> np.ndarray:
        """The 16-bit image: 0 where missing, else ``round((height - offset_mm) / scale_mm)`` (1..65535)."""
        h = self.heights.astype(np.float64)
        v = np.zeros(h.shape, np.uint16)
        ok = np.isfinite(h)
        v[ok] = np.clip(np.rint((h[ok] - self.offset_mm) / self.scale_mm), 1, 65535).astype(np.uint16)
        return v

    def metadata(self) -> dict:
        """What the files record: the grid, the quantisation, the frames and the frame of the coordinates."""
        rows, cols = self.shape
        return {"kind": "lightplane range image", "version": 1, "units": "mm",
                "coordinates": f"{self.frame_description}; rows: frames {self.frame0}..{self.frame0 + rows - 1}",
                "columns": {"coordinate": self.across, "origin_mm": self.origin_mm, "step_mm": self.step_mm,
                            "count": cols, "note": f"{self.across} = origin_mm + column * step_mm"},
                "rows": {"frame0": self.frame0, "count": rows, "note": "row = frame - frame0"},
                "values": {"coordinate": self.height, "scale_mm": self.scale_mm, "offset_mm": self.offset_mm,
                           "missing": 0, "note": f"{self.height} = offset_mm + value * scale_mm; 0: no point"},
                **self.meta}


def _nice_scale(span_mm: float) -> float:
    """The finest of 1, 2, 5 x 10^k µm that spans ``span_mm`` in 65534 steps."""
    need = max(span_mm, 1e-9) / 65534.0
    k = math.floor(math.log10(need))
    for m in (1.0, 2.0, 5.0, 10.0):
        s = m * 10.0 ** k
        if s >= need * (1 - 1e-12):
            return float(s)
    return float(10.0 ** (k + 1))  # pragma: no cover - the loop's 10 x 10^k always fits


def _coords(records: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    names = records.dtype.names or ()
    if not {"x", "y", "z", "frame"} <= set(names):
        raise LightplaneError("a range image needs the points' x, y, z and frame (a cloud written by measure)")
    p = np.column_stack([records["x"], records["y"], records["z"]]).astype(np.float64)
    f = np.asarray(records["frame"]).astype(np.int64)
    ok = np.all(np.isfinite(p), axis=1)
    return p[ok], f[ok]


def _across_axis(p: np.ndarray, f: np.ndarray, height: str) -> str:
    """The coordinate the profiles extend along most (median extent within a frame), of the two not the height."""
    cand = [a for a in _AXES if a != height]
    ext = []
    for a in cand:
        c = p[:, _AXES.index(a)]
        per = [float(np.ptp(c[f == k])) for k in np.unique(f)]
        ext.append(float(np.median(per)) if per else 0.0)
    return cand[int(np.argmax(ext))]


def _step(p: np.ndarray, f: np.ndarray, ia: int) -> float:
    """The median spacing of neighbouring points along the profiles (mm)."""
    gaps = []
    for k in np.unique(f):
        a = np.sort(p[f == k, ia])
        d = np.diff(a)
        gaps.append(d[d > 0])
    g = np.concatenate(gaps) if gaps else np.zeros(0)
    if not len(g):
        raise LightplaneError("the profiles have fewer than two distinct points: no column spacing to take")
    return float(np.median(g))


def _resample(a: np.ndarray, vals: np.ndarray, grid: np.ndarray, max_gap: float) -> np.ndarray:
    """(3, len(grid)): ``vals`` (N, 3) interpolated linearly in ``a`` at ``grid``; NaN off the points or across gaps."""
    order = np.argsort(a, kind="stable")
    a, vals = a[order], vals[order]
    out = np.full((3, len(grid)), np.nan)
    if len(a) < 2:
        return out
    j = np.searchsorted(a, grid, side="right")
    inside = (j > 0) & (j < len(a))
    lo, hi = np.clip(j - 1, 0, len(a) - 1), np.clip(j, 0, len(a) - 1)
    ok = inside & (a[hi] - a[lo] <= max_gap)
    ok |= (j > 0) & (a[lo] == grid)  # exactly on the last point
    for c in range(3):
        out[c, ok] = np.interp(grid[ok], a, vals[:, c])
    return out


def range_image(records: np.ndarray, options: RangeImageOptions | None = None, *,
                frame_description: str = "the cloud's frame", meta: dict | None = None) -> RangeImage:
    """The range image of a linear scan's cloud (records with x, y, z, frame; see the module's notes)."""
    opts = RangeImageOptions() if options is None else options
    p, f = _coords(np.asarray(records))
    if len(p) < 2:
        raise LightplaneError(f"the cloud has {len(p)} finite points: no range image")
    across = _across_axis(p, f, opts.height) if opts.across == "auto" else opts.across
    if across == opts.height:
        raise LightplaneError(f"the columns and the height must be different coordinates, both {across}")
    ia = _AXES.index(across)
    spacing = _step(p, f, ia)
    step = float(opts.step_mm) if opts.step_mm is not None else spacing
    lo, hi = float(p[:, ia].min()), float(p[:, ia].max())
    n_cols = int(math.floor((hi - lo) / step + 1e-9)) + 1
    if n_cols > 100_000:
        raise LightplaneError(f"{n_cols} columns of {step:g} mm: give a coarser step_mm")
    origin = math.floor(lo / step) * step  # a grid through 0: columns of different scans line up
    n_cols = int(math.floor((hi - origin) / step + 1e-9)) + 1
    grid = origin + step * np.arange(n_cols)
    f0, f1 = int(f.min()), int(f.max())
    xyz = np.full((3, f1 - f0 + 1, n_cols), np.nan, np.float32)
    order = np.argsort(f, kind="stable")
    bounds = np.searchsorted(f[order], np.arange(f0, f1 + 2))
    for r in range(f1 - f0 + 1):
        sel = order[bounds[r]:bounds[r + 1]]
        if len(sel) >= 2:
            xyz[:, r, :] = _resample(p[sel, ia], p[sel], grid, opts.max_gap_steps * max(step, spacing))
    xyz[ia] = np.where(np.isfinite(xyz[ia]), grid[None, :].astype(np.float32), np.nan)
    h = xyz[_AXES.index(opts.height)]
    if not np.isfinite(h).any():
        raise LightplaneError("no pixel of the range image has a point (profiles of single points?)")
    hmin, hmax = float(np.nanmin(h)), float(np.nanmax(h))
    scale = float(opts.scale_mm) if opts.scale_mm is not None else _nice_scale(hmax - hmin)
    offset = math.floor(hmin / scale) * scale - scale  # value 1 at (or just below) the lowest height
    if hmax - hmin > 0 and (hmax - hmin) / scale < 1.0:
        raise LightplaneError(f"heights {hmin:.3f}–{hmax:.3f} mm span less than one level of {scale:g} mm: "
                              "give a finer scale")
    if (hmax - offset) / scale > 65535.5:
        raise LightplaneError(f"heights {hmin:.3f}–{hmax:.3f} mm need more than 65535 levels of {scale:g} mm: "
                              "give a coarser scale")
    return RangeImage(xyz, across, opts.height, float(origin), step, f0, scale, float(offset), frame_description,
                      dict(meta or {}))


def _npz_path(path: Path) -> Path:
    return path.with_suffix(".npz")


def write_range_image(path: str | os.PathLike, image: RangeImage, *, force: bool = False) -> list[Path]:
    """Write the 16-bit image (``.png`` or ``.tif``/``.tiff``, by the suffix) with its metadata, and the float
    arrays ``X``, ``Y``, ``Z`` beside it (same name, ``.npz``, with the metadata as JSON under ``meta``);
    atomically, refusing to overwrite without ``force``.  Returns both paths."""
    from PIL import Image
    from PIL.PngImagePlugin import PngInfo

    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in (".png", ".tif", ".tiff"):
        raise LightplaneError(f"{p}: a range image is written as .png or .tif (16 bit)")
    meta = image.metadata()
    text = json.dumps(meta)
    im = Image.fromarray(image.values())  # uint16: mode I;16

    def write_image(tmp: str) -> None:
        if suffix == ".png":
            info = PngInfo()
            info.add_text(META_KEY, text)
            im.save(tmp, format="PNG", pnginfo=info)
        else:
            im.save(tmp, format="TIFF", tiffinfo={270: f"{META_KEY}={text}"})

    npz = _npz_path(p)

    def write_arrays(tmp: str) -> None:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, X=image.xyz[0], Y=image.xyz[1], Z=image.xyz[2], meta=np.array(text))

    for target in (p, npz):  # both refused before either is written
        if target.exists() and not force:
            raise LightplaneError(f"{target}: already exists (use --force to overwrite)")
    return [atomic_write(p, write_image, force=force), atomic_write(npz, write_arrays, force=force)]


def read_range_image(path: str | os.PathLike) -> tuple[np.ndarray, dict]:
    """The 16-bit values and the metadata of a range image written by :func:`write_range_image`."""
    from PIL import Image

    p = Path(path)
    if not p.is_file():
        raise LightplaneError(f"{p}: no such range image")
    try:
        with Image.open(p) as im:
            values = np.array(im).astype(np.uint16)
            text = im.info.get(META_KEY) if p.suffix.lower() == ".png" else str(im.getexif().get(270, ""))
    except (OSError, ValueError) as e:
        raise LightplaneError(f"{p}: not a readable image ({e})") from None
    if text and not text.startswith("{"):
        text = text.partition("=")[2]
    if not text:
        raise LightplaneError(f"{p}: has no {META_KEY} metadata (not written by lightplane?)")
    return values, json.loads(text)
