"""A guided calibration as a live page runs it: images in, the guide's state as plain JSON out.

:class:`GuideSession` holds a :class:`lightplane.plan.planner.CalibrationPlanner`; each accepted
image (:meth:`GuideSession.accept_image`: the circle target and the stripe on it found by
:func:`lightplane.plane.calibrate.observe_image`) is one placement.  :meth:`GuideSession.summary`
is what a page draws: the suggested placement's outline (px, for the ghost), the predicted σ now
and after it, the σ after each placement so far, the coverage and the stop verdict, each number
with its unit in its key.
"""

from __future__ import annotations

import threading

import numpy as np

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.plane.calibrate import ObserveOptions, observe_image
from lightplane.plane.model import LightPlane
from lightplane.plane.uncertainty import WorkingVolume
from lightplane.plan.planner import COVERS, CalibrationPlanner, PlannerOptions
from lightplane.plan.volume import describe_volume

__all__ = ["GuideSession"]


class GuideSession:
    """One guided calibration (thread-safe: a page's requests may come from several threads)."""

    def __init__(self, camera: Camera, plane: LightPlane, volume: WorkingVolume, options: PlannerOptions, *,
                 observe: ObserveOptions | None = None):
        if options.target_sigma_mm is None:
            raise LightplaneError("a guided calibration needs a target sigma")
        self.planner = CalibrationPlanner(camera, plane, volume, options)
        self.observe = observe
        self.history: list[float] = []
        self._lock = threading.Lock()
        self._summary: dict | None = None

    def accept_image(self, image: np.ndarray) -> dict:
        """Take ``image`` as the next placement; raises :class:`LightplaneError` (nothing changes) when the
        target or the stripe on it is not found."""
        pl = self.planner
        obs = observe_image(image, pl.camera, 2 * pl.radius, options=self.observe)
        if not obs.ok:
            raise LightplaneError(f"placement not taken: {obs.reason}")
        return self.accept_points(obs.rim_uv, obs.stripe_uv)

    def accept_points(self, rim_uv: np.ndarray, stripe_uv: np.ndarray) -> dict:
        """Take a placement's rim and stripe points (distorted px) as the next placement."""
        with self._lock:
            st = self.planner.add(rim_uv, stripe_uv)
            self.history.append(st.sigma_mm)
            self._summary = None
        return self.summary()

    def summary(self) -> dict:
        """The guide's state as plain JSON values (see the module docstring)."""
        with self._lock:
            if self._summary is None:
                self._summary = self._build()
            return self._summary

    def _build(self) -> dict:
        pl = self.planner
        st = pl.state()
        verdict = pl.stop()
        out: dict = {"n_placements": st.n_placements, "figure": pl.figure_name(), "sigma_mm": _num(st.sigma_mm),
                     "target_sigma_mm": pl.options.target_sigma_mm, "rms_camera_frame_mm": _num(st.rms_camera_mm),
                     "rms_shape_mm": _num(st.rms_shape_mm), "camera_floor_mm": _num(st.camera_floor_mm),
                     "history_sigma_mm": [_num(x) for x in self.history], "solved": st.solved,
                     "verdict": {"status": verdict.status, "message": verdict.message},
                     "coverage": st.coverage, "working_volume": describe_volume(pl.volume), "covers": COVERS,
                     "image_size_px": [pl.camera.width, pl.camera.height], "suggestion": None}
        if verdict.status == "continue":
            s = pl.suggest()
            out["suggestion"] = {k: (_num(v) if isinstance(v, float) else v) for k, v in s.to_dict().items()}
        return out


def _num(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None
