"""Calibrating the lens models from rendered chessboards (small renders: a 640x480 version of each
camera of lightplane.simulate.geometry.lens_camera), the over-parameterisation warning, and
``calibrate-camera --model``'s bad input."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from _cli import lightplane, one_error_line
from lightplane import Camera
from lightplane.intrinsics import calibrate_camera
from lightplane.lens import coeff_names
from lightplane.simulate.geometry import lens_camera
from lightplane.simulate.render import CALIBRATION_CAPTURE, render_chessboard_dataset

BOARD, SQUARE = CALIBRATION_CAPTURE["board"], CALIBRATION_CAPTURE["square_mm"]


def half(cam: Camera) -> Camera:
    """The same lens on a sensor of half the pixels each way (pixel centres: u' = (u + 0.5) / 2 - 0.5)."""
    K = cam.K.copy()
    K[:2] *= 0.5
    K[0, 2] -= 0.25
    K[1, 2] -= 0.25
    return Camera(K, cam.dist, cam.width // 2, cam.height // 2, model=cam.model)


@pytest.fixture(scope="module")
def tilted_boards():
    cam = half(lens_camera("tilted"))
    return cam, render_chessboard_dataset(8, seed=5, camera=cam, difficulty="clean")


@pytest.fixture(scope="module")
def fisheye_boards():
    cam = half(lens_camera("fisheye"))
    return cam, render_chessboard_dataset(8, seed=6, camera=cam, difficulty="clean", distance_mm=(110.0, 200.0))


def _check_within_sigma(truth: Camera, cal, k: float = 3.5) -> None:
    names = ("fx", "fy", "cx", "cy") + coeff_names(truth.model)
    t = np.concatenate([[truth.fx, truth.fy, truth.cx, truth.cy], truth.dist])
    e = np.concatenate([[cal.camera.fx, cal.camera.fy, cal.camera.cx, cal.camera.cy], cal.camera.dist])
    checked = 0
    for n, a, b in zip(names, t, e):
        s = cal.std[n]
        if s > 0:
            assert abs(b - a) <= k * s, (n, a, b, s)
            checked += 1
    assert checked >= 8


def test_tilted_sensor_calibrates_to_the_truth(tilted_boards):
    cam, ds = tilted_boards
    cal = calibrate_camera(ds.images, BOARD, SQUARE, model="tilted")
    assert cal.camera.model == "tilted" and cal.camera.dist.size == 14
    assert np.all(cal.camera.dist[5:12] == 0)  # the rational and prism terms are not estimated
    # the corners of the renders are where the tilted model puts them (the renderer uses the model)
    assert cal.rms_px < 0.02
    _check_within_sigma(cam, cal)
    assert cal.std["taux"] > 0 and cal.std["k4"] == 0
    # a Scheimpflug tilt is not small against its sigma here: the fit sees it
    assert abs(cal.camera.dist[13]) > 5 * cal.std["tauy"]
    # the result file says what produced it
    d = cal.to_dict()
    assert d["model"] == "tilted" and "corner noise" in d["std_covers"] and set(d["std_opencv"]) >= {"taux", "tauy"}


def test_over_parameterised_model_is_flagged(tilted_boards):
    """The thin-prism terms of a lens that has none, from 4 views: undetermined and correlated."""
    cam, ds = tilted_boards
    cal = calibrate_camera(ds.images[:4], BOARD, SQUARE, model="thin_prism")
    assert cal.camera.model == "thin_prism" and cal.camera.dist.size == 12
    text = " ".join(cal.warnings)
    assert "over-parameterised" in text or "correlated" in text, cal.warnings


def test_fisheye_calibrates_to_the_truth(fisheye_boards):
    """Förstner's corners: the default blurred-saddle fit assumes straight edges across its window and
    is biased under this much distortion (fx, fy +4.4 sigma here; README, Limits)."""
    cam, ds = fisheye_boards
    cal = calibrate_camera(ds.images, BOARD, SQUARE, model="fisheye", refine="forstner")
    assert cal.camera.model == "fisheye" and cal.camera.dist.size == 4
    assert cal.rms_px < 0.06
    # cv2.fisheye gives no std: ours from the Jacobian of the reprojection
    assert all(cal.std[n] > 0 for n in ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"))
    _check_within_sigma(cam, cal)
    # the calibrated camera's rays through the true camera land on their pixels (RMS over the whole
    # image; the image corners, beyond the boards, are extrapolated: 0.6 px there)
    v, u = np.mgrid[0:cam.height:20, 0:cam.width:20]
    uv = np.column_stack([u.ravel(), v.ravel()]).astype(float)
    e = np.linalg.norm(cam.project(cal.camera.rays(uv) * 300.0) - uv, axis=1)
    assert np.sqrt(np.mean(e ** 2)) < 0.15 and e.max() < 1.5


def test_calibrate_camera_cli_model(tmp_path, fisheye_boards):
    cam, ds = fisheye_boards
    for i, img in enumerate(ds.images[:6]):
        cv2.imwrite(str(tmp_path / f"b{i}.png"), img)
    out = tmp_path / "cam.json"
    r = lightplane("calibrate-camera", tmp_path / "b*.png", "--board", f"{BOARD[0]}x{BOARD[1]}", "--square", SQUARE,
                   "--model", "fisheye", "-o", out)
    assert r.returncode == 0, r.stderr
    back = Camera.load(out)
    assert back.model == "fisheye"
    d = json.loads(out.read_text())
    assert d["model"] == "fisheye" and d["provenance"]["options"]["solver"] == "fisheye.calibrate"
    assert "lens model fisheye" in r.stdout and "k4" in r.stdout
    back.save(tmp_path / "cam.yaml", fmt="ros")
    assert "equidistant" in (tmp_path / "cam.yaml").read_text() and Camera.load(tmp_path / "cam.yaml") == back
    one_error_line(lightplane("calibrate-camera", tmp_path / "b*.png", "--board", "9x6", "--square", "10",
                              "--model", "brown", "-o", tmp_path / "x.json"), "--model", "brown")
    one_error_line(lightplane("calibrate-camera", tmp_path / "b*.png", "--board", "9x6", "--square", "10",
                              "--model", "fisheye", "--fix-k3", "-o", tmp_path / "x.json"), "fisheye")
    assert not (tmp_path / "x.json").exists()
