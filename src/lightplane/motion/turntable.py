"""Turntable axis calibration from a board standing on the table (docs/method.md §Turntable).

Images of a calibration board standing on the turntable, the table turned between
them.  Every image gives the board's pose by solvePnP with the calibrated camera
(:func:`lightplane.camera.board_pose.find_board_pose`), so every board point ``k`` is seen
at ``X_jk = R_j P_k + t_j`` (camera frame, image ``j``).  The axis is estimated two ways,
which must agree:

- **circles**: every board point turns on a circle about the axis.  The axis direction
  is the normal of the planes of those circles (smallest eigenvector of the pooled
  scatter of every point's positions about its own mean); each point's circle is fitted
  in its plane (algebraic circle, then geometric least squares); the circle centres lie
  on the axis, whose point is their mean.  The board origins' circle alone is reported
  too.
- **rotations**: the relative rotations ``Q_j = R_j R_0ᵀ`` all turn about the axis:
  its direction is the common null vector of ``Q_j − I`` (smallest eigenvector of
  ``Σ (Q_j − I)ᵀ(Q_j − I)``), its point solves ``(I − Q_j) c = t_j − Q_j t_0`` (least
  squares).  The table's angle at each image is the rotation angle of ``Q_j``.

The result is the circle estimate (it uses the board positions, which solvePnP
determines better than the board's orientation).  Uncertainty: a leave-one-image-out
jackknife of both estimates (covariance of the axis point, taken where the axis passes
nearest the board points' centroid, and of the direction), which covers the pose noise
of the images given, not errors of the camera calibration.  Per image: solvePnP's RMS
reprojection error (px), the RMS distance of its board points from their circles (mm)
and the table angle.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.motion.model import Turntable
from lightplane.camera.board_pose import find_board_pose
from lightplane.camera.diagnostics import outlier_views
from lightplane.core.io import too_few_images_message

__all__ = ["AxisEstimate", "TurntableCalibration", "calibrate_turntable", "axis_from_circles",
           "axis_from_rotations", "axis_agreement"]


@dataclass(frozen=True)
class AxisEstimate:
    """An axis: ``point_mm`` on it (camera frame), unit ``direction`` (up)."""

    point_mm: np.ndarray
    direction: np.ndarray

    def at(self, ref: np.ndarray) -> np.ndarray:
        """The axis' point nearest ``ref``."""
        return self.point_mm + ((ref - self.point_mm) @ self.direction) * self.direction


def _up(d: np.ndarray) -> np.ndarray:
    d = d / np.linalg.norm(d)
    return -d if d[1] > 0 else d


def _fit_circle_2d(xy: np.ndarray) -> tuple[np.ndarray, float]:
    """Circle through (J, 2) points: algebraic (Kåsa) start, geometric least squares."""
    from scipy.optimize import least_squares

    A = np.column_stack([2 * xy, np.ones(len(xy))])
    sol, *_ = np.linalg.lstsq(A, np.sum(xy**2, axis=1), rcond=None)
    c0 = sol[:2]
    r0 = float(np.sqrt(max(sol[2] + c0 @ c0, 1e-12)))
    res = least_squares(lambda x: np.linalg.norm(xy - x[:2], axis=1) - x[2], np.append(c0, r0), method="lm")
    return res.x[:2], float(res.x[2])


def axis_from_circles(points: np.ndarray) -> tuple[AxisEstimate, np.ndarray, np.ndarray]:
    """Axis from (J, K, 3) board points (image j, point k, camera frame mm).

    Returns the axis, the (K, 3) circle centres and the (J, K) distances of every point
    from its circle (mm: radial and axial parts combined).
    """
    X = np.asarray(points, dtype=np.float64)
    m = X.mean(axis=0)  # (K, 3) each point's mean position
    D = (X - m[None]).reshape(-1, 3)
    w, V = np.linalg.eigh(D.T @ D)
    a = _up(V[:, 0])
    e1 = V[:, 2] - (V[:, 2] @ a) * a
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    K = X.shape[1]
    centres = np.empty((K, 3))
    res = np.empty(X.shape[:2])
    for k in range(K):
        xy = np.column_stack([X[:, k] @ e1, X[:, k] @ e2])
        c2, r = _fit_circle_2d(xy)
        h = float(np.mean(X[:, k] @ a))
        centres[k] = c2[0] * e1 + c2[1] * e2 + h * a
        radial = np.linalg.norm(xy - c2, axis=1) - r
        axial = X[:, k] @ a - h
        res[:, k] = np.hypot(radial, axial)
    return AxisEstimate(centres.mean(axis=0), a), centres, res


def axis_from_rotations(R: np.ndarray, t: np.ndarray) -> tuple[AxisEstimate, np.ndarray]:
    """Axis from (J, 3, 3) board rotations and (J, 3) translations; and the table angle of
    every image relative to the first (deg, right-handed about the upward direction)."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    Q = R @ R[0].T  # (J, 3, 3)
    M = sum((q - np.eye(3)).T @ (q - np.eye(3)) for q in Q[1:])
    w, V = np.linalg.eigh(M)
    a = _up(V[:, 0])
    A = np.vstack([np.eye(3) - q for q in Q[1:]])
    b = np.concatenate([t[j] - Q[j] @ t[0] for j in range(1, len(Q))])
    c, *_ = np.linalg.lstsq(A, b, rcond=None)
    rv = Rotation.from_matrix(Q).as_rotvec()
    angles = np.degrees(rv @ a)
    return AxisEstimate(c, a), angles


def axis_agreement(e1: AxisEstimate, e2: AxisEstimate, ref: np.ndarray) -> tuple[float, float]:
    """Angle between the directions (deg) and distance between the axes near ``ref`` (mm)."""
    ang = float(np.degrees(np.arccos(np.clip(abs(e1.direction @ e2.direction), -1.0, 1.0))))
    p1, p2 = e1.at(ref), e2.at(ref)
    d = p2 - p1
    d = d - (d @ e1.direction) * e1.direction
    return ang, float(np.linalg.norm(d))


@dataclass(frozen=True)
class TurntableCalibration:
    """What :func:`calibrate_turntable` found."""

    turntable: Turntable
    circles: AxisEstimate
    rotations: AxisEstimate
    origins: AxisEstimate
    agreement_deg: float
    agreement_mm: float
    sigma_direction_deg: float
    sigma_point_mm: float
    images: list               # per image: name, used, angle_deg, pnp.reprojection_rms_px, circle_rms_mm
    skipped: dict = field(default_factory=dict)

    @property
    def agrees(self) -> bool:
        """The two estimates agree within 3 combined jackknife σ (direction and position)."""
        j = self.turntable.meta.get("jackknife", {})
        sd = np.hypot(j.get("sigma_direction_deg_circles", 0.0), j.get("sigma_direction_deg_rotations", 0.0))
        sp = np.hypot(j.get("sigma_point_mm_circles", 0.0), j.get("sigma_point_mm_rotations", 0.0))
        return bool(self.agreement_deg <= 3 * sd and self.agreement_mm <= 3 * sp)


def _estimates(Rs, ts, obj):
    X = np.einsum("jab,kb->jka", Rs, obj) + ts[:, None, :]
    circ, _, res = axis_from_circles(X)
    rot, angles = axis_from_rotations(Rs, ts)
    orig, _, _ = axis_from_circles(ts[:, None, :])
    return X, circ, rot, orig, res, angles


def _jackknife(Rs, ts, obj, ref):
    """Leave-one-image-out covariances (6x6: point near ``ref``, direction) of both estimates."""
    J = len(Rs)
    vals = {"circles": [], "rotations": []}
    for j in range(J):
        keep = np.arange(J) != j
        _, circ, rot, _, _, _ = _estimates(Rs[keep], ts[keep], obj)
        vals["circles"].append(np.concatenate([circ.at(ref), circ.direction]))
        vals["rotations"].append(np.concatenate([rot.at(ref), rot.direction]))
    out = {}
    for k, v in vals.items():
        v = np.array(v)
        dv = v - v.mean(axis=0)
        out[k] = (J - 1) / J * dv.T @ dv
    return out


def _sigmas(cov: np.ndarray, a: np.ndarray) -> tuple[float, float]:
    """σ of the direction (deg, total of the two components across it) and of the point across the axis (mm)."""
    P = np.eye(3) - np.outer(a, a)
    sp = float(np.sqrt(max(np.trace(P @ cov[:3, :3] @ P), 0.0)))
    sd = float(np.degrees(np.sqrt(max(np.trace(P @ cov[3:, 3:] @ P), 0.0))))
    return sd, sp


def _consistent_order(Rs: np.ndarray, ts: np.ndarray, obj: np.ndarray, target) -> list[int]:
    """Give every pose the same point order (in place); return the images changed.

    A board whose point grid is symmetric under a half turn (a chessboard or a symmetric
    circle grid) may be detected with its points in reverse order: the pose then differs
    from the board's by a half turn about its normal through the grid's centre ``c``
    (``R = R' diag(-1, -1, 1)``, ``t = t' - 2 R c``).  In the order given, each pose takes
    the variant nearer in rotation to the previous one (so successive images must turn
    the table by less than 90 deg).
    """
    if getattr(target, "kind", "chessboard") not in ("chessboard", "circles"):
        return []
    c = 0.5 * (obj.min(axis=0) + obj.max(axis=0))
    D = np.diag([-1.0, -1.0, 1.0])
    changed = []
    for j in range(1, len(Rs)):
        def angle(R):
            return np.arccos(np.clip((np.trace(R @ Rs[j - 1].T) - 1) / 2, -1.0, 1.0))

        R2 = Rs[j] @ D
        if angle(R2) < angle(Rs[j]):
            ts[j] = ts[j] - 2 * R2 @ c
            Rs[j] = R2
            changed.append(j)
    return changed


def _board_poses(images, names: list, camera: Camera, target, channel: str | None, reasons: dict | None,
                 progress) -> tuple[list, dict]:
    """The board's pose in every image where it is found, and the reason for every other image."""
    poses, skipped = [], {}
    for i, (img, name) in enumerate(zip(images, names)):
        if img is None:
            skipped[name] = (reasons or {}).get(name, "not a readable image")
        else:
            try:
                poses.append(find_board_pose(img, camera, target, name=name, channel=channel))
            except LightplaneError as e:
                msg = str(e)
                if "calibrated for" in msg:  # a camera mismatch is not a bad image
                    raise
                skipped[name] = msg.split(": ", 1)[1] if msg.startswith(name + ": ") else msg
        if progress is not None:
            progress(i)
    return poses, skipped


def _table_origin(circ, point: np.ndarray, X: np.ndarray, board_height_mm: float | None) -> tuple[np.ndarray, str]:
    """The turntable frame's origin on the axis and its description: at the level of the board points'
    centroid (``point``), or on the table's top ``board_height_mm`` below the board's lowest points."""
    if board_height_mm is None:
        return point, "on the axis at the level of the board points' centroid"
    if not np.isfinite(board_height_mm):
        raise LightplaneError(f"the board height must be a finite number of mm, got {board_height_mm!r}")
    lowest = float(np.min((X[0] - point) @ circ.direction))
    point = point + (lowest - float(board_height_mm)) * circ.direction
    return point, f"on the table's top: the board's lowest points {board_height_mm:g} mm above it"


def calibrate_turntable(images, camera: Camera, target, *, names=None, channel: str | None = None,
                        min_images: int = 4, reasons: dict | None = None, board_height_mm: float | None = None,
                        progress=None, keep_suspect: bool = False) -> TurntableCalibration:
    """The turntable's axis from images of a board standing on it at several table angles.

    ``images``: arrays (None for an unreadable one: its reason in ``reasons[name]``), ``names``
    their names; ``target`` a
    :class:`lightplane.camera.targets.Target`.  An image whose board is not found is skipped
    with its reason; fewer than ``min_images`` (at least 4: the jackknife) usable ones
    raise :class:`LightplaneError` saying why the others were not usable.  The images
    must turn the board by more than a few degrees in all (else the axis is not
    determined: an error too).  An image whose board pose fits its corners far worse than the
    others' (:func:`lightplane.camera.diagnostics.outlier_views` of the PnP RMS) is dropped with
    its reason (among ``skipped``, ``dropped: ...``) while enough images remain.

    The turntable file's point (the turntable frame's origin) is on the axis at the level
    of the board points' centroid, or, with ``board_height_mm`` (how far the board's lowest
    row of points is above the table's top), on the table's top.

    The axis from the board points' circles and the one from the rotations between poses are
    compared against their combined jackknife σ: beyond :data:`SUSPECT_SIGMAS` σ (direction or
    position) the calibration raises LightplaneError saying so, unless ``keep_suspect`` (the
    file's ``quality`` then says ``kept_by_request``); beyond 3 σ it is flagged (``agrees``).
    """

    names = list(names) if names is not None else [f"image {i}" for i in range(len(images))]
    if len(names) != len(images):
        raise LightplaneError(f"{len(images)} images but {len(names)} names")
    min_images = max(4, int(min_images))
    poses, skipped = _board_poses(images, names, camera, target, channel, reasons, progress)
    dropped = outlier_views([p.name for p in poses], [p.reprojection_rms_px for p in poses])
    if dropped and len(poses) - len(dropped) >= min_images:  # a board's corners far off the others': left out
        poses = [p for p in poses if p.name not in dropped]
        skipped.update({n: f"dropped: {why}" for n, why in dropped.items()})
    if len(poses) < min_images:
        raise LightplaneError(too_few_images_message("images", len(poses), min_images, list(skipped.items())))
    if any(p.ids is not None for p in poses):
        raise LightplaneError("calibrate-turntable needs every board point in every image (a board seen whole: "
                              "chessboard or circle grid); partial ChArUco views are not supported")
    obj = poses[0].object_mm
    assert obj is not None  # find_board_pose records the board points of the pose
    Rs = np.array([p.R_cam_board for p in poses])
    ts = np.array([p.t_cam_board for p in poses])
    flipped = _consistent_order(Rs, ts, obj, target)
    X, circ, rot, orig, res, angles = _estimates(Rs, ts, obj)
    span = float(np.ptp(angles))
    if span < 5.0:
        raise LightplaneError(f"the board turns by {span:.1f} deg over the {len(poses)} images: too little to find "
                              "the axis (turn the table by 30 deg or more in all)")
    ref = X.reshape(-1, 3).mean(axis=0)
    covs = _jackknife(Rs, ts, obj, ref)
    sd_c, sp_c = _sigmas(covs["circles"], circ.direction)
    sd_r, sp_r = _sigmas(covs["rotations"], rot.direction)
    ang, dist = axis_agreement(circ, rot, ref)
    ang_o, dist_o = axis_agreement(circ, orig, ref)
    per = []
    for j, p in enumerate(poses):
        per.append({"name": p.name, "used": True, "angle_deg": float(angles[j]), "pnp_rms_px": float(p.reprojection_rms_px),
                    "circle_rms_mm": float(np.sqrt(np.mean(res[j] ** 2))),
                    "t_cam_board_mm": ts[j].tolist(), "reordered": j in flipped})
    for name, why in skipped.items():
        per.append({"name": name, "used": False, "reason": why})
    point, origin = _table_origin(circ, circ.at(ref), X, board_height_mm)
    meta = {
        "method": "board circles (axis); rotations between poses (check)",
        "n_images": len(poses), "angle_span_deg": span,
        "reordered_images": [poses[j].name for j in flipped], "origin": origin,
        "sense_of_the_images": "counter-clockwise seen from above" if np.mean(np.diff(angles)) > 0
        else "clockwise seen from above",
        "estimates": {"circles": {"point_mm": circ.at(ref).tolist(), "direction": circ.direction.tolist()},
                      "rotations": {"point_mm": rot.at(ref).tolist(), "direction": rot.direction.tolist()},
                      "board_origins": {"point_mm": orig.at(ref).tolist(), "direction": orig.direction.tolist()}},
        "agreement": {"angle_deg": ang, "distance_mm": dist, "origins_angle_deg": ang_o, "origins_distance_mm": dist_o},
        "jackknife": {"sigma_direction_deg_circles": sd_c, "sigma_point_mm_circles": sp_c,
                      "sigma_direction_deg_rotations": sd_r, "sigma_point_mm_rotations": sp_r,
                      "covers": "pose noise of the images given (leave-one-image-out), not camera-calibration errors"},
        "circle_rms_mm": float(np.sqrt(np.mean(res**2))),
        "images": per, "skipped": skipped,
    }
    meta["quality"] = _axis_quality(ang, dist, np.hypot(sd_c, sd_r), np.hypot(sp_c, sp_r), keep_suspect)
    tt = Turntable.from_axis(point, circ.direction, covariance=covs["circles"], camera=camera.to_dict(), meta=meta)
    return TurntableCalibration(tt, circ, rot, orig, ang, dist, sd_c, sp_c, per, skipped)


#: the two axis estimates further apart than this many combined σ: the calibration is refused
SUSPECT_SIGMAS = 10.0


def _axis_quality(ang: float, dist: float, sd: float, sp: float, keep: bool) -> dict:
    """The turntable file's ``quality``: how far apart the circles' and the rotations' axes are in their combined
    σ; LightplaneError beyond :data:`SUSPECT_SIGMAS` unless ``keep``.  FabScan's 17 positions: 1.6 σ and
    2.0 σ with FabScan's camera, 2.7 σ and 3.9 σ with a camera calibrated from 25 of its views."""
    na, nd = ang / sd if sd > 0 else np.inf, dist / sp if sp > 0 else np.inf
    suspect = bool(max(na, nd) > SUSPECT_SIGMAS)
    rec = {"verdict": "suspect" if suspect else ("elevated" if max(na, nd) > 3 else "ok"),
           "direction_sigmas": float(na), "position_sigmas": float(nd), "suspect_sigmas": SUSPECT_SIGMAS,
           "kept_by_request": bool(suspect and keep)}
    if suspect:
        why = (f"the two axis estimates (board circles, rotations between poses) are {ang:.3f} deg and {dist:.3f} mm "
               f"apart, {na:.0f} and {nd:.0f} times their combined σ ({sd:.3f} deg, {sp:.3f} mm): the board moved on "
               "the table between images, images of another set-up among them, or a wrong camera?")
        if not keep:
            raise LightplaneError(f"suspect turntable axis: {why}; keep it with --keep-suspect")
        rec["diagnosis"] = why
    return rec
