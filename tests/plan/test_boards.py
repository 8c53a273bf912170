"""Guided calibration with a board (Zhou's method) against exact truth."""

import numpy as np

from lightplane.camera.board_pose import BoardPose
from lightplane.plane.triangulate import triangulate_normalized
from lightplane.plan.boards import BoardPlanner, board_chord, points_information
from lightplane.plan.candidates import PoseLimits
from lightplane.plan.information import covariance_from_information, plane_jacobian_g
from lightplane.plan.planner import PlannerOptions
from lightplane.plan.volume import region_volume
from lightplane.plane.model import LightPlane
from lightplane.plane.zhou import fit_plane
from lightplane.simulate.scene import default_camera, default_plane

CAM, PLANE = default_camera(), default_plane()
SIZE = (80.0, 60.0)


def _stripe(pose, rng, sigma_px=0.15):
    ch = board_chord(PLANE, pose, SIZE)
    n = int(np.linalg.norm(np.diff(CAM.project(ch), axis=0)))
    uv = CAM.project(np.linspace(ch[0], ch[1], n))
    return uv + rng.normal(0, sigma_px, uv.shape)


def test_points_information_is_the_tls_fit_covariance():
    rng = np.random.default_rng(0)
    P0 = PLANE.point_on_axis()
    B = np.linalg.svd(PLANE.normal[None])[2][1:]
    pts = P0 + rng.uniform(-40, 40, (400, 2)) @ B + rng.normal(0, 0.01, 400)[:, None] * PLANE.normal
    fit = fit_plane(pts)
    G = plane_jacobian_g(CAM, fit)
    r = fit.signed_distance(pts)
    cov = covariance_from_information(points_information(fit, G, pts, np.sqrt(r @ r / (len(r) - 3))), G)
    assert np.allclose(cov, fit.covariance, rtol=1e-3, atol=1e-6 * np.abs(fit.covariance).max())


def test_board_guide_reaches_its_target_with_honest_sigma():
    vol = region_volume(CAM, PLANE, None, distance_mm=(400, 500), step_px=48)
    opts = PlannerOptions(PoseLimits(50.0, distance_mm=(380, 520), grid=(5, 5)), target_sigma_mm=0.01,
                          max_placements=10)
    rough = LightPlane(PLANE.normal + np.array([0.01, 0.0, 0.0]), PLANE.d + 2.0)
    bp = BoardPlanner(CAM, rough, vol, opts, SIZE, noise_mm=0.02)
    rng = np.random.default_rng(1)
    for _ in range(10):
        s = bp.suggest()
        assert s.sigma_after_mm <= s.sigma_now_mm and s.outline_px.shape == (4, 2)
        assert np.all(CAM.in_image(s.outline_px, margin=20))
        pose = BoardPose(np.zeros((0, 2)), s.pose.R, s.pose.center, 0.0)
        bp.add(pose, _stripe(s.pose, rng))
        if bp.stop().status == "reached":
            break
    v = bp.stop()
    assert v.status == "reached", v.message
    st = bp.state()
    xy = CAM.undistort_points(bp.model.uv, normalized=True)
    e = np.linalg.norm(triangulate_normalized(bp.plane, xy).points - triangulate_normalized(PLANE, xy).points, axis=1)
    assert e.max() < 3 * st.sigma_mm and st.coverage["n"] == v.n_placements
    assert abs(np.sum(st.shares) - 1) < 1e-9
