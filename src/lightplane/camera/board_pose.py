"""A calibration board's pose in one image: the target found, its points matched to the board, and the pose
solved with the camera's lens model (``cv2.solvePnP`` and Levenberg–Marquardt); circle grids' dot centroids are
moved to the projected circle centres at the pose."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lightplane.camera.model import Camera, as_points
from lightplane.camera.targets import as_target, correct_circle_centres, dot_diameter_mm
from lightplane.core.errors import LightplaneError
from lightplane.core.io import to_gray_float

__all__ = ["BoardPose", "pose_from_corners", "find_board_pose"]


@dataclass(frozen=True)
class BoardPose:
    """A chessboard found in one image and its pose.

    Attributes
    ----------
    corners_uv : (cols·rows, 2) float, inner corners, distorted px, OpenCV order.
    R_cam_board : (3, 3) float, board → camera rotation.
    t_cam_board : (3,) float, board origin in the camera frame, mm.
    reprojection_rms_px : float, RMS corner reprojection error of the pose.
    name : str, where it came from.
    corner_ok : (cols·rows,) bool or None; False for corners left out of the pose (and of the
        cross-ratio) because the laser stripe runs over them; None: all used.
    ids : (N,) the target's point ids of ``corners_uv`` (None: all, in id order).
    object_mm : (N, 3) board coordinates of ``corners_uv`` (mm).
    """

    corners_uv: np.ndarray
    R_cam_board: np.ndarray
    t_cam_board: np.ndarray
    reprojection_rms_px: float
    name: str = ""
    corner_ok: np.ndarray | None = None
    ids: np.ndarray | None = None
    object_mm: np.ndarray | None = None

    @property
    def normal_cam(self) -> np.ndarray:
        """Board plane normal (board z axis) in the camera frame."""
        return self.R_cam_board[:, 2]

    def to_dict(self) -> dict:
        import cv2

        rvec, _ = cv2.Rodrigues(self.R_cam_board)
        return {"name": self.name, "rvec": rvec.ravel().tolist(), "t_cam_board_mm": self.t_cam_board.tolist(),
                "reprojection_rms_px": self.reprojection_rms_px,
                "corners_left_out": 0 if self.corner_ok is None else int(np.count_nonzero(~self.corner_ok))}


def pose_from_corners(camera: Camera, corners_uv: np.ndarray, board, square_mm: float | None = None,
                      name: str = "", corner_ok: np.ndarray | None = None, ids=None) -> BoardPose:
    """Board pose from its detected points: :meth:`Camera.solve_pnp` (``cv2.solvePnP`` and LM, every lens model).

    ``board``: a :class:`lightplane.camera.targets.Target` or ``(cols, rows)`` chessboard inner corners
    (with ``square_mm``); ``ids``: the target's ids of ``corners_uv`` (default: all, id order);
    ``corner_ok`` (N,) bool: only these points are used (all when None).
    """
    target = as_target(board, square_mm)
    uv = as_points(corners_uv, 2, "corners_uv")
    ids_ = np.arange(target.n_points) if ids is None else np.asarray(ids, dtype=np.intp).ravel()
    obj = target.object_points(ids_)
    if len(uv) != len(obj):
        raise LightplaneError(f"{name or 'corners_uv'}: {len(uv)} points, but {len(obj)} ids for {target.describe()}")
    use = np.ones(len(uv), bool) if corner_ok is None else np.asarray(corner_ok, bool)
    o, u = obj[use], uv[use]
    if len(o) < 4:
        raise LightplaneError(f"{name or 'board'}: {len(o)} points, a pose needs at least 4")
    R, t = camera.solve_pnp(o, u, name=name or "board")
    res = camera.project(o @ R.T + t) - u
    rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
    return BoardPose(uv, R, t, rms, name, None if corner_ok is None else use,
                     None if ids is None else ids_, obj)


def find_board_pose(image: np.ndarray, camera: Camera, board, square_mm: float | None = None, *,
                    name: str = "image", channel: str | None = None) -> BoardPose:
    """Find the target (a :class:`lightplane.camera.targets.Target`, or ``(cols, rows)`` chessboard inner
    corners with ``square_mm``) and solve its pose.

    With ``channel`` (e.g. "red" under a red laser and dim light) the board is
    looked for in that channel, contrast-stretched.  Circle grids: the dots' centroids
    are moved to the projected circle centres at the pose found, and the pose solved
    again.  Raises LightplaneError naming the image when the board is not found.
    """

    target = as_target(board, square_mm)
    camera.check_image(image, name)
    if channel is not None:
        image = to_gray_float(image, channel)  # float: the detectors stretch it to 8 bits
    det = target.detect(image)
    if det is None:
        raise LightplaneError(f"{name}: {target.spec} board not found" + (" (or fewer than 6 corners)" if target.partial_views else ""))
    ids = None if not target.partial_views else det.ids
    pose = pose_from_corners(camera, det.uv, target, name=name, ids=ids)
    if target.kind in ("circles", "acircles"):
        dot = dot_diameter_mm(image, det, target)
        for _ in range(2):
            uv = correct_circle_centres(camera, target, det.uv, det.ids, pose.R_cam_board, pose.t_cam_board, dot)
            pose = pose_from_corners(camera, uv, target, name=name)
    return pose
