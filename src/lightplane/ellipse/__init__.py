"""Ellipse detection (arc-support line segments) and sub-pixel refinement (SPEC §5.1)."""
