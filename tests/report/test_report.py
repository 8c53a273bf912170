"""The HTML report: self-contained, every figure with units, refuses to overwrite; headless Chromium."""

from __future__ import annotations

import json
import re
import shutil
import subprocess

import numpy as np
import pytest

from lightplane.plane.calibrate import PlaneCalibrationOptions, calibrate_plane
from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.plane.model import LightPlane
from lightplane.report.plots import figure_overlays, figure_residuals
from lightplane.report.html import write_report

from _renders import cached_circle_render


@pytest.fixture(scope="module")
def cal_and_truth():
    folder = cached_circle_render()
    truth = json.loads((folder / "truth.json").read_text())
    cam = Camera.load(folder / "camera.json")
    files = [folder / im["file"] for im in truth["images"]]
    blank = np.full((cam.height, cam.width), 30, np.uint8)
    cal = calibrate_plane([*files, blank], cam, 50.0, options=PlaneCalibrationOptions(workers=1))
    return cal, LightPlane.from_dict(truth["plane"])


@pytest.fixture(scope="module")
def report(cal_and_truth, tmp_path_factory):
    cal, truth = cal_and_truth
    out = tmp_path_factory.mktemp("rep") / "report"
    path = write_report(out, cal, plane_true=truth, images=None)
    return path, path.read_text()


def test_self_contained(report):
    path, html = report
    assert path.name == "index.html" and path.parent.is_dir()
    assert list(path.parent.iterdir()) == [path]  # nothing beside it: figures are embedded
    srcs = re.findall(r'src="([^"]*)"', html)
    assert len(srcs) == 4 and all(s.startswith("data:image/png;base64,") for s in srcs)
    assert "http://" not in html and "https://" not in html and "<script" not in html
    assert (path.stat().st_mode & 0o044) == 0o044  # readable by others


def test_content(report, cal_and_truth):
    cal, _ = cal_and_truth
    _, html = report
    for o in cal.images:
        assert o.name in html
    assert "image[5]" in html and "no target ellipse found" in html  # the rejected array, with its reason
    assert "deg" in html and " mm" in html and "µm" in html and " px" in html
    assert "vs truth: normal angle" in html
    # every figure has units in its caption
    for cap in re.findall(r"<figcaption[^>]*>(.*?)</figcaption>", html):
        assert re.search(r"\b(px|mm|µm)\b", cap), cap


def test_figures_are_pngs(cal_and_truth):
    cal, _ = cal_and_truth
    for png in (figure_overlays(cal), figure_residuals(cal)):
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000


def test_refuses_overwrite(report, cal_and_truth):
    path, html = report
    cal, _ = cal_and_truth
    with pytest.raises(LightplaneError, match="already exists"):
        write_report(path.parent, cal)
    assert path.read_text() == html


def _chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable", "headless_shell"):
        p = shutil.which(name)
        if p:
            return p
    return None


def test_renders_in_headless_chromium(report, tmp_path):
    exe = _chromium()
    if exe is None:
        pytest.skip("headless Chromium is not installed (chromium / google-chrome not on PATH)")
    path, _ = report
    shot = tmp_path / "shot.png"
    r = subprocess.run([exe, "--headless", "--disable-gpu", "--no-sandbox", f"--screenshot={shot}",
                        "--window-size=1200,3000", path.as_uri()], capture_output=True, timeout=120)
    assert r.returncode == 0, r.stderr[-500:]
    import cv2

    img = cv2.imread(str(shot))
    assert img is not None and img.shape[0] > 1000 and img.std() > 10  # not a blank page


def test_figures_only_in_plots_module():
    """matplotlib only in lightplane.report.plots; importing the library does not load it."""
    import pathlib

    src = pathlib.Path(__file__).resolve().parents[2] / "src" / "lightplane"
    users = {str(f.relative_to(src)) for f in src.rglob("*.py") if "matplotlib" in f.read_text(encoding="utf-8")}
    assert users == {"report/plots.py"}
    code = ("import sys, pkgutil, importlib, lightplane\n"
            "for m in pkgutil.walk_packages(lightplane.__path__, 'lightplane.'):\n"
            "    if not m.name.startswith(('lightplane.cli', 'lightplane.__main__')):\n"
            "        importlib.import_module(m.name)\n"
            "print('matplotlib' in sys.modules)")
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "False"
