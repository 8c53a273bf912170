"""Calibration targets: descriptions, board frames, detection on exact synthetic images, centre correction."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.camera.targets import Target, as_target, correct_circle_centres, dot_diameter_mm, parse_target

K = np.array([[1400.0, 0, 640.0], [0, 1400.0, 480.0], [0, 0, 1]])


def test_parse_board_forms():
    assert parse_target("9x6", 8) == Target("chessboard", 9, 6, 8.0)
    assert parse_target("chessboard:9x6", 8) == Target("chessboard", 9, 6, 8.0)
    t = parse_target("charuco:11x8", 15, marker_mm=11, dictionary="5x5_100")
    assert (t.kind, t.cols, t.rows, t.dictionary, t.n_points) == ("charuco", 11, 8, "DICT_5X5_100", 70)
    c = parse_target("circles:7x7", 37.5)
    assert c.kind == "circles" and c.n_points == 49 and c.spacing_mm == 37.5
    a = parse_target("ACIRCLES:4x11", 10)
    assert a.kind == "acircles" and np.isclose(a.spacing_mm, 10 * np.sqrt(2))


@pytest.mark.parametrize("text, square, kw, msg", [
    ("hexagons:4x4", 5, {}, "kind must be one of"),
    ("9by6", 5, {}, "KIND:COLSxROWS"),
    ("9x6", None, {}, "--square"),
    ("9x6", -1, {}, "positive"),
    ("charuco:5x4", 10, {}, "marker size"),
    ("charuco:5x4", 10, {"marker_mm": 12}, "marker size"),
    ("charuco:5x4", 10, {"marker_mm": 7, "dictionary": "DICT_9X9_1"}, "unknown ArUco dictionary"),
    ("9x6", 10, {"marker_mm": 7}, "charuco"),
    ("9x6", 10, {"dot_mm": 3}, "circle grids"),
    ("circles:4x4", 10, {"dot_mm": 12}, "dot diameter"),
    ("circles:1x4", 10, {}, "at least 2x2"),
])
def test_parse_board_errors(text, square, kw, msg):
    with pytest.raises(LightplaneError, match=msg):
        parse_target(text, square, **kw)


def test_target_file(tmp_path):
    f = tmp_path / "board.json"
    f.write_text(json.dumps({"kind": "charuco", "cols": 5, "rows": 7, "square_mm": 30, "marker_mm": 22,
                             "dictionary": "DICT_6X6_250"}))
    t = parse_target(None, None, target_file=f)
    assert t == Target("charuco", 5, 7, 30.0, 22.0, "DICT_6X6_250")
    assert Target.from_dict(t.to_dict()) == t
    # a result file carrying "target" names it too
    (tmp_path / "cam.json").write_text(json.dumps({"K": [], "target": t.to_dict()}))
    assert Target.load(tmp_path / "cam.json") == t
    f.write_text(json.dumps({"kind": "circles", "cols": 4, "rows": 5, "square_mm": 20, "colour": "red"}))
    with pytest.raises(LightplaneError, match="unknown target field"):
        Target.load(f)
    f.write_text("{not json")
    with pytest.raises(LightplaneError, match="not a target file"):
        Target.load(f)
    with pytest.raises(LightplaneError, match="no such file"):
        Target.load(tmp_path / "missing.json")
    with pytest.raises(LightplaneError, match="not both"):
        parse_target("9x6", 5, target_file=f)


def test_board_frames_follow_opencv():
    # ChArUco: OpenCV's own chessboard corners, ids in order
    t = Target("charuco", 6, 4, 12.0, 9.0, "DICT_4X4_50")
    np.testing.assert_allclose(t.object_points(), t.cv_board().getChessboardCorners(), atol=1e-9)
    # asymmetric grid: OpenCV sample's ((2 i + j % 2) s, j s)
    a = Target("acircles", 4, 11, 10.0)
    p = a.object_points()
    j, i = np.divmod(np.arange(44), 4)
    np.testing.assert_allclose(p[:, :2], np.column_stack([(2 * i + j % 2) * 10.0, j * 10.0]))
    # chessboard: (i s, j s), i fastest
    c = Target("chessboard", 9, 6, 8.0)
    assert np.allclose(c.object_points()[10], [8.0, 8.0, 0.0])
    assert as_target((9, 6), 8.0) == c and as_target(c) is c
    with pytest.raises(LightplaneError, match="differs"):
        as_target(c, 9.0)


@pytest.mark.parametrize("target", [Target("chessboard", 5, 4, 10.0), Target("circles", 5, 4, 10.0),
                                    Target("acircles", 4, 5, 10.0), Target("charuco", 5, 4, 10.0, 7.0)])
def test_lattice_rows_and_columns_are_straight(target):
    """Points of one lattice row (or column) lie on one board line, equally spaced by a multiple of the square."""
    lat = target.lattice_index()
    p = target.object_points()[:, :2]
    np.testing.assert_allclose(p, target.lattice_origin_mm + lat * target.square_mm)
    nx, ny = target.lattice_shape
    assert lat[:, 0].max() < nx and lat[:, 1].max() < ny


def _pose(tilt_deg: float, dist: float, centre):
    R = cv2.Rodrigues(np.array([np.radians(tilt_deg), np.radians(0.6 * tilt_deg), 0.2]))[0]
    t = np.array([0.0, 0.0, dist]) - R @ np.array([*centre, 0.0])
    return R, t


def test_circle_centre_correction_against_exact_conic():
    """The image of a circle is a conic; its centre (the dot's area centroid) is corrected to the
    projected circle centre.  Exact check with a distortion-free camera (analytic conic centre)."""
    cam = Camera(K, np.zeros(5), 1280, 960)
    t = Target("circles", 6, 5, 20.0)
    R, tv = _pose(50.0, 400.0, (50.0, 40.0))
    r = 6.0  # dot radius, mm
    H = K @ np.column_stack([R[:, 0], R[:, 1], tv])
    Hi = np.linalg.inv(H)
    centres = []
    for x, y, _ in t.object_points():
        C = np.array([[1, 0, -x], [0, 1, -y], [-x, -y, x * x + y * y - r * r]])
        Ci = Hi.T @ C @ Hi
        centres.append(-np.linalg.solve(Ci[:2, :2], Ci[:2, 2]))
    centres = np.array(centres)
    proj = cam.project(t.object_points() @ R.T + tv)
    bias = np.linalg.norm(centres - proj, axis=1)
    assert bias.max() > 0.05  # the bias exists and is of the size the docs state
    fixed = correct_circle_centres(cam, t, centres, np.arange(t.n_points), R, tv, 2 * r)
    assert np.abs(fixed - proj).max() < 2e-3  # 96-gon centroid vs exact ellipse: ~1e-4 relative


def _draw_board(target, scale=8.0, ss=4):
    """Exact fronto-parallel image of a circle grid (anti-aliased by supersampling); returns (image, true uv)."""
    obj = target.object_points()
    pad = 2 * target.spacing_mm
    W, H = int((obj[:, 0].max() + 2 * pad) * scale), int((obj[:, 1].max() + 2 * pad) * scale)
    big = np.full((H * ss, W * ss), 225, np.uint8)
    dot = 0.45 * target.spacing_mm
    for x, y, _ in obj:
        c = (int(round((x + pad) * scale * ss * 16)), int(round((y + pad) * scale * ss * 16)))
        cv2.circle(big, c, int(round(dot / 2 * scale * ss * 16)), 35, -1, cv2.LINE_AA, 4)
    img = cv2.resize(big, (W, H), interpolation=cv2.INTER_AREA)
    uv = ((obj[:, :2] + pad) * scale * ss + 0.5) / ss - 0.5
    return img, uv


@pytest.mark.parametrize("target", [Target("circles", 7, 6, 20.0), Target("acircles", 4, 11, 10.0)])
def test_circle_grid_detection_dark_and_light(target):
    img, uv = _draw_board(target)
    noisy = np.clip(img + np.random.default_rng(0).normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)
    for im in (noisy, 255 - noisy):  # dark dots on light, light dots on dark
        d = target.detect(cv2.GaussianBlur(im, (0, 0), 1.2))
        assert d is not None and len(d) == target.n_points
        err = d.uv - uv
        if np.abs(err).max() > 1.0:  # a symmetric grid may be labelled from the other end
            err = d.uv[::-1] - uv
        # ~20 px dots, 2 grey levels of noise on a contrast of 190: centroid noise << 0.02 px
        assert np.sqrt(np.mean(err ** 2)) < 0.02
        # the dots' diameter is measured the right way round for either polarity (drawn: 0.45 spacing)
        assert d.dark_dots == (im is noisy)
        assert abs(dot_diameter_mm(im, d, target) - 0.45 * target.spacing_mm) < 0.03 * target.spacing_mm


def test_charuco_partial_views():
    t = Target("charuco", 7, 5, 20.0, 15.0, "DICT_4X4_50")
    img = t.cv_board().generateImage((980, 700), marginSize=70)  # 7 x 5 squares of 120 px
    img = cv2.resize(img, (490, 350), interpolation=cv2.INTER_AREA)  # 60 px squares
    d = t.detect(img)
    assert d is not None and len(d) == t.n_points
    # a fronto-parallel image: the corners are an exact similarity of the board (square pitch equal in x, y)
    X = np.column_stack([d.object_mm[:, :2], np.ones(len(d))])
    sol, *_ = np.linalg.lstsq(X, d.uv, rcond=None)
    A = sol.T
    res = X @ sol - d.uv
    assert np.abs(res).max() < 0.05
    assert np.isclose(abs(A[0, 0]), abs(A[1, 1]), rtol=1e-3)
    hidden = img.copy()
    hidden[:, :250] = 255  # a hand over the left half
    p = t.detect(hidden)
    assert p is not None and 6 <= len(p) < t.n_points
    np.testing.assert_allclose(p.object_mm, t.object_points(p.ids))
    assert t.detect(np.full_like(img, 128)) is None


def test_a_board_beyond_an_image_is_refused():
    """More corners along a side than any image holds is bad input (one line), not an OpenCV overflow."""
    with pytest.raises(LightplaneError, match="at most 1000 along a side"):
        Target("chessboard", 99999999999, 6, 10.0)
