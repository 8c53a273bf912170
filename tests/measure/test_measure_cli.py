"""`lightplane measure`: frames → cloud; bad input gives one line on stderr, exit 2, nothing written."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _measure_synth import CAM, PLANE, write_scan  # noqa: E402

from lightplane import Camera  # noqa: E402
from lightplane.measure.pointcloud import read_cloud  # noqa: E402
from _cli import lightplane, one_error_line  # noqa: E402


def run(*args):
    return lightplane("measure", *args)


N_FRAMES = 5


@pytest.fixture(scope="module")
def scan_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("scan")
    write_scan(d, N_FRAMES, "frames")
    return d


def outputs(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir() if p.is_file() and p.suffix in (".ply", ".csv", ".npy", ".bin"))


def test_measure_folder_with_step_motion(scan_dir, tmp_path):
    out = tmp_path / "cloud.ply"
    r = run(scan_dir / "frames", "--camera", scan_dir / "camera.json", "--plane", scan_dir / "plane.json",
            "-o", out, "--step", "0.5", "--direction", "2,0,0")
    assert r.returncode == 0, r.stderr
    assert f"{N_FRAMES} frames" in r.stdout and "points" in r.stdout
    rec = read_cloud(out)
    assert np.array_equal(np.unique(rec["frame"]), np.arange(N_FRAMES))
    assert rec.size > N_FRAMES * 350  # ~390 stripe rows per frame
    # frame 0 stays in the camera frame: on the light plane; frame k moved back by k * 0.5 mm along x
    for k in (0, 3):
        r_k = rec[rec["frame"] == k]
        p = np.column_stack([r_k["x"], r_k["y"], r_k["z"]]).astype(float) + [0.5 * k, 0, 0]
        assert np.max(np.abs(PLANE.signed_distance(p))) < 1e-3
    assert b"binary_little_endian" in out.read_bytes()[:60]
    # the same as CSV, refused again without --force
    r2 = run(scan_dir / "frames", "--camera", scan_dir / "camera.json", "--plane", scan_dir / "plane.json",
             "-o", out, "--workers", "1")
    assert "already exists" in one_error_line(r2)


def test_unreadable_middle_frame_is_skipped_and_reported(scan_dir, tmp_path):
    frames = sorted((scan_dir / "frames").glob("*.png"))
    broken = tmp_path / "f02.png"
    broken.write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    inputs = [frames[0], frames[1], broken, frames[3], frames[4]]
    out = tmp_path / "cloud.csv"
    r = run(*inputs, "--camera", scan_dir / "camera.json", "--plane", scan_dir / "plane.json", "-o", out)
    assert r.returncode == 0, r.stderr
    assert "skipped 1 unreadable frame" in r.stderr and "f02.png" in r.stderr
    rec = read_cloud(out)
    assert sorted(np.unique(rec["frame"]).tolist()) == [0, 1, 3, 4]  # indices keep the input order


def test_video_input(scan_dir, tmp_path):
    video = tmp_path / "scan.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (CAM.width, CAM.height), True)
    if not w.isOpened():
        pytest.skip("OpenCV was built without an MJPG video writer")
    for p in sorted((scan_dir / "frames").glob("*.png")):
        w.write(cv2.cvtColor(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE), cv2.COLOR_GRAY2BGR))
    w.release()
    out = tmp_path / "v.npy"
    r = run(video, "--camera", scan_dir / "camera.json", "--plane", scan_dir / "plane.json", "-o", out)
    assert r.returncode == 0, r.stderr
    rec = read_cloud(out)
    assert np.array_equal(np.unique(rec["frame"]), np.arange(N_FRAMES))
    p = np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(float)
    assert np.max(np.abs(PLANE.signed_distance(p))) < 1e-3
    # positions with one row too few: exit 2 at the first frame without a position, nothing written
    pos = tmp_path / "pos.csv"
    pos.write_text("dx,dy,dz\n" + "".join(f"{0.5 * k},0,0\n" for k in range(N_FRAMES - 1)))
    r = run(video, "--camera", scan_dir / "camera.json", "--plane", scan_dir / "plane.json", "-o",
            tmp_path / "p.ply", "--positions", pos)
    assert "positions give 4 frames but the input has more" in one_error_line(r)
    # one row too many: found when the video ends (its announced frame count is not trusted)
    pos.write_text("dx,dy,dz\n" + "".join(f"{0.5 * k},0,0\n" for k in range(N_FRAMES + 1)))
    r = run(video, "--camera", scan_dir / "camera.json", "--plane", scan_dir / "plane.json", "-o",
            tmp_path / "p.ply", "--positions", pos)
    assert "positions give 6 frames but the input has 5" in one_error_line(r)
    assert not (tmp_path / "p.ply").exists()
    assert not list(tmp_path.glob(".*"))  # no temporary spool or partial output left


def test_bad_input_exit_2_nothing_written(scan_dir, tmp_path):
    cam, plane, frames = scan_dir / "camera.json", scan_dir / "plane.json", scan_dir / "frames"
    fake = tmp_path / "fake.mp4"
    fake.write_bytes(b"this is not a video" * 10)
    assert "cannot be opened as a video" in one_error_line(run(fake, "--camera", cam, "--plane", plane,
                                                               "-o", tmp_path / "a.ply"))
    pos = tmp_path / "pos.csv"
    pos.write_text("".join(f"{0.5 * k}\n" for k in range(N_FRAMES + 2)))
    line = one_error_line(run(frames, "--camera", cam, "--plane", plane, "-o", tmp_path / "b.ply",
                              "--positions", pos, "--direction", "1,0,0"))
    assert "positions give 7 frames but the input has 5" in line
    small = tmp_path / "small.json"
    Camera(CAM.K / [[2], [2], [1]], CAM.dist, 320, 240).save_json(small)
    assert "640x480 px but the camera is calibrated for 320x240" in one_error_line(
        run(frames, "--camera", small, "--plane", plane, "-o", tmp_path / "c.ply"))
    bad_plane = tmp_path / "bad_plane.json"
    bad_plane.write_text('{"normal": [0, 0], "d": -100}')
    assert "bad_plane.json" in one_error_line(run(frames, "--camera", cam, "--plane", bad_plane,
                                                  "-o", tmp_path / "d.ply"))
    assert "--step needs --direction" in one_error_line(run(frames, "--camera", cam, "--plane", plane,
                                                            "-o", tmp_path / "e.ply", "--step", "1"))
    assert outputs(tmp_path) == ["pos.csv"]  # no cloud, no spool left behind


def test_no_stripe_anywhere_is_an_error(scan_dir, tmp_path):
    """Frames without any stripe (laser off): one clear line, exit 2, no cloud written."""
    cam, plane = scan_dir / "camera.json", scan_dir / "plane.json"
    dark = tmp_path / "dark"
    dark.mkdir()
    for k in range(3):
        cv2.imwrite(str(dark / f"f{k}.png"), np.full((480, 640), 20, np.uint8))
    line = one_error_line(run(dark, "--camera", cam, "--plane", plane, "-o", tmp_path / "x.ply"))
    assert "no stripe found in any of the 3 readable frames" in line
    assert outputs(tmp_path) == []


def test_sigma_along_option(scan_dir, tmp_path):
    """--sigma-along reaches the stripe extractor: a straight stripe stays where it is (same points within
    0.01 mm), and an impossible scale is refused with one line, nothing written."""
    base, smooth = tmp_path / "a.npy", tmp_path / "b.npy"
    common = ("--camera", scan_dir / "camera.json", "--plane", scan_dir / "plane.json")
    assert run(scan_dir / "frames", *common, "-o", base).returncode == 0
    r = run(scan_dir / "frames", *common, "-o", smooth, "--sigma-along", "4")
    assert r.returncode == 0, r.stderr
    a, b = read_cloud(base), read_cloud(smooth)
    key = lambda rec: {(int(f), round(float(v))): np.array([x, y, z]) for f, v, x, y, z in  # noqa: E731
                       zip(rec["frame"], rec["v"], rec["x"], rec["y"], rec["z"])}
    ka, kb = key(a), key(b)
    common_keys = [k for k in ka if k in kb]
    assert len(common_keys) > 0.9 * len(ka)
    d = np.array([np.linalg.norm(ka[k] - kb[k]) for k in common_keys])
    assert np.median(d) < 0.01 and not np.all(d == 0)
    bad = tmp_path / "c.npy"
    one_error_line(run(scan_dir / "frames", *common, "-o", bad, "--sigma-along", "0.1"))
    assert not bad.exists()


def _with_static_ridge(scan_dir: Path, d: Path) -> tuple[Path, Path]:
    """The scan's frames with a static bright ridge added (a lamp's edge in the scene, brighter than the
    stripe, at column 100), and the laser-off frame of that scene (ambient level and the ridge)."""
    u = np.arange(CAM.width, dtype=float)[None, :]
    ridge = 240.0 * np.exp(-0.5 * ((u - 100.0) / 1.5) ** 2) * np.ones((CAM.height, 1))
    (d / "laser").mkdir()
    for p in sorted((scan_dir / "frames").glob("*.png")):
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE).astype(float)
        cv2.imwrite(str(d / "laser" / p.name), np.clip(np.rint(img + ridge), 0, 255).astype(np.uint8))
    off = d / "off.png"
    cv2.imwrite(str(off), np.clip(np.rint(10.0 + ridge), 0, 255).astype(np.uint8))
    return d / "laser", off


def test_laser_off_frame_is_subtracted(scan_dir, tmp_path):
    """``--background``: a static bright ridge beside the stripe takes the rows' centres without it,
    and with its laser-off frame every centre is the clean scan's (within 0.02 px); the cloud
    records the laser-off frames."""
    laser, off = _with_static_ridge(scan_dir, tmp_path)
    cam, pl = scan_dir / "camera.json", scan_dir / "plane.json"
    clean = tmp_path / "clean.csv"
    assert run(scan_dir / "frames", "--camera", cam, "--plane", pl, "-o", clean).returncode == 0
    with_off = tmp_path / "off.csv"
    r = run(laser, "--camera", cam, "--plane", pl, "-o", with_off, "--background", off)
    assert r.returncode == 0, r.stderr
    assert "laser-off frame" in r.stdout
    a, b = read_cloud(clean), read_cloud(with_off)
    assert a.size == b.size > N_FRAMES * 350
    assert np.max(np.abs(a["u"].astype(float) - b["u"].astype(float))) < 0.02
    assert "laser-off frames" in with_off.read_text().splitlines()[0] + with_off.read_text()[:2000]
    without = tmp_path / "without.csv"
    run(laser, "--camera", cam, "--plane", pl, "-o", without, "--keep-outliers")
    w = read_cloud(without)
    assert np.mean(np.abs(w["u"].astype(float) - 100.0) < 2.0) > 0.5     # the ridge wins without it


def test_laser_off_frames_that_do_not_pair_are_refused(scan_dir, tmp_path):
    """Laser-off frames neither one nor one per frame, a frame given as its own laser-off frame, or
    --background with --sensor: one line, exit 2, nothing written."""
    laser, off = _with_static_ridge(scan_dir, tmp_path)
    cam, pl = scan_dir / "camera.json", scan_dir / "plane.json"
    two = tmp_path / "two"
    two.mkdir()
    for k in range(2):
        (two / f"o{k}.png").write_bytes(off.read_bytes())
    out = tmp_path / "c.ply"
    for extra, words in ((["--background", two], "2 laser-off frames for 5 frames"),
                         (["--background", sorted(laser.glob("*.png"))[0]], "both as a frame and as a laser-off")):
        r = run(laser, "--camera", cam, "--plane", pl, "-o", out, *extra)
        assert r.returncode == 2 and words in one_error_line(r)
    r = run(laser, "--sensor", cam, "-o", out, "--background", off)
    assert r.returncode == 2 and "--background goes with --camera/--plane" in one_error_line(r)
    assert not out.exists()


def test_laser_off_frame_drops_centres_on_uneven_reflectance(tmp_path):
    """A printed edge along the stripe, 1.5 px beside it, over rows 100-199 (light 1.0 on the stripe's
    side, ink 0.15 beyond; ambient 60 grey levels): the difference alone puts those rows' centres
    more than 0.1 px towards the light side; with ``--background`` they are dropped and counted
    ("on uneven reflectance", per frame in the cloud's comments), every other row's centre is the
    clean stripe's within 0.02 px."""
    from _measure_synth import stripe_image, surface

    CAM.save_json(tmp_path / "camera.json")
    PLANE.save(tmp_path / "plane.json")
    img, u_c = stripe_image(*surface())
    u = np.arange(CAM.width, dtype=float)[None, :]
    refl = np.ones(img.shape)
    rows = np.arange(100, 200)
    refl[rows] = np.where(u < u_c[rows, None] + 1.5, 1.0, 0.15)
    refl = cv2.GaussianBlur(refl, (0, 0), 0.7)
    to8 = lambda x: np.clip(np.rint(x), 0, 255).astype(np.uint8)  # noqa: E731
    (tmp_path / "f").mkdir()
    cv2.imwrite(str(tmp_path / "f" / "a.png"), to8(60.0 * refl + (img - 10.0) * refl))
    cv2.imwrite(str(tmp_path / "off.png"), to8(60.0 * refl))
    cv2.imwrite(str(tmp_path / "clean.png"), to8(img - 10.0))
    args = ("--camera", tmp_path / "camera.json", "--plane", tmp_path / "plane.json")
    assert run(tmp_path / "clean.png", *args, "-o", tmp_path / "clean.csv").returncode == 0
    r = run(tmp_path / "f", *args, "-o", tmp_path / "off.csv", "--background", tmp_path / "off.png")
    assert r.returncode == 0, r.stderr
    diff = tmp_path / "diff.png"
    cv2.imwrite(str(diff), cv2.subtract(cv2.imread(str(tmp_path / "f" / "a.png"), 0), cv2.imread(str(tmp_path / "off.png"), 0)))
    assert run(diff, *args, "-o", tmp_path / "diff.csv").returncode == 0
    clean, off, alone = (read_cloud(tmp_path / f"{n}.csv") for n in ("clean", "off", "diff"))
    row = lambda rec: np.rint(rec["v"].astype(float)).astype(int)  # noqa: E731
    u_clean = dict(zip(row(clean), clean["u"].astype(float)))
    in_band = np.isin(row(alone), rows)
    assert np.median([u_clean[v] - uu for v, uu in zip(row(alone)[in_band], alone["u"][in_band])]) > 0.1
    kept = row(off)
    assert not np.isin(kept, rows[3:-3]).any()            # the band's rows are dropped ...
    outside = ~np.isin(kept, np.arange(90, 210))
    assert outside.sum() > 250 and max(abs(u_clean[v] - uu) for v, uu in zip(kept[outside], off["u"][outside])) < 0.02
    text = (tmp_path / "off.csv").read_text()
    assert "on uneven reflectance" in text and "on uneven reflectance" in r.stderr + r.stdout  # ... and counted
