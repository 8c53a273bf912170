"""A chessboard crossed by a laser stripe, in closed form: the scenes shared by the cross-ratio and Zhou tests."""

from __future__ import annotations

import numpy as np

from lightplane import Camera, LightPlane

BOARD = (9, 6)
SQ = 10.0
CAM = Camera([[1200.0, 0, 640], [0, 1200.0, 480], [0, 0, 1]], [-0.25, 0.12, 0.0008, -0.0005, 0.0], 1280, 960)


def rot(rx, ry, rz):
    import cv2

    return cv2.Rodrigues(np.radians([rx, ry, rz]))[0]


def board_xy(board=BOARD, sq=SQ):
    cols, rows = board
    xs, ys = np.meshgrid(np.arange(cols), np.arange(rows))
    return np.column_stack([xs.ravel(), ys.ravel()]) * sq


def scene(R, t, plane, *, board=BOARD, sq=SQ, n_stripe=400, family="rows"):
    """Exact corners (distorted px), stripe (distorted px) and true ideal points (board frame)."""
    cols, rows = board
    obj = np.column_stack([board_xy(board, sq), np.zeros(cols * rows)])
    corners = CAM.project(obj @ R.T + t)
    # the plane/board line in board coordinates: m·(x, y) + e = 0
    m = R.T @ plane.normal
    e = plane.normal @ t + plane.d
    if family == "rows":
        y = np.linspace(-0.5 * sq, (rows - 0.5) * sq, n_stripe)
        x = -(m[1] * y + e) / m[0]
        yj = np.arange(rows) * sq
        ideal = np.column_stack([-(m[1] * yj + e) / m[0], yj, np.zeros(rows)])
    else:
        x = np.linspace(-0.5 * sq, (cols - 0.5) * sq, n_stripe)
        y = -(m[0] * x + e) / m[1]
        xi = np.arange(cols) * sq
        ideal = np.column_stack([xi, -(m[0] * xi + e) / m[1], np.zeros(cols)])
    line = np.column_stack([x, y, np.zeros_like(x)]) @ R.T + t
    assert np.allclose(plane.signed_distance(line), 0, atol=1e-9)
    return corners, CAM.project(line), ideal


def vertical_plane(through_cam, tilt=(0.95, 0.08, -0.30)):
    n = np.asarray(tilt) / np.linalg.norm(tilt)
    return LightPlane(n, -float(n @ through_cam))


R1, T1 = rot(12, -18, 4), np.array([-40.0, -25.0, 450.0])
PLANE1 = vertical_plane(R1 @ np.array([42.0, 25.0, 0]) + T1)
