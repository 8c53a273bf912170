"""Tests of the light-plane solvers (paper §2.2.3, docs/method.md §Light plane): candidates, `paper`, `global`,
and the public entry `calibrate_plane_from_points`.  Ground truth from lightplane.simulate.scene."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lightplane.core.errors import LightplaneError
from lightplane.plane.solvers import SolverOptions
from lightplane.plane.model import LightPlane
from lightplane.plane.solvers import _KAPPA, _msd, _stripe_line, _tau, calibrate_plane_from_points, prepare_placement
from lightplane.simulate.scene import (
    PlacementOptions,
    PAPER_DISTANCE_MM,
    TargetPlacement,
    default_camera,
    default_plane,
    paper_camera,
    paper_plane,
    sample_placements,
    synthetic_observations,
)


def _angle(a: LightPlane, b: LightPlane) -> float:
    """Angle between plane normals (rad), accurate for tiny angles (arccos is not)."""
    return float(np.arctan2(np.linalg.norm(np.cross(a.normal, b.normal)), abs(a.normal @ b.normal)))


def _scene(n, rng, sigma_px=0.0, camera=None, plane=None, n_rim=200, n_stripe=300, **kw):
    camera = default_camera() if camera is None else camera
    plane = default_plane() if plane is None else plane
    ps = sample_placements(n, rng, PlacementOptions(**kw), camera=camera, plane=plane)
    obs = [synthetic_observations(camera, plane, p, n_rim=n_rim, n_stripe=n_stripe, sigma_px=sigma_px, rng=rng)
           for p in ps]
    return camera, plane, ps, [o[0] for o in obs], [o[1] for o in obs]


def _true_candidates_chosen(res, ps, tol_mm):
    for pr, tp in zip(res.placements, ps):
        if pr.used and np.linalg.norm(pr.pose.center - tp.center) > tol_mm:
            return False
    return True


# ------------------------------------------------------------------ noise-free
def test_noise_free_paper_and_global_exact_over_1000_poses():
    """84 scenes x 12 placements = 1008 random poses (docs/conventions.md §Default sensor geometry, with distortion)."""
    rng = np.random.default_rng(100)
    worst = {"paper": 0.0, "global": 0.0}
    worst_d = {"paper": 0.0, "global": 0.0}
    for _ in range(84):
        cam, plane, ps, rims, stripes = _scene(12, rng)
        for method in ("paper", "global"):
            res = calibrate_plane_from_points(cam, 50.0, rims, stripes, method=method)
            worst[method] = max(worst[method], _angle(res.plane, plane))
            worst_d[method] = max(worst_d[method], abs(res.plane.d - plane.d))
            assert _true_candidates_chosen(res, ps, 1e-9)
            if method == "global":
                assert res.n_used == 12 and res.ambiguity.separated
    for method in worst:
        assert worst[method] < 1e-9, method  # rad
        assert worst_d[method] < 1e-9, method  # mm


def test_global_is_order_independent():
    rng = np.random.default_rng(101)
    cam, plane, ps, rims, stripes = _scene(8, rng, sigma_px=0.2)
    a = calibrate_plane_from_points(cam, 50.0, rims, stripes, method="global")
    perm = rng.permutation(8)
    b = calibrate_plane_from_points(cam, 50.0, [rims[i] for i in perm], [stripes[i] for i in perm], method="global")
    assert _angle(a.plane, b.plane) < 1e-12 and abs(a.plane.d - b.plane.d) < 1e-9
    for j, i in enumerate(perm):
        assert a.placements[i].candidate == b.placements[j].candidate


# -------------------------------------------------------------- noise model
def test_chord_tolerance_model_against_monte_carlo():
    """tau_i (plane.py notes) must bound the true chord's offset: msd/tau² well under κ² = 25
    for every true chord, and the wrong chord far above it (default geometry, 0.3 px)."""
    rng = np.random.default_rng(102)
    sigma = 0.3
    true_r, wrong_r = [], []
    for _ in range(6):
        cam, plane, ps, rims, stripes = _scene(10, rng, sigma_px=sigma, camera=default_camera(distortion=False))
        for i, (tp, rm, st) in enumerate(zip(ps, rims, stripes)):
            c = prepare_placement(cam, 25.0, rm, st, i)
            k = int(np.argmin([np.linalg.norm(p.center - tp.center) for p in c.poses]))
            true_r.append(_msd(c.chords[k], plane.normal, plane.d) / _tau(c, k, sigma) ** 2)
            wrong_r.append(_msd(c.chords[1 - k], plane.normal, plane.d) / _tau(c, 1 - k, sigma) ** 2)
    true_r, wrong_r = np.array(true_r), np.array(wrong_r)
    assert true_r.max() < _KAPPA**2 / 3
    assert 0.2 < true_r.mean() < 1.5  # the model is a scale, not a loose bound
    assert wrong_r.min() > _KAPPA**2


def test_sigma_is_estimated_from_residuals():
    rng = np.random.default_rng(103)
    cam, plane, ps, rims, stripes = _scene(6, rng, sigma_px=0.25)
    res = calibrate_plane_from_points(cam, 50.0, rims, stripes, method="global")
    # 6 x 500 points: the pooled estimate has ~1.3 % std
    assert res.sigma_px == pytest.approx(0.25, rel=0.06)
    for pr in res.placements:
        assert 0.15 < pr.rim_rms_px < 0.35 and 0.15 < pr.stripe_rms_px < 0.35


# ------------------------------------------------------------------ Monte Carlo
def test_monte_carlo_global_beats_paper_and_always_disambiguates():
    """sigma = 0.1 px, 12 placements, 50 mm disc, default geometry (pinhole), 30 trials."""
    rng = np.random.default_rng(104)
    errs = {"paper": [], "global": []}
    for _ in range(30):
        cam, plane, ps, rims, stripes = _scene(12, rng, sigma_px=0.1, camera=default_camera(distortion=False))
        for method in errs:
            res = calibrate_plane_from_points(cam, 50.0, rims, stripes, method=method, options=SolverOptions(sigma_px=0.1))
            assert _true_candidates_chosen(res, ps, 1.0)
            errs[method].append(_angle(res.plane, plane))
    rms = {m: np.sqrt(np.mean(np.square(e))) for m, e in errs.items()}
    assert rms["global"] <= rms["paper"]
    # scale check: 0.1 px at ~450 mm is ~0.01 mm; the plane's angle is good to ~1e-4 rad, not 1e-2
    assert rms["global"] < np.deg2rad(0.05)


@pytest.mark.parametrize("sigma_px", [0.1, 0.2])
def test_three_placements_always_disambiguated(sigma_px):
    rng = np.random.default_rng(105)
    for _ in range(25):
        cam, plane, ps, rims, stripes = _scene(3, rng, sigma_px=sigma_px)
        for method in ("paper", "global"):
            res = calibrate_plane_from_points(cam, 50.0, rims, stripes, method=method)
            assert res.n_used == 3, [p.reason for p in res.placements]
            assert _true_candidates_chosen(res, ps, 1.0)
            assert _angle(res.plane, plane) < np.deg2rad(1.0)


def test_paper_geometry_works():
    rng = np.random.default_rng(106)
    cam, plane = paper_camera(), paper_plane()
    cam_, plane_, ps, rims, stripes = _scene(5, rng, sigma_px=0.4, camera=cam, plane=plane,
                                             distance_mm=PAPER_DISTANCE_MM)
    for method in ("paper", "global"):
        res = calibrate_plane_from_points(cam, 50.0, rims, stripes, method=method)
        assert _true_candidates_chosen(res, ps, 1.0)
        assert _angle(res.plane, plane) < np.deg2rad(0.5)


# --------------------------------------------------------------- the ml entry
def test_ml_from_global_noise_free():
    pytest.importorskip("lightplane.plane.ml")
    rng = np.random.default_rng(107)
    cam, plane, ps, rims, stripes = _scene(4, rng, n_rim=60, n_stripe=60)
    res = calibrate_plane_from_points(cam, 50.0, rims, stripes)  # method="ml" by default
    assert res.method == "ml" and res.covariance is not None and res.covariance.shape == (4, 4)
    assert _angle(res.plane, plane) < 1e-9 and abs(res.plane.d - plane.d) < 1e-9
    assert _true_candidates_chosen(res, ps, 1e-6)



def test_solver_options_reach_the_solvers_and_are_checked():
    from lightplane.plane.ml import MLOptions

    cam, plane, ps, rims, stripes = _good()
    # the ML refinement's options arrive: one iteration cannot converge from the global start
    one = calibrate_plane_from_points(cam, 50.0, rims, stripes, options=SolverOptions(ml=MLOptions(max_iter=1)))
    assert any("without converging" in w for w in one.warnings)
    full = calibrate_plane_from_points(cam, 50.0, rims, stripes)
    assert not any("without converging" in w for w in full.warnings)
    # a spread bar above the placements' spread makes them "too alike"
    with pytest.raises(LightplaneError, match="placements too alike"):
        calibrate_plane_from_points(cam, 50.0, rims, stripes, method="global",
                                    options=SolverOptions(min_normal_spread_deg=179.0))
    for bad in (dict(noise="magic"), dict(max_iter=0), dict(huber_c=-1.0)):
        with pytest.raises(LightplaneError):
            MLOptions(**bad)
    with pytest.raises(LightplaneError, match="sigma_px"):
        SolverOptions(sigma_px=-1.0)
    with pytest.raises(LightplaneError, match="options must be SolverOptions"):
        calibrate_plane_from_points(cam, 50.0, rims, stripes, options={"sigma_px": 0.1})

# ------------------------------------------------------------ result contents
def test_result_to_dict_is_json_and_complete():
    rng = np.random.default_rng(108)
    cam, plane, ps, rims, stripes = _scene(5, rng, sigma_px=0.1)
    stripes[2] = stripes[2][:4]  # too few stripe points: rejected, not fatal
    res = calibrate_plane_from_points(cam, 50.0, rims, stripes, method="global")
    d = json.loads(json.dumps(res.to_dict()))
    assert d["method"] == "global" and len(d["images"]) == 5 and d["n_used"] == 4
    assert d["images"][2]["used"] is False and "too few stripe points" in d["images"][2]["reason"]
    assert any("placement 2" in w for w in res.warnings)
    assert d["ambiguity"]["separated"] is True
    used = [p for p in res.placements if p.used]
    # chord RMS to the plane: of the order of tau (~0.01 mm at 0.1 px), never mm
    assert all(0 < p.chord_rms_mm < 0.1 for p in used)
    assert res.plane.d < 0 and res.plane.meta["method"] == "global"


def test_stripe_outliers_are_rejected():
    rng = np.random.default_rng(109)
    cam, plane, ps, rims, stripes = _scene(5, rng, sigma_px=0.1)
    clean = calibrate_plane_from_points(cam, 50.0, rims, stripes, method="global", options=SolverOptions(sigma_px=0.1))
    bad = [s.copy() for s in stripes]
    for s in bad:
        s[::25] += rng.normal(0, 30.0, s[::25].shape)  # 4 % gross outliers
    res = calibrate_plane_from_points(cam, 50.0, rims, bad, method="global", options=SolverOptions(sigma_px=0.1))
    assert _angle(res.plane, clean.plane) < np.deg2rad(0.01)
    assert all(p.n_stripe <= 300 - 12 + 1 for p in res.placements)


def test_stripe_line_and_fast_undistortion():
    rng = np.random.default_rng(110)
    t = np.linspace(0, 100, 200)
    p = np.column_stack([t, 0.5 * t + 3]) + rng.normal(0, 0.1, (200, 2))
    p[::20] += 50.0
    c, n, inl = _stripe_line(p)
    assert inl.sum() == 190 and not inl[::20].any()
    assert abs(abs(n @ np.array([-0.5, 1.0]) / np.hypot(0.5, 1.0)) - 1) < 1e-4
    cam = default_camera()
    uv = rng.uniform([0, 0], [1279, 959], (500, 2))
    xy = cam.undistort_points(uv, normalized=True)
    assert np.max(np.abs(cam.normalized_to_pixels(xy) - uv)) < 1e-9


def test_stripe_line_is_core_robust_line():
    """The solver's stripe line is core.geometry.robust_line (3 refits after the first fit, the upper median)."""
    from lightplane.core.geometry import robust_line

    rng = np.random.default_rng(9)
    p = np.column_stack([np.arange(40.0), np.zeros(40)]) + rng.normal(0, 0.1, (40, 2))
    c, nrm, inl = _stripe_line(p)
    m, _, n, inl2 = robust_line(p, refits=4, rel_tol=1e-9, upper_median=True)
    np.testing.assert_array_equal(inl, inl2)
    np.testing.assert_array_equal(c, m)
    np.testing.assert_array_equal(nrm, n)
    assert _stripe_line(np.ones((1, 2)))[2].tolist() == [True]


# ------------------------------------------------------------------ bad input
def _good(n=4, seed=111):
    return _scene(n, np.random.default_rng(seed), sigma_px=0.1)


def test_bad_input_errors_name_the_problem():
    cam, plane, ps, rims, stripes = _good()
    with pytest.raises(LightplaneError, match="diameter_mm"):
        calibrate_plane_from_points(cam, 0.0, rims, stripes, method="global")
    with pytest.raises(LightplaneError, match="diameter_mm"):
        calibrate_plane_from_points(cam, -50.0, rims, stripes, method="global")
    with pytest.raises(LightplaneError, match="at least 3 placements"):
        calibrate_plane_from_points(cam, 50.0, rims[:2], stripes[:2], method="global")
    with pytest.raises(LightplaneError, match="one entry per placement"):
        calibrate_plane_from_points(cam, 50.0, rims, stripes[:3], method="global")
    with pytest.raises(LightplaneError, match="method"):
        calibrate_plane_from_points(cam, 50.0, rims, stripes, method="magic")
    r = list(rims)
    r[1] = np.zeros((0, 2))
    with pytest.raises(LightplaneError, match="placement 1: no rim points"):
        calibrate_plane_from_points(cam, 50.0, r, stripes, method="global")
    r[1] = []
    with pytest.raises(LightplaneError, match="placement 1: no rim points"):
        calibrate_plane_from_points(cam, 50.0, r, stripes, method="global")
    r[1] = rims[1][:4]
    with pytest.raises(LightplaneError, match="placement 1.*at least 5"):
        calibrate_plane_from_points(cam, 50.0, r, stripes, method="global")
    r = [a.copy() for a in rims]
    r[2][5, 0] = np.nan
    with pytest.raises(LightplaneError, match="placement 2.*NaN"):
        calibrate_plane_from_points(cam, 50.0, r, stripes, method="global")
    s = [a.copy() for a in stripes]
    s[3][0, 1] = np.inf
    with pytest.raises(LightplaneError, match="placement 3"):
        calibrate_plane_from_points(cam, 50.0, rims, s, method="paper")
    r = list(rims)
    r[0] = np.ones((10, 3))
    with pytest.raises(LightplaneError, match="placement 0"):
        calibrate_plane_from_points(cam, 50.0, r, stripes, method="global")


def test_rim_points_not_an_ellipse():
    cam, plane, ps, rims, stripes = _good()
    r = list(rims)
    r[1] = np.random.default_rng(0).uniform([300, 200], [900, 700], (200, 2))  # a cloud, not a curve
    with pytest.raises(LightplaneError, match="placement 1.*not an ellipse|placement 1.*ellipse"):
        calibrate_plane_from_points(cam, 50.0, r, stripes, method="global")
    r[1] = np.column_stack([np.linspace(100, 900, 50), np.linspace(100, 600, 50)])  # a line
    with pytest.raises(LightplaneError, match="placement 1"):
        calibrate_plane_from_points(cam, 50.0, r, stripes, method="global")
    # a square's outline
    t = np.linspace(0, 1, 50, endpoint=False)
    sq = np.concatenate([np.column_stack([400 + 200 * t, np.full(50, 300)]),
                         np.column_stack([np.full(50, 600), 300 + 200 * t]),
                         np.column_stack([600 - 200 * t, np.full(50, 500)]),
                         np.column_stack([np.full(50, 400), 500 - 200 * t])])
    r[1] = sq
    with pytest.raises(LightplaneError, match="placement 1.*not an ellipse"):
        calibrate_plane_from_points(cam, 50.0, r, stripes, method="global")


def test_too_few_usable_placements_names_them():
    cam, plane, ps, rims, stripes = _good()
    s = list(stripes)
    s[0] = s[0][:3]
    s[2] = []
    with pytest.raises(LightplaneError, match=r"only 2 usable placements.*placement 0.*placement 2"):
        calibrate_plane_from_points(cam, 50.0, rims, s, method="global")


def test_placements_too_alike_are_an_error():
    cam, plane = default_camera(), default_plane()
    rng = np.random.default_rng(112)
    base = sample_placements(1, rng)[0]
    ps = []
    for dz in (-40.0, 0.0, 40.0, 70.0):  # same normal, slid along the light plane
        c = base.center + np.array([0.0, 0.0, dz])
        c[0] = (-plane.d - plane.normal[2] * c[2] - plane.normal[1] * c[1]) / plane.normal[0]
        c = c + rng.uniform(-0.1, 0.1, 3)
        ps.append(TargetPlacement(c, base.normal, 50.0))
    obs = [synthetic_observations(cam, plane, p) for p in ps]
    with pytest.raises(LightplaneError, match="too alike|ambigu"):
        calibrate_plane_from_points(cam, 50.0, [o[0] for o in obs], [o[1] for o in obs], method="global")


def test_two_placements_for_the_paper_study():
    """The paper's §3 runs use 2 placements: allowed with min_placements=2; strict=False always answers."""
    rng = np.random.default_rng(113)
    cam, plane = paper_camera(), paper_plane()
    for _ in range(10):
        _, _, ps, rims, stripes = _scene(2, rng, camera=cam, plane=plane, distance_mm=PAPER_DISTANCE_MM)
        with pytest.raises(LightplaneError, match="at least 3"):
            calibrate_plane_from_points(cam, 50.0, rims, stripes, method="global")
        for method in ("paper", "global"):
            res = calibrate_plane_from_points(cam, 50.0, rims, stripes, method=method, options=SolverOptions(strict=False), min_placements=2)
            # noise-free: two generic chords are coplanar only for the true pair
            assert _angle(res.plane, plane) < 1e-9 and abs(res.plane.d - plane.d) < 1e-8
            assert _true_candidates_chosen(res, ps, 1e-6)


def test_non_strict_keeps_undecided_placements_with_a_warning():
    """A face-on disc: its two poses coincide, so both chords fit; strict drops it, non-strict keeps it."""
    rng = np.random.default_rng(114)
    cam, plane = default_camera(), default_plane()
    ps = sample_placements(4, rng)
    p = plane.point_on_axis() + np.array([0.0, 30.0, 0.0])
    ps.append(TargetPlacement(p, -p / np.linalg.norm(p), 50.0))  # seen exactly face-on
    obs = [synthetic_observations(cam, plane, q, sigma_px=0.1, rng=rng) for q in ps]
    rims, stripes = [o[0] for o in obs], [o[1] for o in obs]
    strict = calibrate_plane_from_points(cam, 50.0, rims, stripes, method="global")
    assert not strict.placements[4].used and "both chords fit" in strict.placements[4].reason
    loose = calibrate_plane_from_points(cam, 50.0, rims, stripes, method="global", options=SolverOptions(strict=False))
    assert loose.placements[4].used and "undecided" in loose.placements[4].reason
    assert any("undecided" in w for w in loose.warnings)
    assert _angle(loose.plane, plane) < np.deg2rad(0.05)


def test_paper_stopping_rule_and_reasons():
    rng = np.random.default_rng(115)
    cam, plane, ps, rims, stripes = _scene(10, rng, sigma_px=0.1)
    res = calibrate_plane_from_points(cam, 50.0, rims, stripes, method="paper")
    used = [p for p in res.placements if p.used]
    assert 3 <= len(used) < 10  # the 0.1 % rule stops early: ||Δ(a,b,c,d)|| is dominated by d (~190 mm)
    assert all("converged" in p.reason for p in res.placements if not p.used)
    every = calibrate_plane_from_points(cam, 50.0, rims, stripes, method="paper", options=SolverOptions(paper_rel_change=0.0))
    assert every.n_used == 10 and every.iterations == 10
    assert _true_candidates_chosen(every, ps, 1.0)
    # more chords, better plane (on average; here with 10 vs few placements)
    assert _angle(every.plane, plane) < np.deg2rad(0.05)


def test_tls_line_recovers_a_line_and_its_normal():
    """Points on u = 3 + 0.5 t, v = -2 + t (t spread over 200 px) with 0.01 px noise across: direction and normal
    of the line to ~1e-4 rad, centroid on the line within the noise, normal orthogonal to the direction."""
    from lightplane.core.geometry import tls_line

    rng = np.random.default_rng(4)
    t = rng.uniform(-100, 100, 400)
    d_true = np.array([0.5, 1.0]) / np.hypot(0.5, 1.0)
    n_true = np.array([-d_true[1], d_true[0]])
    p = np.array([3.0, -2.0]) + t[:, None] * d_true + rng.normal(0, 0.01, 400)[:, None] * n_true
    m, d, n = tls_line(p)
    assert abs(abs(d @ d_true) - 1) < 1e-8 and abs(abs(n @ n_true) - 1) < 1e-8
    assert abs(d @ n) < 1e-12 and abs(np.linalg.norm(d) - 1) < 1e-12
    assert abs((m - [3.0, -2.0]) @ n_true) < 0.005
