"""`lightplane calibrate-camera`: real photographs (Ciclop) and every bad-input case."""

from __future__ import annotations

import json

import cv2
import numpy as np

from lightplane import Camera
from _cli import lightplane


run = lightplane


def synthetic_board(path, cols=9, rows=6, sq=30):
    """A fronto-parallel chessboard image with (cols x rows) inner corners."""
    h, w = (rows + 3) * sq, (cols + 3) * sq
    img = np.full((h, w), 255, np.uint8)
    for r in range(rows + 1):
        for c in range(cols + 1):
            if (r + c) % 2 == 0:
                y0, x0 = sq + r * sq, sq + c * sq
                img[y0 - sq // 2 + sq // 2: y0 + sq // 2 + sq // 2, x0: x0 + sq] = 0
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    cv2.imwrite(str(path), img)


def test_ciclop_reproduces_published_intrinsics(shared_data, tmp_path):
    folder = shared_data / "ciclop" / "camera_calibration_captures"
    out = tmp_path / "camera.json"
    plot = tmp_path / "res.png"
    r = run("calibrate-camera", folder, "--board", "11x6", "--square", "13", "--rotate", "90", "-o", out,
            "--plot", plot)
    assert r.returncode == 0, r.stderr
    cam = Camera.load(out)
    published = dict(fx=1430.39147, fy=1429.66307, cx=636.403930, cy=478.032706)
    for k, v in published.items():
        assert abs(getattr(cam, k) - v) <= 0.5, (k, getattr(cam, k), v)
    assert (cam.width, cam.height) == (1280, 960)
    d = json.loads(out.read_text())
    prov = d["provenance"]
    assert len(prov["inputs"]) == 16 and prov["options"]["board"] == "chessboard:11x6" and "opencv" in prov["versions"]
    assert prov["options"]["target"] == {"kind": "chessboard", "cols": 11, "rows": 6, "square_mm": 13.0}
    assert set(d["calibration"]["std"]) >= {"fx", "fy", "cx", "cy", "k1"}
    # the printed summary has units, the RMS and the ranked per-view errors
    assert "RMS reprojection error" in r.stdout and " px" in r.stdout and "worst first" in r.stdout
    assert plot.stat().st_size > 1000


def test_no_images(tmp_path):
    r = run("calibrate-camera", str(tmp_path / "*.png"), "--board", "9x6", "--square", "10", "-o", tmp_path / "c.json")
    assert r.returncode == 2 and "no images" in r.stderr
    assert not (tmp_path / "c.json").exists()


def test_unreadable_and_non_image_files(tmp_path):
    bad = tmp_path / "notes.png"
    bad.write_text("this is not an image")
    r = run("calibrate-camera", bad, "--board", "9x6", "--square", "10", "-o", tmp_path / "c.json")
    assert r.returncode == 2 and "notes.png" in r.stderr and "not a readable image" in r.stderr
    r = run("calibrate-camera", tmp_path / "missing.png", "--board", "9x6", "--square", "10", "-o", tmp_path / "c.json")
    assert r.returncode == 2 and "missing.png" in r.stderr
    assert not (tmp_path / "c.json").exists()
    assert len(r.stderr.strip().splitlines()) == 1


def test_no_board_anywhere(tmp_path):
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"blank{i}.png"), np.full((120, 160), 90 + i, np.uint8))
    r = run("calibrate-camera", tmp_path, "--board", "9x6", "--square", "10", "-o", tmp_path / "c.json")
    assert r.returncode == 2 and "none of the 3 images usable" in r.stderr and "3 chessboard:9x6 board not found" in r.stderr
    assert "not found" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "c.json").exists()


def test_fewer_than_three_views(tmp_path):
    for i in range(2):
        synthetic_board(tmp_path / f"board{i}.png")
    cv2.imwrite(str(tmp_path / "blank.png"), np.full((270, 360), 128, np.uint8))
    r = run("calibrate-camera", tmp_path, "--board", "9x6", "--square", "10", "-o", tmp_path / "c.json")
    assert r.returncode == 2 and "only 2" in r.stderr and "at least 3" in r.stderr
    assert not (tmp_path / "c.json").exists()


def test_existing_output_needs_force(tmp_path):
    out = tmp_path / "c.json"
    out.write_text("precious")
    synthetic_board(tmp_path / "b.png")
    r = run("calibrate-camera", tmp_path / "b.png", "--board", "9x6", "--square", "10", "-o", out)
    assert r.returncode == 2 and "already exists" in r.stderr and "--force" in r.stderr
    assert out.read_text() == "precious"


def test_bad_board_argument(tmp_path):
    synthetic_board(tmp_path / "b.png")
    r = run("calibrate-camera", tmp_path / "b.png", "--board", "nine", "--square", "10", "-o", tmp_path / "c.json")
    assert r.returncode == 2 and "COLSxROWS" in r.stderr


def test_fix_k3_keeps_k3_zero(shared_data, tmp_path):
    folder = shared_data / "ciclop" / "camera_calibration_captures"
    out = tmp_path / "camera.json"
    r = run("calibrate-camera", folder, "--board", "11x6", "--square", "13", "--rotate", "90", "-o", out, "--fix-k3")
    assert r.returncode == 0, r.stderr
    cam = Camera.load(out)
    assert cam.dist[4] == 0.0 and cam.dist[0] != 0.0
    assert json.loads(out.read_text())["provenance"]["options"]["fix_k3"] is True
