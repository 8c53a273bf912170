"""`lightplane report PLANE.json --out DIR` rebuilds the calibrate-plane report from the plane file alone."""

from __future__ import annotations

import base64
import json
import re
import shutil

import cv2
import numpy as np
import pytest

from lightplane import LightPlane

from _renders import cached_circle_render
from _cli import lightplane, one_error_line


run = lightplane
_bad = one_error_line


def _pngs(html: str) -> list[np.ndarray]:
    out = []
    for b64 in re.findall(r'src="data:image/png;base64,([^"]*)"', html):
        img = cv2.imdecode(np.frombuffer(base64.b64decode(b64), np.uint8), cv2.IMREAD_COLOR)
        assert img is not None
        out.append(img)
    return out


def _text(html: str) -> str:
    """The page without its embedded figures."""
    return re.sub(r'src="data:image/png;base64,[^"]*"', 'src="PNG"', html)


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """calibrate-plane --report on 5 rendered images and one without a target, with relative image names."""
    src = cached_circle_render()
    work = tmp_path_factory.mktemp("rebuild")
    shutil.copytree(src, work / "imgs")
    h, w = cv2.imread(str(next((work / "imgs").glob("*.png"))), cv2.IMREAD_UNCHANGED).shape[:2]
    cv2.imwrite(str(work / "imgs" / "zz_blank.png"), np.full((h, w), 40, np.uint8))
    r = run("calibrate-plane", "imgs", "--camera", "imgs/camera.json", "--diameter", "50", "-o", "plane.json",
            "--report", "rep1", cwd=work)
    assert r.returncode == 0, r.stderr
    return work


def test_plane_file_stores_the_inputs_and_still_loads(calibrated):
    d = json.loads((calibrated / "plane.json").read_text())
    inp = d["report_inputs"]
    assert inp["version"] == 1 and inp["camera"]["width"] > 0
    assert len(inp["images"]) == 6
    used = [r for r in inp["images"] if r["used"]]
    assert len(used) == 5 and all(r["placement"]["poses"] and len(r["shape"]) == 2 for r in used)
    blank = inp["images"][-1]
    assert blank["source"].endswith("zz_blank.png") and not blank["ok"] and blank["placement"] is None
    plane = LightPlane.load(calibrated / "plane.json")
    assert plane.covariance is not None and plane.d < 0


def test_report_reproduces_the_calibrate_plane_report(calibrated):
    r = run("report", "plane.json", "--out", "rep2", cwd=calibrated)
    assert r.returncode == 0, r.stderr
    assert "rep2" in r.stdout
    h1 = (calibrated / "rep1" / "index.html").read_text()
    h2 = (calibrated / "rep2" / "index.html").read_text()
    # same tables, numbers, names, warnings and provenance
    assert _text(h1) == _text(h2)
    for name in ("circle_000.png", "zz_blank.png", "no target ellipse found", "normal σ", "created_utc"):
        assert name in h2, name
    # same figures (the same data drawn: pixel for pixel, up to rounding of the last bit)
    p1, p2 = _pngs(h1), _pngs(h2)
    assert len(p1) == len(p2) == 4
    for a, b in zip(p1, p2):
        assert a.shape == b.shape
        assert np.mean(np.abs(a.astype(int) - b.astype(int))) < 0.01
    # an existing report is not overwritten without --force
    _bad(run("report", "plane.json", "--out", "rep2", cwd=calibrated), "already exists")
    assert run("report", "plane.json", "--out", "rep2", "--force", cwd=calibrated).returncode == 0


def test_images_gone_blank_canvas(calibrated, tmp_path):
    # the plane file alone, elsewhere: the image files it names cannot be found
    shutil.copy(calibrated / "plane.json", tmp_path / "plane.json")
    r = run("report", "plane.json", "--out", "rep", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    h = (tmp_path / "rep" / "index.html").read_text()
    h1 = (calibrated / "rep1" / "index.html").read_text()
    assert "blank canvas" in h and "blank canvas" not in h1
    assert "circle_000.png" in h
    # the tables are those of the original report
    table = re.compile(r"<h2>Images</h2>.*?</table>", re.S)
    assert table.search(h).group(0) == table.search(h1).group(0)
    assert len(_pngs(h)) == 4


def test_old_plane_file_exits_2_with_one_line(calibrated, tmp_path):
    d = json.loads((calibrated / "plane.json").read_text())
    del d["report_inputs"]
    old = tmp_path / "old.json"
    old.write_text(json.dumps(d))
    assert LightPlane.load(old).d < 0  # still a plane file
    _bad(run("report", old, "--out", tmp_path / "rep"), "no stored calibration inputs", "calibrate-plane")
    assert not (tmp_path / "rep").exists()
    _bad(run("report", tmp_path / "missing.json", "--out", tmp_path / "rep"), "no such result file")
    d["report_inputs"] = {"version": 1, "images": [{"index": 0}]}
    old.write_text(json.dumps(d))
    _bad(run("report", old, "--out", tmp_path / "rep"), "report_inputs", "malformed")


# ----------------------------------------------------------------------------- declarative CLI validation
@pytest.mark.parametrize("args, needle", [
    (["calibrate-plane", "x.png", "--camera", "c.json", "--diameter", "50", "-o", "p.json", "--method", "best"],
     "'best' is not one of 'ml', 'global', 'paper'"),
    (["calibrate-plane", "x.png", "--camera", "c.json", "--diameter", "50", "-o", "p.json", "--channel", "pink"],
     "'--channel'"),
    (["calibrate-plane", "x.png", "--camera", "c.json", "--diameter", "50", "-o", "p.json", "--workers", "0"],
     "'--workers'"),
    (["evaluate", "x.png", "--camera", "c.json", "--plane", "p.json", "--lines", "diagonal"], "'--lines'"),
    (["evaluate", "x.png", "--camera", "c.json", "--plane", "p.json", "--corners", "two"], "'--corners'"),
    (["measure", "x.png", "--camera", "c.json", "--plane", "p.json", "-o", "o.ply", "--axis", "diag"], "'--axis'"),
    (["measure", "x.png", "--camera", "c.json", "--plane", "p.json", "-o", "o.ply", "--workers", "0"], "'--workers'"),
    (["render", "circle", "--out", "o", "--difficulty", "extreme"], "'extreme' is not one of"),
    (["report"], "Missing argument"),
    (["calibrate-plane", "x.png", "--bogus"], "No such option: --bogus"),
])
def test_usage_errors_are_one_line_exit_2(tmp_path, args, needle):
    _bad(run(*args, cwd=tmp_path), needle)
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_measure_workers_help_says_threads():
    r = run("measure", "--help")
    assert r.returncode == 0 and "Worker threads" in r.stdout and "processes" not in r.stdout
