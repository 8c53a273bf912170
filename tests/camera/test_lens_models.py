"""Lens models (plumb bob, rational, thin prism, tilted sensor, fisheye): projection against OpenCV,
undistortion exact over the whole image, Jacobians against finite differences, camera files of every
model (ours, ROS, OpenCV), bad files, and the renderer's rays of every model."""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from lightplane import Camera, LightplaneError
from lightplane.simulate.scene import (LENS_CAMERAS, default_plane, lens_camera, scheimpflug_camera,
                                          scheimpflug_focal_plane)
from lightplane.measure.options import MeasureOptions
from lightplane.stripe.options import StripeOptions


def dense_grid(cam: Camera, nu: int = 161, nv: int = 121) -> np.ndarray:
    """Pixel positions over the whole image, its outer pixel edges (and so the corners) included."""
    u, v = np.meshgrid(np.linspace(-0.5, cam.width - 0.5, nu), np.linspace(-0.5, cam.height - 0.5, nv))
    return np.column_stack([u.ravel(), v.ravel()])


@pytest.mark.parametrize("model", LENS_CAMERAS)
def test_undistortion_exact_over_the_whole_image(model):
    cam = lens_camera(model)
    assert cam.model == model
    uv = dense_grid(cam)
    xy = cam.undistort_points(uv, normalized=True)
    assert np.all(np.isfinite(xy))
    assert np.abs(cam.normalized_to_pixels(xy) - uv).max() <= 1e-9
    # and back: the undistorted pixels of projected points are their pinhole projections
    p = np.column_stack([xy, np.ones(len(xy))]) * 377.0
    assert np.abs(cam.undistort_points(cam.project(p)) - cam.project(p, distort=False)).max() <= 1e-9


@pytest.mark.parametrize("model", LENS_CAMERAS)
def test_projection_is_opencvs(model):
    cam = lens_camera(model)
    xy = cam.undistort_points(dense_grid(cam, 41, 31), normalized=True)
    p = np.column_stack([xy, np.ones(len(xy))]) * np.linspace(200, 900, len(xy))[:, None]
    if model == "fisheye":
        ref, _ = cv2.fisheye.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist)
    else:
        ref, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    assert np.abs(cam.project(p) - ref.reshape(-1, 2)).max() < 1e-9


@pytest.mark.parametrize("model", LENS_CAMERAS)
def test_jacobians_match_finite_differences(model):
    cam = lens_camera(model)
    xy = cam.undistort_points(dense_grid(cam, 33, 25), normalized=True)
    xy = np.vstack([xy, [[0.0, 0.0], [1e-10, -2e-10]]])  # the axis itself
    J = cam.pixel_jacobian(xy)
    h = 1e-7
    for k in range(2):
        e = np.zeros(2)
        e[k] = h
        fd = (cam.normalized_to_pixels(xy + e) - cam.normalized_to_pixels(xy - e)) / (2 * h)
        # central differences: error ~ h² f''' ~ 1e-14 * 1e3 px plus rounding 1e-13 px / h ~ 1e-6 px
        assert np.abs(J[:, :, k] - fd).max() < 1e-5 * cam.fx * 1e-3 + 1e-5, k
    if model in ("thin_prism", "tilted"):  # not symmetric: a model that assumed j12 == j21 would be wrong
        assert np.abs(J[:, 0, 1] - J[:, 1, 0]).max() > 1e-3


def test_skew_is_applied_and_inverted():
    base = lens_camera("tilted")
    K = base.K.copy()
    K[0, 1] = 3.5
    cam = Camera(K, base.dist, base.width, base.height)
    uv = dense_grid(cam, 41, 31)
    xy = cam.undistort_points(uv, normalized=True)
    assert np.abs(cam.normalized_to_pixels(xy) - uv).max() <= 1e-9
    xd = cam.distort_normalized(xy)
    manual = np.column_stack([K[0, 0] * xd[:, 0] + 3.5 * xd[:, 1] + K[0, 2], K[1, 1] * xd[:, 1] + K[1, 2]])
    assert np.abs(cam.normalized_to_pixels(xy) - manual).max() < 1e-9
    # a pose through the skewed camera (OpenCV ignores skew: solve_pnp must not)
    obj = np.array([[x, y, 0.0] for x in range(0, 100, 20) for y in range(0, 80, 20)], float)
    R = cv2.Rodrigues(np.array([0.2, -0.3, 0.1]))[0]
    t = np.array([-40.0, -30.0, 420.0])
    R2, t2 = cam.solve_pnp(obj, cam.project(obj @ R.T + t))
    assert np.abs(R2 - R).max() < 1e-9 and np.abs(t2 - t).max() < 1e-7


def test_scheimpflug_rig_focuses_the_light_plane():
    cam = scheimpflug_camera()
    tx, ty = cam.dist[12], cam.dist[13]
    assert 3.0 <= np.rad2deg(np.hypot(tx, ty)) <= 6.0
    focus = scheimpflug_focal_plane(tx, ty, 16.0, cam.meta["focus_mm"])
    plane = default_plane()
    assert np.abs(focus.normal - plane.normal).max() < 1e-12 and abs(focus.d - plane.d) < 1e-9
    # without the tilt the plane in focus is the fronto-parallel one
    flat = scheimpflug_focal_plane(0.0, 0.0, 16.0, 450.0)
    assert np.allclose(np.abs(flat.normal), [0, 0, 1]) and abs(flat.normal @ [0, 0, 450.0] + flat.d) < 1e-9


def test_tilted_pinhole_is_a_rotated_pinhole():
    """OpenCV's tilt matrix is P R (R: the sensor's rotation, P: a scale and shift), so without distortion
    a tilted sensor projects exactly like an untilted one with K' = K P viewing the frame turned by R:
    the tilt then cannot be told from a rotation of the camera frame plus a principal-point shift at all,
    and only the lens distortion, applied before the tilt, tells them apart (README, Lens models)."""
    from lightplane.camera.lens import tilt_matrix

    tx, ty = np.deg2rad(1.3), np.deg2rad(4.52)
    cam = scheimpflug_camera(dist=(0.0, 0.0, 0.0, 0.0, 0.0))
    cam = Camera(cam.K, np.concatenate([np.zeros(12), [tx, ty]]), cam.width, cam.height, model="tilted")
    ry = np.array([[np.cos(ty), 0, -np.sin(ty)], [0, 1, 0], [np.sin(ty), 0, np.cos(ty)]])
    rx = np.array([[1, 0, 0], [0, np.cos(tx), np.sin(tx)], [0, -np.sin(tx), np.cos(tx)]])
    R = ry @ rx
    P = tilt_matrix(tx, ty) @ R.T
    assert np.allclose(P[2], [0, 0, 1], atol=1e-15) and abs(P[0, 1]) + abs(P[1, 0]) < 1e-15  # scale and shift
    turned = Camera(cam.K @ P, np.zeros(5), cam.width, cam.height)
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-60, 60, 500), rng.uniform(-45, 45, 500), rng.uniform(350, 650, 500)])
    assert np.abs(cam.project(pts) - turned.project(pts @ R.T)).max() < 1e-9
    # the principal point moves by f sin(tauY) (~337 px here): what an untilted model of the camera reports
    assert np.isclose(turned.cx - cam.cx, cam.fx * np.sin(ty) * np.cos(tx), rtol=1e-12)


@pytest.mark.parametrize("model", LENS_CAMERAS)
def test_camera_files_round_trip_exactly(tmp_path, model):
    cam = lens_camera(model)
    paths = [cam.save(tmp_path / "c.json"), cam.save(tmp_path / "c.yaml", fmt="ros"),
             cam.save(tmp_path / "c.xml", fmt="opencv"), cam.save(tmp_path / "c_cv.yml", fmt="opencv")]
    for p in paths:
        back = Camera.load(p)
        assert back == cam and back.model == model, p.name
        assert np.array_equal(back.dist, cam.dist) and np.array_equal(back.K, cam.K)
    assert json.loads(paths[0].read_text())["model"] == model
    ros = paths[1].read_text()
    assert {"plumb_bob": "plumb_bob", "fisheye": "equidistant"}.get(model, "rational_polynomial") in ros


@pytest.mark.parametrize("n", [4, 5, 8, 12, 14])
def test_opencv_written_files_of_every_length(tmp_path, n):
    rng = np.random.default_rng(n)
    K = np.array([[1400.0, 0.0, 640.0], [0.0, 1401.0, 480.0], [0.0, 0.0, 1.0]])
    d = rng.normal(0, 0.01, n)
    for name in ("c.yaml", "c.xml"):  # written by OpenCV itself, as calibration samples do
        fs = cv2.FileStorage(str(tmp_path / name), cv2.FILE_STORAGE_WRITE)
        fs.write("image_width", 1280)
        fs.write("image_height", 960)
        fs.write("camera_matrix", K)
        fs.write("distortion_coefficients", d.reshape(-1, 1))
        fs.release()
        cam = Camera.load(tmp_path / name)
        expect = {4: "plumb_bob", 5: "plumb_bob", 8: "rational", 12: "thin_prism", 14: "tilted"}[n]
        assert cam.model == expect
        assert np.array_equal(cam.dist[:n], d) and (n != 4 or cam.dist[4] == 0)
        ref, _ = cv2.projectPoints(np.array([[50.0, -40.0, 300.0]]), np.zeros(3), np.zeros(3), K, d)
        assert np.abs(cam.project(np.array([[50.0, -40.0, 300.0]])) - ref.reshape(-1, 2)).max() < 1e-9


ROS = """image_width: 1280
image_height: 960
camera_name: cam
camera_matrix: {{rows: 3, cols: 3, data: [1400.0, 0.0, 640.0, 0.0, 1400.0, 480.0, 0.0, 0.0, 1.0]}}
distortion_model: {model}
distortion_coefficients: {{rows: 1, cols: {n}, data: [{data}]}}
rectification_matrix: {{rows: 3, cols: 3, data: [1, 0, 0, 0, 1, 0, 0, 0, 1]}}
projection_matrix: {{rows: 3, cols: 4, data: [1400.0, 0.0, 640.0, 0.0, 0.0, 1400.0, 480.0, 0.0, 0.0, 0.0, 1.0, 0.0]}}
"""


@pytest.mark.parametrize("ros_model,n,model", [("plumb_bob", 5, "plumb_bob"), ("plumb_bob", 4, "plumb_bob"),
                                               ("rational_polynomial", 8, "rational"),
                                               ("rational_polynomial", 12, "thin_prism"),
                                               ("rational_polynomial", 14, "tilted"), ("equidistant", 4, "fisheye")])
def test_ros_files_of_every_model(tmp_path, ros_model, n, model):
    data = [0.01 * (i + 1) * (-1) ** i for i in range(n)]
    p = tmp_path / "c.yaml"
    p.write_text(ROS.format(model=ros_model, n=n, data=", ".join(map(str, data))))
    cam = Camera.load(p)
    assert cam.model == model and np.array_equal(cam.dist[:n], data)


@pytest.mark.parametrize("ros_model,n,msg", [("kannala_brandt", 4, "not supported"), ("plumb_bob", 8, "needs 5"),
                                             ("rational_polynomial", 5, "needs 8, 12 or 14"),
                                             ("equidistant", 5, "needs 4")])
def test_bad_ros_files_one_line_exit_2(tmp_path, ros_model, n, msg):
    p = tmp_path / "c.yaml"
    p.write_text(ROS.format(model=ros_model, n=n, data=", ".join(["0.01"] * n)))
    with pytest.raises(LightplaneError, match=msg):
        Camera.load(p)
    r = subprocess.run([sys.executable, "-m", "lightplane", "measure", str(tmp_path / "none.png"), "--camera", str(p),
                        "--plane", str(tmp_path / "plane.json"), "-o", str(tmp_path / "out.ply")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and msg in lines[0] and "c.yaml" in lines[0], r.stderr
    assert not (tmp_path / "out.ply").exists()


def test_bad_json_and_opencv_files(tmp_path):
    good = lens_camera("rational")
    d = good.to_dict()
    for change, msg in (({"model": "brown"}, "unknown lens model"), ({"model": "tilted"}, "needs 14"),
                        ({"dist": [0.1] * 7, "model": None}, "4, 5, 8, 12 or 14"), ({"model": 3}, "model")):
        p = tmp_path / "c.json"
        p.write_text(json.dumps({**d, **change}))
        with pytest.raises(LightplaneError, match=msg):
            Camera.load(p)
    fs = cv2.FileStorage(str(tmp_path / "c.xml"), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 1280)
    fs.write("image_height", 960)
    fs.write("camera_matrix", good.K)
    fs.write("distortion_coefficients", np.zeros((1, 6)))
    fs.release()
    with pytest.raises(LightplaneError, match="c.xml.*4, 5, 8, 12 or 14"):
        Camera.load(tmp_path / "c.xml")


def test_no_silent_plumb_bob():
    """Coefficients beyond the fifth are kept and used (they were once cut or refused)."""
    cam = lens_camera("rational")
    five = Camera(cam.K, cam.dist[:5], cam.width, cam.height)
    p = np.array([[150.0, 100.0, 300.0]])
    assert np.abs(cam.project(p) - five.project(p)).max() > 1.0
    assert cam.pinhole().model == "plumb_bob" and not cam.pinhole().has_distortion
    assert lens_camera("fisheye").has_distortion  # equidistant with zero k is still not a pinhole
    assert Camera(np.eye(3) * [[1], [1], [1]], np.zeros(4), 10, 10, model="fisheye").has_distortion


@pytest.mark.parametrize("model", LENS_CAMERAS)
def test_renderer_rays_are_the_cameras(model):
    from lightplane.simulate.render_core import _ray_maps

    cam = lens_camera(model)
    centre, corner = _ray_maps(cam)
    v, u = np.mgrid[0:cam.height:7, 0:cam.width:7]
    uv = np.column_stack([u.ravel(), v.ravel()]).astype(float)
    xy = cam.undistort_points(uv, normalized=True)
    assert np.abs(centre[v.ravel(), u.ravel()] - xy).max() < 1e-12
    # the renderer's rays reproject onto their pixels (corners of the image included)
    c = corner[[0, 0, -1, -1], [0, -1, 0, -1]]
    assert np.abs(cam.normalized_to_pixels(c) - [[-0.5, -0.5], [cam.width - 0.5, -0.5], [-0.5, cam.height - 0.5],
                                                 [cam.width - 0.5, cam.height - 0.5]]).max() < 1e-9


def _ml_scene(model, n=8, seed=3):
    from lightplane.simulate.scene import sample_placements, synthetic_observations

    cam, plane = lens_camera(model), default_plane()
    ps = sample_placements(n, np.random.default_rng(seed), camera=cam, plane=plane)
    obs = [synthetic_observations(cam, plane, p, n_rim=120, n_stripe=150) for p in ps]
    return cam, plane, ps, obs


@pytest.mark.parametrize("model", ["tilted", "rational", "thin_prism", "fisheye"])
def test_ml_refinement_exact_with_every_model(model):
    """Noise-free observations through the model: the ML solution is the truth (its residual Jacobian
    uses the model's unsymmetric distortion Jacobian)."""
    from lightplane.plane.ml import _Pose, _Problem, refine_ml

    cam, plane, ps, obs = _ml_scene(model)
    rng = np.random.default_rng(4)
    p0 = type(plane)(plane.normal + rng.normal(0, 0.01, 3), plane.d + 3.0)
    poses0 = [_Pose(p.center + rng.normal(0, 1.0, 3), p.normal + rng.normal(0, 0.01, 3)) for p in ps]
    rims, sts = [o[0] for o in obs], [o[1] for o in obs]
    res = refine_ml(cam, 25.0, rims, sts, p0, poses0)
    ang = np.arctan2(np.linalg.norm(np.cross(res.plane.normal, plane.normal)), abs(res.plane.normal @ plane.normal))
    assert ang < 1e-9 and abs(res.plane.d - plane.d) < 1e-8 * abs(plane.d)
    assert res.sigma_px < 1e-8
    # the analytic Jacobian of the joint problem against central differences
    prob = _Problem(cam, 25.0, [r[::6] for r in rims], [s[::6] for s in sts], p0, poses0)
    x = prob.x0 + rng.normal(0, 1e-3, prob.p)
    J = prob.dense_jacobian(x)
    Jn = np.zeros_like(J)
    for k in range(prob.p):
        h = 1e-6 * max(1.0, abs(x[k]))
        xp, xm = x.copy(), x.copy()
        xp[k] += h
        xm[k] -= h
        Jn[:, k] = (prob.residuals(xp) - prob.residuals(xm)) / (2 * h)
    assert (np.abs(J - Jn).max(axis=0) / np.abs(J).max(axis=0)).max() < 1e-5
    if model != "fisheye":  # the same points read with the first five coefficients only: pixels off
        five = Camera(cam.K, cam.dist[:5], cam.width, cam.height)
        all_uv = np.vstack(rims + sts)
        assert np.abs(five.undistort_points(all_uv) - cam.undistort_points(all_uv)).max() > 0.5


@pytest.mark.parametrize("model", ["tilted", "thin_prism", "rational", "fisheye"])
def test_measurement_lookup_tables_with_every_model(model):
    """The lookup tables (undistortion and its unsymmetric Jacobian per grid line, Hermite between)
    equal the exact undistortion to 1e-6 px along rows and along columns."""
    from lightplane.measure.profile import ProfileMeasurer

    cam, plane = lens_camera(model), default_plane()
    rng = np.random.default_rng(7)
    for axis, uv in (("rows", np.column_stack([rng.uniform(-0.49, cam.width - 0.51, 3000),
                                                rng.integers(0, cam.height, 3000)])),
                     ("columns", np.column_stack([rng.integers(0, cam.width, 3000),
                                                   rng.uniform(-0.49, cam.height - 0.51, 3000)]))):
        m = ProfileMeasurer(cam, plane, MeasureOptions(StripeOptions(width_px=3.5), axis=axis))
        got, exact = m.normalized(uv.astype(float)), cam.undistort_points(uv.astype(float), normalized=True)
        assert m.has_lookup
        # in pixels of the undistorted image: through the Jacobian of K
        assert np.abs(got - exact).max() * cam.fx < 1e-6, axis
