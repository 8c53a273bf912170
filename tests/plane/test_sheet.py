"""The curved light sheet: the cone's geometry, the flatness test, triangulation on the sheet."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lightplane.core.errors import LightplaneError
from lightplane.plane.model import LightPlane
from lightplane.plane.sheet import LightSheet, SheetOptions, fit_sheet, sheet_points_sigma_mm, triangulate_sheet
from lightplane.plane.triangulate import triangulate_normalized
from lightplane.plane.zhou import fit_plane
from lightplane.simulate import render_core as rc
from lightplane.simulate.render import _laser_row, _IMAGING, curved_sheet, sheet_tilt_for_sag
from lightplane.simulate.scene import default_plane
from lightplane.simulate.sheet import SheetObservation, onto_sheet, sheet_distance, sheet_field_points, sheet_stripe_points

from _cli import lightplane
from _renders import cached_circle_render

PLANE = default_plane()
TILT = sheet_tilt_for_sag(0.05)


def test_cone_is_tau_y2_over_2x_and_its_sag():
    truth = curved_sheet(PLANE, TILT)
    assert truth["sag_mm"] == pytest.approx(0.05, rel=1e-9)
    apex, ex, ey, tau = truth["apex_mm"], truth["centre_ray"], truth["across_fan"], truth["tilt_rad"]
    x, y = np.meshgrid([380.0, 500.0, 620.0], [-60.0, -20.0, 35.0, 60.0])
    flat = apex + x.reshape(-1, 1) * ex + y.reshape(-1, 1) * ey
    on = onto_sheet(PLANE, TILT, flat, PLANE.normal)
    w = (on - flat) @ PLANE.normal
    # first order in tau and (y/x)²: within 1.5 % at y/x <= 0.16
    np.testing.assert_allclose(w, tau * y.ravel()**2 / (2 * x.ravel()), rtol=0.015, atol=1e-9)
    # the renderer's distance is the same function; flat: the plane's n.p + d, and no cone in the row
    row = _laser_row(PLANE, _IMAGING["clean"], 1.0, np.random.default_rng(0), TILT)
    p = on + np.random.default_rng(1).normal(0, 0.3, on.shape)
    got = np.array([rc._cone_distance(row, *q) for q in p])
    np.testing.assert_allclose(got, sheet_distance(PLANE, TILT, p), atol=1e-12)
    flat_row = _laser_row(PLANE, _IMAGING["clean"], 1.0, np.random.default_rng(0), 0.0)
    assert np.all(flat_row[12:] == 0.0) and curved_sheet(PLANE, 0.0) is None
    np.testing.assert_allclose(sheet_distance(PLANE, 0.0, p), p @ PLANE.normal + PLANE.d, atol=1e-9)


def _calibration(seed: int, tilt: float, obs: SheetObservation = SheetObservation()):
    pts = sheet_stripe_points(12, np.random.default_rng(seed), tilt, obs)
    plane = fit_plane(np.vstack(pts))
    return plane, fit_sheet(plane, pts)


def test_flatness_test_keeps_the_plane_on_a_flat_sheet_and_finds_the_cone():
    for seed in (0, 1, 2):
        _, fit = _calibration(seed, 0.0)
        assert not fit.test.curved and abs(fit.test.z) < 3.0
        _, fit = _calibration(seed, TILT)
        assert fit.test.curved and fit.test.z > 5.0
        # sag along lines of half-length h at distance x from the apex: tau h² / (2 x), x ~ 500 mm
        tau, h = np.radians(TILT), fit.test.half_length_mm
        assert fit.test.sag_mm == pytest.approx(tau * h**2 / (2 * 500.0), abs=4 * fit.test.sag_sigma_mm + 0.001)


def test_triangulation_on_the_sheet_without_noise_and_with_a_zero_curvature():
    obs = SheetObservation(noise_px=1e-4, pose_tilt_deg=0.0, pose_offset_mm=0.0)
    plane, fit = _calibration(3, TILT, obs)
    field = sheet_field_points(TILT)
    xy = field[:, :2] / field[:, 2:]
    err_sheet = np.linalg.norm(triangulate_sheet(fit.sheet, xy) - field, axis=1)
    err_plane = np.linalg.norm(triangulate_normalized(plane, xy).points - field, axis=1)
    assert np.sqrt(np.mean(err_sheet**2)) < 0.003 < 0.03 < np.sqrt(np.mean(err_plane**2))
    flat = LightSheet(plane, fit.sheet.origin, fit.sheet.axes, fit.sheet.scale_mm, np.zeros(8))
    np.testing.assert_allclose(triangulate_sheet(flat, xy), triangulate_normalized(plane, xy).points, atol=1e-9)


def test_point_sigma_is_the_size_of_the_error():
    field = sheet_field_points(TILT)
    xy = field[:, :2] / field[:, 2:]
    pred, actual = [], []
    for seed in range(5):
        _, fit = _calibration(10 + seed, TILT)
        s = sheet_points_sigma_mm(fit.sheet, xy)
        assert np.all(np.isfinite(s)) and np.all(s > 0)
        pred.append(np.mean(s**2))
        actual.append(np.mean(np.sum((triangulate_sheet(fit.sheet, xy) - field)**2, axis=1)))
    # five calibrations: the RMS ratio is known to about +-35 %; the bias of the model is well inside
    assert 0.4 < np.sqrt(np.mean(pred) / np.mean(actual)) < 2.5


def test_bad_options_and_too_few_images():
    with pytest.raises(LightplaneError):
        SheetOptions(z_curved=0.0)
    with pytest.raises(LightplaneError):
        SheetOptions(terms=("q_uu",))
    pts = sheet_stripe_points(2, np.random.default_rng(0), 0.0)
    with pytest.raises(LightplaneError, match="at least 3 images"):
        fit_sheet(fit_plane(np.vstack(pts)), pts)


def test_calibrate_plane_records_the_flatness_test(tmp_path):
    render = cached_circle_render()
    out = tmp_path / "plane.json"
    r = lightplane("calibrate-plane", render, "--camera", render / "camera.json", "--diameter", "50", "-o", out)
    assert r.returncode == 0, r.stderr
    d = json.loads(out.read_text())
    # a flat sheet: the test is recorded, the plane is enough, no curved sheet is written
    assert d["sheet_test"]["images"] == 5 and not d["sheet_test"]["curved"] and "sheet" not in d
    assert abs(d["sheet_test"]["z"]) < 3.0 and "the plane is enough" in r.stdout
    assert LightPlane.load(out).d == pytest.approx(d["d"])


def test_sheet_file_record_round_trip_and_bad_record():
    plane, fit = _calibration(5, TILT)
    back = LightSheet.from_dict(plane, json.loads(json.dumps(fit.sheet.to_dict())))
    field = sheet_field_points(TILT)
    xy = field[:, :2] / field[:, 2:]
    np.testing.assert_array_equal(triangulate_sheet(back, xy), triangulate_sheet(fit.sheet, xy))
    np.testing.assert_array_equal(sheet_points_sigma_mm(back, xy), sheet_points_sigma_mm(fit.sheet, xy))
    assert back.meta["flatness_test"]["curved"]
    with pytest.raises(LightplaneError, match="'sheet'"):
        LightSheet.from_dict(plane, {"origin_mm": [0, 0]})
