"""Chessboard renders against their exact truth: board edges on the projected board
lines (independent moment probe), OpenCV's corners on the projected corners, and
Zhang's calibration recovering the focal length."""

from __future__ import annotations

from dataclasses import replace
import cv2
import numpy as np
import pytest

from lightplane.simulate.scene import default_camera
from lightplane.simulate.render import CALIBRATION_CAPTURE, BoardCapture, BoardOptions, render_chessboard_dataset

BOARD = (9, 6)


def _moment_edge(row, ue, half=5, flank=4):
    """Edge position along one image row by the area (first-moment) method, or None.

    Exact for a straight step edge blurred by a symmetric PSF and pixel-integrated:
    ``x_e = u0 - 1/2 + sum (I - R) / (L - R)`` over the window ``u0..u1``.
    """
    u0, u1 = int(round(ue)) - half, int(round(ue)) + half
    if u0 - flank < 0 or u1 + flank >= row.size:
        return None
    left, right = row[u0 - flank:u0], row[u1 + 1:u1 + 1 + flank]
    if np.ptp(left) > 0 or np.ptp(right) > 0 or left[0] == right[0]:
        return None
    L, R = left[0], right[0]
    return u0 - 0.5 + np.sum((row[u0:u1 + 1] - R) / (L - R))


def _board_edge_residuals(img, camera, R, t, square_mm):
    """Distances (px) of moment-probed edge points to the projected inner board lines (pinhole camera)."""
    cols, rows = BOARD
    I = img.astype(np.float64)
    res = []
    lines = [((-square_mm, j * square_mm), (cols * square_mm, j * square_mm)) for j in range(rows)]
    lines += [((i * square_mm, -square_mm), (i * square_mm, rows * square_mm)) for i in range(cols)]
    for a, b in lines:
        ends = camera.project(np.array([[*a, 0.0], [*b, 0.0]]) @ R.T + t, distort=False)
        d = ends[1] - ends[0]
        n = np.array([-d[1], d[0]]) / np.linalg.norm(d)
        for s in np.linspace(0.0, 1.0, 200):
            # stay away from the corners: only the middle half of every square's side
            q = np.asarray(a) + s * (np.asarray(b) - np.asarray(a))
            along = q[0] if a[1] == b[1] else q[1]
            frac = (along / square_mm) % 1.0
            if not 0.25 < frac < 0.75:
                continue
            p = ends[0] + s * d
            if abs(n[0]) >= abs(n[1]):  # probe along the row through p
                v = int(round(p[1]))
                us = ends[0, 0] + (v - ends[0, 1]) * d[0] / d[1] if abs(d[1]) > 1e-12 else p[0]
                xe = _moment_edge(I[v], us)
                if xe is not None:
                    res.append((xe - us) * abs(n[0]))
            else:
                u = int(round(p[0]))
                vs = ends[0, 1] + (u - ends[0, 0]) * d[1] / d[0]
                ye = _moment_edge(I[:, u], vs)
                if ye is not None:
                    res.append((ye - vs) * abs(n[1]))
    return np.array(res)


def test_board_edges_on_projected_lines():
    cam = default_camera().pinhole()
    ds = render_chessboard_dataset(2, 3, BoardOptions(difficulty="clean", noise=False,
                                                    capture=replace(CALIBRATION_CAPTURE, board=BOARD, square_mm=8.0)),
                                   camera=cam)
    sq = ds.truth["board"]["square_mm"]
    res = np.concatenate([_board_edge_residuals(img, cam, np.asarray(v["T_cam_board"]["R"]),
                                                np.asarray(v["T_cam_board"]["t"]), sq)
                          for img, v in zip(ds.images, ds.truth["views"])])
    print("board edge points", res.size, "rms", np.sqrt(np.mean(res**2)), "max", np.abs(res).max())
    assert res.size > 300
    # 16x16 jittered samples on edges: coverage noise ~0.004 px per pixel; 8-bit levels
    assert np.sqrt(np.mean(res**2)) <= 0.01
    assert abs(res.mean()) <= 0.003


@pytest.fixture(scope="module")
def fifteen_boards():
    # the original small-board capture (the renderer's check)
    return render_chessboard_dataset(15, 0, BoardOptions(difficulty="clean", capture=BoardCapture(
        board=BOARD, square_mm=8.0, tilt_deg=(10.0, 45.0), distance_mm=(330.0, 560.0), centre_frac=0.4)))


def _opencv_corners(img):
    ok, c = cv2.findChessboardCorners(img, BOARD)
    assert ok
    c = cv2.cornerSubPix(img, c, (7, 7), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-6))
    return c.reshape(-1, 2)


def test_opencv_corners_on_truth_and_calibration(fifteen_boards):
    ds = fifteen_boards
    cam = ds.camera
    sq = ds.truth["board"]["square_mm"]
    obj = np.array([[i * sq, j * sq, 0.0] for j in range(BOARD[1]) for i in range(BOARD[0])])
    errs, obj_pts, img_pts = [], [], []
    for img, v in zip(ds.images, ds.truth["views"]):
        c = _opencv_corners(img)
        tr = np.asarray(v["corners_px"])
        if np.linalg.norm(c[0] - tr[0]) > np.linalg.norm(c[-1] - tr[0]):
            c = c[::-1]  # the detector may start from the opposite corner
        errs.append(np.linalg.norm(c - tr, axis=1))
        obj_pts.append(obj.astype(np.float32))
        img_pts.append(c.astype(np.float32))
    e = np.concatenate(errs)
    per_view = [np.sqrt(np.mean(x**2)) for x in errs]
    print("corner rms", np.sqrt(np.mean(e**2)), "worst view rms", max(per_view), "max", e.max())
    assert np.sqrt(np.mean(e**2)) <= 0.05
    rms, K, dist, _, _ = cv2.calibrateCamera(obj_pts, img_pts, (cam.width, cam.height), None, None,
                                             flags=cv2.CALIB_FIX_K3)
    print("calibration rms", rms, "fx", K[0, 0], "truth", cam.fx, "rel", K[0, 0] / cam.fx - 1)
    assert abs(K[0, 0] / cam.fx - 1) <= 0.002
    assert abs(K[1, 1] / cam.fy - 1) <= 0.002
