"""Calibration planning against exact truth: the placement information, the point sigma, the guide and the stop."""

import numpy as np
import pytest

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.plane.ml import crlb, placement_information
from lightplane.plane.model import CameraDependence, LightPlane
from lightplane.plane.triangulate import triangulate_normalized
from lightplane.plane.uncertainty import camera_param_names, point_error_basis, shape_error_basis
from lightplane.plan.candidates import PoseLimits, feasible_placements, outline_px, tilt_deg
from lightplane.plan.information import VolumeModel, covariance_from_information, information_from_covariance
from lightplane.plan.planner import (CalibrationPlanner, PlannerOptions, StripeNoiseTrend, _trend_features,
                                     fit_stripe_trend)
from lightplane.plan.volume import box_volume, parse_working_volume, region_volume
from lightplane.simulate.scene import default_camera, default_plane, sample_placements, synthetic_observations

CAM, PLANE = default_camera(), default_plane()


def _volume():
    return region_volume(CAM, PLANE, None, distance_mm=(380, 520), step_px=48)


def test_placement_information_adds_up_to_the_crlb():
    ps = sample_placements(6, np.random.default_rng(3))
    C = crlb(CAM, 25.0, ps, PLANE, 64, 32, sigma_rim_px=0.05, sigma_stripe_px=0.2)
    info, G = placement_information(CAM, 25.0, ps, PLANE, sigma_rim_px=0.05, sigma_stripe_px=0.2)
    assert info.shape == (6, 3, 3)
    assert np.allclose(covariance_from_information(info.sum(0), G), C, rtol=1e-8, atol=1e-14 * np.abs(C).max())
    # counts scale the information: twice the points, half the covariance
    info2, _ = placement_information(CAM, 25.0, ps, PLANE, sigma_rim_px=0.05, sigma_stripe_px=0.2,
                                     rim_points=np.full(6, 128.0), stripe_points=np.full(6, 64.0))
    assert np.allclose(info2, 2 * info, rtol=1e-9)
    assert np.allclose(information_from_covariance(C, G), info.sum(0), rtol=1e-6)


@pytest.mark.parametrize("frame", ["camera", "shape"])
def test_volume_model_matches_the_point_uncertainty(frame):
    vol = _volume()
    ps = sample_placements(5, np.random.default_rng(4))
    info, G = placement_information(CAM, 25.0, ps, PLANE, sigma_rim_px=0.05, sigma_stripe_px=0.2)
    cov = covariance_from_information(info.sum(0), G)
    m = VolumeModel(CAM, PLANE, vol, frame=frame)
    E, _ = point_error_basis(CAM, PLANE, m.uv, covariance=cov)
    if frame == "shape":
        E = shape_error_basis(E, m.points)
    ref = np.sqrt(np.sum(E**2, axis=(1, 2)))
    assert np.allclose(m.sigma(info.sum(0)), ref, rtol=1e-6)
    shares = m.variance_shares(info)
    assert shares.sum() == pytest.approx(1.0) and np.all(shares > 0)


def test_feasible_placements_satisfy_the_limits():
    vol = _volume()
    lim = PoseLimits(50.0, distance_mm=(380, 520), max_tilt_deg=50, tilts_deg=(0, 30, 50))
    cands = feasible_placements(CAM, PLANE, vol, lim)
    assert len(cands) > 10
    for p in cands:
        assert 380 <= np.linalg.norm(p.center) <= 520 and tilt_deg(p) <= 50 + 1e-6
        ch = p.chord(PLANE)
        assert ch is not None and np.linalg.norm(ch[1] - ch[0]) >= 0.4 * 50
        assert np.all(CAM.in_image(outline_px(CAM, p), margin=20))
    with pytest.raises(LightplaneError, match="no feasible placement"):
        feasible_placements(CAM, PLANE, vol, PoseLimits(400.0))


def test_box_and_text_volumes():
    vol = box_volume(CAM, PLANE, (-30, -40, 400), (30, 40, 480), step_mm=5)
    assert np.all(np.abs(PLANE.signed_distance(vol.points)) < 1e-9)
    assert np.all((vol.points[:, 2] >= 400) & (vol.points[:, 2] <= 480))
    assert np.allclose(CAM.project(vol.points), vol.uv)
    v2 = parse_working_volume("image:0,0,640,960@400,500", CAM, PLANE)
    assert np.all(v2.uv[:, 0] <= 640) and len(v2.uv) > 3
    with pytest.raises(LightplaneError, match="box"):
        parse_working_volume("box:1,2,3", CAM, PLANE)
    with pytest.raises(LightplaneError, match="must be box"):
        parse_working_volume("sphere:1", CAM, PLANE)


def _observe(p, rng, sigma):
    z = p.center[2]
    return synthetic_observations(CAM, PLANE, p, n_rim=int(2 * np.pi * 25 * CAM.fx / z),
                                  n_stripe=int(0.8 * 50 * CAM.fx / z), sigma_px=sigma, rng=rng)


def test_guided_loop_predicts_its_error_and_stops():
    """A scripted user follows the guide; the predicted worst-point sigma is the truth's scale and the
    suggested placements lower it as predicted (the planner's model is the CRLB's)."""
    vol = _volume()
    rough = LightPlane(PLANE.normal + np.array([0.01, 0.0, 0.004]), PLANE.d + 2.0)
    opts = PlannerOptions(PoseLimits(50.0, distance_mm=(380, 520)), target_sigma_mm=0.006, max_placements=12)
    pl = CalibrationPlanner(CAM, rough, vol, opts)
    rng = np.random.default_rng(7)
    for _ in range(12):
        s = pl.suggest()
        assert s.sigma_after_mm <= s.sigma_now_mm
        assert s.outline_px.shape == (72, 2) and np.all(CAM.in_image(s.outline_px))
        st = pl.add(*_observe(s.placement, rng, 0.1))
        if pl.stop().status == "reached":
            break
    verdict = pl.stop()
    assert verdict.status == "reached" and "placements" in verdict.message
    assert verdict.n_placements <= 8
    xy = CAM.undistort_points(pl.model.uv, normalized=True)
    e = np.linalg.norm(triangulate_normalized(pl.plane, xy).points - triangulate_normalized(PLANE, xy).points, axis=1)
    st = pl.state()
    # one run: the actual error is a draw of a Gaussian of the predicted sigma (3 sigma at the worst point)
    assert np.sqrt(np.mean(e**2)) < 3 * st.rms_camera_mm and e.max() < 3 * st.sigma_mm
    assert st.rms_shape_mm < st.rms_camera_mm and st.coverage["n"] == verdict.n_placements
    assert abs(pl.noise.sigma_rim_px - 0.1) < 0.02  # the noise the ML refinement estimated (1 point per px)


def test_unreachable_says_why():
    vol = _volume()
    opts = PlannerOptions(PoseLimits(50.0, distance_mm=(380, 520)), target_sigma_mm=1e-5, max_placements=6)
    v = CalibrationPlanner(CAM, PLANE, vol, opts).stop()
    assert v.status == "unreachable" and "within 6 placements" in v.message and "deg" in v.message


def test_camera_share_sets_a_floor_the_stop_names():
    """A camera with a covariance and a plane that records its dependence on the intrinsics: the camera's share is
    a floor under every point sigma; a target below it is unreachable, and the verdict gives the floor."""
    names = camera_param_names(CAM)
    cov = np.diag([4.0, 4.0, 1.0, 1.0] + [1e-6] * (len(names) - 4))  # px²: fx, fy, cx, cy; distortion
    cam = Camera(CAM.K, CAM.dist, CAM.width, CAM.height, covariance=cov, covariance_params=names)
    J = np.zeros((4, len(names)))
    J[3, 0] = 0.01  # d moves 0.01 mm per px of fx
    dep = CameraDependence(names, J, J @ cov @ J.T, "test")
    plane = LightPlane(PLANE.normal, PLANE.d, meta={CameraDependence.KEY: dep.to_dict()})
    vol = _volume()
    opts = PlannerOptions(PoseLimits(50.0, distance_mm=(380, 520)), target_sigma_mm=1e-4)
    pl = CalibrationPlanner(cam, plane, vol, opts)
    floor = pl.model.camera_floor()
    E, inc = point_error_basis(cam, plane, pl.model.uv, covariance=np.zeros((4, 4)))
    assert inc and np.allclose(floor, np.sqrt(np.sum(E[:, :, 4:] ** 2, axis=(1, 2))))
    assert floor.max() > 1e-4
    v = pl.stop()
    assert v.status == "unreachable" and "camera's own share" in v.message and f"{floor.max():.4f}" in v.message


def _trend_data(rng, n, exponent, noise):
    """``n`` placements at tilts 0-55 deg and their stripe noise per px: ``0.3 cos(tilt)^exponent`` times a
    log-normal scatter of sd ``noise``; features as the planner computes them."""
    ps = sample_placements(n, rng)
    X = np.array([_trend_features(PLANE, p) for p in ps])
    cos_tilt = np.exp(X[:, 0])
    return ps, X, 0.3 * cos_tilt**exponent * np.exp(rng.normal(0.0, noise, n))


def test_stripe_trend_found_where_there_is_one_and_not_otherwise():
    """The stripe's noise per px fitted against the placements' features: a noise that grows with the
    foreshortening (sigma ~ cos(tilt)^1.5, 3 % scatter) is found, shrunk towards no trend by its prior only
    (the ratio of two placements' expected sigma between the truth and 1, nearer the truth); without a trend
    (5 % scatter) every placement's factor stays within 4 sd of the prediction's scatter of 1."""
    rng = np.random.default_rng(11)
    ps, X, s = _trend_data(rng, 14, 1.5, 0.03)
    tr = fit_stripe_trend(X, s)
    i, j = int(np.argmin(X[:, 0])), int(np.argmax(X[:, 0]))    # the most and the least tilted
    truth = float(np.exp(1.5 * (X[i, 0] - X[j, 0])))
    got = tr.factor(X[i]) / tr.factor(X[j])
    assert truth < 0.8 and truth <= got < 0.5 * (truth + 1.0)
    ps, X, s = _trend_data(rng, 14, 0.0, 0.05)
    f = np.array([fit_stripe_trend(X, s).factor(x) for x in X])
    # a prediction's log has sd about 0.05 sqrt(p / n) (p = 3 slopes): 4 of them
    assert np.all(np.abs(np.log(f)) < 4 * 0.05 * np.sqrt(3 / 14))
    assert fit_stripe_trend(X[:3], s[:3]) is None     # too few placements: no trend


def test_planner_weighs_candidates_by_the_stripe_trend():
    """A candidate expected twice as noisy per px as the average placement counts a quarter of its chord."""
    pl = CalibrationPlanner(CAM, PLANE, _volume(), PlannerOptions(PoseLimits(50.0, distance_mm=(380, 520))))
    ps = sample_placements(2, np.random.default_rng(5))
    plain = pl._counts(ps)[1]
    X = np.array([_trend_features(PLANE, p) for p in ps])
    slope = np.array([0.0, 0.0, 0.0])
    slope[0] = np.log(2.0) / (X[0, 0] - X[1, 0])      # the first placement twice as noisy as the second
    pl.trend = StripeNoiseTrend(slope, X[1])
    weighted = pl._counts(ps)[1]
    assert weighted[0] == pytest.approx(plain[0] / 4.0) and weighted[1] == pytest.approx(plain[1])
