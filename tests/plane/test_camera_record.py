"""A plane records the camera it was calibrated with; one comparison tells another camera from the same one."""

from __future__ import annotations

import numpy as np
import pytest
from _board_scenes import BOARD, CAM, PLANE1, R1, SQ, T1, scene

from lightplane import Camera, LightPlane
from lightplane.camera.board_pose import pose_from_corners
from lightplane.camera.model import SAME_CAMERA_RTOL, camera_difference, camera_record
from lightplane.core.errors import LightplaneError
from lightplane.motion.model import Turntable
from lightplane.plane.model import check_camera, recorded_camera
from lightplane.plane.zhou import plane_from_board_stripes


def changed(cam: Camera, *, K=None, dist=None, size=None, model=None) -> Camera:
    return Camera(cam.K if K is None else K, cam.dist if dist is None else dist,
                  *(cam.size if size is None else size), model=model or cam.model)


def test_difference_within_and_beyond_the_tolerance():
    rec = camera_record(CAM)
    f = max(CAM.fx, CAM.fy)
    assert camera_difference(rec, CAM) is None and camera_difference(CAM.to_dict(), CAM) is None
    for (i, j), name in (((0, 0), "fx"), ((1, 1), "fy"), ((0, 2), "cx"), ((1, 2), "cy"), ((0, 1), "skew")):
        for step, same in ((0.5, True), (2.0, False)):
            K = CAM.K.copy()
            K[i, j] += step * SAME_CAMERA_RTOL * f
            diff = camera_difference(rec, changed(CAM, K=K))
            assert (diff is None) == same, (name, step, diff)
            assert same or diff.startswith(f"{name} ")
    dist = CAM.dist.copy()
    dist[0] += 3 * SAME_CAMERA_RTOL * max(1.0, abs(dist[0]))
    assert camera_difference(rec, changed(CAM, dist=dist)).startswith("distortion k1 ")
    assert camera_difference(rec, changed(CAM, size=(CAM.width, CAM.height + 1))).startswith("image size ")
    rational = changed(CAM, dist=np.append(CAM.dist, [0.0, 0.0, 0.0]), model="rational")
    assert camera_difference(rec, rational).startswith("lens model plumb_bob vs rational")
    assert camera_difference({"K": "x"}, CAM) == "its recorded camera is malformed"


@pytest.mark.parametrize("suffix", [".json", ".yaml", ".xml"])
def test_camera_files_written_again_are_the_same_camera(tmp_path, suffix):
    CAM.save(tmp_path / f"c{suffix}")
    assert camera_difference(camera_record(CAM), Camera.load(tmp_path / f"c{suffix}")) is None


def test_check_camera_refuses_allows_and_notes():
    other = changed(CAM, K=CAM.K * np.array([[1.001, 1, 1], [1, 1, 1], [1, 1, 1]]))
    plane = LightPlane(PLANE1.normal, PLANE1.d, meta={"camera": camera_record(CAM)})
    assert check_camera(plane, CAM) is None
    with pytest.raises(LightplaneError, match=r"^p\.json: calibrated with another camera than b\.json \(fx "):
        check_camera(plane, other, plane_file="p.json", camera_file="b.json")
    note = check_camera(plane, other, plane_file="p.json", camera_file="b.json", allow_other=True)
    assert "another camera" in note and "--allow-other-camera" in note
    older = LightPlane(PLANE1.normal, PLANE1.d)
    assert "records no camera" in check_camera(older, other, plane_file="p.json", camera_file="b.json")
    # calibrate-plane's files before the field: the camera of report_inputs
    legacy = LightPlane(PLANE1.normal, PLANE1.d, meta={"report_inputs": {"camera": CAM.to_dict()}})
    assert recorded_camera(legacy) == CAM.to_dict() and check_camera(legacy, CAM) is None
    with pytest.raises(LightplaneError, match="another camera"):
        check_camera(legacy, other)
    # a turntable through the same comparison
    tt = Turntable.from_axis([0, 40, 450], [0, -1, 0], camera=CAM.to_dict())
    assert tt.check_camera(CAM) is None
    with pytest.raises(LightplaneError, match="recalibrate the turntable"):
        tt.check_camera(other, "tt.json")


def test_zhou_plane_records_its_camera():
    poses, stripes = [], []
    for k, (R, t) in enumerate([(R1, T1), (np.eye(3), np.array([-40.0, -20.0, 480.0]))]):
        corners, stripe, _ = scene(R, t, PLANE1, n_stripe=100)
        poses.append(pose_from_corners(CAM, corners, BOARD, SQ, name=f"v{k}"))
        stripes.append(stripe)
    plane = plane_from_board_stripes(CAM, poses, stripes).plane
    assert plane.meta["camera"] == camera_record(CAM)
    assert check_camera(LightPlane.from_dict(plane.to_dict()), CAM) is None
