"""calibrate_turntable leaves out an image whose board pose fits its corners far worse than the others'."""

from __future__ import annotations

import numpy as np

from lightplane.camera.targets import as_target
from lightplane.motion.turntable import calibrate_turntable
from lightplane.simulate.turntable import render_turntable_board


def test_an_image_whose_board_moved_half_way_is_dropped_with_its_reason():
    board = render_turntable_board(angles_deg=(-40, -24, -8, 8, 24, 40), seed=4, difficulty="clean", edge_samples=8)
    cam = board.camera
    imgs = [np.array(im) for im in board.images]
    h = int(np.median(np.asarray(board.truth["views"][2]["points_px"])[:, 1]))
    imgs[2][h:] = np.roll(imgs[2][h:], 2, axis=1)  # the board's lower half moved by 2 px
    names = [f"b{i}.png" for i in range(6)]
    cal = calibrate_turntable(imgs, cam, as_target((9, 6), 8.0), names=names)
    assert list(cal.skipped) == ["b2.png"] and cal.skipped["b2.png"].startswith("dropped: reprojection RMS")
    assert [im["name"] for im in cal.images if im["used"]] == [n for n in names if n != "b2.png"]
