"""Physical limits on what is read (docs/conventions.md §Limits on what is read): each bad number
is refused by its reader with one LightplaneError line naming the file and the field, and the
command line turns it into one line on stderr and exit status 2; the limits themselves are
placed where the docs say (a value just inside passes, just outside fails)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from lightplane.camera.model import (FOV_RANGE_DEG, MAX_LENS_SCALE, PRINCIPAL_POINT_MARGIN, Camera, check_camera_file,
                                     lens_defect)
from lightplane.core.checks import covariance, integer, number, unit_vector
from lightplane.core.errors import LightplaneError
from lightplane.measure.sensor import Sensor, import_fabscan
from lightplane.motion.model import MAX_TURNTABLE_DEG, Motion, Turntable
from lightplane.plane.model import MIN_PLANE_DISTANCE_MM, LightPlane

CAM = Camera(K=[[1000.0, 0, 640.0], [0, 1000.0, 480.0], [0, 0, 1]], dist=[-0.1, 0.01, 0.0, 0.0, 0.0], width=1280,
             height=960)
PLANE = LightPlane([0.8, 0.0, -0.6], -80.0, np.diag([1e-6, 1e-6, 1e-6, 0.01]))
TABLE = Turntable.from_axis([-5.0, 40.0, 130.0], [0.0, -1.0, 0.0], camera=CAM.to_dict())


def run(*args):
    """The command line in this process: (exit status, stderr lines)."""
    from typer.testing import CliRunner

    from lightplane.cli import app

    r = CliRunner().invoke(app, [str(a) for a in args], env={"COLUMNS": "200"})
    return r.exit_code, [ln for ln in r.stderr.splitlines() if ln.strip()]


def refused_by_cli(args, *needles: str) -> None:
    code, lines = run(*args)
    assert code == 2 and len(lines) == 1 and lines[0].startswith("lightplane: error:"), (code, lines)
    for n in needles:
        assert n in lines[0], (n, lines[0])


def _write(path: Path, doc) -> Path:
    path.write_text(json.dumps(doc))
    return path


def _camera(**changes) -> dict:
    d = CAM.to_dict()
    for k, v in changes.items():
        if k in ("fx", "fy", "cx", "cy", "skew"):
            i, j = {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2), "skew": (0, 1)}[k]
            d["K"][i][j] = v
        elif k == "k1":
            d["dist"][0] = v
        else:
            d[k] = v
    return d


@pytest.fixture
def files(tmp_path):
    CAM.save(tmp_path / "cam.json")
    PLANE.save(tmp_path / "plane.json")
    return tmp_path


# --------------------------------------------------------------------------- camera
@pytest.mark.parametrize("change, needles", [
    ({"fx": 1e300}, ("'K'", "fx = 1e+300", "field of view")),
    ({"cx": 1e12}, ("'K'", "cx = 1e+12", "principal point")),
    ({"skew": 1e9}, ("'K'", "skew")),
    ({"k1": 1e6}, ("'dist'", "magnifies")),
    ({"k1": -1e6}, ("'dist'", "one-to-one")),
    ({"width": "abc"}, ("'width'", "integer", "'abc'")),
    ({"width": 1280.5}, ("'width'", "integer")),
    ({"height": True}, ("'height'", "integer")),
    ({"covariance": (-np.eye(9)).tolist(), "covariance_params": ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"]},
     ("'covariance'", "negative variance")),
    ({"covariance": np.eye(9).tolist(), "covariance_params": ["fx", "fy", "cx", "cy", "a", "b", "c", "d", "e"]},
     ("'covariance_params'",)),
    ({"rms_px": float("nan")}, ("'rms_px'", "finite")),
])
def test_bad_camera_json_refused_naming_the_field(files, change, needles):
    f = _write(files / "bad.json", _camera(**change))
    with pytest.raises(LightplaneError) as e:
        Camera.load(f)
    assert str(e.value).startswith(f"{f}: ") and "\n" not in str(e.value)
    for n in needles:
        assert n in str(e.value), (n, str(e.value))
    refused_by_cli(["sensor", "-o", files / "s.json", "--camera", f, "--plane", files / "plane.json"], str(f), *needles)


def _opencv_text(tmp_path: Path, suffix: str) -> str:
    f = tmp_path / f"c{suffix}"
    CAM.save(f, fmt="opencv" if suffix in (".xml", ".yml") else "ros")
    return f.read_text()


@pytest.mark.parametrize("suffix", [".xml", ".yml", ".yaml"])
def test_image_width_abc_refused_in_every_camera_format(files, suffix):
    text = _opencv_text(files, suffix)
    old = "<image_width>1280</image_width>" if suffix == ".xml" else "image_width: 1280"
    assert old in text
    f = files / f"bad{suffix}"
    f.write_text(text.replace(old, "<image_width>abc</image_width>" if suffix == ".xml" else 'image_width: "abc"'))
    with pytest.raises(LightplaneError, match=r"field 'image_width' must be an integer, got 'abc'"):
        Camera.load(f)
    refused_by_cli(["sensor", "-o", files / "s.json", "--camera", f, "--plane", files / "plane.json"], "image_width")


@pytest.mark.parametrize("suffix", [".xml", ".yml"])
def test_truncated_filestorage_refused(files, suffix):
    text = _opencv_text(files, suffix)
    f = files / f"cut{suffix}"
    f.write_text(text[:len(text) // 2])
    with pytest.raises(LightplaneError, match="not a valid OpenCV FileStorage file"):
        Camera.load(f)
    refused_by_cli(["sensor", "-o", files / "s.json", "--camera", f, "--plane", files / "plane.json"],
                   "not a valid OpenCV FileStorage file")


def test_camera_limits_are_where_the_docs_put_them():
    lo, hi = FOV_RANGE_DEG
    w = CAM.width

    def cam(fx=1000.0, cx=640.0, skew=0.0, dist=(0, 0, 0, 0, 0)):
        return Camera([[fx, skew, cx], [0, 1000.0, 480.0], [0, 0, 1]], list(dist), w, 960)

    # the horizontal field of view over w px with the principal point centred: 2 atan(w / 2 fx)
    for fov, ok in ((lo * 1.01, True), (lo * 0.99, False), (hi - 0.1, True), (hi + 0.1, False)):
        fx = (w / 2) / np.tan(np.radians(fov) / 2)
        c = cam(fx=fx, cx=(w - 1) / 2)
        if ok:
            check_camera_file(c, "c")
        else:
            with pytest.raises(LightplaneError, match="field of view"):
                check_camera_file(c, "c")
    m = PRINCIPAL_POINT_MARGIN * w
    check_camera_file(cam(cx=w - 0.5 + 0.99 * m), "c")
    with pytest.raises(LightplaneError, match="principal point cx"):
        check_camera_file(cam(cx=w - 0.5 + 1.01 * m), "c")
    with pytest.raises(LightplaneError, match="principal point cx"):
        check_camera_file(cam(cx=-0.5 - 1.01 * m), "c")
    check_camera_file(cam(skew=99.0), "c")
    with pytest.raises(LightplaneError, match="skew"):
        check_camera_file(cam(skew=101.0), "c")


def test_lens_check_folds_and_magnification():
    """The radial map r -> r (1 + k1 r²) of a plumb bob (k1 < 0) folds at r_f = 1 / sqrt(-3 k1) (its
    derivative 1 + 3 k1 r² vanishes there), where the image radius peaks at 2 r_f / 3: refused when
    that peak lies inside the ellipse inscribed in the image (0.64 focal lengths across here: the
    image beyond is reached by no ray), accepted beyond it; for k1 > 0 its magnification 1 + 3 k1 r²
    at the ellipse is held to MAX_LENS_SCALE."""
    def cam(k1):
        return Camera([[1000.0, 0, 639.5], [0, 1000.0, 479.5], [0, 0, 1]], [k1, 0, 0, 0, 0], 1280, 960)

    r_edge = 0.64  # half the width over fx: the ellipse's horizontal semi-axis, normalised
    fold_inside = -1 / (3 * (1.5 * 0.97 * r_edge) ** 2)
    fold_outside = -1 / (3 * (1.5 * 1.03 * r_edge) ** 2)
    assert "one-to-one" in lens_defect(cam(fold_inside))
    assert lens_defect(cam(fold_outside)) is None
    # magnification at the ellipse's horizontal end: 1 + 3 k1 r², r the undistorted radius there
    for scale, ok in ((0.9 * MAX_LENS_SCALE, True), (1.2 * MAX_LENS_SCALE, False)):
        # r (1 + k1 r²) = r_edge and 1 + 3 k1 r² = scale: r = 3 r_edge / (scale + 2)
        r = 3 * r_edge / (scale + 2)
        k1 = (scale - 1) / (3 * r * r)
        assert (lens_defect(cam(k1)) is None) == ok, (scale, lens_defect(cam(k1)))
    # FabScanPi's calibration folds at 0.69 fx, beyond the ellipse but before its corners: accepted
    fab = Camera([[1319.597, 0, 625.54], [0, 1322.35, 808.36], [0, 0, 1]], [0.145, 0.154, -0.006, 0.006, -1.15],
                 1232, 1640)
    assert lens_defect(fab) is None


# --------------------------------------------------------------------------- plane
@pytest.mark.parametrize("change, needles", [
    ({"d": -0.001}, ("'d'", "0.001 mm from the plane")),
    ({"normal": [0.8, 0.0, -0.7]}, ("'normal'", "unit vector")),
    ({"covariance": (-np.diag([1e-6, 1e-6, 1e-6, 0.01])).tolist()}, ("'covariance'", "negative variance")),
    ({"covariance": np.diag([1e-6, 1e-6, 1e-6, 1e300]).tolist()}, ("'covariance'", "standard deviation")),
    ({"covariance": [[1e-6, 1.0, 0, 0], [1.0, 1e-6, 0, 0], [0, 0, 1e-6, 0], [0, 0, 0, 0.01]]},
     ("'covariance'", "not a covariance")),
    ({"d": float("nan")}, ("'d'", "finite")),
])
def test_bad_plane_refused_naming_the_field(files, change, needles):
    d = PLANE.to_dict()
    d.update(change)
    f = _write(files / "bad_plane.json", d)
    with pytest.raises(LightplaneError) as e:
        LightPlane.load(f)
    for n in needles:
        assert n in str(e.value), (n, str(e.value))
    refused_by_cli(["sensor", "-o", files / "s.json", "--camera", files / "cam.json", "--plane", f], *needles)


def test_plane_limits():
    base = PLANE.to_dict()
    for off, ok in ((1.01 * MIN_PLANE_DISTANCE_MM, True), (0.99 * MIN_PLANE_DISTANCE_MM, False)):
        d = dict(base, d=-off)
        if ok:
            assert LightPlane.from_dict(d, "p").d == pytest.approx(-off)
        else:
            with pytest.raises(LightplaneError, match="from the plane"):
                LightPlane.from_dict(d, "p")
    # a normal off unit by less than 1e-6 is renormalised; by more, refused
    n = np.array([0.8, 0.0, -0.6]) * (1 + 5e-7)
    assert np.linalg.norm(LightPlane.from_dict(dict(base, normal=n.tolist()), "p").normal) == pytest.approx(1, abs=1e-15)
    with pytest.raises(LightplaneError, match="unit vector"):
        LightPlane.from_dict(dict(base, normal=(n * (1 + 2e-6)).tolist()), "p")


# --------------------------------------------------------------------------- motion files
@pytest.fixture
def measure_args(files):
    return ["measure", files / "none.png", "--camera", files / "cam.json", "--plane", files / "plane.json", "-o",
            files / "o.ply"]


def test_huge_pose_translation_refused(files, measure_args):
    f = files / "poses.csv"
    f.write_text("x,y,z,qx,qy,qz,qw\n0,0,0,0,0,0,1\n1e300,0,0,0,0,0,1\n")
    with pytest.raises(LightplaneError, match=r"row 3: translation x,y,z 1e\+300 mm is beyond"):
        Motion.load_poses(f)
    refused_by_cli([*measure_args, "--poses", f], "poses.csv", "translation")


def test_huge_turntable_angle_refused(files, measure_args):
    TABLE.save(files / "table.json")
    f = files / "angles.csv"
    f.write_text("angle_deg\n0\n1e308\n")
    with pytest.raises(LightplaneError, match="turntable angle"):
        Motion.load_turntable_angles(f, TABLE)
    refused_by_cli([*measure_args, "--turntable", files / "table.json", "--turntable-angles", f], "angles.csv",
                   "turntable angle")
    f.write_text(f"angle_deg\n0\n{MAX_TURNTABLE_DEG}\n")  # the limit itself passes
    assert Motion.load_turntable_angles(f, TABLE).n_frames == 2


def test_huge_positions_refused(files):
    f = files / "positions.csv"
    f.write_text("dx,dy,dz\n0,0,0\n0,0,2e6\n")
    with pytest.raises(LightplaneError, match="position"):
        Motion.load_positions(f)


@pytest.mark.parametrize("change, needle", [
    ({"camera": "cam.json"}, "'camera'"),
    ({"direction": [0.0, -2.0, 0.0]}, "'direction'"),
    ({"point_mm": [0.0, 0.0, 1e300]}, "'point_mm'"),
    ({"counts_per_rev": "3200"}, "'counts_per_rev'"),
    ({"covariance": (-np.eye(6)).tolist()}, "'covariance'"),
])
def test_bad_turntable_refused(files, change, needle):
    d = TABLE.to_dict()
    d.update(change)
    f = _write(files / "bad_table.json", d)
    with pytest.raises(LightplaneError, match=needle):
        Turntable.load(f)
    refused_by_cli(["sensor", "-o", files / "s.json", "--camera", files / "cam.json", "--plane", files / "plane.json",
                    "--turntable", f], needle)


# --------------------------------------------------------------------------- sensor and FabScan
@pytest.mark.parametrize("change, needle", [
    ({"frames": "rotated"}, "'frames'"),
    ({"frames": {"rotate_deg": "90"}}, "'frames.rotate_deg'"),
    ({"flange": "hand_eye.json"}, "'flange'"),
    ({"planes": {"laser0": "plane.json"}}, "'plane'"),
])
def test_bad_sensor_refused(files, change, needle):
    d = Sensor(CAM, {"laser0": PLANE}).to_dict()
    d.update(change)
    f = _write(files / "bad_sensor.json", d)
    with pytest.raises(LightplaneError, match=needle):
        Sensor.load(f)
    refused_by_cli(["measure", "--sensor", f, "--laser", "laser0=none/*.png", "-o", files / "o.ply"], needle)


def _fabscan() -> dict:
    return {"calibration": {"camera_matrix": CAM.K.tolist(), "distortion_vector": CAM.dist.tolist(),
                            "laser_planes": [{"normal": [0.8, 0.0, 0.6], "distance": 80.0, "deviation": 0.05}],
                            "platform_translation": [-5.0, 40.0, 130.0],
                            "platform_rotation": [[0, 1, 0], [0, 0, -1], [-1, 0, 0]]},
            "camera": {"resolution": {"width": 1280, "height": 960}, "rotate": "False", "hflip": "False",
                       "vflip": "False"},
            "turntable": {"steps": 3200, "radius": 70}}


@pytest.mark.parametrize("where, value, needle", [
    (("camera", "resolution"), "1280x960", "'camera.resolution'"),
    (("camera", "resolution", "width"), "1280", "'camera.resolution.width'"),
    (("calibration", "laser_planes"), 5, "'calibration.laser_planes'"),
    (("calibration", "laser_planes", 0), "plane", "'calibration.laser_planes[0]'"),
    (("calibration", "laser_planes", 0, "normal"), "abc", "'calibration.laser_planes[0].normal'"),
    (("calibration", "laser_planes", 0, "distance"), 0.0001, "from the plane"),
    (("calibration", "distortion_vector"), [1e6, 0, 0, 0, 0], "'calibration.distortion_vector'"),
    (("calibration", "camera_matrix"), [[1e300, 0, 640], [0, 1000, 480], [0, 0, 1]], "'calibration.camera_matrix'"),
    (("calibration", "platform_translation"), "abc", "'calibration.platform_translation'"),
    (("calibration", "platform_rotation"), [[1, 2], [3, 4]], "'calibration.platform_rotation'"),
    (("turntable",), "x", "'turntable'"),
    (("turntable", "steps"), "abc", "'turntable.steps'"),
])
def test_malformed_fabscan_fields_refused(files, where, value, needle):
    cfg = _fabscan()
    node = cfg
    for k in where[:-1]:
        node = node[k]
    node[where[-1]] = value
    f = _write(files / "fabscan.json", cfg)
    with pytest.raises(LightplaneError, match=needle.replace("[", r"\[").replace("]", r"\]")):
        import_fabscan(f)
    refused_by_cli(["import-fabscan", f, "-o", files / "s.json"], needle)


def test_good_fabscan_reads(files):
    s = import_fabscan(_write(files / "fabscan.json", _fabscan()))
    assert s.turntable is not None and s.turntable.counts_per_rev == 3200
    assert np.allclose(s.planes["laser0"].normal, [0.8, 0.0, 0.6]) and s.planes["laser0"].d == pytest.approx(-80.0)


# --------------------------------------------------------------------------- the shared checks
def test_shared_checks():
    assert integer(1280.0, "w", "f") == 1280 and integer(np.int64(3), "w", "f") == 3
    for bad in (1.5, "12", True, None, float("inf"), [1]):
        with pytest.raises(LightplaneError, match="'w' must be an integer"):
            integer(bad, "w", "f")
    with pytest.raises(LightplaneError, match="within"):
        integer(0, "w", "f", lo=1)
    assert number(10**400 // 10**399, "x", "f") == 10.0
    for bad in (10**400, float("nan"), "1.0", False):
        with pytest.raises(LightplaneError, match="'x'"):
            number(bad, "x", "f")
    assert np.allclose(unit_vector([0, 0, 1 + 1e-7], "n", "f"), [0, 0, 1])
    C = np.array([[4.0, 1.9], [1.9, 1.0]])  # correlation 0.95
    assert np.array_equal(covariance(C.tolist(), "c", "f", 2), C)
    with pytest.raises(LightplaneError, match="not a covariance"):
        covariance([[4.0, 2.1], [2.1, 1.0]], "c", "f", 2)  # correlation 1.05
    with pytest.raises(LightplaneError, match="not a covariance"):
        covariance([[4.0, 1.0], [0.0, 1.0]], "c", "f", 2)  # not symmetric
    with pytest.raises(LightplaneError, match="not a covariance"):
        covariance([[0.0, 1e-9], [1e-9, 1.0]], "c", "f", 2)  # a fixed parameter correlated with another
    # positive semi-definite: a 3x3 whose pairwise correlations are each possible but not together
    with pytest.raises(LightplaneError, match="positive semi-definite"):
        covariance([[1, -0.9, -0.9], [-0.9, 1, -0.9], [-0.9, -0.9, 1]], "c", "f", 3)
