"""GenICam pixel formats (PFNC codes) turned into lightplane images, and the frame counter that turns a camera's
frame ids into a growing index with the dropped frames counted; shared by the Aravis and GenTL sources."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from lightplane.core.errors import LightplaneError

#: GenICam PFNC pixel format code -> (name, kind, bits): kind "mono", "bayer_XX" or "rgb"/"bgr"
PIXEL_FORMATS: dict[int, tuple[str, str, int]] = {
    0x01080001: ("Mono8", "mono", 8),
    0x01100003: ("Mono10", "mono", 16),
    0x01100005: ("Mono12", "mono", 16),
    0x01100025: ("Mono14", "mono", 16),
    0x01100007: ("Mono16", "mono", 16),
    0x01080008: ("BayerGR8", "bayer_GR", 8),
    0x01080009: ("BayerRG8", "bayer_RG", 8),
    0x0108000A: ("BayerGB8", "bayer_GB", 8),
    0x0108000B: ("BayerBG8", "bayer_BG", 8),
    0x0110000C: ("BayerGR10", "bayer_GR", 16),
    0x0110000D: ("BayerRG10", "bayer_RG", 16),
    0x0110000E: ("BayerGB10", "bayer_GB", 16),
    0x0110000F: ("BayerBG10", "bayer_BG", 16),
    0x01100010: ("BayerGR12", "bayer_GR", 16),
    0x01100011: ("BayerRG12", "bayer_RG", 16),
    0x01100012: ("BayerGB12", "bayer_GB", 16),
    0x01100013: ("BayerBG12", "bayer_BG", 16),
    0x0110002E: ("BayerGR16", "bayer_GR", 16),
    0x0110002F: ("BayerRG16", "bayer_RG", 16),
    0x01100030: ("BayerGB16", "bayer_GB", 16),
    0x01100031: ("BayerBG16", "bayer_BG", 16),
    0x02180014: ("RGB8", "rgb", 8),
    0x02180015: ("BGR8", "bgr", 8),
    0x02200016: ("RGBa8", "rgba", 8),
    0x02200017: ("BGRa8", "bgra", 8),
}
#: pixel format name -> PFNC code
PIXEL_FORMAT_CODES = {name: code for code, (name, _, _) in PIXEL_FORMATS.items()}
_PATTERNS = ("RG", "BG", "GR", "GB")
_bayer_codes: dict[str, int] = {}


_BOTTOM_ROW = {"RG": "GB", "BG": "GR", "GR": "BG", "GB": "RG"}


def _bayer_code(pattern: str) -> int:
    """The OpenCV conversion code that turns a mosaic whose top-left 2x2 cell starts with ``pattern`` (GenICam's
    naming: ``RG`` = red at (0, 0), green at (0, 1)) into BGR.  OpenCV's own names for the patterns changed between
    releases, so the code is found once by converting a probe mosaic of known colours with each candidate."""
    if not _bayer_codes:
        value = {"R": 200, "G": 100, "B": 50}
        for name in _PATTERNS:
            cell = np.array([[value[c] for c in name], [value[c] for c in _BOTTOM_ROW[name]]], np.uint8)
            probe = np.tile(cell, (3, 3))
            for cv_name in _PATTERNS:
                code = getattr(cv2, f"COLOR_Bayer{cv_name}2BGR")
                if tuple(int(v) for v in cv2.cvtColor(probe, code)[2, 2]) == (50, 100, 200):
                    _bayer_codes[name] = code
                    break
        if set(_bayer_codes) != set(_PATTERNS):
            raise LightplaneError("OpenCV's Bayer conversions could not be matched to the GenICam patterns")
    return _bayer_codes[pattern]


def convert_pixels(data: bytes, width: int, height: int, pixel_format: int) -> np.ndarray:
    """A camera buffer as an image: 2-D uint8/uint16 for mono formats, H x W x 3 BGR (uint8/uint16) for Bayer
    and RGB/BGR formats (the alpha channel of RGBa8/BGRa8 is dropped).  10/12/14-bit formats arrive unpacked in 16-bit words and stay uint16 with their own
    range.  Packed formats (Mono12p, ...) are refused: choose an unpacked one on the camera."""
    if pixel_format not in PIXEL_FORMATS:
        raise LightplaneError(f"pixel format 0x{pixel_format:08x} is not supported: set the camera to Mono8, Mono16, "
                              "an unpacked Bayer format, RGB8 or BGR8")
    name, kind, bits = PIXEL_FORMATS[pixel_format]
    dtype = np.dtype("u1") if bits == 8 else np.dtype("<u2")
    channels = {"rgb": 3, "bgr": 3, "rgba": 4, "bgra": 4}.get(kind, 1)
    need = width * height * channels * dtype.itemsize
    if len(data) < need:
        raise LightplaneError(f"a {name} buffer of {width}x{height} px needs {need} bytes, got {len(data)}")
    flat: np.ndarray = np.frombuffer(data, dtype=dtype, count=width * height * channels).astype(
        np.uint8 if bits == 8 else np.uint16)
    if channels > 1:
        img = flat.reshape(height, width, channels)
        return np.ascontiguousarray(img[:, :, 2::-1] if kind.startswith("rgb") else img[:, :, :3])
    raw = flat.reshape(height, width)
    if kind.startswith("bayer_"):
        return cv2.cvtColor(raw, _bayer_code(kind[len("bayer_"):]))
    return raw


@dataclass
class FrameCounter:
    """Turns the camera's frame ids into a counter that only grows and counts the ids that never arrived.

    ``wrap`` is the largest id before the counter starts again at 1 (GigE Vision's 16-bit block id: 65535, id 0
    is never used); ``None`` for 64-bit ids.  An id that goes backwards without a wrap (the camera restarted its
    counter; counted in ``restarts``) continues the count without a gap."""

    wrap: int | None = 65535
    index: int = -1
    last_id: int | None = None
    dropped: int = 0
    restarts: int = 0

    def advance(self, frame_id: int) -> int:
        """The counter for ``frame_id``; adds the ids skipped since the previous frame to ``dropped``."""
        frame_id = int(frame_id)
        if self.last_id is None:
            step = 1
        elif frame_id > self.last_id:
            step = frame_id - self.last_id
        elif self.wrap is not None and self.last_id <= self.wrap and frame_id >= 1 \
                and self.last_id - frame_id > self.wrap // 2:
            step = self.wrap - self.last_id + frame_id
        else:
            step = 1
            self.restarts += 1
        self.dropped += step - 1
        self.index += step
        self.last_id = frame_id
        return self.index
