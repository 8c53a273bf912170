"""The guided calibration on the live page: the next placement as a ghost outline, the σ after each placement, the stop.

:class:`LiveGuide` runs one :class:`lightplane.plan.session.GuideSession` over the engine's camera and light
plane (its sensor's; the plane is the rough one the guide starts from).  ``start`` begins a calibration for a
target σ, ``accept`` takes the next frame the camera exposes as the next placement (the circle target and the
stripe on it found in it), ``state`` is the session's summary (the suggested placement's outline in image px,
the σ now and predicted after it, the σ after each placement, the coverage, the verdict).  ``place_simulated``
plays the user on the simulated sensor (``sim:target``): it puts the simulated target where the guide says,
off by a placement error.
"""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING

import numpy as np

from lightplane.core.errors import LightplaneError
from lightplane.plan.candidates import PoseLimits
from lightplane.plan.planner import PlannerOptions
from lightplane.plan.session import GuideSession
from lightplane.plan.volume import parse_working_volume
from lightplane.simulate.scene import TargetPlacement

if TYPE_CHECKING:
    from lightplane.live.engine import LiveEngine

__all__ = ["LiveGuide", "perturbed"]


def perturbed(p: TargetPlacement, rng: np.random.Generator, error_mm: float, error_deg: float) -> TargetPlacement:
    """``p`` as a user puts it: the centre off by ``error_mm`` (each axis), the normal by ``error_deg`` about a
    random axis (Gaussian)."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    a = np.radians(rng.normal(0.0, error_deg))
    n = p.normal * np.cos(a) + np.cross(axis, p.normal) * np.sin(a) + axis * (axis @ p.normal) * (1 - np.cos(a))
    return TargetPlacement(p.center + rng.normal(0.0, error_mm, 3), n, p.diameter_mm)


class LiveGuide:
    """One guided calibration over a live engine (module docstring)."""

    def __init__(self, engine: "LiveEngine") -> None:
        self.engine = engine
        self.session: GuideSession | None = None
        self._lock = threading.Lock()
        self._rng = np.random.default_rng(0)

    def start(self, target_sigma_mm: float, *, diameter_mm: float = 50.0, working_volume: str = "distance:380,520",
              percentile: float = 100.0) -> dict:
        sensor = self.engine.sensor
        if sensor is None:
            raise LightplaneError("the guide needs a sensor file (the camera and a rough light plane)")
        name = self.engine.settings().laser or next(iter(sensor.planes))
        plane = sensor.planes[name]
        vol = parse_working_volume(working_volume, sensor.camera, plane)
        opts = PlannerOptions(PoseLimits(float(diameter_mm)), target_sigma_mm=float(target_sigma_mm),
                              percentile=float(percentile))
        with self._lock:
            self.session = GuideSession(sensor.camera, plane, vol, opts)
        return self.state()

    def state(self) -> dict:
        s = self.session
        return {"active": False} if s is None else {"active": True, **s.summary()}

    def _session(self) -> GuideSession:
        if self.session is None:
            raise LightplaneError("no guided calibration: start one first")
        return self.session

    def accept(self, timeout: float = 10.0) -> dict:
        """The next frame exposed from now as the next placement."""
        s = self._session()
        try:
            frame = self.engine.capture(time.monotonic(), timeout=timeout)
        except TimeoutError as e:
            raise LightplaneError(str(e)) from None
        s.accept_image(frame.image)
        return self.state()

    def place_simulated(self, error_mm: float = 3.0, error_deg: float = 3.0) -> dict:
        """On the simulated sensor: the target where the guide says, off by the placement error."""
        show = getattr(self.engine.source, "show_placement", None)
        if show is None:
            raise LightplaneError("only the simulated target (sim:target) can be placed from here")
        sug = self._session().summary().get("suggestion")
        if sug is None:
            raise LightplaneError("the guide has no next placement (it stopped)")
        p = TargetPlacement(np.array(sug["centre_mm"]), np.array(sug["normal"]), float(sug["diameter_mm"]))
        q = perturbed(p, self._rng, float(error_mm), float(error_deg))
        show(q)
        return {"centre_mm": q.center.tolist(), "normal": q.normal.tolist(), "diameter_mm": q.diameter_mm}

