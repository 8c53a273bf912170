"""`lightplane calibrate-plane --joint-camera`: a run on small renders (6 chessboard views, 5 circle
images) against the renderer's exact camera and plane, and bad input (exit 2, one line, nothing written)."""

from __future__ import annotations

from dataclasses import replace
import json

import numpy as np
import pytest

from lightplane import Camera, LightPlane
from lightplane.plane.model import check_camera

from _cli import lightplane, one_error_line
from _renders import cached_render
from _renders import cached_circle_render


@pytest.fixture(scope="module")
def boards():
    import lightplane.simulate.render as R

    return cached_render("boards_9x7_realistic_n6_s21",
                         lambda: R.render_chessboard_dataset(6, 21, R.BoardOptions(
                             difficulty="realistic", capture=replace(R.CALIBRATION_CAPTURE, board=(9, 7), square_mm=8.0))))


def _run(circles, *extra):
    return lightplane("calibrate-plane", circles, "--diameter", "50", *extra)


def test_joint_run_writes_camera_and_plane_within_their_covariance(boards, tmp_path):
    circles = cached_circle_render()
    out, cam_out = tmp_path / "plane.json", tmp_path / "cam.json"
    r = _run(circles, "--joint-camera", boards / "*.png", "--board", "9x7", "--square", "8", "--camera-out", cam_out,
             "-o", out)
    assert r.returncode == 0, r.stderr
    assert "two-step" in r.stdout and "joint refinement" in r.stdout and "σ of a ray" in r.stdout
    truth = json.loads((circles / "truth.json").read_text())
    plane_true = LightPlane.from_dict(truth["plane"])
    cam_true = Camera.load(circles / "camera.json")  # the renderer's exact camera
    cam, plane = Camera.load(cam_out), LightPlane.load(out)
    assert cam.covariance is not None and plane.meta.get("camera_jacobian")
    assert check_camera(plane, cam) is None  # the plane records the refined camera, not the starting one
    d = json.loads(out.read_text())
    assert d["provenance"]["options"]["joint_camera"].endswith("*.png")
    assert "camera's share is not included" not in json.dumps(d["uncertainty"])
    c = json.loads(cam_out.read_text())
    assert "joint_refinement" in c["calibration"] and c["provenance"]["options"]["board"]
    # the joint dispersion: printed, recorded with the camera and the plane, and named by what the sigmas cover
    jr = c["calibration"]["joint_refinement"]
    psi = jr["joint_dispersion"]
    assert jr["joint_dispersion_applied"] and psi > 0 and f"x{psi:.2f}" in jr["covariance_covers"]
    assert f"joint dispersion ×{psi:.2f}" in r.stdout
    assert plane.meta["joint_dispersion"] == psi and plane.meta["joint_dispersion_applied"]
    assert f"joint problem's dispersion x{psi:.2f}" in d["uncertainty"]["covers"]["shape_sigma_rms_mm"]
    # the plane's offset at the axis against its total sigma (plane's own + the intrinsics' share)
    C = np.asarray(plane.covariance) + np.asarray(plane.meta["camera_jacobian"]["covariance_camera"])
    h = np.append(plane_true.point_on_axis(), 1.0)
    off = float(plane.signed_distance(plane_true.point_on_axis()[None])[0])
    assert abs(off) < 4 * np.sqrt(h @ C @ h), (off, np.sqrt(h @ C @ h))
    # the principal point against its joint sigma
    for k, v in (("cx", 2), ("cy", 3)):
        err = getattr(cam, k) - getattr(cam_true, k)
        assert abs(err) < 4 * np.sqrt(cam.covariance[v, v]), (k, err)


@pytest.mark.parametrize("case", ["no_glob_match", "no_board", "no_camera_out", "with_camera", "no_board_spec",
                                  "board_without_joint", "method", "no_camera_at_all"])
def test_joint_bad_input_one_line_exit_2_nothing_written(boards, tmp_path, case):
    circles = cached_circle_render()
    out, cam_out = tmp_path / "plane.json", tmp_path / "cam.json"
    base = ["--board", "9x7", "--square", "8", "-o", out]
    if case == "no_glob_match":
        r = _run(circles, "--joint-camera", tmp_path / "none_*.png", "--camera-out", cam_out, *base)
        msg = "no images found"
    elif case == "no_board":  # circle images given as the chessboards
        r = _run(circles, "--joint-camera", circles / "*.png", "--camera-out", cam_out, *base)
        msg = "board not found"
    elif case == "no_camera_out":
        r = _run(circles, "--joint-camera", boards / "*.png", *base)
        msg = "--camera-out"
    elif case == "with_camera":
        r = _run(circles, "--joint-camera", boards / "*.png", "--camera", circles / "camera.json", "--camera-out",
                 cam_out, *base)
        msg = "not both"
    elif case == "no_board_spec":
        r = _run(circles, "--joint-camera", boards / "*.png", "--camera-out", cam_out, "-o", out)
        msg = "--board"
    elif case == "board_without_joint":
        r = _run(circles, "--camera", circles / "camera.json", *base)
        msg = "only with --joint-camera"
    elif case == "method":
        r = _run(circles, "--joint-camera", boards / "*.png", "--camera-out", cam_out, "--method", "global", *base)
        msg = "--method ml"
    else:
        r = _run(circles, "-o", out)
        msg = "give --camera FILE"
    one_error_line(r, msg)
    assert not out.exists() and not cam_out.exists()
