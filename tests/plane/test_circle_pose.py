"""Tests of circle_poses (paper §2.2.2, docs/method.md §Circle pose) and fit_rim_conic."""

from __future__ import annotations

import numpy as np
import pytest

from lightplane.plane.circle_pose import circle_poses, conic_residuals_px, fit_rim_conic
from lightplane.core.errors import LightplaneError
from lightplane.simulate.scene import TargetPlacement, default_camera, sample_placements


def _random_placements(n, rng):
    """Discs of 20–100 mm anywhere in the view at 200–800 mm, tilted 3–75 deg (wider than docs/conventions.md §Default sensor).

    (Far, tiny discs, e.g. 5 mm at 2 m — a 12 px ellipse — lose accuracy to rounding in
    the conic itself: ~1e-8 mm.)
    """
    out = []
    cam = default_camera(distortion=False)
    while len(out) < n:
        z = rng.uniform(200.0, 800.0)
        xy = rng.uniform(-0.12, 0.12, 2) * z
        c = np.array([xy[0], xy[1], z])
        view = -c / np.linalg.norm(c)
        tilt = rng.uniform(np.deg2rad(3.0), np.deg2rad(75.0))
        axis = np.cross(view, rng.normal(size=3))
        axis /= np.linalg.norm(axis)
        nrm = np.cos(tilt) * view + np.sin(tilt) * np.cross(axis, view)
        tp = TargetPlacement(c, nrm, rng.uniform(20.0, 100.0))
        if np.all(tp.rim_points(16)[:, 2] > 1.0):
            out.append(tp)
    return cam, out


def test_exactly_one_candidate_matches_truth_1000_poses():
    rng = np.random.default_rng(10)
    cam, tps = _random_placements(1000, rng)
    worst_true, best_false = 0.0, np.inf
    for tp in tps:
        a, b = circle_poses(tp.conic(cam), cam.K, tp.radius_mm)
        errs = []
        for p in (a, b):
            assert abs(np.linalg.norm(p.normal) - 1) < 1e-12
            assert p.normal @ p.center < 0 and p.center[2] > 0 and p.radius_mm == tp.radius_mm
            errs.append(max(np.linalg.norm(p.center - tp.center), np.linalg.norm(p.normal - tp.normal) * tp.radius_mm))
        errs.sort()
        worst_true = max(worst_true, errs[0])
        best_false = min(best_false, errs[1])
    assert worst_true < 1e-9  # mm
    assert best_false > 1e-6  # tilt >= 3 deg: the other solution is clearly different


def test_both_candidates_reproject_onto_the_ellipse():
    rng = np.random.default_rng(11)
    cam = default_camera(distortion=False)
    for tp in sample_placements(30, rng):
        C = tp.conic(cam)
        for p in circle_poses(C, cam.K, tp.radius_mm):
            rim = TargetPlacement(p.center, p.normal, 2 * p.radius_mm).rim_points(50)
            uv = cam.project(rim, distort=False)
            assert np.max(conic_residuals_px(C, uv)) < 1e-7


def test_face_on_gives_coincident_solutions():
    cam = default_camera(distortion=False)
    tp = TargetPlacement([0.0, 0.0, 400.0], [0.0, 0.0, -1.0], 50.0)
    a, b = circle_poses(tp.conic(cam), cam.K, 25.0)
    assert np.allclose(a.center, b.center, atol=1e-6) and np.allclose(a.center, tp.center, atol=1e-6)


def test_scale_and_sign_of_conic_do_not_matter():
    cam = default_camera(distortion=False)
    tp = sample_placements(1, np.random.default_rng(12))[0]
    C = tp.conic(cam)
    a, b = circle_poses(C, cam.K, 25.0)
    a2, b2 = circle_poses(-37.0 * C, cam.K, 25.0)
    got = sorted([a2, b2], key=lambda p: p.center[0])
    ref = sorted([a, b], key=lambda p: p.center[0])
    for p, q in zip(got, ref):
        assert np.allclose(p.center, q.center, atol=1e-9) and np.allclose(p.normal, q.normal, atol=1e-12)


def test_fit_rim_conic_exact_and_noisy():
    rng = np.random.default_rng(13)
    cam = default_camera(distortion=False)
    rms_all = []
    for tp in sample_placements(10, rng):
        uv = cam.project(tp.rim_points(200), distort=False)
        C = fit_rim_conic(uv)
        C0 = tp.conic(cam)
        assert np.max(np.abs(C - C0)) < 1e-9
        sigma = 0.2
        noisy = uv + rng.normal(0, sigma, uv.shape)
        Cn = fit_rim_conic(noisy)
        # residuals of the truth's points to the noisy fit: well below the noise
        assert np.sqrt(np.mean(conic_residuals_px(Cn, uv) ** 2)) < sigma / 2
        # residuals of the noisy points: ~ sigma (RMS of the orthogonal noise component)
        rms_all.append(np.mean(conic_residuals_px(Cn, noisy) ** 2))
    # 2000 residuals, 5 fitted parameters per 200: expected RMS sigma * sqrt(195 / 200); its std ~1.6 %
    assert np.sqrt(np.mean(rms_all)) == pytest.approx(sigma * np.sqrt(195 / 200), rel=0.06)


@pytest.mark.parametrize(
    "conic, msg",
    [
        (np.eye(3), "imaginary"),
        (np.diag([1.0, -1.0, -1.0]), "not an ellipse"),
        (np.full((3, 3), np.nan), "finite"),
        (np.eye(2), "3x3"),
    ],
)
def test_circle_poses_bad_conic(conic, msg):
    with pytest.raises(LightplaneError, match=msg):
        circle_poses(conic, default_camera().K, 25.0)


def test_circle_poses_bad_radius():
    tp = TargetPlacement([0.0, 0.0, 400.0], [0.1, 0.0, -1.0], 50.0)
    cam = default_camera()
    for r in (0.0, -1.0, np.nan):
        with pytest.raises(LightplaneError, match="radius_mm"):
            circle_poses(tp.conic(cam), cam.K, r)


def test_fit_rim_conic_bad_points():
    with pytest.raises(LightplaneError, match="at least 5"):
        fit_rim_conic(np.zeros((3, 2)))
    line = np.column_stack([np.arange(20.0), 2 * np.arange(20.0)])
    with pytest.raises(LightplaneError, match="rim"):
        fit_rim_conic(line)
    t = np.linspace(-2, 2, 40)
    hyperbola = np.column_stack([np.cosh(t), np.sinh(t)]) * 50
    hyperbola = np.vstack([hyperbola, -hyperbola])
    # the direct fit is ellipse-specific: a hyperbola gets an ellipse with huge residuals
    assert np.sqrt(np.mean(conic_residuals_px(fit_rim_conic(hyperbola), hyperbola) ** 2)) > 5.0
    bad = np.ones((10, 2))
    bad[3, 0] = np.nan
    with pytest.raises(LightplaneError, match="NaN"):
        fit_rim_conic(bad)


def test_batched_versions_match_single_and_flag_bad_items():
    from lightplane.core.geometry import fit_conics
    from lightplane.plane.circle_pose import circle_poses_batch

    rng = np.random.default_rng(14)
    cam = default_camera(distortion=False)
    tps = sample_placements(6, rng)
    sets = [cam.project(tp.rim_points(100), distort=False) + rng.normal(0, 0.2, (100, 2)) for tp in tps]
    sets.insert(2, np.column_stack([np.arange(20.0), np.arange(20.0)]))  # collinear: flagged, not fatal
    conics, problems = fit_conics(sets)
    assert problems[2] is not None and "collinear" in problems[2] and np.all(np.isnan(conics[2]))
    for k, pts in enumerate(sets):
        if k != 2:
            assert problems[k] is None
            assert np.allclose(conics[k], fit_rim_conic(pts), atol=1e-15)
    good = [k for k in range(len(sets)) if k != 2]
    centers, normals, probs = circle_poses_batch(conics[good], cam.K, 25.0)
    assert all(p is None for p in probs)
    for j, k in enumerate(good):
        a, b = circle_poses(conics[k], cam.K, 25.0)
        assert np.allclose(centers[j], [a.center, b.center], atol=1e-12)
        assert np.allclose(normals[j], [a.normal, b.normal], atol=1e-15)
    _, _, probs = circle_poses_batch(np.stack([np.eye(3), conics[0]]), cam.K, 25.0)
    assert "imaginary" in probs[0] and probs[1] is None
