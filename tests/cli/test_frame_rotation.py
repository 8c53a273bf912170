"""One rule for frame rotations: a camera or sensor file that records the rotation its images were
read with is applied by every command; a transposed size gets a hint naming --rotate; errors about
many images are summarised."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.measure.sensor import recorded_rotation
from lightplane.plane.zhou import BoardFrames, calibrate_plane_board
from _cli import lightplane, one_error_line


def _small_camera() -> Camera:
    """A 96x64 px camera with a 60 deg field."""
    return Camera(np.array([[83.0, 0, 47.5], [0, 83.0, 31.5], [0, 0, 1]]), np.zeros(5), 96, 64)


def _camera_file(path, rotate_deg=None):
    cam = _small_camera()
    extra = None if rotate_deg is None else {"provenance": {"options": {"rotate_deg": rotate_deg}}}
    cam.save_json(path, extra=extra)
    return cam


def test_recorded_rotation_of_camera_and_sensor_files(tmp_path):
    assert recorded_rotation(None) is None
    _camera_file(tmp_path / "plain.json")
    assert recorded_rotation(tmp_path / "plain.json") is None
    _camera_file(tmp_path / "rot.json", 90)
    assert recorded_rotation(tmp_path / "rot.json") == 90
    cam = Camera.load(tmp_path / "rot.json")
    cam.save(tmp_path / "cam.yaml")
    assert recorded_rotation(tmp_path / "cam.yaml") is None  # ROS files record none
    _camera_file(tmp_path / "bad.json", 45)
    with pytest.raises(LightplaneError, match="rotate_deg' must be 0, 90, 180 or 270"):
        recorded_rotation(tmp_path / "bad.json")


def test_transposed_size_names_rotate():
    cam = _small_camera()
    with pytest.raises(LightplaneError, match=r"a.png: 64x96 px but the camera is calibrated for 96x64 px, its frame turned .*--rotate 90"):
        cam.check_image(np.zeros((96, 64)), "a.png")
    with pytest.raises(LightplaneError, match=r"wrong camera file\?\)$"):
        cam.check_image(np.zeros((60, 90)), "a.png")


def test_many_wrong_sizes_are_one_short_line():
    """17 frames of the transposed size: one group (count, first names), not 17 sentences."""
    cam = _small_camera()
    imgs = [np.zeros((96, 64), np.uint8)] * 17
    with pytest.raises(LightplaneError) as e:
        calibrate_plane_board(BoardFrames(imgs, pattern_images=imgs, names=[f"f{i:02d}.png" for i in range(17)]),
                              cam, (5, 4), 10.0)
    msg = str(e.value)
    assert "17 pattern frame: 64x96 px but the camera is calibrated for 96x64 px" in msg and "14 more" in msg, msg
    assert "--rotate 90" in msg, msg
    assert msg.count("calibrated for") == 1 and len(msg) < 400, msg


@pytest.mark.parametrize("recorded", [90, None])
def test_calibrate_plane_board_reads_frames_as_the_camera_was_calibrated(tmp_path, recorded):
    """Frames stored unrotated (64 wide, 96 high) and a camera of the rotated 96x64 frame: with the
    rotation recorded in the camera file it is applied (the board is then looked for, and not
    found in these blank frames); without it the size error names --rotate, once."""
    _camera_file(tmp_path / "cam.json", recorded)
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), np.full((96, 64), 128, np.uint8))
    r = lightplane("calibrate-plane-board", tmp_path / "f*.png", "--camera", tmp_path / "cam.json", "--board", "5x4",
                   "--square", "10", "-o", tmp_path / "plane.json")
    line = one_error_line(r)
    if recorded:
        assert "board not found" in line and "calibrated for" not in line, line
    else:
        assert line.count("calibrated for") == 1 and "--rotate 90" in line, line
    assert not (tmp_path / "plane.json").exists()
