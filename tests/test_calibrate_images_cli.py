"""`lightplane calibrate-plane`: a run on rendered images, and every bad-input case (exit 2, one line, nothing written)."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from lightplane import Camera, LightPlane

from test_calibrate_images import cached_circle_render
from _cli import lightplane, one_error_line


def run(*args, cwd=None):
    return lightplane("calibrate-plane", *args, cwd=cwd)


@pytest.fixture(scope="module")
def render():
    return cached_circle_render()


_bad = one_error_line


def test_run_writes_plane_with_diagnostics_and_report(render, tmp_path):
    out, rep = tmp_path / "plane.json", tmp_path / "report"
    r = run(render, "--camera", render / "camera.json", "--diameter", "50", "-o", out, "--report", rep)
    assert r.returncode == 0, r.stderr
    truth = LightPlane.from_dict(json.loads((render / "truth.json").read_text())["plane"])
    plane = LightPlane.load(out)
    assert np.degrees(plane.angle_to(truth)) < 0.03
    d = json.loads(out.read_text())
    assert d["method"] == "ml" and len(d["covariance"]) == 4
    assert len(d["images"]) == 5 and all(im["status"] == "used" for im in d["images"])
    assert {"rim_residual_rms_px", "stripe_residual_rms_px", "n_stripe", "reason"} <= set(d["images"][0])
    assert len(d["provenance"]["inputs"]) == 6 and d["provenance"]["options"]["diameter_mm"] == 50.0
    assert d["uncertainty"]["d_sigma_mm"] > 0
    # summary with units: plane sigma in deg and mm, point sigma at the working distance
    assert "deg" in r.stdout and "σ offset" in r.stdout and "working distance 450 mm" in r.stdout
    html = (rep / "index.html").read_text()
    assert "circle_004.png" in html and "data:image/png;base64," in html
    # an existing plane file is never overwritten without --force
    before = out.read_bytes()
    r = run(render, "--camera", render / "camera.json", "--diameter", "50", "-o", out, "--method", "global")
    _bad(r, "already exists", "--force")
    assert out.read_bytes() == before
    r = run(render, "--camera", render / "camera.json", "--diameter", "50", "-o", out, "--method", "global",
            "--force")
    assert r.returncode == 0 and json.loads(out.read_text())["method"] == "global"


def test_folder_without_images(tmp_path, render):
    (tmp_path / "empty").mkdir()
    r = run(tmp_path / "empty", "--camera", render / "camera.json", "--diameter", "50", "-o", tmp_path / "p.json")
    _bad(r, "no images")
    assert not (tmp_path / "p.json").exists()


def test_wrong_image_size(tmp_path, render):
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    for k in range(3):
        cv2.imwrite(str(imgs / f"small_{k}.png"), np.zeros((480, 640), np.uint8))
    r = run(imgs, "--camera", render / "camera.json", "--diameter", "50", "-o", tmp_path / "p.json")
    _bad(r, "small_0.png", "640x480", "1280x960")
    assert not (tmp_path / "p.json").exists()


def test_not_an_image_and_bad_camera_file(tmp_path, render):
    imgs = tmp_path / "imgs"
    shutil.copytree(render, imgs)
    (imgs / "notes.png").write_text("this is not an image")
    # skipped with its reason, not fatal: five good images remain (tests/test_bad_images.py)
    r = run(imgs, "--camera", render / "camera.json", "--diameter", "50", "-o", tmp_path / "q.json",
            "--method", "global")
    assert r.returncode == 0 and "notes.png not used: not a readable image (not an image file)" in r.stdout, r.stderr
    bad_cam = tmp_path / "cam.json"
    bad_cam.write_text("{\"K\": 3}")
    r = run(render, "--camera", bad_cam, "--diameter", "50", "-o", tmp_path / "p.json")
    _bad(r, "cam.json")
    r = run(render, "--camera", render / "camera.json", "--diameter", "0", "-o", tmp_path / "p.json")
    _bad(r, "--diameter")
    assert not (tmp_path / "p.json").exists()


def test_too_few_usable_images(tmp_path, render):
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    for name in ("circle_000.png", "circle_001.png"):
        shutil.copy(render / name, imgs / name)
    cv2.imwrite(str(imgs / "blank.png"), np.full((960, 1280), 40, np.uint8))
    rep = tmp_path / "rep"
    r = run(imgs, "--camera", render / "camera.json", "--diameter", "50", "-o", tmp_path / "p.json", "--report", rep)
    _bad(r, "only 2 of 3 images", "blank.png: no target ellipse found")
    assert not (tmp_path / "p.json").exists() and not rep.exists()
    assert Camera.load(render / "camera.json").width == 1280


@pytest.mark.parametrize("suffix", [".yaml", ".xml"])
def test_ros_and_opencv_camera_files(tmp_path, render, suffix):
    """CAM may be a ROS camera_info YAML or an OpenCV FileStorage XML: same plane as with our JSON."""
    cam = Camera.load(render / "camera.json")
    other = cam.save(tmp_path / f"camera{suffix}")
    out = tmp_path / "p.json"
    r = run(render, "--camera", other, "--diameter", "50", "-o", out, "--method", "global")
    assert r.returncode == 0, r.stderr
    truth = LightPlane.from_dict(json.loads((render / "truth.json").read_text())["plane"])
    assert np.degrees(LightPlane.load(out).angle_to(truth)) < 0.1
