"""Camera model: projection/undistortion round trip, rays, camera files (docs/conventions.md §Lens model, §Camera file)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from lightplane import Camera, LightplaneError

STRONG = dict(K=[[900.0, 0, 655.5], [0, 905.0, 470.25], [0, 0, 1]], dist=[-0.3, 0.1, 0.001, 0.001, 0.0],
              width=1280, height=960)


def grid(cam: Camera, n: int = 50) -> np.ndarray:
    u, v = np.meshgrid(np.linspace(0, cam.width - 1, n), np.linspace(0, cam.height - 1, n))
    return np.column_stack([u.ravel(), v.ravel()])


def test_round_trip_strong_distortion_whole_image():
    cam = Camera(**STRONG)
    uv = grid(cam)
    xy = cam.undistort_points(uv, normalized=True)
    p = np.column_stack([xy, np.ones(len(xy))]) * 437.0
    back = cam.project(p)
    assert np.abs(back - uv).max() < 1e-6
    # and the other way round: undistort(project(X)) recovers the undistorted projection
    und = cam.undistort_points(back)
    assert np.abs(und - cam.project(p, distort=False)).max() < 1e-6


def test_project_matches_opencv():
    cam = Camera(**STRONG)
    rng = np.random.default_rng(1)
    p = np.column_stack([rng.uniform(-150, 150, 200), rng.uniform(-100, 100, 200), rng.uniform(300, 600, 200)])
    ref, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    assert np.abs(cam.project(p) - ref.reshape(-1, 2)).max() < 1e-9


def test_rays_agree_with_project():
    cam = Camera(**STRONG)
    uv = grid(cam, 20)
    r = cam.rays(uv)
    assert np.allclose(r[:, 2], 1.0)
    for depth in (1.0, 250.0, 1000.0):
        assert np.abs(cam.project(r * depth) - uv).max() < 1e-6
    ru = cam.rays(uv, unit=True)
    assert np.allclose(np.linalg.norm(ru, axis=1), 1.0)
    assert np.abs(cam.project(ru * 300.0) - uv).max() < 1e-6


def test_behind_camera_is_nan():
    cam = Camera(**STRONG)
    out = cam.project(np.array([[0.0, 0.0, -5.0], [0.0, 0.0, 0.0], [1.0, 2.0, 100.0]]))
    assert np.all(np.isnan(out[:2])) and np.all(np.isfinite(out[2]))


def test_undistort_image_straightens_a_line():
    cam = Camera(K=[[500.0, 0, 160], [0, 500, 120], [0, 0, 1]], dist=[-0.4, 0.05, 0, 0, 0], width=320, height=240)
    # A straight 3D line projected with distortion is curved; after undistort_image it is straight.
    t = np.linspace(-1, 1, 4000)
    p = np.column_stack([t * 120, 55 + 0 * t, 300 + 0 * t])
    uv = cam.project(p)
    img = np.zeros((240, 320), np.uint8)
    ok = cam.in_image(uv)
    ij = np.round(uv[ok]).astype(int)
    img[ij[:, 1], ij[:, 0]] = 255
    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    und = cam.undistort_image(img)
    rows = np.argmax(und[:, 40:280], axis=0)
    assert np.ptp(rows) <= 1  # straight (horizontal) within quantisation
    rows_dist = np.argmax(img[:, 40:280], axis=0)
    assert np.ptp(rows_dist) >= 2  # the distorted one was not


def test_validation_messages():
    with pytest.raises(LightplaneError, match="K"):
        Camera(K=np.eye(2), dist=np.zeros(5), width=10, height=10)
    with pytest.raises(LightplaneError, match="focal"):
        Camera(K=[[-1, 0, 0], [0, 1, 0], [0, 0, 1]], dist=np.zeros(5), width=10, height=10)
    with pytest.raises(LightplaneError, match="dist"):
        Camera(K=np.eye(3), dist=[0.1, 0.2, 0.3], width=10, height=10)
    with pytest.raises(LightplaneError, match="width"):
        Camera(K=np.eye(3), dist=np.zeros(5), width=0, height=10)


@pytest.fixture
def camera() -> Camera:
    return Camera(K=[[1430.39147, 0, 636.40393], [0, 1429.66307, 478.032706], [0, 0, 1]],
                  dist=[0.0271918728, -0.230991447, -7.13362835e-05, 8.68588435e-04, 0.508921101],
                  width=1280, height=960)


def test_files_round_trip_identical(tmp_path, camera):
    camera.save_json(tmp_path / "c.json")
    camera.save_ros_yaml(tmp_path / "c_ros.yaml")
    # written by OpenCV itself, not by us
    for name in ("c_cv.yaml", "c_cv.xml"):
        fs = cv2.FileStorage(str(tmp_path / name), cv2.FILE_STORAGE_WRITE)
        fs.write("image_width", camera.width)
        fs.write("image_height", camera.height)
        fs.write("camera_matrix", camera.K)
        fs.write("distortion_coefficients", camera.dist.reshape(1, 5))
        fs.release()
    camera.save_opencv(tmp_path / "c_ours.xml")
    for name in ("c.json", "c_ros.yaml", "c_cv.yaml", "c_cv.xml", "c_ours.xml"):
        back = Camera.load(tmp_path / name)
        assert back == camera, name
        assert np.array_equal(back.K, camera.K) and np.array_equal(back.dist, camera.dist)


def test_ros_yaml_written_by_hand(tmp_path):
    text = """image_width: 640
image_height: 480
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [430.2, 0, 311.7, 0, 431.1, 238.5, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.32, 0.11, 0.001, -0.0003, 0]
rectification_matrix: {rows: 3, cols: 3, data: [1, 0, 0, 0, 1, 0, 0, 0, 1]}
projection_matrix: {rows: 3, cols: 4, data: [430.2, 0, 311.7, 0, 0, 431.1, 238.5, 0, 0, 0, 1, 0]}
"""
    (tmp_path / "cam.yaml").write_text(text)
    cam = Camera.load(tmp_path / "cam.yaml")
    assert (cam.width, cam.height) == (640, 480)
    assert cam.fx == 430.2 and cam.cy == 238.5
    assert np.allclose(cam.dist, [-0.32, 0.11, 0.001, -0.0003, 0])


@pytest.mark.parametrize(
    "content,needle",
    [
        ('{"width": 10, "height": 10, "K": [[1,0,0],[0,1,0],[0,0,1]]}', "'dist'"),
        ('{"width": 10, "height": 10, "K": [[1,0],[0,1]], "dist": [0,0,0,0,0]}', "'K'"),
        ('{"width": 10, "K": [[1,0,0],[0,1,0],[0,0,1]], "dist": [0,0,0,0,0]}', "'height'"),
        ('{"width": 10, "height": 10, "K": [[1,0,0],[0,1,0],[0,0,1]], "dist": "x"}', "'dist'"),
        ("{not json", "not valid JSON"),
        ("image_width: 10\nimage_height: 10\n", "'camera_matrix'"),
        ("camera_matrix: {rows: 3, cols: 3, data: [1, 0, 0, 0, 1, 0, 0, 0, 1]}\n"
         "distortion_coefficients: {data: [0, 0, 0, 0, 0]}\nimage_height: 5\n", "'image_width'"),
        ("%YAML:1.0\n---\nimage_width: 10\nimage_height: 10\n", "'camera_matrix'"),
        ("<?xml version=\"1.0\"?>\n<opencv_storage><image_width>10</image_width></opencv_storage>\n", "'camera_matrix'"),
        ("key: [unclosed\n", "not valid YAML"),
    ],
)
def test_bad_camera_files_name_file_and_field(tmp_path, content, needle):
    f = tmp_path / "bad_camera.txt"
    f.write_text(content)
    with pytest.raises(LightplaneError) as e:
        Camera.load(f)
    assert str(f) in str(e.value) and needle in str(e.value)


def test_missing_camera_file(tmp_path):
    with pytest.raises(LightplaneError, match="no such camera file"):
        Camera.load(tmp_path / "nope.json")


def test_json_is_our_documented_layout(tmp_path, camera):
    camera.save_json(tmp_path / "c.json")
    d = json.loads((tmp_path / "c.json").read_text())
    assert set(d) >= {"width", "height", "K", "dist"}
    assert np.array_equal(np.array(d["K"]), camera.K)
