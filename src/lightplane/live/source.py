"""What every live frame source and every hardware controller provides.

A *source* delivers frames with the source's own frame counter and two monotonic times: when the frame was
exposed (the end of the exposure, or the best estimate the source has) and when lightplane received it.  Gaps in
the counter are dropped frames; a source counts them itself as well (``dropped``), so that frames lost inside a
driver are not hidden.  *Hardware* is what a scanner has besides the camera: lasers and, optionally, a turntable.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class Frame:
    """One frame of a source.

    ``image`` is the frame as the camera gave it (2-D grey or H x W x 3 BGR; uint8, uint16 or float32);
    ``index`` the source's frame counter (consecutive unless frames were dropped); ``t_exposure`` and
    ``t_received`` are ``time.monotonic()`` seconds; ``meta`` carries what the source knows about the frame
    (``"laser"``: the lasers' on/off states, ``"angle_deg"``: the turntable angle, ``"truth"``: exact truth
    from the simulated sensor)."""

    image: np.ndarray
    index: int
    t_exposure: float
    t_received: float = field(default_factory=time.monotonic)
    meta: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Control:
    """A camera setting the source exposes (exposure in µs, gain in dB, region of interest as x, y, w, h)."""

    name: str
    value: Any
    unit: str = ""
    minimum: float | None = None
    maximum: float | None = None


@runtime_checkable
class Source(Protocol):
    """A live frame source.  ``read`` blocks up to ``timeout`` seconds and returns ``None`` at the end of a
    finite stream (a file or folder that is not looped); it raises ``TimeoutError`` when no frame came in time."""

    name: str
    nominal_fps: float | None
    dropped: int

    def start(self) -> None: ...

    def read(self, timeout: float | None = None) -> Frame | None: ...

    def stop(self) -> None: ...

    def controls(self) -> dict[str, Control]: ...

    def set_control(self, name: str, value: Any) -> None: ...


@runtime_checkable
class Hardware(Protocol):
    """Lasers and an optional turntable.  ``move_turntable`` turns by ``degrees`` (relative) and returns when the
    table has settled; ``angle_deg`` is the accumulated angle since the controller was opened."""

    n_lasers: int
    has_turntable: bool

    def set_laser(self, index: int, on: bool) -> None: ...

    def laser_states(self) -> tuple[bool, ...]: ...

    def move_turntable(self, degrees: float) -> None: ...

    @property
    def angle_deg(self) -> float: ...

    def close(self) -> None: ...


@runtime_checkable
class Stage(Protocol):
    """A linear stage (optional, besides :class:`Hardware`): ``move_stage`` moves the object by ``mm``
    (relative) along ``stage_direction`` (unit, camera frame, or None when not calibrated) and returns when
    it has settled; ``position_mm`` is the accumulated travel since the controller was opened."""

    has_stage: bool
    stage_direction: tuple[float, float, float] | None

    def move_stage(self, mm: float) -> None: ...

    @property
    def position_mm(self) -> float: ...


class SimulatedHardware:
    """Lasers, a turntable and a linear stage that exist only as state: the simulated sensor renders what
    this state says.  ``stage_direction``: the stage's direction of travel in the camera frame (a linear
    stage exists when it is given)."""

    def __init__(self, n_lasers: int = 1, has_turntable: bool = True, settle_s: float = 0.0,
                 stage_direction: tuple[float, float, float] | None = None) -> None:
        self.n_lasers = int(n_lasers)
        self.has_turntable = bool(has_turntable)
        self.settle_s = float(settle_s)
        self.has_stage = stage_direction is not None
        self.stage_direction = None if stage_direction is None else tuple(float(v) for v in stage_direction)
        self._lasers = [False] * self.n_lasers
        self._angle = 0.0
        self._position = 0.0

    def set_laser(self, index: int, on: bool) -> None:
        self._lasers[index] = bool(on)

    def laser_states(self) -> tuple[bool, ...]:
        return tuple(self._lasers)

    def move_turntable(self, degrees: float) -> None:
        if not self.has_turntable:
            raise RuntimeError("this hardware has no turntable")
        self._angle += float(degrees)
        if self.settle_s:
            time.sleep(self.settle_s)

    @property
    def angle_deg(self) -> float:
        return self._angle

    def move_stage(self, mm: float) -> None:
        if not self.has_stage:
            raise RuntimeError("this hardware has no linear stage")
        self._position += float(mm)
        if self.settle_s:
            time.sleep(self.settle_s)

    @property
    def position_mm(self) -> float:
        return self._position

    def close(self) -> None:
        self._lasers = [False] * self.n_lasers
