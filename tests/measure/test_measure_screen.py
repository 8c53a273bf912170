"""Measured points are points: frames without a stripe give none, outliers are dropped and counted."""

from __future__ import annotations

import json

import numpy as np
import pytest
from _cli import lightplane, one_error_line
from _measure_synth import CAM, PLANE, stripe_image, surface
from _renders import cached_render

from lightplane import LightPlane
from lightplane.measure.options import MeasureOptions
from lightplane.measure.profile import ProfileMeasurer, has_stripe
from lightplane.measure.scan import ArrayFrames, scan_points
from lightplane.stripe.options import StripeOptions

OPTS = StripeOptions(width_px=3.5)
SHIFTED = slice(100, 130)  # rows whose centre is moved far off the stripe: their points land elsewhere on the plane


@pytest.fixture(scope="module")
def boards():
    import lightplane.simulate.render as R

    return cached_render("boards_stripe_off_n4_s21", lambda: R.render_chessboard_dataset(
        4, 21, R.BoardOptions(difficulty="realistic", with_stripe=True, laser_off=True)))


def test_chessboard_frames_without_laser_give_no_points(boards, tmp_path):
    """measure on the laser-off chessboard frames: every frame has no stripe, exit 2 with one line."""
    truth = json.loads((boards / "truth.json").read_text())
    LightPlane.from_dict(truth["plane"]).save(tmp_path / "plane.json")
    off = [boards / v["file_laser_off"] for v in truth["views"]]
    r = lightplane("measure", *off, "--camera", boards / "camera.json", "--plane", tmp_path / "plane.json",
                   "-o", tmp_path / "x.ply")
    one_error_line(r, "no laser stripe in any of the 4 readable frames")
    assert not (tmp_path / "x.ply").exists()


def test_stripe_evidence():
    """A stripe across the frame is one; fragments as long as they are wide, or a stripe cut into pieces
    shorter than STRIPE_MIN_RUN, are not."""
    img, u_c = stripe_image(*surface())
    prof = ProfileMeasurer(CAM, PLANE, MeasureOptions(OPTS))(img)
    assert prof.n_valid > 300 and not prof.dropped
    assert has_stripe(prof.valid, prof.width_px)
    pieces = prof.valid.copy()
    pieces[::15] = False  # runs of 14 lines
    assert not has_stripe(pieces, prof.width_px)
    assert not has_stripe(prof.valid, np.full(len(prof.valid), 0.25 * prof.n_valid))  # as wide as long: a blob
    assert has_stripe(np.ones(8, bool), np.full(8, 1.0))  # a roi of 8 lines: half of them suffice


def _frames(n=3):
    """Stripe frames of the tilted surface, rows SHIFTED moved 150 px to the right (their points lie on the
    plane, ~20 % deeper than the stripe's)."""
    out = []
    n_s, d_s = surface()
    for k in range(n):
        img, u_c = stripe_image(*surface(), shift_px=0.25 * k)
        bad, _ = stripe_image(n_s, d_s, shift_px=0.25 * k + 150.0)
        img[SHIFTED] = bad[SHIFTED]
        out.append(img)
    return out


def _plane_with_volume():
    """PLANE with a covariance and the working volume of the true stripe (depths of its unshifted rows)."""
    img, _ = stripe_image(*surface())
    prof = ProfileMeasurer(CAM, PLANE, MeasureOptions(OPTS))(img)
    z = prof.points[prof.valid, 2]
    cov = np.diag([1e-8, 1e-8, 1e-8, 1e-4])
    wv = {"depth_mm": [float(z.min()), float(z.max())], "centre_mm": np.nanmean(prof.points[prof.valid], axis=0).tolist()}
    return LightPlane(PLANE.normal, PLANE.d, cov, meta={"working_volume": wv})


def test_far_points_dropped_counted_and_kept_on_request():
    """The 30 shifted rows per frame (28-30 of them keep a centre) lie outside the working volume (depth factor 1.05 around the stripe's
    depths): dropped and counted per frame and in total; with keep_outliers every point stays."""
    plane = _plane_with_volume()
    frames = _frames()
    opts = MeasureOptions(OPTS, depth_factor=1.05)
    kept, s = scan_points(ArrayFrames(frames), CAM, plane, opts)
    allpts, s_all = scan_points(ArrayFrames(frames), CAM, plane, MeasureOptions(OPTS, depth_factor=1.05,
                                                                                 keep_outliers=True))
    n_far = s.dropped.totals["outside the working volume"]
    assert list(s.dropped.totals) == ["outside the working volume"]
    per_frame = [d["outside the working volume"] for _, _, d in s.dropped.frames]
    assert len(per_frame) == len(frames) and all(28 <= k <= 30 for k in per_frame) and sum(per_frame) == n_far
    assert kept.size + n_far == allpts.size and not s_all.dropped.totals
    lo, hi = plane.meta["working_volume"]["depth_mm"]
    assert np.all((kept["z"] >= lo / 1.05) & (kept["z"] <= hi * 1.05))
    assert np.sum((allpts["z"] < lo / 1.05) | (allpts["z"] > hi * 1.05)) == n_far
    assert f"dropped: {n_far} points outside the working volume" in s.dropped.summary()


def test_sigma_beyond_the_bound_dropped():
    """Points whose σ exceeds max_sigma_ratio x the σ at the calibration's centre are dropped, exactly those."""
    plane = _plane_with_volume()
    frames = _frames(1)
    everything, _ = scan_points(ArrayFrames(frames), CAM, plane, MeasureOptions(OPTS, keep_outliers=True))
    m = ProfileMeasurer(CAM, plane, MeasureOptions(OPTS, max_sigma_ratio=1.02))
    ref = m.sigma_bound / 1.02
    over = everything["sigma_mm"] > 1.02 * ref
    assert 0 < over.sum() < len(over)
    kept, s = scan_points(ArrayFrames(frames), CAM, plane, MeasureOptions(OPTS, max_sigma_ratio=1.02))
    assert s.dropped.totals == {"sigma beyond the bound": int(over.sum())}
    assert kept.size == int((~over).sum())


def test_cli_counts_dropped_points_in_the_file(tmp_path):
    """measure writes the dropped points' counts in the summary (stderr) and per frame in the cloud's comments;
    --keep-outliers keeps them."""
    import cv2

    CAM.save_json(tmp_path / "camera.json")
    plane = _plane_with_volume()
    lo, hi = plane.meta["working_volume"]["depth_mm"]
    # the command's depth factor is 2: a recorded range whose doubled far end lies between the stripe's
    # depths and the shifted rows' (~20 % deeper)
    wv = {"depth_mm": [0.5 * lo, 0.55 * hi], "centre_mm": plane.meta["working_volume"]["centre_mm"]}
    LightPlane(plane.normal, plane.d, None, meta={"working_volume": wv}).save(tmp_path / "plane.json")
    paths = []
    for k, img in enumerate(_frames(2)):
        paths.append(tmp_path / f"f{k}.png")
        cv2.imwrite(str(paths[-1]), np.clip(np.rint(img), 0, 255).astype(np.uint8))
    args = ["--camera", tmp_path / "camera.json", "--plane", tmp_path / "plane.json", "--stripe-width", "3.5"]
    r = lightplane("measure", *paths, *args, "-o", tmp_path / "a.ply", "--ascii")
    assert r.returncode == 0, r.stderr
    assert "points outside the working volume" in r.stderr
    text = (tmp_path / "a.ply").read_text(errors="replace")
    assert "comment frame 0 (f0.png): dropped" in text and "comment frame 1 (f1.png): dropped" in text
    r = lightplane("measure", *paths, *args, "--keep-outliers", "-o", tmp_path / "b.ply", "--ascii")
    assert r.returncode == 0, r.stderr
    assert "points outside the working volume" not in r.stderr
    n = [int(next(ln for ln in (tmp_path / f).read_text(errors="replace").splitlines()
                  if ln.startswith("element vertex")).split()[-1]) for f in ("a.ply", "b.ply")]
    assert n[0] < n[1]


def test_points_past_the_lens_models_fold_dropped():
    """A lens model that folds inside the image (k3 = -1.15 at a wide field: FabScan's published camera
    folds at r = 0.76): the measurer sees once that its roi does not come back onto itself and checks
    each frame's points, dropping exactly those whose pixel does not come back within 0.05 px; a
    camera without a fold over its image (the default sensor's) skips that per-frame check, and its
    points come back within 1e-6 px."""
    from lightplane import Camera

    fold = Camera(K=[[400.0, 0, 319.5], [0, 400.0, 239.5], [0, 0, 1]], dist=[0, 0, 0, 0, -1.15], width=640, height=480)
    m = ProfileMeasurer(fold, PLANE, MeasureOptions(OPTS, keep_outliers=False))
    assert m.round_trip_everywhere is False and ProfileMeasurer(CAM, PLANE, MeasureOptions(OPTS)).round_trip_everywhere
    rows = np.arange(480.0)
    uv = np.column_stack([np.full_like(rows, 600.0), rows])       # one centre per row, near the right edge
    prof = m.from_stripe(uv, np.ones(len(rows), bool))
    with np.errstate(invalid="ignore"):
        back = fold.project(fold.undistort_points(uv, normalized=True) @ np.array([[1, 0, 0], [0, 1, 0]]) +
                            np.array([0, 0, 1.0]))
    bad = ~(np.linalg.norm(back - uv, axis=1) <= 0.05)
    assert 0 < bad.sum() < len(rows)
    kept = m.screen(prof)
    assert kept.dropped.get("outside the camera model") == int(np.count_nonzero(bad & prof.valid))
    assert not np.any(kept.valid & bad)
    good = ProfileMeasurer(CAM, PLANE, MeasureOptions(OPTS))
    p = good.from_stripe(np.column_stack([np.full_like(rows, 600.0), rows]), np.ones(len(rows), bool))
    assert np.nanmax(np.linalg.norm(CAM.project(p.points[p.valid]) - p.uv[p.valid], axis=1)) < 1e-6
