"""calibrate_camera names views whose reprojection RMS is far above the others'."""

from __future__ import annotations

from lightplane.camera.intrinsics import VIEW_OUTLIER_FLOOR_PX, VIEW_OUTLIER_RATIO, view_outlier_warnings


def test_a_view_at_five_times_the_median_is_named():
    """FabScan's 25 views: frame 008 at 3.67 px against a median of ~0.7 px is named; the others are not."""
    names = [f"calibration_{i:03d}.jpg" for i in range(8)]
    rms = [0.70, 0.68, 0.74, 0.66, 0.71, 0.69, 0.72, 3.67]
    w = view_outlier_warnings(names, rms)
    assert len(w) == 1 and w[0].startswith("view calibration_007.jpg: reprojection RMS 3.67 px, 5.2x")


def test_no_warning_below_the_ratio_or_the_floor():
    assert view_outlier_warnings(["a", "b", "c"], [0.7, 0.7, 0.99 * VIEW_OUTLIER_RATIO * 0.7]) == []
    tiny = 0.9 * VIEW_OUTLIER_FLOOR_PX  # clean renders: 10x the median but a fraction of a pixel
    assert view_outlier_warnings(["a", "b", "c"], [tiny / 10, tiny / 10, tiny]) == []
    assert view_outlier_warnings(["a", "b"], [0.1, 5.0]) == []  # two views: no median to speak of
