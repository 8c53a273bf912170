"""Options of a measurement, checked on construction.

:class:`MeasureOptions` -- how stripe frames become points (the stripe's centres, the profile
direction and region, the per-point filters): :class:`lightplane.measure.profile.ProfileMeasurer`,
:func:`~lightplane.measure.profile.measure_profile`, the scans
(:func:`~lightplane.measure.scan.scan_points`, :func:`~lightplane.measure.scan.measure_scan`),
:func:`~lightplane.measure.sensor.measure_lasers` and
:func:`~lightplane.measure.batch.measure_batch`.  :class:`CloudOutput` -- how a scan's point
cloud is written.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from lightplane.core.errors import LightplaneError
from lightplane.core.io import check_output
from lightplane.measure.pointcloud import cloud_format
from lightplane.plane.triangulate import AXES, GRAZING_COS
from lightplane.stripe.options import StripeOptions

__all__ = ["MeasureOptions", "CloudOutput", "MIN_WIDTH_RATIO", "MAX_WIDTH_RATIO", "DEPTH_FACTOR", "MAX_SIGMA_RATIO"]

#: defaults of the per-point stripe-width filter (:class:`MeasureOptions`): width / frame median
MIN_WIDTH_RATIO = 0.8
MAX_WIDTH_RATIO = 2.0
#: defaults of the outlier screen (:class:`MeasureOptions`): the depth range beyond the calibration's, and σ
#: over the plane's σ where it was calibrated
DEPTH_FACTOR = 2.0
MAX_SIGMA_RATIO = 100.0


@dataclass(frozen=True)
class MeasureOptions:
    """How stripe frames become 3D points.

    stripe : :class:`~lightplane.stripe.options.StripeOptions` of
        :func:`lightplane.stripe.extract.extract_profile` (``width_px``, ``channel``,
        ``min_peak``, ``max_width_px``, ``min_cos`` -- the stripe's own limit on how
        obliquely it may cross a line, ...).  In a scan a ``width_px`` of None is
        estimated once, on the first frame, and used for all frames.
    axis : ``"columns"`` (stripe roughly horizontal), ``"rows"`` or ``"auto"``
        (:func:`lightplane.plane.triangulate.profile_axis`).
    roi : ``(x, y, width, height)`` px or None (whole image).
    smooth_lines : 0 (default: every line's own centre) or an odd window ``>= 5``: the
        sub-pixel centres along each run of consecutive valid lines are smoothed by a
        quadratic Savitzky–Golay filter over that many lines (runs shorter than the
        window are left alone).  Laser speckle gives each centre 0.1–0.3 px of
        independent-ish noise (docs/conventions.md §Noise); a quadratic local fit averages it away
        (noise × ~0.6 for 7 lines) without biasing curves of radius much larger than
        the window (a quadratic is reproduced exactly).  It also blurs real detail
        finer than the window (edges, steps): off for edge-sensitive measurement.
    min_ray_cos : grazing-ray limit (``min_cos`` of
        :func:`lightplane.plane.triangulate.triangulate_normalized`).
    min_width_ratio, max_width_ratio : per-point quality filter on the stripe's width
        (FWHM across the stripe, px); see :class:`lightplane.measure.profile.ProfileMeasurer`.
        ``0`` and ``inf`` switch the filter off.
    parallel : ``parallel`` of :func:`lightplane.stripe.extract.extract_profile` (None:
        its own choice; given, frames are profiled one at a time); the numbers are the same.
    stripe_evidence : a frame whose centres form no line (no run of consecutive lines as long as
        :data:`lightplane.measure.profile.STRIPE_MIN_RUN` and 5 times the stripe's width) has no
        stripe and gives no point (chessboard squares, texture: docs/limits.md §Frames without a stripe).
    keep_outliers : keep points outside the calibrated working volume or with a σ beyond
        ``max_sigma_ratio`` (dropped and counted by default; see
        :class:`lightplane.measure.profile.ProfileMeasurer`).
    depth_factor : the working volume's depth range: the plane's calibrated depth range divided
        and multiplied by this (1: the calibrated range exactly, ``measure --crop``; ``inf``: no depth
        limit).
    max_sigma_ratio : a point's σ over the plane's σ where it was calibrated beyond which the point
        is dropped (``inf``: no limit).
    """

    stripe: StripeOptions = field(default_factory=StripeOptions)
    axis: str = "auto"
    roi: tuple[int, int, int, int] | None = None
    smooth_lines: int = 0
    min_ray_cos: float = GRAZING_COS
    min_width_ratio: float = MIN_WIDTH_RATIO
    max_width_ratio: float = MAX_WIDTH_RATIO
    parallel: bool | None = None
    stripe_evidence: bool = True
    keep_outliers: bool = False
    depth_factor: float = DEPTH_FACTOR
    max_sigma_ratio: float = MAX_SIGMA_RATIO

    def __post_init__(self) -> None:
        if not isinstance(self.stripe, StripeOptions):
            raise LightplaneError(f"stripe must be a StripeOptions, got {type(self.stripe).__name__}")
        if self.axis != "auto" and self.axis not in AXES:
            raise LightplaneError(f"axis must be 'columns', 'rows' or 'auto', got {self.axis!r}")
        k = int(self.smooth_lines)
        if k != self.smooth_lines or k < 0 or (k and (k < 5 or k % 2 == 0)):
            raise LightplaneError(f"smooth_lines must be 0 or an odd integer >= 5, got {self.smooth_lines!r}")
        lo, hi = float(self.min_width_ratio), float(self.max_width_ratio)
        if not (0.0 <= lo < 1.0 < hi) or np.isnan(hi):
            raise LightplaneError(f"need 0 <= min_width_ratio < 1 < max_width_ratio, got {self.min_width_ratio!r}, "
                                  f"{self.max_width_ratio!r}")
        if not float(self.depth_factor) >= 1.0:
            raise LightplaneError(f"depth_factor must be >= 1 (1: the calibrated depth range exactly, inf: off), got "
                                  f"{self.depth_factor!r}")
        if not float(self.max_sigma_ratio) > 1.0:
            raise LightplaneError(f"max_sigma_ratio must be > 1 (inf: off), got {self.max_sigma_ratio!r}")

    def changed(self) -> dict:
        """``smooth_lines`` and every other option not at its default, stripe options included
        (``width_px`` and ``channel`` aside), as one flat dict: a scan's record of its options."""
        out = {"smooth_lines": self.smooth_lines}
        skip = {"stripe", "axis", "roi", "smooth_lines"}
        for opts, default, leave in ((self, MeasureOptions(), skip), (self.stripe, StripeOptions(), {"width_px", "channel"})):
            for f in fields(opts):
                v = getattr(opts, f.name)
                if f.name not in leave and v != getattr(default, f.name):
                    out[f.name] = v
        return out


@dataclass(frozen=True)
class CloudOutput:
    """How a scan's point cloud is written (:func:`lightplane.measure.pointcloud.write_cloud`).

    fmt : ``"ply"``, ``"csv"`` or ``"npy"``; None: from the output's suffix.
    ascii : ASCII PLY instead of binary (PLY only).
    force : overwrite an existing file.
    comments : extra comment lines for the file (after lightplane's own).
    """

    fmt: str | None = None
    ascii: bool = False
    force: bool = False
    comments: tuple[str, ...] = ()

    def target(self, path: str | os.PathLike) -> tuple[Path, str]:
        """The output path, checked (exists without ``force``, no such folder), and its format."""
        out = check_output(path, self.force)
        fmt = cloud_format(out, self.fmt)
        if self.ascii and fmt != "ply":
            raise LightplaneError("--ascii applies to PLY output only")
        return out, fmt
