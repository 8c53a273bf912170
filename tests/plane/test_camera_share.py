"""The camera's share of a measured point's uncertainty: the plane's
dependence on the intrinsics, the ray-plane correlation, camera-frame and shape sigmas.

Synthetic observations (exact projections plus injected Gaussian noise: chessboard corners
for the camera, rim and stripe points for the plane), so that many independent
calibrations fit in a fast test; the rendered-image version is
benchmarks/bench_camera_uncertainty.py.
"""

from __future__ import annotations

from dataclasses import replace
import cv2
import numpy as np
import pytest

from lightplane import Camera
from lightplane.plane.calibrate import propagate_camera
from lightplane.camera.intrinsics import intrinsics_covariance
from lightplane.measure.profile import ProfileMeasurer
from lightplane.plane.triangulate import triangulate
from lightplane.plane.model import CameraDependence, LightPlane
from lightplane.plane.solvers import calibrate_plane_from_points
from lightplane.evaluate.shapes import rigid_align
from lightplane.simulate.scene import default_camera, default_plane, sample_placements, synthetic_observations
from lightplane.simulate.render import CALIBRATION_CAPTURE as CC
from lightplane.simulate.render import board_corners, sample_board_poses
from lightplane.plane.uncertainty import (camera_params, camera_share_status, camera_steps, camera_with_params,
                                    point_error_basis, point_sigma_mm, shape_error_basis, volume_sigma,
                                    working_volume_grid)

BOARD = (9, 7)
CORNER_PX = 0.05
IMAGE_PX = 0.05
FLAGS = cv2.CALIB_FIX_K3


def _camera(rng, n_views=10):
    """A camera calibrated from noisy synthetic corners, with its covariance."""
    true = default_camera()
    poses = sample_board_poses(n_views, rng, replace(CC, board=BOARD, square_mm=8.0), camera=true)
    obj = board_corners(BOARD, 8.0).astype(np.float32)
    ip = [(true.project(obj.astype(float) @ R.T + t) + CORNER_PX * rng.standard_normal((len(obj), 2)))
          .astype(np.float32) for R, t in poses]
    _, K, d, rv, tv = cv2.calibrateCamera([obj] * len(ip), ip, (1280, 960), None, None, flags=FLAGS,
                                          criteria=(3, 100, 1e-12))
    d = d.ravel()[:5]
    c = intrinsics_covariance([obj] * len(ip), ip, rv, tv, K, d, FLAGS, noise="white")  # white noise injected
    return Camera(K, d, 1280, 960, covariance=c.covariance, covariance_params=c.params)


def _plane(cam, rng, n=6):
    """(plane with camera_jacobian, solve) from noisy synthetic rim/stripe points of ``n`` placements."""
    true_cam, true_plane = default_camera(), default_plane()
    obs = [synthetic_observations(true_cam, true_plane, p, n_rim=80, n_stripe=40, sigma_px=IMAGE_PX, rng=rng)
           for p in sample_placements(n, rng, camera=true_cam, plane=true_plane)]

    def solve(c):
        return calibrate_plane_from_points(c, 50.0, [o[0] for o in obs], [o[1] for o in obs], method="ml").plane

    pl = solve(cam)
    rec = propagate_camera(solve, cam, pl)
    return LightPlane(pl.normal, pl.d, pl.covariance, meta={CameraDependence.KEY: rec.to_dict()}), solve


@pytest.fixture(scope="module")
def one():
    rng = np.random.default_rng(11)
    cam = _camera(rng)
    plane, solve = _plane(cam, rng)
    return cam, plane, solve


def test_plane_and_point_sensitivity_are_first_order_exact(one):
    """A fresh change of the intrinsics (not one of the steps used): the re-solved plane and
    the points measured with it move as the recorded Jacobian and the error basis predict, to
    first order: the central difference of the changes at ±half a sigma (the plane's offset also
    moves to second order, as the re-estimated rim and stripe sigmas do: ~35 % of the first-order
    change at half a sigma along this direction, the same sign either way)."""
    cam, plane, solve = one
    steps = camera_steps(cam)
    xi = np.random.default_rng(5).standard_normal(len(steps))
    delta = 0.5 * xi @ steps  # a half-sigma change along a random direction
    moved = [camera_with_params(cam, camera_params(cam) + s * delta) for s in (1.0, -1.0)]
    pl2 = [solve(m) for m in moved]
    J = plane.camera_dependence.matrix
    dth = 0.5 * (pl2[0].coefficients - pl2[1].coefficients)
    assert np.linalg.norm(dth - J @ delta) < 0.05 * np.linalg.norm(dth)
    vol = working_volume_grid(cam, plane)
    actual = 0.5 * (triangulate(moved[0], pl2[0], vol.uv) - triangulate(moved[1], pl2[1], vol.uv))
    E, inc = point_error_basis(cam, plane, vol.uv)
    assert inc
    pred = E[:, :, 4:] @ (0.5 * xi)
    assert np.linalg.norm(actual - pred) < 0.05 * np.linalg.norm(actual)
    # ray and plane move together: adding their shares as if independent would be far off
    ray_only = 0.5 * (triangulate(moved[0], plane, vol.uv) - triangulate(moved[1], plane, vol.uv))
    assert np.linalg.norm(ray_only - pred) > 0.2 * np.linalg.norm(actual)


def test_images_dispersion_part_due_to_the_camera(one):
    """The images' dispersion statistic is quadratic in the intrinsics; its part due to Cov(K), recorded
    from the steps' second differences, is its mean curvature over changes drawn from Cov(K): checked over
    8 fresh random directions (tolerance 3 sd of their mean, from the draws), and the dispersion measured
    against both."""
    from lightplane.plane.calibrate import _dispersion_beside_camera

    cam, plane, solve = one
    extra = plane.camera_dependence.extra
    T0, EK = extra["image_dispersion_statistic"], extra["image_dispersion_camera_expected"]
    assert EK > 0

    def stat(c):
        nm = solve(c).meta["noise_model"]
        return nm["image_dispersion"] * nm["image_dispersion_expected"]

    assert abs(stat(cam) - T0) < 1e-6 * T0
    steps = camera_steps(cam)
    rng = np.random.default_rng(8)
    curv = []
    for _ in range(8):
        delta = rng.standard_normal(len(steps)) @ steps
        p0 = camera_params(cam)
        curv.append(0.5 * (stat(camera_with_params(cam, p0 + delta)) + stat(camera_with_params(cam, p0 - delta)))
                    - T0)
    # measured: 1.27 of the recorded part, the draws' relative sd 1.04 (a few directions dominate)
    assert abs(np.mean(curv) / EK - 1) < 3 * np.std(curv, ddof=1) / np.sqrt(len(curv)) / EK, (np.mean(curv), EK)
    nm = solve(cam).meta["noise_model"]
    out, f = _dispersion_beside_camera(nm, plane.camera_dependence)
    assert out["image_dispersion"] == pytest.approx(T0 / (nm["image_dispersion_expected"] + EK))
    assert out["image_dispersion_noise_only"] == nm["image_dispersion"]
    # the covariance's factor is the dispersion never below 1 (the positive part of a variance component)
    assert out["image_dispersion_factor"] == pytest.approx(max(out["image_dispersion"], 1.0))
    assert f == pytest.approx(max(out["image_dispersion"], 1.0) / max(nm["image_dispersion"], 1.0))


def test_outputs_with_and_without_the_camera_share(one):
    cam, plane, _ = one
    vol = working_volume_grid(cam, plane)
    vs = volume_sigma(cam, plane, vol)
    plain = Camera(cam.K, cam.dist, cam.width, cam.height)
    vp = volume_sigma(plain, plane, vol)
    assert vs.camera_included and not vp.camera_included and "not included" in vp.covers
    assert vs.camera_frame_mm > vs.plane_only_mm and vs.shape_mm < vs.camera_frame_mm
    assert vp.camera_frame_mm == pytest.approx(vs.plane_only_mm)
    # a plane file without the images' dispersion (earlier versions): read as before, and said
    assert "errors shared within an image not included" in vs.covers
    nm = {"image_dispersion": 1.3, "image_dispersion_applied": True}
    with_disp = LightPlane(plane.normal, plane.d, plane.covariance, meta={**plane.meta, "noise_model": nm})
    assert "the images' dispersion x1.30" in volume_sigma(cam, with_disp, vol).covers
    # point_sigma_mm and the profile's per-point sigma carry the same figure
    uv = vol.uv[::7]
    s = point_sigma_mm(cam, plane, uv)
    assert np.sqrt(np.mean(s**2)) > 1.5 * np.sqrt(np.mean(point_sigma_mm(plain, plane, uv) ** 2))
    m = ProfileMeasurer(cam, plane, lookup=False)
    assert m.camera_share_missing is None
    prof = m.from_stripe(uv, np.ones(len(uv), bool))
    assert np.allclose(prof.sigma_mm, s, rtol=1e-6)
    assert "not included" in ProfileMeasurer(plain, plane, lookup=False).camera_share_missing
    # a plane calibrated without the camera's covariance: said, not silently mixed
    bare = LightPlane(plane.normal, plane.d, plane.covariance)
    assert "records no dependence" in camera_share_status(cam, bare)


def test_predicted_sigmas_match_independent_calibrations():
    """Over independent calibrations (camera and plane from fresh noise each time) the error
    of the points over the working volume, whitened by the predicted basis, is chi²: its mean
    is the basis's rank; and the RMS camera-frame and shape errors match the predictions."""
    true_cam, true_plane = default_camera(), default_plane()
    vol = working_volume_grid(true_cam, true_plane)
    rng = np.random.default_rng(21)
    stats, act, pred = [], [], []
    trials = 10
    for _ in range(trials):
        cam = _camera(rng)
        plane, _ = _plane(cam, rng)
        est = triangulate(cam, plane, vol.uv)
        e = est - vol.points
        E, _ = point_error_basis(cam, plane, vol.uv)
        flat = E.reshape(-1, E.shape[2])
        U, S, Vt = np.linalg.svd(flat, full_matrices=False)
        keep = S > 1e-9 * S[0]
        z = (U[:, keep].T @ e.ravel()) / S[keep]
        stats.append((np.sum(z**2), int(keep.sum())))
        Es = shape_error_basis(E, vol.points)
        act.append((np.mean(np.sum(e**2, axis=1)), rigid_align(est, vol.points).rms_mm ** 2))
        pred.append((np.sum(E**2) / len(E), np.sum(Es**2) / len(E)))
    chi2 = np.mean([s for s, _ in stats])
    dof = np.mean([k for _, k in stats])
    assert abs(chi2 - dof) < 3.0 * np.sqrt(2 * dof / trials), (chi2, dof)
    act, pred = np.sqrt(np.mean(act, axis=0)), np.sqrt(np.mean(pred, axis=0))
    ratio = pred / act
    print(f"camera frame: actual {act[0]:.4f} mm, predicted {pred[0]:.4f}; shape: actual {act[1]:.4f}, "
          f"predicted {pred[1]:.4f}; chi² {chi2:.1f} for {dof:.0f} dof")
    # an RMS over 10 draws of an error of a few dof: within ~±40 % (about 3 sd)
    assert np.all(np.abs(ratio - 1) < 0.4), ratio
