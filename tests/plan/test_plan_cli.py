"""``lightplane plan``: the offline placement plan, printed, drawn and written; bad input in one line."""

import json

import cv2
import numpy as np

from lightplane.simulate.scene import default_camera, default_plane
from tests._cli import lightplane, one_error_line


def test_plan_prints_draws_and_writes(tmp_path):
    cam, plane = tmp_path / "cam.json", tmp_path / "plane.json"
    default_camera().save(cam)
    default_plane().save(plane)
    png, js = tmp_path / "plan.png", tmp_path / "plan.json"
    r = lightplane("plan", "--camera", cam, "--diameter", "50", "--working-volume", "distance:400,500",
                   "--plane", plane, "--target-sigma", "0.01", "-o", png, "--json", js)
    assert r.returncode == 0, r.stderr
    assert "target 0.01 mm reached after" in r.stdout and "σ after (mm)" in r.stdout
    d = json.loads(js.read_text())
    steps = d["placements"]
    assert 3 <= len(steps) <= 12 and steps[-1]["sigma_after_mm"] <= 0.01
    assert all(s["sigma_after_mm"] <= s["sigma_now_mm"] for s in steps)
    ol = np.array(steps[0]["outline_px"])
    assert ol.shape == (72, 2) and np.all((ol >= 0) & (ol < [1280, 960]))
    assert d["provenance"]["options"]["diameter_mm"] == 50.0 and "covers" in d
    img = cv2.imread(str(png))
    assert img.shape == (960, 1280, 3)
    bad = lightplane("plan", "--camera", cam, "--diameter", "50", "--working-volume", "sphere:1", "--plane", plane,
                     "-o", tmp_path / "other.png")
    one_error_line(bad, "working volume")
    assert not (tmp_path / "other.png").exists()


def test_plan_refuses_infinite_distances_and_mismatched_file_names(tmp_path):
    """An infinite far distance is not a working volume; the drawing is a PNG and the plan JSON: other file
    names are refused before anything is written."""
    cam = tmp_path / "cam.json"
    default_camera().save(cam)
    base = ("plan", "--camera", cam, "--diameter", "50")
    one_error_line(lightplane(*base, "--working-volume", "distance:380,inf"), "finite")
    one_error_line(lightplane(*base, "--working-volume", "distance:380,520", "--distance", "380,inf"), "finite")
    one_error_line(lightplane(*base, "--working-volume", "distance:380,520", "-o", tmp_path / "plan.txt"), ".png")
    one_error_line(lightplane(*base, "--working-volume", "distance:380,520", "--json", tmp_path / "plan.png"), ".json")
    assert not any(tmp_path.glob("plan.*"))
    huge = lightplane(*base, "--working-volume", "box:-1e308,-1e308,300,1e308,1e308,600")
    one_error_line(huge, "too large")
