"""Cropping a cloud to the calibrated working volume (``measure --crop``): exactly the points whose depth lies in
the plane's calibrated depth range are kept, against the exact stripe frames of tests/_measure_synth.py."""

from __future__ import annotations

import numpy as np
import pytest

from lightplane import LightPlane
from lightplane.measure.options import MeasureOptions
from lightplane.measure.pointcloud import read_cloud
from lightplane.measure.scan import ArrayFrames, scan_points

from _cli import lightplane, one_error_line
from _measure_synth import CAM, PLANE, stripe_image, surface, write_scan

NEAR, FAR = 452.0, 458.0  # the calibrated depth range: part of the tilted surface (depths ~444-466 mm)


def _plane(with_volume: bool = True) -> LightPlane:
    meta = {"working_volume": {"depth_mm": [NEAR, FAR], "centre_mm": [0.0, 0.0, 455.0]}} if with_volume else {}
    return LightPlane(PLANE.normal, PLANE.d, PLANE.covariance, meta=meta)


def test_crop_keeps_exactly_the_points_in_the_calibrated_depth_range():
    n_s, d_s = surface()
    frames = [stripe_image(n_s, d_s, shift_px=0.25 * k)[0] for k in range(3)]
    every, _ = scan_points(ArrayFrames(frames), CAM, _plane(), MeasureOptions(keep_outliers=True))
    crop, s = scan_points(ArrayFrames(frames), CAM, _plane(), MeasureOptions(depth_factor=1.0))
    inside = (every["z"] >= NEAR) & (every["z"] <= FAR)
    assert 0.2 < inside.mean() < 0.8  # the range cuts the surface
    key = lambda r: sorted(zip(r["frame"].tolist(), np.round(r["v"], 3).tolist()))  # noqa: E731
    assert key(crop) == key(every[inside])
    assert s.dropped.totals.get("outside the working volume") == int((~inside).sum())
    default, _ = scan_points(ArrayFrames(frames), CAM, _plane(), MeasureOptions())  # twice as wide: all kept
    assert default.size == every.size


def test_cli_crop(tmp_path):
    paths = write_scan(tmp_path, 2)
    _plane().save(tmp_path / "wv.json")
    r = lightplane("measure", *paths, "--camera", tmp_path / "camera.json", "--plane", tmp_path / "wv.json",
                   "--crop", "-o", tmp_path / "c.ply")
    assert r.returncode == 0, r.stderr
    z = read_cloud(tmp_path / "c.ply")["z"]
    assert len(z) and z.min() >= NEAR and z.max() <= FAR and "outside the working volume" in r.stderr
    one_error_line(lightplane("measure", *paths, "--camera", tmp_path / "camera.json", "--plane",
                              tmp_path / "plane.json", "--crop", "-o", tmp_path / "d.ply"), "no working volume")
    assert not (tmp_path / "d.ply").exists()


@pytest.mark.parametrize("flags", [("--crop", "--keep-outliers")])
def test_cli_crop_conflict(tmp_path, flags):
    one_error_line(lightplane("measure", tmp_path / "x.png", "--camera", "c.json", "--plane", "p.json", *flags, "-o",
                              tmp_path / "e.ply"), "--crop")
