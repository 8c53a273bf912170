"""lightplane: line-structured-light calibration with a single circular target, and 3D measurement.

Implements Wang & Li, "Calibration Method for Line-Structured Light
Three-Dimensional Measurements Based on a Single Circular Target",
Appl. Sci. 2022, 12, 588, and goes beyond it (global disambiguation, joint
maximum-likelihood refinement, uncertainty).  Conventions: docs/conventions.md
(camera frame x right, y down, z forward; mm; plane normal with d < 0).

The stable API (docs/conventions.md §Python API): :class:`Camera`, :class:`LightPlane`,
:func:`detect_ellipses`, :func:`extract_stripe`, :func:`circle_poses`,
:func:`calibrate_plane`, :func:`triangulate`; also :func:`distance_errors`,
:func:`measure_profile`, :func:`measure_scan`, :func:`read_cloud`/:func:`write_cloud`.
"""

from __future__ import annotations

from lightplane.version import __version__

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.plane.model import LightPlane
from lightplane.plane.solvers import PlaneCalibration, SolverOptions, calibrate_plane_from_points
from lightplane.plane.ml import MLOptions
from lightplane.plane.joint import JointOptions
from lightplane.plane.triangulate import triangulate
from lightplane.plane.circle_pose import CirclePose, circle_poses
from lightplane.ellipse import (Ellipse, EllipseDetectionOptions, EllipseRefinementOptions, detect_ellipses,
                                refine_ellipse, select_target)
from lightplane.stripe.extract import StripePoints, StripeProfile, extract_profile, extract_stripe
from lightplane.stripe.options import StripeOptions, StripePointsOptions
from lightplane.plane.calibrate import ObserveOptions, PlaneCalibrationOptions, calibrate_plane
from lightplane.evaluate.crossratio import DistanceErrors, distance_errors
from lightplane.plane.uncertainty import point_sigma_mm
from lightplane.measure.options import CloudOutput, MeasureOptions
from lightplane.measure.profile import Profile, ProfileMeasurer, measure_profile
from lightplane.measure.pointcloud import read_cloud, write_cloud
from lightplane.measure.scan import Motion, measure_scan
from lightplane.camera.targets import Detection, Target, parse_target
from lightplane.camera.corners import CornerFitOptions
from lightplane.camera.intrinsics import CameraCalibrationOptions, calibrate_camera
from lightplane.plane.zhou import BoardFrames, BoardPlaneOptions, calibrate_plane_board
from lightplane.evaluate.crossratio import EvaluateOptions, evaluate_images

__all__ = [
    "Camera",
    "CirclePose",
    "Detection",
    "Target",
    "calibrate_camera",
    "CameraCalibrationOptions",
    "CornerFitOptions",
    "calibrate_plane_board",
    "evaluate_images",
    "EvaluateOptions",
    "parse_target",
    "DistanceErrors",
    "Ellipse",
    "EllipseDetectionOptions",
    "EllipseRefinementOptions",
    "LightPlane",
    "LightplaneError",
    "CloudOutput",
    "MeasureOptions",
    "Motion",
    "Profile",
    "ProfileMeasurer",
    "PlaneCalibration",
    "SolverOptions",
    "MLOptions",
    "ObserveOptions",
    "PlaneCalibrationOptions",
    "BoardFrames",
    "BoardPlaneOptions",
    "JointOptions",
    "StripeOptions",
    "StripePoints",
    "StripePointsOptions",
    "StripeProfile",
    "__version__",
    "calibrate_plane",
    "calibrate_plane_from_points",
    "circle_poses",
    "detect_ellipses",
    "distance_errors",
    "extract_profile",
    "extract_stripe",
    "measure_profile",
    "measure_scan",
    "point_sigma_mm",
    "read_cloud",
    "refine_ellipse",
    "select_target",
    "triangulate",
    "write_cloud",
]
