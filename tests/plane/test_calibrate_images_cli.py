"""`lightplane calibrate-plane`: a run on rendered images, and every bad-input case (exit 2, one line, nothing written)."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from lightplane import Camera, LightPlane
from lightplane.camera.model import camera_record

from _renders import cached_circle_render
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
    assert d["camera"] == camera_record(Camera.load(render / "camera.json"))  # the camera it belongs to
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


def test_camera_share_in_every_output(render, tmp_path):
    """A camera file with a covariance: the plane file, the summary and the report carry the
    camera-frame and the shape sigma with the camera's share; without one they say it is missing."""
    cam = Camera.load(render / "camera.json")
    names = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    sd = np.array([0.5, 0.5, 0.3, 0.3, 1e-3, 1e-2, 2e-5, 2e-5, 0.0])
    cov_cam = Camera(cam.K, cam.dist, cam.width, cam.height, covariance=np.diag(sd**2), covariance_params=names)
    camfile = cov_cam.save_json(tmp_path / "cam_cov.json")
    out, rep = tmp_path / "plane.json", tmp_path / "report"
    r = run(render, "--camera", camfile, "--diameter", "50", "-o", out, "--report", rep)
    assert r.returncode == 0, r.stderr
    d = json.loads(out.read_text())
    u = d["uncertainty"]
    assert u["camera_share"] == "included" and d["camera_jacobian"]["params"] == list(names)
    assert u["point_sigma_rms_mm"] > 3 * u["plane_only_sigma_rms_mm"] and u["shape_sigma_rms_mm"] < u["point_sigma_rms_mm"]
    assert "intrinsics" in u["covers"]["point_sigma_rms_mm"] and "rigid motion" in u["covers"]["shape_sigma_rms_mm"]
    assert "camera frame" in r.stdout and "shape" in r.stdout and "with the camera's share" in r.stdout
    assert "RMS shape σ" in (rep / "index.html").read_text()
    # the plane file's sigma is what the library computes for the same files (measure's per-point sigma too)
    from lightplane.measure.profile import ProfileMeasurer
    from lightplane.plane.uncertainty import point_sigma_mm

    plane = LightPlane.load(out)
    cam2 = Camera.load(camfile)
    uv = np.array([[640.0, 300.0], [700.0, 500.0]])
    prof = ProfileMeasurer(cam2, plane, lookup=False).from_stripe(uv, np.ones(2, bool))
    assert np.allclose(prof.sigma_mm, point_sigma_mm(cam2, plane, uv))
    assert np.all(prof.sigma_mm > point_sigma_mm(cam2, plane, uv, covariance=plane.covariance))
    # the same images with the covariance-free camera file: every output says the share is missing
    out2 = tmp_path / "plane2.json"
    r = run(render, "--camera", render / "camera.json", "--diameter", "50", "-o", out2)
    assert r.returncode == 0, r.stderr
    u2 = json.loads(out2.read_text())["uncertainty"]
    assert "not included" in u2["camera_share"] and "not included" in u2["covers"]["point_sigma_rms_mm"]
    assert "not included" in r.stdout
    assert u2["point_sigma_rms_mm"] == pytest.approx(u2["plane_only_sigma_rms_mm"])
