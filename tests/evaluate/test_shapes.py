"""lightplane.evaluate.shapes: spheres, planes, steps, rigid alignment on exact synthetic points (tolerances from the noise)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lightplane.core.errors import LightplaneError
from lightplane.evaluate.shapes import fit_plane, fit_sphere, plane_accuracy, rigid_align, step_height


def _cap(rng, n, center, radius, sigma):
    v = rng.normal(size=(n, 3))
    v = v[v[:, 2] < 0]  # the half a scanner sees
    return np.asarray(center) + radius * v / np.linalg.norm(v, axis=1, keepdims=True) + rng.normal(0, sigma, (len(v), 3))


def _plane_points(rng, n, normal, d, sigma, half=30.0):
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    e1 = np.cross(normal, [1.0, 0, 0]) if abs(normal[0]) < 0.9 else np.cross(normal, [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    uv = rng.uniform(-half, half, (n, 2))
    p0 = -d * normal + np.array([0.0, 0.0, 0.0])
    return p0 + uv[:, :1] * e1 + uv[:, 1:] * e2 + rng.normal(0, sigma, (n, 1)) * normal


def test_sphere_exact():
    rng = np.random.default_rng(0)
    p = _cap(rng, 400, [3.0, -1.0, 450.0], 25.4, 0.0)
    f = fit_sphere(p)
    assert abs(f.radius_mm - 25.4) < 1e-9 and np.allclose(f.center_mm, [3, -1, 450], atol=1e-9)
    assert f.rms_mm < 1e-9 and f.n_inliers == f.n_points == len(p)


@pytest.mark.parametrize("sigma", [0.005, 0.03])
def test_sphere_noise_and_outliers(sigma):
    rng = np.random.default_rng(2)
    p = _cap(rng, 4000, [1.0, -2.0, 470.0], 25.4, sigma)
    n_good = len(p)
    p = np.vstack([p, rng.uniform(-60, 60, (100, 3)) + [0, 0, 560], np.full((3, 3), np.nan)])
    f = fit_sphere(p)
    # a half sphere of N points with isotropic noise sigma: radius sigma ~ sigma * 2 / sqrt(N) (centre along z
    # and radius correlate); 6 such sigmas as the tolerance
    tol = 6 * sigma * 2 / np.sqrt(n_good)
    assert abs(f.radius_mm - 25.4) < tol
    assert np.linalg.norm(f.center_mm - [1, -2, 470]) < 2 * tol
    # rms of the 3D noise's radial part: sigma (4 MAD keeps ~all of a Gaussian)
    assert abs(f.rms_mm - sigma) < 0.1 * sigma
    assert n_good - 0.01 * n_good <= f.n_inliers <= n_good and f.n_points == n_good + 100
    d = f.to_dict()
    assert set(d) == {"center_mm", "radius_mm", "rms_mm", "n_inliers", "n_points"} and isinstance(d["center_mm"], list)


def test_sphere_degenerate():
    with pytest.raises(LightplaneError, match="at least 4"):
        fit_sphere(np.zeros((3, 3)))
    with pytest.raises(LightplaneError, match="at least 4"):
        fit_sphere(np.full((10, 3), np.nan))
    rng = np.random.default_rng(0)
    flat = np.column_stack([rng.uniform(-10, 10, (50, 2)), np.full(50, 400.0)])
    with pytest.raises(LightplaneError, match="one plane"):
        fit_sphere(flat)
    with pytest.raises(LightplaneError, match=r"\(N, 3\)"):
        fit_sphere(np.zeros((10, 2)))


def test_plane_flatness_with_noise_and_outliers():
    rng = np.random.default_rng(3)
    n_true = np.array([0.1, -0.3, 1.0])
    n_true /= np.linalg.norm(n_true)
    sigma = 0.01
    p = _plane_points(rng, 3000, n_true, -480.0, sigma)
    p = np.vstack([p, p[:40] + 2.0 * n_true])  # 40 points 2 mm off
    f = fit_plane(p)
    assert f.normal @ n_true > 0 and np.degrees(np.arccos(min(1.0, f.normal @ n_true))) < 6 * sigma / 30 * 180 / np.pi
    assert abs(f.d + 480.0) < 6 * sigma
    assert abs(f.rms_mm - sigma) < 0.1 * sigma
    assert f.n_inliers >= 3000 - 30 and not f.inliers[-40:].any()
    assert 4 * sigma < f.peak_to_valley_mm < 10 * sigma
    assert np.allclose(f.distances(p[:5]), p[:5] @ f.normal + f.d)
    exact = fit_plane(_plane_points(rng, 50, n_true, -480.0, 0.0))
    assert exact.rms_mm < 1e-9 and abs(exact.d + 480.0) < 1e-9 and exact.n_inliers == 50


def test_plane_degenerate():
    with pytest.raises(LightplaneError, match="at least 3"):
        fit_plane(np.zeros((2, 3)))
    line = np.outer(np.linspace(0, 10, 20), [1.0, 2.0, 3.0])
    with pytest.raises(LightplaneError, match="one line"):
        fit_plane(line)
    with pytest.raises(LightplaneError, match="one line"):
        fit_plane(np.ones((10, 3)))


def test_step_height():
    rng = np.random.default_rng(4)
    n = np.array([0.0, -0.2, 1.0])
    n /= np.linalg.norm(n)
    sigma = 0.01
    base = _plane_points(rng, 2000, n, -500.0, sigma)
    top = _plane_points(rng, 2000, n, -490.0, sigma)  # 10 mm towards the camera
    s = step_height(base, np.vstack([top, top[:20] + 3 * n]))
    # separation of two centroids of 2000 points with sigma along the normal
    assert abs(s.height_mm - 10.0) < 6 * sigma * np.sqrt(2 / 2000) + 1e-6
    assert s.parallel_deg < 0.01 and abs(abs(s.normal @ n) - 1) < 1e-6
    assert s.top.n_inliers <= 2000 and not s.top.inliers[-20:].any()
    exact = step_height(_plane_points(rng, 30, n, -500.0, 0.0), _plane_points(rng, 30, n, -490.0, 0.0))
    assert abs(exact.height_mm - 10.0) < 1e-9 and exact.parallel_deg < 1e-6
    assert set(exact.to_dict()) == {"height_mm", "normal", "parallel_deg", "base", "top"}


def test_rigid_align():
    rng = np.random.default_rng(5)
    a = rng.uniform(-50, 50, (200, 3))
    R = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    t = np.array([1.0, 2.0, -3.0])
    b = a @ R.T + t
    al = rigid_align(a, b)
    assert np.allclose(al.rotation, R, atol=1e-12) and np.allclose(al.translation, t, atol=1e-9) and al.rms_mm < 1e-9
    assert np.allclose(al.apply(a), b, atol=1e-9)
    sigma = 0.02
    bn = b + rng.normal(0, sigma, b.shape)
    al = rigid_align(a, bn)
    # 3D residual after fitting 6 parameters to 600 coordinates: sigma * sqrt(3 (N - 2) / N)
    assert abs(al.rms_mm - sigma * np.sqrt(3 * 198 / 200)) < 0.1 * sigma
    # a mirror image is not a rotation: the best proper rotation leaves a residual
    assert rigid_align(a, a * [1, 1, -1]).rms_mm > 1.0
    a[0] = np.nan  # ignored
    assert rigid_align(a, b).rms_mm < 1e-9


def test_rigid_align_degenerate():
    with pytest.raises(LightplaneError, match="same shape"):
        rigid_align(np.zeros((4, 3)), np.zeros((5, 3)))
    with pytest.raises(LightplaneError, match="at least 3"):
        rigid_align(np.zeros((2, 3)), np.zeros((2, 3)))
    line = np.outer(np.arange(5.0), [1.0, 0, 0])
    assert rigid_align(line, line + 1.0).rms_mm < 1e-12  # collinear: the rotation about the line is free


def test_plane_accuracy_exact():
    from lightplane.plane.model import LightPlane
    from lightplane.simulate.scene import default_camera, default_plane

    cam, pl = default_camera(), default_plane()
    a = plane_accuracy(pl, cam, pl, cam)
    assert a["angle_deg"] == 0 and a["tri_rms_mm"] < 1e-9 and a["tri_rms_aligned_mm"] < 1e-9
    a = plane_accuracy(LightPlane(pl.normal, pl.d - 0.01), cam, pl, cam)
    assert abs(abs(a["offset_mm"]) - 0.01) < 1e-9 and a["tri_rms_aligned_mm"] <= a["tri_rms_mm"]
