"""Tests of the simulated sensor geometry (docs/conventions.md §Default sensor)."""

from __future__ import annotations

import numpy as np
import pytest

from lightplane.core.errors import LightplaneError
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


def test_default_camera_matches_spec():
    cam = default_camera()
    assert cam.width == 1280 and cam.height == 960
    assert cam.fx == pytest.approx(16 / 0.00375) and cam.fy == pytest.approx(16 / 0.00375)
    assert cam.has_distortion
    flat = default_camera(distortion=False)
    assert np.array_equal(flat.K, cam.K) and not flat.has_distortion


def test_default_plane_geometry():
    p = default_plane()
    z = p.point_on_axis()[2]
    assert z == pytest.approx(450.0)
    # 25 deg between plane and optical axis: |n . z_axis| = sin(25 deg)
    assert abs(p.normal[2]) == pytest.approx(np.sin(np.deg2rad(25.0)))
    # the laser (plane at z = 0 on the x axis) sits ~210 mm beside the camera
    x_laser = -p.d / p.normal[0]
    assert 160 <= abs(x_laser) <= 260


def test_paper_plane():
    p = paper_plane()
    assert p.d < 0
    c = p.coefficients
    ref = -np.array([0.0, 0.9336, -0.3584, 140.04])
    assert np.allclose(c, ref / np.linalg.norm(ref[:3]), atol=1e-12)


@pytest.mark.parametrize("which", ["default", "paper"])
def test_sampled_placements_satisfy_constraints(which):
    rng = np.random.default_rng(1)
    if which == "default":
        cam, plane, dist, D = default_camera(), default_plane(), (380.0, 520.0), 50.0
    else:
        cam, plane, dist, D = paper_camera(), paper_plane(), PAPER_DISTANCE_MM, 70.0
    ps = sample_placements(40, rng, PlacementOptions(diameter_mm=D, distance_mm=dist), camera=cam, plane=plane)
    assert len(ps) == 40
    for tp in ps:
        dist_c = np.linalg.norm(tp.center)
        assert dist[0] <= dist_c <= dist[1]
        assert tp.normal @ tp.center < 0
        tilt = np.degrees(np.arccos(-tp.normal @ tp.center / dist_c))
        assert 15 - 1e-9 <= tilt <= 55 + 1e-9
        ch = tp.chord(plane)
        assert ch is not None and np.linalg.norm(ch[1] - ch[0]) >= 0.4 * D - 1e-9
        assert np.all(cam.in_image(cam.project(tp.rim_points(200)), margin=19.0))


def test_placement_geometry_exact():
    rng = np.random.default_rng(2)
    cam, plane = default_camera(), default_plane()
    for tp in sample_placements(20, rng):
        R = tp.basis()
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-14) and np.linalg.det(R) == pytest.approx(1.0)
        rim = tp.rim_points(64)
        assert np.allclose(np.linalg.norm(rim - tp.center, axis=1), tp.radius_mm, atol=1e-12)
        assert np.allclose((rim - tp.center) @ tp.normal, 0.0, atol=1e-12)
        ch = tp.chord(plane)
        assert np.allclose(plane.signed_distance(ch), 0.0, atol=1e-10)
        assert np.allclose((ch - tp.center) @ tp.normal, 0.0, atol=1e-10)
        assert np.allclose(np.linalg.norm(ch - tp.center, axis=1), tp.radius_mm, atol=1e-10)
        # the conic vanishes on the undistorted projection of the rim, negative at the centre
        C = tp.conic(cam)
        uvh = np.column_stack([cam.project(rim, distort=False), np.ones(len(rim))])
        vals = np.einsum("ij,jk,ik->i", uvh, C, uvh)
        assert np.max(np.abs(vals)) < 1e-12
        ch_img = np.append(cam.project(tp.center[None], distort=False)[0], 1.0)
        assert ch_img @ C @ ch_img < 0
        assert np.linalg.norm(C) == pytest.approx(1.0)


def test_synthetic_observations_noise_free_and_noisy():
    rng = np.random.default_rng(3)
    cam, plane = default_camera(), default_plane()
    tp = sample_placements(1, rng)[0]
    rim, stripe = synthetic_observations(cam, plane, tp, n_rim=100, n_stripe=80)
    assert rim.shape == (100, 2) and stripe.shape == (80, 2)
    # stripe pixels back-projected onto the light plane lie on the disc plane within the radius
    rays = cam.rays(stripe)
    p = rays * (-plane.d / (rays @ plane.normal))[:, None]
    assert np.allclose((p - tp.center) @ tp.normal, 0.0, atol=1e-8)
    assert np.all(np.linalg.norm(p - tp.center, axis=1) < tp.radius_mm)
    rim_n, stripe_n = synthetic_observations(cam, plane, tp, n_rim=4000, n_stripe=4000, sigma_px=0.3,
                                             rng=np.random.default_rng(4))
    rim0, stripe0 = synthetic_observations(cam, plane, tp, n_rim=4000, n_stripe=4000)
    est = np.std(np.concatenate([rim_n - rim0, stripe_n - stripe0]))
    assert est == pytest.approx(0.3, rel=0.05)  # 16000 samples: std of the estimate ~0.6 %


def test_bad_input():
    with pytest.raises(LightplaneError):
        TargetPlacement([0, 0, 400], [0, 0, 1], -5.0)
    with pytest.raises(LightplaneError):
        synthetic_observations(default_camera(), default_plane(), TargetPlacement([0, 0, 400], [0, 0, -1], 50.0),
                               sigma_px=0.1)
    far = TargetPlacement([500.0, 0, 400], [0, 0, -1], 10.0)
    assert far.chord(default_plane()) is None
    with pytest.raises(LightplaneError):
        sample_placements(1, np.random.default_rng(0), PlacementOptions(distance_mm=(5000.0, 6000.0), max_tries=200))
