"""Zhou's method takes the stripe on the board's white margin beside its printed pattern.

Rendered boards with a 30 mm white margin in front of a grey background 250 mm behind them:
the margin found in the lit (laser-off) frame stays on the board, poses whose stripe crosses
only the margin are used, and the plane stays within its own uncertainty of the truth.
"""

from __future__ import annotations

import numpy as np
import pytest

from lightplane.camera.board_pose import find_board_pose
from lightplane.camera.model import Camera
from lightplane.camera.targets import as_target
from lightplane.core.errors import LightplaneError
from lightplane.plane.zhou import BoardFrames, BoardPlaneOptions, board_area_mask, board_polygon_mask, calibrate_plane_board
from lightplane.simulate.render import BoardOptions, render_board_pose
from lightplane.simulate.scene import default_plane

CAM = Camera(np.array([[1600.0, 0, 321.5], [0, 1600.0, 241.0], [0, 0, 1]]), np.array([-0.05, 0.04, 0, 0, 0]), 640, 480)
PLANE = default_plane()  # contains the camera's y axis: the stripe is a column of the image
TARGET = as_target((6, 4), 8.0)  # printed squares: x -8..48 mm, y -8..32 mm
MARGIN_MM = 30.0  # the board: x -38..78 mm, y -38..62 mm
BOARD_RECT = (-8.0 - MARGIN_MM, 48.0 + MARGIN_MM, -8.0 - MARGIN_MM, 32.0 + MARGIN_MM)
# (tilt about x, about y (deg), depth of the stripe's point (mm), board x of the stripe (mm)):
# three poses with the stripe across the squares, three with it only on the margin (x < -8 or > 48)
OPTIONS = BoardOptions(difficulty="realistic", with_stripe=True, laser_off=True)
POSES = [(10, -15, 430, 20), (-12, 20, 470, 30), (6, 10, 500, 10),
         (8, 18, 450, 63), (-10, -20, 420, -23), (12, -8, 480, 60)]


def _rot(ax: float, ay: float) -> np.ndarray:
    a, b = np.radians(ax), np.radians(ay)
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    return rx @ ry


def _pose(ax, ay, z, xs):
    """The board pose putting board point (xs, 12) on the light plane at depth z on the camera's x-z plane."""
    R = _rot(ax, ay)
    q = np.array([(z - 450.0) * np.tan(np.radians(25.0)), 0.0, z])
    return R, q - R @ np.array([xs, 12.0, 0.0])


@pytest.fixture(scope="module")
def frames():
    on, off = [], []
    for k, p in enumerate(POSES):
        R, t = _pose(*p)
        shots = render_board_pose(TARGET, R, t, margin_mm=MARGIN_MM, seed=k, camera=CAM, plane=PLANE, options=OPTIONS)
        on.append(shots[""])
        off.append(shots["_off"])
    return on, off


def _board_coords(pose, X):
    return (X - pose.t_cam_board) @ pose.R_cam_board


def test_margin_mask_stays_on_the_board(frames):
    """The grown margin covers most of the board seen and nothing beyond its edges (2 px of blur allowed)."""
    import cv2

    _, off = frames
    for k, p in enumerate(POSES[:4]):
        R, t = _pose(*p)
        pose = find_board_pose(off[k], CAM, TARGET)
        mask = board_area_mask(CAM, pose, TARGET, image=off[k]) > 0
        x0, x1, y0, y1 = BOARD_RECT
        s = np.linspace(0, 1, 200)
        edge = np.vstack([np.column_stack([x0 + (x1 - x0) * s, np.full_like(s, y0)]),
                          np.column_stack([np.full_like(s, x1), y0 + (y1 - y0) * s]),
                          np.column_stack([x1 - (x1 - x0) * s, np.full_like(s, y1)]),
                          np.column_stack([np.full_like(s, x0), y1 - (y1 - y0) * s])])
        uv = CAM.project(np.column_stack([edge, np.zeros(len(edge))]) @ R.T + t)
        board = np.zeros((CAM.height, CAM.width), np.uint8)
        cv2.fillPoly(board, [np.round(uv).astype(np.int32).reshape(-1, 1, 2)], 1)
        grown = cv2.dilate(board, np.ones((5, 5), np.uint8)) > 0
        inner = cv2.erode(board, np.ones((25, 25), np.uint8)) > 0
        assert not np.any(mask & ~grown), f"pose {k}: {np.count_nonzero(mask & ~grown)} px off the board"
        assert np.mean(mask[inner]) > 0.9, f"pose {k}: the mask covers {np.mean(mask[inner]):.2f} of the board"
        assert np.count_nonzero(mask) > 2 * np.count_nonzero(board_polygon_mask(CAM, pose, TARGET))


def test_margin_only_poses_used_and_plane_within_its_sigma(frames):
    """All six poses are used (three with the stripe only on the margin); every point is on the board
    (not on the background beside it); the plane is within 5 sigma of the truth (angle and offset)."""
    on, off = frames
    z = calibrate_plane_board(BoardFrames(on, pattern_images=off), CAM, TARGET)
    assert not z.plane.meta["skipped"], z.plane.meta["skipped"]
    assert len(set(z.view_index.tolist())) == len(POSES)
    for k, pose in enumerate(z.poses):
        q = _board_coords(pose, z.points_cam_mm[z.view_index == k])
        assert np.all((q[:, 0] > BOARD_RECT[0]) & (q[:, 0] < BOARD_RECT[1]) & (q[:, 1] > BOARD_RECT[2])
                      & (q[:, 1] < BOARD_RECT[3])), f"pose {k}: stripe points off the board"
        if k >= 3:
            assert np.all((q[:, 0] < -8) | (q[:, 0] > 48)), f"pose {k}: the stripe should be on the margin only"
    p = z.plane
    cov = p.covariance
    sigma_angle = np.sqrt(np.trace(cov[:3, :3]))
    assert p.angle_to(PLANE) < 5 * sigma_angle, (np.degrees(p.angle_to(PLANE)), np.degrees(sigma_angle))
    c = np.append(z.points_cam_mm.mean(axis=0), 1.0)
    offset = float(p.coefficients @ c * np.sign(p.normal @ PLANE.normal) - PLANE.coefficients @ c)
    assert abs(offset) < 5 * np.sqrt(c @ cov @ c), (offset, np.sqrt(c @ cov @ c))
    assert p.meta["quality"]["verdict"] == "ok", p.meta["quality"]


def test_board_margin_option(frames):
    """--board-margin 0: the pattern only, the margin-only poses are skipped; 20 mm: the stripe 15 mm
    beyond the squares is kept; 10 mm: not."""
    on, off = frames
    z0 = calibrate_plane_board(BoardFrames(on, pattern_images=off), CAM, TARGET, options=BoardPlaneOptions(board_margin_mm=0))
    assert set(z0.plane.meta["skipped"]) == {"image 3", "image 4", "image 5"}
    assert all(v == "no stripe on the board" for v in z0.plane.meta["skipped"].values())
    z20 = calibrate_plane_board(BoardFrames(on, pattern_images=off), CAM, TARGET,
                                options=BoardPlaneOptions(board_margin_mm=20))
    assert not z20.plane.meta["skipped"]
    for k, pose in enumerate(z20.poses):
        q = _board_coords(pose, z20.points_cam_mm[z20.view_index == k])
        assert np.all((q[:, :2] > [-28.5, -28.5]) & (q[:, :2] < [68.5, 52.5]))
    z10 = calibrate_plane_board(BoardFrames(on, pattern_images=off), CAM, TARGET,
                                options=BoardPlaneOptions(board_margin_mm=10))
    assert set(z10.plane.meta["skipped"]) == {"image 3", "image 4", "image 5"}


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf")])
def test_board_margin_checked(bad):
    with pytest.raises(LightplaneError, match="board_margin_mm"):
        BoardPlaneOptions(board_margin_mm=bad)


def test_cli_board_margin(frames, tmp_path):
    """calibrate-plane-board --board-margin 10: the margin-only poses are skipped and the option is recorded;
    a negative margin: exit 2, one line."""
    import json

    import cv2
    from _cli import lightplane, one_error_line

    on, off = frames
    files, pats = [], []
    for k in range(len(on)):
        files.append(tmp_path / f"on_{k}.png")
        pats.append(tmp_path / f"off_{k}.png")
        cv2.imwrite(str(files[-1]), on[k])
        cv2.imwrite(str(pats[-1]), off[k])
    CAM.save_json(tmp_path / "cam.json")
    args = ["--camera", tmp_path / "cam.json", "--board", "6x4", "--square", "8"]
    pat = [a for p in pats for a in ("--pattern", p)]
    r = lightplane("calibrate-plane-board", *files, *pat, *args, "--board-margin", "10", "-o", tmp_path / "p.json")
    assert r.returncode == 0, r.stderr
    rec = json.loads((tmp_path / "p.json").read_text())
    assert rec["provenance"]["options"]["board_margin_mm"] == 10
    assert all(f"on_{k}.png" in r.stdout + r.stderr for k in (3, 4, 5))
    r = lightplane("calibrate-plane-board", *files, *pat, *args, "--board-margin", "-1", "-o", tmp_path / "q.json")
    one_error_line(r, "--board-margin")
