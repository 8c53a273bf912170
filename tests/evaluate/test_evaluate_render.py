"""Rendered chessboards with the stripe (lightplane.simulate.render): cross-ratio ideal points,
Zhou's plane and the `evaluate` / `calibrate-plane-board` commands against the renderer's truth.

Five board poses, each with a laser-off companion frame (4x4 samples per pixel, 8 per
edge: a few seconds).  At ~8 px/mm the corners (≈0.04 px RMS) and the stripe line
put the ideal points within 0.01 mm and Zhou's plane within 0.01 deg.
"""

from __future__ import annotations

from dataclasses import replace
import json
from types import SimpleNamespace

import numpy as np
import pytest

from lightplane import LightPlane
from lightplane.plane.zhou import board_views_and_stripes, plane_from_board_stripes
from lightplane.evaluate.crossratio import evaluate_views

BOARD = (9, 6)


@pytest.fixture(scope="module")
def dataset():
    from lightplane.simulate.render import STRIPE_CAPTURE, BoardOptions, render_chessboard_dataset

    ds = render_chessboard_dataset(5, 11, BoardOptions(
        capture=replace(STRIPE_CAPTURE, board=BOARD, square_mm=8.0), with_stripe=True, laser_off=True, samples=4,
        edge_samples=8))
    on = [im for im, n in zip(ds.images, ds.names) if "_off" not in n]
    off = [im for im, n in zip(ds.images, ds.names) if "_off" in n]
    return ds, on, off


@pytest.fixture(scope="module")
def detected(dataset):
    ds, on, off = dataset
    sq = ds.truth["board"]["square_mm"]
    poses, stripes, _ = board_views_and_stripes(on, ds.camera, board=BOARD, square_mm=sq, background_images=off)
    return poses, stripes


def _to_truth_board(pose, view, sq):
    """The detected board frame may be the true one turned by 180 deg (corner order from the far
    corner); return (F, o) with p_true = F p_detected + o, from the corners themselves."""
    cols, rows = BOARD
    if np.linalg.norm(pose.corners_uv[0] - np.asarray(view["corners_px"])[0]) < 1.0:
        return np.eye(3), np.zeros(3)
    assert np.linalg.norm(pose.corners_uv[0] - np.asarray(view["corners_px"])[-1]) < 1.0
    return np.diag([-1.0, -1.0, 1.0]), np.array([(cols - 1) * sq, (rows - 1) * sq, 0.0])


@pytest.fixture(scope="module")
def detected_without_laser_off(dataset):
    ds, on, _ = dataset
    poses, stripes, _ = board_views_and_stripes(on, ds.camera, board=BOARD, square_mm=ds.truth["board"]["square_mm"])
    return poses, stripes


@pytest.mark.parametrize("frames", ["laser-off frames", "laser-on only"])
def test_ideal_points_match_truth(dataset, detected, detected_without_laser_off, frames):
    """Without laser-off frames the corners the stripe runs over are left out (they move by
    up to ~0.5 px); with them, the board is found in the laser-off frame."""
    ds, _, _ = dataset
    poses, stripes = detected if frames == "laser-off frames" else detected_without_laser_off
    if frames == "laser-on only":
        left_out = [0 if p.corner_ok is None else np.count_nonzero(~p.corner_ok) for p in poses]
        assert max(left_out) < 20 and sum(left_out) > 0, left_out
    sq = ds.truth["board"]["square_mm"]
    truth = LightPlane.from_dict(ds.truth["plane"])
    ev = evaluate_views(ds.camera, [truth], poses, stripes, board=BOARD, square_mm=sq)
    assert len(set(ev.view_index.tolist())) == 5 and len(ev.pairs) >= 10
    errs = []
    for k, view in enumerate(ds.truth["views"]):
        R, t = np.asarray(view["T_cam_board"]["R"]), np.asarray(view["T_cam_board"]["t"])
        F, o = _to_truth_board(poses[k], view, sq)
        pb = ev.ideal_board_mm[ev.view_index == k] @ F.T + o
        # the true plane/board line in true board coordinates: m . (x, y) + e = 0
        m, e = R.T @ truth.normal, truth.normal @ t + truth.d
        on_row = np.isclose(pb[:, 1] / sq, np.round(pb[:, 1] / sq), atol=1e-9)
        assert on_row.all()  # rows in this data set: the ideal point's y is exact, x is measured
        errs.append(pb[:, 0] + (m[1] * pb[:, 1] + e) / m[0])
    errs = np.concatenate(errs)
    assert np.max(np.abs(errs)) < 0.01, errs


@pytest.mark.parametrize("frames", ["laser-off frames", "laser-on only"])
def test_zhou_plane_matches_truth(dataset, detected, detected_without_laser_off, frames):
    ds, _, _ = dataset
    truth = LightPlane.from_dict(ds.truth["plane"])
    res = plane_from_board_stripes(ds.camera, *(detected if frames == "laser-off frames" else detected_without_laser_off))
    assert np.degrees(res.plane.angle_to(truth)) < 0.01
    assert abs(res.plane.d - truth.d) < 0.05  # mm, at ~500 mm
    # stripe centres good to ~0.2 px at ~8 px/mm: residuals of a few hundredths of a mm
    assert res.residual_rms_mm < 0.03
    assert [im["used"] for im in res.plane.meta["images"]] == [True] * 5


@pytest.fixture(scope="module")
def circle_plane(dataset):
    """The light plane calibrated the paper's way (lightplane.plane.calibrate.calibrate_plane) from 8
    rendered images of the circular target, same camera and plane as the chessboard renders."""
    from lightplane.plane.calibrate import PlaneCalibrationOptions, calibrate_plane
    from lightplane.simulate.render import CircleOptions, render_circle_dataset

    ds, _, _ = dataset
    truth = LightPlane.from_dict(ds.truth["plane"])
    circ = render_circle_dataset(8, 2, CircleOptions(diameter_mm=50.0), camera=ds.camera, plane=truth)
    return calibrate_plane(circ.images, circ.camera, 50.0, options=PlaneCalibrationOptions(workers=1)).plane


def test_circle_and_zhou_side_by_side(dataset, detected, circle_plane):
    ds, _, _ = dataset
    zhou = plane_from_board_stripes(ds.camera, *detected).plane
    ev = evaluate_views(ds.camera, [circle_plane, zhou], *detected, board=BOARD,
                        square_mm=ds.truth["board"]["square_mm"], labels=["circle", "zhou"])
    assert ev.errors[0].rms_mm < 0.02 and ev.errors[1].rms_mm < 0.02
    np.testing.assert_array_equal(ev.errors[0].dt_mm, ev.errors[1].dt_mm)  # same ideal distances for both


def run(*args):
    """The command in-process (the subprocess path is covered by test_evaluate_cli.py): the numba
    kernels and OpenCV are already loaded, which keeps this test to seconds."""
    from typer.testing import CliRunner

    from lightplane.cli import app

    r = CliRunner().invoke(app, [str(a) for a in args], env={"COLUMNS": "120"})
    return SimpleNamespace(returncode=r.exit_code, stdout=r.stdout, stderr=r.stderr)


def test_cli_zhou_then_evaluate_side_by_side(dataset, circle_plane, tmp_path):
    ds, _, _ = dataset
    ds.save(tmp_path / "data")
    d = tmp_path / "data"
    on, off = sorted(d.glob("board_???.png")), str(d / "board_???_off.png")  # a glob for --background
    cam, sq = d / "camera.json", str(ds.truth["board"]["square_mm"])
    truth_file = tmp_path / "truth_plane.json"
    LightPlane.from_dict(ds.truth["plane"]).save(truth_file)
    zhou = tmp_path / "zhou.json"
    r = run("calibrate-plane-board", *on, "--background", off, "--camera", cam, "--board", "9x6", "--square", sq,
            "-o", zhou, "--report", tmp_path / "zhou_report")
    assert r.returncode == 0, r.stderr
    assert "mm" in r.stdout and "deg" in r.stdout
    page = (tmp_path / "zhou_report" / "index.html").read_text()  # the report, from the plane file
    assert "for triangulating points" in page and " on 5 boards to " in page
    zp = LightPlane.load(zhou)
    assert np.degrees(zp.angle_to(LightPlane.load(truth_file))) < 0.01
    zd = json.loads(zhou.read_text())
    assert zd["method"] == "zhou" and len(zd["images"]) == 5 and np.shape(zd["covariance"]) == (4, 4)
    assert "provenance" in zd

    js, cs = tmp_path / "eval.json", tmp_path / "eval.csv"
    circle = tmp_path / "circle.json"
    circle_plane.save(circle)
    r = run("evaluate", *on, "--background", off, "--camera", cam, "--plane", truth_file, "--plane", circle,
            "--plane", zhou,
            "--board", "9x6", "--square", sq, "--json", js, "--csv", cs)
    assert r.returncode == 0, r.stderr
    assert "in mm" in r.stdout and "dm3" in r.stdout and "Δ3" in r.stdout and "RMS" in r.stdout
    e = json.loads(js.read_text())
    assert set(e["planes"]) == {str(truth_file), str(circle), str(zhou)}
    for p in e["planes"].values():
        assert p["rms_mm"] < 0.02
        assert len(p["pairs"]) >= 10 and {"dt_mm", "dm_mm", "delta_mm"} <= set(p["pairs"][0])
        delta = np.array([q["delta_mm"] for q in p["pairs"]])
        np.testing.assert_allclose(np.sqrt(np.mean(delta**2)), p["rms_mm"], rtol=1e-12)
    rows = cs.read_text().splitlines()
    assert rows[0].startswith("no,image,i,j,dt_mm") and rows[-1].startswith("rms")
    assert len(rows) == len(e["planes"][str(zhou)]["pairs"]) + 2

    # laser-off frames given as the laser images: no stripe -> exit 2, nothing written
    js2, out2 = tmp_path / "none.json", tmp_path / "none_plane.json"
    offs = sorted(d.glob("board_???_off.png"))[:2]
    r = run("evaluate", *offs, "--camera", cam, "--plane", truth_file, "--board", "9x6", "--square", sq,
            "--json", js2)
    assert r.returncode == 2 and "none of the 2 images usable" in r.stderr and "no stripe on the board" in r.stderr
    assert not js2.exists()
    r = run("calibrate-plane-board", *offs, "--camera", cam, "--board", "9x6", "--square", sq, "-o", out2)
    assert r.returncode == 2 and "need at least 2" in r.stderr and "no stripe on the board" in r.stderr
    assert not out2.exists()
