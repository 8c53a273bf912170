"""Ellipse detection (arc-support line segments) and sub-pixel refinement (SPEC §5.1)."""

from .detect import detect_ellipses
from .metrics import ellipse_iou, match_ellipses, read_ellipse_labels
from .model import Ellipse, fit_ellipse_direct, fit_ellipse_geometric

__all__ = ["Ellipse", "detect_ellipses", "ellipse_iou", "match_ellipses", "read_ellipse_labels",
           "fit_ellipse_direct", "fit_ellipse_geometric"]
