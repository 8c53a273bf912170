"""Several lasers in the same calibration images: which stripe belongs to which laser.

Every plane-calibration command takes a repeatable ``--laser NAME=SELECTOR``; each laser
gets its own plane from the same images (the same target or board poses).  A selector is
one or more parts joined by ``+``:

- a colour, ``red``, ``green``, ``blue`` or ``gray``: the laser's stripe is read in that
  channel of colour images (two lasers of different colours in the same frame);
- a region ``x0,y0,x1,y1`` (pixels of the image as read, after ``--rotate``): only stripe
  centres with ``x0 <= u < x1`` and ``y0 <= v < y1`` are the laser's (two stripes apart in
  the image);
- ``frames:PATTERN``: only the images whose file name (or path, when the pattern holds a
  ``/``) matches the shell pattern are the laser's frames;
- ``cycle:K``: the K-th laser frame (counted from 1) of each pose, with ``--cycle`` (the
  K-th ``L`` of the cycle) or ``--pattern`` (the K-th of the laser frames shared out to
  each pattern frame); FabScan's ``--cycle P,L,L`` with ``laser0=cycle:1 laser1=cycle:2``.

Without ``--laser`` a command calibrates one plane exactly as before.
"""

from __future__ import annotations

import fnmatch
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from lightplane.core.errors import LightplaneError
from lightplane.core.io import to_gray_float

COLOURS = ("red", "green", "blue", "gray")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


@dataclass(frozen=True)
class LaserSelector:
    """One laser of a multi-laser calibration: its name and how its stripe is told apart.

    channel : colour channel (``red``/``green``/``blue``/``gray``) or None (the command's ``--channel``).
    region : ``(x0, y0, x1, y1)`` px, half-open, or None (the whole image).
    frames : shell pattern on the image file names, or None (every image).
    cycle : K (>= 1): the K-th laser frame of each pose, or None.
    """

    name: str
    channel: str | None = None
    region: tuple[float, float, float, float] | None = None
    frames: str | None = None
    cycle: int | None = None
    text: str = ""

    def to_dict(self) -> dict:
        return {"name": self.name, "selector": self.text, "channel": self.channel,
                "region_px": None if self.region is None else list(self.region), "frames": self.frames,
                "cycle": self.cycle}

    def describe(self) -> str:
        return f"{self.name}={self.text}" if self.text else self.name

    def with_channel(self, channel: str | None) -> "LaserSelector":
        """The command's ``--channel`` as this laser's colour when its selector names none."""
        if self.channel is not None or channel is None:
            return self
        return LaserSelector(self.name, channel, self.region, self.frames, self.cycle, self.text)

    # -- frames
    def takes_file(self, path) -> bool:
        """Whether the image file ``path`` is one of this laser's frames (``frames:`` part)."""
        if self.frames is None:
            return True
        p = Path(str(path))
        if "/" in self.frames:
            return fnmatch.fnmatch(p.as_posix(), self.frames) or fnmatch.fnmatch(str(path), self.frames)
        return fnmatch.fnmatch(p.name, self.frames)

    # -- region
    def region_mask(self, shape: tuple[int, int], offset: tuple[float, float] = (0.0, 0.0)) -> np.ndarray | None:
        """Boolean mask ``shape`` of the pixels in this laser's region (``offset``: the (u, v) of
        pixel (0, 0), for crops); None when the laser has no region."""
        if self.region is None:
            return None
        x0, y0, x1, y1 = self.region
        u = np.arange(shape[1]) + offset[0]
        v = np.arange(shape[0]) + offset[1]
        return ((v >= y0) & (v < y1))[:, None] & ((u >= x0) & (u < x1))[None, :]

    def in_region(self, uv: np.ndarray) -> np.ndarray:
        """Which of the points ``uv`` (N, 2) px lie in this laser's region (all without one)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if self.region is None:
            return np.ones(len(uv), bool)
        x0, y0, x1, y1 = self.region
        return (uv[:, 0] >= x0) & (uv[:, 0] < x1) & (uv[:, 1] >= y0) & (uv[:, 1] < y1)

    # -- image
    def check_image(self, img: np.ndarray, name: str) -> None:
        """A colour selector needs a colour image; a region must lie (partly) inside the image."""
        if self.channel in ("red", "green", "blue") and img.ndim != 3:
            raise LightplaneError(f"{name}: laser {self.name} is told apart by its colour ({self.channel}), "
                                  "but this image has no colour channels")
        if self.region is not None:
            x0, y0, x1, y1 = self.region
            h, w = img.shape[:2]
            if x0 >= w or y0 >= h or x1 <= 0 or y1 <= 0:
                raise LightplaneError(f"{name}: the region {_fmt_region(self.region)} of laser {self.name} lies "
                                      f"outside the {w}x{h} px image")

    def view(self, img: np.ndarray) -> np.ndarray:
        """The image as this laser's stripe is looked for in it: its channel (float32 gray),
        without bright lines outside its region (:meth:`outside_removed`)."""
        return self.outside_removed(to_gray_float(img, self.channel))

    def outside_removed(self, gray: np.ndarray, offset: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
        """``gray`` (float32) with the bright lines outside this laser's region taken out: there
        the image is replaced by its morphological opening (a disc of 25 px removes stripes up
        to ~20 px wide and keeps the target and the background) raised by the median of
        ``gray - opening`` outside (an opening sits below a noisy level by about the noise),
        so no other laser's stripe is seen and the region's border adds no step.
        ``offset``: the (u, v) of pixel (0, 0)."""
        import cv2

        m = self.region_mask(gray.shape[:2], offset)
        if m is None:
            return gray
        opened = cv2.morphologyEx(np.ascontiguousarray(gray, dtype=np.float32), cv2.MORPH_OPEN,
                                  cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (25, 25)))
        out = ~m
        if out.any():
            opened = opened + np.float32(np.median((gray - opened)[out]))
        return np.where(m, gray, opened).astype(np.float32)


def _fmt_region(r) -> str:
    return ",".join(f"{x:g}" for x in r)


def parse_laser(text: str) -> LaserSelector:
    """``NAME=SELECTOR`` (see the module) -> :class:`LaserSelector`; LightplaneError for a bad one."""
    s = str(text).strip()
    name, eq, sel = s.partition("=")
    name = name.strip()
    if not eq or not name or not sel.strip():
        raise LightplaneError(f"--laser must be NAME=SELECTOR (a colour red/green/blue/gray, a region x0,y0,x1,y1 "
                              f"in px, frames:PATTERN or cycle:K, joined by +), e.g. laser0=red; got {text!r}")
    if not _NAME.match(name):
        raise LightplaneError(f"--laser {text!r}: the name must be letters, digits, '_', '-' or '.' "
                              "(it names the laser's plane file)")
    channel = region = frames = cycle = None
    for part in sel.split("+"):
        p = part.strip()
        low = p.lower()
        if low.startswith("frames:"):
            if frames is not None:
                raise LightplaneError(f"--laser {text!r}: more than one frames: part")
            frames = p[len("frames:"):].strip()
            if not frames:
                raise LightplaneError(f"--laser {text!r}: frames: needs a file-name pattern, e.g. frames:*_l0.png")
        elif low.startswith("cycle:"):
            if cycle is not None:
                raise LightplaneError(f"--laser {text!r}: more than one cycle: part")
            try:
                cycle = int(p[len("cycle:"):])
            except ValueError:
                cycle = 0
            if cycle < 1:
                raise LightplaneError(f"--laser {text!r}: cycle:K needs an integer K >= 1 (the K-th laser frame "
                                      "of each pose)")
        elif "," in p:
            if region is not None:
                raise LightplaneError(f"--laser {text!r}: more than one region")
            try:
                vals = [float(t) for t in p.split(",")]
            except ValueError:
                vals = []
            if len(vals) != 4 or not all(np.isfinite(vals)):
                raise LightplaneError(f"--laser {text!r}: a region is x0,y0,x1,y1 (four numbers, px), got {p!r}")
            if not (vals[0] < vals[2] and vals[1] < vals[3]):
                raise LightplaneError(f"--laser {text!r}: the region {p} is empty (need x0 < x1 and y0 < y1)")
            region = (vals[0], vals[1], vals[2], vals[3])
        elif low in COLOURS:
            if channel is not None:
                raise LightplaneError(f"--laser {text!r}: more than one colour")
            channel = low
        else:
            raise LightplaneError(f"--laser {text!r}: unknown selector {p!r} (a colour red, green, blue or gray; "
                                  "a region x0,y0,x1,y1; frames:PATTERN; cycle:K)")
    return LaserSelector(name, channel, region, frames, cycle, sel.strip())


def _overlap(a, b) -> bool:
    return max(a[0], b[0]) < min(a[2], b[2]) and max(a[1], b[1]) < min(a[3], b[3])


def parse_lasers(texts: Sequence[str] | None, channel: str | None = None) -> list[LaserSelector] | None:
    """The ``--laser`` options of a command, checked together; None when none is given.

    ``channel``: the command's ``--channel``, the colour of lasers whose selector names none.
    Refused (LightplaneError): a repeated name; two lasers that would take the same stripe
    (same colour, same frames, no regions or overlapping ones).
    """
    if not texts:
        return None
    lasers = [parse_laser(t).with_channel(channel) for t in texts]
    seen: dict[str, str] = {}
    for s in lasers:
        if s.name in seen:
            raise LightplaneError(f"--laser: the name {s.name!r} is given twice")
        seen[s.name] = s.text
    for i, a in enumerate(lasers):
        for b in lasers[i + 1:]:
            if a.frames != b.frames or a.cycle != b.cycle:
                continue  # different frames: the lasers need not be told apart within an image
            ca, cb = a.channel or "gray", b.channel or "gray"
            if ca != cb and "gray" not in (ca, cb):
                continue  # different colour channels
            if a.region is not None and b.region is not None:
                if _overlap(a.region, b.region):
                    raise LightplaneError(f"--laser: the regions of {a.name} ({_fmt_region(a.region)}) and {b.name} "
                                          f"({_fmt_region(b.region)}) overlap")
                continue
            raise LightplaneError(f"--laser: {a.name} ({a.text}) and {b.name} ({b.text}) would take the same stripe "
                                  "(give them different colours, separate regions or their own frames)")
    return lasers


def output_paths(output: Path, names: Sequence[str]) -> dict[str, Path]:
    """Where each laser's plane file goes: ``output`` itself for one laser; for several,
    ``output`` with ``{laser}`` replaced by the name, or else ``STEM_NAME.SUFFIX`` beside it."""
    output = Path(output)
    if "{laser}" in str(output):
        return {n: Path(str(output).replace("{laser}", n)) for n in names}
    if len(names) == 1:
        return {names[0]: output}
    return {n: output.with_name(f"{output.stem}_{n}{output.suffix or '.json'}") for n in names}


def no_stripe_message(name: str, selector: LaserSelector, n_images: int, reasons: dict[str, str]) -> str:
    """The one line for a laser whose selector found its stripe in no image."""
    why = sorted(set(reasons.values()))
    return (f"laser {name} ({selector.text}): its stripe was found in none of its {n_images} images"
            + (f" ({'; '.join(why[:3])})" if why else ""))
