"""The live engine on the simulated sensor: a live scan gives the cloud ``lightplane measure`` gives from the
frames it wrote, bit for bit; the live profile agrees with the truth within its σ; status, preview,
subscribers, settings and recording."""

from __future__ import annotations

import shlex
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from lightplane.core.errors import LightplaneError
from lightplane.core.io import read_json
from lightplane.live.engine import SUBSCRIBER_QUEUE, LiveEngine, LiveSettings, plane_axes
from lightplane.live.simulated import SimulatedSensor
from lightplane.live.sources import ArraySource
from lightplane.measure.pointcloud import read_cloud


def run_cli(args: list[str], cwd: Path):
    import os

    from typer.testing import CliRunner

    from lightplane.cli import app

    old = os.getcwd()
    os.chdir(cwd)
    try:
        return CliRunner().invoke(app, args, env={"COLUMNS": "160"})
    finally:
        os.chdir(old)


def wait_for(cond, timeout: float = 30.0) -> None:
    end = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.02)


class TurnedCamera:
    """The simulated sensor's camera mounted turned: its frames rotated 90° counter-clockwise, so that a
    sensor file with ``rotate_deg`` 90 reads them upright again (as FabScan's)."""

    def __init__(self, sim: SimulatedSensor) -> None:
        self.sim, self.name, self.nominal_fps, self.hardware = sim, "turned " + sim.name, sim.nominal_fps, sim.hardware
        self.sensor = replace(sim.sensor, rotate_deg=90)

    dropped = property(lambda self: self.sim.dropped)

    def read(self, timeout=None):
        f = self.sim.read(timeout)
        return replace(f, image=np.ascontiguousarray(np.rot90(f.image)))

    def __getattr__(self, name):
        return getattr(self.sim, name)


@pytest.mark.parametrize("kind, steps, step, turned", [("turntable", 3, 40.0, False), ("linear", 3, 4.0, False),
                                                       ("turntable", 2, 40.0, True)])
def test_live_scan_gives_the_measure_cloud_bit_for_bit(tmp_path, kind, steps, step, turned):
    sim = SimulatedSensor(kind, fps=60.0, scale=0.5, lasers=2 if kind == "turntable" and not turned else 1)
    if kind == "linear":
        sim.hardware.move_stage(-step)  # start before the sheet
    eng = LiveEngine(TurnedCamera(sim) if turned else sim)
    eng.start()
    try:
        eng.start_scan(kind, steps, step, tmp_path / "scan")
        with pytest.raises(LightplaneError, match="already running"):
            eng.start_scan(kind, steps, step, tmp_path / "other")
        wait_for(lambda: eng.scan_status()["state"] != "running")
        st = eng.scan_status()
        assert st["state"] == "done" and st["done"] == steps, st
        live_points = eng.scan_points()
    finally:
        eng.stop()
    assert sim.hardware.laser_states() == (True,) + (False,) * (len(sim.true_planes) - 1)  # as before the scan
    folder = tmp_path / "scan"
    names = [f"laser{i}" for i in range(len(sim.true_planes))]
    for sub in ["pattern", *names]:
        assert sorted(p.name for p in (folder / sub).iterdir()) == [f"{k:04d}.png" for k in range(steps)]
    rec = read_json(folder / "scan.json")
    assert rec["cycle"] == ["pattern", *names] and rec["steps"] == steps
    args = shlex.split(rec["measure"])[1:]
    args[args.index("cloud.ply")] = "again.ply"
    r = run_cli(args, folder)
    assert r.exit_code == 0, r.output
    live, again = read_cloud(folder / "cloud.ply"), read_cloud(folder / "again.ply")
    assert live.dtype == again.dtype and live.size > 100 * steps
    assert live.tobytes() == again.tobytes()  # bit for bit
    assert np.array_equal(np.sort(live_points[:, 0]), np.sort(live["x"].astype(np.float64)))
    # every step's laser-off frame shows no stripe and every laser frame shows one (none is a stale frame)
    import cv2

    for k in range(steps):
        off = cv2.imread(str(folder / "pattern" / f"{k:04d}.png"), cv2.IMREAD_UNCHANGED)
        on = cv2.imread(str(folder / "laser0" / f"{k:04d}.png"), cv2.IMREAD_UNCHANGED)
        assert off.max() < 60 <= on.max(), k
        assert np.count_nonzero(live["frame"][live["laser"] == 0] == k) > 100, k
    assert on.shape == ((sim.camera.width, sim.camera.height) if turned else (sim.camera.height, sim.camera.width))


def test_live_profile_agrees_with_the_truth_within_its_sigma():
    # a clean full-size render: the stripe centres' own noise (not in sigma) stays below the plane's share
    sim = SimulatedSensor("turntable", fps=30.0, seed=1)
    eng = LiveEngine(sim)
    eng.start()
    try:
        wait_for(lambda: eng.latest_points() is not None)
        frame, p, sig = eng.latest_points()
        prof = eng.latest_profile()
    finally:
        eng.stop()
    truth = frame.meta["truth"]
    c, R = truth["sphere"]["center_mm"], truth["sphere"]["radius_mm"]
    r_sphere = np.linalg.norm(p - c, axis=1) - R
    r_table = p @ truth["table"]["normal"] + truth["table"]["d"]
    res = np.where(np.abs(r_sphere) < np.abs(r_table), r_sphere, r_table)  # off the nearer true surface
    z = res / sig
    assert len(p) > 300 and np.all(np.isfinite(z))
    assert np.percentile(np.abs(z), 95) < 3.0 and np.abs(z).max() < 4.0, (np.abs(z).max(), np.median(sig))
    # the profile event: the same points in the plane's coordinates
    o, ex, ez = plane_axes(eng.sensor.planes["laser0"])
    assert prof["units"] == "mm" and len(prof["x"]) == len(p)
    assert np.allclose(prof["x"], (p - o) @ ex) and np.allclose(prof["z"], (p - o) @ ez)
    assert np.allclose(prof["sigma_mm"], sig)
    # the estimated plane is off the true one: the test would see a profile triangulated on the wrong plane
    true_plane = truth["planes"][0]
    assert abs(eng.sensor.planes["laser0"].d - true_plane["d"]) > 1e-4


def stripe_frames(n: int = 4, h: int = 96, w: int = 128) -> list[np.ndarray]:
    v = np.arange(h, dtype=float)[:, None]
    return [np.broadcast_to(200 * np.exp(-0.5 * ((v - 40.3 - k) / 1.5) ** 2), (h, w)).astype(np.uint8)
            for k in range(n)]


def test_status_preview_subscribers_and_px_profiles():
    eng = LiveEngine(ArraySource(stripe_frames(), fps=200.0), settings=LiveSettings(axis="columns", width_px=3.5))
    slow = eng.subscribe()  # never read
    eng.start()
    try:
        wait_for(lambda: eng.status()["frames"] >= 3 * SUBSCRIBER_QUEUE)
        st = eng.status()
        prof = eng.latest_profile()
        jpeg, info = eng.latest_preview(max_width=64)
    finally:
        eng.stop()
    assert set(st) >= {"source", "fps", "latency_ms", "dropped", "frames", "points", "units", "recording", "scan"}
    assert st["units"] == "px" and st["points"] == 128 and st["fps"] > 0 and st["latency_ms"]["median"] >= 0
    assert prof is not None and prof["units"] == "px" and len(prof["u"]) == 128 and prof["sigma_mm"] is None
    k = prof["frame"] % 4
    assert np.allclose(prof["v"], 40.3 + k, atol=0.05)
    assert slow.qsize() == SUBSCRIBER_QUEUE  # full, its oldest events dropped; the loop went on
    events = [slow.get_nowait() for _ in range(SUBSCRIBER_QUEUE)]
    assert [e["frame"] for e in events] == sorted(e["frame"] for e in events)
    import cv2

    img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img.shape == (48, 64) and info["scale"] == 0.5
    assert np.allclose(np.array(info["stripe_uv"])[:, 1], (40.3 + info["frame"] % 4) * 0.5, atol=0.05)


def test_settings_checked():
    eng = LiveEngine(ArraySource(stripe_frames()))
    for bad in ({"axis": "diagonal"}, {"smooth_lines": 4}, {"roi": (0, 0, 2, 50)}, {"jpeg_quality": 5},
                {"channel": "purple"}, {"bogus": 1}, {"laser": "laser0"}):
        with pytest.raises(LightplaneError):
            eng.update_settings(**bad)
    assert eng.settings() == LiveSettings()
    assert eng.update_settings(width_px=4.0, roi=[0, 10, 128, 60]).roi == (0, 10, 128, 60)


def test_recording(tmp_path):
    import pyarrow.parquet as pq

    sim = SimulatedSensor("turntable", fps=30.0, scale=0.5)
    eng = LiveEngine(sim)
    eng.start()
    try:
        wait_for(lambda: eng.status()["frames"] > 0)
        (tmp_path / "busy").mkdir()
        (tmp_path / "busy" / "x").write_text("")
        with pytest.raises(LightplaneError, match="not an empty folder"):
            eng.start_recording(tmp_path / "busy")
        eng.start_recording(tmp_path / "rec")
        assert eng.status()["recording"]
        wait_for(lambda: eng.status()["frames"] > 8)
        files = eng.stop_recording()
    finally:
        eng.stop()
    t = pq.read_table(files["profiles"])
    assert t.schema.metadata[b"units"] == b"mm" and t.num_rows >= 1
    n_png = len(list(files["frames"].iterdir()))
    assert n_png == t.num_rows  # nothing lost at this rate
    assert sorted(int(p.stem) for p in files["frames"].iterdir()) == t.column("frame").to_pylist()
    cloud = read_cloud(files["cloud"])
    assert cloud.size == sum(len(x) for x in t.column("x").to_pylist())


def test_preview_shows_the_circle_target():
    sim = SimulatedSensor("target", fps=30.0, scale=0.5)
    sim.set_placement(1)
    eng = LiveEngine(sim, settings=LiveSettings(target=True))
    eng.start()
    try:
        wait_for(lambda: eng.latest_points() is not None)
        frame, _, _ = eng.latest_points()
        _, info = eng.latest_preview(max_width=320)
    finally:
        eng.stop()
    from lightplane.simulate.scene import TargetPlacement

    pl = frame.meta["truth"]["placement"]
    rim = sim.camera.project(TargetPlacement(pl["center_mm"], pl["normal"], pl["diameter_mm"]).rim_points(360))
    centre = (rim.min(axis=0) + rim.max(axis=0)) / 2  # the rim's image: its box's centre is the ellipse's
    t = info["target"]
    assert t is not None and info["scale"] == 0.5
    assert np.allclose(np.array(t["centre"]) / info["scale"], centre, atol=1.5)
    assert abs(t["axes"][0] / info["scale"] - np.ptp(rim, axis=0).max() / 2) < 3.0


def test_a_finite_source_ends_and_every_frame_is_profiled_or_counted(tmp_path):
    n = 40
    eng = LiveEngine(ArraySource(stripe_frames(n), fps=None, loop=False), settings=LiveSettings(width_px=3.5))
    eng.start_recording(tmp_path / "rec")
    eng.start()
    try:
        wait_for(lambda: eng.status()["ended"])
        st = eng.status()
        files = eng.stop_recording()
    finally:
        eng.stop()
    assert st["frames"] + st["dropped"] == n and st["frames"] >= 1  # as fast as it reads: some may be dropped
    import pyarrow.parquet as pq

    t = pq.read_table(files["profiles"])
    assert t.schema.metadata[b"units"] == b"px" and set(t.column_names) >= {"frame", "u", "v"}
    assert "cloud" not in files and t.num_rows == st["frames"]
    with pytest.raises(LightplaneError, match="not running"):
        eng.capture(time.monotonic(), timeout=0.1)


def test_stopping_the_engine_stops_a_scan(tmp_path):
    sim = SimulatedSensor("turntable", fps=30.0, scale=0.25)
    eng = LiveEngine(sim)
    with pytest.raises(LightplaneError, match="start the engine"):
        eng.start_scan("turntable", 3, 10.0, tmp_path / "s0")
    eng.start()
    try:
        with pytest.raises(LightplaneError, match="linear stage"):
            eng.start_scan("linear", 3, 1.0, tmp_path / "s1")
        with pytest.raises(LightplaneError, match="steps"):
            eng.start_scan("turntable", 0, 10.0, tmp_path / "s2")
        eng.start_scan("turntable", 200, 1.0, tmp_path / "s3")
        wait_for(lambda: eng.scan_status()["done"] >= 1)
    finally:
        eng.stop()
    st = eng.scan_status()
    assert st["state"] == "stopped" and 1 <= st["done"] < 200
    assert sim.hardware.laser_states() == (True,)  # the lasers as before the scan


def test_the_profile_follows_the_laser_that_is_on():
    sim = SimulatedSensor("turntable", fps=30.0, scale=0.5, lasers=2)
    eng = LiveEngine(sim)
    eng.start()
    try:
        for i, on in enumerate(((True, False), (False, True))):
            for k, v in enumerate(on):
                sim.hardware.set_laser(k, v)
            t = time.monotonic()
            wait_for(lambda: (lp := eng.latest_points()) is not None and lp[0].t_exposure > t)
            frame, p, sig = eng.latest_points()
            assert eng.latest_profile()["laser"] == f"laser{i}"
            truth = frame.meta["truth"]
            c, R = truth["sphere"]["center_mm"], truth["sphere"]["radius_mm"]
            res = np.minimum(np.abs(np.linalg.norm(p - c, axis=1) - R),
                             np.abs(p @ truth["table"]["normal"] + truth["table"]["d"]))
            assert len(p) > 100 and np.median(res) < 0.02  # on the wrong plane: millimetres off
    finally:
        eng.stop()


def test_frames_of_another_size_than_the_sensor_camera_are_reported():
    sensor = SimulatedSensor("turntable", fps=None, scale=0.25).sensor
    eng = LiveEngine(ArraySource(stripe_frames(2), fps=100.0), sensor=sensor)
    eng.start()
    try:
        wait_for(lambda: eng.status()["error"] is not None)
        st = eng.status()
    finally:
        eng.stop()
    assert st["frames"] == 0 and st["units"] == "mm" and "128" in st["error"] and "320" in st["error"], st["error"]
