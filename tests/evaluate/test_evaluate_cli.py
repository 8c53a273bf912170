"""`lightplane evaluate` and `lightplane calibrate-plane-board`: bad input gives one line, exit 2, nothing written."""

from __future__ import annotations


import cv2
import numpy as np
import pytest

from lightplane import Camera, LightPlane
from _cli import lightplane, one_error_line

CAM = Camera([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]], np.zeros(5), 640, 480)


run = lightplane


@pytest.fixture()
def files(tmp_path):
    cam = CAM.save_json(tmp_path / "camera.json")
    plane = tmp_path / "plane.json"
    LightPlane([0.95, 0, -0.3], -100.0).save(plane)
    blanks = []
    for k in range(2):
        p = tmp_path / f"blank{k}.png"
        cv2.imwrite(str(p), np.full((480, 640), 128, np.uint8))
        blanks.append(p)
    return tmp_path, cam, plane, blanks


_one_error_line = one_error_line


def test_zhou_board_not_found(files):
    d, cam, _, blanks = files
    out = d / "out.json"
    r = run("calibrate-plane-board", *blanks, "--camera", cam, "--board", "9x6", "--square", "8", "-o", out)
    msg = _one_error_line(r)
    assert "chessboard" in msg and "not found" in msg and "blank0.png" in msg
    assert not out.exists()


def test_zhou_needs_two_poses(files):
    d, cam, _, blanks = files
    out = d / "out.json"
    r = run("calibrate-plane-board", blanks[0], "--camera", cam, "--board", "9x6", "--square", "8", "-o", out)
    assert "at least 2 board poses" in _one_error_line(r)
    assert not out.exists()


def test_zhou_refuses_overwrite_and_bad_options(files):
    d, cam, _, blanks = files
    out = d / "out.json"
    out.write_text("keep")
    r = run("calibrate-plane-board", *blanks, "--camera", cam, "--board", "9x6", "--square", "8", "-o", out)
    assert "already exists" in _one_error_line(r)
    assert out.read_text() == "keep"
    r = run("calibrate-plane-board", *blanks, "--camera", cam, "--board", "9by6", "--square", "8", "-o", d / "o2.json")
    assert "--board" in _one_error_line(r)
    r = run("calibrate-plane-board", *blanks, "--camera", cam, "--board", "9x6", "--square", "0", "-o", d / "o2.json")
    assert "--square" in _one_error_line(r)
    r = run("calibrate-plane-board", *blanks, "--camera", d / "nope.json", "--board", "9x6", "--square", "8",
            "-o", d / "o2.json")
    assert "nope.json" in _one_error_line(r)
    assert not (d / "o2.json").exists()


def test_evaluate_board_not_found(files):
    d, cam, plane, blanks = files
    js, cs = d / "e.json", d / "e.csv"
    r = run("evaluate", *blanks, "--camera", cam, "--plane", plane, "--board", "9x6", "--square", "8",
            "--json", js, "--csv", cs)
    msg = _one_error_line(r)
    assert "not found" in msg and "blank0.png" in msg
    assert not js.exists() and not cs.exists()


def test_evaluate_bad_plane_and_existing_output(files):
    d, cam, plane, blanks = files
    bad = d / "bad.json"
    bad.write_text('{"normal": [0, 0, 1]}')
    r = run("evaluate", *blanks, "--camera", cam, "--plane", bad, "--board", "9x6", "--square", "8")
    assert "bad.json" in _one_error_line(r) and "'d'" in r.stderr
    js = d / "e.json"
    js.write_text("keep")
    r = run("evaluate", *blanks, "--camera", cam, "--plane", plane, "--board", "9x6", "--square", "8", "--json", js)
    assert "already exists" in _one_error_line(r)
    assert js.read_text() == "keep"
    r = run("evaluate", *blanks, "--camera", cam, "--plane", plane, "--board", "9x6", "--square", "8",
            "--lines", "diagonal")
    assert "--lines" in _one_error_line(r)
