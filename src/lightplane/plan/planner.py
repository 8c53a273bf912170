"""Guided calibration with the circular target: the state after each placement, the next placement, the stop.

:class:`CalibrationPlanner` takes the placements one at a time (their rim and stripe points,
as :func:`lightplane.plane.calibrate.observe_image` finds them).  After each it solves the
plane (the ML refinement, from two placements on) and states:

- the plane and its covariance: from the placements' information at the solved plane and
  poses (:func:`lightplane.plane.ml.placement_information`, the Cramér–Rao model of the ML
  refinement), with the rim and stripe noise the ML refinement estimated from the residuals,
  inflated by their autocorrelation along the curves; before two placements, a prior from
  the rough plane;
- the predicted point sigma over the working volume (:class:`lightplane.plan.information.VolumeModel`:
  per point; the stated percentile, 100 the worst, and the RMS, camera frame and shape);
- the coverage: where the target has been (centres, distances, tilts).

:meth:`CalibrationPlanner.suggest` scores every feasible placement
(:func:`lightplane.plan.candidates.feasible_placements`) by the objective after adding its
expected information (the same model, at the current plane, with the noise estimated so far)
and returns the best, with its outline in the image and the predicted sigma after it.  The
stripe's noise per px of chord need not be the same for every placement (on the realistic
renders it falls by half from a disc facing the camera to one tilted by 50°, and with the
distance): from four placements on, a trend of its logarithm in the tilt, the distance and the
angle to the light sheet is fitted on the placements taken (:func:`fit_stripe_trend`, each
slope with a zero-mean prior, so data without a trend leave every placement as noisy as the
average one), and each candidate's stripe counts as its chord divided by its expected noise
over the average squared.  The state's sigma (the placements taken) keeps the ML refinement's
single noise model.
:meth:`CalibrationPlanner.stop` applies the stop rule; :meth:`CalibrationPlanner.plan` plays
the greedy choice forward without images (the offline plan).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.core.geometry import ray_plane
from lightplane.plane.calibrate import stripe_line_scatter_px
from lightplane.plane.circle_pose import circle_poses, fit_rim_conic
from lightplane.plane.model import LightPlane
from lightplane.plane.ml import placement_information, refine_ml
from lightplane.plane.solvers import calibrate_plane_from_points
from lightplane.plane.uncertainty import WorkingVolume
from lightplane.plan.candidates import PoseLimits, feasible_placements, outline_px, sheet_angle_deg, tilt_deg
from lightplane.plan.information import FRAMES, VolumeModel, covariance_from_information
from lightplane.simulate.scene import TargetPlacement

__all__ = ["NoiseModel", "PlannerOptions", "Suggestion", "PlanState", "StopVerdict", "CalibrationPlanner",
           "StripeNoiseTrend", "fit_stripe_trend", "COVERS"]

#: What the planner's sigmas cover (one sentence, printed with them).
COVERS = ("the plane calibration's image noise (rim and stripe points: their sigmas and their correlation along the "
          "curves, estimated from the residuals of the placements so far; errors shared within an image not "
          "included), first order, and the camera's share where the files carry it")


@dataclass(frozen=True)
class NoiseModel:
    """Image noise of a placement, per pixel of curve length.

    ``sigma_rim_px`` and ``sigma_stripe_px``: the sigma of one point when there is one point per
    px of rim or stripe, its correlation along the curve included (``sigma sqrt(tau)``); a curve
    of ``L`` px then carries the information of ``L`` such points.  The defaults are those of the
    realistic renders (docs/calibration-guide.md: rim 0.053 px, stripe centres 0.11 px with an
    autocorrelation time of ~6); after two placements the planner uses the ML refinement's.
    """

    sigma_rim_px: float = 0.06
    sigma_stripe_px: float = 0.27

    def __post_init__(self) -> None:
        if not (self.sigma_rim_px > 0 and self.sigma_stripe_px > 0):
            raise LightplaneError(f"noise sigmas must be positive, got rim {self.sigma_rim_px} px, "
                                  f"stripe {self.sigma_stripe_px} px")


@dataclass(frozen=True)
class PlannerOptions:
    """Options of :class:`CalibrationPlanner`.

    ``target_sigma_mm``: the sigma to reach (None: no stop rule); ``percentile``: which point
    sigma over the volume is the figure (100: the worst); ``frame``: ``"camera"`` or ``"shape"``;
    ``max_placements``: the most placements a calibration may take (beyond: unreachable);
    ``min_placements``: fewest before a stop; ``prior_deg`` / ``prior_mm``: the rough plane's
    uncertainty (normal, offset) until two placements are solved; ``noise``: :class:`NoiseModel`
    until then; ``limits``: :class:`lightplane.plan.candidates.PoseLimits` (its diameter is the disc's);
    ``repeat_mm`` / ``repeat_deg``: a candidate this close to a placement taken (centre, normal) is not
    suggested again (:meth:`CalibrationPlanner.near`; 0 allows repeats).
    """

    limits: PoseLimits
    target_sigma_mm: float | None = None
    percentile: float = 100.0
    frame: str = "camera"
    max_placements: int = 30
    min_placements: int = 3
    prior_deg: float = 2.0
    prior_mm: float = 5.0
    noise: NoiseModel = field(default_factory=NoiseModel)
    repeat_mm: float = 10.0
    repeat_deg: float = 10.0

    def __post_init__(self) -> None:
        if not isinstance(self.limits, PoseLimits):
            raise LightplaneError(f"limits must be PoseLimits, got {type(self.limits).__name__}")
        if self.target_sigma_mm is not None and not (np.isfinite(self.target_sigma_mm) and self.target_sigma_mm > 0):
            raise LightplaneError(f"the target sigma must be positive, got {self.target_sigma_mm} mm")
        if not (0 < self.percentile <= 100):
            raise LightplaneError(f"percentile must be in (0, 100], got {self.percentile}")
        if self.frame not in FRAMES:
            raise LightplaneError(f"frame must be one of {', '.join(FRAMES)}, got {self.frame!r}")
        if not (2 <= self.min_placements <= self.max_placements):
            raise LightplaneError(f"need 2 <= min_placements <= max_placements, got {self.min_placements} and "
                                  f"{self.max_placements}")
        if not (self.prior_deg > 0 and self.prior_mm > 0):
            raise LightplaneError("prior_deg and prior_mm must be positive")
        if not (self.repeat_mm >= 0 and self.repeat_deg >= 0):
            raise LightplaneError("repeat_mm and repeat_deg must be >= 0")


@dataclass(frozen=True)
class Suggestion:
    """The next placement: the disc's pose (camera frame), its rim in the image (the ghost outline, px),
    the figure now and after it (mm), and its tilt (deg) and distance (mm)."""

    placement: TargetPlacement
    outline_px: np.ndarray
    sigma_now_mm: float
    sigma_after_mm: float
    tilt_deg: float
    distance_mm: float

    def to_dict(self) -> dict:
        return {"centre_mm": self.placement.center.tolist(), "normal": self.placement.normal.tolist(),
                "diameter_mm": self.placement.diameter_mm, "tilt_deg": self.tilt_deg,
                "distance_mm": self.distance_mm, "outline_px": np.round(self.outline_px, 2).tolist(),
                "sigma_now_mm": self.sigma_now_mm, "sigma_after_mm": self.sigma_after_mm}


@dataclass(frozen=True)
class PlanState:
    """After the placements so far: the plane, its covariance (None before two placements), the figure
    (the stated percentile of the point sigma, mm), RMS camera-frame and shape sigma (mm), the camera's
    floor (mm, at the same percentile), each placement's share of the information and its coverage."""

    n_placements: int
    plane: LightPlane
    covariance: np.ndarray | None
    sigma_mm: float
    rms_camera_mm: float
    rms_shape_mm: float
    camera_floor_mm: float
    shares: np.ndarray
    coverage: dict
    solved: bool
    covers: str = COVERS


@dataclass(frozen=True)
class StopVerdict:
    """The stop rule: ``status`` ``"continue"``, ``"reached"`` or ``"unreachable"``, and one sentence."""

    status: str
    n_placements: int
    sigma_mm: float
    target_mm: float
    message: str


@dataclass
class _Accepted:
    rim_uv: np.ndarray
    stripe_uv: np.ndarray
    pose: TargetPlacement | None = None


def _curve_lengths_px(camera: Camera, plane: LightPlane, placement: TargetPlacement) -> tuple[float, float]:
    """Rim perimeter and chord length of a placement in the image (px)."""
    rim = outline_px(camera, placement, 96)
    per = float(np.sum(np.linalg.norm(np.diff(np.vstack([rim, rim[:1]]), axis=0), axis=1)))
    chord = placement.chord(plane)
    if chord is None:
        return per, 0.0
    c = camera.project(np.linspace(chord[0], chord[1], 16))
    return per, float(np.sum(np.linalg.norm(np.diff(c, axis=0), axis=1)))


#: the stripe-noise trend's prior: each exponent ~ N(0, TREND_PRIOR_SD²) (a factor e over a factor e of the feature)
TREND_PRIOR_SD = 1.0
#: placements needed before the trend is fitted (with fewer the stripe noise is the same for every placement)
TREND_MIN_PLACEMENTS = 4


def _trend_features(plane: LightPlane, placement: TargetPlacement) -> np.ndarray:
    """What a placement's stripe noise per px may depend on: log of the foreshortening (cos of the tilt to the
    line of sight), of the distance (mm) and of the sine of the angle between the disc and the light sheet
    (the stripe's width on the disc grows as the sheet grazes it)."""
    c = max(float(np.cos(np.radians(tilt_deg(placement)))), 0.05)
    s = max(float(np.sin(np.radians(sheet_angle_deg(plane, placement)))), 0.05)
    return np.array([np.log(c), np.log(float(np.linalg.norm(placement.center))), np.log(s)])


@dataclass(frozen=True)
class StripeNoiseTrend:
    """How the stripe's noise per px of chord varies between placements (fitted on the placements taken).

    ``log sigma = log sigma_mean + slope . (features - mean)`` (:func:`_trend_features`); the slopes have a
    zero-mean prior of sd :data:`TREND_PRIOR_SD`, so on data without a trend they stay near 0 and every
    placement is expected to be as noisy as the average one.  ``factor(x)`` is a placement's sigma over the
    average placement's, held within 1/4 .. 4 (an extrapolation far outside the placements taken is not
    trusted further)."""

    slope: np.ndarray
    mean: np.ndarray

    def factor(self, x: np.ndarray) -> float:
        return float(np.exp(np.clip(self.slope @ (x - self.mean), -np.log(4.0), np.log(4.0))))


def _stripe_sigma_per_px(camera: Camera, stripe_uv: np.ndarray, chord_px: float) -> float:
    """A placement's stripe noise per px of chord: the robust scatter of its points about their straight
    line (:func:`lightplane.plane.calibrate.stripe_line_scatter_px`) times the root of px per point."""
    if len(stripe_uv) < 6 or chord_px <= 0:
        return float("nan")
    return stripe_line_scatter_px(camera, stripe_uv) * float(np.sqrt(chord_px / len(stripe_uv)))


def fit_stripe_trend(features: np.ndarray, sigmas_px: np.ndarray) -> StripeNoiseTrend | None:
    """:class:`StripeNoiseTrend` from each placement's features and stripe noise per px (Bayesian linear
    regression of log sigma, the slopes' prior :data:`TREND_PRIOR_SD`, the residual scale estimated); None
    with fewer than :data:`TREND_MIN_PLACEMENTS` usable placements."""
    X = np.asarray(features, float).reshape(len(sigmas_px), -1)
    y = np.log(np.asarray(sigmas_px, float))
    ok = np.isfinite(y) & np.all(np.isfinite(X), axis=1)
    if ok.sum() < TREND_MIN_PLACEMENTS:
        return None
    X, y = X[ok], y[ok]
    mx = X.mean(axis=0)
    Xc, yc = X - mx, y - y.mean()
    s2 = max(float(np.var(yc)), 1e-6)      # the scatter about the mean: an upper bound of the residual's
    lam = s2 / TREND_PRIOR_SD**2
    slope = np.linalg.solve(Xc.T @ Xc + lam * np.eye(X.shape[1]), Xc.T @ yc)
    return StripeNoiseTrend(slope, mx)


class CalibrationPlanner:
    """Guided calibration of one light plane with a circular target (module docstring).

    ``camera``: the calibrated camera; ``plane``: a rough plane (a plane file, or the design);
    ``volume``: where measurements will be made; ``options``: :class:`PlannerOptions`.
    """

    def __init__(self, camera: Camera, plane: LightPlane, volume: WorkingVolume, options: PlannerOptions):
        self.camera, self.rough, self.volume, self.options = camera, plane, volume, options
        self.radius = 0.5 * options.limits.diameter_mm
        self.accepted: list[_Accepted] = []
        self.plane = plane
        self.noise = options.noise
        self.solved = False
        self._info_cur: np.ndarray | None = None
        self._infos = np.zeros((0, 3, 3))
        self._model: VolumeModel | None = None
        self._cands: tuple[list[TargetPlacement], np.ndarray] | None = None
        self.trend: StripeNoiseTrend | None = None
        self._set_plane(plane)

    # ---------------------------------------------------------------- state
    def _set_plane(self, plane: LightPlane) -> None:
        self.plane = plane
        self._model = VolumeModel(self.camera, plane, self.volume, frame=self.options.frame, camera_plane=self.rough)
        self._shape_model = VolumeModel(self.camera, plane, self.volume, frame="shape", camera_plane=self.rough) \
            if self.options.frame == "camera" else self._model
        self._frame_model = self._model if self.options.frame == "camera" else \
            VolumeModel(self.camera, plane, self.volume, frame="camera", camera_plane=self.rough)
        self._cands = None

    @property
    def model(self) -> VolumeModel:
        assert self._model is not None  # set on construction
        return self._model

    def _prior(self) -> np.ndarray:
        return np.diag([np.radians(self.options.prior_deg) ** -2] * 2 + [self.options.prior_mm ** -2])

    def information(self) -> np.ndarray:
        """(3, 3) the plane's information now (minimal parameters at the current plane)."""
        return self._infos.sum(axis=0) + (0 if self.solved else self._prior())

    def _counts(self, placements: list[TargetPlacement]) -> tuple[np.ndarray, np.ndarray]:
        """Each placement's rim and stripe length (px): the number of unit-density points it stands for, the
        stripe's divided by its expected noise relative to the average placement's squared (:attr:`trend`)."""
        lengths = np.array([_curve_lengths_px(self.camera, self.plane, p) for p in placements]).reshape(-1, 2)
        stripe = np.maximum(lengths[:, 1], 2.0)
        if self.trend is not None:
            f = np.array([self.trend.factor(_trend_features(self.plane, p)) for p in placements])
            stripe = stripe / f**2
        return np.maximum(lengths[:, 0], 8.0), stripe

    def _placement_infos(self, placements: list[TargetPlacement], observations=None) -> np.ndarray:
        if not placements:
            return np.zeros((0, 3, 3))
        rim_n, st_n = (None, None) if observations is not None else self._counts(placements)
        return placement_information(self.camera, self.radius, placements, self.plane,
                                     sigma_rim_px=self.noise.sigma_rim_px, sigma_stripe_px=self.noise.sigma_stripe_px,
                                     rim_points=rim_n, stripe_points=st_n, observations=observations)[0]

    def state(self) -> PlanState:
        """Where the calibration stands (see :class:`PlanState`)."""
        info = self.information()
        sig = self.model.sigma(info)
        fig = float(self.model.figure(sig, self.options.percentile))
        rms_c = float(np.sqrt(np.mean(self._frame_model.sigma(info) ** 2)))
        rms_s = float(np.sqrt(np.mean(self._shape_model.sigma(info) ** 2)))
        floor = float(self.model.figure(self.model.camera_floor(), self.options.percentile))
        shares = self.model.variance_shares(self._infos) if len(self._infos) >= 2 and self.solved else \
            np.full(len(self._infos), np.nan)
        cov = covariance_from_information(info, self.model.G) if self.solved else None
        return PlanState(len(self.accepted), self.plane, cov, fig, rms_c, rms_s, floor, shares, self.coverage(),
                         self.solved)

    def coverage(self) -> dict:
        """Where the target has been: centres (mm, camera frame), distances (mm), tilts (deg), and the working
        volume's depth range (mm) for comparison."""
        poses = [a.pose for a in self.accepted if a.pose is not None]
        z = self.volume.points[:, 2]
        out: dict = {"n": len(poses), "volume_depth_mm": [float(z.min()), float(z.max())],
                     "centres_mm": [np.round(p.center, 2).tolist() for p in poses],
                     "distance_mm": [float(np.linalg.norm(p.center)) for p in poses],
                     "tilt_deg": [tilt_deg(p) for p in poses]}
        if poses:
            cz = np.array([p.center[2] for p in poses])
            span = max(float(z.max() - z.min()), 1e-9)
            out["depth_covered_frac"] = float(min(1.0, (cz.max() - cz.min()) / span))
        return out

    # ---------------------------------------------------------------- placements
    def add(self, rim_uv: np.ndarray, stripe_uv: np.ndarray) -> PlanState:
        """Accept a placement (its rim and stripe points, distorted px) and return the new state."""
        rim = np.asarray(rim_uv, float).reshape(-1, 2)
        st = np.asarray(stripe_uv, float).reshape(-1, 2)
        if len(rim) < 5 or len(st) < 2:
            raise LightplaneError(f"a placement needs at least 5 rim and 2 stripe points, got {len(rim)} and {len(st)}")
        self.accepted.append(_Accepted(rim, st))
        if len(self.accepted) >= 2:
            self._solve()
        else:
            self.accepted[-1].pose = self._pose_from_rim(rim, st)
            self._infos = self._placement_infos([self.accepted[-1].pose])
        return self.state()

    def _pose_from_rim(self, rim_uv: np.ndarray, stripe_uv: np.ndarray) -> TargetPlacement:
        """Of the rim's two circle poses, the one on which the stripe's points lie nearer the current plane."""
        conic = fit_rim_conic(self.camera.undistort_points(rim_uv))
        xy = self.camera.undistort_points(stripe_uv, normalized=True)

        def off(q) -> float:
            pts = ray_plane(xy, np.asarray(q.normal), np.asarray(q.center))
            return float(np.nanmean(self.plane.signed_distance(pts) ** 2))

        best = min(circle_poses(conic, self.camera.K, self.radius), key=off)
        return TargetPlacement(best.center, best.normal, 2 * self.radius)

    def _solve_points(self) -> tuple[LightPlane, list, dict]:
        """The plane, each placement's pose (None: not used) and the noise model: the ML calibration of
        :func:`lightplane.plane.solvers.calibrate_plane_from_points`; where its chords are still ambiguous
        (two placements can be), the ML refinement from the poses the current plane picks."""
        rims = [a.rim_uv for a in self.accepted]
        stripes = [a.stripe_uv for a in self.accepted]
        try:
            cal = calibrate_plane_from_points(self.camera, 2 * self.radius, rims, stripes, method="ml",
                                              min_placements=2)
            poses = [p.pose if p.used else None for p in cal.placements]
            return cal.plane, poses, dict(cal.plane.meta.get("noise_model") or {})
        except LightplaneError:
            pass
        poses0 = [self._pose_from_rim(r, s) for r, s in zip(rims, stripes)]
        res = refine_ml(self.camera, self.radius, rims, stripes, self.plane, poses0)
        nm = {"sigma_rim_px": res.sigma_rim_px, "sigma_stripe_px": res.sigma_stripe_px, "tau_rim": res.tau_rim,
              "tau_stripe": res.tau_stripe}
        return res.plane, list(res.poses), nm

    def _solve(self) -> None:
        try:
            plane, poses, nm = self._solve_points()
        except LightplaneError:  # not yet determined (e.g. parallel chords): the prior and the rim's pose
            self.accepted[-1].pose = self._pose_from_rim(self.accepted[-1].rim_uv, self.accepted[-1].stripe_uv)
            self._infos = self._placement_infos([a.pose for a in self.accepted if a.pose is not None])
            return
        per_point = NoiseModel(float(nm.get("sigma_rim_px", 0.0) or 0.0) * np.sqrt(float(nm.get("tau_rim", 1.0))),
                               float(nm.get("sigma_stripe_px", 0.0) or 0.0) * np.sqrt(float(nm.get("tau_stripe", 1.0))))
        self._set_plane(LightPlane(plane.normal, plane.d, plane.covariance, meta=dict(plane.meta)))
        self.solved = True
        for a, q in zip(self.accepted, poses):
            a.pose = None if q is None else TargetPlacement(q.center, q.normal, 2 * self.radius)
        keep = [(a.pose, (a.rim_uv, a.stripe_uv)) for a in self.accepted if a.pose is not None]
        self.noise = per_point
        self._infos = self._placement_infos([k[0] for k in keep], [k[1] for k in keep])
        # per px of curve, for placements not yet taken: the observed points' density along the rims and stripes
        lengths = np.array([_curve_lengths_px(self.camera, self.plane, q) for q, _ in keep])
        counts = np.array([[len(o[0]), len(o[1])] for _, o in keep], float)
        d = np.median(counts / np.maximum(lengths, 1.0), axis=0)
        self.noise = NoiseModel(per_point.sigma_rim_px / np.sqrt(d[0]), per_point.sigma_stripe_px / np.sqrt(d[1]))
        # how the stripe's noise per px differs between placements (the tilt, the distance, the sheet's angle)
        self.trend = fit_stripe_trend(np.array([_trend_features(self.plane, q) for q, _ in keep]),
                                      np.array([_stripe_sigma_per_px(self.camera, o[1], ln[1])
                                                for (_, o), ln in zip(keep, lengths)]))

    # ---------------------------------------------------------------- the next placement
    def candidates(self) -> tuple[list[TargetPlacement], np.ndarray]:
        """The feasible placements and their information (n, 3, 3) at the current plane and noise."""
        if self._cands is None:
            cands = feasible_placements(self.camera, self.plane, self.volume, self.options.limits)
            self._cands = (cands, self._placement_infos(cands))
        return self._cands

    def _best(self, info: np.ndarray, taken: list[TargetPlacement]) -> tuple[int, float]:
        """The best candidate away from the poses ``taken`` (:meth:`near`), and the figure after it."""
        cands, infos = self.candidates()
        figs = self.model.figure(self.model.sigma(info[None] + infos), self.options.percentile)
        free = np.array([not any(self.near(c, t) for t in taken) for c in cands])
        k = int(np.argmin(np.where(free, figs, np.inf))) if free.any() else int(np.argmin(figs))
        return k, float(figs[k])

    def near(self, a: TargetPlacement, b: TargetPlacement) -> bool:
        """Whether two placements are nearly the same: centres within ``options.repeat_mm``, normals within
        ``options.repeat_deg``.  The guide does not suggest a place again: errors shared by one image (a
        pose's own bias in the rim or the stripe, which the noise model does not include) do not average
        out over images taken at the same place."""
        o = self.options
        return bool(np.linalg.norm(a.center - b.center) < o.repeat_mm
                    and np.degrees(np.arccos(np.clip(a.normal @ b.normal, -1, 1))) < o.repeat_deg)

    def suggest(self) -> Suggestion:
        """The feasible placement whose expected information most lowers the figure (module docstring)."""
        info = self.information()
        now = float(self.model.figure(self.model.sigma(info), self.options.percentile))
        k, after = self._best(info, [a.pose for a in self.accepted if a.pose is not None])
        p = self.candidates()[0][k]
        return Suggestion(p, outline_px(self.camera, p), now, after, tilt_deg(p), float(np.linalg.norm(p.center)))

    def plan(self, n: int | None = None) -> list[Suggestion]:
        """Greedy placements from now on, each with the predicted figure after it, without images: up to ``n``
        (default: until the target sigma or ``max_placements`` in all)."""
        info = self.information()
        solved = self.solved
        total = len(self.accepted)
        limit = self.options.max_placements - total if n is None else int(n)
        out = []
        cands, infos = self.candidates()
        target = self.options.target_sigma_mm
        taken = [a.pose for a in self.accepted if a.pose is not None]
        for _ in range(max(limit, 0)):
            now = float(self.model.figure(self.model.sigma(info), self.options.percentile))
            k, after = self._best(info, taken)
            p = cands[k]
            taken.append(p)
            out.append(Suggestion(p, outline_px(self.camera, p), now, after, tilt_deg(p),
                                  float(np.linalg.norm(p.center))))
            info = info + infos[k]
            total += 1
            if not solved and total >= 2:  # once solved, the prior no longer counts
                info, solved = info - self._prior(), True
            if n is None and target is not None and after <= target and total >= self.options.min_placements:
                break
        return out

    # ---------------------------------------------------------------- the stop rule
    def stop(self) -> StopVerdict:
        """Reached, unreachable (and why, with numbers) or continue, for ``options.target_sigma_mm``."""
        target = self.options.target_sigma_mm
        if target is None:
            raise LightplaneError("no target sigma given: the stop rule needs one")
        st = self.state()
        n, what = st.n_placements, self.figure_name()
        if st.solved and n >= self.options.min_placements and st.sigma_mm <= target:
            return StopVerdict("reached", n, st.sigma_mm, target,
                               f"target reached: {what} {st.sigma_mm:.4f} mm <= {target:g} mm after {n} placements")
        if st.camera_floor_mm >= target:
            return StopVerdict("unreachable", n, st.sigma_mm, target, self._camera_message(st.camera_floor_mm))
        rest = self.plan()
        if rest and rest[-1].sigma_after_mm > target:
            return StopVerdict("unreachable", n, st.sigma_mm, target, self.unreachable_message(rest[-1].sigma_after_mm))
        return StopVerdict("continue", n, st.sigma_mm, target,
                           f"continue: {what} {st.sigma_mm:.4f} mm > {target:g} mm after {n} placements; "
                           f"about {len(rest)} more expected")

    def plan_verdict(self, steps: list[Suggestion]) -> StopVerdict:
        """What a forward plan (:meth:`plan`) comes to: the target reached after how many placements in all,
        or unreachable and why; without a target, the figure after the plan."""
        target = self.options.target_sigma_mm
        n = len(self.accepted) + len(steps)
        end = steps[-1].sigma_after_mm if steps else float(self.model.figure(self.model.sigma(self.information()),
                                                                              self.options.percentile))
        if target is None:
            return StopVerdict("continue", n, end, float("nan"),
                               f"after {n} placements: predicted {self.figure_name()} {end:.4f} mm")
        if end <= target:
            return StopVerdict("reached", n, end, target,
                               f"target {target:g} mm reached after {n} placements (predicted {end:.4f} mm)")
        floor = float(self.model.figure(self.model.camera_floor(), self.options.percentile))
        if floor >= target:
            return StopVerdict("unreachable", n, end, target, self._camera_message(floor))
        return StopVerdict("unreachable", n, end, target, self.unreachable_message(end))

    def _camera_message(self, floor: float) -> str:
        return (f"unreachable: the camera's own share alone is {floor:.4f} mm ({self.figure_name()}), above the "
                f"target {self.options.target_sigma_mm:g} mm; recalibrate the camera (more, more tilted views)")

    def figure_name(self) -> str:
        q = self.options.percentile
        where = "worst point" if q >= 100 else f"{q:g}th percentile of the points"
        return f"{where} sigma ({'camera frame' if self.options.frame == 'camera' else 'shape'})"

    def triangulation_angle_deg(self) -> float:
        """The smallest angle (deg) between a working-volume ray and the light plane: small angles magnify every
        error of the plane (by ``1/sin``)."""
        rays = self.camera.rays(self.model.uv, unit=True)
        return float(np.degrees(np.arcsin(np.min(np.abs(rays @ self.plane.normal)))))

    def unreachable_message(self, sigma_end: float) -> str:
        ang = self.triangulation_angle_deg()
        m = self.options.max_placements
        return (f"unreachable within {m} placements: the best plan ends at {sigma_end:.4f} mm "
                f"({self.figure_name()}) against the target {self.options.target_sigma_mm:g} mm; the rays meet the "
                f"light plane at {ang:.1f} deg at the least (errors of the plane grow by 1/sin = "
                f"{1 / np.sin(np.radians(ang)):.1f}x there): a wider triangulation angle or a smaller working "
                "volume would reach it")

    def with_options(self, **changes) -> "CalibrationPlanner":
        """A fresh planner with changed options and the same camera, rough plane and volume (no placements)."""
        return CalibrationPlanner(self.camera, self.rough, self.volume, replace(self.options, **changes))
