"""Bad image files among good ones: each is skipped with its reason, shown and stored; a command
fails (exit 2, one stderr line with counts and reasons, nothing written) only when fewer than its
minimum remain; OpenCV's and the decoders' own lines never reach stderr."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _measure_synth import write_scan  # noqa: E402
from _renders import cached_circle_render  # noqa: E402

from lightplane.core.errors import LightplaneError  # noqa: E402
from lightplane.core.io import read_image, read_images, summarize_reasons, too_few_images_message, try_read_image  # noqa: E402
from _cli import lightplane, one_error_line  # noqa: E402

NATIVE_NOISE = re.compile(r"libpng|libjpeg|libtiff|TIFF|\[ ?WARN|\[ ?ERROR|Premature end|Corrupt JPEG|OpenCV")


def truncate(src: Path, dst: Path, keep: float = 0.5) -> Path:
    b = src.read_bytes()
    dst.write_bytes(b[:int(len(b) * keep)])
    return dst


def corrupt_png(src: Path, dst: Path) -> Path:
    """Complete chunk structure (IEND present) but damaged compressed data: libpng's CRC check fails."""
    b = bytearray(src.read_bytes())
    i = b.index(b"IDAT") + 40
    b[i:i + 64] = bytes(64)
    dst.write_bytes(bytes(b))
    return dst


def tiny(ext: str, *params: int) -> bytes:
    img = np.zeros((60, 80, 3), np.uint8)
    cv2.circle(img, (40, 30), 20, (200, 120, 40), -1)
    img = (img + np.random.default_rng(0).integers(0, 30, img.shape)).astype(np.uint8)
    ok, buf = cv2.imencode(ext, img, list(params))
    assert ok
    return buf.tobytes()


# ----------------------------------------------------------------------------- read_images
def test_read_images_skips_every_kind_of_bad_file_with_a_reason(tmp_path):
    png, jpg = tiny(".png"), tiny(".jpg")
    prog = tiny(".jpg", cv2.IMWRITE_JPEG_PROGRESSIVE, 1)
    files = {
        "good.png": png,
        "good.jpg": jpg,
        "trailing.jpg": jpg + b"camera maker data\x00\x00",  # bytes after the end-of-image marker: fine
        "half.png": png[:len(png) // 2],
        "no_iend.png": png[:-12],  # every pixel there, only the IEND chunk missing
        "half.jpg": jpg[:len(jpg) // 2],
        "no_eoi.jpg": jpg[:-2],
        "prog_cut.jpg": prog[:int(len(prog) * 0.9)],
        "empty.png": b"",
        "notes.png": b"this is not an image\n",
    }
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    (tmp_path / "folder.png").mkdir()
    paths = [tmp_path / n for n in files] + [tmp_path / "folder.png", tmp_path / "missing.png"]
    ok, skipped = read_images(paths)
    assert [p.name for p, _ in ok] == ["good.png", "good.jpg", "trailing.jpg"]
    assert all(img.shape == (60, 80, 3) and img.dtype == np.uint8 for _, img in ok)
    reasons = {p.name: r for p, r in skipped}
    assert reasons == {
        "half.png": "not a readable image (truncated)",
        "no_iend.png": "not a readable image (truncated)",
        "half.jpg": "not a readable image (truncated)",
        "no_eoi.jpg": "not a readable image (truncated)",
        "prog_cut.jpg": "not a readable image (truncated)",
        "empty.png": "not a readable image (empty file)",
        "notes.png": "not a readable image (not an image file)",
        "folder.png": "is a folder, not an image",
        "missing.png": "no such file",
    }
    assert [p.name for p, _ in skipped] == [p.name for p in paths if p.name in reasons]  # input order
    # rotation applies to what was read; a bad rotation is the caller's error, not a file's
    ok90, _ = read_images([tmp_path / "good.png"], rotate_deg=90)
    assert ok90[0][1].shape == (80, 60, 3)
    with pytest.raises(LightplaneError, match="rotate_deg"):
        read_images([tmp_path / "good.png"], rotate_deg=45)
    # read_image raises with the file and the same reason
    with pytest.raises(LightplaneError, match=r"half\.png: not a readable image \(truncated\)"):
        read_image(tmp_path / "half.png")
    assert try_read_image(tmp_path / "empty.png") == (None, "not a readable image (empty file)")


def test_truncated_bmp_and_corrupt_png(tmp_path):
    bmp = tiny(".bmp")
    (tmp_path / "cut.bmp").write_bytes(bmp[:-100])
    assert try_read_image(tmp_path / "cut.bmp")[1] == "not a readable image (truncated)"
    (tmp_path / "good.png").write_bytes(tiny(".png"))
    corrupt_png(tmp_path / "good.png", tmp_path / "bad.png")
    img, reason = try_read_image(tmp_path / "bad.png")
    assert img is None and reason == "not a readable image (corrupt)"


def test_too_few_images_message_counts_and_groups_reasons():
    skipped = [(f"/data/img_{k:02d}.png", "board not found") for k in range(10)]
    skipped.append(("/data/img_10.png", "not a readable image (truncated)"))
    msg = too_few_images_message("images", 1, 3, skipped)
    assert msg == ("only 1 of 12 images usable, need at least 3: 10 board not found: img_00.png, img_01.png, "
                   "img_02.png and 7 more; img_10.png: not a readable image (truncated)")
    assert "\n" not in msg
    # per-image numbers do not split a group; a single one keeps its detail
    assert summarize_reasons([("a", "too few stripe points (4)"), ("b", "too few stripe points (7)"),
                              ("c", "too few corners (11)")]) == \
        "2 too few stripe points: a, b; c: too few corners (11)"
    assert too_few_images_message("frames", 0, 1, [("f.png", "no such file")]) == \
        "none of the 1 frames usable, need at least 1: f.png: no such file"


def test_quiet_opencv_keeps_decoder_complaints_off_stderr(tmp_path):
    """Corrupt PNG (libpng prints its error itself) and truncated TIFF (OpenCV logs libtiff's errors)."""
    (tmp_path / "good.png").write_bytes(tiny(".png"))
    corrupt_png(tmp_path / "good.png", tmp_path / "bad.png")
    tif = tiny(".tif")
    (tmp_path / "cut.tif").write_bytes(tif[:len(tif) // 2])
    code = ("import sys; from lightplane.core.io import quiet_opencv, read_images; quiet_opencv(); "
            "ok, sk = read_images(sys.argv[1:]); print(len(ok), [r for _, r in sk])")
    r = subprocess.run([sys.executable, "-c", code, tmp_path / "good.png", tmp_path / "bad.png", tmp_path / "cut.tif"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stderr == ""
    assert "1 ['not a readable image (corrupt)', 'not a readable image (corrupt or truncated)']" in r.stdout


# ----------------------------------------------------------------------------- calibrate-plane
@pytest.fixture(scope="module")
def render():
    return cached_circle_render()


def test_calibrate_plane_skips_bad_files_and_says_why(render, tmp_path):
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    for k in range(5):
        shutil.copy(render / f"circle_{k:03d}.png", imgs / f"circle_{k:03d}.png")
    truncate(render / "circle_000.png", imgs / "circle_000_cut.png")
    corrupt_png(render / "circle_001.png", imgs / "circle_001_bad.png")
    tif = cv2.imencode(".tif", cv2.imread(str(render / "circle_002.png"), cv2.IMREAD_UNCHANGED))[1].tobytes()
    (imgs / "circle_002_cut.tif").write_bytes(tif[:len(tif) // 3])
    out = tmp_path / "plane.json"
    r = lightplane("calibrate-plane", imgs, "--camera", render / "camera.json", "--diameter", "50", "-o", out,
                   "--method", "global")
    assert r.returncode == 0, (r.stdout, r.stderr)
    assert not NATIVE_NOISE.search(r.stderr), r.stderr
    assert r.stderr.strip() == ""
    # the summary table lists each with its status and reason
    row = next(ln for ln in r.stdout.splitlines() if "circle_000_cut.png" in ln)
    assert "skipped" in row and "not a" in row  # the reason column folds on a narrow terminal
    assert "circle_000_cut.png not used: not a readable image (truncated)" in r.stdout
    assert "circle_001_bad.png not used: not a readable image (corrupt)" in r.stdout
    assert "5 of 8 images used" in r.stdout
    d = json.loads(out.read_text())
    by_file = {Path(im["file"]).name: im for im in d["images"]}
    assert len(by_file) == 8
    assert by_file["circle_000_cut.png"]["status"] == "skipped"
    assert by_file["circle_000_cut.png"]["reason"] == "not a readable image (truncated)"
    assert by_file["circle_001_bad.png"]["reason"] == "not a readable image (corrupt)"
    assert by_file["circle_002_cut.tif"]["reason"] == "not a readable image (corrupt or truncated)"
    assert sum(im["status"] == "used" for im in d["images"]) == 5


def test_calibrate_plane_too_few_usable_images_exit_2_nothing_written(render, tmp_path):
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    for k in range(2):
        shutil.copy(render / f"circle_{k:03d}.png", imgs / f"circle_{k:03d}.png")
    truncate(render / "circle_002.png", imgs / "circle_002.png", keep=0.8)
    cv2.imwrite(str(imgs / "circle_003.png"), np.full((960, 1280), 40, np.uint8))
    out = tmp_path / "plane.json"
    r = lightplane("calibrate-plane", imgs, "--camera", render / "camera.json", "--diameter", "50", "-o", out)
    line = one_error_line(r)
    assert "only 2 of 4 images usable, need at least 3" in line
    assert "circle_002.png: not a readable image (truncated)" in line
    assert "circle_003.png: no target ellipse found" in line
    assert not out.exists()
    # an existing result is left as it was, even with --force
    out.write_text("{\"previous\": true}\n")
    r = lightplane("calibrate-plane", imgs, "--camera", render / "camera.json", "--diameter", "50", "-o", out,
                   "--force")
    assert "only 2 of 4 images usable" in one_error_line(r)
    assert out.read_text() == "{\"previous\": true}\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["imgs", "plane.json"]  # no temporary left


# ----------------------------------------------------------------------------- measure
@pytest.fixture(scope="module")
def scan_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("scan")
    write_scan(d, 4)
    return d


def test_measure_skips_a_truncated_frame_and_records_it(scan_dir, tmp_path):
    frames = [scan_dir / f"f{k:02d}.png" for k in range(4)]
    cut = truncate(frames[1], tmp_path / "f01_cut.png", keep=0.9)
    out = tmp_path / "cloud.ply"
    r = lightplane("measure", frames[0], cut, frames[2], frames[3], "--camera", scan_dir / "camera.json",
                   "--plane", scan_dir / "plane.json", "-o", out, "--ascii")
    assert r.returncode == 0, (r.stdout, r.stderr)
    assert not NATIVE_NOISE.search(r.stderr), r.stderr
    assert "3 of 4 frames used, 1 skipped: f01_cut.png: not a readable image (truncated)" in r.stdout
    assert "f01_cut.png" in r.stderr and "truncated" in r.stderr  # our warning lines
    header = out.read_bytes().split(b"end_header")[0].decode()
    assert "comment skipped frame 1 (f01_cut.png): not a readable image (truncated)" in header
    from lightplane.measure.pointcloud import read_cloud

    assert sorted(np.unique(read_cloud(out)["frame"]).tolist()) == [0, 2, 3]


def test_measure_nothing_usable_exit_2_with_reasons(scan_dir, tmp_path):
    a = truncate(scan_dir / "f00.png", tmp_path / "a.png")
    b = truncate(scan_dir / "f01.png", tmp_path / "b.png", keep=0.99)
    c = tmp_path / "c.png"
    c.write_bytes(b"")
    out = tmp_path / "cloud.ply"
    r = lightplane("measure", a, b, c, "--camera", scan_dir / "camera.json", "--plane", scan_dir / "plane.json",
                   "-o", out)
    line = one_error_line(r)
    assert "none of the 3 frames usable, need at least 1" in line
    assert "2 not a readable image (truncated): a.png, b.png" in line and "c.png: not a readable image (empty file)" in line
    assert not out.exists()
