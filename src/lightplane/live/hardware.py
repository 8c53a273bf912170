"""Lasers and turntables over a serial line: the Ciclop/Horus board (BQ's Horus firmware G-code) and the FabScanPi
HAT (its Arduino firmware), both implementing ``live.source.Hardware``; :func:`open_hardware` opens one from a
specification such as ``ciclop:/dev/ttyUSB0``.  The protocols are described in ``live.protocols``.

Every failure of the line (no such port, a wrong firmware, no reply in time, the cable pulled) raises one
``LightplaneError`` that names the port and what was sent.
"""

from __future__ import annotations

import re
import threading
import time
from dataclasses import dataclass
from typing import Any

from lightplane.core.errors import LightplaneError
from lightplane.live.protocols import (
    CICLOP_GREETING,
    CICLOP_MAX_RATE_DEG_S,
    CICLOP_RESET,
    FABSCAN_LASER_COMMANDS,
    FABSCAN_PROMPT,
    move_duration_s,
)
from lightplane.live.simdevice import SimulatedDevice
from lightplane.live.source import Hardware, SimulatedHardware
from lightplane.live.spec import split_spec


def _positive(name: str, value: float, allow_zero: bool = False) -> None:
    if not (value >= 0 if allow_zero else value > 0):
        raise LightplaneError(f"{name} must be {'>= 0' if allow_zero else '> 0'}, got {value}")


@dataclass(frozen=True)
class CiclopOptions:
    """How to drive a Ciclop board: the turntable's speed (deg/s) and acceleration (deg/s²) sent to the firmware
    (Horus' defaults 200 and 200), the firmware's maximum rate (deg/s, its ``$110``; the speed is capped there),
    the time the table needs to come to rest after the move's computed end (``settle_s``), how long to wait for a
    reply (``timeout_s``), the number of lasers and the baud rate."""

    speed_deg_s: float = 200.0
    acceleration_deg_s2: float = 200.0
    max_rate_deg_s: float = CICLOP_MAX_RATE_DEG_S
    settle_s: float = 0.2
    timeout_s: float = 2.0
    n_lasers: int = 2
    baud: int = 115200

    def __post_init__(self) -> None:
        _positive("speed_deg_s", self.speed_deg_s)
        _positive("acceleration_deg_s2", self.acceleration_deg_s2)
        _positive("max_rate_deg_s", self.max_rate_deg_s)
        _positive("settle_s", self.settle_s, allow_zero=True)
        _positive("timeout_s", self.timeout_s)
        if not 1 <= self.n_lasers <= 4:
            raise LightplaneError(f"n_lasers must be 1 to 4, got {self.n_lasers}")
        _positive("baud", self.baud)

    @property
    def move_speed_deg_s(self) -> float:
        """The speed the firmware really moves at (the requested speed, capped at the maximum rate), deg/s."""
        return min(self.speed_deg_s, self.max_rate_deg_s)


@dataclass(frozen=True)
class FabScanOptions:
    """How to drive a FabScanPi HAT: motor steps per table turn (a 200-step motor at 1/16 microstepping: 3200),
    the step rate sent with each move (steps/s), the settle time after the firmware reports the move done, the
    reply timeout (a move's own duration is added), the wait after opening the port while the Arduino restarts
    (``boot_s``), the number of lasers and the baud rate."""

    steps_per_turn: int = 3200
    step_rate: float = 1600.0
    settle_s: float = 0.2
    timeout_s: float = 2.0
    boot_s: float = 2.0
    n_lasers: int = 2
    baud: int = 115200

    def __post_init__(self) -> None:
        _positive("steps_per_turn", self.steps_per_turn)
        _positive("step_rate", self.step_rate)
        _positive("settle_s", self.settle_s, allow_zero=True)
        _positive("timeout_s", self.timeout_s)
        _positive("boot_s", self.boot_s, allow_zero=True)
        if not 1 <= self.n_lasers <= 2:
            raise LightplaneError(f"n_lasers must be 1 or 2 on a FabScanPi, got {self.n_lasers}")
        _positive("baud", self.baud)


class _SerialLine:
    """A serial port that turns every failure into one ``LightplaneError`` naming the board and the port."""

    def __init__(self, board: str, port: str, baud: int) -> None:
        import serial

        self.board, self.port = board, port
        # termios.error (a vanished pseudo-terminal or USB serial device, e.g. tcdrain's EIO) is not an OSError
        self._errors: tuple[type[BaseException], ...] = (serial.SerialException, OSError, *_termios_errors())
        self._read_errors: tuple[type[BaseException], ...] = (*self._errors, TypeError)
        try:
            self._s = serial.Serial(port, baud, timeout=0.05, write_timeout=2.0)
        except (serial.SerialException, OSError, ValueError) as e:
            raise LightplaneError(f"cannot open the {board} on {port}: {_reason(e)}") from None

    def fail(self, what: str) -> LightplaneError:
        return LightplaneError(f"the {self.board} on {self.port} {what}")

    def write(self, data: bytes) -> None:
        try:
            self._s.write(data)
            self._s.flush()
        except self._errors as e:
            raise self.fail(f"is gone (writing failed: {_reason(e)})") from None

    def read(self, n: int = 256) -> bytes:
        try:
            return self._s.read(max(1, min(n, self._s.in_waiting or 1)))
        except self._read_errors as e:
            raise self.fail(f"is gone (reading failed: {_reason(e)})") from None

    def discard_input(self) -> None:
        try:
            self._s.reset_input_buffer()
        except self._errors as e:
            raise self.fail(f"is gone ({_reason(e)})") from None

    def close(self) -> None:
        try:
            self._s.close()
        except self._errors:
            pass


def _termios_errors() -> tuple[type[BaseException], ...]:
    try:
        import termios
    except ImportError:  # not on Windows
        return ()
    return (termios.error,)


def _reason(e: BaseException) -> str:
    if len(e.args) == 2 and isinstance(e.args[0], int) and isinstance(e.args[1], str):  # termios.error(errno, text)
        return e.args[1]
    return str(e).strip().rstrip(".") or type(e).__name__


class _LineReader:
    """Reads CR/LF-terminated lines (and a trailing prompt without newline) from a :class:`_SerialLine`."""

    def __init__(self, line: _SerialLine) -> None:
        self.line = line
        self.pending = b""

    def readline(self, deadline: float, prompt: str | None = None) -> str | None:
        """The next line without its end (or the prompt, when it is all that is pending); None at the deadline."""
        while True:
            i = self.pending.find(b"\n")
            if i >= 0:
                out, self.pending = self.pending[:i], self.pending[i + 1:]
                return out.decode("ascii", "replace").strip("\r")
            if prompt is not None and self.pending == prompt.encode():
                self.pending = b""
                return prompt
            if time.monotonic() >= deadline:
                return None
            self.pending += self.line.read()


class CiclopBoard:
    """The Ciclop scanner's board running BQ's Horus firmware, as ``live.source.Hardware``.

    Opening resets the firmware (Ctrl-X), waits for its greeting, makes the present table angle the origin and sets
    speed and acceleration.  ``move_turntable`` sends an absolute ``G1 X`` move, waits for the firmware's ``ok`` and
    then for the move's computed duration (trapezoid from speed and acceleration) plus ``settle_s``."""

    has_turntable = True

    def __init__(self, port: str, options: CiclopOptions | None = None) -> None:
        self.options = options or CiclopOptions()
        self.n_lasers = self.options.n_lasers
        self.port = port
        self._lock = threading.RLock()
        self._line = _SerialLine("Ciclop board", port, self.options.baud)
        self._reader = _LineReader(self._line)
        self._lasers = [False] * self.n_lasers
        self._target = 0.0
        self._motor_on = False
        try:
            self.firmware = self._handshake()
            if self.firmware != "0.1":
                self.command("G50")
            self.command(f"G1F{_num(self.options.speed_deg_s)}")
            self.command(f"$120={_num(self.options.acceleration_deg_s2)}")
        except LightplaneError:
            self._line.close()
            raise

    def _handshake(self) -> str:
        self._line.discard_input()
        self._line.write(CICLOP_RESET)
        deadline = time.monotonic() + self.options.timeout_s + 1.0  # a board that has just been reset boots first
        seen: list[str] = []
        while True:
            line = self._reader.readline(deadline)
            if line is None:
                got = f" (it sent {seen[-1]!r})" if seen else " (no reply at all)"
                raise self._line.fail(f"did not greet as the Horus firmware after a reset{got}")
            m = CICLOP_GREETING.search(line)
            if m:
                time.sleep(0.05)
                self._line.discard_input()
                self._reader.pending = b""
                return m.group(1)
            if line.strip():
                seen.append(line.strip())

    def command(self, cmd: str, timeout_s: float | None = None) -> list[str]:
        """Send one G-code line and wait for ``ok``; returns the lines that came before it.  One command at a time
        holds the line (other threads wait their turn)."""
        with self._lock:
            return self._command(cmd, timeout_s)

    def _command(self, cmd: str, timeout_s: float | None) -> list[str]:
        self._line.write(cmd.encode("ascii") + b"\r\n")
        deadline = time.monotonic() + (self.options.timeout_s if timeout_s is None else timeout_s)
        before: list[str] = []
        while True:
            line = self._reader.readline(deadline)
            if line is None:
                raise self._line.fail(f"did not answer {cmd!r} within {self.options.timeout_s:g} s")
            text = line.strip()
            if text == "ok":
                return before
            if text.lower().startswith("error"):
                raise self._line.fail(f"refused {cmd!r}: {text}")
            if text:
                before.append(text)

    def set_laser(self, index: int, on: bool) -> None:
        _check_laser(index, self.n_lasers)
        self.command(f"M{71 if on else 70}T{index + 1}")
        self._lasers[index] = bool(on)

    def laser_states(self) -> tuple[bool, ...]:
        return tuple(self._lasers)

    def move_duration_s(self, degrees: float) -> float:
        """How long the firmware takes to turn the table by ``degrees`` (without the settle time), seconds."""
        o = self.options
        return move_duration_s(degrees, o.move_speed_deg_s, o.acceleration_deg_s2)

    def move_turntable(self, degrees: float) -> None:
        with self._lock:
            if not self._motor_on:
                self.command("M17")
                self._motor_on = True
            target = self._target + float(degrees)
            self.command(f"G1X{_num(target)}")
            self._target = target
        time.sleep(self.move_duration_s(degrees) + self.options.settle_s)

    @property
    def angle_deg(self) -> float:
        return self._target

    def close(self) -> None:
        try:
            for i, on in enumerate(self._lasers):
                if on:
                    self.set_laser(i, False)
            if self._motor_on:
                self.command("M18")
        except LightplaneError:
            pass
        finally:
            self._line.close()


class FabScanBoard:
    """The FabScanPi HAT (or an Arduino with the FabScanPi firmware), as ``live.source.Hardware``.

    Opening waits ``boot_s`` for the Arduino to restart, asks the firmware version (``M200;``) and powers the motor.
    ``move_turntable`` sends ``G04 T<steps> F<rate>;``, waits for the prompt that the firmware prints once the steps
    are done, then ``settle_s``.  The firmware ignores commands it does not know, so a wrong command cannot be
    detected; a silent or missing board can."""

    has_turntable = True

    def __init__(self, port: str, options: FabScanOptions | None = None) -> None:
        self.options = options or FabScanOptions()
        self.n_lasers = self.options.n_lasers
        self.port = port
        self._lock = threading.RLock()
        self._line = _SerialLine("FabScanPi board", port, self.options.baud)
        self._reader = _LineReader(self._line)
        self._lasers = [False] * self.n_lasers
        self._steps = 0
        try:
            time.sleep(self.options.boot_s)
            self._line.discard_input()
            out = self.command("M200;")
            if not out:
                raise self._line.fail("answered 'M200;' without a firmware version")
            self.firmware = out[0]
            self.command("M17;")
        except LightplaneError:
            self._line.close()
            raise

    def command(self, cmd: str, timeout_s: float | None = None) -> list[str]:
        """Send one command, wait for its echo and the prompt; returns the lines printed in between.  One command
        at a time holds the line (other threads wait their turn)."""
        with self._lock:
            return self._command(cmd, timeout_s)

    def _command(self, cmd: str, timeout_s: float | None) -> list[str]:
        self._line.write(cmd.encode("ascii") + b"\n")
        wait = self.options.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + wait
        echoed = False
        out: list[str] = []
        while True:
            line = self._reader.readline(deadline, prompt=FABSCAN_PROMPT)
            if line is None:
                what = "the prompt" if echoed else "an echo"
                raise self._line.fail(f"did not answer {cmd!r} with {what} within {wait:g} s")
            text = line.lstrip(FABSCAN_PROMPT).strip()
            if line == FABSCAN_PROMPT and echoed:
                return out
            if not echoed and text == cmd.strip():
                echoed = True
            elif echoed and text:
                out.append(text)

    def set_laser(self, index: int, on: bool) -> None:
        _check_laser(index, self.n_lasers)
        on_cmd, off_cmd = FABSCAN_LASER_COMMANDS[index]
        self.command(f"{on_cmd if on else off_cmd};")
        self._lasers[index] = bool(on)

    def laser_states(self) -> tuple[bool, ...]:
        return tuple(self._lasers)

    def move_turntable(self, degrees: float) -> None:
        o = self.options
        steps = int(round(float(degrees) * o.steps_per_turn / 360.0))
        if steps == 0:
            return
        with self._lock:
            self.command(f"G04 T{steps} F{_num(o.step_rate)};", timeout_s=o.timeout_s + abs(steps) / o.step_rate)
            self._steps += steps
        time.sleep(o.settle_s)

    @property
    def angle_deg(self) -> float:
        return self._steps * 360.0 / self.options.steps_per_turn

    def close(self) -> None:
        try:
            for i, on in enumerate(self._lasers):
                if on:
                    self.set_laser(i, False)
            self.command("M18;")
        except LightplaneError:
            pass
        finally:
            self._line.close()


class SimulatedDeviceBoard(CiclopBoard):
    """A :class:`CiclopBoard` on a :class:`~lightplane.live.simdevice.SimulatedDevice` (Horus protocol) that it
    owns and closes; ``state`` is the device's :class:`~lightplane.live.simdevice.DeviceState`, what a simulated
    sensor renders from."""

    def __init__(self, options: CiclopOptions | None = None) -> None:
        self.device = SimulatedDevice("ciclop", n_lasers=(options or CiclopOptions()).n_lasers)
        self.state = self.device.state
        try:
            super().__init__(self.device.port, options)
        except LightplaneError:
            self.device.close()
            raise

    def close(self) -> None:
        super().close()
        self.device.close()


class SimulatedFabScanBoard(FabScanBoard):
    """A :class:`FabScanBoard` on a :class:`~lightplane.live.simdevice.SimulatedDevice` (FabScanPi protocol) that
    it owns and closes; ``state`` is the device's :class:`~lightplane.live.simdevice.DeviceState`."""

    def __init__(self, options: FabScanOptions | None = None) -> None:
        o = options or FabScanOptions(boot_s=0.0)
        self.device = SimulatedDevice("fabscan", n_lasers=o.n_lasers, fabscan_steps_per_turn=o.steps_per_turn,
                                      fabscan_step_rate=o.step_rate)
        self.state = self.device.state
        try:
            super().__init__(self.device.port, o)
        except LightplaneError:
            self.device.close()
            raise

    def close(self) -> None:
        super().close()
        self.device.close()


def _check_laser(index: int, n: int) -> None:
    if not 0 <= index < n:
        raise LightplaneError(f"laser {index} does not exist: this hardware has lasers 0 to {n - 1}")


def _num(value: float) -> str:
    """A number as G-code wants it: no exponent, no trailing zeros."""
    text = f"{float(value):.4f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0") else text


_CICLOP_KEYS = {"speed": "speed_deg_s", "accel": "acceleration_deg_s2", "max_rate": "max_rate_deg_s",
                "settle": "settle_s", "timeout": "timeout_s", "lasers": "n_lasers", "baud": "baud"}
_FABSCAN_KEYS = {"steps": "steps_per_turn", "rate": "step_rate", "settle": "settle_s", "timeout": "timeout_s",
                 "boot": "boot_s", "lasers": "n_lasers", "baud": "baud"}


def _options(kind: str, pairs: list[tuple[str, str]], keys: dict[str, str], cls: Any, **defaults: Any) -> Any:
    kwargs: dict[str, Any] = dict(defaults)
    for key, value in pairs:
        if key not in keys:
            raise LightplaneError(f"unknown {kind} option {key!r}: use {', '.join(sorted(keys))}")
        field = keys[key]
        try:
            kwargs[field] = int(value) if field in ("n_lasers", "baud", "steps_per_turn") else float(value)
        except ValueError:
            raise LightplaneError(f"{kind} option {key}={value!r} is not a number") from None
    return cls(**kwargs)


def open_hardware(spec: str) -> Hardware:
    """Open lasers and turntable from a specification (options after ``?`` joined by ``&``, or after commas):

    - ``ciclop:PORT[?speed=200&accel=200&max_rate=180&settle=0.2&timeout=2&lasers=2&baud=115200]``: a Ciclop
      board with the Horus firmware;
    - ``fabscan:PORT[?steps=3200&rate=1600&settle=0.2&timeout=2&boot=2&lasers=2&baud=115200]``: a FabScanPi HAT;
    - ``sim[:N]``: ``SimulatedHardware`` with N lasers (1 by default), no serial line;
    - ``simdevice[:ciclop][?...]``: a Ciclop board on a simulated device (pseudo-terminal), options as ``ciclop``;
      ``simdevice:fabscan[?...]``: a FabScanPi board on a simulated device, options as ``fabscan`` (``boot`` 0)."""
    m = re.match(r"[a-z]+", spec.strip())
    kind = m.group(0) if m else ""
    target, pairs = split_spec(spec, kind)
    if kind == "sim":
        try:
            n = int(target) if target else 1
        except ValueError:
            raise LightplaneError(f"'sim:{target}' needs a number of lasers, e.g. sim:2") from None
        if not 1 <= n <= 4:
            raise LightplaneError(f"sim needs 1 to 4 lasers, got {n}")
        return SimulatedHardware(n_lasers=n)
    if kind == "simdevice" and target in ("", "ciclop"):
        return SimulatedDeviceBoard(_options("simdevice", pairs, _CICLOP_KEYS, CiclopOptions))
    if kind == "simdevice" and target == "fabscan":
        return SimulatedFabScanBoard(_options("simdevice", pairs, _FABSCAN_KEYS, FabScanOptions, boot_s=0.0))
    if kind == "simdevice":
        raise LightplaneError(f"unknown simulated device {target!r}: use simdevice:ciclop or simdevice:fabscan")
    if kind in ("ciclop", "fabscan") and not target:
        raise LightplaneError(f"'{spec}' names no serial port: write {kind}:/dev/ttyUSB0")
    if kind == "ciclop":
        return CiclopBoard(target, _options("ciclop", pairs, _CICLOP_KEYS, CiclopOptions))
    if kind == "fabscan":
        return FabScanBoard(target, _options("fabscan", pairs, _FABSCAN_KEYS, FabScanOptions))
    raise LightplaneError(f"unknown hardware {spec!r}: use ciclop:PORT, fabscan:PORT, sim[:N] or simdevice[:fabscan]")
