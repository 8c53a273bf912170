"""Calibrating the lens models from rendered chessboards (small renders: a 640x480 version of each
camera of lightplane.simulate.scene.lens_camera), the over-parameterisation warning, and
``calibrate-camera --model``'s bad input."""

from __future__ import annotations

from dataclasses import replace
import functools
import json

import cv2
import numpy as np
import pytest

from _cli import lightplane, one_error_line
from lightplane import Camera
from lightplane.camera.intrinsics import CameraCalibrationOptions, calibrate_camera
from lightplane.camera.lens import coeff_names
from lightplane.simulate.scene import lens_camera
from lightplane.simulate.render import CALIBRATION_CAPTURE, BoardOptions, render_chessboard_dataset

BOARD, SQUARE = CALIBRATION_CAPTURE.board, CALIBRATION_CAPTURE.square_mm


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
    return cam, render_chessboard_dataset(8, 5, BoardOptions(difficulty="clean"), camera=cam)


@pytest.fixture(scope="module")
def fisheye_boards():
    cam = half(lens_camera("fisheye"))
    return cam, render_chessboard_dataset(8, 6, BoardOptions(
        difficulty="clean", capture=replace(CALIBRATION_CAPTURE, distance_mm=(110.0, 200.0))), camera=cam)


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
    cal = calibrate_camera(ds.images, BOARD, SQUARE, options=CameraCalibrationOptions(model="tilted"))
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


def test_calibrate_camera_cli_tilted_says_which_std(tmp_path, tilted_boards):
    """The std printed and written for the tilted model are the covariance's (OpenCV's own are its
    pseudo-inverse's, which can drop the tilt's weak direction: test_opencv_sigma_of_the_tilted_model;
    on these 8 small clean views they are not truncated, and no note is printed)."""
    cam, ds = tilted_boards
    for i, img in enumerate(ds.images):
        cv2.imwrite(str(tmp_path / f"b{i}.png"), img)
    out = tmp_path / "cam.json"
    r = lightplane("calibrate-camera", tmp_path / "b*.png", "--board", f"{BOARD[0]}x{BOARD[1]}", "--square", SQUARE,
                   "--model", "tilted", "-o", out)
    assert r.returncode == 0, r.stderr
    text = " ".join(r.stdout.split())
    assert "± std: from the full covariance" in text
    d = json.loads(out.read_text())
    back = Camera.load(out)
    sd = dict(zip(back.covariance_params, np.sqrt(np.diag(back.covariance))))
    for n in ("fx", "cx", "cy", "p1", "taux", "tauy"):
        assert np.isclose(d["calibration"]["std"][n], sd[n], rtol=1e-9), n
    # on the same corner noise (OpenCV's is the residuals' alone, ours times the views' dispersion)
    f = np.sqrt(d["calibration"]["covariance"]["view_dispersion"])
    ratio = max(d["calibration"]["std"][n] / (f * d["calibration"]["std_opencv"][n]) for n in sd if sd[n] > 0)
    assert ("OpenCV's own stdDeviationsIntrinsics are up to" in text) == (ratio > 2.0)
    assert isinstance(d["calibration"]["corners"]["lens_frame_refit_corners"], int)


def test_over_parameterised_model_is_flagged(tilted_boards):
    """The thin-prism terms of a lens that has none, from 4 views: undetermined and correlated."""
    cam, ds = tilted_boards
    cal = calibrate_camera(ds.images[:4], BOARD, SQUARE, options=CameraCalibrationOptions(model="thin_prism"))
    assert cal.camera.model == "thin_prism" and cal.camera.dist.size == 12
    text = " ".join(cal.warnings)
    assert "over-parameterised" in text or "correlated" in text, cal.warnings


@pytest.mark.parametrize("refine", ["saddle", "forstner"])
def test_fisheye_calibrates_to_the_truth(fisheye_boards, refine):
    """The default corners: the blurred-saddle fit's edges are straight, so under this much distortion
    the corners are fitted again in the lens frame of a first calibration (with the straight-edge fit
    alone fx, fy were +4.4 sigma off here); Förstner's corners need no such step."""
    cam, ds = fisheye_boards
    cal = calibrate_camera(ds.images, BOARD, SQUARE, options=CameraCalibrationOptions(model="fisheye", refine=refine))
    assert cal.camera.model == "fisheye" and cal.camera.dist.size == 4
    assert cal.options["refine"] == refine
    assert (cal.options["lens_frame_refit_corners"] > 0) == (refine == "saddle")
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
    for model, tilt, needle in (("plumb_bob", "0,4.5", "--model tilted"), ("tilted", "a,b", "TAUX,TAUY")):
        one_error_line(lightplane("calibrate-camera", tmp_path / "b*.png", "--board", "9x6", "--square", "10",
                                  "--model", model, "--tilt", tilt, "-o", tmp_path / "x.json"), needle)
    assert not (tmp_path / "x.json").exists()
    # a held tilt is checked before any image is read
    from lightplane import LightplaneError
    for model, tilt, needle in (("tilted", (0.0, 60.0), "under 45 degrees"), ("tilted", (4.5,), "two finite"),
                                ("rational", (0.0, 4.5), "tilted model")):
        with pytest.raises(LightplaneError, match=needle):
            calibrate_camera([tmp_path / "none.png"], BOARD, SQUARE,
                             options=CameraCalibrationOptions(model=model, tilt_deg=tilt))  # type: ignore[arg-type]


def test_tilted_sensor_with_the_tilt_held(tilted_boards):
    """The tilt held (at the truth here, as a mechanical design would give it): the rest is determined,
    OpenCV's own std are right (its normal matrix is regular) and the intrinsics are within 3.5 of them
    (these clean renders' corner noise is 0.005 px, so their small systematic errors show: fx +3.45 of
    the same sigma here, and up to 3.1 sigma with the tilt free; 3.5 as in _check_within_sigma)."""
    cam, ds = tilted_boards
    held = (float(np.rad2deg(cam.dist[12])), float(np.rad2deg(cam.dist[13])))
    cal = calibrate_camera(ds.images, BOARD, SQUARE, options=CameraCalibrationOptions(model="tilted", tilt_deg=held))
    assert np.allclose(cal.camera.dist[12:], cam.dist[12:], rtol=1e-12, atol=1e-15)
    assert cal.std["taux"] == 0 and cal.std["tauy"] == 0
    f = np.sqrt(cal.options["covariance_dispersion"])  # ours: the residuals' noise times the views' dispersion
    for n in ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"):
        assert np.isclose(cal.std_opencv[n], cal.std[n] / f, rtol=0.05), (n, cal.std_opencv[n], cal.std[n] / f)
    for n, t, e in zip(("fx", "fy", "cx", "cy"), (cam.fx, cam.fy, cam.cx, cam.cy),
                       (cal.camera.fx, cal.camera.fy, cal.camera.cx, cal.camera.cy)):
        assert abs(e - t) <= 3.5 * cal.std_opencv[n], (n, t, e, cal.std_opencv[n])
    assert not any("tilt is not separated" in w for w in cal.warnings)


@functools.lru_cache(maxsize=None)  # shared by the tests below (not changed by them): its poses take ~6 s
def _synthetic_tilted(zero_p: bool, seed: int = 1, sigma_px: float = 0.006):
    """Exact corners of the Scheimpflug camera (p1 = p2 = 0 with ``zero_p``) for 20 poses of the calibration
    capture, plus Gaussian noise of ``sigma_px``: object and image points as calibrateCamera takes them."""
    from lightplane.simulate.scene import scheimpflug_camera
    from lightplane.simulate.render import board_corners, sample_board_poses

    cam = scheimpflug_camera(dist=(-0.08, 0.12, 0.0, 0.0, 0.0) if zero_p else (-0.08, 0.12, 4e-4, -3e-4, 0.0))
    rng = np.random.default_rng(seed)
    poses = sample_board_poses(20, rng, CALIBRATION_CAPTURE, camera=cam)
    obj = board_corners(BOARD, SQUARE)
    objs = [obj.astype(np.float32) for _ in poses]
    ims = [(cam.project(obj @ R.T + t) + rng.normal(0, sigma_px, (len(obj), 2))).astype(np.float32).reshape(-1, 1, 2)
           for R, t in poses]
    return cam, objs, ims


@pytest.mark.parametrize("zero_tangent", [False, True])
def test_opencv_sigma_of_the_tilted_model(zero_tangent):
    """OpenCV's stdDeviationsIntrinsics are its pseudo-inverse of the full normal matrix (cv2.invert,
    DECOMP_EIG, which drops eigenvalues below ~2 eps sum): with p1, p2 free the sensor tilt trades against
    them and the principal point, the weakest direction falls under the cut, and OpenCV's sigma are >10x
    too small; the exact inverse (our covariance) is not.  With p1 = p2 = 0 held (a lens without
    tangential distortion) the tilt is determined and the two agree."""
    from lightplane.camera.intrinsics import free_parameters, calibration_flags, intrinsics_covariance

    cam, objs, ims = _synthetic_tilted(zero_tangent)
    _, flags = calibration_flags("tilted", cv2.CALIB_ZERO_TANGENT_DIST if zero_tangent else 0)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    _, K, dist, rv, tv, std_cv, _, _ = cv2.calibrateCameraExtended(objs, ims, cam.size, None, None, flags=flags,
                                                                   criteria=crit)
    dist = dist.ravel()
    free = np.flatnonzero(free_parameters(14, flags))
    p, nv = free.size, len(objs)
    J = np.zeros((2 * sum(len(o) for o in objs), p + 6 * nv))
    r = []
    for i, (o, u) in enumerate(zip(objs, ims)):
        proj, jac = cv2.projectPoints(o.astype(np.float64), rv[i], tv[i], K, dist)
        rows = slice(2 * len(o) * i, 2 * len(o) * (i + 1))
        J[rows, :p] = jac[:, 6:][:, free]
        J[rows, p + 6 * i:p + 6 * i + 6] = jac[:, :6]
        r.append((proj.reshape(-1, 2) - u.reshape(-1, 2)).ravel())
    res = np.concatenate(r)
    JtJ = J.T @ J
    s2 = res @ res / (J.shape[0] - J.shape[1])  # OpenCV: 2 N - (intrinsics + poses)
    _, pinv = cv2.invert(JtJ, flags=cv2.DECOMP_EIG)
    cv_ours = np.sqrt(np.diag(pinv)[:p] * s2)
    # OpenCV's sigma, reproduced where the normal matrix is well conditioned (p1 = p2 = 0 held).  With p1, p2
    # free the weakest directions sit next to the pseudo-inverse's cut, where OpenCV's numbers depend on the last
    # bits of its float32 accumulation, its thread order and its release: there only the claim of the test is
    # checked (OpenCV's cx sigma > 10x too small, a margin of ~70x), never one release's truncation.
    if zero_tangent:
        assert np.allclose(cv_ours, std_cv.ravel()[free], rtol=0.02), (cv_ours, std_cv.ravel()[free])
    icov = intrinsics_covariance(objs, ims, rv, tv, K, dist, flags, noise="white")  # OpenCV's noise model
    exact = np.sqrt(np.diag(np.linalg.inv(JtJ))[:p] * s2)
    names = ("fx", "fy", "cx", "cy") + coeff_names("tilted")
    ours = np.array([icov.std()[names[k]] for k in free])
    assert np.allclose(ours, exact, rtol=0.02)  # the covariance is the exact inverse, poses marginalised
    cx = list(free).index(2)
    if zero_tangent:
        assert np.allclose(std_cv.ravel()[free], ours, rtol=0.02)
        assert ours[cx] < 2.0  # px: the tilt is determined
    else:
        assert np.linalg.eigvalsh(JtJ)[0] < 2 * np.finfo(float).eps * np.trace(JtJ)  # under OpenCV's cut
        assert ours[cx] > 10 * std_cv.ravel()[2] and ours[cx] > 3.0


def test_scheimpflug_tilt_of_a_narrow_lens_is_a_rotation_to_the_noise():
    """Through the 16 mm lens (field half-diagonal 10.6 deg) a 4.52 deg sensor tilt shows only where the
    distortion, applied before the tilt, meets it (at order tau k1 r^4, ~0.03 px at the image corners); at
    first order it is a rotation of the camera frame by tau, a principal-point shift of f sin(tau) and
    p2 += k1 tau (the radial distortion's centre moved off the principal point).  So the plumb bob,
    no tilt at all, fits the corners to ~0.002 px RMS of the tilted model and its rays are the true ones
    after that rotation; the tilted model's own calibration is the truth up to a small rotation, whatever its
    principal point (OpenCV's sigma: test_opencv_sigma_of_the_tilted_model).  20 views, 0.006 px noise."""
    from lightplane.camera.intrinsics import (calibration_flags, intrinsics_covariance, overparameterisation_warnings,
                                       rays_up_to_rotation)

    cam, objs, ims = _synthetic_tilted(False)
    tau = cam.dist[13]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    rms_p, K, d, _, _ = cv2.calibrateCamera(objs, ims, cam.size, None, None, flags=0, criteria=crit)
    _, flags = calibration_flags("tilted", 0)
    rms_t, Kt, dt, rv, tv = cv2.calibrateCamera(objs, ims, cam.size, None, None, flags=flags, criteria=crit)
    # 0.006 px per coordinate: 0.0085 px; what the plumb bob misses of the tilt adds ~0.002 px RMS (0.0018 px
    # on noise-free corners: bench_scheimpflug_views.py)
    assert rms_t < 0.0095 and np.sqrt(max(rms_p ** 2 - rms_t ** 2, 0.0)) < 0.003
    d = d.ravel()
    assert abs(K[0, 2] - (cam.cx + cam.fx * np.sin(tau))) < 2.0  # 337 px off the lens axis
    assert abs(K[1, 2] - cam.cy) < 2.0
    assert abs(d[3] - (cam.dist[3] + cam.dist[0] * tau)) < 0.1 * abs(cam.dist[0] * tau)
    plumb = rays_up_to_rotation(cam, Camera(K, d, cam.width, cam.height), step_px=32)
    assert plumb.rms_px > 300 and abs(plumb.rotation_deg - np.rad2deg(tau)) < 0.02
    assert plumb.rotated_rms_px < 0.05 and plumb.rotated_max_px < 0.2
    tilted = Camera(Kt, dt.ravel(), cam.width, cam.height, model="tilted")
    cmp = rays_up_to_rotation(cam, tilted, step_px=32)
    assert cmp.rotated_rms_px < 0.03 and cmp.rotated_max_px < 0.15
    # the calibration says why the principal point is not pinned, and what pins it
    icov = intrinsics_covariance(objs, ims, rv, tv, Kt, dt.ravel(), flags)
    text = " ".join(overparameterisation_warnings(tilted, icov, icov.std(), len(objs)))
    assert "rotation of the camera frame" in text and "--tilt" in text
