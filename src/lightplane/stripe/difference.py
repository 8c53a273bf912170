"""The laser-on minus laser-off image, from the colour channels that can carry the stripe.

A colour laser on a bright surface can clip its own channel in the laser-off frame already (a red line on
white paper: the paper is at the red channel's full scale with or without the laser).  There the laser's own
channel holds no difference at all, and the stripe survives only in the other channels (their share of the
laser's light: the narrow core that the sensor's colour filters let through).  The difference image is
therefore taken from the requested channels *that are not clipped in the laser-off frame* over the region
where the stripe is looked for; when that leaves none, from the channels that are not clipped.  A channel
counts as clipped when at least :data:`CLIPPED_SHARE` of the region's pixels lie within
:data:`CLIPPED_LEVEL` of its full scale in the laser-off frame.  The channels kept are summed unweighted:
the stripe's height then does not depend on how a grey conversion weighs them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lightplane.core.errors import LightplaneError
from lightplane.core.io import to_gray_float

#: a channel is clipped in a laser-off frame when this share of the region's pixels is near its full scale ...
CLIPPED_SHARE = 0.10
#: ... that is, at or above this fraction of the full scale (JPEG compression moves clipped pixels a few levels)
CLIPPED_LEVEL = 0.98
#: channel index of each name in a BGR image
_INDEX = {"blue": 0, "green": 1, "red": 2}
#: the channels a request reads (None / "gray": every channel, weighted by the grey conversion)
_REQUEST = {None: ("blue", "green", "red"), "gray": ("blue", "green", "red"), "sum": ("blue", "green", "red"),
            "red": ("red",), "green": ("green",), "blue": ("blue",)}


@dataclass(frozen=True)
class LaserDifference:
    """The difference image (float32, >= 0) and what it was taken from.

    ``channels``: the channels summed (empty for a grey image); ``clipped``: channel -> share of the region's
    pixels clipped in the laser-off frame, for each channel left out for that reason; ``note``: one sentence
    for the user when channels were left out ("" otherwise)."""

    image: np.ndarray
    channels: tuple[str, ...]
    clipped: dict
    note: str


def _full_scale(image: np.ndarray) -> float:
    if image.dtype == np.uint8:
        return 255.0
    if image.dtype == np.uint16:
        top = int(image.max()) if image.size else 0
        return next(float(2**b - 1) for b in (10, 12, 14, 16) if top <= 2**b - 1)
    return 1.0 if image.size == 0 or float(np.max(image)) <= 1.0 else 255.0


def difference_channels(image: np.ndarray, background: np.ndarray, channel: str | None = None,
                        region: np.ndarray | None = None) -> tuple[tuple[str, ...], dict, str]:
    """Which channels :func:`laser_difference` reads: ``(channels, left_out, note)``.  ``left_out``
    (channel -> share of the region clipped in the laser-off frame) is empty when the request is
    read as it is (a grey pair; nothing it reads is clipped; every channel clipped, with a note);
    otherwise ``channels`` are the ones summed.  Checks the pair's shapes, the request and the
    region (one line each)."""
    img, bg = np.asarray(image), np.asarray(background)
    if img.shape != bg.shape:
        raise LightplaneError(f"background image shape {bg.shape} differs from image shape {img.shape}")
    if img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 1):
        return (), {}, ""
    if channel not in _REQUEST:
        raise LightplaneError(f"channel must be red, green, blue, sum or gray, got {channel!r}")
    fs = max(_full_scale(img), _full_scale(bg))
    inside = np.ones(img.shape[:2], bool) if region is None else np.asarray(region) > 0
    if inside.shape != img.shape[:2]:
        raise LightplaneError(f"region mask shape {inside.shape} differs from the image's {img.shape[:2]}")
    n = max(int(np.count_nonzero(inside)), 1)
    share = {c: float(np.count_nonzero(bg[:, :, i][inside] >= CLIPPED_LEVEL * fs)) / n for c, i in _INDEX.items()}
    clipped = {c for c, s in share.items() if s >= CLIPPED_SHARE}
    wanted = _REQUEST[channel]
    keep = tuple(c for c in wanted if c not in clipped)
    if not (clipped & set(wanted)):  # nothing clipped that the request reads: the request as it is
        return wanted, {}, ""
    if not keep:
        keep = tuple(c for c in ("blue", "green", "red") if c not in clipped)
    if not keep:  # every channel clipped: nothing better to offer than the request
        return wanted, {}, "every colour channel is clipped in the laser-off frame; the stripe may be lost"
    left_out = {c: round(share[c], 3) for c in wanted if c in clipped}
    note = (f"stripe taken from {'+'.join(keep)}: {', '.join(sorted(left_out))} clipped in the laser-off frame "
            f"over {100 * max(left_out.values()):.0f} % of the stripe's region")
    return keep, left_out, note


def laser_difference(image: np.ndarray, background: np.ndarray, channel: str | None = None,
                     region: np.ndarray | None = None) -> LaserDifference:
    """``max(image - background, 0)`` in the channels that carry the stripe (module doc;
    :func:`difference_channels`).

    ``channel``: the user's choice (None / ``"gray"``, ``"red"``, ``"green"``, ``"blue"``, ``"sum"``);
    ``region``: where the stripe is looked for (a mask of the image's size; default the whole image), over
    which clipping is judged.  A grey image pair gives the plain difference.  With no channel clipped the
    result is what :func:`lightplane.core.io.to_gray_float` gives for ``channel``, difference taken."""
    img, bg = np.asarray(image), np.asarray(background)
    channels, left_out, note = difference_channels(img, bg, channel, region)
    if not left_out:
        diff = to_gray_float(img, channel) - to_gray_float(bg, channel)
        return LaserDifference(np.clip(diff, 0, None), channels, {}, note)
    diff = np.zeros(img.shape[:2], np.float32)
    for c in channels:
        i = _INDEX[c]
        diff += img[:, :, i].astype(np.float32) - bg[:, :, i].astype(np.float32)
    return LaserDifference(np.clip(diff, 0, None), channels, left_out, note)


def laser_off_level(background: np.ndarray, diff: LaserDifference, channel: str | None = None) -> np.ndarray:
    """The laser-off frame in the channels that ``diff`` (:func:`laser_difference`) was taken from, float32:
    the scene's reflectance times its ambient light, on the difference image's scale."""
    bg = np.asarray(background)
    if diff.clipped and bg.ndim == 3:
        out = np.zeros(bg.shape[:2], np.float32)
        for c in diff.channels:
            out += bg[:, :, _INDEX[c]].astype(np.float32)
        return out
    return np.asarray(to_gray_float(bg, channel), dtype=np.float32)


def difference_full_scale(image: np.ndarray, diff: LaserDifference, channel: str | None = None) -> float:
    """The full scale of :func:`laser_difference`'s image: the input's, times the channels summed."""
    fs = _full_scale(np.asarray(image))
    if np.asarray(image).ndim == 3 and (diff.clipped or channel == "sum"):
        fs *= max(1, len(diff.channels))
    return fs
