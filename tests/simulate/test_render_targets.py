"""Rendered circle grids, asymmetric circle grids and ChArUco boards against their exact truth.

OpenCV's own detectors (``findCirclesGrid``, ``aruco.CharucoDetector``) must find the rendered
boards, with the recorded ids and where the truth says.  The renders are small (640x480, the
default sensor binned 2x2: same field of view) and few.

Tolerances.  The realistic level's noise at the white board (129 DN): sqrt(129/40 + 1) = 2.1 DN;
edge slope at PSF sigma 0.9 px for the 120 DN contrast: 120 / (sqrt(2 pi) 0.9) = 53 DN/px, so
0.04 px of noise per edge pixel, averaged over the ~pi D edge pixels of a dot of D px: ~0.006 px
for a blob centre.  OpenCV's blob centres (moments of thresholded contours, averaged over
threshold steps) measure 0.02-0.03 px RMS on these renders, ChArUco corners (cornerSubPix on a
homography-interpolated guess) ~0.1 px RMS: the bars below are 2-3x those, and each test also
requires the right truth to explain the detections better than the wrong one.
"""

from __future__ import annotations

from dataclasses import replace
import types

import cv2
import numpy as np
import pytest

import lightplane.simulate.render as R
from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.simulate.scene import default_camera


def _small_camera() -> Camera:
    c0 = default_camera()
    K = c0.K.copy()
    K[:2] /= 2
    K[0, 2], K[1, 2] = (c0.cx + 0.5) / 2 - 0.5, (c0.cy + 0.5) / 2 - 0.5
    return Camera(K, c0.dist, 640, 480)


CAM = _small_camera()
#: big dots, strongly tilted, near: the dots' ellipse centres 0.16-0.28 px from their projected centres
BIASED = dict(target=("circles", 5, 4, 14.0, 10.0), distance_mm=(300.0, 340.0), tilt_deg=(50.0, 60.0),
              centre_frac=0.3)


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(e ** 2, axis=1))))


def _circles(img: np.ndarray, spec: R.TargetSpec, max_area: float = 5000.0,
             clustering: bool = False) -> np.ndarray | None:
    flags = cv2.CALIB_CB_SYMMETRIC_GRID if spec.kind == "circles" else cv2.CALIB_CB_ASYMMETRIC_GRID
    flags |= cv2.CALIB_CB_CLUSTERING if clustering else 0
    # OpenCV's default blob detector (dots of 25-5000 px²; more for the big dots); with
    # CALIB_CB_CLUSTERING the symmetric grid comes back in the reverse order on these views
    params = cv2.SimpleBlobDetector_Params()
    params.maxArea = max_area
    ok, c = cv2.findCirclesGrid(img, (spec.cols, spec.rows), flags=flags,
                                blobDetector=cv2.SimpleBlobDetector_create(params))
    return c.reshape(-1, 2) if ok else None


# ----------------------------------------------------------------------------- specs, layout
def test_target_spec_accepts_objects_dicts_tuples_and_names():
    ref = R.TargetSpec("charuco", 11, 8, 12.0, 9.0, "DICT_4X4_50")
    obj = types.SimpleNamespace(kind="charuco", cols=11, rows=8, square_mm=12.0, marker_mm=9.0,
                                dictionary="DICT_4X4_50", dot_mm=None)
    assert R.target_spec(obj) == ref
    assert R.target_spec(ref.to_dict()) == ref
    assert R.target_spec(("charuco", 11, 8, 12, 9, "DICT_4X4_50")) == ref
    assert R.target_spec("charuco") == ref
    assert R.target_spec(("circles", 4, 3, 10.0)).dot_diameter_mm == 5.0
    assert R.target_spec(("acircles", 4, 3, 10.0, 14.0)).dot_diameter_mm == 14.0  # < 10 sqrt(2)
    for bad in (("circles", 4, 3, 10.0, 10.0), ("acircles", 4, 3, 10.0, 14.2), ("charuco", 5, 4, 10.0),
                ("charuco", 5, 4, 10.0, 11.0, "DICT_4X4_50"), ("hexagons", 4, 3, 1.0), ("circles", 1, 3, 1.0),
                {"kind": "circles", "cols": 4, "rows": 3}, {"kind": "circles", "cols": 4, "rows": 3, "square_mm": 1,
                                                             "colour": "red"}):
        with pytest.raises(LightplaneError):
            R.target_spec(bad)


def test_object_points_follow_the_opencv_conventions():
    a = R.target_object_points(("acircles", 4, 3, 10.0))
    assert a.shape == (12, 3) and np.all(a[:, 2] == 0)
    assert np.allclose(a[:5], [[0, 0, 0], [20, 0, 0], [40, 0, 0], [60, 0, 0], [10, 10, 0]])
    c = R.target_object_points(("circles", 4, 3, 10.0))
    assert np.allclose(c[[0, 1, 4, 11]], [[0, 0, 0], [10, 0, 0], [0, 10, 0], [30, 20, 0]])
    spec = R.target_spec("charuco")
    board = R._charuco_layout(spec)["board"]
    ch = R.target_object_points(spec)
    assert np.allclose(ch, np.asarray(board.getChessboardCorners()).reshape(-1, 3), atol=1e-5)


@pytest.mark.parametrize("target", ["charuco", ("charuco", 5, 6, 10.0, 7.5, "DICT_6X6_250"),
                                    ("charuco", 7, 5, 10.0, 7.0, "DICT_5X5_100")])
def test_charuco_texture_is_opencvs_own_board(target):
    # one texel per pixel: OpenCV's drawing of the board is the renderer's texture, bit for bit
    lay = R._charuco_layout(R.target_spec(target))
    tex = lay["texels"]
    img = lay["board"].generateImage((tex.shape[1], tex.shape[0]), marginSize=0, borderBits=1)
    assert np.array_equal(img == 0, tex == 1)


def test_dot_ellipse_centres_are_the_centres_of_the_projected_rims():
    # pinhole camera, strongly tilted disc: the analytic centre of the image ellipse (dual conic)
    # is the centre of a conic fitted to densely projected rim points; the image of the disc's
    # centre is off it by the perspective bias, which grows as the disc's radius squared
    cam = CAM.pinhole()
    Rm = R._rotation(np.array([0.6, 0.8, 0.0]), np.deg2rad(55.0))
    t = np.array([-20.0, 10.0, 300.0])
    centres = np.array([[0.0, 0.0, 0.0], [30.0, -15.0, 0.0]])
    ang = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    biases = []
    for r in (3.0, 6.0):
        d = R.dot_image_centres(cam, Rm, t, centres, r)
        for k, c in enumerate(centres):
            rim = c + r * np.column_stack([np.cos(ang), np.sin(ang), 0 * ang])
            uv = cam.project(rim @ Rm.T + t)
            x, y = uv[:, 0], uv[:, 1]
            A = np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)])
            a, b, cc, dd, e, _ = np.linalg.svd(A / np.abs(A).max(axis=0))[2][-1] / np.abs(A).max(axis=0)
            centre = np.linalg.solve([[2 * a, b], [b, 2 * cc]], [-dd, -e])
            assert np.allclose(centre, d["ellipse_centres_undistorted_px"][k], atol=1e-6)
            assert np.allclose(d["ellipse_centres_px"][k], centre, atol=1e-6)  # no distortion
            assert np.allclose(d["blob_centroids_px"][k], centre, atol=1e-6)   # an ellipse's centroid
        biases.append(np.linalg.norm(d["ellipse_centres_px"] - d["projected_centres_px"], axis=1))
    assert np.all(biases[0] > 0.01)
    assert np.allclose(biases[1] / biases[0], 4.0, rtol=0.02)


# ----------------------------------------------------------------------------- renders
@pytest.fixture(scope="module")
def circle_sets():
    out = {}
    for kind, target in (("circles", ("circles", 7, 5, 12.0)), ("acircles", ("acircles", 4, 7, 10.0))):
        out[kind] = R.render_target_dataset(target, 2, 1, R.BoardOptions(difficulty="realistic"), camera=CAM)
    out["biased"] = R.render_target_dataset(BIASED["target"], 2, 2, R.BoardOptions(
        difficulty="realistic", capture=replace(R.CALIBRATION_CAPTURE, **{k: v for k, v in BIASED.items() if k != "target"})),
        camera=CAM)
    return out


@pytest.mark.parametrize("kind", ["circles", "acircles", "biased"])
def test_opencv_finds_the_circle_grids_at_their_ellipse_centres(circle_sets, kind):
    ds = circle_sets[kind]
    spec = R.target_spec(ds.truth["options"]["target"])
    for img, v in zip(ds.images, ds.truth["views"]):
        # the big, steeply seen dots: the grid is found by clustering only (in its own order)
        c = _circles(img, spec, 20000.0 if kind == "biased" else 5000.0, clustering=kind == "biased")
        assert c is not None, v["file"]
        nearest = np.argmin(np.linalg.norm(c[:, None] - v["points_px"][None], axis=2), axis=1)
        if kind == "biased":
            assert sorted(nearest) == list(v["ids"])
            c = c[np.argsort(nearest)]
        else:  # id order: OpenCV's point k is the truth's id k
            assert np.array_equal(nearest, v["ids"])
        e_ell = _rms(c - v["ellipse_centres_px"])
        e_blob = _rms(c - v["blob_centroids_px"])
        e_proj = _rms(c - v["points_px"])
        tol = 0.1 if kind == "biased" else 0.06  # 70 px dots: coarser contour moments
        assert e_ell < tol and e_blob < tol, (e_ell, e_blob)
        if kind == "biased":
            # the detections are off the projected centres by the perspective bias geometry predicts
            b = v["ellipse_centres_px"] - v["points_px"]
            d = c - v["points_px"]
            slope = float(np.sum(d * b) / np.sum(b * b))
            assert 0.85 < slope < 1.15, slope
            assert np.median(v["centre_bias_px"]) > 0.15 and e_ell < 0.3 * e_proj


def test_opencv_finds_the_charuco_board_with_the_true_ids():
    spec = R.target_spec("charuco")
    ds = R.render_target_dataset(spec, 2, 3, R.BoardOptions(difficulty="realistic"), camera=CAM)
    det = cv2.aruco.CharucoDetector(R._charuco_layout(spec)["board"])
    for img, v in zip(ds.images, ds.truth["views"]):
        cc, cid, mc, mid = det.detectBoard(img)
        assert cid is not None
        cid, cc, mid = cid.ravel(), cc.reshape(-1, 2), mid.ravel()
        n_pts = (spec.cols - 1) * (spec.rows - 1)
        assert len(cid) >= 0.9 * n_pts and len(set(cid.tolist())) == len(cid) and cid.max() < n_pts
        assert _rms(cc - v["points_px"][cid]) < 0.25
        # every detected marker carries its true id, its corners where the truth has them
        truth_ids = list(v["marker_ids"])
        assert len(mid) >= 0.9 * len(truth_ids)
        for k, m in zip(mid, mc):
            corners = v["marker_corners_px"][truth_ids.index(int(k))]
            m = m.reshape(4, 2)
            # contour-polygon corners (integer px, cut inwards by the blur): ~1 px off, evenly
            assert np.max(np.linalg.norm(m - corners, axis=1)) < 3.5
            assert np.linalg.norm(m.mean(axis=0) - corners.mean(axis=0)) < 1.0


def test_chessboard_target_renders_as_render_chessboard_dataset():
    a = R.render_target_dataset(("chessboard", 6, 4, 14.0), 1, 5, R.BoardOptions(difficulty="realistic"), camera=CAM)
    b = R.render_chessboard_dataset(1, 5, R.BoardOptions(
        difficulty="realistic", capture=replace(R.CALIBRATION_CAPTURE, board=(6, 4), square_mm=14.0)), camera=CAM)
    assert np.array_equal(a.images[0], b.images[0])
    assert np.allclose(a.truth["views"][0]["points_px"], b.truth["views"][0]["corners_px"])
    ok, c = cv2.findChessboardCorners(a.images[0], (6, 4))
    assert ok


def test_render_target_dataset_saves_its_truth(tmp_path):
    import json

    ds = R.render_target_dataset(("acircles", 3, 3, 20.0), 1, 0, R.BoardOptions(samples=4, edge_samples=4), camera=CAM)
    ds.save(tmp_path / "ac")
    truth = json.loads((tmp_path / "ac" / "truth.json").read_text())
    assert truth["scene"] == "target" and truth["target"]["kind"] == "acircles"
    v = truth["views"][0]
    assert (tmp_path / "ac" / v["file"]).exists()
    assert np.asarray(v["ellipse_centres_px"]).shape == (9, 2) and len(v["centre_bias_px"]) == 9
