"""Real photographs (Ciclop scanner, shared/data/ciclop/laser_segmentation_in_pattern): the
cross-ratio ideal points of a real red stripe on a real chessboard.

No light plane was published for these images, so the check is a property that
needs no reference: the light plane meets the flat board in a straight line, so
the ideal points of all corner rows must be collinear in board coordinates.
Corners in these dim frames reproject to ~1 px, i.e. ~0.3 mm at ~3.5 px/mm
along a row, averaged over 11 corners: we allow 0.15 mm.
"""

from __future__ import annotations

import numpy as np
import pytest

from lightplane import Camera
from lightplane.plane.zhou import board_views_and_stripes
from lightplane.core.errors import LightplaneError
from lightplane.evaluate.crossratio import cross_ratio_points
from lightplane.core.io import read_image

# the published intrinsics of the Ciclop captures (shared/data/ciclop/README.txt), images rotated to 1280x960
CAM = Camera([[1430.39147, 0, 636.403930], [0, 1429.66307, 478.032706], [0, 0, 1]],
             [0.0271918728, -0.230991447, -7.13362835e-05, 8.68588435e-04, 0.508921101], 1280, 960)


@pytest.mark.parametrize("suffix", ["-x", ""])
def test_ciclop_ideal_points_collinear(shared_data, suffix):
    d = shared_data / "ciclop" / "laser_segmentation_in_pattern"
    im = read_image(d / f"laser-0-255-255-8{suffix}.png", rotate_deg=90)
    bg = read_image(d / f"laser-background-0-255-255-8{suffix}.png", rotate_deg=90)
    poses, stripes, _ = board_views_and_stripes([im], CAM, board=(11, 6), square_mm=13.0, background_images=[bg],
                                                channel="red")
    assert poses[0].reprojection_rms_px < 2.0
    cr = cross_ratio_points(CAM.undistort_points(poses[0].corners_uv), (11, 6), CAM.undistort_points(stripes[0]),
                            square_mm=13.0)
    assert cr.family == "rows" and len(cr) == 6
    p = cr.p_board_mm[:, :2]
    m = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - m)
    assert np.max(np.abs((p - m) @ vt[1])) < 0.15


def test_ciclop_dim_laser_frame_without_background(shared_data):
    """The dim laser frame alone does not show the board: a clear error naming the image."""
    d = shared_data / "ciclop" / "laser_segmentation_in_pattern"
    im = read_image(d / "laser-0-255-255-8-x.png", rotate_deg=90)
    with pytest.raises(LightplaneError, match="laser-0-255-255-8-x.png: chessboard:11x6 board not found"):
        board_views_and_stripes([im], CAM, board=(11, 6), square_mm=13.0, channel="red",
                                image_names=[str(d / "laser-0-255-255-8-x.png")])
