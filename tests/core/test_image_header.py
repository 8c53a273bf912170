"""An image's size is read from its header and checked against the limit before anything is decoded."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest

from lightplane.core import io
from lightplane.core.errors import LightplaneError
from lightplane.core.io import DEFAULT_MAX_PIXELS, MAX_PIXELS_ENV, image_header_size, read_image, try_read_image

W, H = 53, 37  # odd, unequal: a swapped width and height shows


@pytest.mark.parametrize("name,dtype,channels", [
    ("a.png", np.uint8, 3), ("a16.png", np.uint16, 1), ("a.jpg", np.uint8, 3), ("g.jpg", np.uint8, 1),
    ("a.bmp", np.uint8, 3), ("a.tif", np.uint8, 3), ("a16.tif", np.uint16, 1), ("a.pgm", np.uint8, 1),
    ("a16.pgm", np.uint16, 1), ("a.ppm", np.uint8, 3), ("a.pbm", np.uint8, 1)])
def test_header_size_is_the_decoded_size(tmp_path, name, dtype, channels):
    rng = np.random.default_rng(1)
    img = rng.integers(0, np.iinfo(dtype).max, (H, W, channels) if channels > 1 else (H, W), dtype=dtype)
    f = tmp_path / name
    assert cv2.imwrite(str(f), img)
    assert image_header_size(f) == (W, H)
    assert read_image(f).shape[:2] == (H, W)


def test_header_size_of_other_layouts(tmp_path):
    f = tmp_path / "p.jpg"
    assert cv2.imwrite(str(f), np.zeros((H, W, 3), np.uint8), [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])
    assert image_header_size(f) == (W, H)
    # big-endian TIFF, width a SHORT and length a LONG
    entries = struct.pack(">HHII", 256, 3, 1, 300 << 16) + struct.pack(">HHII", 257, 4, 1, 200)
    (tmp_path / "m.tif").write_bytes(b"MM\x00*" + struct.pack(">I", 8) + struct.pack(">H", 2) + entries)
    assert image_header_size(tmp_path / "m.tif") == (300, 200)
    # PGM with a comment between the numbers; a top-down BMP (negative height)
    (tmp_path / "c.pgm").write_bytes(b"P5\n# made 99 99\n 640\n  480\n255\n" + bytes(10))
    assert image_header_size(tmp_path / "c.pgm") == (640, 480)
    bmp = bytearray(cv2.imencode(".bmp", np.zeros((H, W), np.uint8))[1].tobytes())
    bmp[22:26] = struct.pack("<i", -H)
    (tmp_path / "t.bmp").write_bytes(bytes(bmp))
    assert image_header_size(tmp_path / "t.bmp") == (W, H)
    (tmp_path / "x.gif").write_bytes(b"GIF89a" + bytes(20))
    assert image_header_size(tmp_path / "x.gif") is None  # not parsed here: the decoder judges


def _png_header(w: int, h: int) -> bytes:
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    chunk = struct.pack(">I", len(ihdr)) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    return b"\x89PNG\r\n\x1a\n" + chunk + struct.pack(">I", 4096) + b"IDAT\x78\x9c"  # data cut short


def _jpeg_header(w: int, h: int) -> bytes:
    app0 = b"\xff\xe0" + struct.pack(">H", 16) + b"JFIF\x00\x01\x01\x00\x00\x01\x00\x01\x00\x00"
    sof = b"\xff\xc0" + struct.pack(">HBHHB", 11, 8, h, w, 1) + b"\x01\x11\x00"
    return b"\xff\xd8" + app0 + sof + b"\xff\xda\x00\x08\x01\x01\x00\x00\x3f\x00" + bytes(16)


@pytest.mark.parametrize("kind,header", [("png", _png_header), ("jpg", _jpeg_header)])
def test_huge_header_refused_before_decoding(tmp_path, monkeypatch, kind, header):
    f = tmp_path / f"huge.{kind}"
    f.write_bytes(header(20000, 20000))
    assert f.stat().st_size < 100

    def no_decoding(*args, **kwargs):
        raise AssertionError("decoded")

    monkeypatch.setattr(cv2, "imdecode", no_decoding)
    monkeypatch.setattr(io.np, "fromfile", no_decoding)  # not even read whole
    monkeypatch.delenv(MAX_PIXELS_ENV, raising=False)
    img, why = try_read_image(f)
    assert img is None
    assert "20000x20000 px" in why and "400 megapixels" in why and f"limit of {DEFAULT_MAX_PIXELS // 10**6} megapixels" in why
    assert MAX_PIXELS_ENV in why
    with pytest.raises(LightplaneError, match=r"huge\.%s: too large: 20000x20000 px" % kind):
        read_image(f)
    # the environment raises the limit: the file is then read, and found truncated as before
    monkeypatch.undo()
    monkeypatch.setenv(MAX_PIXELS_ENV, "500000000")
    assert try_read_image(f) == (None, "not a readable image (truncated)")


def test_limit_from_the_environment(tmp_path, monkeypatch):
    f = tmp_path / "a.png"
    cv2.imwrite(str(f), np.zeros((H, W), np.uint8))
    monkeypatch.setenv(MAX_PIXELS_ENV, str(W * H - 1))
    img, why = try_read_image(f)
    assert img is None and f"{W}x{H} px" in why
    monkeypatch.setenv(MAX_PIXELS_ENV, str(W * H))
    assert try_read_image(f)[0].shape == (H, W)
    for bad in ("0", "-5", "many"):
        monkeypatch.setenv(MAX_PIXELS_ENV, bad)
        with pytest.raises(LightplaneError, match=MAX_PIXELS_ENV):
            try_read_image(f)


def test_the_command_lines_limit_and_video_headers(tmp_path, monkeypatch):
    """``lightplane --max-pixels N`` sets the limit for every command; a video's frame size is checked in its
    container's header before any frame is decoded."""
    from tests._cli import lightplane, one_error_line

    for i in range(3):
        cv2.imwrite(str(tmp_path / f"v{i}.png"), np.zeros((H, W), np.uint8))
    r = lightplane("--max-pixels", W * H - 1, "calibrate-camera", *sorted(tmp_path.glob("v*.png")),
                   "--board", "9x6", "--square", "10", "-o", tmp_path / "cam.json")
    one_error_line(r, f"3 too large: {W}x{H} px", "--max-pixels")
    assert not (tmp_path / "cam.json").exists()
    VW, VH = 64, 48  # a size every MJPG writer keeps
    video = tmp_path / "v.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (VW, VH), False)
    if not w.isOpened():
        pytest.skip("this OpenCV build writes no MJPG video")
    for _ in range(3):
        w.write(np.zeros((VH, VW), np.uint8))
    w.release()
    from lightplane.measure.scan import VideoFrames

    monkeypatch.setenv(MAX_PIXELS_ENV, str(VW * VH - 1))
    with pytest.raises(LightplaneError, match=rf"frames of {VW}x{VH} px .* in its header, above the limit"):
        VideoFrames(video)
    monkeypatch.setenv(MAX_PIXELS_ENV, str(VW * VH))
    v = VideoFrames(video)
    assert sum(1 for _ in v.items()) == 3
    v.close()
