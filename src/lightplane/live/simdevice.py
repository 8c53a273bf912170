"""A simulated scanner controller on a pseudo-terminal: it speaks the Ciclop/Horus firmware's G-code or the
FabScanPi firmware's protocol (``live.protocols``) with the same greeting, replies and timing of moves, and keeps the
lasers' states and the turntable's angle in a :class:`DeviceState` that a simulated sensor can render from.

The real controllers of ``live.hardware`` open :attr:`SimulatedDevice.port` like any serial port.
"""

from __future__ import annotations

import os
import re
import select
import threading
import time
from dataclasses import dataclass

from lightplane.core.errors import LightplaneError
from lightplane.live.protocols import (
    CICLOP_GREETING_TEXT,
    CICLOP_MAX_RATE_DEG_S,
    FABSCAN_LASER_COMMANDS,
    FABSCAN_PROMPT,
    FABSCAN_VERSION_TEXT,
    move_duration_s,
    move_fraction,
)


@dataclass(frozen=True)
class _Move:
    start_deg: float
    end_deg: float
    t_start: float
    duration_s: float
    speed: float
    acceleration: float


class DeviceState:
    """What the simulated device's lasers and turntable do, readable like ``live.source.SimulatedHardware``
    (``n_lasers``, ``has_turntable``, ``laser_states()``, ``angle_deg``).  The angle follows the queued moves in
    time (trapezoidal profiles), so a frame rendered during a move sees the table where it is at that moment.
    ``set_laser`` and ``move_turntable`` act on the state directly, without the serial line."""

    def __init__(self, n_lasers: int = 2, has_turntable: bool = True) -> None:
        self.n_lasers = int(n_lasers)
        self.has_turntable = bool(has_turntable)
        self.motor_enabled = False
        self._lasers = [False] * self.n_lasers
        self._origin = 0.0
        self._moves: list[_Move] = []
        self._lock = threading.Lock()

    def laser_states(self) -> tuple[bool, ...]:
        with self._lock:
            return tuple(self._lasers)

    def set_laser(self, index: int, on: bool) -> None:
        if not 0 <= index < self.n_lasers:
            raise LightplaneError(f"laser {index} does not exist: the device has {self.n_lasers}")
        with self._lock:
            self._lasers[index] = bool(on)

    def lasers_off(self) -> None:
        with self._lock:
            self._lasers = [False] * self.n_lasers

    def _angle_at(self, t: float) -> float:
        angle = self._origin
        for m in self._moves:
            if t < m.t_start:
                break
            f = move_fraction(t - m.t_start, m.end_deg - m.start_deg, m.speed, m.acceleration)
            angle = m.start_deg + f * (m.end_deg - m.start_deg)
        return angle

    @property
    def angle_deg(self) -> float:
        """The table's angle now, in degrees (relative to the origin of the last reset)."""
        with self._lock:
            return self._angle_at(time.monotonic())

    @property
    def target_deg(self) -> float:
        """The angle at which the table stops once every queued move is done, in degrees."""
        with self._lock:
            return self._moves[-1].end_deg if self._moves else self._origin

    @property
    def moving(self) -> bool:
        with self._lock:
            return bool(self._moves) and time.monotonic() < self._moves[-1].t_start + self._moves[-1].duration_s

    def queue_move(self, target_deg: float, speed: float, acceleration: float) -> float:
        """Queue a move to the absolute ``target_deg`` after the moves already queued; returns its end time
        (``time.monotonic()`` seconds)."""
        with self._lock:
            now = time.monotonic()
            start = self._moves[-1].end_deg if self._moves else self._origin
            t0 = max(now, self._moves[-1].t_start + self._moves[-1].duration_s) if self._moves else now
            duration = move_duration_s(target_deg - start, speed, acceleration)
            self._moves = [m for m in self._moves if m.t_start + m.duration_s > now][-8:]
            if not self._moves:
                self._origin = start
            self._moves.append(_Move(start, float(target_deg), t0, duration, speed, acceleration))
            return t0 + duration

    def reset_origin(self) -> None:
        """Make the table's present angle zero (the moves queued so far are finished at once)."""
        with self._lock:
            self._moves = []
            self._origin = 0.0

    def move_turntable(self, degrees: float) -> None:
        """Turn by ``degrees`` at once (no serial line involved)."""
        with self._lock:
            end = (self._moves[-1].end_deg if self._moves else self._origin) + float(degrees)
            self._moves = []
            self._origin = end

    def close(self) -> None:
        self.lasers_off()


class SimulatedDevice:
    """A controller board on a pseudo-terminal.  ``protocol`` is ``"ciclop"`` (Horus firmware G-code) or
    ``"fabscan"`` (FabScanPi firmware).  Open :attr:`port` with the matching controller of ``live.hardware``.

    Test hooks: ``silent = True`` makes the device read commands without ever answering (a hung board);
    :meth:`unplug` closes the line as a pulled USB cable does; ``commands`` lists every command line received.
    ``greeting`` replaces the Horus greeting (a wrong firmware); ``fabscan_step_rate`` is the FabScanPi firmware's
    step rate in steps/s for moves sent without ``F``."""

    def __init__(self, protocol: str = "ciclop", n_lasers: int = 2, *, greeting: str | None = None,
                 max_rate_deg_s: float = CICLOP_MAX_RATE_DEG_S, fabscan_steps_per_turn: int = 3200,
                 fabscan_step_rate: float = 1600.0) -> None:
        if protocol not in ("ciclop", "fabscan"):
            raise LightplaneError(f"unknown device protocol {protocol!r}: use 'ciclop' or 'fabscan'")
        self.protocol = protocol
        self.state = DeviceState(n_lasers=n_lasers)
        self.greeting = CICLOP_GREETING_TEXT if greeting is None else greeting
        self.max_rate = float(max_rate_deg_s)
        self.speed = 0.0  # G1 F, deg/s (grbl starts with an undefined feed rate)
        self.acceleration = 200.0  # $120, deg/s²
        self.steps_per_turn = int(fabscan_steps_per_turn)
        self.step_rate = float(fabscan_step_rate)
        self.silent = False
        self.commands: list[str] = []
        import tty  # POSIX only: the simulated device needs a pseudo-terminal

        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self._buf = b""
        self._running = True
        self._thread = threading.Thread(target=self._serve, name=f"simdevice-{protocol}", daemon=True)
        self._thread.start()

    # --- line handling -------------------------------------------------------------------------------------
    def _write(self, text: str) -> None:
        if self._master >= 0:
            try:
                os.write(self._master, text.encode("ascii"))
            except OSError:
                pass

    def _serve(self) -> None:
        while self._running:
            try:
                ready, _, _ = select.select([self._master], [], [], 0.05)
                if not ready:
                    continue
                data = os.read(self._master, 4096)
            except (OSError, ValueError):
                return
            if data:
                self._receive(data)

    def _receive(self, data: bytes) -> None:
        for byte in data:
            ch = bytes([byte])
            if self.protocol == "ciclop" and ch == b"\x18":
                self._buf = b""
                self._ciclop_reset()
                continue
            if ch == b"\r":
                continue
            if self.protocol == "fabscan" and not self.silent:
                self._write(ch.decode("ascii", "replace"))
            if ch == b"\n":
                line = self._buf.decode("ascii", "replace").strip()
                self._buf = b""
                self.commands.append(line)
                if not self.silent:
                    self._ciclop_line(line) if self.protocol == "ciclop" else self._fabscan_line(line)
            else:
                self._buf += ch

    # --- Ciclop / Horus ------------------------------------------------------------------------------------
    def _ciclop_reset(self) -> None:
        self.state.lasers_off()
        self.state.motor_enabled = False
        if not self.silent:
            self._write("\r\n" + self.greeting + "\r\n")

    def _ciclop_line(self, line: str) -> None:
        reply = self._ciclop_execute(line.upper().replace(" ", ""))
        self._write(reply + "\r\n")

    def _ciclop_execute(self, line: str) -> str:
        if not line:
            return "ok"
        if line.startswith("$"):
            m = re.fullmatch(r"\$(\d+)=([-+]?\d*\.?\d+)", line)
            if not m:
                return "error: Invalid statement"
            key, value = int(m.group(1)), float(m.group(2))
            if key == 120:
                self.acceleration = value
            elif key == 110:
                self.max_rate = value
            return "ok"
        words = re.findall(r"([A-Z])([-+]?\d*\.?\d+)", line)
        if not words or "".join(letter + num for letter, num in words) != line:
            return "error: Expected command letter"
        return self._ciclop_words({letter: float(num) for letter, num in words}, line)

    def _ciclop_words(self, w: dict[str, float], line: str) -> str:
        if "G" in w and int(w["G"]) not in (0, 1, 50):
            return "error: Unsupported command"
        if "M" in w and int(w["M"]) not in (17, 18, 50, 70, 71):
            return "error: Unsupported command"
        if set(w) - {"G", "M", "F", "X", "T"}:
            return "error: Unsupported command"
        if "F" in w:
            if w["F"] < 0:
                return "error: Negative value"
            self.speed = w["F"]
        if w.get("G") == 50:
            self.state.reset_origin()
        if "X" in w:
            if self.speed <= 0:
                return "error: Undefined feed rate"
            self.state.queue_move(w["X"], min(self.speed, self.max_rate), self.acceleration)
        m = int(w["M"]) if "M" in w else None
        laser = int(w.get("T", 0)) - 1
        if m in (70, 71) and 0 <= laser < self.state.n_lasers:
            self.state.set_laser(laser, m == 71)
        elif m in (17, 18):
            self.state.motor_enabled = m == 17
        elif m == 50:
            return "0\r\nok"
        return "ok"

    # --- FabScanPi -----------------------------------------------------------------------------------------
    def _fabscan_line(self, line: str) -> None:
        cmd = line.rstrip(";").strip().upper()
        m = re.match(r"([GM])0*(\d+)", cmd)
        if m is not None:
            code = f"{m.group(1)}{int(m.group(2))}"
            for i, (on, off) in enumerate(FABSCAN_LASER_COMMANDS[:self.state.n_lasers]):
                if code in (on, off):
                    self.state.set_laser(i, code == on)
            if code == "M17":
                self.state.motor_enabled = True
            elif code == "M18":
                self.state.motor_enabled = False
            elif code == "M200":
                self._write(FABSCAN_VERSION_TEXT + "\r\n")
            elif code in ("G4", "G2"):
                self._fabscan_move(cmd)
        self._write(FABSCAN_PROMPT)

    def _fabscan_move(self, cmd: str) -> None:
        steps = re.search(r"T([-+]?\d+)", cmd)
        rate = re.search(r"F(\d*\.?\d+)", cmd)
        if steps is None:
            return
        step_rate = float(rate.group(1)) if rate and float(rate.group(1)) > 0 else self.step_rate
        deg_per_step = 360.0 / self.steps_per_turn
        end = self.state.queue_move(self.state.target_deg + int(steps.group(1)) * deg_per_step,
                                    step_rate * deg_per_step, float("inf"))
        # the firmware steps inside the command: the prompt comes when the steps are done
        time.sleep(max(0.0, end - time.monotonic()))

    # --- life cycle ----------------------------------------------------------------------------------------
    def unplug(self) -> None:
        """Close the line as a pulled cable does: the controller's next read or write fails."""
        self._running = False
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass
        self._master = self._slave = -1

    def close(self) -> None:
        self.unplug()
        self._thread.join(timeout=1.0)

    def __enter__(self) -> SimulatedDevice:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
