"""The live page as a user sees it: ``lightplane live`` on the simulated sensor, the page opened in a headless
Chromium (Debian's, driven over its DevTools protocol; nothing is downloaded).  The page shows the live image
and the profile and keeps updating them; a stripe setting changed on the page changes the engine's; a short
recording and a short scan started from the page leave their files.  The screenshot it takes is the README's
(written to docs/images/live.png when LIGHTPLANE_UPDATE_SCREENSHOTS=1)."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import pytest

pytest.importorskip("uvicorn", reason="the live extra (starlette, uvicorn, websockets) is not installed")
pytest.importorskip("websockets", reason="the live extra (starlette, uvicorn, websockets) is not installed")

from _chromium import Chromium, find_chromium, poll  # noqa: E402

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
UPDATE_SCREENSHOT = os.environ.get("LIGHTPLANE_UPDATE_SCREENSHOTS") == "1"


def _get(url: str) -> dict:
    with urllib.request.urlopen(url, timeout=10) as r:
        return json.load(r)


class LiveCommand:
    """``lightplane live`` in a subprocess; its URL from the line it prints."""

    def __init__(self, args: list[str], env: dict):
        self.proc = subprocess.Popen([sys.executable, "-m", "lightplane", "live", *args], stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, env=env)
        self.lines: list[str] = []
        self.err: list[str] = []
        threading.Thread(target=self._pump, args=(self.proc.stdout, self.lines), daemon=True).start()
        threading.Thread(target=self._pump, args=(self.proc.stderr, self.err), daemon=True).start()

    @staticmethod
    def _pump(stream, into: list[str]) -> None:
        for line in stream:
            into.append(line)

    def url(self, timeout: float = 120) -> str:
        def found():
            if self.proc.poll() is not None:
                raise AssertionError(f"lightplane live exited {self.proc.returncode}: {''.join(self.err)[-800:]}")
            m = re.search(r"http://\S+/", "".join(self.lines))
            return m.group(0) if m else None
        return poll(found, timeout, "the URL line of lightplane live")

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode


@pytest.fixture
def chromium_exe():
    exe = find_chromium()
    if exe is None:
        pytest.skip("headless Chromium is not installed (chromium / google-chrome not on PATH)")
    return exe


def test_target_drawn_on_the_live_image(chromium_exe, tmp_path):
    """The circle target of the simulated target scene, found when the page asks for it, drawn on the image."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")])}
    live = LiveCommand(["--source", "sim:target,scale=0.5", "--port", "0", "--output-dir", str(tmp_path / "out")], env)
    page = None
    try:
        url = live.url()
        page = Chromium(chromium_exe, tmp_path / "profile", size=(1200, 900))
        page.open(url)
        page.wait_for("window.lpState && lpState.previews >= 2 && lpState.settings", 300, "the live image")
        assert page.js("lpState.targets") == 0  # not looked for until asked
        page.js("(() => { const el = document.getElementById('set-target'); el.click(); })()")
        poll(lambda: _get(url + "api/settings")["target"] is True, 10, "the engine's target setting")
        page.wait_for("lpState.targets >= 2", 30, "the target's ellipse on the image")
        assert page.js("lpState.errors") == []
    finally:
        if page is not None:
            page.close()
        live.stop()


def _change_setting(page: Chromium, name: str, value) -> None:
    """Type a value into the settings form and leave the field, as a user does."""
    page.js(f"(() => {{ const el = document.getElementById('set-{name}'); el.focus(); el.value = {json.dumps(str(value))};"
            " el.dispatchEvent(new Event('change', {bubbles: true})); el.blur(); })()")


def test_live_page_in_headless_chromium(chromium_exe, tmp_path):
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")])}
    live = LiveCommand(["--source", "sim:turntable", "--hardware", "sim", "--port", "0", "--output-dir", str(out)],
                       env)
    page = None
    try:
        url = live.url()
        assert url.startswith("http://127.0.0.1:")
        page = Chromium(chromium_exe, tmp_path / "profile", size=(1400, 1500))
        page.open(url)
        # the live image and the profile arrive, and keep coming
        page.wait_for("window.lpState && lpState.previews >= 2 && lpState.profiles >= 2", 300,
                      "image and profile")  # the first run compiles the kernels
        f1 = page.js("lpState.lastProfileFrame")
        page.wait_for(f"lpState.lastProfileFrame > {f1} && lpState.previews >= 4", 20, "a newer profile")
        assert page.js("lpState.stripePoints") > 100  # stripe centres drawn on the image
        assert page.js("lpState.units") == "mm"  # the simulated sensor's own calibration: millimetres
        assert page.js("document.getElementById('fps').textContent") not in ("", "–")
        # a stripe setting changed on the page is the engine's
        name, value = "width_px", 4.5  # the stripe's width: estimated until set
        assert page.js("lpState.settings").get(name) != value
        _change_setting(page, name, value)
        poll(lambda: _get(url + "api/settings")[name] == value, 10, f"the engine's {name} to become {value}")
        assert page.js("lpState.errors") == []
        # a short recording
        page.js("document.getElementById('rec-folder').value = 'rec1'; document.getElementById('rec-start').click()")
        page.wait_for("!document.getElementById('rec-stop').disabled", 10, "recording")
        time.sleep(1.0)
        page.js("document.getElementById('rec-stop').click()")
        page.wait_for("document.querySelectorAll('#rec-files li').length > 0", 30, "the recording's files")
        rec = [p for p in (out / "rec1").rglob("*") if p.is_file()]
        assert rec and all(p.stat().st_size > 0 for p in rec), rec
        # a short scan, its cloud growing on the page
        steps, step = (36, 10) if UPDATE_SCREENSHOT else (4, 90)  # the README's picture: a finer scan
        page.js(f"document.getElementById('scan-steps').value = {steps}; "
                f"document.getElementById('scan-step').value = {step};"
                "document.getElementById('scan-folder').value = 'scan1'; document.getElementById('scan-start').click()")
        page.wait_for("lpState.scan && lpState.scan.state === 'done'", 120 + 10 * steps, "the scan to finish")
        page.wait_for("lpState.cloudPoints > 100", 10, "the scan's cloud")
        files = [p for p in (out / "scan1").rglob("*") if p.is_file()]
        assert any(p.suffix == ".ply" for p in files), files
        assert page.js("lpState.errors") == []
        assert page.js("document.documentElement.scrollWidth") <= 1400  # nothing wider than the window
        if UPDATE_SCREENSHOT:  # the README's picture: the rates after the scan's renders, not during them
            poll(lambda: _get(url + "api/status")["fps"] > 25, 90, "the simulated sensor's rate after the scan")
            time.sleep(1.0)
        shot = page.screenshot(tmp_path / "live.png")
        if UPDATE_SCREENSHOT:
            (ROOT / "docs" / "images").mkdir(exist_ok=True)
            shutil.copy(shot, ROOT / "docs" / "images" / "live.png")
        import cv2

        img = cv2.imread(str(shot))
        assert img is not None and img.shape[1] == 1400 and img.std() > 10
    finally:
        if page is not None:
            page.close()
        code = live.stop()
    assert code in (0, 143, -15), "".join(live.err)[-800:]

