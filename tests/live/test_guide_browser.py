"""The guided calibration on the live page, driven by a simulated user: ``lightplane live`` on the simulated
circle target, the page in a headless Chromium.  The user starts a guided calibration on the page, then, until
the page says the target σ is reached, puts the simulated target where the ghost outline says (off by 3 mm and
3°, through the simulated sensor's endpoint) and takes the placement with the page's button; the page draws
the ghost, lists the σ after each placement and shows the stop."""

from __future__ import annotations

import json
import os
import shutil
import urllib.request
from pathlib import Path

import pytest

from _chromium import Chromium
from test_page_browser import LiveCommand, chromium_exe  # noqa: F401  (the fixture)

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]


def _post(url: str, body: dict) -> dict:
    req = urllib.request.Request(url, data=json.dumps(body).encode(), headers={"Content-Type": "application/json"},
                                 method="POST")
    with urllib.request.urlopen(req, timeout=60) as r:
        return json.load(r)


def test_guided_calibration_in_headless_chromium(chromium_exe, tmp_path):  # noqa: F811
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")])}
    live = LiveCommand(["--source", "sim:target,scale=0.5", "--port", "0", "--output-dir", str(tmp_path / "out")], env)
    page = None
    try:
        url = live.url()
        page = Chromium(chromium_exe, tmp_path / "profile", size=(1400, 1600))
        page.open(url)
        page.wait_for("window.lpState && lpState.previews >= 2", 90, "the live image")
        page.js("document.getElementById('guide-sigma').value = '0.02'; document.getElementById('guide-start').click()")
        page.wait_for("lpState.guide && lpState.guide.active && lpState.guide.suggestion", 60, "the first ghost")
        page.wait_for("lpState.ghostsDrawn > 0", 20, "the ghost drawn on the live image")
        for k in range(1, 16):
            _post(url + "api/guide/simulate", {"error_mm": 3.0, "error_deg": 3.0})  # the user moves the target
            page.js("document.getElementById('guide-accept').click()")
            page.wait_for(f"lpState.guide.n_placements >= {k} || lpState.errors.length > 0", 120, f"placement {k}")
            assert page.js("lpState.errors") == []
            if page.js("lpState.guide.verdict.status") != "continue":
                break
            if k == 1:  # the ghost of the second placement over the live image, the first sigma listed
                drawn = page.js("lpState.ghostsDrawn")
                page.wait_for(f"lpState.ghostsDrawn > {drawn}", 20, "the next ghost")
                shot = page.screenshot(tmp_path / "guide.png")
                if os.environ.get("LIGHTPLANE_UPDATE_SCREENSHOTS") == "1":
                    (ROOT / "docs" / "images").mkdir(exist_ok=True)
                    shutil.copy(shot, ROOT / "docs" / "images" / "live-guide.png")
        g = page.js("lpState.guide")
        assert g["verdict"]["status"] == "reached", g["verdict"]
        assert g["history_sigma_mm"][-1] <= 0.02 and len(g["history_sigma_mm"]) == g["n_placements"]
        assert "target reached" in page.js("document.getElementById('guide-verdict').textContent")
        assert page.js("document.querySelectorAll('#guide-history li').length") == g["n_placements"]
        assert page.js("document.getElementById('guide-accept').disabled")
    finally:
        if page is not None:
            page.close()
        live.stop()
