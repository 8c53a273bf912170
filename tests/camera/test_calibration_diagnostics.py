"""What a camera calibration's views determine, and its RMS against its corners' own noise
(lightplane.camera.diagnostics; docs/calibration-guide.md §What the views determine).

Exact corners projected by a known camera (Gaussian noise of known σ added) test the statistics fast;
small renders with the renderer's realistic imaging test the corner noise measured from the images."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from lightplane.camera.corners import _detect_board, corner_noise
from lightplane.camera.diagnostics import (NOISE_RATIO, board_tilts, corner_noise_check, degenerate_views_message,
                                           focal_length_problem, outlier_views, perspective_px)
from lightplane.camera.intrinsics import CameraCalibrationOptions, calibrate_camera
from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.core.io import to_gray_float
from lightplane.simulate.render import BoardCapture, BoardOptions, render_chessboard_dataset
from _cli import lightplane, one_error_line

K = np.array([[900.0, 0, 322.0], [0, 900.0, 236.0], [0, 0, 1]])
DIST = np.array([-0.12, 0.08, 3e-4, -2e-4, 0.0])
BOARD, SQ = (7, 5), 10.0


def _board(scale_x: float = 1.0) -> np.ndarray:
    g = np.stack(np.meshgrid(np.arange(BOARD[0]), np.arange(BOARD[1])), -1).reshape(-1, 2)
    return np.column_stack([g[:, 0] * SQ * scale_x, g[:, 1] * SQ, np.zeros(len(g))]).astype(np.float64)


def _poses(rng, n: int, tilt_deg: tuple[float, float] = (20.0, 40.0)):
    """Board poses facing the camera at ~300 mm, tilted about random in-plane axes."""
    out = []
    for _ in range(n):
        a = rng.uniform(0, 2 * np.pi)
        t = np.radians(rng.uniform(*tilt_deg))
        rv = t * np.array([np.cos(a), np.sin(a), 0.0]) + np.array([0, 0, rng.uniform(-0.3, 0.3)])
        tv = np.array([-30.0 + rng.uniform(-20, 20), -20.0 + rng.uniform(-15, 15), rng.uniform(260, 340)])
        out.append((rv, tv))
    return out


def _project(obj, poses, dist=DIST, k=K):
    return [cv2.projectPoints(obj, rv, tv, k, dist)[0].reshape(-1, 2) for rv, tv in poses]


def _check(obj_true, obj_used, poses, rng, sigma, flags=0, dist=DIST, bend=None):
    """Corners of ``obj_true`` (``bend``: per view extra z, mm) projected with noise ``sigma`` (N,) px,
    calibrated with ``obj_used``: the :class:`CornerNoiseCheck` with the noise model's covariances."""
    uv = []
    for i, (rv, tv) in enumerate(poses):
        o = obj_true.copy()
        if bend is not None and bend[i] is not None:
            o[:, 2] += bend[i]
        p = cv2.projectPoints(o, rv, tv, K, dist)[0].reshape(-1, 2)
        uv.append(p + rng.normal(size=p.shape) * sigma[:, None])
    objs = [obj_used.astype(np.float32)] * len(poses)
    rms, k, d, rvs, tvs = cv2.calibrateCamera(objs, [u.astype(np.float32) for u in uv], (640, 480), None, None,
                                              flags=flags)
    res = [u - cv2.projectPoints(obj_used, r, t, k, d)[0].reshape(-1, 2) for u, r, t in zip(uv, rvs, tvs)]
    covs = [np.eye(2)[None] * (sigma**2)[:, None, None]] * len(poses)
    return corner_noise_check([f"v{i}" for i in range(len(poses))], res, covs, 9 + 6 * len(poses))


def test_a_right_calibration_passes_its_noise_check():
    """150 calibrations of 6 views with corner noise of 0.005-0.05 px (a different σ per corner, the
    covariances known): the RMS is what the corners' noise predicts (ratio 1.00 ± 0.03) and none is
    called suspect (0 of 150 here; 0 of 2000 of 10 views measured, <= 1 % asked)."""
    rng = np.random.default_rng(1)
    obj = _board()
    ratios, suspect = [], 0
    for _ in range(150):
        sigma = rng.uniform(0.005, 0.05, len(obj))
        c = _check(obj, obj, _poses(rng, 6), rng, sigma)
        ratios.append(c.ratio)
        suspect += c.suspect
    assert abs(np.mean(ratios) - 1) < 0.03 and np.max(ratios) < 1.3, (np.mean(ratios), np.max(ratios))
    assert suspect == 0


@pytest.mark.parametrize("case", ["print scaled 2 % along x", "one view's board bent 1 mm",
                                  "one view moved 1 px half-way", "k3 and tangential held at 0 (wrong model)"])
def test_a_wrong_calibration_is_suspect(case):
    """Each defect at corner noise 0.02 px: the check calls the calibration suspect and names the
    defective view where one view carries it."""
    rng = np.random.default_rng(2)
    obj = _board()
    poses = _poses(rng, 10)
    sigma = np.full(len(obj), 0.02)
    if case.startswith("print"):
        c = _check(_board(1.03), obj, poses, rng, sigma)
    elif case.startswith("one view's board"):
        r2 = np.sum((obj[:, :2] - obj[:, :2].mean(0)) ** 2, axis=1)
        c = _check(obj, obj, poses, rng, sigma, bend=[1.0 * r2 / r2.max()] + [None] * 9)
    elif case.startswith("one view moved"):
        uv = _project(obj, poses)
        c0 = _check(obj, obj, poses, rng, sigma)
        assert not c0.suspect
        half = obj[:, 1] > obj[:, 1].mean()
        shifted = [u.copy() for u in uv]
        shifted[3][half] += [1.0, 0.0]
        objs = [obj.astype(np.float32)] * 10
        shifted = [u + rng.normal(size=u.shape) * 0.02 for u in shifted]
        _, k, d, rvs, tvs = cv2.calibrateCamera(objs, [u.astype(np.float32) for u in shifted], (640, 480), None, None)
        res = [u - cv2.projectPoints(obj, r, t, k, d)[0].reshape(-1, 2) for u, r, t in zip(shifted, rvs, tvs)]
        c = corner_noise_check([f"v{i}" for i in range(10)], res, [np.eye(2)[None] * 4e-4] * 10, 69)
        assert [n for n, _, _ in c.suspect_views] == ["v3"]
    else:
        wide = np.array([-0.3, 0.12, 6e-3, -5e-3, -0.03])
        c = _check(obj, obj, poses, rng, sigma, flags=cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST, dist=wide)
    assert c.suspect and (c.ratio > NOISE_RATIO or c.suspect_views), (case, c.ratio)
    assert "corners' own noise predicts" in c.diagnosis()


def test_perspective_and_tilts_of_exact_views():
    """A face-on board shows no perspective whatever its distance; a tilted one shows it, growing with
    the tilt; the tilts recovered from exact poses are the poses' own."""
    obj = _board()
    face_on = _project(obj, [(np.zeros(3), np.array([-30.0, -20, 300]))], dist=np.zeros(5))[0]
    assert perspective_px(obj, face_on) < 1e-9
    p = [perspective_px(obj, _project(obj, [(np.array([np.radians(t), 0, 0]), np.array([-30.0, -20, 300]))],
                                      dist=np.zeros(5))[0]) for t in (5, 20, 40)]
    assert 0 < p[0] < p[1] < p[2], p
    tilts, _ = board_tilts([obj], [np.array([np.radians(30), 0, 0])], [np.array([-30.0, -20, 300])])
    c = cv2.Rodrigues(np.array([np.radians(30), 0, 0]))[0] @ obj.mean(0) + [-30.0, -20, 300]
    n = cv2.Rodrigues(np.array([np.radians(30), 0, 0]))[0][:, 2]
    assert tilts[0] == pytest.approx(np.degrees(np.arccos(abs(n @ c) / np.linalg.norm(c))), abs=1e-9)


def test_degenerate_views_are_explained_not_solved():
    msg = degenerate_views_message([1e-6, 2e-6, 3e-6], 0.02, 3)
    assert msg is not None and "cannot be determined" in msg and "tilt the board 20-40 deg" in msg
    assert degenerate_views_message([0.01, 0.5], 0.02, 2) is None
    # a solve that ends at a negative focal length, or at a std larger than 5 % of it
    why = focal_length_problem(-2806.7, 16294.0, {}, [0.3, 0.4], [0.01, 0.02])
    assert why is not None and "not a camera" in why and "tilt the board" in why
    why = focal_length_problem(16294.0, 16294.0, {"fx": 1200.0, "fy": 1200.0}, [0.3], [0.05])
    assert why is not None and "7 % of it" in why
    assert focal_length_problem(900.0, 900.0, {"fx": 2.0, "fy": 2.0}, [30.0], [3.0]) is None


def test_outlier_views_named_with_their_reason():
    """FabScan's frame 008: 3.67 px against a median of ~0.7 px."""
    rms = [0.70, 0.68, 0.74, 0.66, 0.71, 0.69, 0.72, 3.67]
    out = outlier_views([f"calibration_{i:03d}.jpg" for i in range(8)], rms)
    assert list(out) == ["calibration_007.jpg"] and "5.2x the views' median" in out["calibration_007.jpg"]
    assert outlier_views(["a", "b", "c"], [0.01, 0.01, 0.2]) == {}  # under the floor


SMALL = Camera(np.array([[560.0, 0, 241.0], [0, 560.0, 178.0], [0, 0, 1]]), np.array([-0.1, 0.06, 2e-4, -1e-4, 0.0]),
               480, 360)


@pytest.fixture(scope="module")
def small_renders():
    """8 realistic renders (480x360, a 7x5 board of 6 mm tilted 20-45 deg)."""
    cap = BoardCapture(board=(7, 5), square_mm=6.0, distance_mm=(180.0, 240.0), tilt_deg=(20.0, 45.0),
                       margin_px=10.0)
    return render_chessboard_dataset(8, 4, BoardOptions(difficulty="realistic", capture=cap), camera=SMALL)


def test_corner_noise_from_the_image_is_the_corners_error(small_renders):
    """Each saddle-fit corner's covariance from its own image predicts its error against the rendered
    truth: mean |e|² / tr C within 0.6-1.6 (measured 1.12 on the default capture)."""
    z = []
    for img, v in zip(small_renders.images, small_renders.truth["views"]):
        truth = np.asarray(v["corners_px"])
        c, q, _, P = _detect_board(img, BOARD, True, "saddle")
        if c is None:  # the board is not found in one of them
            continue
        if np.linalg.norm(c[0] - truth[0]) > np.linalg.norm(c[-1] - truth[0]):
            c, q, P = c[::-1], q[::-1], P[::-1]
        C, noise = corner_noise(img if img.ndim == 2 else to_gray_float(img), c, BOARD, P)
        ok = np.isfinite(C[:, 0, 0])
        assert ok.mean() > 0.9 and np.all(noise[ok] > 0)
        z.append(np.sum((q - truth)[ok] ** 2, axis=1) / np.trace(C[ok], axis1=1, axis2=2))
    z = np.concatenate(z)
    assert 0.6 < z.mean() < 1.6, z.mean()


def test_calibrate_camera_passes_renders_and_drops_a_moved_view(small_renders):
    """The renders calibrate with their RMS at the corners' noise; one view whose lower half of the board
    moved by 1 px during the exposure is dropped with its reason, stored in the result."""
    imgs = list(small_renders.images)
    cal = calibrate_camera(imgs, BOARD, 6.0)
    assert cal.noise_check is not None and not cal.noise_check.suspect and cal.noise_check.ratio < 1.5
    assert not cal.dropped and cal.geometry["tilt_deg_range"][1] > 30
    moved = imgs[2].copy()
    h = int(np.median(np.asarray(small_renders.truth["views"][2]["corners_px"])[:, 1]))
    moved[h:] = np.roll(moved[h:], 1, axis=1)
    cal2 = calibrate_camera(imgs[:2] + [moved] + imgs[3:], BOARD, 6.0)
    d = cal2.to_dict()
    assert list(d["views_dropped"]) == ["image 2"] and "the views' median" in d["views_dropped"]["image 2"]
    assert "image 2" not in cal2.used and d["views_skipped"]["image 2"].startswith("dropped: ")
    kept = calibrate_camera(imgs[:2] + [moved] + imgs[3:], BOARD, 6.0,
                            options=CameraCalibrationOptions(drop_outlier_views=False, keep_suspect=True))
    assert "image 2" in kept.used and kept.noise_check.suspect and kept.to_dict()["corner_noise_check"]["kept_by_request"]
    with pytest.raises(LightplaneError, match="suspect camera calibration: .* image 2 .*--keep-suspect"):
        calibrate_camera(imgs[:2] + [moved] + imgs[3:], BOARD, 6.0,
                         options=CameraCalibrationOptions(drop_outlier_views=False))


def test_face_on_renders_are_refused_in_words():
    """6 renders of a 5x5 board tilted under 0.5 deg: no focal length comes out; the error says why
    and what to do."""
    cap = BoardCapture(board=(5, 5), square_mm=6.0, distance_mm=(160.0, 220.0), tilt_deg=(0.0, 0.5), margin_px=10.0)
    ds = render_chessboard_dataset(6, 1, BoardOptions(difficulty="realistic", capture=cap), camera=SMALL)
    with pytest.raises(LightplaneError, match=r"focal length (is not determined|cannot be determined).*tilt the board"):
        calibrate_camera(list(ds.images), (5, 5), 6.0)


def test_cli_refuses_a_suspect_camera_then_keeps_it(small_renders, tmp_path):
    """calibrate-camera: a view moved half-way, kept (--keep-outlier-views), makes the camera suspect:
    exit 2, one line naming the view, nothing written; with --keep-suspect the file says so."""
    imgs = list(small_renders.images)
    h = int(np.median(np.asarray(small_renders.truth["views"][2]["corners_px"])[:, 1]))
    imgs[2] = imgs[2].copy()
    imgs[2][h:] = np.roll(imgs[2][h:], 1, axis=1)
    for i, im in enumerate(imgs):
        cv2.imwrite(str(tmp_path / f"v{i}.png"), im if im.ndim == 2 else cv2.cvtColor(im, cv2.COLOR_RGB2BGR))
    out = tmp_path / "cam.json"
    args = ("calibrate-camera", tmp_path / "v*.png", "--board", "7x5", "--square", "6", "-o", out,
            "--keep-outlier-views")
    line = one_error_line(lightplane(*args), "suspect camera calibration", "v2.png", "--keep-suspect")
    assert "corners' own noise predicts" in line and not out.exists()
    r = lightplane(*args, "--keep-suspect")
    assert r.returncode == 0, r.stderr
    d = json.loads(out.read_text())["calibration"]
    assert d["corner_noise_check"]["kept_by_request"] and d["corner_noise_check"]["suspect_views"] == [str(tmp_path / "v2.png")]
    assert "Corner noise check" in r.stdout and "suspect, kept by request" in r.stdout
