"""Motion as one rigid transform per frame (lightplane.motion.model) and the measure command's motion
forms; bad motion input (pose CSV of the wrong length, non-unit quaternions, a turntable file
of another camera, a sensor file without the laser named): one line, exit 2, nothing written."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _measure_synth import CAM, PLANE, stripe_image, surface  # noqa: E402

from lightplane.core.errors import LightplaneError  # noqa: E402
from lightplane.motion.model import Motion, Turntable, load_rigid, rotation_about  # noqa: E402
from lightplane.measure.pointcloud import read_cloud  # noqa: E402
from lightplane.measure.scan import ArrayFrames, scan_points  # noqa: E402
from lightplane.measure.options import MeasureOptions  # noqa: E402
from lightplane.stripe.options import StripeOptions  # noqa: E402

RNG = np.random.default_rng(5)
PTS = RNG.uniform(-50, 50, (20, 3)) + [0, 0, 450]
TABLE = Turntable.from_axis([10.0, 30.0, 470.0], [0.05, -0.95, -0.25])


def test_turntable_maps_a_point_fixed_to_the_table_to_one_place():
    o, B = TABLE.basis()
    assert np.allclose(B.T @ B, np.eye(3)) and np.isclose(np.linalg.det(B), 1.0)
    assert B[1, 2] < 0  # the axis points up (camera y points down)
    q = np.array([12.0, -5.0, 20.0])  # a point of the object, turntable frame
    m = Motion.turntable(TABLE, 7.5, start_deg=-15.0)
    for i in range(6):
        ang = np.deg2rad(-15.0 + 7.5 * i)
        # where the camera sees it after the table turned by ang (right-handed about the axis)
        p_cam = o + rotation_about(B[:, 2], ang) @ (B @ q)
        assert np.allclose(m.apply(i, p_cam[None])[0], q, atol=1e-9)
        R, t = m.transform(i)
        assert np.allclose(R @ p_cam + t, q, atol=1e-9)


def test_turntable_angles_from_csv_degrees_and_counts(tmp_path):
    f = tmp_path / "a.csv"
    f.write_text("frame,angle_deg\n0,10\n1,13.6\n2,17.2\n")
    a = Motion.load_turntable_angles(f, TABLE)
    b = Motion.turntable(TABLE, 3.6)
    assert a.n_frames == 3 and all(np.allclose(a.apply(i, PTS), b.apply(i, PTS)) for i in range(3))
    f.write_text("counts\n100\n164\n228\n")
    c = Motion.load_turntable_angles(f, TABLE, counts_per_rev=6400)
    assert np.isclose(c.angle_deg(2), 2 * 64 * 360 / 6400)
    with pytest.raises(LightplaneError, match="counts per revolution"):
        Motion.load_turntable_angles(f, TABLE)
    with pytest.raises(LightplaneError, match="no turntable angle"):
        c.transform(3)


def test_linear_motion_is_the_pure_translation_case_of_poses():
    lin = Motion.linear(0.7, [1.0, -2.0, 0.5])
    offs = np.array([lin.offset(i) for i in range(5)])
    poses = Motion.from_poses(np.repeat(np.eye(3)[None], 5, axis=0), -offs)
    for i in range(5):
        assert np.allclose(lin.apply(i, PTS), poses.apply(i, PTS), atol=1e-12)


def test_pose_csv_and_flange_composition(tmp_path):
    rot = Rotation.from_euler("xyz", RNG.uniform(-0.5, 0.5, (4, 3)))
    t = RNG.uniform(-100, 100, (4, 3))
    q = rot.as_quat()  # x, y, z, w
    f = tmp_path / "poses.csv"
    f.write_text("frame,qw,x,y,z,qx,qy,qz\n" + "".join(
        f"{i}," + ",".join(f"{v:.17g}" for v in (q[i, 3], *t[i], *q[i, :3])) + "\n" for i in range(4)))
    m = Motion.load_poses(f)
    for i in range(4):
        assert np.allclose(m.apply(i, PTS), PTS @ rot[i].as_matrix().T + t[i], atol=1e-9)
    # flange: T_object_cam = T_object_flange · T_flange_cam
    Rf, tf = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix(), np.array([5.0, -3.0, 80.0])
    hand_eye = tmp_path / "he.json"
    hand_eye.write_text(json.dumps({"T_flange_cam": {"R": Rf.tolist(), "t_mm": tf.tolist()}}))
    mf = Motion.load_poses(f, flange=load_rigid(hand_eye))
    for i in range(4):
        p_flange = PTS @ Rf.T + tf
        assert np.allclose(mf.apply(i, PTS), p_flange @ rot[i].as_matrix().T + t[i], atol=1e-9)
    f.write_text("x,y,z,qx,qy,qz,qw\n0,0,0,0,0,0,1\n1,2,3,0.1,0,0,1\n")
    with pytest.raises(LightplaneError, match=r"row 3: quaternion .* norm 1.00499"):
        Motion.load_poses(f)
    f.write_text("x,y,z,qx,qy,qz\n0,0,0,0,0,0\n")
    with pytest.raises(LightplaneError, match="missing qw"):
        Motion.load_poses(f)


def test_scan_points_with_poses_equals_the_linear_scan():
    n_s, d_s = surface()
    frames = [stripe_image(n_s, d_s, shift_px=0.3 * k)[0].astype(np.float32) for k in range(3)]
    lin = Motion.linear(1.5, [1, 0, 0])
    offs = np.array([lin.offset(i) for i in range(3)])
    a, _ = scan_points(ArrayFrames(frames), CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5)), motion=lin)
    b, _ = scan_points(ArrayFrames(frames), CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5)),
                       motion=Motion.from_poses(np.repeat(np.eye(3)[None], 3, 0), -offs))
    assert a.size > 100 and np.array_equal(a.view(np.uint8), b.view(np.uint8))


# ----------------------------------------------------------------------------- command line
def run(*args):
    return subprocess.run([sys.executable, "-m", "lightplane", *map(str, args)], capture_output=True, text=True,
                          timeout=300)


def one_error_line(r) -> str:
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    assert len(lines) == 1 and lines[0].startswith("lightplane: error:"), r.stderr
    return lines[0]


@pytest.fixture(scope="module")
def scan_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("motion")
    CAM.save_json(d / "camera.json")
    PLANE.save(d / "plane.json")
    n_s, d_s = surface()
    (d / "frames").mkdir()
    for k in range(3):
        img, _ = stripe_image(n_s, d_s, shift_px=0.25 * k)
        cv2.imwrite(str(d / "frames" / f"f{k:02d}.png"), np.clip(np.rint(img), 0, 255).astype(np.uint8))
    (d / "poses.csv").write_text("x,y,z,qx,qy,qz,qw\n" + "0,0,0,0,0,0,1\n" * 3)
    TABLE_CAM = Turntable.from_axis(TABLE.point_mm, TABLE.direction, camera=CAM.to_dict())
    TABLE_CAM.save(d / "tt.json")
    return d


def test_measure_poses_and_turntable_and_sensor(scan_dir):
    d = scan_dir
    r = run("measure", d / "frames", "--camera", d / "camera.json", "--plane", d / "plane.json", "--poses",
            d / "poses.csv", "-o", d / "p.npy")
    assert r.returncode == 0, r.stderr
    r = run("measure", d / "frames", "--camera", d / "camera.json", "--plane", d / "plane.json", "-o", d / "c.npy")
    assert np.array_equal(read_cloud(d / "p.npy").view(np.uint8), read_cloud(d / "c.npy").view(np.uint8))  # identity poses
    r = run("measure", d / "frames", "--camera", d / "camera.json", "--plane", d / "plane.json", "--turntable",
            d / "tt.json", "--turntable-step", "5", "-o", d / "t.npy")
    assert r.returncode == 0, r.stderr
    cam_pts, t_pts = read_cloud(d / "c.npy"), read_cloud(d / "t.npy")
    m = Motion.turntable(Turntable.load(d / "tt.json"), 5.0)
    for i in range(3):
        s = cam_pts["frame"] == i
        p = np.column_stack([cam_pts["x"][s], cam_pts["y"][s], cam_pts["z"][s]]).astype(float)
        q = np.column_stack([t_pts["x"][s], t_pts["y"][s], t_pts["z"][s]]).astype(float)
        assert np.allclose(m.apply(i, p), q, atol=1e-3)
    # a sensor file, two "lasers" (the same plane), one merged cloud with the laser attribute
    (d / "p2.json").write_text(json.dumps({**json.loads((d / "plane.json").read_text()), "laser": "right"}))
    r = run("sensor", "-o", d / "s.json", "--camera", d / "camera.json", "--plane", f"left={d / 'plane.json'}",
            "--plane", d / "p2.json", "--turntable", d / "tt.json")
    assert r.returncode == 0, r.stderr
    s = json.loads((d / "s.json").read_text())
    assert set(s["planes"]) == {"left", "right"} and s["turntable"] is not None and "provenance" in s
    r = run("measure", "--sensor", d / "s.json", "--laser", f"left={d / 'frames'}", "--laser",
            f"right={d / 'frames' / 'f0[01].png'}", "--turntable-step", "5", "-o", d / "m.ply")
    assert r.returncode == 0, r.stderr
    merged = read_cloud(d / "m.ply")
    assert set(np.unique(merged["laser"]).tolist()) == {0, 1}
    a = merged[merged["laser"] == 0]
    assert a.size == t_pts.size and np.allclose(a["x"], t_pts["x"]) and np.allclose(a["z"], t_pts["z"])
    assert np.count_nonzero(merged["laser"] == 1) == np.count_nonzero(t_pts["frame"] < 2)


@pytest.mark.parametrize("case", ["short_poses", "non_unit", "other_camera", "missing_laser", "poses_columns"])
def test_bad_motion_input_one_line_exit_2_nothing_written(scan_dir, tmp_path, case):
    d = scan_dir
    base = ["measure", d / "frames", "--camera", d / "camera.json", "--plane", d / "plane.json"]
    out = tmp_path / "out.ply"
    if case == "short_poses":
        f = tmp_path / "p.csv"
        f.write_text("x,y,z,qx,qy,qz,qw\n0,0,0,0,0,0,1\n0,0,1,0,0,0,1\n")
        msg = one_error_line(run(*base, "--poses", f, "-o", out))
        assert "the poses give 2 frames but the input has 3" in msg
    elif case == "non_unit":
        f = tmp_path / "p.csv"
        f.write_text("x,y,z,qx,qy,qz,qw\n0,0,0,0,0,0,1\n0,0,1,0,0,0,2\n0,0,2,0,0,0,1\n")
        msg = one_error_line(run(*base, "--poses", f, "-o", out))
        assert "row 3" in msg and "norm 2" in msg
    elif case == "poses_columns":
        f = tmp_path / "p.csv"
        f.write_text("0,0,0,0,0,1\n" * 3)
        assert "7 numbers" in one_error_line(run(*base, "--poses", f, "-o", out))
    elif case == "other_camera":
        other = json.loads((d / "camera.json").read_text())
        other["K"][0][0] += 5.0
        tt = json.loads((d / "tt.json").read_text())
        tt["camera"] = other
        (tmp_path / "tt.json").write_text(json.dumps(tt))
        msg = one_error_line(run(*base, "--turntable", tmp_path / "tt.json", "--turntable-step", "3", "-o", out))
        assert "another camera" in msg
        msg = one_error_line(run("sensor", "-o", tmp_path / "s.json", "--camera", d / "camera.json", "--plane",
                                 d / "plane.json", "--turntable", tmp_path / "tt.json"))
        assert "another camera" in msg
    else:
        run("sensor", "-o", tmp_path / "s.json", "--camera", d / "camera.json", "--plane", f"a={d / 'plane.json'}")
        msg = one_error_line(run("measure", "--sensor", tmp_path / "s.json", "--laser", f"a={d / 'frames'}",
                                 "--laser", f"b={d / 'frames'}", "-o", out))
        assert "no laser named 'b'" in msg and "a" in msg
    assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_a_linear_step_beyond_any_scan_is_refused():
    """A step of 1e308 mm turned the second frame's points into inf in the cloud (float32): refused in one line."""
    for bad in (1e308, -2e6, float("nan")):
        with pytest.raises(LightplaneError, match="step must be a finite number of mm"):
            Motion.linear(bad, [1, 0, 0])
    assert Motion.linear(-1e6, [1, 0, 0]).step_mm == -1e6
