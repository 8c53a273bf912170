"""Guided calibration with a board (Zhou's method): the state after each board pose, the next pose, the stop.

Zhou's method fits the light plane to the stripe's points on the boards (each triangulated on
its board's plane, :func:`lightplane.plane.zhou.stripe_points_on_board`) by total least squares,
:func:`lightplane.plane.zhou.fit_plane`, whose covariance is the first-order one of points with
a common noise ``σ`` along the plane's normal (estimated from the residuals).  In the minimal
plane parameters ``(α, β, d)`` a point ``p`` contributes the information ``g gᵀ / σ²`` with
``g = (t1·p, t2·p, 1)`` (``t1, t2`` the normal's tangent basis): the same model, so a board
pose's information is the sum over its stripe points, and a candidate's over points along
its chord at the observed density.  :class:`BoardPlanner` mirrors
:class:`lightplane.plan.planner.CalibrationPlanner`: :meth:`~BoardPlanner.add` (a board pose and its
stripe points), :meth:`~BoardPlanner.state`, :meth:`~BoardPlanner.suggest` (the board's outline in
the image), :meth:`~BoardPlanner.stop`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.plane.model import LightPlane
from lightplane.plane.uncertainty import WorkingVolume
from lightplane.plane.zhou import fit_plane, stripe_points_on_board
from lightplane.plan.candidates import PoseLimits, candidate_poses, tilt_deg
from lightplane.plan.information import VolumeModel, covariance_from_information
from lightplane.plan.planner import PlanState, PlannerOptions, StopVerdict
from lightplane.simulate.scene import TargetPlacement

__all__ = ["BoardPose3D", "BoardSuggestion", "BoardPlanner", "points_information", "board_chord"]


@dataclass(frozen=True)
class BoardPose3D:
    """A board's pose: centre (mm, camera frame), rotation board → camera (columns: its x, y axes and normal)."""

    center: np.ndarray
    R: np.ndarray

    def corners(self, size_mm: tuple[float, float]) -> np.ndarray:
        """(4, 3) the board's corners (mm, camera frame)."""
        w, h = 0.5 * size_mm[0], 0.5 * size_mm[1]
        xy = np.array([[-w, -h], [w, -h], [w, h], [-w, h]])
        return self.center + xy @ self.R[:, :2].T


@dataclass(frozen=True)
class BoardSuggestion:
    """The next board pose, its outline in the image (px), the figure now and after it (mm), tilt (deg), distance (mm)."""

    pose: BoardPose3D
    outline_px: np.ndarray
    sigma_now_mm: float
    sigma_after_mm: float
    tilt_deg: float
    distance_mm: float


def points_information(plane: LightPlane, G: np.ndarray, points: np.ndarray, sigma_mm: float,
                       weight: float = 1.0) -> np.ndarray:
    """(3, 3) information on ``(α, β, d)`` of points on the plane with noise ``sigma_mm`` along its normal,
    each counted ``weight`` times (``G``: :func:`lightplane.plan.information.plane_jacobian_g`)."""
    p = np.asarray(points, float).reshape(-1, 3)
    g = np.column_stack([p, np.ones(len(p))]) @ G  # ∂(n·p + d)/∂(α, β, d)
    return weight * (g.T @ g) / sigma_mm**2


def board_chord(plane: LightPlane, pose: BoardPose3D, size_mm: tuple[float, float]) -> np.ndarray | None:
    """(2, 3) the light plane's chord across the board's rectangle (mm), or None where it misses."""
    n = plane.normal
    gx, gy = n @ pose.R[:, 0], n @ pose.R[:, 1]
    s = float(n @ pose.center + plane.d)  # line: gx x + gy y + s = 0 in board coordinates
    gn = np.hypot(gx, gy)
    if gn < 1e-9:
        return None
    foot = -s * np.array([gx, gy]) / gn**2
    dirn = np.array([-gy, gx]) / gn
    lo, hi = -np.inf, np.inf
    for k, half in ((0, 0.5 * size_mm[0]), (1, 0.5 * size_mm[1])):
        if abs(dirn[k]) < 1e-12:
            if abs(foot[k]) > half:
                return None
            continue
        a, b = sorted(((-half - foot[k]) / dirn[k], (half - foot[k]) / dirn[k]))
        lo, hi = max(lo, a), min(hi, b)
    if not hi > lo:
        return None
    ends = np.array([foot + lo * dirn, foot + hi * dirn])
    return pose.center + ends @ pose.R[:, :2].T


class BoardPlanner:
    """Guided calibration of one light plane with a board of ``size_mm`` (the area the stripe is found on).

    ``options.limits``: its distance, tilt, margin and grid apply to the board (its diameter is not used;
    ``min_chord_frac`` of the board's shorter side); ``noise_mm`` the stripe points' sigma along the plane's
    normal until two poses give one from their residuals; ``density_per_px`` stripe points per px of chord.
    """

    def __init__(self, camera: Camera, plane: LightPlane, volume: WorkingVolume, options: PlannerOptions,
                 size_mm: tuple[float, float], *, noise_mm: float = 0.02, density_per_px: float = 1.0):
        if not (len(size_mm) == 2 and min(size_mm) > 0):
            raise LightplaneError(f"the board size must be two positive lengths (mm), got {size_mm}")
        if not (noise_mm > 0 and density_per_px > 0):
            raise LightplaneError("noise_mm and density_per_px must be positive")
        self.camera, self.rough, self.volume, self.options = camera, plane, volume, options
        self.size = (float(size_mm[0]), float(size_mm[1]))
        self.noise_mm, self.density = float(noise_mm), float(density_per_px)
        self.points: list[np.ndarray] = []
        self.poses: list[BoardPose3D] = []
        self.plane = plane
        self.solved = False
        self._set_plane(plane)

    def _set_plane(self, plane: LightPlane) -> None:
        self.plane = plane
        self.model = VolumeModel(self.camera, plane, self.volume, frame=self.options.frame, camera_plane=self.rough)
        self._cands: tuple[list[BoardPose3D], np.ndarray] | None = None

    def information(self) -> np.ndarray:
        G = self.model.G
        info = sum((points_information(self.plane, G, p, self.noise_mm) for p in self.points), np.zeros((3, 3)))
        if not self.solved:
            info = info + np.diag([np.radians(self.options.prior_deg) ** -2] * 2 + [self.options.prior_mm ** -2])
        return info

    def add(self, pose, stripe_uv: np.ndarray) -> PlanState:
        """Accept a board pose (:class:`lightplane.camera.board_pose.BoardPose`) and its stripe points (distorted px)."""
        pts = stripe_points_on_board(self.camera, pose, stripe_uv)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        if len(pts) < 3:
            raise LightplaneError(f"a board pose needs at least 3 stripe points on the board, got {len(pts)}")
        self.points.append(pts)
        self.poses.append(BoardPose3D(np.asarray(pose.t_cam_board, float), np.asarray(pose.R_cam_board, float)))
        if len(self.points) >= 2:
            try:
                fit = fit_plane(np.vstack(self.points))
            except LightplaneError:  # still collinear
                return self.state()
            r = np.concatenate([fit.signed_distance(p) for p in self.points])
            self.noise_mm = float(np.sqrt(np.sum(r**2) / max(len(r) - 3, 1)))
            self.solved = True
            self._set_plane(fit)
        return self.state()

    def state(self) -> PlanState:
        info = self.information()
        sig = self.model.sigma(info)
        fig = float(self.model.figure(sig, self.options.percentile))
        shape = VolumeModel(self.camera, self.plane, self.volume, frame="shape", camera_plane=self.rough)
        cov = covariance_from_information(info, self.model.G) if self.solved else None
        infos = np.array([points_information(self.plane, self.model.G, p, self.noise_mm) for p in self.points])
        shares = self.model.variance_shares(infos) if self.solved and len(infos) >= 2 else np.full(len(infos), np.nan)
        cov_dict = {"n": len(self.poses), "centres_mm": [np.round(p.center, 2).tolist() for p in self.poses],
                    "distance_mm": [float(np.linalg.norm(p.center)) for p in self.poses],
                    "tilt_deg": [float(np.degrees(np.arccos(abs(p.R[:, 2] @ p.center) / np.linalg.norm(p.center))))
                                 for p in self.poses]}
        return PlanState(len(self.poses), self.plane, cov, fig, float(np.sqrt(np.mean(sig**2))),
                         float(np.sqrt(np.mean(shape.sigma(info) ** 2))),
                         float(self.model.figure(self.model.camera_floor(), self.options.percentile)), shares,
                         cov_dict, self.solved,
                         covers="the stripe points' scatter about the fitted plane (Zhou's total least squares, "
                                "first order), and the camera's share where the files carry it")

    def _candidate(self, t: TargetPlacement) -> BoardPose3D | None:
        pose = BoardPose3D(t.center, t.basis())
        lim: PoseLimits = self.options.limits
        uv = self.camera.project(pose.corners(self.size))
        if not (np.all(np.isfinite(uv)) and np.all(self.camera.in_image(uv, margin=lim.margin_px))):
            return None
        ch = board_chord(self.plane, pose, self.size)
        if ch is None or np.linalg.norm(ch[1] - ch[0]) < lim.min_chord_frac * min(self.size):
            return None
        return pose

    def candidates(self) -> tuple[list[BoardPose3D], np.ndarray]:
        """Feasible board poses (the disc candidates' centres and tilts, the board's outline in the image) and
        their information."""
        if self._cands is None:
            lim = self.options.limits
            big = PoseLimits(max(self.size), distance_mm=lim.distance_mm, max_tilt_deg=lim.max_tilt_deg,
                             min_chord_frac=0.0, margin_px=-1e6, tilts_deg=lim.tilts_deg, n_azimuth=lim.n_azimuth,
                             grid=lim.grid)
            from_discs = candidate_poses(self.plane, self.volume, big)
            poses = [p for p in (self._candidate(t) for t in from_discs) if p is not None]
            if not poses:
                raise LightplaneError(f"no feasible pose of a {self.size[0]:g} x {self.size[1]:g} mm board with the "
                                      "stripe across it and its corners inside the image")
            infos = np.array([self._pose_information(p) for p in poses])
            self._cands = (poses, infos)
        return self._cands

    def _pose_information(self, pose: BoardPose3D) -> np.ndarray:
        ch = board_chord(self.plane, pose, self.size)
        assert ch is not None  # feasible poses have a chord
        pts = np.linspace(ch[0], ch[1], 32)
        length_px = float(np.sum(np.linalg.norm(np.diff(self.camera.project(pts), axis=0), axis=1)))
        return points_information(self.plane, self.model.G, pts, self.noise_mm, self.density * length_px / 32)

    def suggest(self) -> BoardSuggestion:
        """The feasible board pose whose expected information most lowers the figure."""
        info = self.information()
        poses, infos = self.candidates()
        figs = self.model.figure(self.model.sigma(info[None] + infos), self.options.percentile)
        k = int(np.argmin(figs))
        p = poses[k]
        tp = TargetPlacement(p.center, p.R[:, 2], 1.0)
        return BoardSuggestion(p, self.camera.project(p.corners(self.size)),
                               float(self.model.figure(self.model.sigma(info), self.options.percentile)),
                               float(figs[k]), tilt_deg(tp), float(np.linalg.norm(p.center)))

    def stop(self) -> StopVerdict:
        """Reached or continue for ``options.target_sigma_mm`` (and unreachable by the camera's share)."""
        target = self.options.target_sigma_mm
        if target is None:
            raise LightplaneError("no target sigma given: the stop rule needs one")
        st = self.state()
        if st.solved and st.n_placements >= self.options.min_placements and st.sigma_mm <= target:
            return StopVerdict("reached", st.n_placements, st.sigma_mm, target,
                               f"target reached: {st.sigma_mm:.4f} mm <= {target:g} mm after {st.n_placements} "
                               "board poses")
        if st.camera_floor_mm >= target:
            return StopVerdict("unreachable", st.n_placements, st.sigma_mm, target,
                               f"unreachable: the camera's own share alone is {st.camera_floor_mm:.4f} mm, above "
                               f"the target {target:g} mm")
        return StopVerdict("continue", st.n_placements, st.sigma_mm, target,
                           f"continue: {st.sigma_mm:.4f} mm > {target:g} mm after {st.n_placements} board poses")

