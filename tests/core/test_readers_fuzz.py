"""No traceback on any file lightplane reads: every reader, given a valid file mutated at random
(a value replaced by any JSON value, a huge number, NaN, a string; a key dropped; the bytes
truncated, overwritten or UTF-16 encoded), returns a valid object or raises LightplaneError --
never another exception (property-based, hypothesis)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lightplane.camera.model import Camera
from lightplane.camera.targets import Target
from lightplane.core.errors import LightplaneError
from lightplane.measure.sensor import Sensor, import_fabscan
from lightplane.motion.model import Motion, Turntable, load_rigid
from lightplane.plane.model import CameraDependence, LightPlane

SETTINGS = settings(max_examples=60, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

CAM = Camera(K=[[1300.0, 0, 610.0], [0, 1302.0, 820.0], [0, 0, 1]], dist=[0.1, -0.2, 0.001, -0.002, 0.05],
             width=1232, height=1640,
             covariance=np.diag([4.0, 4.0, 1.0, 1.0, 1e-4, 1e-3, 1e-6, 1e-6, 1e-2]),
             covariance_params=("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"))
PLANE = LightPlane([0.8, 0.0, -0.6], -80.0, np.diag([1e-6, 1e-6, 1e-6, 0.01]),
                   meta={CameraDependence.KEY: CameraDependence(
                       tuple(CAM.covariance_params or ()), np.full((4, 9), 1e-3), np.diag([1e-7] * 3 + [1e-3]),
                       "finite differences").to_dict()})
TABLE = Turntable.from_axis([-5.0, 40.0, 130.0], [0.0, -1.0, 0.01], covariance=np.diag([1.0] * 3 + [1e-6] * 3),
                            camera=CAM.to_dict(), counts_per_rev=3200)


def _fabscan() -> dict:
    return {"calibration": {"camera_matrix": CAM.K.tolist(), "distortion_vector": CAM.dist.tolist(),
                            "laser_planes": [{"normal": [0.8, 0.0, 0.6], "distance": 80.0, "deviation": 0.05}],
                            "platform_translation": [-5.0, 40.0, 130.0],
                            "platform_rotation": [[0, 1, 0], [0, 0, -1], [-1, 0, 0]]},
            "camera": {"resolution": {"width": 1640, "height": 1232}, "rotate": "True", "hflip": "True",
                       "vflip": "False"},
            "turntable": {"steps": 3200, "radius": 70}}


# --------------------------------------------------------------------------- mutations
JUNK = st.one_of(
    st.none(), st.booleans(), st.integers(-2**70, 2**70), st.just(10**400),
    st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([1e300, -1e300, 1e308, 1e-300, 0.0, -1.0]),
    st.text(max_size=8), st.sampled_from(["abc", "1e400", "nan", "", "True"]),
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=5),
    st.lists(st.lists(st.integers(-3, 3), max_size=4), max_size=4),
    st.dictionaries(st.text(max_size=4), st.integers(), max_size=3))


def _paths(obj, prefix=()):
    """Every path (tuple of keys / indices) into a nested JSON value."""
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _paths(v, prefix + (i,))


def _mutated(doc, path, value, drop: bool):
    doc = json.loads(json.dumps(doc))
    if not path:
        return value
    parent = doc
    for k in path[:-1]:
        parent = parent[k]
    if drop and isinstance(parent, dict):
        del parent[path[-1]]
    else:
        parent[path[-1]] = value
    return doc


@st.composite
def json_mutations(draw, doc: dict):
    """A JSON document: ``doc`` with one to three values replaced or dropped."""
    for _ in range(draw(st.integers(1, 3))):
        paths = list(_paths(doc))
        path = draw(st.sampled_from(paths))
        doc = _mutated(doc, path, draw(JUNK), draw(st.booleans()))
    return doc


@st.composite
def byte_mutations(draw, data: bytes):
    """``data`` truncated, overwritten with random bytes, or re-encoded as UTF-16."""
    how = draw(st.sampled_from(["truncate", "overwrite", "insert", "utf16", "random"]))
    if how == "truncate":
        return data[:draw(st.integers(0, len(data)))]
    if how == "utf16":
        return data.decode("utf-8").encode("utf-16")
    if how == "random":
        return draw(st.binary(max_size=200))
    i = draw(st.integers(0, len(data)))
    junk = draw(st.binary(min_size=1, max_size=16))
    return data[:i] + junk + data[i + (len(junk) if how == "overwrite" else 0):]


NUMBER = re.compile(rb"-?\d+(?:\.\d*)?(?:e[-+]?\d+)?")
TOKENS = st.sampled_from([b"abc", b"1e400", b"1e300", b"-1e300", b"nan", b"inf", b"", b"-1", b"0", b"1.5",
                          b"99999999999", b"\"x\"", b"[1, 2]", b"{}", b"1e-300"])


@st.composite
def token_mutations(draw, data: bytes):
    """``data`` with one to three of its numbers replaced by a junk token."""
    for _ in range(draw(st.integers(1, 3))):
        spans = [m.span() for m in NUMBER.finditer(data)]
        if not spans:
            break
        a, b = draw(st.sampled_from(spans))
        data = data[:a] + draw(TOKENS) + data[b:]
    return data


def _read_or_refuse(reader, path: Path, kind) -> None:
    """The property: a valid object, or LightplaneError (anything else propagates and fails the test)."""
    try:
        obj = reader(path)
    except LightplaneError as e:
        assert str(e) and "\n" not in str(e), repr(e)
        return
    assert isinstance(obj, kind)


# --------------------------------------------------------------------------- the readers
@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


JSON_READERS = {
    "camera": (Camera.load, Camera, lambda: CAM.to_dict()),
    "plane": (LightPlane.load, LightPlane, lambda: PLANE.to_dict()),
    "turntable": (Turntable.load, Turntable, lambda: TABLE.to_dict()),
    "sensor": (Sensor.load, Sensor, lambda: Sensor(CAM, {"laser0": PLANE}, TABLE, None, 90).to_dict()),
    "sensor_flange": (Sensor.load, Sensor, lambda: Sensor(CAM, {"laser0": PLANE}, None,
                                                          (np.eye(3), np.array([1.0, 2.0, 3.0]))).to_dict()),
    "target": (Target.load, Target, lambda: Target("charuco", 8, 6, 11.0, 8.0, "DICT_4X4_50").to_dict()),
    "fabscan": (import_fabscan, Sensor, _fabscan),
    "flange": (load_rigid, tuple, lambda: {"T_flange_cam": {"translation_mm": [1.0, 2.0, 3.0],
                                                            "quaternion_xyzw": [0.0, 0.0, 0.0, 1.0]}}),
}


@pytest.mark.parametrize("name", list(JSON_READERS))
def test_valid_json_files_read(work, name):
    reader, kind, doc = JSON_READERS[name]
    f = work / f"{name}.json"
    f.write_text(json.dumps(doc()))
    assert isinstance(reader(f), kind)


@pytest.mark.parametrize("name", list(JSON_READERS))
@SETTINGS
@given(data=st.data())
def test_json_readers_never_raise_anything_else(work, name, data):
    reader, kind, doc = JSON_READERS[name]
    f = work / f"{name}_m.json"
    if data.draw(st.booleans()):
        f.write_text(json.dumps(data.draw(json_mutations(doc()))))
    else:
        f.write_bytes(data.draw(byte_mutations(json.dumps(doc()).encode())))
    _read_or_refuse(reader, f, kind)


def _camera_text(fmt: str, work: Path) -> bytes:
    f = work / {"ros": "c_ros.yaml", "opencv_yaml": "c_cv.yml", "opencv_xml": "c_cv.xml"}[fmt]
    CAM.save(f, fmt="ros" if fmt == "ros" else "opencv", force=True)
    return f.read_bytes()


@pytest.mark.parametrize("fmt", ["ros", "opencv_yaml", "opencv_xml"])
@SETTINGS
@given(data=st.data())
def test_camera_text_formats_never_raise_anything_else(work, fmt, data):
    text = _camera_text(fmt, work)
    f = work / f"m_{fmt}{'.xml' if fmt.endswith('xml') else '.yaml'}"
    how = data.draw(st.sampled_from(["tokens", "bytes", "structure"] if fmt == "ros" else ["tokens", "bytes"]))
    if how == "tokens":
        f.write_bytes(data.draw(token_mutations(text)))
    elif how == "bytes":
        f.write_bytes(data.draw(byte_mutations(text)))
    else:
        f.write_text(yaml.safe_dump(data.draw(json_mutations(yaml.safe_load(text)))))
    _read_or_refuse(Camera.load, f, Camera)


CSV_READERS = {
    "poses": (lambda p: Motion.load_poses(p), "frame,x,y,z,qx,qy,qz,qw\n0,1.5,2,3,0,0,0,1\n1,1.5,2,4,0,0,0.7071068,0.7071068\n"),
    "angles": (lambda p: Motion.load_turntable_angles(p, TABLE), "angle_deg\n0\n22.5\n45\n"),
    "counts": (lambda p: Motion.load_turntable_angles(p, TABLE), "frame,counts\n0,0\n1,200\n2,400\n"),
    "positions": (lambda p: Motion.load_positions(p), "dx,dy,dz\n0,0,0\n0.5,0,0\n1.0,0,0\n"),
}


@pytest.mark.parametrize("name", list(CSV_READERS))
@SETTINGS
@given(data=st.data())
def test_csv_readers_never_raise_anything_else(work, name, data):
    reader, text = CSV_READERS[name]
    f = work / f"{name}.csv"
    f.write_text(text)
    assert isinstance(reader(f), Motion)
    mutate = data.draw(st.sampled_from([token_mutations, byte_mutations]))
    f.write_bytes(data.draw(mutate(text.encode())))
    _read_or_refuse(reader, f, Motion)
