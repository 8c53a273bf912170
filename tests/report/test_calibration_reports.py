"""Reports of the camera, board-plane, turntable and refinement calibrations, from their result files.

Every input is built in closed form with known truth (board poses projected through a known camera,
stripe points on a known plane, board origins turned about a known axis, two scans of one object),
so the report's verdict and tables are checked against numbers computed here; the pages are
self-contained and render in headless Chromium.
"""

from __future__ import annotations

import json
import math
import re
import shutil
import subprocess
from types import SimpleNamespace

import numpy as np
import pytest

from lightplane import Camera, LightPlane
from lightplane.camera.board_pose import pose_from_corners
from lightplane.core.errors import LightplaneError
from lightplane.measure.sensor import Sensor
from lightplane.motion.model import Turntable, rotation_about
from lightplane.motion.turntable_refine import TurntableScan, refine_turntable
from lightplane.plane.zhou import plane_from_board_stripes
from lightplane.report.calibrations import (board_plane_report_inputs, calibration_report_html, camera_report_inputs,
                                            refine_report_inputs, report_kind, write_calibration_report)

from _board_scenes import BOARD, CAM as PINHOLE_Z, SQ, board_xy, rot, scene, vertical_plane
from _cli import lightplane, one_error_line

F = 1200.0
PINHOLE = Camera([[F, 0, 640], [0, F, 480], [0, 0, 1]], [0.0, 0, 0, 0, 0], 1280, 960)
OBJ = np.column_stack([board_xy(), np.zeros(BOARD[0] * BOARD[1])])


def _verdict(page: str) -> str:
    m = re.search(r"<p class=verdict>(.*?)</p>", page, re.S)
    assert m, "no verdict line"
    return m.group(1).replace("&#x27;", "'")


def _camera_file(tmp_path, poses, noise_px, camera=PINHOLE, name="cam.json"):
    """A camera file with report inputs: the board seen in each pose (R, t), corners with the given noise."""
    import cv2

    rng = np.random.default_rng(3)
    corners, res, rv, tv, rms, names = [], [], [], [], [], []
    for k, ((R, t), s) in enumerate(zip(poses, noise_px)):
        uv = camera.project(OBJ @ R.T + t)
        r = rng.normal(scale=s, size=uv.shape)
        corners.append(uv + r)
        res.append(r)
        rv.append(cv2.Rodrigues(R)[0])
        tv.append(np.asarray(t, float).reshape(3, 1))
        rms.append(float(np.sqrt(np.mean(np.sum(r ** 2, axis=1)))))
        names.append(f"views/view_{k:02d}.png")
    result = SimpleNamespace(used=tuple(names), corners_uv=corners, residuals_px=res, rvecs=rv, tvecs=tv,
                             per_view_rms_px=np.array(rms))
    all_rms = float(np.sqrt(np.mean(np.concatenate([np.sum(r ** 2, axis=1) for r in res]))))
    cam = Camera(camera.K, camera.dist, camera.width, camera.height, rms_px=all_rms,
                 covariance=camera.covariance, covariance_params=camera.covariance_params)
    path = tmp_path / name
    cam.save_json(path, extra={"calibration": {"std": {"fx": 0.5, "fy": 0.5}, "warnings": [],
                                                "views_skipped": {"views/blur.png": "board not found"}},
                               "report_inputs": camera_report_inputs(result)})
    return path, rms, all_rms


def _tilted_poses(n=8, tilt=30.0):
    out = []
    for k in range(n):
        a = 2 * math.pi * k / n
        R = rot(tilt * math.cos(a), tilt * math.sin(a), 5.0 * k)
        c = np.array([40.0, 25.0, 0.0])  # the board's centre in its frame
        t = np.array([150 * math.cos(a), 110 * math.sin(a), 450.0]) - R @ c
        out.append((R, t))
    return out


def test_camera_report_verdict_coverage_tilts_and_outlier(tmp_path):
    poses = _tilted_poses()
    noise = [0.1] * 7 + [0.8]  # the last view 8x the others: flagged by name
    path, rms, all_rms = _camera_file(tmp_path, poses, noise)
    assert report_kind(json.loads(path.read_text())) == "camera"
    page = calibration_report_html(path)
    v = _verdict(page)
    assert v.startswith("Good for measuring at about") and f"{all_rms:.3f} px over 8 views" in v
    assert "view_07.png" in v and f"{rms[7]:.3f} px" in v and "What limits it" in v
    # the tilts in the table: each pose's tilt about the camera's x and y axes, as built
    for k, (R, _) in enumerate(poses):
        n = R[:, 2] if R[2, 2] < 0 else -R[:, 2]
        tx, ty = math.degrees(math.atan2(n[1], -n[2])), math.degrees(math.atan2(n[0], -n[2]))
        assert f"{tx:+.1f}, {ty:+.1f}" in page
        assert f"{rms[k]:.4f}" in page
    assert "blur.png" in page and "board not found" in page  # the view not used, with its reason
    assert len(re.findall(r'src="data:image/png;base64,', page)) == 3  # coverage, per view, over the image
    assert "http://" not in page and "<script" not in page


def test_camera_report_fronto_parallel_boards_are_named_as_the_limit(tmp_path):
    poses = [(rot(0.2 * k, -0.2 * k, 3.0 * k), np.array([-40.0 + 10 * k, -25.0, 450.0])) for k in range(6)]
    path, _, _ = _camera_file(tmp_path, poses, [0.1] * 6)
    v = _verdict(calibration_report_html(path))
    assert "face the camera" in v and "tilt the board 20–40 deg" in v
    # coverage: the boards' union in the image, against the exact area of the projected rectangles
    import cv2

    mask = np.zeros((960, 1280), np.uint8)
    for R, t in poses:
        uv = PINHOLE.project(OBJ @ R.T + t)
        cv2.fillPoly(mask, [np.round(cv2.convexHull(uv.astype(np.float32))[:, 0]).astype(np.int32)], 1)
    truth = 100 * mask.mean()
    got = float(re.search(r"the boards cover (\d+) %", v).group(1))
    assert abs(got - truth) <= 1.5, (got, truth)


def test_camera_report_sigma_map_matches_a_principal_point_covariance(tmp_path):
    """σ(cx) = σ(cy) = 1 px alone: a ray's direction is uncertain by √2 px / f at the centre (two independent
    directions), less towards the edges (cos² of the ray's angle)."""
    names = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    cov = np.zeros((9, 9))
    cov[2, 2] = cov[3, 3] = 1.0
    cam = Camera(PINHOLE.K, PINHOLE.dist, 1280, 960, covariance=cov, covariance_params=names)
    path, _, _ = _camera_file(tmp_path, _tilted_poses(), [0.1] * 8, camera=cam)
    page = calibration_report_html(path)
    v = _verdict(page)
    deg = float(re.search(r"direction σ ([0-9.]+) deg RMS", v).group(1))
    centre = math.degrees(math.sqrt(2) / F)
    assert 0.8 * centre < deg <= 1.001 * centre, (deg, centre)
    assert "Ray σ map" in page and len(re.findall(r'src="data:image/png;base64,', page)) == 4


def _zhou_calibration(shift_px=0.0, noise_px=0.05):
    rng = np.random.default_rng(5)
    plane = vertical_plane(np.array([0.0, 0.0, 450.0]))
    poses, stripes = [], []
    specs = [((12, -18, 4), (-40, -25, 430)), ((-15, 20, -3), (-45, -20, 470)), ((25, 5, 8), (-35, -30, 500)),
             ((-8, -28, 2), (-50, -22, 410)), ((18, 22, -6), (-42, -28, 455))]
    for k, (ang, t) in enumerate(specs):
        R, t = rot(*ang), np.array(t, float)
        corners, stripe, _ = scene(R, t, plane, n_stripe=200)
        pose = pose_from_corners(PINHOLE_Z, corners, BOARD, SQ, name=f"boards/board_{k}.png")
        s = stripe + rng.normal(scale=noise_px, size=stripe.shape)
        if k == 4:
            s[:, 0] += shift_px
        poses.append(pose)
        stripes.append(s)
    return plane_from_board_stripes(PINHOLE_Z, poses, stripes), plane


def _plane_file(tmp_path, z, name="plane.json"):
    path = tmp_path / name
    z.plane.save(path, extra={"report_inputs": board_plane_report_inputs(z, PINHOLE_Z),
                              "working_volume": {"depth_mm": [float(z.points_cam_mm[:, 2].min()),
                                                              float(z.points_cam_mm[:, 2].max())],
                                                 "centre_mm": z.points_cam_mm.mean(axis=0).tolist()}})
    return path


def test_board_plane_report_numbers_and_an_offset_board(tmp_path):
    z, truth = _zhou_calibration(shift_px=3.0)
    path = _plane_file(tmp_path, z)
    assert report_kind(json.loads(path.read_text())) == "board_plane"
    page = calibration_report_html(path)
    v = _verdict(page)
    n = len(z.points_cam_mm)
    assert f"its {n} stripe points on 5 boards to {z.residual_rms_mm * 1e3:.1f} µm RMS" in v
    lo, hi = z.points_cam_mm[:, 2].min(), z.points_cam_mm[:, 2].max()
    assert f"points {lo:.0f}–{hi:.0f} mm from the camera" in v
    # the shifted board: its points' RMS distance to the plane, flagged in the verdict by name
    per = [float(np.sqrt(np.mean(z.residual_mm[z.view_index == k] ** 2))) for k in range(5)]
    assert max(per) == per[4] and per[4] > 3 * np.median(per)
    assert "board_4.png" in v and f"{per[4] * 1e3:.0f} µm RMS" in v
    for k in range(5):
        assert f"{per[k] * 1e3:.1f}" in page
    assert "Point σ map" in page and len(re.findall(r'src="data:image/png;base64,', page)) == 4


def test_board_plane_report_clean_boards_nothing_limits(tmp_path):
    z, _ = _zhou_calibration()
    v = _verdict(calibration_report_html(_plane_file(tmp_path, z)))
    assert "Nothing obvious limits it: 5 boards" in v


def test_board_plane_file_without_inputs_is_refused(tmp_path):
    z, _ = _zhou_calibration()
    z.plane.save(tmp_path / "old.json")
    with pytest.raises(LightplaneError, match="no stored report inputs"):
        calibration_report_html(tmp_path / "old.json")
    r = lightplane("report", tmp_path / "old.json", "--out", tmp_path / "rep")
    one_error_line(r, "calibrate-plane-board")
    assert not (tmp_path / "rep").exists()


def _turntable_file(tmp_path, sigma_mm=0.1):
    """A turntable file as calibrate-turntable writes it: the board origin turned about a known axis in 20 deg
    steps; the axis point's covariance σ_mm across the axis (x of the turntable frame) only."""
    table = Turntable.from_axis([10.0, 40.0, 420.0], [0.02, -0.96, -0.28])
    o, B = table.basis()
    cov = np.zeros((6, 6))
    cov[:3, :3] = sigma_mm ** 2 * np.outer(B[:, 0], B[:, 0])
    images = []
    for k in range(9):
        a = math.radians(20.0 * k)
        local = np.array([60 * math.cos(a), 60 * math.sin(a), 15.0])
        images.append({"name": f"tt/turn_{k}.png", "used": True, "angle_deg": 20.0 * k, "pnp_rms_px": 0.2,
                       "circle_rms_mm": 0.01 + (0.2 if k == 5 else 0.0), "t_cam_board_mm": (o + B @ local).tolist()})
    meta = {"images": images, "angle_span_deg": 160.0, "sense_of_the_images": "counter-clockwise seen from above",
            "agreement": {"angle_deg": 0.01, "distance_mm": 0.02},
            "jackknife": {"sigma_direction_deg_circles": 0.01, "sigma_point_mm_circles": sigma_mm,
                          "covers": "pose noise of the images given"},
            "quality": {"verdict": "ok"}, "circle_rms_mm": 0.03, "skipped": {"tt/dark.png": "board not found"}}
    tt = Turntable(table.point_mm, table.direction, covariance=cov, camera=PINHOLE.to_dict(), meta=meta)
    path = tmp_path / "tt.json"
    tt.save(path)
    return path


def test_turntable_report_axis_sigma_as_a_point_error(tmp_path):
    """A point turned half a turn about an axis whose position is off by δ across it moves by 2δ: σ 0.2 mm."""
    path = _turntable_file(tmp_path, sigma_mm=0.1)
    d = json.loads(path.read_text())
    assert report_kind(d) == "turntable"
    page = calibration_report_html(path)
    v = _verdict(page)
    assert "moves by σ 200 µm" in v and "within about 90 mm of the axis" in v  # 1.5 x the 60 mm radius
    assert "turn_5.png" in v  # its circle residual far above the others
    assert v.startswith("Good for merging")
    d["quality"] = {"verdict": "elevated", "direction_sigmas": 4.2, "position_sigmas": 1.0}  # 3-10 σ apart
    path.write_text(json.dumps(d))
    v = _verdict(calibration_report_html(path))
    assert v.startswith("Usable with care (its checks lie above their noise) for merging") and "4.2 and 1.0 times" in v
    assert "dark.png" in page and "board not found" in page
    assert len(re.findall(r'src="data:image/png;base64,', page)) == 2


def _scans(n=12000, seed=0):
    rng = np.random.default_rng(seed)
    table = Turntable.from_axis([5.0, 30.0, 320.0], [0.05, -0.95, -0.3])
    o, B = table.basis()
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    th = np.arctan2(u[:, 1], u[:, 0])
    obj = u * (20 + 3 * np.cos(3 * th + 0.5))[:, None] + [6.0, 0.0, 25.0]
    scans = []
    for li, (tilt, start) in enumerate(((25.0, 0.0), (-25.0, 131.0))):
        nrm = rotation_about(table.direction, np.deg2rad(tilt)) @ np.cross(table.direction, B[:, 0])
        pts, frames = [], []
        for f in range(20):
            cam = (obj @ rotation_about([0, 0, 1.0], np.deg2rad(start + 18.0 * f)).T) @ B.T + o
            p = cam[np.abs((cam - o) @ nrm) < 0.3]
            pts.append(p + rng.normal(scale=0.02, size=p.shape))
            frames.append(np.full(len(p), f))
        scans.append(TurntableScan(f"laser{li}", np.concatenate(pts), np.concatenate(frames), 18.0))
    given = Turntable.from_axis(table.point_mm + [1.0, 0, 0], table.direction)
    return given, scans


def test_refine_report_states_the_agreement_before_and_after(tmp_path):
    given, scans = _scans()
    r = refine_turntable(given, scans, rounds=2)
    tt = r.turntable
    tt.meta["refined_from_scans"] = {
        "scans": [{"laser": s.name, "frames": f"scan{k}", "start_deg": a} for k, (s, a) in enumerate(zip(scans, r.start_deg))],
        "step_deg": 18.0, "agreement_before_mm": r.before, "agreement_searched_mm": r.searched,
        "agreement_after_mm": r.after, "axis_moved_deg": r.axis_moved_deg, "axis_moved_mm": r.axis_moved_mm,
        "report_inputs": refine_report_inputs(scans, given, r)}
    path = tmp_path / "s2.json"
    Sensor(PINHOLE, {"laser0": LightPlane([1.0, 0, 0], -5.0), "laser1": LightPlane([1.0, 0, 0], -5.0)}, tt).save(path)
    assert report_kind(json.loads(path.read_text())) == "refine"
    page = calibration_report_html(path)
    v = _verdict(page)
    a, b = r.after, r.before
    assert f"agree to {a['median_mm']:.3f} mm median and {a['p90_mm']:.3f} mm" in v
    assert f"against {b['median_mm']:.3f} / {b['p90_mm']:.3f} mm" in v and "no covariance" in v
    assert f"{r.start_deg[1]:.3f} deg" in page and len(re.findall(r'src="data:image/png;base64,', page)) == 1
    ri = json.loads(path.read_text())["turntable"]["refined_from_scans"]["report_inputs"]
    assert len(ri["after_mm"][0]) == min(4000, len(scans[0].points_cam))  # an even subsample of each scan


def test_cli_report_refuses_overwrite_and_every_kind_renders_in_chromium(tmp_path):
    cam, _, _ = _camera_file(tmp_path, _tilted_poses(), [0.1] * 8)
    r = lightplane("report", cam, "--out", tmp_path / "rep_camera")
    assert r.returncode == 0, r.stderr
    page = (tmp_path / "rep_camera" / "index.html").read_text()
    assert "class=verdict" in page and (tmp_path / "rep_camera" / "index.html").stat().st_mode & 0o044 == 0o044
    one_error_line(lightplane("report", cam, "--out", tmp_path / "rep_camera"), "already exists")
    assert (tmp_path / "rep_camera" / "index.html").read_text() == page
    (tmp_path / "x.json").write_text("{}")
    with pytest.raises(LightplaneError, match="not a camera, plane, turntable or sensor file"):
        write_calibration_report(tmp_path / "x.json", tmp_path / "rep_x")
    z, _ = _zhou_calibration()
    pages = [tmp_path / "rep_camera" / "index.html",
             write_calibration_report(_plane_file(tmp_path, z), tmp_path / "rep_plane"),
             write_calibration_report(_turntable_file(tmp_path), tmp_path / "rep_tt")]
    exe = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome", "headless_shell")
                if shutil.which(n)), None)
    if exe is None:
        pytest.skip("headless Chromium is not installed")
    import cv2

    for k, p in enumerate(pages):
        shot = tmp_path / f"shot{k}.png"
        r = subprocess.run([exe, "--headless", "--disable-gpu", "--no-sandbox", f"--screenshot={shot}",
                            "--window-size=1200,2400", p.as_uri()], capture_output=True, timeout=120)
        assert r.returncode == 0, r.stderr[-500:]
        img = cv2.imread(str(shot))
        assert img is not None and img.std() > 10  # not a blank page


def test_camera_report_needs_a_json_camera_file(tmp_path):
    r = lightplane("calibrate-camera", tmp_path / "x.png", "--board", "9x6", "--square", "10", "-o",
                   tmp_path / "c.yaml", "--report", tmp_path / "rep")
    one_error_line(r, "--report", "c.yaml")
    assert not (tmp_path / "c.yaml").exists() and not (tmp_path / "rep").exists()
