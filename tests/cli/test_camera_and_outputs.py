"""The command line's file checks: a plane (sensor, turntable) and the camera it was calibrated with
belong together; output paths (not an input, not a folder, the format of the suffix); every file
argument that is missing or a folder gives one line and exit 2."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _measure_synth import CAM, PLANE, write_scan  # noqa: E402

from lightplane import Camera, LightPlane  # noqa: E402
from lightplane.camera.model import camera_record  # noqa: E402
from lightplane.cli import app  # noqa: E402
from lightplane.measure.pointcloud import read_cloud  # noqa: E402
from lightplane.motion.model import Turntable  # noqa: E402


def cli(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def one_line(r, *needles: str) -> str:
    """Exit 2 and exactly one ``lightplane: error:`` line on stderr, holding each of ``needles``."""
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.exit_code == 2 and len(lines) == 1 and lines[0].startswith("lightplane: error:"), (r.exit_code, r.stderr)
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


def ply_comments(path: Path) -> list[str]:
    head = path.read_bytes().split(b"end_header", 1)[0].decode()
    return [ln[len("comment "):] for ln in head.splitlines() if ln.startswith("comment ")]


def other_camera(rel: float = 1e-4) -> Camera:
    """CAM with its focal length changed by ``rel`` (another calibration of the same camera moves it by more)."""
    K = CAM.K.copy()
    K[0, 0] *= 1 + rel
    return Camera(K, CAM.dist, CAM.width, CAM.height)


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    d = tmp_path_factory.mktemp("camera_check")
    write_scan(d, 2, "frames")  # camera.json (CAM), plane.json (PLANE, no camera recorded: an older plane file)
    LightPlane(PLANE.normal, PLANE.d, meta={"camera": camera_record(CAM)}).save(d / "plane_a.json")
    other_camera().save_json(d / "camera_b.json")
    other_camera(2e-7).save_json(d / "camera_near.json")  # within the tolerance: the same camera
    CAM.save(d / "camera.yaml")  # ROS YAML of the same camera
    Turntable.from_axis([0, 40, 450], [0, -1, 0], camera=CAM.to_dict()).save(d / "tt_a.json")
    return d


def measure(d: Path, camera: str, plane: str, out: Path, *extra):
    return cli("measure", d / "frames", "--camera", d / camera, "--plane", d / plane, "-o", out, "--workers", "1",
               *extra)


def test_plane_of_another_camera_refused_in_measure_and_sensor(scan, tmp_path):
    out = tmp_path / "c.ply"
    msg = one_line(measure(scan, "camera_b.json", "plane_a.json", out), "plane_a.json", "camera_b.json",
                   "calibrated with another camera", "fx 2000 px vs 2000.2 px", "--allow-other-camera")
    assert str(scan / "plane_a.json") in msg and str(scan / "camera_b.json") in msg
    assert not out.exists()
    one_line(cli("sensor", "-o", tmp_path / "s.json", "--camera", scan / "camera_b.json", "--plane",
                 f"a={scan / 'plane_a.json'}"), "plane_a.json", "camera_b.json", "fx")
    assert not (tmp_path / "s.json").exists()
    one_line(cli("evaluate", scan / "frames", "--camera", scan / "camera_b.json", "--plane", scan / "plane_a.json",
                 "--board", "9x6", "--square", "8"), "plane_a.json", "camera_b.json")
    # the turntable goes through the same comparison
    one_line(measure(scan, "camera_b.json", "plane.json", out, "--turntable", scan / "tt_a.json",
                     "--turntable-step", "3"), "tt_a.json", "camera_b.json", "fx 2000 px vs 2000.2 px",
             "recalibrate the turntable")


def test_same_camera_within_tolerance_and_through_yaml(scan, tmp_path):
    for k, cam in enumerate(("camera.json", "camera_near.json", "camera.yaml")):
        out = tmp_path / f"c{k}.ply"
        r = measure(scan, cam, "plane_a.json", out)
        assert r.exit_code == 0, r.stderr
        assert "warning" not in r.stderr and not any("camera check" in c for c in ply_comments(out))


def test_allow_other_camera_is_recorded(scan, tmp_path):
    out = tmp_path / "c.ply"
    r = measure(scan, "camera_b.json", "plane_a.json", out, "--allow-other-camera")
    assert r.exit_code == 0, r.stderr
    assert "calibrated with another camera" in r.stderr and "used by --allow-other-camera" in r.stderr
    comments = ply_comments(out)
    assert "camera check: --allow-other-camera given" in comments
    assert any("plane_a.json: calibrated with another camera" in c and "fx" in c for c in comments)
    assert read_cloud(out).size > 300


def test_sensor_built_with_the_override_measures_and_records_it(scan, tmp_path):
    s = tmp_path / "s.json"
    r = cli("sensor", "-o", s, "--camera", scan / "camera_b.json", "--plane", f"a={scan / 'plane_a.json'}",
            "--allow-other-camera")
    assert r.exit_code == 0, r.stderr
    opts = json.loads(s.read_text())["provenance"]["options"]
    assert opts["allow_other_camera"] is True and "plane_a.json: calibrated with another camera" in opts["camera_check"][0]
    out = tmp_path / "c.ply"
    r = cli("measure", "--sensor", s, "--laser", f"a={scan / 'frames'}", "-o", out, "--workers", "1")
    assert r.exit_code == 0, r.stderr
    assert any("recorded with it" in c for c in ply_comments(out))
    # a sensor file whose plane belongs to another camera, without the override recorded: refused
    d = json.loads(s.read_text())
    del d["planes"]["a"]["allowed_camera"]
    s.write_text(json.dumps(d))
    one_line(cli("measure", "--sensor", s, "--laser", f"a={scan / 'frames'}", "-o", out, "--force"),
             f"{s}: plane 'a'", "calibrated with another camera", "fx")


def test_older_plane_without_camera_warned_and_recorded(scan, tmp_path):
    out = tmp_path / "c.ply"
    r = measure(scan, "camera_b.json", "plane.json", out)
    assert r.exit_code == 0, r.stderr
    warn = [ln for ln in r.stderr.splitlines() if ln.startswith("warning:")]
    assert len(warn) == 1 and "records no camera" in warn[0] and "camera_b.json" in warn[0]
    assert any("records no camera" in c for c in ply_comments(out))


def test_output_naming_an_input_or_a_folder_refused(scan, tmp_path):
    pos = tmp_path / "pos.csv"
    pos.write_text("dx,dy,dz\n0,0,0\n0.5,0,0\n")
    before = pos.read_bytes()
    one_line(measure(scan, "camera.json", "plane_a.json", pos, "--positions", pos, "--format", "csv", "--force"),
             f"-o {pos}", "is also an input")
    assert pos.read_bytes() == before
    one_line(cli("sensor", "-o", scan / "plane_a.json", "--camera", scan / "camera.json", "--plane",
                 scan / "plane_a.json", "--force"), "is also an input")
    folder = tmp_path / "cloud.ply"
    folder.mkdir()
    one_line(measure(scan, "camera.json", "plane_a.json", folder, "--force"), f"-o {folder}", "is a folder")
    assert folder.is_dir() and not list(folder.iterdir())
    one_line(cli("sensor", "-o", tmp_path, "--camera", scan / "camera.json", "--plane", scan / "plane_a.json",
                 "--force"), "is a folder")


def test_format_follows_the_suffix(scan, tmp_path):
    out = tmp_path / "cloud.ply"
    one_line(measure(scan, "camera.json", "plane_a.json", out, "--format", "csv"),
             "cloud.ply", "format csv does not match", ".ply")
    assert not out.exists()
    txt = tmp_path / "cloud.txt"  # a suffix that names no format: --format says which
    r = measure(scan, "camera.json", "plane_a.json", txt, "--format", "csv")
    assert r.exit_code == 0, r.stderr
    lines = txt.read_text().splitlines()  # the units, frame and provenance as '#' lines, then the header
    assert lines[0].startswith("# units: x mm") and [ln for ln in lines if not ln.startswith("#")][0].startswith("x,y,z")
    r = measure(scan, "camera.json", "plane_a.json", tmp_path / "c.csv", "--format", "CSV")
    assert r.exit_code == 0, r.stderr
    assert np.array_equal(read_cloud(tmp_path / "c.csv")["x"], read_cloud(txt, "csv")["x"])


def test_missing_or_folder_file_arguments_one_line(scan, tmp_path):
    missing, folder = tmp_path / "missing.json", tmp_path / "folder"
    folder.mkdir()
    cam, pl, fr, out = scan / "camera.json", scan / "plane_a.json", scan / "frames", tmp_path / "o.json"
    board = ("--board", "9x6", "--square", "8")
    for bad in (missing, folder):
        cases = [
            ("calibrate-plane", fr, "--camera", bad, "--diameter", "50", "-o", out),
            ("calibrate-plane-board", fr, "--camera", bad, *board, "-o", out),
            ("calibrate-turntable", fr, "--camera", bad, *board, "-o", out),
            ("calibrate-camera", fr, "--target", bad, "-o", out),
            ("evaluate", fr, "--camera", cam, "--plane", bad, *board),
            ("measure", fr, "--camera", cam, "--plane", bad, "-o", tmp_path / "o.ply"),
            ("measure", fr, "--camera", bad, "--plane", pl, "-o", tmp_path / "o.ply"),
            ("measure", fr, "--camera", cam, "--plane", pl, "--positions", bad, "-o", tmp_path / "o.ply"),
            ("measure", fr, "--camera", cam, "--plane", pl, "--poses", bad, "-o", tmp_path / "o.ply"),
            ("measure", fr, "--camera", cam, "--plane", pl, "--turntable", bad, "--turntable-step", "3",
             "-o", tmp_path / "o.ply"),
            ("measure", fr, "--sensor", bad, "--laser", "a", "-o", tmp_path / "o.ply"),
            ("sensor", "--camera", cam, "--plane", bad, "-o", out),
            ("sensor", "--camera", cam, "--plane", pl, "--flange", bad, "-o", out),
            ("import-fabscan", bad, "-o", out),
            ("refine-turntable", "--sensor", bad, "--scan", "a=x", "--scan", "b=y", "--turntable-step", "3",
             "-o", out),
            ("report", bad, "--out", tmp_path / "rep"),
        ]
        for args in cases:
            one_line(cli(*args), str(bad))
    one_line(cli("calibrate-camera", tmp_path / "missing.png", *board, "-o", out), "missing.png", "no such file")
    one_line(cli("measure", tmp_path / "missing.png", "--camera", cam, "--plane", pl, "-o", tmp_path / "o.ply"),
             "missing.png", "no such file")
    assert not out.exists() and not (tmp_path / "o.ply").exists()
