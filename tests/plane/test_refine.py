"""Joint ML refinement (lightplane.plane.ml) and point uncertainty (lightplane.plane.uncertainty).

Ground truth: lightplane's default sensor (docs/conventions.md §Default sensor) and random placements from
lightplane.simulate.scene; noise injected in pixels.
"""

from __future__ import annotations

import numpy as np
import pytest

from lightplane import LightPlane, LightplaneError
from lightplane.plane.ml import MLOptions, _Pose, _Problem, crlb, refine_ml
from lightplane.simulate.scene import default_camera, default_plane, sample_placements, synthetic_observations
from lightplane.plane.uncertainty import (
    point_covariance,
    point_sigma_mm,
    rms_point_sigma_mm,
    rms_triangulation_error_mm,
    working_volume_grid,
)

R_MM = 25.0


def _angle(n1, n2) -> float:
    """Angle between unit normals (rad), accurate for tiny angles."""
    return float(np.arctan2(np.linalg.norm(np.cross(n1, n2)), abs(n1 @ n2)))


def _scene(n, seed, distortion=True, n_rim=200, n_stripe=300):
    cam = default_camera(distortion=distortion)
    plane = default_plane()
    rng = np.random.default_rng(seed)
    ps = sample_placements(n, rng, camera=cam, plane=plane)
    obs = [synthetic_observations(cam, plane, p, n_rim=n_rim, n_stripe=n_stripe) for p in ps]
    return cam, plane, ps, obs


def _perturbed_start(plane, ps, rng, ang=0.01, dd=3.0, dc=1.0, dn=0.01):
    p0 = LightPlane(plane.normal + rng.normal(0, ang, 3), plane.d + dd)
    poses0 = [_Pose(p.center + rng.normal(0, dc, 3), p.normal + rng.normal(0, dn, 3)) for p in ps]
    return p0, poses0


def test_jacobian_matches_finite_differences():
    cam, plane, ps, obs = _scene(4, 1, n_rim=40, n_stripe=40)
    rng = np.random.default_rng(2)
    p0, poses0 = _perturbed_start(plane, ps, rng)
    rims = [o[0] + rng.normal(0, 0.3, o[0].shape) for o in obs]
    sts = [o[1] + rng.normal(0, 0.3, o[1].shape) for o in obs]
    prob = _Problem(cam, R_MM, rims, sts, p0, poses0)
    x = prob.x0 + rng.normal(0, 1e-3, prob.p)
    J = prob.dense_jacobian(x)
    Jn = np.zeros_like(J)
    for k in range(prob.p):
        h = 1e-6 * max(1.0, abs(x[k]))
        xp, xm = x.copy(), x.copy()
        xp[k] += h
        xm[k] -= h
        Jn[:, k] = (prob.residuals(xp) - prob.residuals(xm)) / (2 * h)
    # central differences: error ~ h² f''' + rounding ~1e-7 relative
    err = np.abs(J - Jn).max(axis=0) / np.abs(J).max(axis=0)
    assert err.max() < 1e-5, err


def test_noise_free_recovers_truth_with_distortion():
    cam, plane, ps, obs = _scene(12, 3)
    p0, poses0 = _perturbed_start(plane, ps, np.random.default_rng(4))
    res = refine_ml(cam, R_MM, [o[0] for o in obs], [o[1] for o in obs], p0, poses0)
    assert _angle(res.plane.normal, plane.normal) < 1e-9
    assert abs(res.plane.d - plane.d) < 1e-9 * abs(plane.d)
    for got, p in zip(res.poses, ps):
        assert np.linalg.norm(got.center - p.center) < 1e-9 * 500
        assert _angle(got.normal, p.normal) < 1e-9
        assert got.normal @ got.center < 0  # towards the camera (docs/conventions.md §Target pose)
    assert res.sigma_px < 1e-9
    assert np.all(res.rim_rms_px < 1e-9) and np.all(res.stripe_rms_px < 1e-9)
    assert res.covariance.shape == (4, 4)
    assert res.plane.covariance is not None
    # the covariance is rank 3: no uncertainty along the normal's length
    assert abs(res.plane.normal @ res.covariance[:3, :3] @ res.plane.normal) <= 1e-12 * np.trace(res.covariance[:3, :3])


def test_sigma_estimate_matches_injected_noise():
    """sigma from the residuals (dof-corrected) estimates the injected noise; its relative
    standard error is 1/sqrt(2 (m - p)) ~ 0.3 % here, so 3 % is > 10 standard errors."""
    cam, plane, ps, obs = _scene(6, 5)
    rng = np.random.default_rng(6)
    sigma = 0.25
    rims = [o[0] + rng.normal(0, sigma, o[0].shape) for o in obs]
    sts = [o[1] + rng.normal(0, sigma, o[1].shape) for o in obs]
    res = refine_ml(cam, R_MM, rims, sts, plane, ps)
    assert abs(res.sigma_px / sigma - 1) < 0.03
    assert np.all(np.abs(res.rim_rms_px / sigma - 1) < 0.2)
    assert np.all(np.abs(res.stripe_rms_px / sigma - 1) < 0.2)


def test_monte_carlo_ml_reaches_crlb_and_covariance_is_calibrated():
    """12 placements, pinhole default sensor, sigma = 0.1 px (the requirement).

    N = 60 noise trials on one fixed geometry.  The RMS over N trials of an error with
    k >= 1 Gaussian degrees of freedom has a relative standard error <= 1/sqrt(2 N) = 9.1 %;
    the tolerances are the target (1.15x the CRLB, predicted sigma within 15 %) widened by
    3 standard errors (27 %), and ML cannot beat the bound by more than those 3 standard errors.
    The 200-trial check at the nominal tolerances is benchmarks/bench_ml.py.
    """
    n_trials = 60
    se3 = 3 / np.sqrt(2 * n_trials)
    sigma = 0.1
    cam, plane, ps, obs = _scene(12, 11, distortion=False)
    vol = working_volume_grid(cam, plane, step_px=40.0)
    bound = crlb(cam, R_MM, ps, plane, 200, 300, sigma)
    bound_ang = np.sqrt(np.trace(bound[:3, :3]))
    bound_tri = rms_point_sigma_mm(cam, plane, vol, covariance=bound)
    rng = np.random.default_rng(12)
    ang2, tri2, pred_ang2, pred_tri2, disp = [], [], [], [], []
    for _ in range(n_trials):
        rims = [o[0] + rng.normal(0, sigma, o[0].shape) for o in obs]
        sts = [o[1] + rng.normal(0, sigma, o[1].shape) for o in obs]
        res = refine_ml(cam, R_MM, rims, sts, plane, ps)
        assert res.dispersion_applied
        disp.append(res.image_dispersion)
        ang2.append(_angle(res.plane.normal, plane.normal) ** 2)
        tri2.append(rms_triangulation_error_mm(cam, res.plane, plane, vol) ** 2)
        pred_ang2.append(np.trace(res.covariance[:3, :3]))
        pred_tri2.append(rms_point_sigma_mm(cam, res.plane, vol) ** 2)
    rms_ang, rms_tri = np.sqrt(np.mean(ang2)), np.sqrt(np.mean(tri2))
    ratio_ang, ratio_tri = rms_ang / bound_ang, rms_tri / bound_tri
    assert 1 - se3 < ratio_ang < 1.15 * (1 + se3), ratio_ang
    assert 1 - se3 < ratio_tri < 1.15 * (1 + se3), ratio_tri
    pred_ang, pred_tri = np.sqrt(np.mean(pred_ang2)), np.sqrt(np.mean(pred_tri2))
    assert abs(pred_ang / rms_ang - 1) < 0.15 + se3
    assert abs(pred_tri / rms_tri - 1) < 0.15 + se3
    # the images' dispersion (in the covariance by default) is 1 for white noise, within its sampling
    # (its sd from the trials: ~0.37 here, against sqrt(2 / (3 · 11)) = 0.25 at the least)
    assert abs(np.mean(disp) - 1) < 3.5 * np.std(disp) / np.sqrt(n_trials), (np.mean(disp), np.std(disp))
    # the predicted sigma is a property of the geometry times the dispersion: equal to the bound within a
    # few % plus the dispersion's mean sampling error (3.5 sd of the mean of sqrt(dispersion))
    tol_d = 3.5 * np.std(np.sqrt(disp)) / np.sqrt(n_trials)
    assert abs(pred_ang / bound_ang - 1) < 0.05 + tol_d
    assert abs(pred_tri / bound_tri - 1) < 0.05 + tol_d


def _plane_mahalanobis2(est: LightPlane, truth: LightPlane, cov: np.ndarray) -> float:
    """The plane's error (a, b, c, d) in ``cov`` (rank 3: the normal's length is fixed)."""
    s = 1.0 if est.normal @ truth.normal > 0 else -1.0
    e = np.r_[est.normal - s * truth.normal, est.d - s * truth.d]
    return float(e @ np.linalg.pinv(cov, rcond=1e-10) @ e)


def test_image_correlated_errors_are_found_by_the_images_dispersion():
    """Each image's stripe turned about its middle by its own random error (0.04 px sd at the ends,
    on 0.1 px white noise): the residuals' sigmas and autocorrelation times do not see it (a
    stripe's slope is what they remove) and the noise model's covariance is too small; the images'
    dispersion finds it and the default covariance's Mahalanobis² averages the 3 plane parameters
    again (chi² mean 3; tolerance 3.5 sd of the trials' mean plus the inflation E[1/dispersion]
    brings, ~ its relative variance)."""
    cam, plane, ps, obs = _scene(12, 11, distortion=False, n_rim=150, n_stripe=150)
    rng = np.random.default_rng(21)
    trials = 30
    d2, d2_model, disp = [], [], []
    for _ in range(trials):
        rims = [o[0] + rng.normal(0, 0.1, o[0].shape) for o in obs]
        sts = []
        for o in obs:
            q = o[1] - o[1].mean(axis=0)
            _, _, vt = np.linalg.svd(q, full_matrices=False)
            u = q @ vt[0]
            sts.append(o[1] + rng.normal(0, 0.1, o[1].shape)
                       + rng.normal(0, 0.04) * (u / np.abs(u).max())[:, None] * vt[1])
        res = refine_ml(cam, R_MM, rims, sts, plane, ps)
        disp.append(res.image_dispersion)
        d2.append(_plane_mahalanobis2(res.plane, plane, res.covariance))
        d2_model.append(d2[-1] * res.image_dispersion)  # under the noise model's covariance alone
    d2, d2_model, disp = np.array(d2), np.array(d2_model), np.array(disp)
    # measured: dispersion 2.9 (sd 1.3 over the trials), the model's Mahalanobis² 7.8, the default's 3.1
    assert np.mean(disp) > 2.0, np.mean(disp)
    assert np.mean(d2_model) > 1.5 * 3, np.mean(d2_model)
    tol = 3.5 * np.std(d2) / np.sqrt(trials) + 3 * np.var(disp / np.mean(disp))
    assert abs(np.mean(d2) - 3) < tol, (np.mean(d2), tol)


def test_crlb_scales_with_sigma_and_shrinks_with_placements():
    cam, plane, ps, _ = _scene(8, 21)
    c1 = crlb(cam, R_MM, ps, plane, 100, 100, 0.1)
    c2 = crlb(cam, R_MM, ps, plane, 100, 100, 0.2)
    np.testing.assert_allclose(c2, 4 * c1, rtol=1e-9, atol=0)
    c_few = crlb(cam, R_MM, ps[:3], plane, 100, 100, 0.1)
    assert np.trace(c_few[:3, :3]) > np.trace(c1[:3, :3])
    assert c_few[3, 3] > c1[3, 3]


def test_refine_bad_input_names_the_placement():
    cam, plane, ps, obs = _scene(3, 31, n_rim=30, n_stripe=30)
    rims = [o[0].copy() for o in obs]
    sts = [o[1] for o in obs]
    rims[1][4] = np.nan
    with pytest.raises(LightplaneError, match="placement 1"):
        refine_ml(cam, R_MM, rims, sts, plane, ps)
    with pytest.raises(LightplaneError, match="radius_mm"):
        refine_ml(cam, -1.0, [o[0] for o in obs], sts, plane, ps)
    with pytest.raises(LightplaneError, match="one entry per placement"):
        refine_ml(cam, R_MM, [o[0] for o in obs], sts[:2], plane, ps)
    with pytest.raises(LightplaneError, match="rims_uv\\[0\\]"):
        refine_ml(cam, R_MM, [np.zeros((5, 3))] + [o[0] for o in obs[1:]], sts, plane, ps)
    with pytest.raises(LightplaneError, match="placement 2: needs at least 2 stripe"):
        refine_ml(cam, R_MM, [o[0] for o in obs], sts[:2] + [sts[2][:1]], plane, ps)


# ------------------------------------------------------------------ uncertainty
def test_point_sigma_matches_sampled_plane_perturbations():
    """First-order propagation against sampling plane errors from the covariance (errors of
    1e-5 rad: the linearisation error is ~1e-5 relative, the sampling error 1/sqrt(2 N) ~ 0.7 %)."""
    cam = default_camera()
    plane = default_plane()
    t = np.linalg.svd(plane.normal[None, :])[2][1:]  # tangent basis (2, 3)
    G = np.zeros((4, 3))
    G[:3, :2] = t.T
    G[3, 2] = 1.0
    cov3 = np.diag([1e-5, 2e-5, 0.01]) ** 2
    cov3[0, 2] = cov3[2, 0] = 0.5 * 1e-5 * 0.01
    cov = G @ cov3 @ G.T
    pl = LightPlane(plane.normal, plane.d, cov)
    vol = working_volume_grid(cam, pl, step_px=120.0)
    s = point_sigma_mm(cam, pl, vol.uv)
    rng = np.random.default_rng(41)
    N = 10000
    L = np.linalg.cholesky(cov3)
    xy = cam.undistort_points(vol.uv, normalized=True)
    xt = np.column_stack([xy, np.ones(len(xy))])
    X0 = vol.points
    err2 = np.zeros(len(xy))
    for z in (L @ rng.normal(size=(3, N))).T:
        n = plane.normal + t.T @ z[:2]
        n /= np.linalg.norm(n)
        d = plane.d + z[2]
        X = -d * xt / (xt @ n)[:, None]
        err2 += np.sum((X - X0) ** 2, axis=1)
    mc = np.sqrt(err2 / N)
    np.testing.assert_allclose(s, mc, rtol=0.03)
    C = point_covariance(cam, pl, vol.uv)
    assert C.shape == (len(vol.uv), 3, 3)
    np.testing.assert_allclose(np.sqrt(np.trace(C, axis1=1, axis2=2)), s, rtol=1e-12)


def test_point_sigma_requires_covariance_and_working_volume_checks():
    cam, plane = default_camera(), default_plane()
    with pytest.raises(LightplaneError, match="covariance"):
        point_sigma_mm(cam, plane, np.array([[600.0, 400.0]]))
    with pytest.raises(LightplaneError, match="not in view"):
        working_volume_grid(cam, plane, distance_mm=(5000.0, 6000.0))
    vol = working_volume_grid(cam, plane)
    dist = np.linalg.norm(vol.points, axis=1)
    assert np.all((dist >= 380) & (dist <= 520))
    np.testing.assert_allclose(plane.signed_distance(vol.points), 0, atol=1e-9)


def test_plot_point_sigma_map(tmp_path):
    from lightplane.report.plots import point_sigma_map as plot_point_sigma_map

    cam, plane = default_camera(), default_plane()
    pl = LightPlane(plane.normal, plane.d, np.diag([1e-10, 1e-10, 1e-10, 1e-4]))
    out = tmp_path / "sigma.png"
    plot_point_sigma_map(cam, pl, out, step_px=40.0)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(LightplaneError, match="already exists"):
        plot_point_sigma_map(cam, pl, out, step_px=40.0)


# ------------------------------------------------- per-type noise, correlated noise
def _scene8(seed=11):
    cam = default_camera(distortion=False)
    plane = default_plane()
    ps = sample_placements(8, np.random.default_rng(seed), camera=cam, plane=plane)
    obs = [synthetic_observations(cam, plane, p, n_rim=150, n_stripe=200) for p in ps]
    return cam, plane, ps, obs


def test_crlb_with_separate_sigmas():
    cam, plane, ps, obs = _scene8()
    c_equal = crlb(cam, R_MM, ps, plane, 150, 200, 0.1, observations=obs)
    c_sep = crlb(cam, R_MM, ps, plane, 150, 200, sigma_rim_px=0.1, sigma_stripe_px=0.1, observations=obs)
    np.testing.assert_allclose(c_sep, c_equal, rtol=1e-9, atol=1e-20)
    # more rim noise can only loosen the bound, less stripe noise only tighten it
    c_rim = crlb(cam, R_MM, ps, plane, 150, 200, sigma_rim_px=0.2, sigma_stripe_px=0.1, observations=obs)
    c_st = crlb(cam, R_MM, ps, plane, 150, 200, sigma_rim_px=0.1, sigma_stripe_px=0.05, observations=obs)
    assert np.all(np.linalg.eigvalsh(c_rim - c_equal) > -1e-12 * np.trace(c_equal))
    assert np.all(np.linalg.eigvalsh(c_equal - c_st) > -1e-12 * np.trace(c_equal))
    with pytest.raises(LightplaneError, match="sigma"):
        crlb(cam, R_MM, ps, plane, 150, 200)


def test_per_type_weighting_reaches_crlb_where_a_shared_sigma_does_not():
    """Rim points at 0.05 px, stripe points at 0.2 px (the renders' levels), 8 placements.

    Theory first: the shared-sigma (unweighted) estimator's covariance, the sandwich
    ``(JᵀJ)⁻¹ Jᵀ Σ J (JᵀJ)⁻¹`` with the true per-type Σ, exceeds the per-type CRLB
    clearly (here ~1.4x in angle).  Monte Carlo, N = 60 trials: per-type ML's RMS
    triangulation error is within 1.15x the CRLB widened by 3 standard errors of an RMS
    (3/sqrt(2N) = 27 %), and on the same noise (paired) its mean squared error is below
    0.8x that of the shared-sigma fit (theory ~0.5x).  The sigma estimates have relative
    standard errors ~1/sqrt(2 m_g) < 2 %: checked to 6 %.
    """
    cam, plane, ps, obs = _scene8()
    s_rim, s_st = 0.05, 0.2
    bound = crlb(cam, R_MM, ps, plane, 150, 200, sigma_rim_px=s_rim, sigma_stripe_px=s_st, observations=obs)
    prob = _Problem(cam, R_MM, [o[0] for o in obs], [o[1] for o in obs], plane, ps)
    J = prob.dense_jacobian(prob.x0)
    var = np.concatenate([np.full(prob.m_rim, s_rim**2), np.full(prob.m - prob.m_rim, s_st**2)])
    Hi = np.linalg.inv(J.T @ J)
    c_shared = Hi @ (J.T * var) @ J @ Hi  # minimal parameters: plane (alpha, beta, d) first
    assert np.sqrt(np.trace(c_shared[:2, :2])) > 1.2 * np.sqrt(np.trace(bound[:3, :3]))
    vol = working_volume_grid(cam, plane, step_px=40.0)
    bound_tri = rms_point_sigma_mm(cam, plane, vol, covariance=bound)
    n_trials = 60
    se3 = 3 / np.sqrt(2 * n_trials)
    rng = np.random.default_rng(5)
    e_typ, e_sh, s_r, s_s = [], [], [], []
    for _ in range(n_trials):
        rims = [o[0] + rng.normal(0, s_rim, o[0].shape) for o in obs]
        sts = [o[1] + rng.normal(0, s_st, o[1].shape) for o in obs]
        r1 = refine_ml(cam, R_MM, rims, sts, plane, ps, MLOptions(correlated=False))
        r2 = refine_ml(cam, R_MM, rims, sts, plane, ps, MLOptions(noise="shared", huber_c=None, correlated=False))
        e_typ.append(rms_triangulation_error_mm(cam, r1.plane, plane, vol) ** 2)
        e_sh.append(rms_triangulation_error_mm(cam, r2.plane, plane, vol) ** 2)
        s_r.append(r1.sigma_rim_px)
        s_s.append(r1.sigma_stripe_px)
    ratio = np.sqrt(np.mean(e_typ)) / bound_tri
    assert 1 - se3 < ratio < 1.15 * (1 + se3), ratio
    assert np.mean(e_typ) < 0.8 * np.mean(e_sh), (np.mean(e_typ), np.mean(e_sh))
    assert abs(np.median(s_r) / s_rim - 1) < 0.06
    assert abs(np.median(s_s) / s_st - 1) < 0.06


def _ar1(rng, n, phi, sigma, shape2=2):
    """(n, 2) AR(1) noise along the sequence, marginal sigma, lag-1 correlation phi."""
    z = rng.normal(0, sigma * np.sqrt(1 - phi**2), (n, shape2))
    e = np.empty_like(z)
    e[0] = rng.normal(0, sigma, shape2)
    for i in range(1, n):
        e[i] = phi * e[i - 1] + z[i]
    return e


def test_correlated_stripe_noise_inflated_covariance_matches_monte_carlo():
    """Stripe centre noise AR(1) along the chord (phi = 0.8: integrated autocorrelation time
    tau = (1 + phi)/(1 - phi) = 9), marginal 0.2 px; white rim noise 0.05 px.

    The white-noise covariance ignores the correlation and is ~sqrt(9) too small where the
    stripes dominate; the inflated one must match the Monte-Carlo RMS triangulation error.
    N = 50 trials: the MC RMS has a relative standard error 1/sqrt(2N) = 10 %; tau's
    estimate scatters ~20 % per data set (~10 % in sigma, averaged over the trials) and is
    ~5 % high on average (integrated_autocorr_time): tolerance 3 SE + 5 % = 35 %.
    """
    cam, plane, ps, obs = _scene8(13)
    vol = working_volume_grid(cam, plane, step_px=40.0)
    rng = np.random.default_rng(7)
    phi, s_rim, s_st = 0.8, 0.05, 0.2
    n_trials = 50
    e2, pred2, white2, taus, e2_w = [], [], [], [], []
    for _ in range(n_trials):
        rims = [o[0] + rng.normal(0, s_rim, o[0].shape) for o in obs]
        sts = [o[1] + _ar1(rng, len(o[1]), phi, s_st) for o in obs]
        res = refine_ml(cam, R_MM, rims, sts, plane, ps)
        res_w = refine_ml(cam, R_MM, rims, sts, plane, ps, MLOptions(correlated=False))
        e2_w.append(rms_triangulation_error_mm(cam, res_w.plane, plane, vol) ** 2)
        e2.append(rms_triangulation_error_mm(cam, res.plane, plane, vol) ** 2)
        pred2.append(rms_point_sigma_mm(cam, res.plane, vol) ** 2)
        white2.append(rms_point_sigma_mm(cam, res.plane, vol, covariance=res.covariance_white) ** 2)
        taus.append(res.tau_stripe)
    mc, pred, white = np.sqrt(np.mean(e2)), np.sqrt(np.mean(pred2)), np.sqrt(np.mean(white2))
    assert abs(pred / mc - 1) < 0.35, (pred, mc)
    assert white / mc < 0.6, (white, mc)
    assert 6.0 < np.median(taus) < 12.0, np.median(taus)
    # long-run weights 1/(tau sigma²) against white per-type weights, on the same noise: theory
    # (exact banded sandwich, test below) ~0.54x the variance of d and ~0.76x of the angle; here
    # 0.66x the mean squared triangulation error with a paired z of -5; checked at 0.85x
    assert np.mean(e2) < 0.85 * np.mean(e2_w), (np.mean(e2), np.mean(e2_w))


def test_white_noise_is_not_inflated_and_outliers_are_downweighted():
    """White noise: tau stays near 1 (its estimate scatters ~5 %); a few gross outliers on the
    stripe (3 px across it) barely move the plane with the Huber reweighting (the fit stays within
    a few sigma of the clean one) and are counted."""
    cam, plane, ps, obs = _scene8(17)
    rng = np.random.default_rng(9)
    rims = [o[0] + rng.normal(0, 0.05, o[0].shape) for o in obs]
    sts = [o[1] + rng.normal(0, 0.2, o[1].shape) for o in obs]
    clean = refine_ml(cam, R_MM, rims, sts, plane, ps)
    assert 1.0 <= clean.tau_rim < 1.3 and 1.0 <= clean.tau_stripe < 1.3
    bad = [s.copy() for s in sts]
    for s in bad:  # 4 points per stripe moved 3 px (15 sigma) across the stripe
        nrm = np.linalg.svd(s - s.mean(axis=0), full_matrices=False)[2][1]
        s[rng.choice(len(s), 4, replace=False)] += 3.0 * nrm
    robust = refine_ml(cam, R_MM, rims, bad, plane, ps)
    plain = refine_ml(cam, R_MM, rims, bad, plane, ps, MLOptions(huber_c=None))
    assert robust.n_outliers >= 32
    sd = np.sqrt(np.trace(clean.covariance[:3, :3]))
    assert _angle(robust.plane.normal, clean.plane.normal) < 1.0 * sd
    assert _angle(plain.plane.normal, clean.plane.normal) > _angle(robust.plane.normal, clean.plane.normal)
    assert abs(robust.sigma_stripe_px / 0.2 - 1) < 0.1


def test_per_group_tau_matches_the_exact_banded_sandwich():
    """The covariance model of refine_ml (one tau per group) against the exact sandwich
    ``H⁻¹ JᵀW Σ W J H⁻¹`` with the true AR(1) Toeplitz Σ along each stripe (phi = 0.8,
    tau = 9): the plane's sigmas agree within 3 % (the reduction assumes ``J_{i+k} ≈ J_i``
    over the ~10-point correlation length of 200-point stripes), while the white-noise
    covariance is >= 1.5x too small in sigma (the rim's white noise shares the offset d)."""
    cam, plane, ps, obs = _scene8(13)
    prob = _Problem(cam, R_MM, [o[0] for o in obs], [o[1] for o in obs], plane, ps)
    J = prob.dense_jacobian(prob.x0)
    phi, s_rim, s_st = 0.8, 0.05, 0.2
    tau = (1 + phi) / (1 - phi)
    m_r = prob.m_rim
    w = np.concatenate([np.full(m_r, 1 / s_rim**2), np.full(prob.m - m_r, 1 / (tau * s_st**2))])
    Hi = np.linalg.inv((J.T * w) @ J)
    k = np.arange(200)
    R = phi ** np.abs(k[:, None] - k[None, :])
    WJ = J * w[:, None]
    M = s_rim**2 * WJ[:m_r].T @ WJ[:m_r]
    for i in range(len(obs)):
        a = m_r + prob.st_starts[i]
        M += s_st**2 * WJ[a:a + 200].T @ R @ WJ[a:a + 200]
    exact = Hi @ M @ Hi
    white = np.linalg.inv((J.T * np.concatenate([np.full(m_r, 1 / s_rim**2),
                                                 np.full(prob.m - m_r, 1 / s_st**2)])) @ J)
    for sl in (slice(0, 2), slice(2, 3)):
        ratio = np.sqrt(np.trace(Hi[sl, sl]) / np.trace(exact[sl, sl]))
        assert abs(ratio - 1) < 0.03, ratio
        assert np.sqrt(np.trace(white[sl, sl]) / np.trace(exact[sl, sl])) < 0.7
