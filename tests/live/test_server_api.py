"""The live page's API over a scripted engine: what each endpoint returns, how it refuses bad requests (a 4xx
status and one sentence), the websocket's rates, the page's assets (all shipped, nothing from the internet)."""

from __future__ import annotations

import dataclasses
import queue
import re
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("starlette")
pytest.importorskip("httpx")

with warnings.catch_warnings():  # starlette's note that its test client will move to httpx2
    warnings.simplefilter("ignore")
    from starlette.testclient import TestClient  # noqa: E402

from lightplane.core.errors import LightplaneError  # noqa: E402
from lightplane.live.server import ServerOptions, create_app, jsonable, output_folder, ApiError  # noqa: E402
from lightplane.live.source import SimulatedHardware  # noqa: E402


@dataclasses.dataclass(frozen=True)
class Settings:
    threshold: float = 20.0
    channel: str = "red"


class ScriptedEngine:
    """The engine's interface with scripted answers: the test says what it holds and sees what the API did."""

    def __init__(self, hardware=None):
        self.hardware = hardware
        self._settings = Settings()
        self.profile = None
        self.subscribers: list[queue.Queue] = []
        self.calls: list[tuple] = []
        self.points = np.arange(30, dtype=float).reshape(10, 3)
        self.scanning = False

    def start(self):
        self.calls.append(("start",))

    def stop(self):
        self.calls.append(("stop",))

    def status(self):
        return {"source": "scripted", "fps": 61.25, "latency_ms": {"median": 7.5, "p99": 12.0}, "dropped": 3,
                "frames": 100, "points": 5, "units": "px", "recording": False, "scan": None}

    def latest_profile(self):
        return self.profile

    def latest_preview(self, max_width=640):
        return b"\xff\xd8jpeg", {"scale": max_width / 1280, "stripe_uv": np.array([[1.234, 2.0]]), "target": None}

    def settings(self):
        return self._settings

    def update_settings(self, **changes):
        if changes.get("threshold", 0) < 0:
            raise LightplaneError("threshold must be >= 0")
        self._settings = dataclasses.replace(self._settings, **changes)
        return self._settings

    def subscribe(self):
        q: queue.Queue = queue.Queue()
        self.subscribers.append(q)
        return q

    def unsubscribe(self, q):
        self.subscribers.remove(q)

    def start_recording(self, folder):
        self.calls.append(("record", folder))

    def stop_recording(self):
        return {"profiles": Path("/x/profiles.parquet")}

    def start_scan(self, kind, steps, step, folder):
        self.calls.append(("scan", kind, steps, step, folder))
        self.scanning = True

    def scan_status(self):
        return {"state": "running" if self.scanning else "idle", "done": 0, "total": 3}

    def scan_points(self, since=0):
        return self.points[since:]


@pytest.fixture
def engine():
    return ScriptedEngine(SimulatedHardware(n_lasers=2))


@pytest.fixture
def client(engine, tmp_path):
    with TestClient(create_app(engine, ServerOptions(output_dir=tmp_path, sensor_name="s.json"))) as c:
        yield c


def _error(r, status: int, pattern: str) -> None:
    assert r.status_code == status, r.text
    msg = r.json()["error"]
    assert re.search(pattern, msg), msg
    assert "\n" not in msg and len(msg) < 200


def test_app_starts_and_stops_the_engine(engine, tmp_path):
    with TestClient(create_app(engine, ServerOptions(output_dir=tmp_path))):
        assert engine.calls == [("start",)]
    assert engine.calls == [("start",), ("stop",)]


def test_status_profile_preview(client, engine):
    s = client.get("/api/status").json()
    assert s["fps"] == 61.25 and s["latency_ms"] == {"median": 7.5, "p99": 12.0} and s["dropped"] == 3
    assert s["hardware"] == {"lasers": [False, False], "n_lasers": 2, "turntable": True, "angle_deg": 0.0,
                             "stage": False, "position_mm": None}
    assert s["sensor"] == "s.json"
    _error(client.get("/api/profile"), 503, "no profile yet")
    engine.profile = {"frame": 7, "t_exposure": 1.5, "units": "mm", "x": np.array([1.0, np.nan]),
                      "z": np.array([100.0, 101.0]), "sigma_mm": np.array([0.01, 0.02])}
    p = client.get("/api/profile").json()
    assert p == {"frame": 7, "t_exposure": 1.5, "units": "mm", "x": [1.0, None], "z": [100.0, 101.0],
                 "sigma_mm": [0.01, 0.02]}
    r = client.get("/api/preview.jpg?max_width=320")
    assert r.status_code == 200 and r.headers["content-type"] == "image/jpeg" and r.content == b"\xff\xd8jpeg"
    j = client.get("/api/preview?max_width=640").json()
    assert j["scale"] == 0.5 and j["stripe_uv"] == [[1.23, 2.0]] and j["jpeg_base64"] == "/9hqcGVn"
    _error(client.get("/api/preview?max_width=abc"), 400, "max_width.*integer")
    _error(client.get("/api/preview?max_width=4"), 400, "max_width must be 16 to 8192")


def test_settings(client, engine):
    assert client.get("/api/settings").json() == {"threshold": 20.0, "channel": "red"}
    assert client.post("/api/settings", json={"threshold": 5}).json()["threshold"] == 5
    assert engine.settings().threshold == 5
    _error(client.post("/api/settings", json={"threshold": -1}), 400, "^threshold must be >= 0$")
    _error(client.post("/api/settings", json={"nope": 1}), 400, "unknown setting 'nope'.*threshold, channel")
    _error(client.post("/api/settings", json={}), 400, "names no setting")
    _error(client.post("/api/settings", content=b"{not json"), 400, "not valid JSON")
    _error(client.post("/api/settings", json=[1, 2]), 400, "must be a JSON object")
    assert engine.settings().threshold == 5  # nothing refused changed anything


def test_lasers_and_turntable(client, engine):
    assert client.post("/api/laser", json={"index": 1, "on": True}).json() == {"lasers": [False, True]}
    assert client.post("/api/laser", json={"index": "all", "on": True}).json() == {"lasers": [True, True]}
    assert engine.hardware.laser_states() == (True, True)
    _error(client.post("/api/laser", json={"index": 2, "on": True}), 400, "laser index must be 0 to 1")
    _error(client.post("/api/laser", json={"index": 0}), 400, "needs the field 'on'")
    _error(client.post("/api/laser", json={"on": "yes"}), 400, "'on' must be a true/false")
    assert client.post("/api/turntable", json={"degrees": 12.5}).json() == {"angle_deg": 12.5}
    assert engine.hardware.angle_deg == 12.5
    _error(client.post("/api/turntable", json={"degrees": True}), 400, "'degrees' must be a number")
    _error(client.post("/api/turntable", json={"degrees": 1e6}), 400, "within \\+-3600")
    _error(client.get("/api/turntable"), 405, "GET is not allowed on /api/turntable")
    _error(client.post("/api/stage", json={"mm": 1}), 409, "no linear stage")


def test_stage(tmp_path):
    hw = SimulatedHardware(has_turntable=False, stage_direction=(1.0, 0.0, 0.0))
    with TestClient(create_app(ScriptedEngine(hw), ServerOptions(output_dir=tmp_path))) as c:
        assert c.post("/api/stage", json={"mm": 2.5}).json() == {"position_mm": 2.5}
        assert c.post("/api/stage", json={"mm": -1}).json() == {"position_mm": 1.5}
        assert c.get("/api/status").json()["hardware"]["position_mm"] == 1.5
        _error(c.post("/api/stage", json={"mm": "far"}), 400, "'mm' must be a number")


def test_no_hardware(tmp_path):
    with TestClient(create_app(ScriptedEngine(None), ServerOptions(output_dir=tmp_path))) as c:
        assert c.get("/api/status").json()["hardware"] is None
        _error(c.post("/api/laser", json={"on": True}), 409, "no lasers or turntable")
    with TestClient(create_app(ScriptedEngine(SimulatedHardware(has_turntable=False)),
                               ServerOptions(output_dir=tmp_path))) as c:
        _error(c.post("/api/turntable", json={"degrees": 1}), 409, "no turntable")


def test_record_and_scan(client, engine, tmp_path):
    r = client.post("/api/record", json={"action": "start", "folder": "run1"}).json()
    assert r == {"recording": True, "folder": str(tmp_path / "run1")} and engine.calls[-1] == ("record", tmp_path / "run1")
    assert client.post("/api/record", json={"action": "stop"}).json() == {
        "recording": False, "files": {"profiles": "/x/profiles.parquet"}}
    r = client.post("/api/record", json={"action": "start"}).json()
    assert re.fullmatch(r"record-\d{8}-\d{6}", Path(r["folder"]).name)
    for bad in ("../up", "/abs", "a/b", ".hidden", "x" * 101, ""):
        if bad:
            _error(client.post("/api/record", json={"action": "start", "folder": bad}), 400, "plain name")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "f").write_text("x")
    _error(client.post("/api/record", json={"action": "start", "folder": "full"}), 409, "not empty")
    _error(client.post("/api/record", json={"action": "pause"}), 400, "action must be")
    s = client.post("/api/scan", json={"kind": "turntable", "steps": 3, "step": 10, "folder": "scan1"}).json()
    assert s["state"] == "running" and engine.calls[-1] == ("scan", "turntable", 3, 10.0, tmp_path / "scan1")
    # the scan drives the hardware: no one else does meanwhile
    _error(client.post("/api/turntable", json={"degrees": 5}), 409, "a scan is running")
    _error(client.post("/api/laser", json={"on": False}), 409, "a scan is running")
    _error(client.post("/api/scan", json={"kind": "spiral", "steps": 3, "step": 1}), 400, "kind must be")
    _error(client.post("/api/scan", json={"kind": "linear", "steps": 0, "step": 1}), 400, "steps must be 1 to")
    _error(client.post("/api/scan", json={"kind": "linear", "steps": 2.5, "step": 1}), 400, "'steps' must be a number")
    _error(client.post("/api/scan", json={"kind": "linear", "steps": 2, "step": 0}), 400, "step must not be 0")
    p = client.get("/api/scan/points?since=8").json()
    assert p == {"since": 8, "count": 2, "next": 10, "units": "mm", "points": list(map(float, range(24, 30)))}
    _error(client.get("/api/scan/points?since=-1"), 400, "since must be >= 0")


def test_unknown_paths(client):
    _error(client.get("/api/nothing"), 404, "no such page or endpoint: /api/nothing")


def test_websocket_rates(client, engine):
    with client.websocket_connect("/api/ws") as ws:
        ws.send_json({"profile_hz": 5, "status_hz": 1000})
        first = ws.receive_json()
        assert first["type"] == "status" and first["fps"] == 61.25
        q = engine.subscribers[0]
        t0 = time.monotonic()
        frames = []
        for k in range(60):  # 60 profiles in 1.2 s; 5 a second get through, the latest each time
            q.put({"type": "profile", "frame": k, "units": "px", "u": np.array([1.0]), "v": np.array([2.0])})
            if k == 30:
                q.put({"type": "scan", "state": "done"})
            time.sleep(0.02)
        events = []
        while time.monotonic() - t0 < 1.6:
            m = ws.receive_json()
            events.append(m["type"])
            if m["type"] == "profile":
                frames.append(m["frame"])
        assert "scan" in events  # other events are never thinned
        assert 4 <= len(frames) <= 10 and frames == sorted(frames), frames
    time.sleep(0.1)
    assert engine.subscribers == []  # the client went: unsubscribed


def test_host_guard(engine, tmp_path):
    app = create_app(engine, ServerOptions(output_dir=tmp_path, allowed_hosts=("127.0.0.1", "testserver")))
    with TestClient(app) as c:
        assert c.get("/api/status").status_code == 200
        assert c.get("/api/status", headers={"host": "evil.example"}).status_code == 400


def test_page_assets_ship_in_the_package(client):
    html = client.get("/").text
    assets = re.findall(r'(?:src|href)="([^"]+)"', html)
    assert {"app.js", "style.css"} <= set(assets)
    for a in assets:
        if a.startswith("data:"):
            continue
        r = client.get("/" + a)
        assert r.status_code == 200 and len(r.content) > 500, a
        # nothing from elsewhere: no absolute URL, no @import or url() of another host
        assert not re.search(r"https?://|//[a-z0-9.-]+\.[a-z]{2,}/", r.text), a
    assert not re.search(r"https?://", html)


def test_options_and_helpers(tmp_path):
    with pytest.raises(LightplaneError, match="profile_hz"):
        ServerOptions(profile_hz=0)
    with pytest.raises(LightplaneError, match="preview_width"):
        ServerOptions(preview_width=5)
    assert jsonable({"a": np.float32(1.5), "b": float("inf"), "c": Path("/p"), "d": (np.int64(2),)}) == {
        "a": 1.5, "b": None, "c": "/p", "d": [2]}
    with pytest.raises(ApiError):
        output_folder(tmp_path, "..", "x")
    a = output_folder(tmp_path, None, "rec")
    a.mkdir()
    assert output_folder(tmp_path, None, "rec") != a  # a second one in the same second gets its own folder
