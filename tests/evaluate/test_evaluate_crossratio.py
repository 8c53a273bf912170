"""Cross-ratio ideal points and the evaluation pipeline on exact point-level synthetic scenes.

The scene: a distorted camera, a 9x6 chessboard (10 mm squares) at ~450 mm, and
a light plane crossing it.  The true ideal points are the intersections of the
plane/board line with the corner lines, solved in the board frame; the stripe is
that 3D line sampled densely and projected.
"""

from __future__ import annotations

import numpy as np
import pytest

from lightplane import LightPlane
from lightplane.camera.board_pose import pose_from_corners
from lightplane.core.errors import LightplaneError
from lightplane.evaluate.crossratio import (CrossRatioOptions, cross_ratio, cross_ratio_points, evaluate_views,
                                           first_point_pairs, point_from_cross_ratio)

from _board_scenes import BOARD, CAM, PLANE1, R1, SQ, T1, rot, scene, vertical_plane


def test_cross_ratio_formula_roundtrip():
    rng = np.random.default_rng(3)
    a, b, c, d = np.sort(rng.uniform(-5, 5, (4, 50)), axis=0)
    np.testing.assert_allclose(point_from_cross_ratio(cross_ratio(a, b, c, d), a, b, c), d, atol=1e-9)
    # invariant under a 1D projective map
    f = lambda x: (2.0 * x + 1.0) / (0.05 * x + 1.3)  # noqa: E731
    np.testing.assert_allclose(cross_ratio(f(a), f(b), f(c), f(d)), cross_ratio(a, b, c, d), rtol=1e-9)


@pytest.mark.parametrize("corners_used", ["three", "all"])
def test_ideal_points_exact_rows(corners_used):
    corners, stripe, ideal = scene(R1, T1, PLANE1)
    cr = cross_ratio_points(CAM.undistort_points(corners), BOARD, CAM.undistort_points(stripe), square_mm=SQ,
                            options=CrossRatioOptions(corners_used=corners_used))
    assert cr.family == "rows"
    np.testing.assert_array_equal(cr.line_index, np.arange(6))
    np.testing.assert_allclose(cr.p_board_mm, ideal, atol=1e-8)
    assert np.all(cr.crossing_angle_deg > 45)


def test_ideal_points_exact_with_corners_left_out():
    """Corners the stripe runs over (or any others) can be left out; three per line suffice."""
    from lightplane.plane.zhou import corners_clear_of_stripe

    corners, stripe, ideal = scene(R1, T1, PLANE1)
    pose = pose_from_corners(CAM, corners, BOARD, SQ)
    clear = corners_clear_of_stripe(CAM, pose, stripe, clearance_px=10.0)  # ~0.35 square
    assert 0 < np.count_nonzero(~clear) < 20
    # the left-out corners are those within 10 px of the true stripe line (undistorted)
    a, b = CAM.undistort_points(stripe[[0, -1]])
    n = np.array([a[1] - b[1], b[0] - a[0]]) / np.linalg.norm(b - a)
    np.testing.assert_array_equal(clear, np.abs((CAM.undistort_points(corners) - a) @ n) > 10.0)
    ok = clear.copy()
    ok[[0, 1, 2, 3, 4, 5]] = False  # row 0 keeps only three corners
    for mode in ("three", "all"):
        cr = cross_ratio_points(CAM.undistort_points(corners), BOARD, CAM.undistort_points(stripe), square_mm=SQ,
                                options=CrossRatioOptions(corners_used=mode), corner_ok=ok)
        np.testing.assert_array_equal(cr.line_index, np.arange(6))
        np.testing.assert_allclose(cr.p_board_mm, ideal, atol=1e-8)
    ok[6] = False  # row 0: two corners left -> that row is skipped
    cr = cross_ratio_points(CAM.undistort_points(corners), BOARD, CAM.undistort_points(stripe), square_mm=SQ,
                            corner_ok=ok)
    np.testing.assert_array_equal(cr.line_index, np.arange(1, 6))
    pose2 = pose_from_corners(CAM, corners, BOARD, SQ, corner_ok=clear)
    np.testing.assert_allclose(pose2.t_cam_board, T1, atol=1e-6)
    assert pose2.to_dict()["corners_left_out"] == np.count_nonzero(~clear)


def test_ideal_points_exact_columns():
    R, t = rot(-10, 15, 2), np.array([-40.0, -25.0, 420.0])
    plane = vertical_plane(R @ np.array([40.0, 23.0, 0]) + t, tilt=(0.05, 0.95, -0.3))
    corners, stripe, ideal = scene(R, t, plane, family="columns")
    cr = cross_ratio_points(CAM.undistort_points(corners), BOARD, CAM.undistort_points(stripe), square_mm=SQ)
    assert cr.family == "columns"
    np.testing.assert_allclose(cr.p_board_mm, ideal, atol=1e-8)
    # forcing the other family finds no crossing (the stripe is along the rows)
    rows = cross_ratio_points(CAM.undistort_points(corners), BOARD, CAM.undistort_points(stripe), square_mm=SQ,
                              options=CrossRatioOptions(lines="rows"))
    assert len(rows) < len(cr)


def test_ideal_points_noise():
    """Corner noise 0.05 px, stripe noise 0.1 px: at ~2.7 px/mm the ideal points stay within ~0.02 mm."""
    rng = np.random.default_rng(7)
    corners, stripe, ideal = scene(R1, T1, PLANE1, n_stripe=2000)
    err = {"three": [], "all": []}
    for _ in range(30):
        c = CAM.undistort_points(corners + rng.normal(0, 0.05, corners.shape))
        s = CAM.undistort_points(stripe + rng.normal(0, 0.1, stripe.shape))
        for mode in err:
            cr = cross_ratio_points(c, BOARD, s, square_mm=SQ, options=CrossRatioOptions(corners_used=mode))
            err[mode].append(cr.p_board_mm[:, 0] - ideal[:, 0])
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in err.items()}
    # one corner's 0.05 px is ~0.019 mm; the all-corner fit averages 9 of them
    assert rms["all"] < 0.02
    assert rms["three"] < 0.04
    assert rms["all"] < rms["three"]


def test_evaluate_views_true_plane_and_tilted_plane():
    """Through the pipeline (distorted inputs, solvePnP poses): the true plane gives zero
    error; a plane rotated by 0.2 deg gives the distance errors of exact ray/plane
    intersections computed here independently."""
    R2, T2 = rot(-8, 20, -3), np.array([-45.0, -20.0, 480.0])
    views, stripes, ideals = [], [], []
    for k, (R, t) in enumerate([(R1, T1), (R2, T2)]):
        corners, stripe, ideal = scene(R, t, PLANE1)
        views.append(pose_from_corners(CAM, corners, BOARD, SQ, name=f"v{k}"))
        stripes.append(stripe)
        ideals.append(ideal @ R.T + t)
    tilted = LightPlane(rot(0.2, 0, 0) @ PLANE1.normal, PLANE1.d)
    ev = evaluate_views(CAM, [PLANE1, tilted], views, stripes, board=BOARD, square_mm=SQ, labels=["true", "tilted"])
    truth_cam = np.vstack(ideals)
    np.testing.assert_allclose(ev.ideal_cam_mm, truth_cam, atol=1e-6)
    np.testing.assert_array_equal(ev.view_index, np.repeat([0, 1], 6))
    np.testing.assert_array_equal(ev.pairs, first_point_pairs(np.repeat([0, 1], 6)))
    assert ev.errors[0].rms_mm < 1e-6
    assert np.max(ev.point_error_mm[0]) < 1e-6
    # expected measured points for the tilted plane: rays through the true points
    rays = truth_cam / truth_cam[:, 2:]
    s = -tilted.d / (rays @ tilted.normal)
    meas = rays * s[:, None]
    i, j = ev.pairs.T
    dm = np.linalg.norm(meas[i] - meas[j], axis=1)
    dt = np.linalg.norm(truth_cam[i] - truth_cam[j], axis=1)
    np.testing.assert_allclose(ev.errors[1].dm_mm, dm, atol=1e-6)
    np.testing.assert_allclose(ev.errors[1].delta_mm, dt - dm, atol=1e-6)
    assert ev.errors[1].rms_mm > 0.01
    d = ev.to_dict()
    assert set(d["planes"]) == {"true", "tilted"} and len(d["planes"]["tilted"]["pairs"]) == 10


def test_no_crossing_raises():
    corners, stripe, _ = scene(R1, T1, PLANE1)
    pose = pose_from_corners(CAM, corners, BOARD, SQ)
    with pytest.raises(LightplaneError, match="crosses no corner"):
        evaluate_views(CAM, [PLANE1], [pose], [np.zeros((0, 2))], board=BOARD, square_mm=SQ)
    # stripe far off the board
    with pytest.raises(LightplaneError, match="crosses no corner"):
        evaluate_views(CAM, [PLANE1], [pose], [stripe + [2000.0, 0]], board=BOARD, square_mm=SQ)


def test_bad_arguments():
    corners, stripe, _ = scene(R1, T1, PLANE1)
    with pytest.raises(LightplaneError, match="corners_uv_undist has"):
        cross_ratio_points(corners[:-1], BOARD, stripe, square_mm=SQ)
    with pytest.raises(LightplaneError, match="lines"):
        cross_ratio_points(corners, BOARD, stripe, square_mm=SQ, options=CrossRatioOptions(lines="diagonal"))
    with pytest.raises(LightplaneError, match="square_mm"):
        cross_ratio_points(corners, BOARD, stripe, square_mm=-1)
