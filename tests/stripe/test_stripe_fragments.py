"""No spurious stripe fragments on a rendered, textured laser-minus-background frame.

A chessboard crossed by the stripe is rendered with the laser on and off; the laser-off frame
is moved by (0.6, 0.4) px before it is subtracted (a camera that moved between the two
exposures), so every rising edge of the squares and of the board's outline leaves a thin
bright residual line in the difference: short ridges on texture edges, as on real
laser-minus-background frames.  The true stripe is the light plane's line across the board
(and across the background plane behind it), projected.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from lightplane.simulate.render import BoardOptions, render_chessboard_dataset
from lightplane.stripe.extract import extract_stripe
from lightplane.stripe.options import StripePointsOptions

SHIFT_PX = (0.6, 0.4)
MAX_FALSE = 0.005        # returned points farther than 1 px from the true stripe
OFF_PX = 1.0


def _true_stripe(ds) -> np.ndarray:
    """Pixels of the true stripe, 0.05 mm apart on the board (within its outline) and on the
    background plane 250 mm behind it (distorted projection)."""
    view = ds.truth["views"][0]
    R, t = np.asarray(view["T_cam_board"]["R"]), np.asarray(view["T_cam_board"]["t"])
    n, d = np.asarray(ds.truth["plane"]["normal"]), float(ds.truth["plane"]["d"])
    x0, x1, y0, y1 = ds.truth["board"]["outline_board_mm"]
    g, s = (R.T @ n)[:2], float(n @ t + d)           # the plane in board coordinates: g . q = -s
    if abs(g[1]) > abs(g[0]):
        a = np.arange(x0, x1, 0.05)
        b = (-s - g[0] * a) / g[1]
    else:
        b = np.arange(y0, y1, 0.05)
        a = (-s - g[1] * b) / g[0]
    on = (a >= x0) & (a <= x1) & (b >= y0) & (b <= y1)
    board = np.column_stack([a[on], b[on], np.zeros(on.sum())]) @ R.T + t
    z = float(t[2]) + 250.0
    y = np.arange(-2000.0, 2000.0, 0.2)
    back = np.column_stack([(-d - n[2] * z - n[1] * y) / n[0], y, np.full_like(y, z)])
    return ds.camera.project(board), ds.camera.project(back)


@pytest.fixture(scope="module")
def scene():
    ds = render_chessboard_dataset(1, 1, BoardOptions(difficulty="realistic", with_stripe=True, laser_off=True))
    laser, off = ds.images
    M = np.float32([[1, 0, SHIFT_PX[0]], [0, 1, SHIFT_PX[1]]])
    moved = cv2.warpAffine(off.astype(np.float32), M, (off.shape[1], off.shape[0]), borderMode=cv2.BORDER_REPLICATE)
    diff = np.clip(laser.astype(np.float32) - moved, 0, 255).astype(np.uint8)
    board, back = _true_stripe(ds)
    return diff, board, back


def test_no_fragments_on_textured_render(scene):
    """``reject_fragments=True`` (opt-in: as default it drops real stripe rows on FabScan): <= 0.5 % of the points more than 1 px from the true stripe (the edge residuals
    return 80 % false points without the rule), and the stripe's own points stay: the true
    stripe's samples on the board with a point within 1 px are at least 98 % of those without
    the rule (the stripe is only visible on the white squares: about half the board)."""
    diff, board, back = scene
    truth = cKDTree(np.concatenate([board, back]))
    sp = extract_stripe(diff, StripePointsOptions(reject_fragments=True))
    old = extract_stripe(diff, StripePointsOptions(reject_fragments=False))
    false = np.mean(truth.query(sp.uv)[0] > OFF_PX)
    false_old = np.mean(truth.query(old.uv)[0] > OFF_PX)
    cov = np.mean(cKDTree(sp.uv).query(board)[0] < OFF_PX)
    cov_old = np.mean(cKDTree(old.uv).query(board)[0] < OFF_PX)
    print(f"false points {false:.4f} (without the rule {false_old:.4f}); coverage {cov:.3f} ({cov_old:.3f})")
    assert false_old > 0.5             # the scene does hold fragments
    assert false <= MAX_FALSE
    assert cov >= 0.98 * cov_old
    assert cov >= 0.45                 # the white squares' share of the stripe, less their edges
