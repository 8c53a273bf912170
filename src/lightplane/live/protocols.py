"""The serial protocols of the open scanners' controller boards, shared by the controllers (``live.hardware``)
and the simulated device that speaks them (``live.simdevice``).

*Ciclop / Horus* (BQ's Horus firmware, derived from grbl 0.9; 115200 baud; lines end in CR LF):

- Ctrl-X (``0x18``) resets the firmware, which answers with a blank line and the greeting
  ``Horus 0.2 ['$' for help]`` (``0.1`` on the first release);
- every command line is answered by ``ok`` or by ``error: <reason>``; ``M50 T<n>`` sends its reading first;
- ``G1 F<v>`` sets the turntable's speed in deg/s (the firmware caps it at its ``$110`` maximum rate, 180 deg/s by
  default), ``$120=<a>`` its acceleration in deg/s², ``G1 X<deg>`` moves to an absolute angle in degrees,
  ``G50`` makes the present angle the origin (firmware 0.2), ``M17`` / ``M18`` power the stepper on / off,
  ``M71 T<n>`` / ``M70 T<n>`` switch laser ``n`` (1-based) on / off;
- a move is answered as soon as it is queued, not when it ends: the table settles after the move's duration.

*FabScanPi* (the FabScanPi HAT's Arduino firmware; commands end in ``;`` and a newline):

- the firmware echoes every character it receives and prints the prompt ``>`` after each command;
- ``M200;`` prints the firmware version; ``M21;`` / ``M22;`` switch the first (right) laser on / off, ``M19;`` /
  ``M20;`` the second (left) one; ``M17;`` / ``M18;`` power the motors; ``G04 T<steps> F<rate>;`` turns the table by
  ``steps`` motor steps (relative); the firmware returns the prompt when the steps are done;
- unknown commands are ignored (only the prompt comes back), so errors cannot be told apart from success.
"""

from __future__ import annotations

import math
import re

#: the Horus firmware's greeting after a reset; group 1 is the version
CICLOP_GREETING = re.compile(r"Horus (\d+\.\d+) \['\$' for help\]")
#: the greeting the simulated device sends (the current Horus firmware)
CICLOP_GREETING_TEXT = "Horus 0.2 ['$' for help]"
#: the Horus firmware's maximum turntable rate ($110) unless changed on the board, deg/s
CICLOP_MAX_RATE_DEG_S = 180.0
#: Ctrl-X: the grbl soft reset
CICLOP_RESET = b"\x18"
#: FabScanPi: the firmware's prompt after each command
FABSCAN_PROMPT = ">"
#: FabScanPi: laser index -> (on, off) command
FABSCAN_LASER_COMMANDS = (("M21", "M22"), ("M19", "M20"))
#: the version the simulated FabScanPi device reports
FABSCAN_VERSION_TEXT = "v.20190101"


def move_duration_s(distance: float, speed: float, acceleration: float) -> float:
    """Duration of a trapezoidal move over ``distance`` (any unit) at top ``speed`` (unit/s) and ``acceleration``
    (unit/s²), starting and ending at rest; a triangle when the move is too short to reach the speed."""
    d = abs(float(distance))
    if d == 0.0:
        return 0.0
    if acceleration <= 0.0 or math.isinf(acceleration):
        return d / speed
    if d >= speed * speed / acceleration:
        return d / speed + speed / acceleration
    return 2.0 * math.sqrt(d / acceleration)


def move_fraction(t: float, distance: float, speed: float, acceleration: float) -> float:
    """Fraction (0..1) of a trapezoidal move covered ``t`` seconds after it started."""
    d = abs(float(distance))
    total = move_duration_s(d, speed, acceleration)
    if d == 0.0 or t >= total:
        return 1.0
    if t <= 0.0:
        return 0.0
    if acceleration <= 0.0 or math.isinf(acceleration):
        return t * speed / d
    v_top = min(speed, math.sqrt(d * acceleration))
    t_ramp = v_top / acceleration
    d_ramp = 0.5 * acceleration * t_ramp ** 2
    if t <= t_ramp:
        s = 0.5 * acceleration * t * t
    elif t <= total - t_ramp:
        s = d_ramp + v_top * (t - t_ramp)
    else:
        s = d - 0.5 * acceleration * (total - t) ** 2
    return min(1.0, max(0.0, s / d))
