"""The demo: a small run end to end, missing stages reported as skipped, bad output folder."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from lightplane.report.demo import run_demo
from lightplane.core.errors import LightplaneError
from lightplane.evaluate.shapes import fit_sphere, plane_accuracy

SMALL = {"chessboards": 0, "circles": 4, "striped_boards": 0, "scan_frames": 0}


def test_small_demo_runs_and_reports(tmp_path):
    out = tmp_path / "demo"
    lines = []
    s = run_demo(out, settings=SMALL, workers=1, console=type("C", (), {"print": staticmethod(lines.append)})())
    assert s["stages"]["render"]["status"] == "ok" and s["stages"]["plane"]["status"] == "ok"
    acc = s["plane"]["accuracy"]["ml"]
    # 4 placements, true camera: a few predicted sigmas of ~7 µm
    assert acc["angle_deg"] < 0.05 and acc["tri_rms_mm"] < 0.08
    assert (out / "report" / "index.html").stat().st_size > 10000
    assert json.loads((out / "summary.json").read_text())["plane"]["ml"]["n_used"] == 4
    text = "\n".join(map(str, lines))
    assert "deg" in text and "mm" in text and "truth" in text
    with pytest.raises(LightplaneError, match="not empty"):
        run_demo(out, settings=SMALL, workers=1, console=type("C", (), {"print": staticmethod(lambda *a: None)})())


def test_missing_module_is_skipped_not_a_crash(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "lightplane.simulate.render", None)  # import -> ImportError
    s = run_demo(tmp_path / "d", settings=SMALL, workers=1,
                 console=type("C", (), {"print": staticmethod(lambda *a: None)})())
    assert s["stages"]["render"]["status"] == "skipped" and "module" in s["stages"]["render"]["reason"]
    assert (tmp_path / "d" / "summary.json").exists()


def test_cli_bad_output(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    r = subprocess.run([sys.executable, "-m", "lightplane", "demo", "--out", str(f)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2 and "not a folder" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_plane_accuracy_exact():
    from lightplane.plane.model import LightPlane
    from lightplane.simulate.scene import default_camera, default_plane

    cam, pl = default_camera(), default_plane()
    a = plane_accuracy(pl, cam, pl, cam)
    assert a["angle_deg"] == 0 and abs(a["offset_mm"]) < 1e-9 and a["tri_rms_mm"] < 1e-9
    shifted = LightPlane(pl.normal, pl.d - 0.01)  # 0.01 mm along the normal
    a = plane_accuracy(shifted, cam, pl, cam)
    assert abs(abs(a["offset_mm"]) - 0.01) < 1e-9 and a["tri_rms_mm"] > 0.01  # oblique rays: > 0.01 mm


def test_fit_sphere():
    rng = np.random.default_rng(1)
    v = rng.normal(size=(500, 3))
    v = v[v[:, 2] < 0]  # one cap, as a scan sees it
    p = np.array([1.0, -2.0, 470.0]) + 25.4 * v / np.linalg.norm(v, axis=1, keepdims=True)
    p += rng.normal(0, 0.01, p.shape)
    p = np.vstack([p, rng.uniform(-50, 50, (20, 3)) + [0, 0, 600]])  # outliers
    fit = fit_sphere(p).to_dict()
    assert abs(fit["radius_mm"] - 25.4) < 0.01 and np.linalg.norm(np.array(fit["center_mm"]) - [1, -2, 470]) < 0.02
    assert abs(fit["rms_mm"] - 0.01) < 0.003 and fit["n_inliers"] >= len(v) - 3


def test_demo_scan_cloud_as_ply_with_units(tmp_path):
    """The demo's scan stage writes its cloud as PLY (x y z, frame, intensity, σ, pixel; units and frame in the
    comments) beside the NPY of x y z; the two hold the same points, on the true sphere."""
    from lightplane.measure.pointcloud import cloud_comments, read_cloud
    from lightplane.report.demo import _measure_scan
    from lightplane.simulate.render import render_scan_dataset
    from lightplane.simulate.scene import default_camera, default_plane

    render_scan_dataset("sphere", n_frames=2, seed=1, difficulty="clean").save(tmp_path / "scan")
    res = _measure_scan(tmp_path / "scan", default_camera(), default_plane(), tmp_path)
    c = read_cloud(tmp_path / "scan_points.ply")
    xyz = np.load(tmp_path / "scan_points.npy")
    assert c.size == res["n_points"] == len(xyz) and set(c["frame"].tolist()) == {0, 1}
    assert np.allclose(np.column_stack([c["x"], c["y"], c["z"]]), xyz, atol=1e-4)  # float32 in the PLY
    assert np.all(np.isfinite(c["u"])) and np.all(np.isnan(c["sigma_mm"]))  # the true plane has no covariance
    com = cloud_comments(tmp_path / "scan_points.ply")
    assert com[0].startswith("units: x mm") and "object at frame 0" in com[1]
    assert abs(res["radius_error_mm"]) < 0.05  # the true camera and plane, clean frames
