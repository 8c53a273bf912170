"""The FabScanPi turntable (real photographs; skipped without ../shared/data/fabscan).

``import-fabscan`` reads FabScan's configuration into a sensor file; the turntable's
axis from the 17 lit board frames of the calibration sequence (frames 67, 70, ... 115,
the table turned between them), with FabScan's own published camera (the frame its
platform pose refers to), against FabScan's published platform pose.  Measured (this
test's data, docs: README §Turntables): 0.33 deg between the axis directions, the
published platform centre 1.02 mm from our axis (mostly along the optical axis), the
table's mean step 3.585 deg (64 of its 6400 motor steps are 3.6 deg).
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from lightplane.core.io import read_image
from lightplane.measure.sensor import Sensor, import_fabscan
from lightplane.camera.targets import parse_target
from lightplane.motion.turntable import calibrate_turntable

pytestmark = pytest.mark.realdata


@pytest.fixture(scope="module")
def fabscan(shared_data):
    root = shared_data / "fabscan"
    if not root.is_dir():
        pytest.skip(f"real-data test: {root} is absent")
    return root


def test_import_fabscan_config(fabscan, tmp_path):
    cfg = json.loads((fabscan / "fabscan-config.json").read_text())["calibration"]
    s = import_fabscan(fabscan / "fabscan-config.json")
    assert (s.camera.width, s.camera.height, s.rotate_deg) == (1232, 1640, 90)
    assert np.allclose(s.camera.K, cfg["camera_matrix"]) and np.allclose(s.camera.dist, cfg["distortion_vector"])
    p = s.planes["laser0"]
    assert np.allclose(p.normal, np.array(cfg["laser_planes"][0]["normal"]) / np.linalg.norm(cfg["laser_planes"][0]["normal"]))
    assert np.isclose(p.d, -cfg["laser_planes"][0]["distance"], atol=1e-4)
    assert np.allclose(s.turntable.point_mm, cfg["platform_translation"])
    assert abs(s.turntable.direction @ np.asarray(cfg["platform_rotation"])[:, 2]) > 0.9999
    assert s.turntable.counts_per_rev == 6400
    r = subprocess.run([sys.executable, "-m", "lightplane", "import-fabscan", fabscan / "fabscan-config.json", "-o",
                        tmp_path / "s.json"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    back = Sensor.load(tmp_path / "s.json")
    assert back.rotate_deg == 90 and list(back.planes) == ["laser0"] and back.turntable is not None
    assert "provenance" in json.loads((tmp_path / "s.json").read_text())


def test_turntable_axis_against_fabscans_platform_pose(fabscan):
    cfg = json.loads((fabscan / "fabscan-config.json").read_text())["calibration"]
    sensor = import_fabscan(fabscan / "fabscan-config.json")
    files = [fabscan / "calibration_8x10" / f"calibration_{i:03d}.jpg" for i in range(67, 118, 3)]
    imgs = [read_image(f, rotate_deg=90) for f in files]
    cal = calibrate_turntable(imgs, sensor.camera, parse_target("chessboard:10x8", 7.0), names=[f.name for f in files])
    assert len([im for im in cal.images if im["used"]]) == 17
    angles = np.array([im["angle_deg"] for im in cal.images])
    assert abs(np.ptp(angles) / 16 - 3.6) < 0.05  # 16 steps of 64 motor steps (3.6 deg) each
    tt = cal.turntable
    published_axis = np.asarray(cfg["platform_rotation"])[:, 2]
    ang = np.degrees(np.arccos(abs(tt.direction @ published_axis)))
    v = np.asarray(cfg["platform_translation"]) - tt.point_mm
    off = np.linalg.norm(v - (v @ tt.direction) * tt.direction)
    assert ang < 0.5 and off < 1.5, (ang, off)  # measured 0.33 deg, 1.02 mm
    # circles and rotations: 0.17 deg and 0.22 mm apart on these photographs
    assert cal.agreement_deg < 0.5 and cal.agreement_mm < 1.0
