"""Ellipse detection (arc-support line segments) and sub-pixel refinement (docs/method.md §Ellipse).

- :class:`Ellipse` — the project's one ellipse type (centre, a >= b, angle, conic).
- :func:`detect_ellipses` — arc-support-segment detector (Lu et al. 2020, RALS).
- :func:`refine_ellipse` — sub-pixel edge points, Halir–Flusser + geometric fit,
  optionally in undistorted pixels.
- :func:`select_target` — the ellipse of the circular target the laser stripe crosses.
"""

from lightplane.ellipse.detect import EllipseDetectionOptions, detect_ellipses
from lightplane.ellipse.metrics import MatchCounts, ellipse_iou, match_ellipses, read_ellipse_labels
from lightplane.ellipse.model import Ellipse, fit_ellipse_direct, fit_ellipse_geometric, sampson_distance
from lightplane.ellipse.refine import EllipseRefinementOptions, RefinedEllipse, fit_conic_robust, refine_ellipse
from lightplane.ellipse.synthetic import render_ellipses
from lightplane.ellipse.target import StripeCrossing, TargetSelection, expected_axis_range_px, select_target, stripe_crossing

__all__ = ["Ellipse", "EllipseDetectionOptions", "EllipseRefinementOptions", "detect_ellipses", "refine_ellipse",
           "RefinedEllipse", "fit_conic_robust",
           "ellipse_iou", "match_ellipses", "read_ellipse_labels", "MatchCounts",
           "fit_ellipse_direct", "fit_ellipse_geometric", "sampson_distance", "render_ellipses",
           "select_target", "TargetSelection", "stripe_crossing", "StripeCrossing", "expected_axis_range_px"]
