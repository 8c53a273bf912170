"""The serial controllers (Ciclop/Horus G-code, FabScanPi) driving the simulated device over a pseudo-terminal:
lasers, moves and their settle time, the motion profile, and every failure as one LightplaneError."""

from __future__ import annotations

import threading
import time

import pytest

from lightplane.core.errors import LightplaneError
from lightplane.live.hardware import (
    CiclopBoard,
    CiclopOptions,
    FabScanBoard,
    FabScanOptions,
    SimulatedDeviceBoard,
    SimulatedFabScanBoard,
    open_hardware,
)
from lightplane.live.protocols import FABSCAN_VERSION_TEXT, move_duration_s, move_fraction
from lightplane.live.simdevice import SimulatedDevice
from lightplane.live.source import Hardware, SimulatedHardware

pytest.importorskip("serial", reason="pyserial (the live extra) is not installed")

FAST = CiclopOptions(settle_s=0.0, timeout_s=0.5)


@pytest.fixture()
def ciclop():
    with SimulatedDevice("ciclop") as dev:
        yield dev


def test_trapezoid_profile_exact():
    # long move: accelerate to 180 deg/s in 0.9 s (81 deg), cruise, brake: 360 deg -> 360/180 + 180/200 s
    assert move_duration_s(360.0, 180.0, 200.0) == pytest.approx(2.0 + 0.9, abs=1e-12)
    # short move never reaches the speed: 2 sqrt(d/a)
    assert move_duration_s(9.0, 180.0, 200.0) == pytest.approx(2 * (9 / 200) ** 0.5, abs=1e-12)
    # covered distance is 1/2 a t^2 while accelerating, symmetric, and complete at the end
    assert move_fraction(0.1, 9.0, 180.0, 200.0) == pytest.approx(0.5 * 200 * 0.01 / 9.0, abs=1e-12)
    total = move_duration_s(9.0, 180.0, 200.0)
    assert move_fraction(total / 2, 9.0, 180.0, 200.0) == pytest.approx(0.5, abs=1e-12)
    assert move_fraction(total, 9.0, 180.0, 200.0) == 1.0
    assert move_duration_s(36.0, 100.0, float("inf")) == pytest.approx(0.36)


def test_ciclop_handshake_lasers_and_commands(ciclop):
    board = CiclopBoard(ciclop.port, FAST)
    try:
        assert isinstance(board, Hardware)
        assert isinstance(ciclop.state, Hardware)  # what a simulated sensor reads, like SimulatedHardware
        assert board.firmware == "0.2"
        # what Horus sends on connect: origin, speed, acceleration
        assert ciclop.commands[:3] == ["G50", "G1F200", "$120=200"]
        board.set_laser(1, True)
        assert ciclop.state.laser_states() == (False, True) == board.laser_states()
        board.set_laser(0, True)
        board.set_laser(1, False)
        assert ciclop.state.laser_states() == (True, False)
        assert ciclop.commands[-3:] == ["M71T2", "M71T1", "M70T2"]
        with pytest.raises(LightplaneError, match="laser 2 does not exist"):
            board.set_laser(2, True)
    finally:
        board.close()
    # closing switches the lasers off
    assert ciclop.state.laser_states() == (False, False)


def test_ciclop_move_waits_for_the_table_to_settle(ciclop):
    opts = CiclopOptions(speed_deg_s=200.0, acceleration_deg_s2=400.0, settle_s=0.05, timeout_s=0.5)
    board = CiclopBoard(ciclop.port, opts)
    try:
        expected = move_duration_s(18.0, 180.0, 400.0)  # the firmware caps 200 deg/s at its 180 deg/s
        assert board.move_duration_s(18.0) == pytest.approx(expected)
        seen: list[float] = []
        watcher = threading.Thread(target=lambda: [seen.append(ciclop.state.angle_deg) or time.sleep(0.02)
                                                   for _ in range(10)])
        t0 = time.monotonic()
        watcher.start()
        board.move_turntable(18.0)
        elapsed = time.monotonic() - t0
        watcher.join()
        assert elapsed >= expected + 0.05
        assert elapsed < expected + 0.05 + 1.0  # generous: a busy machine schedules late
        # settled: the device has arrived and stands still
        assert not ciclop.state.moving
        assert ciclop.state.angle_deg == pytest.approx(18.0, abs=1e-9)
        assert board.angle_deg == pytest.approx(18.0)
        # the table was seen on its way, not jumping
        assert any(0.0 < a < 18.0 for a in seen), seen
        board.move_turntable(-4.5)
        assert ciclop.state.angle_deg == pytest.approx(13.5, abs=1e-9)
        assert ciclop.commands[-1] == "G1X13.5"
        assert "M17" in ciclop.commands
    finally:
        board.close()
    assert "M18" in ciclop.commands


def test_ciclop_firmware_error_is_one_lightplane_error(ciclop):
    board = CiclopBoard(ciclop.port, FAST)
    try:
        with pytest.raises(LightplaneError, match=r"refused 'M99': error: Unsupported command"):
            board.command("M99")
        # the line keeps working after a refused command
        board.set_laser(0, True)
        assert ciclop.state.laser_states()[0]
    finally:
        board.close()


def test_ciclop_timeout_and_unplugged_board(ciclop):
    board = CiclopBoard(ciclop.port, FAST)
    try:
        ciclop.silent = True
        t0 = time.monotonic()
        with pytest.raises(LightplaneError, match=r"did not answer 'M71T1' within 0.5 s"):
            board.set_laser(0, True)
        assert 0.5 <= time.monotonic() - t0 < 2.5
        ciclop.silent = False
        ciclop.unplug()
        with pytest.raises(LightplaneError, match=r"the Ciclop board on /dev/pts/\d+ is gone"):
            board.set_laser(0, True)
    finally:
        board.close()


def test_ciclop_first_firmware_has_no_origin_command():
    with SimulatedDevice("ciclop", greeting="Horus 0.1 ['$' for help]") as dev:
        board = CiclopBoard(dev.port, FAST)
        try:
            assert board.firmware == "0.1" and "G50" not in dev.commands
            assert dev.commands[:2] == ["G1F200", "$120=200"]
        finally:
            board.close()


def test_ciclop_wrong_or_missing_device():
    with SimulatedDevice("ciclop", greeting="Grbl 1.1h ['$' for help]") as dev:
        with pytest.raises(LightplaneError, match="did not greet as the Horus firmware.*Grbl 1.1h"):
            CiclopBoard(dev.port, FAST)
    with SimulatedDevice("ciclop") as dev:
        dev.silent = True
        with pytest.raises(LightplaneError, match="did not greet.*no reply at all"):
            CiclopBoard(dev.port, FAST)
    with pytest.raises(LightplaneError, match="cannot open the Ciclop board on /dev/lightplane-no-such-port"):
        CiclopBoard("/dev/lightplane-no-such-port", FAST)


def test_fabscan_lasers_moves_and_silence():
    with SimulatedDevice("fabscan", fabscan_steps_per_turn=3200) as dev:
        opts = FabScanOptions(steps_per_turn=3200, step_rate=3200.0, boot_s=0.0, settle_s=0.0, timeout_s=0.5)
        board = FabScanBoard(dev.port, opts)
        try:
            assert board.firmware == FABSCAN_VERSION_TEXT
            board.set_laser(0, True)
            assert dev.state.laser_states() == (True, False)
            board.set_laser(1, True)
            board.set_laser(0, False)
            assert dev.state.laser_states() == (False, True)
            assert dev.commands[-3:] == ["M21;", "M19;", "M22;"]
            t0 = time.monotonic()
            board.move_turntable(90.0)  # 800 steps at 3200 steps/s: the prompt comes after 0.25 s
            assert time.monotonic() - t0 >= 0.25
            assert dev.state.angle_deg == pytest.approx(90.0) and not dev.state.moving
            assert dev.commands[-1] == "G04 T800 F3200;"
            assert board.angle_deg == pytest.approx(90.0)
            # the firmware ignores what it does not know: only the prompt comes back, nothing to detect
            assert board.command("M99;") == []
            dev.silent = True
            with pytest.raises(LightplaneError, match="FabScanPi board .* did not answer 'M21;' with an echo"):
                board.set_laser(0, True)
        finally:
            board.close()


def test_open_hardware_specs():
    sim = open_hardware("sim:2")
    assert isinstance(sim, SimulatedHardware) and sim.n_lasers == 2
    board = open_hardware("simdevice?settle=0&timeout=0.5&lasers=1")
    try:
        assert isinstance(board, SimulatedDeviceBoard) and board.n_lasers == 1
        board.set_laser(0, True)
        board.move_turntable(2.0)
        assert board.state.laser_states() == (True,)
        assert board.state.angle_deg == pytest.approx(2.0)
    finally:
        board.close()
    fab = open_hardware("simdevice:fabscan,settle=0,rate=6400,timeout=0.5")
    try:
        assert isinstance(fab, SimulatedFabScanBoard) and isinstance(fab, Hardware)
        fab.set_laser(1, True)
        fab.move_turntable(45.0)
        assert fab.state.laser_states() == (False, True) and fab.state.angle_deg == pytest.approx(45.0)
    finally:
        fab.close()
    for spec, msg in [("ciclop:", "names no serial port"), ("simdevice:grbl", "unknown simulated device"), ("webcam:/dev/video0", "unknown hardware"),
                      ("ciclop:/dev/x?speed=fast", "speed='fast' is not a number"),
                      ("fabscan:/dev/x?speed=3", "unknown fabscan option 'speed'"),
                      ("simdevice?settle=-1", "settle_s must be >= 0"), ("sim:many", "needs a number of lasers")]:
        with pytest.raises(LightplaneError, match=msg):
            open_hardware(spec)


def test_ciclop_lasers_and_moves_from_two_threads(ciclop):
    board = CiclopBoard(ciclop.port, CiclopOptions(settle_s=0.0, timeout_s=1.0, acceleration_deg_s2=2000.0))
    errors: list[BaseException] = []

    def toggle():
        try:
            for i in range(30):
                board.set_laser(i % 2, i % 4 < 2)
        except BaseException as e:  # noqa: BLE001 - reported below
            errors.append(e)

    t = threading.Thread(target=toggle)
    try:
        t.start()
        for _ in range(4):
            board.move_turntable(2.5)
        t.join(timeout=10.0)
        assert not errors, errors
        assert ciclop.state.angle_deg == pytest.approx(10.0) and board.angle_deg == pytest.approx(10.0)
        # every command arrived whole, in one of the two threads' orders
        moves = [c for c in ciclop.commands if c.startswith("G1X")]
        assert moves == ["G1X2.5", "G1X5", "G1X7.5", "G1X10"]
        assert len([c for c in ciclop.commands if c.startswith("M7")]) == 30
        assert board.laser_states() == ciclop.state.laser_states()
    finally:
        board.close()
