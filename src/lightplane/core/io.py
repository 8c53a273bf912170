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
import re
import sys
import threading
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from lightplane.core.errors import LightplaneError
from lightplane.version import __version__

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".pbm")


def read_image(path: str | os.PathLike, *, rotate_deg: int = 0) -> np.ndarray:
    """Read an image file as stored (8- or 16-bit, gray or colour, BGR order).

    ``rotate_deg`` (0, 90, 180, 270) rotates clockwise after reading.  A missing,
    unreadable, truncated or non-image file raises :class:`LightplaneError` naming the
    file and the reason (see :func:`try_read_image`).
    """
    img, reason = try_read_image(path, rotate_deg=rotate_deg)
    if img is None:
        raise LightplaneError(f"{Path(path)}: {reason}")
    return img


def try_read_image(path: str | os.PathLike, *, rotate_deg: int = 0) -> tuple[np.ndarray | None, str]:
    """``(image, "")``, or ``(None, reason)`` when the file cannot be used as an image.

    Reasons (one short phrase, without the file name): ``no such file``, ``is a folder,
    not an image``, ``cannot be read (permission denied)``, ``not a readable image (empty
    file)``, ``too large: W x H px ...`` (the size in a PNG, JPEG, BMP, TIFF or PNM header
    above :func:`max_pixels`, refused before anything is decoded), ``not a readable image (truncated)`` (a PNG without its IEND chunk, a JPEG
    without its end-of-image marker, a BMP shorter than its header says: decoders may
    otherwise return a partly grey image with only a warning), ``not a readable image
    (not an image file)``, ``not a readable image (corrupt)`` or, for the formats whose end
    is not checked here (TIFF, WebP...), ``not a readable image (corrupt or truncated)``.  A bad ``rotate_deg``
    raises (it is the caller's error, not the file's).
    """
    import cv2

    rotation_code(rotate_deg)
    p = Path(path)
    if not p.exists():
        return None, "no such file"
    if p.is_dir():
        return None, "is a folder, not an image"
    limit = max_pixels()
    try:
        size = image_header_size(p)
        if size is not None and size[0] * size[1] > limit:
            return None, (f"too large: {size[0]}x{size[1]} px ({size[0] * size[1] / 1e6:.3g} megapixels) in its header, "
                          f"above the limit of {limit / 1e6:g} megapixels (--max-pixels or {MAX_PIXELS_ENV} raises it)")
        data = np.fromfile(str(p), dtype=np.uint8)
    except PermissionError:
        return None, "cannot be read (permission denied)"
    except OSError as e:
        return None, f"cannot be read ({e.strerror or e})"
    if data.size == 0:
        return None, "not a readable image (empty file)"
    kind = _image_kind(data[:16].tobytes())
    if kind is not None and _is_truncated(kind, data):
        return None, "not a readable image (truncated)"
    with _quiet_decoder():
        try:
            img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
        except cv2.error:
            img = None
    if img is None or img.size == 0:
        if kind is not None:  # complete PNG / JPEG / BMP structure, bad content
            return None, "not a readable image (corrupt)"
        return None, "not a readable image (corrupt or truncated)" if _looks_like_image(data) \
            else "not a readable image (not an image file)"
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, :3]
    return rotate_image(img, rotate_deg), ""


#: the largest image read, in pixels (width x height), unless :data:`MAX_PIXELS_ENV` says otherwise:
#: 100 megapixels, beyond every line-scan-free industrial sensor lightplane is used with; a 16-bit
#: colour image of that size takes 0.6 GB decoded
DEFAULT_MAX_PIXELS = 100_000_000
#: the environment variable that sets the limit (a positive integer, pixels)
MAX_PIXELS_ENV = "LIGHTPLANE_MAX_PIXELS"


def max_pixels() -> int:
    """The largest image :func:`try_read_image` decodes: :data:`DEFAULT_MAX_PIXELS`, or the value of
    the environment variable :data:`MAX_PIXELS_ENV` (read at each call)."""
    text = os.environ.get(MAX_PIXELS_ENV, "").strip()
    if not text:
        return DEFAULT_MAX_PIXELS
    try:
        value = int(float(text))
    except ValueError:
        value = 0
    if value <= 0:
        raise LightplaneError(f"{MAX_PIXELS_ENV} must be a positive number of pixels, got {text!r}")
    return value


def image_header_size(path: str | os.PathLike) -> tuple[int, int] | None:
    """``(width, height)`` from the header of a PNG, JPEG, BMP, TIFF or PNM (PBM/PGM/PPM) file, read
    without decoding the pixels; None for other formats or a header that cannot be parsed (the
    decoder then judges the file)."""
    with open(path, "rb") as f:
        head = f.read(32)
        try:
            if head.startswith(b"\x89PNG\r\n\x1a\n"):
                return _png_size(head)
            if head.startswith(b"\xff\xd8"):
                return _jpeg_size(f)
            if head.startswith(b"BM"):
                return _bmp_size(head)
            if head[:4] in (b"II*\x00", b"MM\x00*"):
                return _tiff_size(f, "<" if head[:2] == b"II" else ">")
            if len(head) >= 2 and head[:1] == b"P" and head[1:2] in b"123456":
                return _pnm_size(f)
        except (ValueError, IndexError, OSError):
            return None
    return None


def _png_size(head: bytes) -> tuple[int, int] | None:
    if head[12:16] != b"IHDR":
        return None
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def _jpeg_size(f) -> tuple[int, int] | None:
    """The first start-of-frame marker's size, walking the marker segments from the file's start."""
    f.seek(2)
    while True:
        b = f.read(1)
        while b == b"\xff":  # fill bytes before the marker code
            b = f.read(1)
        if not b:
            return None
        marker = b[0]
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:
            if f.read(1) != b"\xff":
                return None
            continue
        if marker in (0xD9, 0xDA):  # end of image, start of scan: no frame header before them
            return None
        seg = f.read(2)
        if len(seg) < 2:
            return None
        length = int.from_bytes(seg, "big")
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            sof = f.read(5)
            if len(sof) < 5:
                return None
            return int.from_bytes(sof[3:5], "big"), int.from_bytes(sof[1:3], "big")
        f.seek(length - 2, 1)
        if f.read(1) != b"\xff":
            return None


def _bmp_size(head: bytes) -> tuple[int, int] | None:
    if len(head) < 26:
        return None
    if int.from_bytes(head[14:18], "little") == 12:  # OS/2 core header: 16-bit sizes
        return int.from_bytes(head[18:20], "little"), int.from_bytes(head[20:22], "little")
    w = int.from_bytes(head[18:22], "little", signed=True)
    h = int.from_bytes(head[22:26], "little", signed=True)  # negative: rows stored top-down
    return abs(w), abs(h)


def _tiff_size(f, order: str) -> tuple[int, int] | None:
    """ImageWidth (256) and ImageLength (257) of the first image file directory."""
    big = order == ">"
    f.seek(4)
    f.seek(int.from_bytes(f.read(4), "big" if big else "little"))
    raw = f.read(2)
    count = int.from_bytes(raw, "big" if big else "little")
    if len(raw) < 2 or count > 4096:
        return None
    entries = f.read(12 * count)
    found: dict[int, int] = {}
    for k in range(len(entries) // 12):
        e = entries[12 * k:12 * k + 12]
        tag, typ = (int.from_bytes(e[i:i + 2], "big" if big else "little") for i in (0, 2))
        if tag in (256, 257) and typ in (3, 4):
            found[tag] = int.from_bytes(e[8:10] if typ == 3 else e[8:12], "big" if big else "little")
    return (found[256], found[257]) if 256 in found and 257 in found else None


def _pnm_size(f) -> tuple[int, int] | None:
    """Width and height after the magic number, skipping whitespace and comments."""
    f.seek(2)
    text = f.read(1024)
    numbers: list[int] = []
    for line in text.split(b"\n"):
        for token in line.split(b"#", 1)[0].split():
            if not token.isdigit():
                return None
            numbers.append(int(token))
            if len(numbers) == 2:
                return numbers[0], numbers[1]
    return None


def read_images(paths: Iterable[str | os.PathLike], *, rotate_deg: int = 0
                ) -> tuple[list[tuple[Path, np.ndarray]], list[tuple[Path, str]]]:
    """Read every file; the unusable ones are skipped with their reason, not fatal.

    Returns ``(images, skipped)``: ``images`` the ``(path, array)`` pairs read, in input
    order; ``skipped`` the ``(path, reason)`` pairs of the files that are missing,
    folders, empty, truncated, corrupt or not images (reasons: :func:`try_read_image`).
    Callers decide whether enough images remain (:func:`too_few_images_message`).
    """
    rotation_code(rotate_deg)
    ok: list[tuple[Path, np.ndarray]] = []
    skipped: list[tuple[Path, str]] = []
    for item in paths:
        p = Path(item)
        img, reason = try_read_image(p, rotate_deg=rotate_deg)
        if img is None:
            skipped.append((p, reason))
        else:
            ok.append((p, img))
    return ok, skipped


def _display_name(name: Any) -> str:
    s = str(name)
    return Path(s).name or s


_DETAIL = re.compile(r"\s*\([^()]*\d[^()]*\)\s*$")


def summarize_reasons(skipped: Iterable[tuple[Any, str]], *, max_names: int = 3) -> str:
    """One line grouping skipped items by reason, most frequent first.

    A reason given once reads ``name: reason``; a repeated one ``N reason: a, b, c and
    K more``; groups are separated by ``;``.  A trailing parenthesis with numbers in it (``too few stripe points
    (12)``) is left out when grouping, so per-image counts do not split a group.
    """
    groups: dict[str, list[tuple[str, str]]] = {}
    for name, reason in skipped:
        reason = str(reason) or "not usable"
        key = _DETAIL.sub("", reason) or reason
        groups.setdefault(key, []).append((_display_name(name), reason))
    parts = []
    for key, items in sorted(groups.items(), key=lambda kv: -len(kv[1])):  # stable: first seen first on ties
        if len(items) == 1:
            parts.append(f"{items[0][0]}: {items[0][1]}")
        else:
            names = ", ".join(n for n, _ in items[:max_names])
            more = f" and {len(items) - max_names} more" if len(items) > max_names else ""
            parts.append(f"{len(items)} {key}: {names}{more}")
    return "; ".join(parts)


def too_few_images_message(what: str, n_usable: int, minimum: int, skipped: Iterable[tuple[Any, str]]) -> str:
    """The one-line error when fewer than ``minimum`` of the inputs are usable.

    ``what``: the plural noun of the inputs ("images", "frames", "background images");
    ``skipped``: ``(name, reason)`` of every input not usable (the total is
    ``n_usable + len(skipped)``).  E.g. ``only 1 of 12 images usable, need at least 3:
    10 board not found: a.png, b.png, c.png and 7 more; x.png: not a readable image
    (truncated)``.
    """
    skipped = list(skipped)
    total = int(n_usable) + len(skipped)
    head = f"none of the {total} {what} usable" if n_usable == 0 else f"only {n_usable} of {total} {what} usable"
    msg = f"{head}, need at least {minimum}"
    why = summarize_reasons(skipped)
    return f"{msg}: {why}" if why else msg


_SIGNATURES = ((b"\x89PNG\r\n\x1a\n", "png"), (b"\xff\xd8\xff", "jpeg"), (b"BM", "bmp"))


def _image_kind(head: bytes) -> str | None:
    """``png``, ``jpeg`` or ``bmp`` (whose completeness is checked), else None (the decoder judges)."""
    for sig, kind in _SIGNATURES:
        if head.startswith(sig):
            return kind
    return None


_OTHER_SIGNATURES = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+", b"RIFF", b"GIF8", b"\x00\x00\x00\x0cjP  ",
                     b"\xff\x4f\xff\x51", b"v/1\x01", b"#?", b"\x59\xa6\x6a\x95", b"PF", b"Pf")


def _looks_like_image(data: np.ndarray) -> bool:
    """A known image signature (TIFF, WebP, GIF, JPEG 2000, EXR, HDR, Sun raster, PNM/PFM, HEIF/AVIF)."""
    head = data[:16].tobytes()
    if head.startswith(_OTHER_SIGNATURES) or head[4:8] == b"ftyp":
        return True
    return len(head) >= 2 and head[:1] == b"P" and head[1:2].isdigit()


_JPEG_MARKER = re.compile(rb"\xff[^\x00\xd0-\xd7\xff]")


def _is_truncated(kind: str, data: np.ndarray) -> bool:
    """True when a PNG, JPEG or BMP file ends before its structure does."""
    if kind == "png":
        return not _png_complete(data.tobytes())
    if kind == "jpeg":
        return not _jpeg_complete(data.tobytes())
    if kind == "bmp" and data.size >= 6:
        declared = int.from_bytes(data[2:6].tobytes(), "little")
        return declared > data.size  # 0 (some writers) or a larger file: fine
    return False


def _png_complete(b: bytes) -> bool:
    pos, n = 8, len(b)
    while pos + 8 <= n:
        length = int.from_bytes(b[pos:pos + 4], "big")
        end = pos + 12 + length
        if end > n:
            return False
        if b[pos + 4:pos + 8] == b"IEND":
            return True
        pos = end
    return False


def _jpeg_complete(b: bytes) -> bool:
    """Walk the marker segments (APPn thumbnails are skipped whole) and the entropy-coded
    scans to the end-of-image marker; a file that ends first is truncated.  Bytes after
    the marker are allowed (some cameras append data)."""
    pos, n = 2, len(b)
    while pos < n:
        if b[pos] != 0xFF:  # not where a marker should be: let the decoder judge
            m = _JPEG_MARKER.search(b, pos)
            if m is None:
                return False
            pos = m.start()
        while pos + 1 < n and b[pos + 1] == 0xFF:  # fill bytes
            pos += 1
        if pos + 1 >= n:
            return False
        marker = b[pos + 1]
        if marker == 0xD9:
            return True
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:
            pos += 2
            continue
        if pos + 4 > n:
            return False
        end = pos + 2 + int.from_bytes(b[pos + 2:pos + 4], "big")
        if end > n:
            return False
        pos = end
        if marker == 0xDA:  # start of scan: entropy-coded data up to the next marker
            m = _JPEG_MARKER.search(b, pos)
            if m is None:
                return False
            pos = m.start()
    return False


# on in worker processes started (spawned) by a command line that called quiet_opencv
_QUIET = {"on": os.environ.get("LIGHTPLANE_QUIET_DECODERS") == "1", "depth": 0, "saved": None}
_QUIET_LOCK = threading.Lock()


class _quiet_decoder:
    """While an image decodes, send file descriptor 2 to /dev/null when :func:`quiet_opencv`
    asked for it (libpng and libjpeg print their complaints there themselves).  Counted,
    so that threads decoding at once restore stderr only when the last one is done."""

    def __enter__(self):
        if not _QUIET["on"]:
            self.active = False
            return self
        self.active = True
        with _QUIET_LOCK:
            if _QUIET["depth"] == 0:
                try:
                    sys.stderr.flush()
                    saved = os.dup(2)
                    devnull = os.open(os.devnull, os.O_WRONLY)
                    os.dup2(devnull, 2)
                    os.close(devnull)
                    _QUIET["saved"] = saved
                except (OSError, ValueError):  # pragma: no cover - no fd 2
                    _QUIET["saved"] = None
            _QUIET["depth"] += 1
        return self

    def __exit__(self, *exc):
        if not self.active:
            return
        with _QUIET_LOCK:
            _QUIET["depth"] -= 1
            if _QUIET["depth"] == 0 and _QUIET["saved"] is not None:
                os.dup2(_QUIET["saved"], 2)
                os.close(_QUIET["saved"])
                _QUIET["saved"] = None


def quiet_opencv(decoders: bool = True) -> None:
    """Keep OpenCV's own log lines ("[ WARN:0@...] ...", "[ERROR:0@...] ...") off stderr, and
    with ``decoders`` also what libpng / libjpeg / libtiff print there while an image is read.

    Called once by the command line at start, so that a bad image gives only our one line
    (the reason is in the summary and the result file).  Library users keep OpenCV's
    defaults unless they call it.  Worker processes started afterwards inherit it through
    the environment (``OPENCV_LOG_LEVEL``, ``LIGHTPLANE_QUIET_DECODERS``).
    """
    os.environ["OPENCV_LOG_LEVEL"] = "SILENT"
    if decoders:
        os.environ["LIGHTPLANE_QUIET_DECODERS"] = "1"
    import cv2

    try:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    except AttributeError:  # pragma: no cover - older builds
        set_level = getattr(cv2, "setLogLevel", None)
        if set_level is not None:
            set_level(0)
    _QUIET["on"] = bool(decoders)


def rotation_code(rotate_deg: int):
    import cv2

    codes = {0: None, 90: cv2.ROTATE_90_CLOCKWISE, 180: cv2.ROTATE_180, 270: cv2.ROTATE_90_COUNTERCLOCKWISE}
    if rotate_deg not in codes:
        raise LightplaneError(f"rotate_deg must be 0, 90, 180 or 270, got {rotate_deg}")
    return codes[rotate_deg]


def rotate_image(img: np.ndarray, rotate_deg: int) -> np.ndarray:
    """Rotate clockwise by 0, 90, 180 or 270 degrees."""
    import cv2

    code = rotation_code(rotate_deg)
    return img if code is None else cv2.rotate(img, code)


CHANNELS = ("gray", "red", "green", "blue", "sum")


def to_gray_float(image: np.ndarray, channel: str | None = None, *, name: str = "image",
                  native: bool = False) -> np.ndarray:
    """The project's one conversion of an image to one gray channel, (H, W).

    ``image``: (H, W), (H, W, 1), (H, W, 3) BGR or (H, W, 4) BGRA; any integer, bool or
    float dtype.  ``channel``: None / ``"gray"`` (OpenCV's weighted gray, 0.114 B +
    0.587 G + 0.299 R), ``"red"``, ``"green"``, ``"blue"``, or ``"sum"`` (B + G + R
    unweighted); a colour channel asked of a gray image is an error.

    Returns float32, or with ``native`` the image's own type where the kernels take it
    (uint8 and uint16 stay integers, ``"sum"`` of 8-bit gives uint16; other types become
    float32).  One rule for bad pixels: NaN or infinite values are an error
    (:class:`~lightplane.core.errors.LightplaneError`, naming ``name``), as are arrays that are
    not images.
    """
    import cv2

    img = np.asarray(image)
    if img.dtype == np.bool_:
        img = img.astype(np.uint8) * 255
    if img.dtype.kind not in "uif":
        raise LightplaneError(f"{name} must be an integer or float image, got dtype {img.dtype}")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if channel is not None and channel not in CHANNELS:
        raise LightplaneError(f"channel must be red, green, blue, sum or gray, got {channel!r}")
    if img.dtype.kind == "f" and not np.all(np.isfinite(img)):
        raise LightplaneError(f"{name} contains NaN or infinite values")
    cv_types = (np.uint8, np.uint16, np.float32)
    if img.ndim == 2:
        if channel not in (None, "gray"):
            raise LightplaneError(f"channel={channel!r} given but {name} is single-channel")
        out = img
    elif img.ndim == 3 and img.shape[2] in (3, 4):
        bgr = np.ascontiguousarray(img[:, :, :3])
        if channel in ("red", "green", "blue"):
            idx = {"blue": 0, "green": 1, "red": 2}[channel]
            out = cv2.extractChannel(bgr, idx) if img.dtype in cv_types else bgr[:, :, idx].copy()
        elif channel == "sum":
            acc = np.uint16 if img.dtype == np.uint8 else np.float32
            out = bgr[:, :, 0].astype(acc) + bgr[:, :, 1].astype(acc) + bgr[:, :, 2].astype(acc)
        elif img.dtype in cv_types:
            out = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
        else:
            f = bgr.astype(np.float32)
            out = 0.114 * f[:, :, 0] + 0.587 * f[:, :, 1] + 0.299 * f[:, :, 2]
    else:
        raise LightplaneError(f"{name} must be (H, W) or (H, W, 3), got shape {img.shape}")
    if native and out.dtype in (np.uint8, np.uint16):
        return out
    return out.astype(np.float32, copy=False)


def to_gray8(image: np.ndarray, *, percentiles: tuple[float, float] = (0.5, 99.5), keep_8bit: bool = True,
             name: str = "image") -> np.ndarray:
    """8-bit gray image for OpenCV's detectors and for pictures: the project's one stretch.

    Gray as :func:`to_gray_float`.  With ``keep_8bit`` (default) 8-bit data stays as it
    is, and so does data already on the 8-bit scale (values within [0, 255] reaching
    above 1, e.g. a float copy of an 8-bit image; fractions are cut); other data (16-bit
    or float data beyond that range, or within [0, 1]) is stretched
    linearly from its ``percentiles`` (of a subsample of ~64k pixels) to 0..255.
    ``keep_8bit=False`` always stretches (contrast for a picture).
    """
    img = np.asarray(image)
    g = to_gray_float(img, name=name, native=True)
    if keep_8bit:
        if g.dtype == np.uint8:
            return g
        lo, hi = float(g.min()), float(g.max())
        if lo >= 0 and hi <= 255 and hi > 1.0:
            return g.astype(np.uint8)
    g = g.astype(np.float32, copy=False)
    step = max(1, int(np.sqrt(g.size / 65536.0)))
    p0, p1 = (float(v) for v in np.percentile(g[::step, ::step], percentiles))
    if p1 <= p0:
        p0, p1 = float(g.min()), float(g.max())
    if p1 <= p0:
        return np.zeros(g.shape, np.uint8)
    return np.clip((g - p0) * (255.0 / (p1 - p0)), 0, 255).astype(np.uint8)


def check_output(path: str | os.PathLike, force: bool) -> Path:
    """Refuse to overwrite an existing file without ``force``, and an existing folder always (a file
    cannot replace it); check the folder it goes into exists and is writable."""
    p = Path(path)
    if p.is_dir():
        raise LightplaneError(f"{p}: is a folder, not a file; give a file name")
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
    if p.is_dir():
        raise LightplaneError(f"{p}: is a folder, not a {what}")
    if not p.is_file():
        raise LightplaneError(f"{p}: no such {what}")
    try:
        obj = json.loads(p.read_text())
    except OSError as e:
        raise LightplaneError(f"{p}: cannot read the {what} ({e.strerror or e})") from None
    except (ValueError, RecursionError) as e:  # bad JSON, undecodable bytes, an integer of thousands of digits
        raise LightplaneError(f"{p}: not valid JSON ({(str(e).strip().splitlines() or [type(e).__name__])[0]})") from None
    if not isinstance(obj, dict):
        raise LightplaneError(f"{p}: expected a JSON object at the top level")
    return obj


def versions() -> dict[str, str]:
    """Versions of lightplane and the libraries that shape its numbers."""
    import cv2
    import scipy

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
