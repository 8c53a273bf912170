"""Several lasers: selectors, two planes from the same circle-target images, bad input.

The two-laser render: the default sensor's laser (red) and a second one turned 90 degrees
about the optical axis (green, ``second_laser_plane``), both stripes crossing the disc in
every image, colour images (each channel its own noise).  Rendered once per renderer
version (cached like test_calibrate_images' renders): 6 images, ~20 s on 2 loaded cores.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from _cli import lightplane as run, one_error_line as _bad

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.stripe.lasers import output_paths, parse_laser, parse_lasers
from lightplane.plane.model import LightPlane
from _renders import cached_render

N_IMAGES = 6


def mirrored_plane() -> LightPlane:
    """A second laser on the other side of the camera (x -> -x), crossing the optical axis at the
    same 450 mm: nearer than that its stripe is right of the image centre, the first one's left
    (FabScan's two lasers)."""
    from lightplane.simulate.scene import default_plane

    p = default_plane()
    return LightPlane(np.array([-p.normal[0], p.normal[1], p.normal[2]]), p.d)


def cached_two_laser_render(n: int = N_IMAGES, seed: int = 5, difficulty: str = "realistic",
                            kind: str = "crossed") -> Path:
    """``crossed``: colour images, the second laser turned 90 deg (stripes crossing on the disc);
    ``mirrored``: gray images, the mirrored laser, discs at 395-435 mm (the stripes apart, one
    each side of the image centre)."""
    import lightplane.simulate.render as R

    def make():
        if kind == "crossed":
            return R.render_circle_dataset(n, seed, R.CircleOptions(difficulty=difficulty, more_planes=(R.second_laser_plane(),)))
        return R.render_circle_dataset(n, seed, R.CircleOptions(difficulty=difficulty, more_planes=(mirrored_plane(),),
                                                          colour=False, distance_mm=(395.0, 435.0)))

    return cached_render(f"circle2_{kind}_{difficulty}_n{n}_s{seed}", make)


@pytest.fixture(scope="module")
def render():
    folder = cached_two_laser_render()
    truth = json.loads((folder / "truth.json").read_text())
    files = [folder / im["file"] for im in truth["images"]]
    planes = [LightPlane.from_dict(las["plane"]) for las in truth["lasers"]]
    return folder, Camera.load(folder / "camera.json"), planes, files, truth


@pytest.fixture(scope="module")
def two_planes(render):
    from lightplane.plane.calibrate import PlaneCalibrationOptions, calibrate_planes

    _, cam, _, files, _ = render
    return calibrate_planes(files, cam, 50.0, parse_lasers(["a=red", "b=green"]), options=PlaneCalibrationOptions(workers=1))


# ----------------------------------------------------------------------------- selectors
def test_selectors_parse():
    s = parse_laser("left=red")
    assert (s.name, s.channel, s.region, s.frames, s.cycle) == ("left", "red", None, None, None)
    s = parse_laser("r=640,0,1280,960")
    assert s.region == (640.0, 0.0, 1280.0, 960.0) and s.channel is None
    s = parse_laser("l1=cycle:2")
    assert s.cycle == 2
    s = parse_laser("x=frames:*_b.png+green+0,0,10,10")
    assert (s.frames, s.channel, s.region) == ("*_b.png", "green", (0.0, 0.0, 10.0, 10.0))
    assert s.takes_file("/a/img_3_b.png") and not s.takes_file("/a/img_3_a.png")
    assert parse_laser("q=0,0,10,10").in_region(np.array([[0, 0], [9.9, 9.9], [10, 5]])).tolist() == [True, True, False]
    # the command's --channel colours the lasers that name none
    a, b = parse_lasers(["a=0,0,5,5", "b=5,0,10,5"], channel="red")
    assert a.channel == b.channel == "red"
    assert parse_lasers(None) is None


@pytest.mark.parametrize("texts, needle", [
    (["a=purple"], "unknown selector 'purple'"),
    (["a"], "NAME=SELECTOR"),
    (["a=1,2,3"], "four numbers"),
    (["a=5,0,1,10"], "empty"),
    (["a=cycle:0"], "K >= 1"),
    (["a/b=red"], "name"),
    (["a=red", "a=green"], "given twice"),
    (["a=0,0,100,100", "b=50,50,200,200"], "overlap"),
    (["a=red", "b=red"], "same stripe"),
    (["a=0,0,100,100", "b=gray"], "same stripe"),
])
def test_bad_selectors(texts, needle):
    with pytest.raises(LightplaneError, match=needle):
        parse_lasers(texts)


def test_non_overlapping_and_separable_selectors():
    # touching regions, different colours, or different frames: fine
    assert len(parse_lasers(["a=0,0,100,100", "b=100,0,200,100"])) == 2
    assert len(parse_lasers(["a=red", "b=green"])) == 2
    assert len(parse_lasers(["a=frames:*_a.png", "b=frames:*_b.png"])) == 2
    assert len(parse_lasers(["a=cycle:1", "b=cycle:2"])) == 2


def test_output_paths(tmp_path):
    o = tmp_path / "plane.json"
    assert output_paths(o, ["a"]) == {"a": o}
    assert output_paths(o, ["a", "b"]) == {"a": tmp_path / "plane_a.json", "b": tmp_path / "plane_b.json"}
    assert output_paths(tmp_path / "{laser}.json", ["a", "b"])["b"] == tmp_path / "b.json"


# ----------------------------------------------------------------------------- two lasers, one target
def test_two_planes_from_the_same_placements_match_the_truth(render, two_planes):
    """Both planes against the exact truth, with the README's one-laser bars (normal
    0.01 deg, offset at the optical axis 0.02 mm, RMS triangulation over 380-520 mm 0.02 mm),
    and within 4 sigma of each plane's own predicted uncertainty (the covariance from the
    measured rim and stripe noise).  Measured (6 images, seed 5): angle 0.0035 / 0.0046 deg,
    offset -0.0012 / -0.0002 mm, triangulation 0.0036 / 0.0052 mm."""
    from lightplane.plane.calibrate import uncertainty_summary
    from lightplane.plane.uncertainty import rms_point_sigma_mm, rms_triangulation_error_mm, working_volume_grid

    _, cam, truths, _, _ = render
    for (name, cal), true in zip(two_planes.items(), truths):
        assert cal.n_used == N_IMAGES, [o.reason for o in cal.images]
        pl = cal.plane
        angle = float(np.degrees(pl.angle_to(true)))
        offset = float(pl.signed_distance(true.point_on_axis()[None])[0])
        vol = working_volume_grid(cam, true)
        tri = rms_triangulation_error_mm(cam, pl, true, vol)
        unc = uncertainty_summary(cal, cam)
        s_angle = float(np.hypot(*unc["normal_sigma_deg"]))
        s_axis = unc["point_sigma_axis_mm"]
        s_tri = rms_point_sigma_mm(cam, pl, vol, covariance=cal.covariance)
        print(f"\nlaser {name}: angle {angle:.4f} deg (sigma {s_angle:.4f}), offset {offset:+.4f} mm "
              f"(sigma {s_axis:.4f}), triangulation {tri:.4f} mm (sigma {s_tri:.4f})")
        assert angle < 0.01 and angle < 4 * s_angle
        assert abs(offset) < 0.02 and abs(offset) < 4 * s_axis
        assert tri < 0.02 and tri < 4 * s_tri


def test_same_ellipse_and_rim_for_both_lasers(render, two_planes):
    """The same placements: per image both lasers' observations hold the very same rim points
    (found once, with the points near either stripe left out) and different stripes; each
    solve refines the target poses with its own stripe, and they agree to well within the
    pose noise (measured: centres <= 0.003 mm, normals <= 0.002 deg apart; bars 0.02 mm,
    0.01 deg, the single-laser circle-pose bars of README's image-processing table / 2.5)."""
    from lightplane.cli.calibrate_plane import shared_pose_lines

    _, cam, _, _, truth = render
    a, b = two_planes["a"], two_planes["b"]
    for oa, ob, t in zip(a.images, b.images, truth["images"]):
        assert np.array_equal(oa.rim_uv, ob.rim_uv) and oa.source == ob.source
        # each laser's stripe points on its own true chord (speckle: ~0.2 px per point)
        for o, k in ((oa, "laser0"), (ob, "laser1")):
            p, q = cam.project(np.array(t["chords_mm"][k]), distort=False)
            d = (q - p) / np.linalg.norm(q - p)
            off = (cam.undistort_points(o.stripe_raw_uv) - p) @ np.array([-d[1], d[0]])
            assert abs(np.mean(off)) < 0.15 and np.max(np.abs(off)) < 1.5, (o.source, k)
        pa, pb = oa.placement.pose, ob.placement.pose
        assert np.linalg.norm(pa.center - pb.center) < 0.02
        assert np.degrees(np.arccos(min(1.0, pa.normal @ pb.normal))) < 0.01
    (line,) = shared_pose_lines(two_planes)
    assert f"{N_IMAGES} placements" in line and "mm apart" in line


def test_image_without_one_lasers_stripe_is_skipped_for_that_laser(render):
    """A colour image whose green channel shows no stripe (replaced by the laser-free blue
    channel) is skipped for laser b with the reason, and still used for laser a."""
    from lightplane.plane.calibrate import PlaneCalibrationOptions, calibrate_planes
    from lightplane.core.io import read_image

    _, cam, _, files, _ = render
    imgs = [read_image(f) for f in files[:4]]
    imgs[1] = imgs[1].copy()
    imgs[1][:, :, 1] = imgs[1][:, :, 0]
    cals = calibrate_planes(imgs, cam, 50.0, parse_lasers(["a=red", "b=green"]), "global", PlaneCalibrationOptions(workers=1))
    assert [o.used for o in cals["a"].images] == [True] * 4
    assert [o.used for o in cals["b"].images] == [True, False, True, True]
    assert cals["b"].images[1].reason == "no stripe crossing the target"
    # a laser whose stripe is in no image: an error naming it, nothing solved
    with pytest.raises(LightplaneError, match="laser c .blue.: its stripe was found in none of its 4 images"):
        calibrate_planes(imgs, cam, 50.0, parse_lasers(["a=red", "c=blue"]), "global", PlaneCalibrationOptions(workers=1))


# ----------------------------------------------------------------------------- command line
def test_cli_two_lasers_one_file_each(render, two_planes, tmp_path):
    folder, _, _, files, _ = render
    out = tmp_path / "plane.json"
    r = run("calibrate-plane", *files, "--camera", folder / "camera.json", "--diameter", "50", "-o", out,
            "--laser", "a=red", "--laser", "b=green", "--workers", "1")
    assert r.returncode == 0, r.stderr
    assert "laser a (red)" in r.stdout and "laser b (green)" in r.stdout and "placements lasers a and b share" in r.stdout
    for name in ("a", "b"):
        d = json.loads((tmp_path / f"plane_{name}.json").read_text())
        assert d["laser"] == name
        assert [x["name"] for x in d["provenance"]["options"]["lasers"]] == ["a", "b"]
        pl = LightPlane.load(tmp_path / f"plane_{name}.json")
        assert np.allclose(pl.coefficients, two_planes[name].plane.coefficients, atol=1e-9)
    assert not out.exists()


@pytest.mark.parametrize("lasers, needle", [
    (["a=red", "b=mauve"], "unknown selector 'mauve'"),
    (["a=0,0,700,960", "b=600,0,1280,960"], "overlap"),
    (["a=red", "c=blue"], "laser c (blue): its stripe was found in none"),
])
def test_cli_bad_lasers_exit_2_nothing_written(render, tmp_path, lasers, needle):
    folder, _, _, files, _ = render
    args = [x for s in lasers for x in ("--laser", s)]
    r = run("calibrate-plane", *files[:3], "--camera", folder / "camera.json", "--diameter", "50",
            "-o", tmp_path / "plane.json", "--method", "global", "--workers", "1", *args)
    _bad(r, needle)
    assert list(tmp_path.iterdir()) == []


def test_cli_colour_selector_on_gray_images(tmp_path):
    from _renders import cached_circle_render

    folder = cached_circle_render()
    r = run("calibrate-plane", folder / "circle_000.png", "--camera", folder / "camera.json", "--diameter", "50",
            "-o", tmp_path / "p.json", "--laser", "a=red", "--laser", "b=green")
    _bad(r, "laser a is told apart by its colour (red)", "no colour channels")
    assert list(tmp_path.iterdir()) == []


def test_frames_selector_gives_each_laser_its_images(render):
    """``frames:`` parts: each laser gets the images whose names match; images shared by both
    are observed once for both (same rim points), the others for one laser only."""
    from lightplane.plane.calibrate import PlaneCalibrationOptions, calibrate_planes

    _, cam, _, files, _ = render
    # circle_000's red chord lies at the target's rim; the points read there are not the stripe
    # (11.6 mm off the plane the other images agree on): the calibration refuses it by name rather
    # than using it (the green laser's images 2-5 are refused likewise)
    with pytest.raises(LightplaneError, match=r"suspect light plane.*circle_000\.png"):
        calibrate_planes(files, cam, 50.0, parse_lasers(["a=red+frames:circle_00[0-3].png"]), "global",
                         PlaneCalibrationOptions(workers=1))
    with pytest.raises(LightplaneError, match=r"suspect light plane"):
        calibrate_planes(files, cam, 50.0, parse_lasers(["b=green+frames:circle_00[2-5].png"]), "global",
                         PlaneCalibrationOptions(workers=1))
    # the selector itself: the planes kept as they are (their quality record says so)
    sels = parse_lasers(["a=red+frames:circle_00[0-3].png", "b=green+frames:circle_00[2-5].png"])
    cals = calibrate_planes(files, cam, 50.0, sels, "global", PlaneCalibrationOptions(workers=1, keep_suspect=True))
    assert [Path(o.source).name for o in cals["a"].images] == [f"circle_00{i}.png" for i in range(4)]
    assert [Path(o.source).name for o in cals["b"].images] == [f"circle_00{i}.png" for i in range(2, 6)]
    # an image is used or skipped with its reason (a chord at the rim, a stripe with too few points
    # are skipped, never used with wrong points); each laser keeps enough images for its plane
    assert all(o.used or o.reason for c in cals.values() for o in c.images)
    assert all(sum(o.used for o in c.images) >= 3 for c in cals.values())
    assert np.array_equal(cals["a"].images[2].rim_uv, cals["b"].images[0].rim_uv)
    with pytest.raises(LightplaneError, match=re.escape("laser c (green+frames:none_*.png): none of the 6 images is "
                                                        "one of its frames")):
        calibrate_planes(files, cam, 50.0, parse_lasers(["a=red", "c=green+frames:none_*.png"]), options=PlaneCalibrationOptions(workers=1))


def test_two_stripes_told_apart_by_region():
    """Gray images, two lasers on either side of the camera (FabScan-like), discs nearer than
    where the planes cross: the left half of the image is one laser's, the right half the
    other's.  5 images: the bars of test_calibrate_images' 5-image check (0.03 deg, 0.06 mm,
    0.06 mm: the 12-image bars scaled by sqrt(12/5) and doubled) and 4 sigma of the predicted
    uncertainty.  Measured: left 5/5 used, 0.0011 deg, -0.0025 mm, 0.0062 mm; right 4/5 (its
    chord in circle_000 is 0.42 of the diameter, at the rim: "no stripe crossing the target"),
    0.0057 deg, -0.0003 mm, 0.0090 mm."""
    from lightplane.plane.calibrate import PlaneCalibrationOptions, calibrate_planes, uncertainty_summary
    from lightplane.plane.uncertainty import rms_point_sigma_mm, rms_triangulation_error_mm, working_volume_grid

    folder = cached_two_laser_render(n=5, seed=4, kind="mirrored")
    truth = json.loads((folder / "truth.json").read_text())
    cam = Camera.load(folder / "camera.json")
    files = [folder / im["file"] for im in truth["images"]]
    half = f"{cam.cx:.0f}"
    sels = parse_lasers([f"left=0,0,{half},{cam.height}", f"right={half},0,{cam.width},{cam.height}"])
    cals = calibrate_planes(files, cam, 50.0, sels, options=PlaneCalibrationOptions(workers=1))
    for (name, cal), las in zip(cals.items(), truth["lasers"]):
        true = LightPlane.from_dict(las["plane"])
        assert cal.n_used >= 4, [o.reason for o in cal.images]
        for o in cal.images:  # every used stripe is the laser's own, on its own side
            if o.used:
                assert np.all(sels[0 if name == "left" else 1].in_region(o.stripe_raw_uv))
        angle = float(np.degrees(cal.plane.angle_to(true)))
        offset = float(cal.plane.signed_distance(true.point_on_axis()[None])[0])
        vol = working_volume_grid(cam, true)
        tri = rms_triangulation_error_mm(cam, cal.plane, true, vol)
        unc = uncertainty_summary(cal, cam)
        s_tri = rms_point_sigma_mm(cam, cal.plane, vol, covariance=cal.covariance)
        print(f"\nlaser {name}: {cal.n_used} used, angle {angle:.4f} deg, offset {offset:+.4f} mm, "
              f"triangulation {tri:.4f} mm (sigma {s_tri:.4f})")
        assert angle < 0.03 and angle < 4 * float(np.hypot(*unc["normal_sigma_deg"]))
        assert abs(offset) < 0.06 and abs(offset) < 4 * unc["point_sigma_axis_mm"]
        assert tri < 0.06 and tri < 4 * s_tri


@pytest.mark.parametrize("extra, needle", [
    (["--cycle", "P,L,L", "--laser", "a=cycle:1", "--laser", "b=cycle:3"], "has only 2 laser frame(s) per pose"),
    (["--laser", "a=cycle:1", "--laser", "b=cycle:2"], "cycle:K needs --cycle or --pattern"),
    (["--cycle", "P,L,L", "--laser", "a=cycle:1", "--laser", "b=frames:nothing_*.png"],
     "b=frames:nothing_*.png: none of the 4 laser frames is one of its frames"),
    (["--laser", "a=0,0,700,960", "--laser", "b=600,0,1280,960"], "overlap"),
    (["--laser", "a=infrared"], "unknown selector 'infrared'"),
])
def test_board_cli_bad_lasers_exit_2_nothing_written(render, tmp_path, extra, needle):
    """calibrate-plane-board: selectors that cannot work are refused before any image is read."""
    folder, _, _, files, _ = render
    r = run("calibrate-plane-board", *files, "--camera", folder / "camera.json", "--board", "9x6", "--square", "10",
            "-o", tmp_path / "plane.json", *extra)
    _bad(r, needle)
    assert list(tmp_path.iterdir()) == []
