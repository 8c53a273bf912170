"""The calibration reports on real photographs with the defaults (``../shared/data``; skipped when absent)."""

from __future__ import annotations

import re

import pytest

from _cli import lightplane

pytestmark = pytest.mark.realdata


def test_ciclop_camera_report(shared_data, tmp_path):
    """Ciclop's 16 captures (README: portrait JPEGs, rotated 90 deg clockwise): the report's verdict states the
    RMS the command printed and the ray σ at the boards' distance; every view is in its table."""
    folder = shared_data / "ciclop" / "camera_calibration_captures"
    if not folder.is_dir():
        pytest.skip(f"real-data test: {folder} is absent")
    r = lightplane("calibrate-camera", folder, "--board", "11x6", "--square", "13", "--rotate", "90", "-o",
                   tmp_path / "cam.json", "--report", tmp_path / "rep")
    assert r.returncode == 0, r.stderr
    rms = re.search(r"RMS reprojection error: ([0-9.]+) px over (\d+) views", r.stdout)
    page = (tmp_path / "rep" / "index.html").read_text()
    verdict = re.search(r"<p class=verdict>(.*?)</p>", page, re.S).group(1)
    assert f"RMS reprojection {float(rms.group(1)):.3f} px over {rms.group(2)} views" in verdict
    assert "deg RMS over the image" in verdict and "µm across the ray" in verdict
    assert all(f"frame{k}.jpg" in page for k in range(16))
    assert len(re.findall(r'src="data:image/png;base64,', page)) == 4  # coverage, per view, over the image, σ map
    assert f"wrote {tmp_path / 'rep' / 'index.html'}" in " ".join(r.stdout.split())


def test_fabscan_turntable_report(shared_data, tmp_path):
    """FabScan's 17 lit board frames at the laser positions (README: frames 67, 70, ... 115), with the camera of
    its own configuration: the table turned about 58 deg in all, which the verdict names as a limit."""
    root = shared_data / "fabscan"
    if not root.is_dir():
        pytest.skip(f"real-data test: {root} is absent")
    assert lightplane("import-fabscan", root / "fabscan-config.json", "-o", tmp_path / "s.json").returncode == 0
    frames = [root / "calibration_8x10" / f"calibration_{k:03d}.jpg" for k in range(67, 118, 3)]
    r = lightplane("calibrate-turntable", *frames, "--camera", tmp_path / "s.json", "--board", "10x8", "--square", "7",
                   "-o", tmp_path / "tt.json", "--report", tmp_path / "rep")
    assert r.returncode == 0, r.stderr
    page = (tmp_path / "rep" / "index.html").read_text()
    verdict = re.search(r"<p class=verdict>(.*?)</p>", page, re.S).group(1)
    span = float(re.search(r"table turned ([0-9.]+) deg in all", r.stdout).group(1))
    assert 50 < span < 65 and f"the table turned {span:.0f} deg in all" in verdict
    assert "deg in direction and" in verdict and "µm" in verdict
    assert all(f.name in page for f in frames)
