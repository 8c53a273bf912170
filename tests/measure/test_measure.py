"""Profiles: stripe frames → 3D points (docs/method.md §Triangulation, §Stripe centres), lookup tables, σ, scans with motion."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _measure_synth import CAM, PLANE, stripe_image, surface  # noqa: E402

from lightplane import LightPlane, LightplaneError  # noqa: E402
from lightplane.measure.profile import ProfileMeasurer, measure_profile
from lightplane.plane.triangulate import points_sigma_mm, profile_axis  # noqa: E402
from lightplane.measure.scan import ArrayFrames, Motion, scan_points  # noqa: E402
from lightplane.measure.options import MeasureOptions  # noqa: E402
from lightplane.stripe.options import StripeOptions  # noqa: E402

# stripe centres of a noise-free Gaussian stripe are good to ~0.01 px (stripe module's spec: 0.015 px);
# rows within END_ROWS of the stripe's ends are biased by the abrupt end and excluded
CENTRE_TOL_PX = 0.015
END_ROWS = 8


def interior(valid: np.ndarray) -> np.ndarray:
    idx = np.flatnonzero(valid)
    keep = valid.copy()
    keep[: idx[0] + END_ROWS] = False
    keep[idx[-1] - END_ROWS + 1:] = False
    return keep


@pytest.fixture(scope="module")
def measurer() -> ProfileMeasurer:
    return ProfileMeasurer(CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5)))


def test_lookup_matches_exact_undistortion(measurer):
    rng = np.random.default_rng(3)
    # rows axis: v on integer rows, u sub-pixel anywhere along the row (also beyond the last pixel centre)
    uv = np.column_stack([rng.uniform(-0.49, CAM.width - 0.51, 4000), rng.integers(0, CAM.height, 4000)])
    exact = CAM.undistort_points(uv, normalized=True)
    err_px = np.abs(measurer.normalized(uv) - exact) * CAM.fx
    assert measurer.axis == "rows" and measurer.has_lookup
    assert err_px.max() < 1e-6
    # columns axis with a roi: same requirement
    m = ProfileMeasurer(CAM, PLANE, MeasureOptions(axis="columns", roi=(40, 30, 500, 400)))
    uvc = np.column_stack([rng.integers(40, 540, 4000), rng.uniform(30, 429, 4000)])
    assert np.max(np.abs(m.normalized(uvc) - CAM.undistort_points(uvc, normalized=True))) * CAM.fx < 1e-6
    # off the grid lines or NaN: exact undistortion / NaN, never a wrong table value
    odd = np.array([[100.3, 200.5], [np.nan, 3.0]])
    got = m.normalized(odd)
    assert np.allclose(got[0], CAM.undistort_points(odd[:1], normalized=True)[0], atol=1e-12)
    assert np.all(np.isnan(got[1]))


def _hermite_reference(m: ProfileMeasurer, uv: np.ndarray) -> np.ndarray:
    """The lookup as numpy expressions (what the kernel replaced), from ``m``'s tables (the blocks the
    points need built)."""
    li, si = (0, 1) if m.axis == "columns" else (1, 0)
    x, y = m.roi[:2]
    line = uv[:, li] - (x if m.axis == "columns" else y)
    t = uv[:, si] - (y if m.axis == "columns" else x)
    L, S = m._xy.shape[:2]
    ok = np.isfinite(line) & np.isfinite(t)
    lidx = np.where(ok, np.rint(line), 0).astype(np.intp)
    on = ok & (np.abs(line - lidx) < 1e-9) & (lidx >= 0) & (lidx < L)
    i0 = np.clip(np.floor(np.where(on, t, 0.0)), 0, S - 2).astype(np.intp)
    f = (np.where(on, t, 0.0) - i0)[:, None]
    li_ = np.where(on, lidx, 0)
    p0, p1 = m._xy[li_, i0], m._xy[li_, i0 + 1]
    m0, m1 = m._dxy[li_, i0].astype(np.float64), m._dxy[li_, i0 + 1].astype(np.float64)
    f2, f3 = f * f, f * f * f
    val = (2 * f3 - 3 * f2 + 1) * p0 + (f3 - 2 * f2 + f) * m0 + (-2 * f3 + 3 * f2) * p1 + (f3 - f2) * m1
    out = np.full(uv.shape, np.nan)
    out[on] = val[on]
    out[ok & ~on] = m.camera.undistort_points(uv[ok & ~on], normalized=True)
    return out


@pytest.mark.parametrize("axis, roi", [("rows", None), ("columns", (40, 30, 500, 400))])
def test_lookup_kernel_equals_the_numpy_expressions(axis, roi):
    """The numba lookup (tables filled lazily, block by block) gives the numpy expressions' numbers bit for
    bit: on and off the grid lines, outside the roi, NaN, the last sample; and from tables built all at
    once the same numbers (a block's values do not depend on which blocks were built with it)."""
    rng = np.random.default_rng(5)
    lazy = ProfileMeasurer(CAM, PLANE, MeasureOptions(axis=axis, roi=roi))
    full = ProfileMeasurer(CAM, PLANE, MeasureOptions(axis=axis, roi=roi))
    full.build_lookup()
    x0, y0, w, h = lazy.roi
    nl, ns = (w, h) if axis == "columns" else (h, w)
    for k in range(3):
        lines = rng.integers(-2, nl + 2 if k else 40, 2000) + (x0 if axis == "columns" else y0)
        samples = rng.uniform(-2, ns + 1, 2000) + (y0 if axis == "columns" else x0)
        uv = np.column_stack([lines, samples] if axis == "columns" else [samples, lines]).astype(float)
        uv[::17] = np.nan
        uv[3::19, 0 if axis == "columns" else 1] += 0.25  # off the grid lines
        uv[0] = (x0 + w - 1, y0 + h - 1)
        got = lazy.normalized(uv)
        assert np.array_equal(got, _hermite_reference(lazy, uv), equal_nan=True)
        assert np.array_equal(got, _hermite_reference(full, uv), equal_nan=True)
        if k == 0:  # the first 40 lines: only the blocks they need are built
            assert 0 < lazy.blocks_built < lazy._built.size


def test_profile_axis_follows_the_plane():
    assert profile_axis(PLANE) == "rows"  # plane contains the camera's y axis: vertical stripe
    assert profile_axis(LightPlane([0.0, np.cos(0.4), -np.sin(0.4)], 190.0)) == "columns"


def test_measure_profile_points_on_surface_and_plane(measurer):
    n_s, d_s = surface()
    img, u_true = stripe_image(n_s, d_s)
    prof = measure_profile(img, CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5)))
    assert prof.axis == "rows" and len(prof) == CAM.height
    assert np.array_equal(prof.valid, np.isfinite(u_true))  # every stripe row, nothing else
    keep = interior(prof.valid)
    assert np.max(np.abs(prof.uv[keep, 0] - u_true[keep])) < CENTRE_TOL_PX
    assert np.array_equal(prof.uv[keep, 1], np.flatnonzero(keep).astype(float))
    pts = prof.points[keep]
    assert np.max(np.abs(PLANE.signed_distance(pts))) < 1e-9  # exactly on the light plane
    # depth error from the centre error: |dX/du| ~ 0.5 mm/px here -> well under 0.01 mm
    assert np.max(np.abs(pts @ n_s + d_s)) < 0.01
    assert np.all(np.isnan(prof.points[~prof.valid]))
    assert np.all(np.isnan(prof.sigma_mm))  # no covariance: sigma unknown, not zero
    # intensity: the stripe (200 over 10, sigma 1.5 px) smoothed by the profile's Gaussian (sigma 1 px and the
    # pixel's 1/12 px^2): 10 + 200 * 1.5 / sqrt(1.5^2 + 1 + 1/12) = 174 at the peak, less off the pixel centre
    expected = 10 + 200 * 1.5 / np.sqrt(1.5**2 + 1 + 1 / 12)
    assert np.all(prof.intensity[keep] <= expected + 1) and np.all(prof.intensity[keep] > expected - 10)
    # the lookup-table path gives the same points
    fast = measurer(img)
    assert np.array_equal(fast.valid, prof.valid)
    assert np.nanmax(np.abs(fast.points - prof.points)) < 1e-6


def test_sigma_from_plane_covariance_matches_uncertainty_module():
    from lightplane.plane.uncertainty import point_sigma_mm

    cov = np.diag([2e-7, 1e-7, 3e-7, 4e-3])
    pl = LightPlane(PLANE.normal, PLANE.d, covariance=cov)
    rng = np.random.default_rng(5)
    uv = np.column_stack([rng.uniform(0, 639, 300), rng.uniform(0, 479, 300)])
    ref = point_sigma_mm(CAM, pl, uv)
    got = points_sigma_mm(pl, CAM.undistort_points(uv, normalized=True))
    assert np.allclose(got, ref, rtol=1e-9, equal_nan=True)
    n_s, d_s = surface()
    img, _ = stripe_image(n_s, d_s)
    prof = ProfileMeasurer(CAM, pl, MeasureOptions(StripeOptions(width_px=3.5)))(img)
    v = prof.valid
    assert np.allclose(prof.sigma_mm[v], point_sigma_mm(CAM, pl, prof.uv[v]), rtol=1e-6)
    assert np.all(prof.sigma_mm[v] > 0)


def test_bad_input_is_refused(measurer):
    with pytest.raises(LightplaneError, match="calibrated for 640x480"):
        measurer(np.zeros((240, 320), np.uint8))
    with pytest.raises(LightplaneError, match="axis"):
        ProfileMeasurer(CAM, PLANE, MeasureOptions(axis="diagonal"))
    with pytest.raises(LightplaneError, match="roi"):
        ProfileMeasurer(CAM, PLANE, MeasureOptions(roi=(600, 0, 100, 100)))
    with pytest.raises(LightplaneError, match="camera"):
        measure_profile(np.zeros((480, 640)), "cam.json", PLANE)


def test_scan_places_frames_by_the_motion():
    n_s, d_s = surface()
    img, _ = stripe_image(n_s, d_s)
    frames = [img] * 4
    base, _ = scan_points(ArrayFrames(frames[:1]), CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5)))
    step, direction = 0.75, np.array([1.0, 0.0, 0.2])
    rec, summ = scan_points(ArrayFrames(frames), CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5)),
                            motion=Motion.linear(step, direction))
    assert summ.n_frames == 4 and summ.n_points == 4 * base.size and not summ.skipped
    unit = direction / np.linalg.norm(direction)
    p0 = np.column_stack([base["x"], base["y"], base["z"]]).astype(float)
    for i in range(4):
        r = rec[rec["frame"] == i]
        p = np.column_stack([r["x"], r["y"], r["z"]]).astype(float)
        assert np.allclose(p, p0 - i * step * unit, atol=1e-4)  # float32 storage at ~450 mm
        assert np.array_equal(r["v"], base["v"])
    # positions: only differences to the first row matter
    pos = np.array([[5.0, 1.0, 0.0], [5.0, 1.0, 0.0], [7.0, 1.0, 0.0], [5.0, 4.0, 0.0]])
    rec2, _ = scan_points(ArrayFrames(frames), CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5)),
                          motion=Motion.from_positions(pos))
    for i in range(4):
        r = rec2[rec2["frame"] == i]
        p = np.column_stack([r["x"], r["y"], r["z"]]).astype(float)
        assert np.allclose(p, p0 - (pos[i] - pos[0]), atol=1e-4)


def test_scan_in_worker_processes_or_threads_gives_the_same_records():
    n_s, d_s = surface()
    frames = [stripe_image(n_s, d_s, shift_px=0.3 * k)[0] for k in range(6)]
    one, _ = scan_points(ArrayFrames(frames), CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5)),
                         motion=Motion.linear(1.0, [1, 0, 0]))
    two, _ = scan_points(ArrayFrames(frames), CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5)),
                         motion=Motion.linear(1.0, [1, 0, 0]), workers=2)
    threads, _ = scan_points(ArrayFrames(frames), CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5)),
                             motion=Motion.linear(1.0, [1, 0, 0]), workers=2, executor="thread")
    assert one.size > 6 * 300
    assert np.array_equal(one.view(np.uint8), two.view(np.uint8))
    assert np.array_equal(one.view(np.uint8), threads.view(np.uint8))


def test_positions_file_formats(tmp_path):
    f = tmp_path / "enc.csv"
    f.write_text("frame,dx,dy,dz\n0,0,0,0\n1,0.5,0,0.1\n2,1.0,0,0.2\n")
    m = Motion.load_positions(f)
    assert m.n_frames == 3 and np.allclose(m.offset(2), [1.0, 0.0, 0.2])
    f.write_text("# encoder mm\n10.0\n10.5\n11.5\n")
    m = Motion.load_positions(f, direction=[0, 2, 0])
    assert np.allclose(m.offset(2), [0.0, 1.5, 0.0])
    with pytest.raises(LightplaneError, match="direction"):
        Motion.load_positions(f)
    f.write_text("1,2\n3,x\n")
    with pytest.raises(LightplaneError, match="row 2"):
        Motion.load_positions(f)
    with pytest.raises(LightplaneError, match="no such"):
        Motion.load_positions(tmp_path / "none.csv")
    with pytest.raises(LightplaneError, match="direction"):
        Motion.linear(1.0, [0, 0, 0])


def test_smoothing_along_the_profile_averages_noise_without_bias():
    n_s, d_s = surface()
    clean, u_true = stripe_image(n_s, d_s)
    rng = np.random.default_rng(11)
    noisy = clean + rng.normal(0, 3.0, clean.shape).astype(np.float32)  # independent centre noise per row
    rows = interior(np.isfinite(u_true))
    raw = ProfileMeasurer(CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5)), lookup=False)
    smooth = ProfileMeasurer(CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5), smooth_lines=15), lookup=False)

    def rms_to_surface(prof):
        assert prof.valid[rows].all()
        return float(np.sqrt(np.mean((prof.points[rows] @ n_s + d_s) ** 2)))

    # independent pixel noise gives centre noise correlated over a few rows (the profile's Gaussian spans
    # them), so a quadratic fit over 15 lines keeps ~0.7 of it, not the 0.38 of independent noise
    assert rms_to_surface(smooth(noisy)) < 0.8 * rms_to_surface(raw(noisy))
    # noise-free: the stripe is nearly straight over 15 rows, so smoothing changes nothing measurable
    # (away from the stripe's ends, whose few biased centres the window carries inwards)
    a, b = raw(clean), smooth(clean)
    keep = rows.copy()
    idx = np.flatnonzero(keep)
    keep[idx[:15]] = keep[idx[-15:]] = False
    assert np.max(np.abs(a.points[keep] - b.points[keep])) < 2e-3
    with pytest.raises(LightplaneError, match="smooth_lines"):
        ProfileMeasurer(CAM, PLANE, MeasureOptions(smooth_lines=4))


def test_wrong_size_frame_mid_scan_stops_worker_processes_cleanly():
    n_s, d_s = surface()
    img, _ = stripe_image(n_s, d_s)
    frames = [img] * 3 + [img[:240, :320]] + [img] * 3
    with pytest.raises(LightplaneError, match="calibrated for 640x480"):
        scan_points(ArrayFrames(frames), CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5)), workers=2,
                    executor="process")


def test_width_filter_drops_lines_whose_stripe_is_too_narrow_or_too_wide():
    n_s, d_s = surface()
    _, u_c = stripe_image(n_s, d_s)
    rows = np.arange(CAM.height)
    on = np.isfinite(u_c)
    sigma = np.full(CAM.height, 1.5)
    narrow = on & (rows >= 100) & (rows < 130)  # FWHM 0.5x the rest: below the default 0.8x
    wide = on & (rows >= 300) & (rows < 320)  # 3x: above the default 2x
    sigma[narrow], sigma[wide] = 0.75, 4.5
    u = np.arange(CAM.width, dtype=float)[None, :]
    img = 10.0 + np.where(on[:, None], 200.0 * np.exp(-0.5 * ((u - u_c[:, None]) / sigma[:, None]) ** 2), 0.0)
    img = img.astype(np.float32)
    off = ProfileMeasurer(CAM, PLANE,
                          MeasureOptions(StripeOptions(width_px=3.5), min_width_ratio=0.0, max_width_ratio=np.inf))(img)
    assert not off.width_rejected.any()
    # lines 2 rows away from a width change: the smoothing scale blurs the boundary
    core = lambda m: m & ~np.convolve(~m & on, np.ones(7), "same").astype(bool)  # noqa: E731
    assert off.valid[core(narrow) | core(wide)].all()  # the extractor itself keeps them
    prof = ProfileMeasurer(CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5, local_width=False)))(img)
    assert prof.width_rejected[core(narrow)].all() and prof.width_rejected[core(wide)].all()
    assert not prof.valid[prof.width_rejected].any() and np.isnan(prof.points[prof.width_rejected]).all()
    # elsewhere (uniform width) nothing is dropped and the points are untouched
    rest = interior(off.valid) & ~np.convolve(narrow | wide, np.ones(15), "same").astype(bool)
    assert not prof.width_rejected[rest].any()
    assert np.array_equal(prof.points[rest], off.points[rest], equal_nan=True)
    assert prof.n_valid == off.n_valid - int(prof.width_rejected.sum())
    # measure_profile filters the same way
    assert np.array_equal(measure_profile(img, CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5, local_width=False))
                                          ).width_rejected, prof.width_rejected)
    # by default a run of 20 lines three times as wide is measured at its own width and kept (a scattering
    # surface, defocus); the narrow run is still dropped
    local = ProfileMeasurer(CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5)))(img)
    assert local.valid[core(wide)].all() and not local.width_rejected[core(wide)].any()
    assert local.width_rejected[core(narrow)].all()
    assert np.allclose(local.line_width_px[core(wide)], 3 * np.median(local.width_px[rest]), rtol=0.15)


def test_width_filter_needs_enough_lines_and_valid_ratios():
    n_s, d_s = surface()
    img, u_c = stripe_image(n_s, d_s)
    img[np.flatnonzero(np.isfinite(u_c))[15:]] = 10.0  # keep only 15 stripe rows: too few for a median
    # (15 rows are also too few to count as a stripe: the stripe evidence is off to see the width filter alone)
    m = ProfileMeasurer(CAM, PLANE, MeasureOptions(StripeOptions(width_px=3.5), min_width_ratio=0.99,
                                                   max_width_ratio=1.01, stripe_evidence=False))
    prof = m(img)
    assert 0 < prof.n_valid < 20 and not prof.width_rejected.any()
    for lo, hi in ((-0.1, 2.0), (1.0, 2.0), (0.5, 1.0), (0.5, np.nan)):
        with pytest.raises(LightplaneError, match="width_ratio"):
            ProfileMeasurer(CAM, PLANE, MeasureOptions(min_width_ratio=lo, max_width_ratio=hi))


def test_profile_kernels_match_numpy():
    """The compiled triangulation and width median give numpy's numbers bit for bit
    (triangulate_normalized against the intersection in numpy array operations, its grazing and
    behind flags; np.median of the valid finite widths), with
    grazing rays, rays behind the camera, NaN rays and even and odd counts."""
    from lightplane.measure._kernels import median_where
    from lightplane.plane.triangulate import triangulate_normalized

    rng = np.random.default_rng(5)
    n = 2000
    xy = rng.uniform(-0.8, 0.8, (n, 2))
    xy[::17] = np.nan
    for plane in (PLANE, LightPlane([0.3, -0.2, 0.93], -40.0), LightPlane([1.0, 0.0, 0.0], -1.0)):
        a, b, c = plane.normal
        # rays along the plane: grazing (den exactly 0 for the first few)
        xy[1:40:3] = np.column_stack([rng.uniform(-0.5, 0.5, 13), np.zeros(13)])
        if abs(b) > 0:
            xy[1:40:3, 1] = -(a * xy[1:40:3, 0] + c) / b
        # the ray-plane intersection written out with numpy's array operations
        den = a * xy[:, 0] + b * xy[:, 1] + c
        grazing = ~(np.abs(den) >= 1e-3 * np.sqrt(xy[:, 0] ** 2 + xy[:, 1] ** 2 + 1.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            s = -plane.d / den
        behind = ~grazing & ~(s > 0)
        s[grazing | behind] = np.nan
        ref = np.column_stack([xy[:, 0] * s, xy[:, 1] * s, s])
        tri = triangulate_normalized(plane, xy, min_cos=1e-3)
        assert tri.grazing.any() and tri.valid.any() and (plane.d != -1.0 or tri.behind.any())
        np.testing.assert_array_equal(tri.grazing, grazing)
        np.testing.assert_array_equal(tri.behind, behind)
        assert np.array_equal(tri.points, ref, equal_nan=True)
    for m in (0, 1, 2, 7, 20, 501, 1000):
        w = rng.normal(5.0, 1.0, m)
        w[::5] = np.nan
        mask = rng.random(m) > 0.2
        med, cnt = median_where(w, mask)
        sel = w[mask & np.isfinite(w)]
        assert cnt == sel.size
        assert (np.isnan(med) and cnt == 0) or med == np.median(sel)
