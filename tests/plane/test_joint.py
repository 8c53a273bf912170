"""The joint refinement of camera and light plane: exact recovery without
noise, errors within the stated covariance with noise, bad input.

Synthetic observations (exact projections of the default sensor's corners, rims and stripes
plus injected Gaussian noise of known sigma), so that several refinements fit in a fast test;
the rendered-image version is benchmarks/bench_camera_uncertainty.py.
"""

from __future__ import annotations

from dataclasses import replace
import cv2
import numpy as np
import pytest

from lightplane.core.errors import LightplaneError
from lightplane.camera.intrinsics import free_parameters, intrinsics_covariance
from lightplane.plane.joint import JointBoardViews, JointOptions, JointTargetPlacements, refine_joint_points
from lightplane.plane.model import LightPlane
from lightplane.plane.ml import _Pose
from lightplane.simulate.scene import default_camera, default_plane, sample_placements, synthetic_observations
from lightplane.simulate.render import CALIBRATION_CAPTURE as CC
from lightplane.simulate.render import board_corners, sample_board_poses
from lightplane.plane.uncertainty import camera_params, camera_with_params, point_error_basis, working_volume_grid

BOARD = (9, 7)
FLAGS = cv2.CALIB_FIX_K3
N_VIEWS, N_PLACEMENTS = 8, 6


def _data(rng, sigma_px: float):
    """Exact geometry and its noisy observations: board views and target placements."""
    true, plane = default_camera(), default_plane()
    poses = sample_board_poses(N_VIEWS, rng, replace(CC, board=BOARD, square_mm=8.0), camera=true)
    obj = board_corners(BOARD, 8.0)
    uv = [true.project(obj @ R.T + t) + sigma_px * rng.standard_normal((len(obj), 2)) for R, t in poses]
    placements = sample_placements(N_PLACEMENTS, rng, camera=true, plane=plane)
    obs = [synthetic_observations(true, plane, p, n_rim=80, n_stripe=40, sigma_px=sigma_px, rng=rng)
           for p in placements]
    return true, plane, poses, obj, uv, placements, obs


def _solve(true, plane, poses, obj, uv, placements, obs, sigma_px, start_camera, start_plane, start_poses,
           board_poses=None):
    free = free_parameters(5, FLAGS)
    if board_poses is None:
        board_poses = [(cv2.Rodrigues(R)[0].ravel(), t) for R, t in poses]
    views = JointBoardViews([obj] * len(uv), uv, [b[0] for b in board_poses], [b[1] for b in board_poses], sigma_px)
    targets = JointTargetPlacements(25.0, [o[0] for o in obs], [o[1] for o in obs], start_plane, start_poses,
                                    sigma_px, sigma_px)
    return refine_joint_points(start_camera, free, views, targets, JointOptions(huber_c=None))


def test_noise_free_recovers_the_truth_from_a_perturbed_start():
    rng = np.random.default_rng(3)
    true, plane, poses, obj, uv, placements, obs = _data(rng, 0.0)
    p0 = camera_params(true)
    off = np.r_[2.0, -1.5, 1.0, -1.0, 0.003, -0.01, 1e-4, -1e-4, 0.0]  # k3 held (FIX_K3)
    start_cam = camera_with_params(true, p0 + off)
    start_plane = LightPlane(plane.normal + np.array([0.002, -0.001, 0.001]), plane.d + 0.3)
    start_poses = [_Pose(p.center + 0.2, (p.normal + 0.003) / np.linalg.norm(p.normal + 0.003)) for p in placements]
    board0 = [(cv2.Rodrigues(R)[0].ravel() + 1e-3, t + 0.2) for R, t in poses]
    res = _solve(true, plane, poses, obj, uv, placements, obs, 0.05, start_cam, start_plane, start_poses, board0)
    assert res.converged
    assert np.max(np.abs(camera_params(res.camera) - p0)[:4]) < 1e-6  # px
    assert np.max(np.abs(camera_params(res.camera) - p0)[4:]) < 1e-9
    assert np.linalg.norm(res.plane.normal - plane.normal) < 1e-10 and abs(res.plane.d - plane.d) < 1e-7
    for q, p in zip(res.poses, placements):
        assert np.linalg.norm(q.center - p.center) < 1e-6
    for (R, t), rv, tv in zip(poses, res.rvecs, res.tvecs):
        assert np.allclose(cv2.Rodrigues(rv)[0], R, atol=1e-10) and np.allclose(tv, t, atol=1e-6)
    assert res.cost < 1e-12 * res.cost_start
    # k3 held fixed: no variance; the plane file's split adds up to the plane's total covariance
    assert res.camera.covariance[8, 8] == 0 and np.all(res.camera.covariance[8] == 0)
    rec = res.plane.meta["camera_jacobian"]
    assert np.allclose(res.plane.covariance + np.asarray(rec["covariance_camera"]), res.plane_covariance_total,
                       rtol=1e-6, atol=1e-14)


def test_errors_within_the_stated_covariance_and_the_circles_add_information():
    """Monte Carlo over independent noisy data sets: the mean Mahalanobis² of the intrinsics'
    error is their number of free parameters (8) and that of the plane's 3 (its marginal
    covariance); the joint covariance of the intrinsics is never larger than the corners'
    alone (the circle images add information); points' errors match the error basis."""
    sigma = 0.05
    n_trials = 10
    m_k, m_p, m_pt, psi = [], [], [], []
    for seed in range(n_trials):
        rng = np.random.default_rng(100 + seed)
        true, plane, poses, obj, uv, placements, obs = _data(rng, sigma)
        o32 = [obj.astype(np.float32)] * len(uv)
        i32 = [u.astype(np.float32) for u in uv]
        _, K, d, rv, tv = cv2.calibrateCamera(o32, i32, (1280, 960), None, None, flags=FLAGS,
                                              criteria=(3, 100, 1e-12))
        d = d.ravel()[:5]
        two = intrinsics_covariance(o32, i32, rv, tv, K, d, FLAGS, noise="white")  # white noise injected
        cam0 = camera_with_params(true, np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], d])
        res = _solve(true, plane, poses, obj, uv, placements, obs, sigma, cam0, plane,
                     [_Pose(p.center, p.normal) for p in placements],
                     [(np.ravel(a), np.ravel(b)) for a, b in zip(rv, tv)])
        e = camera_params(res.camera) - camera_params(true)
        Ck = res.camera.covariance
        assert res.dispersion_applied
        psi.append(res.dispersion)
        m_k.append(e @ np.linalg.pinv(Ck) @ e)
        dp = np.append(res.plane.normal - plane.normal, res.plane.d - plane.d)
        m_p.append(dp @ np.linalg.pinv(res.plane_covariance_total, rcond=1e-10) @ dp)
        # the circle images can only add information: Cov(two-step) - Cov(joint) is positive semi-definite
        # (the joint's before its dispersion, which is a measured scale, not information)
        # (the corners' covariance with the same, known noise sigma; the two are linearised at points
        # ~1 sigma apart, hence the tolerance); and in some direction they add much (> 10 % of the variance)
        c_two = two.covariance * (sigma / two.sigma_px) ** 2
        sd = np.sqrt(np.diag(c_two))[:8]
        w = np.linalg.eigvalsh((c_two - Ck / res.dispersion)[:8, :8] / np.outer(sd, sd))  # the weights' information
        assert w[0] > -0.01 and w[-1] > 0.1, w
        # the points over the working volume: errors against the error basis (camera frame)
        vol = working_volume_grid(true, plane)
        E, inc = point_error_basis(res.camera, res.plane, vol.uv[::40])
        assert inc
        from lightplane.plane.triangulate import triangulate

        err = triangulate(res.camera, res.plane, vol.uv[::40]) - vol.points[::40]
        Ef = E.reshape(-1, E.shape[2])
        rank = int(np.linalg.matrix_rank(Ef, tol=1e-9 * np.linalg.norm(Ef, 2)))
        m_pt.append(err.ravel() @ np.linalg.pinv(Ef @ Ef.T, rcond=1e-9) @ err.ravel() - rank)
    # mean of a chi-square with k dof over n trials: sd sqrt(2k / n); 3.5 sd bands
    assert abs(np.mean(m_k) - 8) < 3.5 * np.sqrt(16 / n_trials), m_k
    assert abs(np.mean(m_p) - 3) < 3.5 * np.sqrt(6 / n_trials), m_p
    assert abs(np.mean(m_pt)) < 3.5 * np.sqrt(2 * rank / n_trials), (m_pt, rank)
    # the joint dispersion (in the covariance by default) is 1 for white noise, within its sampling
    # (its sd over the trials ~0.3 with 8 views and 6 images)
    assert abs(np.mean(psi) - 1) < 3.5 * np.std(psi) / np.sqrt(n_trials), psi


def test_errors_correlated_within_images_are_found_by_the_joint_dispersion():
    """Each image's stripe turned about its middle by its own random error (0.1 px sd at the ends,
    on 0.05 px white noise), a coherent pull on the plane and, through the joint solve, on the
    intrinsics, that the weights (the white noise's sigma) do not see: the weights' covariance of
    the intrinsics is too small; the joint dispersion finds it and the default covariance's
    Mahalanobis² averages the 8 free intrinsics again (chi² mean 8; tolerance 3.5 sd of the
    trials' mean plus the inflation E[1/dispersion] brings, ~ its relative variance)."""
    sigma, n_trials = 0.05, 10
    m_k, m_k_model, psi = [], [], []
    for seed in range(n_trials):
        rng = np.random.default_rng(300 + seed)
        true, plane, poses, obj, uv, placements, obs = _data(rng, sigma)
        tilted = []
        for o in obs:
            q = o[1] - o[1].mean(axis=0)
            _, _, vt = np.linalg.svd(q, full_matrices=False)
            u = q @ vt[0]
            tilted.append((o[0], o[1] + rng.normal(0, 0.1) * (u / np.abs(u).max())[:, None] * vt[1]))
        o32 = [obj.astype(np.float32)] * len(uv)
        _, K, d, rv, tv = cv2.calibrateCamera(o32, [u.astype(np.float32) for u in uv], (1280, 960), None, None,
                                              flags=FLAGS, criteria=(3, 100, 1e-12))
        cam0 = camera_with_params(true, np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], d.ravel()[:5]])
        res = _solve(true, plane, poses, obj, uv, placements, tilted, sigma, cam0, plane,
                     [_Pose(p.center, p.normal) for p in placements],
                     [(np.ravel(a), np.ravel(b)) for a, b in zip(rv, tv)])
        e = camera_params(res.camera) - camera_params(true)
        m_k.append(e @ np.linalg.pinv(res.camera.covariance) @ e)
        m_k_model.append(m_k[-1] * res.dispersion)  # under the weights' covariance alone
        psi.append(res.dispersion)
    m_k, m_k_model, psi = np.array(m_k), np.array(m_k_model), np.array(psi)
    # measured: dispersion 6.7 (1.1-12.6), the weights' Mahalanobis² 46, the default's 11 (6 trials)
    assert np.mean(psi) > 2.0, psi
    assert np.mean(m_k_model) > 2 * 8, m_k_model
    tol = 3.5 * np.std(m_k) / np.sqrt(n_trials) + 8 * np.var(psi / np.mean(psi))
    assert abs(np.mean(m_k) - 8) < tol, (np.mean(m_k), tol, psi)


@pytest.mark.parametrize("case", ["lengths", "placements", "sigma", "free"])
def test_bad_input_is_one_clear_error(case):
    rng = np.random.default_rng(1)
    true, plane, poses, obj, uv, placements, obs = _data(rng, 0.0)
    free = free_parameters(5, FLAGS)
    rv = [cv2.Rodrigues(R)[0].ravel() for R, _ in poses]
    tv = [t for _, t in poses]
    args = dict(board_points=[obj] * len(uv), corners_uv=uv, rvecs=rv, tvecs=tv, sigma_corner_px=0.05,
                radius_mm=25.0, rims_uv=[o[0] for o in obs], stripes_uv=[o[1] for o in obs], plane0=plane,
                poses0=placements, sigma_rim_px=0.05, sigma_stripe_px=0.05)
    if case == "lengths":
        args["rvecs"] = rv[:-1]
        msg = "one entry per view"
    elif case == "placements":
        args.update(rims_uv=args["rims_uv"][:1], stripes_uv=args["stripes_uv"][:1], poses0=placements[:1])
        msg = "at least 2 target placements"
    elif case == "sigma":
        args["sigma_corner_px"] = 0.0
        msg = "sigma_corner_px must be positive"
    else:
        free = free[:5]
        msg = "'free' must have 9 entries"
    views = JointBoardViews(*(args[k] for k in ("board_points", "corners_uv", "rvecs", "tvecs", "sigma_corner_px")))
    targets = JointTargetPlacements(*(args[k] for k in ("radius_mm", "rims_uv", "stripes_uv", "plane0", "poses0",
                                                        "sigma_rim_px", "sigma_stripe_px")))
    with pytest.raises(LightplaneError, match=msg):
        refine_joint_points(true, free, views, targets)
