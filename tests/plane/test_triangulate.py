"""LightPlane conventions and triangulation (docs/conventions.md §Light plane, docs/method.md §Triangulation)."""

from __future__ import annotations

import numpy as np
import pytest

from lightplane import Camera, LightPlane, LightplaneError, triangulate

CAM = Camera(K=[[4266.7, 0, 652.3], [0, 4266.7, 471.8], [0, 0, 1]], dist=[-0.08, 0.12, 4e-4, -3e-4, 0],
             width=1280, height=960)


def test_sign_convention_and_normalisation():
    p = LightPlane([0, 2 * 0.9336, -2 * 0.3584], 2 * 140.04)
    assert p.d < 0 and np.isclose(np.linalg.norm(p.normal), 1)
    # the same plane: a point on it has zero distance either way
    q = LightPlane([0, 0.9336, -0.3584], 140.04)
    x = np.array([[10.0, 0.0, 140.04 / 0.3584]])
    assert abs(q.signed_distance(x)[0]) < 1e-9 and abs(p.signed_distance(x)[0]) < 1e-9
    with pytest.raises(LightplaneError, match="camera centre"):
        LightPlane([0, 0, 1], 0.0)
    with pytest.raises(LightplaneError, match="zero"):
        LightPlane([0, 0, 0], -1.0)


def test_plane_json_round_trip(tmp_path):
    cov = np.diag([1e-8, 2e-8, 3e-8, 1e-3])
    p = LightPlane([0.1, 0.9, -0.4], -150.0, cov, meta={"method": "test"})
    p.save(tmp_path / "p.json")
    q = LightPlane.load(tmp_path / "p.json")
    assert q == p and np.allclose(q.covariance, p.covariance) and q.meta["method"] == "test"
    with pytest.raises(LightplaneError, match="exists"):
        p.save(tmp_path / "p.json")


def test_triangulate_matches_analytic_intersection():
    rng = np.random.default_rng(7)
    n = rng.normal(size=3)
    n[2] = abs(n[2]) + 0.5  # the plane is in front of the camera for most rays
    plane = LightPlane(n, -450.0 * n[2])
    # analytic: pick points on the plane in front of the camera, project, triangulate back
    uv = np.column_stack([rng.uniform(0, 1279, 500), rng.uniform(0, 959, 500)])
    xy = CAM.undistort_points(uv, normalized=True)
    ray = np.column_stack([xy, np.ones(len(xy))])
    s = -plane.d / (ray @ plane.normal)
    expected = ray * s[:, None]
    t = triangulate(CAM, plane, uv, return_flags=True)
    good = t.valid
    assert good.sum() > 0
    assert np.abs(t.points[good] - expected[good]).max() < 1e-9
    assert np.abs(plane.signed_distance(t.points[good])).max() < 1e-9
    assert np.all((s > 0) == good | t.grazing)


def test_grazing_rays_are_flagged_not_huge():
    plane = LightPlane([1.0, 0.0, 0.0], -100.0)  # x = 100: rays near the optical axis are parallel
    uv = np.array([[CAM.cx, CAM.cy], [CAM.cx + 1e-3, CAM.cy], [CAM.cx + 600, CAM.cy]])
    t = triangulate(CAM, plane, uv, return_flags=True)
    assert t.grazing[0] and t.grazing[1]
    assert np.all(np.isnan(t.points[:2]))
    assert not t.grazing[2] and np.isfinite(t.points[2]).all()
    assert abs(t.points[2, 0] - 100.0) < 1e-9


def test_bad_shapes():
    plane = LightPlane([0, 0, 1], -500)
    with pytest.raises(LightplaneError, match="uv"):
        triangulate(CAM, plane, np.zeros((3, 3)))


def test_result_files_are_ordinary_permissions(tmp_path):
    import os
    import stat

    p = LightPlane([0, 0, 1], -500)
    p.save(tmp_path / "p.json")
    mode = stat.S_IMODE(os.stat(tmp_path / "p.json").st_mode)
    assert mode & stat.S_IRGRP and mode & stat.S_IROTH  # not the 0600 of a temporary file
