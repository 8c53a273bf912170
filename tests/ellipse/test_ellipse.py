"""Ellipse model, fitting, detection, refinement and target selection on exact synthetic images."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.ellipse import (
    Ellipse,
    EllipseDetectionOptions,
    detect_ellipses,
    ellipse_iou,
    fit_conic_robust,
    fit_ellipse_direct,
    fit_ellipse_geometric,
    match_ellipses,
    refine_ellipse,
    render_ellipses,
    select_target,
)
from lightplane.core.geometry import Failure
from lightplane.ellipse.detect import arc_groups, arc_support_segments
from lightplane.ellipse.edges import gradients, to_uint8


# ----------------------------------------------------------------------------- model
def test_params_conic_roundtrip_and_normalisation():
    rng = np.random.default_rng(1)
    for _ in range(50):
        c = rng.uniform(-500, 1500, 2)
        a, b = sorted(rng.uniform(1, 400, 2), reverse=True)
        th = rng.uniform(-5, 5)
        e = Ellipse.from_params(c, a, b, th)
        assert 0 <= e.angle < math.pi and e.a >= e.b
        C = e.conic
        assert abs(np.linalg.norm(C) - 1) < 1e-12 and np.allclose(C, C.T)
        # points on the ellipse satisfy the conic; the centre is inside (negative)
        X = np.column_stack([e.points(16), np.ones(16)])
        assert np.max(np.abs(np.einsum("ij,jk,ik->i", X, C, X))) < 1e-9 * np.max(np.abs(C))
        assert np.array([*c, 1]) @ C @ np.array([*c, 1]) < 0
        e2 = Ellipse.from_conic(-7.5 * C)
        assert np.allclose(e2.centre, c, atol=1e-7 * max(1, a)) and abs(e2.a - a) < 1e-7 * a and abs(e2.b - b) < 1e-7 * a
        if a - b > 1e-3 * a:
            d = (e2.angle - th) % math.pi
            assert min(d, math.pi - d) < 1e-6


def test_swapped_axes_are_reordered():
    e = Ellipse.from_params((0, 0), 5, 10, 0.0)
    assert e.a == 10 and e.b == 5 and abs(e.angle - math.pi / 2) < 1e-12


def test_opencv_rotated_rect_roundtrip_matches_cv2_ellipse_drawing():
    import cv2

    e = Ellipse.from_params((60.0, 40.0), 30.0, 12.0, math.radians(35))
    rect = e.to_cv_rotated_rect()
    assert rect[1] == (60.0, 24.0) and abs(rect[2] - 35) < 1e-12
    img = np.zeros((80, 120), np.uint8)
    cv2.ellipse(img, ((60, 40), (60, 24), 35), 255, -1)
    m = e.mask(img.shape)
    assert np.mean(m == (img > 0)) > 0.99
    # (w, h) swapped with the angle turned by 90 degrees is the same ellipse
    e2 = Ellipse.from_cv_rotated_rect(((60.0, 40.0), (24.0, 60.0), 125.0))
    assert np.allclose(e2.conic, e.conic, atol=1e-12)


def test_contains_scaled_mask_and_bbox():
    e = Ellipse.from_params((50.0, 30.0), 20.0, 10.0, 0.3)
    assert e.contains(np.array([[50.0, 30.0]]))[0] and not e.contains(np.array([[80.0, 30.0]]))[0]
    s = e.scaled(0.5)
    assert s.a == 10 and s.b == 5 and np.allclose(s.centre, e.centre)
    m = e.mask((60, 100))
    assert abs(m.sum() - e.area) < 0.03 * e.area
    m2 = e.mask((60, 100), shrink_px=3)
    assert m2.sum() < m.sum() and not np.any(m2 & ~m)
    u0, v0, u1, v1 = e.bbox()
    pts = e.points(1000)
    assert abs(pts[:, 0].min() - u0) < 1e-3 and abs(pts[:, 1].max() - v1) < 1e-3
    with pytest.raises(LightplaneError):
        e.scaled(0)


@pytest.mark.parametrize("bad", [dict(a=-1, b=1), dict(a=1, b=0), dict(a=np.nan, b=1)])
def test_bad_parameters_raise(bad):
    with pytest.raises(LightplaneError):
        Ellipse.from_params((0, 0), bad["a"], bad["b"], 0.0)


def test_from_conic_rejects_non_ellipses():
    with pytest.raises(LightplaneError):
        Ellipse.from_conic(np.diag([1.0, -1.0, -1.0]))  # hyperbola
    with pytest.raises(LightplaneError):
        Ellipse.from_conic(np.diag([1.0, 1.0, 1.0]))  # imaginary


def test_iou_and_matching():
    e = Ellipse.from_params((50, 50), 20, 10, 0.0)
    assert ellipse_iou(e, e) == pytest.approx(1.0)
    # concentric, scaled by s: IoU = s^2 exactly
    assert ellipse_iou(e, e.scaled(0.9)) == pytest.approx(0.81, abs=0.01)
    far = Ellipse.from_params((500, 50), 20, 10, 0.0)
    assert ellipse_iou(e, far) == 0.0
    m = match_ellipses([e, e, far], [e])  # duplicate counts as a false positive
    assert (m.tp, m.fp, m.fn) == (1, 2, 0)


# ----------------------------------------------------------------------------- fitting
def test_direct_and_geometric_fit_recover_ellipse_from_noisy_points():
    rng = np.random.default_rng(2)
    e = Ellipse.from_params((1000.0, -300.0), 80.0, 30.0, 1.0)
    sigma = 0.2
    n = 400
    t = rng.uniform(0, 2 * np.pi, n)
    pts = e.points_at(t) + e.normals_at(t) * rng.normal(0, sigma, n)[:, None]
    C = fit_ellipse_direct(pts)
    assert not isinstance(C, Failure)
    g = fit_ellipse_geometric(pts, C)
    assert not isinstance(g, Failure)
    eg = Ellipse.from_conic(g[0])
    # centre standard error ~ sigma * sqrt(2 / n); allow 5 sigma
    tol = 5 * sigma * math.sqrt(2 / n)
    assert np.hypot(*(eg.centre - e.centre)) < tol
    assert abs(eg.a - e.a) < 2 * tol and abs(eg.b - e.b) < 2 * tol
    assert abs(np.std(g[1]) - sigma) < 0.15 * sigma
    few = fit_ellipse_direct(np.zeros((3, 2)))  # too few points
    assert isinstance(few, Failure) and "at least 5" in few.reason
    line = fit_ellipse_direct(np.column_stack([np.arange(20.0), np.arange(20.0)]))  # a line
    assert isinstance(line, Failure) and "collinear" in line.reason
    assert isinstance(fit_ellipse_geometric(np.zeros((3, 2)), C), Failure)
    assert isinstance(fit_conic_robust(np.zeros((3, 2))), Failure)


def test_robust_fit_rejects_outliers():
    rng = np.random.default_rng(3)
    e = Ellipse.from_params((200.0, 150.0), 60.0, 40.0, 0.2)
    t = rng.uniform(0, 2 * np.pi, 300)
    pts = e.points_at(t) + rng.normal(0, 0.05, (300, 2))
    pts[:30] += rng.uniform(3, 15, (30, 2))  # 10 % gross outliers
    fit = fit_conic_robust(pts)
    assert not isinstance(fit, Failure)
    C, keep, res = fit
    assert not np.any(keep[:30])
    assert np.hypot(*(Ellipse.from_conic(C).centre - e.centre)) < 0.03


# ----------------------------------------------------------------------------- refinement
@pytest.mark.parametrize("polarity", ["dark", "light"])
def test_refine_subpixel_centre_on_rendered_ellipse(polarity):
    rng = np.random.default_rng(4 if polarity == "dark" else 5)
    truth = Ellipse.from_params((321.37, 242.81), 150.0, 95.0, 0.7)
    inside, bg = (30.0, 210.0) if polarity == "dark" else (210.0, 30.0)
    noise = 2.0
    img = render_ellipses((480, 640), [truth], inside=inside, background=bg, blur_px=0.8, noise_sigma=noise,
                          rng=rng, dtype=np.uint8)
    start = Ellipse.from_params(truth.centre + [1.2, -0.8], truth.a + 1.0, truth.b - 1.0, truth.angle + 0.02)
    r = refine_ellipse(img, start)
    e = r.ellipse
    # edge-point noise ~ residual rms; centre standard error ~ rms * sqrt(2 / N); 5 sigma + render model 0.005 px
    tol = 5 * r.residual_rms_px * math.sqrt(2 / r.n_inliers) + 0.005
    assert np.hypot(*(e.centre - truth.centre)) < tol
    assert abs(e.a - truth.a) < 0.03 and abs(e.b - truth.b) < 0.03
    assert r.residual_rms_px < 0.2
    assert r.n_inliers > 0.8 * r.n_samples
    assert np.array_equal(r.edge_points_px, r.edge_points_undistorted)
    assert r.ellipse.polarity == (-1 if polarity == "dark" else 1)


def test_refine_with_camera_fits_in_undistorted_pixels():
    cam = Camera(K=[[800.0, 0, 330.0], [0, 800.0, 235.0], [0, 0, 1]], dist=[-0.25, 0.08, 0.001, -0.0005, 0.0],
                 width=640, height=480)
    truth_u = Ellipse.from_params((420.0, 300.0), 110.0, 70.0, 0.5)  # ellipse in undistorted pixels
    # render the distorted image: each pixel's undistorted position decides inside/outside (supersampled 3x3)
    vv, uu = np.mgrid[0:480, 0:640].astype(np.float64)
    acc = np.zeros((480, 640))
    for du in (-1 / 3, 0, 1 / 3):
        for dv in (-1 / 3, 0, 1 / 3):
            q = np.column_stack([(uu + du).ravel(), (vv + dv).ravel()])
            und = cam.undistort_points(q)
            acc += truth_u.contains(und).reshape(uu.shape)
    import cv2

    img = (200.0 - 160.0 * acc / 9.0)
    img = cv2.GaussianBlur(img, (0, 0), 0.7)
    start = Ellipse.from_params((420.0, 300.0), 110.0, 70.0, 0.5)  # a rough start in the image
    r = refine_ellipse(img, start, cam)
    assert np.hypot(*(r.ellipse.centre - truth_u.centre)) < 0.05
    assert abs(r.ellipse.a - truth_u.a) < 0.1 and abs(r.ellipse.b - truth_u.b) < 0.1
    # the undistorted edge points lie on the truth; the distorted ones do not
    d_und = np.abs(truth_u.algebraic(r.edge_points_undistorted)) * truth_u.b
    d_img = np.abs(truth_u.algebraic(r.edge_points_px)) * truth_u.b
    assert np.median(d_und) < 0.1 < np.median(d_img)


def test_refine_bad_input():
    img = np.zeros((100, 100), np.uint8)
    e = Ellipse.from_params((50, 50), 20, 10, 0)
    with pytest.raises(LightplaneError):
        refine_ellipse(img, e)  # no edge at all
    with pytest.raises(LightplaneError):
        refine_ellipse(img, "not an ellipse")
    with pytest.raises(LightplaneError):
        refine_ellipse(img, Ellipse.from_params((500, 500), 20, 10, 0))


# ----------------------------------------------------------------------------- detection
def _scene(rng):
    es = [Ellipse.from_params((150.0, 120.0), 60.0, 40.0, 0.3),
          Ellipse.from_params((420.0, 300.0), 90.0, 35.0, 2.0),
          Ellipse.from_params((480.0, 110.0), 45.0, 44.0, 0.0)]
    img = render_ellipses((480, 640), es, inside=[40.0, 230.0, 60.0], background=140.0, blur_px=0.9,
                          noise_sigma=3.0, rng=rng, dtype=np.uint8)
    return es, img


def test_detect_finds_each_ellipse_once_with_polarity():
    es, img = _scene(np.random.default_rng(6))
    found = detect_ellipses(img, EllipseDetectionOptions(min_axis_px=10))
    m = match_ellipses(found, es, iou_min=0.95)
    assert (m.tp, m.fp, m.fn) == (3, 0, 0)
    for e in found:
        t = min(es, key=lambda x: np.hypot(*(x.centre - e.centre)))
        assert np.hypot(*(e.centre - t.centre)) < 0.5
        assert 0.9 <= e.inlier_ratio <= 1 and 0.9 <= e.coverage <= 1 and e.score == pytest.approx(e.inlier_ratio * e.coverage)
    assert [e.score for e in found] == sorted([e.score for e in found], reverse=True)
    dark = detect_ellipses(img, EllipseDetectionOptions(min_axis_px=10, polarity="dark"))
    assert len(dark) == 2 and all(e.polarity == -1 for e in dark)
    light = detect_ellipses(img, EllipseDetectionOptions(min_axis_px=10, polarity="light"))
    assert len(light) == 1 and light[0].polarity == 1
    assert len(detect_ellipses(img, EllipseDetectionOptions(min_axis_px=10, max_count=1))) == 1
    # the 35 px minor axis is excluded by min_axis_px=38
    assert len(detect_ellipses(img, EllipseDetectionOptions(min_axis_px=38))) == 2


def test_arc_support_groups_turn_with_polarity():
    es, img = _scene(np.random.default_rng(7))
    g8 = to_uint8(img.astype(np.float32))
    segs = arc_support_segments(g8, gradients(g8.astype(np.float32), 0.8, with_magnitude=False))
    groups = arc_groups(segs)
    owners_seen = set()
    for idx, sign in groups:
        if len(idx) < 3:  # a pair of short noisy segments may turn either way; verification sorts it out
            continue
        mids = 0.5 * (segs[idx, :2] + segs[idx, 2:])
        # the ellipse whose edge the group follows (all segment midpoints within 2 px)
        for k, e in enumerate(es):
            if np.all(np.abs(e.algebraic(mids)) * e.b < 2.0):
                owners_seen.add(k)
                assert sign == (1 if k == 1 else -1)  # ellipse 1 is brighter than the background
    assert owners_seen == {0, 1, 2}


def test_detect_with_stripe_across_the_rim():
    """A bright stripe splits the rim into two arcs: the whole ellipse is still found."""
    rng = np.random.default_rng(8)
    e = Ellipse.from_params((320.0, 240.0), 150.0, 100.0, 0.4)
    img = render_ellipses((480, 640), [e], inside=180.0, background=30.0, blur_px=0.8)
    vv, uu = np.mgrid[0:480, 0:640]
    dist = np.abs((uu - 300) * math.cos(1.2) + (vv - 240) * math.sin(1.2))
    img = np.maximum(img, 255.0 * np.exp(-0.5 * (dist / 2.5) ** 2))
    img = np.clip(img + rng.normal(0, 2, img.shape), 0, 255).astype(np.uint8)
    found = detect_ellipses(img, EllipseDetectionOptions(min_axis_px=20))
    assert len(found) >= 1
    assert ellipse_iou(found[0], e) > 0.98
    sel = select_target(img, found)
    assert sel.ellipse is found[0] and sel.crossing.coverage > 0.8


def test_detect_ellipse_cut_by_the_image_border():
    """Judged on its visible part: found when most of it is in the image, not when most is out."""
    rng = np.random.default_rng(11)
    mostly_in = Ellipse.from_params((20.0, 120.0), 50.0, 35.0, 0.3)  # ~70 % of the rim visible
    mostly_out = Ellipse.from_params((330.0, 120.0), 50.0, 35.0, 0.3)  # centre 10 px outside: < 40 % visible
    img = render_ellipses((240, 320), [mostly_in, mostly_out], inside=40.0, background=200.0, blur_px=0.8,
                          noise_sigma=2.0, rng=rng, dtype=np.uint8)
    found = detect_ellipses(img, EllipseDetectionOptions(min_axis_px=10))
    assert len(found) == 1 and ellipse_iou(found[0], mostly_in) > 0.95
    assert found[0].coverage > 0.9  # coverage of the visible sectors


def test_detect_non_finite_images_are_an_error():
    # one rule for every gray conversion (lightplane.core.io.to_gray_float): NaN/inf pixels are bad input
    for bad in (np.full((50, 50), np.nan), np.where(np.eye(60, dtype=bool), np.inf, 10.0)):
        with pytest.raises(LightplaneError, match="NaN or infinite"):
            detect_ellipses(bad)


@pytest.mark.parametrize("kind", ["blank", "white", "noise8", "noise16", "tiny", "tiny_colour", "one_px", "empty",
                                  "colour_noise"])
def test_detect_degenerate_images_give_empty_list(kind):
    rng = np.random.default_rng(9)
    img = {
        "blank": np.zeros((240, 320), np.uint8),
        "white": np.full((240, 320), 255, np.uint8),
        "noise8": rng.integers(0, 256, (240, 320)).astype(np.uint8),
        "noise16": rng.integers(0, 65536, (240, 320)).astype(np.uint16),
        "tiny": rng.integers(0, 256, (5, 5)).astype(np.uint8),
        "tiny_colour": rng.integers(0, 256, (5, 5, 3)).astype(np.uint8),
        "one_px": np.zeros((1, 1)),
        "empty": np.zeros((0, 0)),
        "colour_noise": rng.integers(0, 256, (240, 320, 3)).astype(np.uint8),
    }[kind]
    assert detect_ellipses(img) == []
    assert detect_ellipses(img, EllipseDetectionOptions(min_axis_px=20)) == []


@pytest.mark.parametrize("kind", ["uint16", "colour", "float01", "bgra"])
def test_detect_other_depths_and_colour(kind):
    e = Ellipse.from_params((160.3, 120.6), 70.0, 45.0, 0.9)
    img = render_ellipses((240, 320), [e], inside=50.0, background=200.0, blur_px=0.8)
    img = {"uint16": (img * 257).astype(np.uint16), "colour": np.dstack([img, 0.5 * img, img]).astype(np.uint8),
           "float01": img / 255.0, "bgra": np.dstack([img, img, img, np.full_like(img, 255)]).astype(np.uint8)}[kind]
    found = detect_ellipses(img, EllipseDetectionOptions(min_axis_px=10))
    assert len(found) == 1 and ellipse_iou(found[0], e) > 0.97


def test_detect_bad_arguments():
    img = np.zeros((50, 50), np.uint8)
    with pytest.raises(LightplaneError):
        detect_ellipses(img, EllipseDetectionOptions(polarity="bright"))
    with pytest.raises(LightplaneError):
        detect_ellipses(img, EllipseDetectionOptions(min_axis_px=30, max_axis_px=10))
    with pytest.raises(LightplaneError):
        detect_ellipses(np.zeros((4, 4, 4, 4)))
    with pytest.raises(LightplaneError):
        detect_ellipses(img, EllipseDetectionOptions(max_count=0))
    with pytest.raises(LightplaneError):
        detect_ellipses(img, EllipseDetectionOptions(min_axis_px=np.nan))


# ----------------------------------------------------------------------------- target selection
def _stripe(img, p0, ang, width=2.5, level=255.0):
    vv, uu = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    dist = np.abs((uu - p0[0]) * math.cos(ang) + (vv - p0[1]) * math.sin(ang))
    return np.maximum(img, level * np.exp(-0.5 * (dist / width) ** 2))


def test_select_target_ignores_uncrossed_clutter_and_small_crossed_holes():
    rng = np.random.default_rng(10)
    target = Ellipse.from_params((220.0, 250.0), 130.0, 90.0, 0.2)
    big_uncrossed = Ellipse.from_params((520.0, 120.0), 100.0, 80.0, 1.0)
    small_crossed = Ellipse.from_params((560.0, 380.0), 40.0, 30.0, 0.0)
    img = render_ellipses((480, 640), [target, big_uncrossed, small_crossed], inside=[170.0, 170.0, 170.0],
                          background=30.0, blur_px=0.8)
    # a vertical stripe through the target and a saturated one through the small clutter ellipse
    img = _stripe(img, (230.0, 0.0), 0.0, level=240.0)
    img = _stripe(img, (560.0, 0.0), 0.0, width=4.0, level=255.0)
    img = np.clip(img + rng.normal(0, 2, img.shape), 0, 255).astype(np.uint8)
    found = detect_ellipses(img, EllipseDetectionOptions(min_axis_px=20))
    sel = select_target(img, found)
    assert sel.ellipse is not None and ellipse_iou(sel.ellipse, target) > 0.97
    status = dict(sel.candidates)
    assert status[sel.index] == "chosen"
    # with no stripe through the target nothing is chosen
    img2 = render_ellipses((480, 640), [target, big_uncrossed], inside=170.0, background=30.0, blur_px=0.8)
    img2 = _stripe(img2, (620.0, 0.0), 0.0).astype(np.uint8)
    sel2 = select_target(img2, detect_ellipses(img2, EllipseDetectionOptions(min_axis_px=20)))
    assert sel2.ellipse is None and sel2.reason == "stripe misses the target"


def test_select_target_with_stripe_hint_and_size_prior():
    target = Ellipse.from_params((320.0, 240.0), 120.0, 80.0, 0.0)
    img = render_ellipses((480, 640), [target], inside=170.0, background=30.0, blur_px=0.8).astype(np.uint8)
    found = detect_ellipses(img, EllipseDetectionOptions(min_axis_px=20))
    hint = np.column_stack([np.full(200, 330.0), np.linspace(0, 479, 200)])
    sel = select_target(img, found, stripe_hint=hint)
    assert sel.ellipse is not None and sel.crossing.chord_fraction > 0.9
    assert select_target(img, found, stripe_hint=hint, axis_range_px=(150, 300)).ellipse is None
    assert select_target(img, found).ellipse is None  # no stripe in the image itself
    assert select_target(img, []).ellipse is None
    with pytest.raises(LightplaneError):
        select_target(img, ["x"])
