"""Zhou's planar-target method on exact point-level synthetic scenes, and the plane fit's covariance."""

from __future__ import annotations

import numpy as np
import pytest
from _board_scenes import BOARD, CAM, PLANE1, R1, SQ, T1, rot, scene

from lightplane import LightPlane
from lightplane.plane.zhou import board_polygon_mask, fit_plane, plane_from_board_stripes, stripe_points_on_board
from lightplane.camera.board_pose import pose_from_corners
from lightplane.core.errors import LightplaneError

POSES = [(R1, T1), (rot(-8, 20, -3), np.array([-45.0, -20.0, 480.0])), (rot(20, 5, 6), np.array([-35.0, -30.0, 420.0]))]


def _views(noise_px=0.0, rng=None):
    poses, stripes = [], []
    for k, (R, t) in enumerate(POSES):
        corners, stripe, _ = scene(R, t, PLANE1, n_stripe=300)
        poses.append(pose_from_corners(CAM, corners, BOARD, SQ, name=f"v{k}"))
        if noise_px:
            stripe = stripe + rng.normal(0, noise_px, stripe.shape)
        stripes.append(stripe)
    return poses, stripes


def test_pose_from_exact_corners():
    corners, _, _ = scene(R1, T1, PLANE1)
    pose = pose_from_corners(CAM, corners, BOARD, SQ)
    np.testing.assert_allclose(pose.R_cam_board, R1, atol=1e-9)
    np.testing.assert_allclose(pose.t_cam_board, T1, atol=1e-6)
    assert pose.reprojection_rms_px < 1e-6


def test_stripe_points_on_board_exact():
    corners, stripe, _ = scene(R1, T1, PLANE1)
    pose = pose_from_corners(CAM, corners, BOARD, SQ)
    p = stripe_points_on_board(CAM, pose, stripe)
    np.testing.assert_allclose(PLANE1.signed_distance(p), 0, atol=1e-6)
    np.testing.assert_allclose((p - T1) @ R1[:, 2], 0, atol=1e-6)  # on the board plane


def test_zhou_exact():
    poses, stripes = _views()
    res = plane_from_board_stripes(CAM, poses, stripes)
    assert np.degrees(res.plane.angle_to(PLANE1)) < 1e-7
    assert abs(res.plane.d - PLANE1.d) < 1e-5
    assert res.residual_rms_mm < 1e-6
    assert res.plane.meta["method"] == "zhou" and len(res.plane.meta["images"]) == 3
    assert all(im["used"] and im["n_stripe_points"] == 300 for im in res.plane.meta["images"])


def test_zhou_noise_within_covariance():
    """Stripe noise 0.1 px on exact poses: the plane error agrees with the fit covariance (chi-square, 3 dof)."""
    rng = np.random.default_rng(11)
    chi2 = []
    for _ in range(20):
        res = plane_from_board_stripes(CAM, *_views(0.1, rng))
        dv = res.plane.coefficients - PLANE1.coefficients
        chi2.append(dv @ np.linalg.pinv(res.plane.covariance, rcond=1e-10) @ dv)
        assert res.plane.angle_to(PLANE1) < 5 * np.sqrt(np.trace(res.plane.covariance[:3, :3]))
    # mean of chi2(3) is 3; with 20 draws its sample mean lies within [1.5, 5] with probability > 0.99
    assert 1.5 < np.mean(chi2) < 5.0


def test_fit_plane_covariance_monte_carlo():
    """The first-order covariance of fit_plane matches the scatter of 400 noisy refits (σ = 0.05 mm)."""
    rng = np.random.default_rng(5)
    n = np.array([0.3, -0.2, 0.93])
    n /= np.linalg.norm(n)
    truth = LightPlane(n, -400.0)
    u = np.cross(n, [1.0, 0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    ab = rng.uniform(-40, 40, (200, 2))
    base = -truth.d * n + ab[:, :1] * u + ab[:, 1:] * v
    coeffs, covs = [], []
    for _ in range(400):
        pl = fit_plane(base + rng.normal(0, 0.05, base.shape))
        coeffs.append(pl.coefficients)
        covs.append(pl.covariance)
    emp = np.cov(np.array(coeffs).T)
    pred = np.mean(covs, axis=0)
    # standard deviations within 12 % (sampling error of a std from 400 draws is ~3.5 %)
    np.testing.assert_allclose(np.sqrt(np.diag(emp)[[0, 1, 2, 3]]), np.sqrt(np.diag(pred)), rtol=0.12)
    assert abs(np.mean(coeffs, axis=0) - truth.coefficients).max() < 4 * np.sqrt(np.diag(pred)).max() / 20 + 1e-12


def test_fewer_than_two_poses():
    poses, stripes = _views()
    with pytest.raises(LightplaneError, match="at least 2 board poses"):
        plane_from_board_stripes(CAM, poses[:1], stripes[:1])
    with pytest.raises(LightplaneError, match="at least 2 board poses"):
        plane_from_board_stripes(CAM, poses[:2], [stripes[0], np.zeros((0, 2))])


def test_fit_plane_degenerate():
    with pytest.raises(LightplaneError, match="collinear"):
        fit_plane(np.outer(np.linspace(0, 1, 10), [1.0, 2.0, 3.0]) + [0, 0, 100])
    with pytest.raises(LightplaneError, match="at least 3"):
        fit_plane(np.ones((2, 3)))


def test_board_mask_contains_stripe_and_corners():
    corners, stripe, _ = scene(R1, T1, PLANE1)
    pose = pose_from_corners(CAM, corners, BOARD, SQ)
    mask = board_polygon_mask(CAM, pose, BOARD, SQ)
    ij = np.round(corners).astype(int)
    assert np.all(mask[ij[:, 1], ij[:, 0]] > 0)
    inner = stripe[5:-5]  # the stripe samples run to 0.5 square beyond the corners: the mask edge
    ij = np.round(inner).astype(int)
    assert np.mean(mask[ij[:, 1], ij[:, 0]] > 0) > 0.97
    assert mask.mean() / 255 < 0.3


def test_jackknife_covariance_sees_pose_errors():
    """Corner noise 0.1 px moves each board pose; the jackknife variance of the normal over 6 poses
    matches the Monte-Carlo scatter (within a factor 2 on average), the residual-only one is far below."""
    rng = np.random.default_rng(21)
    poses6 = POSES + [(rot(-15, -10, 3), np.array([-40.0, -22.0, 520.0])), (rot(5, 25, -8), np.array([-50.0, -28.0, 400.0])),
                      (rot(-20, 12, 2), np.array([-38.0, -26.0, 460.0]))]
    normals, var_jk, var_fit = [], [], []
    for _ in range(25):
        poses, stripes = [], []
        for R, t in poses6:
            corners, stripe, _ = scene(R, t, PLANE1, n_stripe=200)
            poses.append(pose_from_corners(CAM, corners + rng.normal(0, 0.1, corners.shape), BOARD, SQ))
            stripes.append(stripe)
        res = plane_from_board_stripes(CAM, poses, stripes)
        assert res.plane.meta["covariance_method"].startswith("jackknife")
        normals.append(res.plane.normal)
        var_jk.append(np.trace(res.plane.covariance[:3, :3]))
        var_fit.append(np.trace(np.asarray(res.plane.meta["covariance_fit"])[:3, :3]))
    normals = np.array(normals)
    var_mc = np.sum(np.var(normals, axis=0, ddof=1))
    assert 0.5 < np.mean(var_jk) / var_mc < 2.0
    assert np.mean(var_fit) < 0.5 * var_mc
