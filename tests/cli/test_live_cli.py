"""``lightplane live``: a source, sensor file, hardware or address that cannot be used is one line and exit 2,
before anything is served (run in this process: the command fails before it serves)."""

from __future__ import annotations

import socket

import pytest
from typer.testing import CliRunner

from lightplane.cli import app


def _refused(*args, needles=()) -> str:
    r = CliRunner().invoke(app, ["live", *map(str, args)])
    assert r.exit_code == 2, (r.exit_code, r.output)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("lightplane: error:"), r.stderr
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)


def test_bad_inputs_one_line(tmp_path):
    _refused("--source", "sim:nope", needles=["simulated sensor kind", "'nope'"])
    _refused("--source", tmp_path / "missing.mp4", needles=["missing.mp4"])
    _refused("--source", "sim:turntable", "--sensor", tmp_path / "s.json", needles=["s.json", "no such"])
    (tmp_path / "bad.json").write_text('{"kind": "something else"}')
    _refused("--source", "sim:turntable", "--sensor", tmp_path / "bad.json", needles=["not a lightplane sensor file"])
    _refused("--source", "sim:turntable", "--hardware", "laser-cannon", needles=["--hardware", "laser-cannon"])
    (tmp_path / "file").write_text("x")
    _refused("--source", "sim:turntable", "--output-dir", tmp_path / "file", needles=["--output-dir", "not a folder"])
    _refused("--source", "sim:turntable", "--port", "70000", needles=["--port"])
    assert not (tmp_path / "live-output").exists()  # nothing written


def test_address_unusable():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        _refused("--source", "sim:turntable", "--port", port, needles=[f"127.0.0.1:{port}", "in use"])
    _refused("--source", "sim:turntable", "--host", "no-such-host.invalid",
             needles=["cannot listen on no-such-host.invalid"])


def test_hardware_choice():
    from lightplane.cli.live import live_hardware
    from lightplane.live.source import SimulatedHardware
    from lightplane.live.sources import open_source

    sim = open_source("sim:turntable")
    assert live_hardware(None, sim) is sim.hardware  # the simulated sensor renders its own lasers and table
    assert live_hardware("sim", sim) is sim.hardware
    camera = object()  # a source without hardware of its own
    assert live_hardware(None, camera) is None
    hw = live_hardware("sim:2", camera)
    assert isinstance(hw, SimulatedHardware) and hw.n_lasers == 2
