"""Sensor files (lightplane.measure.sensor): round trip, FabScan import from a configuration written
here (the real one: test_fabscan_turntable.py), and bad files refused with a clear reason."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lightplane import Camera, LightPlane
from lightplane.core.errors import LightplaneError
from lightplane.motion.model import Turntable
from lightplane.measure.sensor import Sensor, import_fabscan

CAM = Camera(K=[[1300.0, 0, 610.0], [0, 1302.0, 820.0], [0, 0, 1]], dist=[0.1, -0.2, 0.0, 0.0, 0.0], width=1232,
             height=1640)


def _config(**camera):
    return {"calibration": {"camera_matrix": CAM.K.tolist(), "distortion_vector": CAM.dist.tolist(),
                            "laser_planes": [{"normal": [0.8, 0.0, 0.6], "distance": 80.0, "deviation": 0.05},
                                             {"normal": [-0.8, 0.0, 0.6], "distance": 70.0, "deviation": 0.04}],
                            "platform_translation": [-5.0, 40.0, 130.0],
                            "platform_rotation": [[0, 1, 0], [0, 0, -1], [-1, 0, 0]]},
            "camera": {"resolution": {"width": 1640, "height": 1232}, "rotate": "True", "hflip": "True",
                       "vflip": "False", **camera},
            "turntable": {"steps": 3200}}


def test_fabscan_config_to_sensor_and_back(tmp_path):
    f = tmp_path / "cfg.json"
    f.write_text(json.dumps(_config()))
    s = import_fabscan(f)
    assert (s.camera.width, s.camera.height, s.rotate_deg) == (1232, 1640, 90)
    assert list(s.planes) == ["laser0", "laser1"]
    assert np.allclose(s.planes["laser1"].normal, [-0.8, 0.0, 0.6]) and np.isclose(s.planes["laser1"].d, -70.0)
    assert np.allclose(s.turntable.point_mm, [-5, 40, 130]) and np.allclose(s.turntable.direction, [0, -1, 0])
    assert s.turntable.counts_per_rev == 3200
    s.save(tmp_path / "s.json")
    back = Sensor.load(tmp_path / "s.json")
    assert back.rotate_deg == 90 and list(back.planes) == ["laser0", "laser1"]
    assert np.allclose(back.turntable.direction, s.turntable.direction) and np.allclose(back.camera.K, CAM.K)
    assert np.allclose(Camera.load(tmp_path / "s.json").K, CAM.K)  # a sensor file serves as a camera file
    with pytest.raises(LightplaneError, match="no laser named 'laser7'.*laser0, laser1"):
        back.plane("laser7", "s.json")


@pytest.mark.parametrize("flags, message", [({"rotate": "True", "hflip": "False"}, "mirrors the frames"),
                                            ({"rotate": "False", "hflip": "True"}, "mirrors the frames")])
def test_fabscan_mirrored_frames_refused(tmp_path, flags, message):
    f = tmp_path / "cfg.json"
    f.write_text(json.dumps(_config(**flags)))
    with pytest.raises(LightplaneError, match=message):
        import_fabscan(f)


def test_bad_sensor_files(tmp_path):
    f = tmp_path / "x.json"
    f.write_text(json.dumps({"normal": [0, 0, 1], "d": -1}))
    with pytest.raises(LightplaneError, match="not a lightplane sensor file"):
        Sensor.load(f)
    other = Camera(K=[[1310.0, 0, 610.0], [0, 1302.0, 820.0], [0, 0, 1]], dist=CAM.dist, width=1232, height=1640)
    s = Sensor(CAM, {"a": LightPlane([1.0, 0, 0.5], -50.0)},
               Turntable.from_axis([0, 40, 130], [0, -1, 0], camera=other.to_dict()))
    s.save(tmp_path / "s.json")
    with pytest.raises(LightplaneError, match="turntable: calibrated with another camera"):
        Sensor.load(tmp_path / "s.json")
    cfg = _config()
    cfg["calibration"]["laser_planes"] = []
    f.write_text(json.dumps(cfg))
    with pytest.raises(LightplaneError, match="no calibrated laser"):
        import_fabscan(f)


@pytest.mark.parametrize("turntable", [None, {}, {"steps": None}, {"steps": 0}])
def test_fabscan_config_without_turntable_steps_imports_in_the_cli(tmp_path, turntable):
    """A configuration without the turntable's steps (or an empty one) imports; the command says the counts are
    not given (it printed a traceback after writing the file)."""
    import subprocess
    import sys

    cfg = _config()
    cfg["turntable"] = turntable
    f, out = tmp_path / "cfg.json", tmp_path / "s.json"
    f.write_text(json.dumps(cfg))
    r = subprocess.run([sys.executable, "-m", "lightplane", "import-fabscan", str(f), "-o", str(out)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    assert "counts per turn not given" in r.stdout and Sensor.load(out).turntable.counts_per_rev is None
