"""The guided calibration's API over the real engine on the simulated circle target: a scripted user puts the
target where the guide says (3 mm and 3° off) and takes each placement, until the guide says the target σ is
reached; the σ after each placement falls and the outline of the next placement lies in the image."""

from __future__ import annotations

import warnings

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

pytestmark = pytest.mark.slow  # ~30 s: the simulated target rendered at each placement


def test_guide_api_with_a_simulated_user(tmp_path):
    sim = SimulatedSensor("target", fps=30.0, scale=0.5)
    with TestClient(create_app(LiveEngine(sim), ServerOptions(output_dir=tmp_path))) as c:
        assert c.get("/api/guide").json() == {"active": False}
        r = c.post("/api/guide/accept", json={})
        assert r.status_code == 400 and "start one first" in r.json()["error"]
        assert c.post("/api/guide", json={}).status_code == 400  # the target sigma is needed
        g = c.post("/api/guide", json={"target_sigma_mm": 0.02}).json()
        assert g["active"] and g["n_placements"] == 0 and g["verdict"]["status"] == "continue"
        for _ in range(15):
            out = np.array(g["suggestion"]["outline_px"])
            assert out.shape == (72, 2) and np.all((out >= 0) & (out < [sim.camera.width, sim.camera.height]))
            assert c.post("/api/guide/simulate", json={"error_mm": 3, "error_deg": 3}).status_code == 200
            r = c.post("/api/guide/accept", json={})
            assert r.status_code == 200, r.json()
            g = r.json()
            if g["verdict"]["status"] != "continue":
                break
        assert g["verdict"]["status"] == "reached", g["verdict"]
        h = g["history_sigma_mm"]
        assert len(h) == g["n_placements"] and h[-1] <= 0.02 < h[0]
        assert c.get("/api/guide").json()["n_placements"] == g["n_placements"]
