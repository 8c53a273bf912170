"""Range images of a linear scan against the exact surface: a tilted flat surface moved across the sheet in
known steps, its stripe drawn exactly (tests/_measure_synth.py), measured, resampled; the 16-bit values read
back through their scale and offset must give the true height within half a level plus the measurement's
own error, which the float arrays show against the same truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lightplane.core.errors import LightplaneError
from lightplane.measure.pointcloud import read_cloud, write_cloud
from lightplane.measure.rangeimage import RangeImageOptions, range_image, read_range_image, write_range_image
from lightplane.measure.scan import ArrayFrames, scan_points
from lightplane.motion.model import Motion

from _cli import lightplane, one_error_line
from _measure_synth import CAM, PLANE, stripe_image, surface

STEP_MM = 0.4
DIRECTION = np.array([1.0, 0.0, 0.0])  # across the sheet (its normal is mostly along x)
N_FRAMES = 9


@pytest.fixture(scope="module")
def scan():
    n_s, d_s = surface()
    frames = [stripe_image(n_s, d_s - k * STEP_MM * float(n_s @ DIRECTION))[0] for k in range(N_FRAMES)]
    rec, _ = scan_points(ArrayFrames(frames), CAM, PLANE, motion=Motion.linear(STEP_MM, DIRECTION))
    return rec, n_s, d_s


def _true_z(n_s, d_s, x, y):
    return -(n_s[0] * x + n_s[1] * y + d_s) / n_s[2]


def _raw_error(rec, n_s, d_s):
    x, y, z = (rec[c].astype(np.float64) for c in "xyz")
    return z - _true_z(n_s, d_s, x, y)


def test_interpolation_is_never_worse_than_its_points(scan):
    """A flat surface is affine: a pixel interpolated between two points on it lies on it, so a pixel's
    error is at most its points' (the drawn stripe's cut ends give the cloud's few biased points)."""
    rec, n_s, d_s = scan
    raw = np.abs(_raw_error(rec, n_s, d_s))
    ri = range_image(rec, RangeImageOptions(step_mm=0.05))
    X, Y, Z = ri.xyz.astype(np.float64)
    ok = np.isfinite(Z)
    assert np.max(np.abs(Z[ok] - _true_z(n_s, d_s, X[ok], Y[ok]))) <= raw.max() + 1e-4


def test_range_image_values_through_scale_and_offset_match_the_surface(scan, tmp_path):
    rec, n_s, d_s = scan
    # the points of the stripe's last drawn rows (cut ends: the measurement's own bias, up to 0.5 mm) left out
    rec = rec[np.abs(_raw_error(rec, n_s, d_s)) < 0.01]
    ri = range_image(rec, RangeImageOptions(step_mm=0.05), frame_description="camera frame, object at frame 0")
    assert ri.across == "y" and ri.height == "z"  # the stripe runs down the image: profiles along y
    rows, cols = ri.shape
    assert rows == N_FRAMES and ri.frame0 == 0
    X, Y, Z = ri.xyz.astype(np.float64)
    ok = np.isfinite(Z)
    assert ok.mean() > 0.9
    # the columns: a regular grid through 0 (exact), the across coordinate's array is the grid itself
    grid = ri.origin_mm + ri.step_mm * np.arange(cols)
    assert np.allclose(Y[ok], np.broadcast_to(grid, Y.shape)[ok], atol=1e-4)
    assert abs(ri.origin_mm / ri.step_mm - round(ri.origin_mm / ri.step_mm)) < 1e-9
    # the float arrays on the surface: the measurement's own error (noise-free exact stripes)
    err_float = Z[ok] - _true_z(n_s, d_s, X[ok], Y[ok])
    assert np.max(np.abs(err_float)) < 0.01, np.max(np.abs(err_float))
    # the 16-bit image written, read back, through its scale and offset
    png, npz = write_range_image(tmp_path / "r.png", ri)
    values, meta = read_range_image(png)
    assert values.dtype == np.uint16 and values.shape == (rows, cols)
    assert np.array_equal(values == 0, ~ok)  # 0: no point, SICK's missing data
    v = meta["values"]
    assert v["coordinate"] == "z" and meta["columns"]["step_mm"] == ri.step_mm
    z16 = v["offset_mm"] + values.astype(np.float64) * v["scale_mm"]
    assert np.max(np.abs(z16[ok] - Z[ok])) <= v["scale_mm"] / 2 + 1e-4  # float32 arrays: 1e-4 mm at 450 mm
    assert np.max(np.abs(z16[ok] - _true_z(n_s, d_s, X[ok], Y[ok]))) <= v["scale_mm"] / 2 + 0.01
    span = float(np.nanmax(Z) - np.nanmin(Z))  # the finest 1/2/5 x 10^k that spans the heights
    assert v["scale_mm"] * 65534 >= span and v["scale_mm"] <= 2.5 * span / 65534 + 1e-15
    assert round(v["scale_mm"] / 10 ** np.floor(np.log10(v["scale_mm"])), 9) in (1.0, 2.0, 5.0)
    arrays = np.load(npz)
    assert np.array_equal(arrays["Z"], ri.xyz[2], equal_nan=True) and json.loads(str(arrays["meta"])) == meta
    # TIFF: the same values and metadata
    tif, _ = write_range_image(tmp_path / "t.tif", ri)
    tv, tmeta = read_range_image(tif)
    assert np.array_equal(tv, values) and tmeta == meta


def test_gaps_are_not_bridged_and_bad_options_refused(scan):
    rec, _, _ = scan
    cut = rec[(rec["y"] < -1.0) | (rec["y"] > 1.0)]  # a 2 mm hole across every profile
    ri = range_image(cut, RangeImageOptions(step_mm=0.05))
    cols = ri.origin_mm + ri.step_mm * np.arange(ri.shape[1])
    hole = (cols > -0.9) & (cols < 0.9)
    assert not np.isfinite(ri.heights[:, hole]).any() and np.isfinite(ri.heights[:, ~hole]).mean() > 0.8
    for kw in ({"across": "q"}, {"height": "z", "across": "z"}, {"step_mm": 0.0}, {"scale_mm": -1.0},
               {"max_gap_steps": 0.5}, {"scale_mm": 1e308}, {"step_mm": 1e308}):
        with pytest.raises(LightplaneError):
            RangeImageOptions(**kw)
    with pytest.raises(LightplaneError, match="65535 levels"):
        range_image(rec, RangeImageOptions(scale_mm=1e-6))
    # a level coarser than the heights' whole span would write one flat value: refused
    span = float(np.ptp(rec["z"]))
    with pytest.raises(LightplaneError, match="less than one level"):
        range_image(rec, RangeImageOptions(scale_mm=2.0 * span))


def test_cli_writes_both_files_and_refuses_bad_input(scan, tmp_path):
    rec, _, _ = scan
    write_cloud(tmp_path / "c.ply", rec, comments=["lightplane point cloud: x y z in mm (camera frame, object at frame 0)"])
    r = lightplane("range-image", tmp_path / "c.ply", "-o", tmp_path / "r.png", "--step", "0.05")
    assert r.returncode == 0, r.stderr
    assert "mm" in r.stdout and (tmp_path / "r.npz").is_file()
    _, meta = read_range_image(tmp_path / "r.png")
    assert meta["coordinates"].startswith("camera frame, object at frame 0")
    assert meta["provenance"]["inputs"] == [str(tmp_path / "c.ply")] and meta["provenance"]["versions"]["lightplane"]
    one_error_line(lightplane("range-image", tmp_path / "c.ply", "-o", tmp_path / "r.png"), "already exists")
    one_error_line(lightplane("range-image", tmp_path / "c.ply", "-o", tmp_path / "r.jpg"), ".png")
    np.save(tmp_path / "xyz.npy", np.zeros((3, 3)))
    one_error_line(lightplane("range-image", tmp_path / "xyz.npy", "-o", tmp_path / "q.png"))
    assert not (tmp_path / "q.png").exists() and not (tmp_path / "q.npz").exists()
    assert read_cloud(tmp_path / "c.ply").size == rec.size
