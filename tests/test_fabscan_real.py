"""Real photographs of a FabScanPi: camera, Zhou's laser planes and scan stripes.

Data: ``shared/data/fabscan`` (see its README; GPL test data, read from there, never
copied into the repository).  A Raspberry Pi camera, 1640x1232 JPEGs stored
unrotated; everything here works in the frame rotated 90 degrees clockwise
(``read_image(path, rotate_deg=90)``), the frame of FabScan's published calibration.
The chessboard has 8 x 10 inner corners of 7 mm; in the rotated frame it shows 10
corners along the image rows and 8 down the columns, so it is ``(10, 8)`` as
``(cols, rows)``.  (``findChessboardCornersSB`` also accepts ``(8, 10)`` on these
images: it returns the same 80 corners in transposed order, and the calibration is the
same to 1e-5 px.)

Frames 67-117 are 17 turntable positions of three frames each: the lit board (laser
off), laser 0 alone in a dark frame, laser 1 alone in a dark frame.  Checked: 67, 70,
... 115 are the lit boards (mean grey ~160-240); in 68, 71, ... the stripe is on the
right of the image (columns ~1050 -> 745 as the board turns), in 69, 72, ... on the
left (~395 -> 100); laser 0 is the one of the ``1_1`` scan, whose stripe is also the
right one.  Frame 68 (laser 0, first position) is black: laser 0 misses the board there.

Measured figures and how they were obtained: docs/real-data-fabscan.md.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from lightplane.plane.zhou import BoardFrames, BoardPlaneOptions, calibrate_plane_board
from lightplane.camera.intrinsics import CameraCalibrationOptions, calibrate_camera
from lightplane.core.io import read_image
from lightplane.plane.model import LightPlane
from lightplane.core.geometry import tls_line
from lightplane.stripe.extract import extract_stripe

pytestmark = pytest.mark.realdata

BOARD = (10, 8)            # (cols, rows) inner corners in the rotated frame
SQUARE_MM = 7.0
ROTATE = 90

# FabScan's published calibration (fabscan-config.json; rotated frame).
PUBLISHED_FX, PUBLISHED_FY = 1319.597, 1322.35
PUBLISHED_CX, PUBLISHED_CY = 625.54, 808.36
# FabScan's plane is normal . X = distance; ours is a x + b y + c z + d = 0, so d = -distance.
PUBLISHED_PLANE_0 = LightPlane(np.array([0.788195, -0.025909, 0.614880]), -77.479)
PLATFORM_CENTRE_MM = np.array([-5.431, 43.628, 135.607])  # turntable origin, FabScan's camera frame

# The lit-board frames (frames 0-66 and 118-133, and the lit frame of each of the 17
# laser positions): 100 frames.  calibrate_camera finds the board in the 73 below (in
# the others it is seen edge-on); from all 73 it takes ~80 s of CPU, so the test uses
# every third of them (25 frames, from frame 0 on; ~22 s).  fx, fy from all 73:
# 1321.61, 1323.04; from the three thirds: +0.16 / +0.44 / -0.13 % and +0.05 / +0.33 /
# -0.21 % from the published values.
LIT = list(range(0, 67)) + list(range(67, 118, 3)) + list(range(118, 134))
FOUND = [0] + list(range(8, 44)) + [50] + list(range(59, 68)) + list(range(70, 116, 3)) + list(range(118, 128))
CAMERA_FRAMES = FOUND[::3]
# frame 008, a view at 3.7 px RMS against the others' ~0.7 px, added: dropped by default
CAMERA_FRAMES_WITH_008 = sorted(CAMERA_FRAMES + [8])

# Scan frames whose stripe coverage is checked (both scans; frame 0 of 1_1 is stale).
SCAN_FRAMES = (1, 13, 25, 38, 50, 63, 75, 88)
SCAN_ROWS = (400, 1280)    # rows between the wall's stripe (ends <= row 395) and the turntable's (from row >= 1286)
LIT_LEVEL = 60             # red level (8 bit) of a row's brightest pixel for "the laser lights the object here"


def _calib(shared_data, i: int):
    return shared_data / "fabscan" / "calibration_8x10" / f"calibration_{i:03d}.jpg"


@pytest.fixture(scope="module")
def fabscan(shared_data):
    root = shared_data / "fabscan"
    if not root.is_dir():
        pytest.skip(f"real-data test: {root} is absent")
    return shared_data


@pytest.fixture(scope="module")
def camera_cal(fabscan):
    t = time.perf_counter()
    # kept on request: the views are ~50x over their corners' own noise (test_camera_is_suspect_...)
    cal = calibrate_camera([_calib(fabscan, i) for i in CAMERA_FRAMES_WITH_008], BOARD, SQUARE_MM,
                           options=CameraCalibrationOptions(rotate_deg=ROTATE, keep_suspect=True))
    return cal, time.perf_counter() - t


def test_camera_matches_published_focal_lengths(camera_cal):
    """Default options (saddle-fit corners, 5 distortion coefficients), 25 views:
    fx, fy within 1 % of FabScan's published 1319.597 / 1322.35 (measured: +0.16 %, +0.05 %).

    cx, cy and the distortion are reported, not bounded: nothing states FabScan computed
    its numbers from these frames (measured cx 617.1 / cy 824.1 against 625.5 / 808.4;
    k1, k2, k3 0.19, -0.29, -0.05 against 0.145, 0.154, -1.15: k2 and k3 trade off).
    """
    cal, seconds = camera_cal
    K = cal.camera.K
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    print(f"\ncamera from {len(cal.used)} of {len(CAMERA_FRAMES)} frames in {seconds:.1f} s: "
          f"fx {fx:.2f} fy {fy:.2f} cx {cx:.2f} cy {cy:.2f} (published {PUBLISHED_FX} {PUBLISHED_FY} "
          f"{PUBLISHED_CX} {PUBLISHED_CY}); dist {np.round(cal.camera.dist, 4).tolist()}; RMS {cal.rms_px:.3f} px; "
          f"worst views {[(n.rsplit('_', 1)[-1], round(r, 2)) for n, r in cal.ranked_views()[:3]]}")
    assert len(cal.used) == len(CAMERA_FRAMES), f"board not found in {cal.not_found}, dropped {list(cal.dropped)}"
    assert abs(fx / PUBLISHED_FX - 1) < 0.01, f"fx {fx:.2f} vs published {PUBLISHED_FX}"
    assert abs(fy / PUBLISHED_FY - 1) < 0.01, f"fy {fy:.2f} vs published {PUBLISHED_FY}"


def test_camera_drops_the_outlier_view_and_is_suspect_against_its_corner_noise(camera_cal):
    """Frame 008 (3.7 px RMS, ~5x the other views) is dropped with its reason. The others' 0.7-0.9 px
    RMS is ~50x what their corners' own noise predicts (0.01-0.03 px: sharp, high-contrast corners),
    in every view alike, and no lens model takes it away (rational: 0.835 px against 0.837): each
    view's corners depart from the homography of a flat regular board by ~0.65 px after undistortion,
    so the printed board is not flat or not regular.  By default the calibration is refused with that
    diagnosis; here it is kept on request and says so."""
    cal, _ = camera_cal
    assert [Path(n).name for n in cal.dropped] == ["calibration_008.jpg"]
    assert "the views' median" in next(iter(cal.dropped.values()))
    nc = cal.noise_check
    print(f"\ncorner noise check: RMS {nc.rms_px:.3f} px, predicted {nc.predicted_px:.4f} px, {nc.ratio:.0f}x; "
          f"dropped {cal.dropped}")
    assert nc.suspect and nc.ratio > 10 and len(nc.suspect_views) == len(nc.views)
    assert "in every view alike" in nc.diagnosis()
    assert cal.to_dict()["corner_noise_check"]["kept_by_request"]


@pytest.fixture(scope="module")
def zhou_runs(fabscan, camera_cal):
    """Zhou's plane of each laser from the 17 positions: the board pose from each lit frame,
    the stripe from the laser's dark frame (default stripe extraction); with the default board
    area (the pattern and the board's white margin, key None) and the pattern only (key 0)."""
    cam = camera_cal[0].camera
    lit = [read_image(_calib(fabscan, 67 + 3 * k), rotate_deg=ROTATE) for k in range(17)]
    out, cache = {}, {}
    for laser in (0, 1):
        idx = [68 + 3 * k + laser for k in range(17)]
        dark = [read_image(_calib(fabscan, i), rotate_deg=ROTATE) for i in idx]
        for margin in (None, 0.0):
            out[laser, margin] = calibrate_plane_board(
                BoardFrames(dark, pattern_images=lit, names=[f"{i:03d}" for i in idx]), cam, BOARD, SQUARE_MM,
                options=BoardPlaneOptions(board_margin_mm=margin), pose_cache=cache)
    return cam, out


@pytest.fixture(scope="module")
def planes(zhou_runs):
    """The planes with the defaults (stripe points on the pattern and the board's margin)."""
    cam, runs = zhou_runs
    return cam, {laser: runs[laser, None] for laser in (0, 1)}


@pytest.fixture(scope="module")
def pattern_planes(zhou_runs):
    """The planes from the stripe on the printed pattern only (``board_margin_mm=0``)."""
    cam, runs = zhou_runs
    return cam, {laser: runs[laser, 0.0] for laser in (0, 1)}


def _per_pose(cam, z):
    """Per used pose: (name, points, residual RMS mm, RMS predicted from the stripe noise mm).

    The stripe noise of a pose is the RMS distance of its centres from their own straight
    line (undistorted px; the board is flat, so the stripe on it is straight).  Moving a
    centre by 1 px across the stripe moves its point on the board plane, and its distance
    to the light plane by g mm (computed per point); the prediction is noise x RMS(g).
    """
    K = cam.K
    Kinv = np.linalg.inv(K)
    nL, dL = z.plane.normal, z.plane.d
    rows = []
    for k, pose in enumerate(z.poses):
        sel = z.view_index == k
        if not sel.any():
            continue
        X = z.points_cam_mm[sel]
        uv = (X[:, :2] / X[:, 2:]) @ K[:2, :2].T + K[:2, 2]  # undistorted px of the centres
        m, _, nrm = tls_line(uv)
        noise_px = float(np.sqrt(np.mean(((uv - m) @ nrm) ** 2)))
        nB, t = pose.normal_cam, pose.t_cam_board

        def on_board(p):
            r = np.column_stack([p, np.ones(len(p))]) @ Kinv.T
            return r * ((nB @ t) / (r @ nB))[:, None]

        g = ((on_board(uv + 0.1 * nrm) - on_board(uv)) @ nL) / 0.1
        res = X @ nL + dL
        rows.append((pose.name, int(sel.sum()), float(np.sqrt(np.mean(res**2))),
                     noise_px * float(np.sqrt(np.mean(g**2))), noise_px, float(res.mean())))
    return rows


def _report(laser, z, rows):
    print(f"\nlaser {laser}: {z.plane}, {len(rows)} poses, {len(z.residual_mm)} points, "
          f"RMS {z.residual_rms_mm:.4f} mm; skipped {z.plane.meta.get('skipped')}")
    for name, n, rms, pred, noise_px, mean in rows:
        print(f"   {name}: {n:4d} pts  stripe noise {noise_px:.3f} px  residual RMS {rms:.4f} mm "
              f"(mean {mean:+.4f})  predicted {pred:.4f} mm  ratio {rms / pred:.2f}")


# Measured with the default stripe extraction: laser 0 has the stripe on the board's
# printed squares in positions 6-17 (in 2-5 it runs on the white margin beside the
# squares; in 1 it misses the board), laser 1 in positions 1-15 (16-17: on the margin).
MIN_POSES = {0: 12, 1: 15}           # the pattern only
MIN_POSES_MARGIN = {0: 15, 1: 16}    # with the margin (the default); measured 16 and 17


@pytest.mark.parametrize("laser", [0, 1])
def test_zhou_planes_noise_limited(pattern_planes, laser):
    """One plane per laser from the 17 positions, stripe points on the printed pattern only; the
    typical pose is limited by the stripe noise.

    Bar, derived from the stripe noise: a pose whose residuals come from the stripe noise
    alone has residual RMS / predicted RMS ~1 (``_per_pose``; >= 100 points per pose,
    so the RMS itself scatters by < 10 %); the board pose adds an offset per pose (70 corners
    at 0.7 px RMS: ~0.02 mm, against ~0.03 mm of noise), so the median pose must stay
    within 2x the noise.  Measured: median 1.37 (laser 0), 1.92 (laser 1; its poses' mean
    residuals drift from -0.07 to +0.05 mm and back as the board turns); overall RMS
    0.080 / 0.089 mm; stripe noise 0.25-0.56 px per pose.
    """
    cam, zs = pattern_planes
    z = zs[laser]
    rows = _per_pose(cam, z)
    _report(laser, z, rows)
    assert len(rows) >= MIN_POSES[laser], f"only {len(rows)} usable poses: {z.plane.meta.get('skipped')}"
    ratio = np.array([r[2] / r[3] for r in rows])
    assert np.median(ratio) <= 2.0, f"median pose residual / stripe-noise prediction {np.median(ratio):.2f}"


@pytest.mark.xfail(strict=True, reason=(
    "measured: 6 of 27 poses have residuals 4-17x what their stripe noise explains, mostly "
    "an offset of the pose's whole stripe off the common plane (mean residual 0.07-0.26 mm), "
    "causes in the data (docs/real-data-fabscan.md): laser 0 frame 089 (17.3; the stripe along "
    "a column of corners, every centre next to a printed edge); position 8, laser 0 092 (5.0) and "
    "laser 1 093 (5.4): its lit frame taken 0.74 deg of table rotation short of the laser frames; "
    "laser 1 frames 105 (5.2), 108 (4.1), 111 (11.3): the most saturated dark frames, blooming"))
@pytest.mark.parametrize("laser", [0, 1])
def test_zhou_every_pose_noise_limited(pattern_planes, laser):
    """Every pose within 3x the residual its stripe noise predicts (see test_zhou_planes_noise_limited)."""
    cam, zs = pattern_planes
    rows = _per_pose(cam, zs[laser])
    bad = [(r[0], round(r[2] / r[3], 2)) for r in rows if r[2] > 3.0 * r[3]]
    assert not bad, f"poses beyond 3x their stripe-noise residual: {bad}"


@pytest.mark.parametrize("laser", [0, 1])
def test_margin_keeps_positions_and_plane(planes, pattern_planes, laser):
    """The stripe on the board's white margin: laser 0 keeps >= 15 of its 17 positions (measured 16; the
    first misses the board), laser 1 all 17 (measured); no image is suspect (the calibration would refuse).

    The plane against the pattern-only one (same camera, same frames), in the pattern-only plane's own
    jackknife sigma: the normal within 1 sigma (measured 0.17 deg against 0.34 for laser 0, 0.19 against
    0.26 for laser 1), the offset at the pattern-only points' centroid within 2 sigma (measured +0.023 mm
    against 0.018 mm, -0.001 against 0.021).  It may move: the margin lengthens each stripe by up to 21 mm
    beyond the squares (the board's top margin), where the poses' residuals trend by up to 0.2 mm along the
    stripe (the board pose extrapolated beyond its corners, the board's edge not quite flat).
    """
    _, zs = planes
    _, zp = pattern_planes
    z, z0 = zs[laser], zp[laser]
    used = len(set(z.view_index.tolist()))
    print(f"\nlaser {laser}: {used} poses with the margin ({len(z.residual_mm)} points, RMS {z.residual_rms_mm:.4f} mm), "
          f"{len(set(z0.view_index.tolist()))} on the pattern only; skipped {z.plane.meta['skipped']}")
    assert used >= MIN_POSES_MARGIN[laser], z.plane.meta["skipped"]
    assert z.plane.meta["quality"]["verdict"] != "suspect"
    cov = z0.plane.covariance
    angle = z.plane.angle_to(z0.plane)
    c = np.append(z0.points_cam_mm.mean(axis=0), 1.0)
    offset = float((z.plane.coefficients - z0.plane.coefficients) @ c)
    print(f"plane moved {np.degrees(angle):.3f} deg (sigma {np.degrees(np.sqrt(np.trace(cov[:3, :3]))):.3f}), "
          f"{offset:+.4f} mm at the centroid (sigma {np.sqrt(c @ cov @ c):.4f})")
    assert angle < np.sqrt(np.trace(cov[:3, :3]))
    assert abs(offset) < 2 * np.sqrt(c @ cov @ c)


def test_laser0_plane_near_published(planes):
    """Laser 0 against FabScan's published plane: a sanity bound, not an accuracy bar.

    The published plane need not come from these frames: the README notes the scans were
    taken in another geometry than the calibration frames (the stripe on the turntable sits
    16-20 px elsewhere, ~2 mm at the turntable's 136 mm).  Measured (defaults: the stripe on
    the board's margin too): 1.92 deg between the normals; the published plane lies 0.60 mm (mean)
    from our stripe points (z 102-114 mm), and 2.3 mm (~23 px) to the side of ours at the turntable
    centre (the pattern only: 1.76 deg, 0.72 mm, 2.1 mm).  Bound: 5 deg and
    3 mm, which catch a wrong laser (laser 1 is 70 deg away), a mirrored or unrotated frame
    or a scale error, none of which a session change can produce.
    """
    _, zs = planes
    p = zs[0].plane
    pub = PUBLISHED_PLANE_0
    angle = float(np.degrees(np.arccos(min(1.0, abs(p.normal @ pub.normal)))))
    dist = pub.signed_distance(zs[0].points_cam_mm)
    # lateral offset (x) of the two planes at the turntable centre's y, z
    y, zc = PLATFORM_CENTRE_MM[1:]
    x_ours = -(p.normal[1] * y + p.normal[2] * zc + p.d) / p.normal[0]
    x_pub = -(pub.normal[1] * y + pub.normal[2] * zc + pub.d) / pub.normal[0]
    print(f"\nlaser 0 {p} vs published {pub}: angle {angle:.3f} deg, d {p.d - pub.d:+.3f} mm, "
          f"published plane from our points {dist.mean():+.3f} mm (RMS {np.sqrt(np.mean(dist**2)):.3f}), "
          f"x at the turntable centre {x_ours:.2f} vs {x_pub:.2f} mm")
    other = float(np.degrees(np.arccos(abs(zs[1].plane.normal @ pub.normal))))
    print(f"laser 1 {zs[1].plane}: {other:.1f} deg from the published laser-0 plane")
    assert angle < 5.0
    assert abs(dist.mean()) < 3.0


def _lit_rows(red: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows where the laser draws a line on the object, and each row's brightest column.

    A row counts when its brightest red pixel reaches ``LIT_LEVEL`` and stands out of
    the profile 20-30 px to either side by a quarter of its level: that keeps the narrow
    and the blooming (saturated, 15-45 px wide) stripe and leaves out rows where the
    laser only washes a grazed surface with diffuse light (a 100 px plateau, no line).
    """
    pk = red.max(axis=1)
    col = red.argmax(axis=1)
    w = red.shape[1]
    ok = np.zeros(len(red), bool)
    for k in np.nonzero(pk >= LIT_LEVEL)[0]:
        c = col[k]
        left = red[k, max(c - 30, 0):max(c - 20, 1)].mean()
        right = red[k, min(c + 21, w - 1):min(c + 31, w)].mean()
        ok[k] = pk[k] - max(left, right) >= 0.25 * pk[k]
    return ok, col


@pytest.mark.parametrize("scan", ["1_1", "1_2"])
def test_scan_stripe_coverage(fabscan, scan):
    """Default ``extract_stripe`` on the turntable scans: centres along the object.

    In the rotated frame the stripe on the object runs roughly down the image (rows
    ~430-1300): the fraction of rows in which the laser draws a line on the object
    (``_lit_rows``, rows 400-1280: below the wall's stripe, above the turntable's) that
    hold a stripe centre within 15 px of that row's brightest red pixel.  A user scanning
    an object expects the profile wherever the laser visibly lights it: at least 90 % of
    those rows in every frame (one-in-ten rows lost is already a visible hole in the
    mesh), and 95 % on average.  Measured over frames 1, 13, ... 88: 1_1 0.904-1.000
    (mean 0.979), 1_2 0.940-1.000 (mean 0.981).  The worst, 1_1 frame 13, loses rows
    889-995: a clear 4 px stripe (red contrast 50-90) whose centres form fragments
    shorter than ``min_length`` at the estimated width (7.6 px); they are found with
    ``width_px=6`` or ``min_length=2``.
    """
    files = sorted((fabscan / "fabscan" / scan).glob("*.jpg"))
    v0, v1 = SCAN_ROWS
    cov = []
    for i in SCAN_FRAMES:
        img = read_image(files[i], rotate_deg=ROTATE)
        lit, col = _lit_rows(img[v0:v1, :, 2].astype(np.float64))
        uv = np.asarray(extract_stripe(img).uv, dtype=np.float64).reshape(-1, 2)
        v = np.round(uv[:, 1]).astype(int)
        sel = (v >= v0) & (v < v1)
        k = v[sel] - v0
        near = np.abs(uv[sel, 0] - col[k]) <= 15
        has = np.zeros(v1 - v0, bool)
        has[k[near]] = True
        cov.append(float(has[lit].mean()))
        assert lit.sum() > 500, f"{scan} frame {i}: the laser lights only {lit.sum()} rows"
    print(f"\n{scan} coverage per frame {dict(zip(SCAN_FRAMES, np.round(cov, 3)))}; mean {np.mean(cov):.3f}")
    assert min(cov) >= 0.90, f"{scan}: coverage {dict(zip(SCAN_FRAMES, np.round(cov, 3)))}"
    assert np.mean(cov) >= 0.95


def test_cli_two_lasers_from_the_cycle_of_frames(fabscan, camera_cal, planes, tmp_path):
    """``calibrate-plane-board`` with both lasers at once, defaults otherwise:
    the 51 frames 67-117 in order, ``--cycle P,L,L --laser laser0=cycle:1 --laser laser1=cycle:2``.

    Two plane files, each naming its laser; each equals Zhou's plane of that laser computed
    on its own (the ``planes`` fixture: same camera, frames and defaults) to 1e-9, i.e.
    several lasers change nothing about any one; and against FabScan's published values as
    in test_laser0_plane_near_published: laser 0 within 5 deg (measured 1.92 deg) and 3 mm at
    the turntable centre of FabScan's plane 0 (its config lists one plane; laser 1 is ~70 deg
    away from it).  The boards of the 17 lit frames are found once for both lasers.
    """
    from typer.testing import CliRunner

    from lightplane.cli import app

    cam_file = tmp_path / "camera.json"
    camera_cal[0].camera.save_json(cam_file)
    files = [str(_calib(fabscan, i)) for i in range(67, 118)]
    out = tmp_path / "plane.json"
    r = CliRunner().invoke(app, ["calibrate-plane-board", *files, "--camera", str(cam_file), "--board", "10x8",
                                 "--square", "7", "--rotate", "90", "--cycle", "P,L,L",
                                 "--laser", "laser0=cycle:1", "--laser", "laser1=cycle:2", "-o", str(out)],
                           env={"COLUMNS": "160"})
    assert r.exit_code == 0, r.output
    _, zs = planes
    got = {}
    for laser in (0, 1):
        f = tmp_path / f"plane_laser{laser}.json"
        d = json.loads(f.read_text())
        assert d["laser"] == f"laser{laser}"
        assert d["provenance"]["options"]["cycle"] == "P,L,L"
        got[laser] = LightPlane.load(f)
        assert np.allclose(got[laser].coefficients, zs[laser].plane.coefficients, atol=1e-9), (got[laser], zs[laser].plane)
        used = [im["name"] for im in d["images"] if im["used"]]
        assert len(used) >= MIN_POSES[laser] and all(int(Path(n).stem[-3:]) % 3 == (68 + laser) % 3 for n in used)
    assert not out.exists()
    pub = PUBLISHED_PLANE_0
    angle = float(np.degrees(np.arccos(min(1.0, abs(got[0].normal @ pub.normal)))))
    y, zc = PLATFORM_CENTRE_MM[1:]
    x_ours = -(got[0].normal[1] * y + got[0].normal[2] * zc + got[0].d) / got[0].normal[0]
    x_pub = -(pub.normal[1] * y + pub.normal[2] * zc + pub.d) / pub.normal[0]
    other = float(np.degrees(np.arccos(abs(got[1].normal @ pub.normal))))
    print(f"\nCLI laser0 {got[0]} ({angle:.2f} deg, x at the turntable centre {x_ours - x_pub:+.2f} mm from the "
          f"published plane); laser1 {got[1]} ({other:.1f} deg from it)")
    assert angle < 5.0 and abs(x_ours - x_pub) < 3.0
    assert other > 30.0
