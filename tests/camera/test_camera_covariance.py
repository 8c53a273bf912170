"""The camera calibration's full covariance: Monte Carlo against the
prediction on exact projected corners with injected noise, OpenCV's standard deviations as
a cross-check, the camera JSON round trip, and ``calibrate-camera``'s output."""

from __future__ import annotations

from dataclasses import replace
import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from lightplane import Camera
from lightplane.core.errors import LightplaneError
from lightplane.camera.intrinsics import intrinsics_covariance
from lightplane.simulate.scene import default_camera
from lightplane.simulate.render import CALIBRATION_CAPTURE as CC
from lightplane.simulate.render import board_corners, sample_board_poses
from lightplane.plane.uncertainty import camera_steps, camera_uncertainty_summary, ray_sigma_rad

BOARD = (9, 7)
SIGMA_PX = 0.1
CRIT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


def _scene(seed=0, n=16):
    cam = default_camera()
    poses = sample_board_poses(n, np.random.default_rng(seed), replace(CC, board=BOARD, square_mm=8.0), camera=cam)
    obj = board_corners(BOARD, 8.0).astype(np.float64)
    return cam, obj, [cam.project(obj @ R.T + t) for R, t in poses]


def _calibrate(obj, truth, rng, flags=0, noise="views", view_excess=0.0):
    """Calibrate from ``truth`` with white corner noise of SIGMA_PX plus, with ``view_excess``,
    each view's own extra white noise of ``view_excess * SIGMA_PX`` projected onto the directions
    in which its corners move with the intrinsics (its pose's projected out): errors correlated
    within a view, of variance ``(1 + view_excess²) SIGMA_PX²`` along the intrinsics."""
    cam = default_camera()
    ip = []
    for u in truth:
        e = SIGMA_PX * rng.standard_normal(u.shape)
        if view_excess:
            R, t = cam.solve_pnp(obj, u)
            _, jac = cv2.projectPoints(obj, cv2.Rodrigues(R)[0], t, cam.K, cam.dist)
            Je, Ji = jac[:, :6], jac[:, 6:15]
            Jt = Ji - Je @ np.linalg.lstsq(Je, Ji, rcond=None)[0]
            Q, _ = np.linalg.qr(Jt)
            e = e + (view_excess * SIGMA_PX * Q @ rng.standard_normal(Q.shape[1])).reshape(e.shape)
        ip.append((u + e).astype(np.float32))
    ob = [obj.astype(np.float32)] * len(ip)
    rms, K, d, rv, tv, std_int, _, _ = cv2.calibrateCameraExtended(ob, ip, (1280, 960), None, None, flags=flags,
                                                                   criteria=CRIT)
    d = d.ravel()[:5]
    return (np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], d], intrinsics_covariance(ob, ip, rv, tv, K, d, flags, noise=noise),
            std_int)


@pytest.mark.parametrize("flags, n_free", [(0, 9), (cv2.CALIB_FIX_K3, 8)])
def test_covariance_matches_monte_carlo(flags, n_free):
    """Over repeated calibrations with fresh white noise the error's Mahalanobis distance² under the
    white-noise covariance averages the number of free parameters (chi²: mean n, sd sqrt(2n/T));
    the views' dispersion averages 1, and the default covariance (scaled by it) stays right."""
    cam, obj, truth = _scene()
    p_true = np.r_[cam.fx, cam.fy, cam.cx, cam.cy, cam.dist]
    rng = np.random.default_rng(1)
    trials = 60
    d2, d2v, sig, disp = [], [], [], []
    for _ in range(trials):
        p, c, std_cv = _calibrate(obj, truth, rng, flags, noise="white")
        free = c.free
        assert free.sum() == n_free
        assert np.all(c.covariance[~free] == 0) and np.all(c.covariance[:, ~free] == 0)
        e = (p - p_true)[free]
        d2.append(e @ np.linalg.solve(c.covariance[np.ix_(free, free)], e))
        # the default: the same covariance times the dispersion
        d2v.append(d2[-1] / c.dispersion)
        sig.append(c.sigma_px)
        disp.append(c.dispersion)
    mean = np.mean(d2)
    tol = 3.5 * np.sqrt(2 * n_free / trials)
    assert abs(mean - n_free) < tol, (mean, n_free, tol)
    # the noise estimated from the residuals (with its dof) is unbiased
    assert abs(np.mean(sig) / SIGMA_PX - 1) < 0.02
    # the dispersion is 1 for white noise, within its sampling (its sd from the trials)
    assert abs(np.mean(disp) - 1) < 3.5 * np.std(disp) / np.sqrt(trials), (np.mean(disp), np.std(disp))
    # with it the Mahalanobis² grows only by its own noise (E[1/dispersion] ~ 1 + its relative variance)
    assert abs(np.mean(d2v) - n_free) < tol + n_free * 2 * np.var(disp), (np.mean(d2v), np.var(disp))
    # the diagonal is OpenCV's own standard deviation (same model, its own dof count)
    std_ours = np.sqrt(np.diag(c.covariance))[free]
    std_cv = np.asarray(std_cv).ravel()[:9][free]
    assert np.allclose(std_ours, std_cv, rtol=0.02), (std_ours, std_cv)
    # and the parameters are strongly correlated: the diagonal alone is not the covariance
    corr = c.covariance[:4, :4] / np.outer(std_ours[:4], std_ours[:4])
    assert abs(corr[0, 1]) > 0.5


def test_view_correlated_corner_errors():
    """Corner errors correlated within a view (each view's own extra noise along the directions that
    move the intrinsics, twice the white variance there in all): the residuals' sigma does not see
    it and the white-noise covariance is too small by that factor; the views' dispersion finds it
    and the default covariance's Mahalanobis² averages the number of parameters again."""
    cam, obj, truth = _scene(seed=6)
    p_true = np.r_[cam.fx, cam.fy, cam.cx, cam.cy, cam.dist]
    rng = np.random.default_rng(7)
    trials, n = 40, 9
    d2, d2w, disp, sig = [], [], [], []
    for _ in range(trials):
        p, c, _ = _calibrate(obj, truth, rng, view_excess=1.0)
        e = p - p_true
        d2.append(e @ np.linalg.solve(c.covariance, e))
        d2w.append(d2[-1] * c.dispersion)  # under the white-noise covariance
        disp.append(c.dispersion)
        sig.append(c.sigma_px)
    # sigma from the residuals: the extra noise lies mostly in what each view's own fit absorbs
    assert np.mean(sig) / SIGMA_PX < 1.1
    # the white-noise covariance is too small by the factor 2 (chi² mean 2n), the default is right
    tol = 3.5 * np.sqrt(2 * n / trials)
    assert np.mean(d2w) > 1.5 * n, np.mean(d2w)
    assert abs(np.mean(disp) - 2) < 3.5 * np.std(disp) / np.sqrt(trials) + 0.1, np.mean(disp)
    assert abs(np.mean(d2) - n) < tol + n * 2 * np.var(np.asarray(disp) / np.mean(disp)), np.mean(d2)


def test_ray_sigma_matches_monte_carlo():
    """The ray-direction sigma printed by calibrate-camera: against the spread of the rays of
    repeated calibrations (the same pixel), within the sampling tolerance of 60 trials."""
    cam, obj, truth = _scene(seed=2)
    rng = np.random.default_rng(3)
    uv = np.array([[640.0, 480.0], [50.0, 40.0], [1200.0, 900.0]])
    r_true = cam.rays(uv, unit=True)
    errs, pred = [], []
    for _ in range(60):
        p, c, _ = _calibrate(obj, truth, rng)
        K = np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1]])
        est = Camera(K, p[4:], 1280, 960, covariance=c.covariance, covariance_params=c.params)
        errs.append(np.sum((est.rays(uv, unit=True) - r_true) ** 2, axis=1))
        pred.append(ray_sigma_rad(est, uv) ** 2)
    ratio = np.sqrt(np.mean(errs, axis=0) / np.mean(pred, axis=0))
    # sampling: the RMS of 60 draws of a 2-dof error is within ~±16 % (2 sd) of its sigma
    assert np.all(np.abs(ratio - 1) < 0.2), ratio


def test_camera_json_round_trip_and_validation(tmp_path):
    cam, obj, truth = _scene(seed=4, n=8)
    p, c, _ = _calibrate(obj, truth, np.random.default_rng(5))
    K = np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1]])
    est = Camera(K, p[4:], 1280, 960, covariance=c.covariance, covariance_params=c.params)
    f = est.save_json(tmp_path / "cam.json")
    back = Camera.load(f)
    assert back == est and np.array_equal(back.covariance, est.covariance)
    assert back.covariance_params == ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    assert len(camera_steps(back)) == 9
    # a camera without a covariance still works, and says the camera's share is missing
    plain = Camera(K, p[4:], 1280, 960)
    assert "covariance" not in plain.to_dict() and len(camera_steps(plain)) == 0
    s = camera_uncertainty_summary(plain, 450.0)
    assert s["included"] is False and "not included" in s["note"]
    d = json.loads(f.read_text())
    for bad, needle in (({"covariance": d["covariance"]}, "go together"),
                        ({"covariance": [[1.0]], "covariance_params": d["covariance_params"]}, "covariance"),
                        ({"covariance": "x", "covariance_params": d["covariance_params"]}, "covariance")):
        g = dict(d)
        g.pop("covariance_params")
        g.update(bad)
        with pytest.raises(LightplaneError, match=needle):
            Camera.from_dict(g, "cam.json")
    # a covariance of another model's parameters is refused where it is used
    other = Camera(K, p[4:], 1280, 960, covariance=np.eye(8), covariance_params=tuple("abcdefgh"))
    with pytest.raises(LightplaneError, match="another model"):
        camera_steps(other)


def test_calibrate_camera_cli_prints_and_stores_the_covariance(tmp_path):
    from lightplane.simulate.render import BoardOptions, render_chessboard_dataset

    ds = render_chessboard_dataset(5, 7, BoardOptions(difficulty="realistic", capture=replace(CC, board=BOARD, square_mm=8.0)))
    ds.save(tmp_path / "cb")
    out = tmp_path / "cam.json"
    r = subprocess.run([sys.executable, "-m", "lightplane", "calibrate-camera", str(tmp_path / "cb" / "*.png"),
                        "--board", "9x7", "--square", "8", "-o", str(out), "--distance", "500"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "Camera uncertainty" in r.stdout and "deg RMS over the image" in r.stdout and "at 500 mm" in r.stdout
    d = json.loads(out.read_text())
    cov = np.asarray(d["covariance"])
    assert cov.shape == (9, 9) and d["covariance_params"][:4] == ["fx", "fy", "cx", "cy"]
    # its diagonal is OpenCV's standard deviations (independent computation) within its dof count
    # (fx..cy: with only 5 views k1, k2, k3 are nearly collinear and OpenCV's inversion of its
    # normal matrix departs from ours there; at 16 views all nine agree to 0.1 %)
    std = d["calibration"]["std"]
    for i, n in enumerate(d["covariance_params"][:4]):
        assert np.sqrt(cov[i, i]) == pytest.approx(std[n], rel=0.05), n
    cu = d["camera_uncertainty"]
    assert cu["included"] and cu["distance_mm"] == 500.0
    assert cu["ray_sigma_mm_rms"] == pytest.approx(np.radians(cu["ray_sigma_deg_rms"]) * 500.0)
    # the true camera's rays lie within a few sigma of the calibrated ones
    cam = Camera.load(out)
    true = ds.camera
    grid = np.array([[100.0, 100.0], [640.0, 480.0], [1180.0, 860.0]])
    ang = np.arccos(np.clip(np.sum(cam.rays(grid, unit=True) * true.rays(grid, unit=True), axis=1), -1, 1))
    assert np.all(ang < 5 * ray_sigma_rad(cam, grid) + 1e-7)
    # a bad --distance: one line, exit 2, nothing written
    r = subprocess.run([sys.executable, "-m", "lightplane", "calibrate-camera", str(tmp_path / "cb" / "*.png"),
                        "--board", "9x7", "--square", "8", "-o", str(tmp_path / "c2.json"), "--distance", "-1"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "--distance" in r.stderr and not (tmp_path / "c2.json").exists()
