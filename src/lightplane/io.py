"""Small I/O helpers shared by every command: images, atomic writes, provenance.

Outputs are written to a temporary file in the destination folder and renamed,
so a crash or a bad input never leaves a half-written file, and an existing
file is only replaced when the caller says ``force``.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import sys
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from .errors import LightplaneError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".pbm")


def read_image(path: str | os.PathLike, *, rotate_deg: int = 0) -> np.ndarray:
    """Read an image file as stored (8- or 16-bit, gray or colour, BGR order).

    ``rotate_deg`` (0, 90, 180, 270) rotates clockwise after reading.  A missing,
    unreadable or non-image file raises :class:`LightplaneError` naming the file.
    """
    import cv2

    p = Path(path)
    if not p.exists():
        raise LightplaneError(f"{p}: no such file")
    if p.is_dir():
        raise LightplaneError(f"{p}: is a folder, not an image")
    data = np.fromfile(str(p), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise LightplaneError(f"{p}: not a readable image")
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, :3]
    return rotate_image(img, rotate_deg)


def rotate_image(img: np.ndarray, rotate_deg: int) -> np.ndarray:
    """Rotate clockwise by 0, 90, 180 or 270 degrees."""
    import cv2

    codes = {0: None, 90: cv2.ROTATE_90_CLOCKWISE, 180: cv2.ROTATE_180, 270: cv2.ROTATE_90_COUNTERCLOCKWISE}
    if rotate_deg not in codes:
        raise LightplaneError(f"rotate_deg must be 0, 90, 180 or 270, got {rotate_deg}")
    code = codes[rotate_deg]
    return img if code is None else cv2.rotate(img, code)


def to_gray_float(img: np.ndarray, channel: str | None = None) -> np.ndarray:
    """Gray float32 image from gray or BGR input; ``channel`` in {red, green, blue, gray}."""
    import cv2

    if img.ndim == 2:
        return img.astype(np.float32, copy=False)
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise LightplaneError(f"image must be (H, W) or (H, W, 3), got shape {img.shape}")
    if channel in (None, "gray"):
        return cv2.cvtColor(img[:, :, :3], cv2.COLOR_BGR2GRAY).astype(np.float32) if img.dtype == np.uint8 \
            else (0.114 * img[:, :, 0] + 0.587 * img[:, :, 1] + 0.299 * img[:, :, 2]).astype(np.float32)
    idx = {"blue": 0, "green": 1, "red": 2}.get(channel)
    if idx is None:
        raise LightplaneError(f"channel must be red, green, blue or gray, got {channel!r}")
    return img[:, :, idx].astype(np.float32)


def check_output(path: str | os.PathLike, force: bool) -> Path:
    """Refuse to overwrite an existing file without ``force``; check the folder exists."""
    p = Path(path)
    if p.exists() and not force:
        raise LightplaneError(f"{p}: already exists (use --force to overwrite)")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.exists():
        raise LightplaneError(f"{parent}: output folder does not exist")
    if not os.access(parent, os.W_OK):
        raise LightplaneError(f"{parent}: output folder is not writable")
    return p


def atomic_write(path: str | os.PathLike, writer: Callable[[str], None] | bytes | str, *, force: bool = False) -> Path:
    """Write ``path`` atomically: ``writer(tmp_path)`` (or the given bytes/text) then rename.

    The temporary file lives in the destination folder (same file system), keeps
    the destination's suffix (some writers dispatch on it), and is removed if
    anything fails.
    """
    p = check_output(path, force)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=p.suffix or ".tmp", dir=str(p.parent) or ".")
    os.close(fd)
    try:
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; results are ordinary files
        if callable(writer):
            writer(tmp)
        else:
            mode = "wb" if isinstance(writer, (bytes, bytearray)) else "w"
            with open(tmp, mode) as f:
                f.write(writer)
        os.replace(tmp, p)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return p


def save_figure(fig, path: str | os.PathLike, *, force: bool = False, dpi: int | None = None) -> Path:
    """Save a matplotlib figure atomically (format from the suffix, PNG by default) and close it."""
    import matplotlib.pyplot as plt

    fmt = Path(path).suffix.lstrip(".").lower() or "png"
    try:
        return atomic_write(path, lambda tmp: fig.savefig(tmp, format=fmt, dpi=dpi), force=force)
    finally:
        plt.close(fig)


def _read_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _read_umask()  # read once at import: os.umask is process-wide, not thread-safe


def _jsonable(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def dumps_json(obj: Any) -> str:
    """JSON text with numpy arrays and paths converted; NaN is written as null."""
    return json.dumps(_nan_to_none(obj), indent=2, default=_jsonable) + "\n"


def _nan_to_none(obj: Any) -> Any:
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _nan_to_none(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_nan_to_none(v) for v in obj]
    if isinstance(obj, np.ndarray) and obj.dtype.kind == "f":
        return _nan_to_none(obj.tolist())
    return obj


def write_json(path: str | os.PathLike, obj: Any, *, force: bool = False) -> Path:
    """Atomically write ``obj`` as JSON."""
    return atomic_write(path, dumps_json(obj), force=force)


def read_json(path: str | os.PathLike, what: str = "file") -> dict:
    """Read a JSON object, with one clear error for a missing or corrupt file."""
    p = Path(path)
    if not p.is_file():
        raise LightplaneError(f"{p}: no such {what}")
    try:
        obj = json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise LightplaneError(f"{p}: not valid JSON ({e})") from None
    if not isinstance(obj, dict):
        raise LightplaneError(f"{p}: expected a JSON object at the top level")
    return obj


def versions() -> dict[str, str]:
    """Versions of lightplane and the libraries that shape its numbers."""
    import cv2
    import scipy

    from . import __version__

    return {
        "lightplane": __version__,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "opencv": cv2.__version__,
    }


def provenance(inputs: Iterable[Any] = (), options: dict | None = None) -> dict:
    """What produced a result file: command line, inputs, options, versions, time (UTC)."""
    return {
        "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]) if sys.argv else "",
        "inputs": [str(x) for x in inputs],
        "options": options or {},
        "versions": versions(),
        "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }


def expand_inputs(items: Iterable[str | os.PathLike], suffixes: tuple[str, ...] = IMAGE_SUFFIXES) -> list[Path]:
    """Expand folders and glob patterns into a sorted list of files (natural order)."""
    import glob
    import re

    def natural(p: Path):
        return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", str(p))]

    out: list[Path] = []
    for item in items:
        s = str(item)
        p = Path(s)
        if p.is_dir():
            out.extend(sorted((q for q in p.iterdir() if q.suffix.lower() in suffixes), key=natural))
        elif any(ch in s for ch in "*?["):
            out.extend(sorted((Path(q) for q in glob.glob(s)), key=natural))
        else:
            out.append(p)
    return out
