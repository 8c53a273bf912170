"""The live page's API over the real engine on the simulated sensor: the profile in mm with its sigma, the
preview a JPEG of the frame with the stripe on it, a setting reaching the engine, a recording and a short
turntable scan leaving their files, the websocket streaming profiles of increasing frame number."""

from __future__ import annotations

import base64
import time
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

pytest.importorskip("starlette")
pytest.importorskip("httpx")

with warnings.catch_warnings():  # starlette's note that its test client will move to httpx2
    warnings.simplefilter("ignore")
    from starlette.testclient import TestClient  # noqa: E402

from lightplane.live.engine import LiveEngine  # noqa: E402
from lightplane.live.server import ServerOptions, create_app  # noqa: E402
from lightplane.live.simulated import SimulatedSensor  # noqa: E402


def _until(fn, timeout=120.0, what=""):
    t_end = time.monotonic() + timeout
    while True:
        v = fn()
        if v:
            return v
        assert time.monotonic() < t_end, f"timed out waiting for {what}"
        time.sleep(0.05)


def test_api_on_the_simulated_sensor(tmp_path):
    sim = SimulatedSensor("turntable", fps=30.0, scale=0.25)
    engine = LiveEngine(sim)
    with TestClient(create_app(engine, ServerOptions(output_dir=tmp_path))) as c:
        r = _until(lambda: (lambda r: r if r.status_code == 200 else None)(c.get("/api/profile")), what="a profile")
        p = r.json()
        assert p["units"] == "mm" and len(p["x"]) == len(p["z"]) == len(p["sigma_mm"]) > 20
        assert all(0 < s < 0.5 for s in p["sigma_mm"])  # one point's sigma, mm
        s = c.get("/api/status").json()
        assert s["source"] == "sim:turntable" and s["units"] == "mm" and s["hardware"]["turntable"] is True
        pv = c.get("/api/preview?max_width=160").json()
        img = cv2.imdecode(np.frombuffer(base64.b64decode(pv["jpeg_base64"]), np.uint8), cv2.IMREAD_UNCHANGED)
        assert img is not None and img.shape[1] == round(sim.camera.width * pv["scale"]) <= 160
        uv = np.array(pv["stripe_uv"])
        assert len(uv) > 20 and (uv >= 0).all() and (uv[:, 0] < img.shape[1]).all()
        assert c.post("/api/settings", json={"smooth_lines": 5}).json()["smooth_lines"] == 5
        assert engine.settings().smooth_lines == 5
        assert c.post("/api/settings", json={"jpeg_quality": 5}).status_code == 400
        with c.websocket_connect("/api/ws") as ws:
            frames = []
            while len(frames) < 3:
                m = ws.receive_json()
                if m["type"] == "profile":
                    frames.append(m["frame"])
        assert frames == sorted(set(frames))
        assert c.post("/api/record", json={"action": "start", "folder": "rec"}).status_code == 200
        time.sleep(0.5)
        files = c.post("/api/record", json={"action": "stop"}).json()["files"]
        assert {"frames", "profiles"} <= set(files)
        assert all(Path(f).exists() and Path(f).is_relative_to(tmp_path / "rec") for f in files.values())
        assert c.post("/api/scan", json={"kind": "turntable", "steps": 2, "step": 180, "folder": "scan"}).status_code \
            == 200
        st = _until(lambda: (lambda s: s if s["state"] != "running" else None)(c.get("/api/scan").json()),
                    what="the scan")
        assert st["state"] == "done", st
        pts = c.get("/api/scan/points").json()
        assert pts["count"] > 20 and pts["next"] == pts["count"] and len(pts["points"]) == 3 * pts["count"]
        assert (tmp_path / "scan" / "cloud.ply").is_file()
