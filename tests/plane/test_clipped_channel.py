"""A colour laser whose own channel is clipped in the laser-off frame (a red line on white paper): the stripe
is taken from the channels that carry the difference (lightplane.stripe.difference), by default.

Colour frames are made from the renderer's grey laser-off / laser-on pair of each board pose (exact truth):
the red channel is three times the grey level (the white squares clip at 255 with or without the laser), the
laser adds its light to red and, weaker, to green and blue (the share the sensor's colour filters let
through).  Zhou's plane from the colour pairs with the defaults must be as good as from the grey pairs
(within 0.01 deg of the truth, as the grey renders are)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lightplane import LightPlane
from lightplane.core.io import to_gray_float
from lightplane.plane.zhou import BoardFrames, calibrate_plane_board
from lightplane.stripe.difference import CLIPPED_SHARE, laser_difference

BOARD = (9, 6)


@pytest.fixture(scope="module")
def dataset():
    from lightplane.simulate.render import STRIPE_CAPTURE, BoardOptions, render_chessboard_dataset

    ds = render_chessboard_dataset(5, 11, BoardOptions(
        capture=replace(STRIPE_CAPTURE, board=BOARD, square_mm=8.0), with_stripe=True, laser_off=True, samples=4,
        edge_samples=8))
    on = [im for im, n in zip(ds.images, ds.names) if "_off" not in n]
    off = [im for im, n in zip(ds.images, ds.names) if "_off" in n]
    return ds, on, off


def _colour(off: np.ndarray, laser: np.ndarray) -> np.ndarray:
    """BGR: red clips on the white squares; the laser's light mostly in red, a share in green and blue."""
    off = off.astype(np.float64)
    bgr = np.stack([0.55 * off + 0.30 * laser, 0.75 * off + 0.45 * laser, 3.0 * off + 3.0 * laser], axis=2)
    return np.clip(np.rint(bgr), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def colour_pairs(dataset):
    _, on, off = dataset
    pairs = []
    for a, b in zip(on, off):
        laser = np.clip(a.astype(np.float64) - b.astype(np.float64), 0, None)
        pairs.append((_colour(a * 0 + b, laser), _colour(b, np.zeros_like(laser))))
    return pairs


def test_the_difference_without_clipping_is_the_requested_channel(dataset):
    _, on, off = dataset
    rng = np.random.default_rng(3)
    a = np.clip(np.stack([on[0] * f for f in (0.4, 0.6, 0.8)], axis=2) + rng.normal(0, 2, on[0].shape + (3,)), 0, 255)
    b = np.clip(np.stack([off[0] * f for f in (0.4, 0.6, 0.8)], axis=2), 0, 255)
    a, b = a.astype(np.uint8), b.astype(np.uint8)
    for ch in (None, "gray", "red", "green", "sum"):
        d = laser_difference(a, b, ch)
        assert d.note == "" and not d.clipped
        assert np.array_equal(d.image, np.clip(to_gray_float(a, ch) - to_gray_float(b, ch), 0, None))


def test_a_clipped_channel_is_left_out(colour_pairs):
    on, off = colour_pairs[0]
    share = float(np.mean(off[:, :, 2] >= 250))
    assert share >= CLIPPED_SHARE  # the scene clips red, as white paper under a red laser does
    for ch in (None, "red", "sum"):
        d = laser_difference(on, off, ch)
        assert d.channels == ("blue", "green") and set(d.clipped) == {"red"}, (ch, d.channels)
        assert "red clipped in the laser-off frame" in d.note
        expect = (on[:, :, :2].astype(np.float32) - off[:, :, :2].astype(np.float32)).sum(axis=2)
        assert np.array_equal(d.image, np.clip(expect, 0, None))
    # a channel that is not clipped is taken as asked
    assert laser_difference(on, off, "green").channels == ("green",)


def test_zhou_plane_from_colour_pairs_with_clipped_red(dataset, colour_pairs, monkeypatch):
    ds, on, off = dataset
    truth = LightPlane.from_dict(ds.truth["plane"])
    sq = ds.truth["board"]["square_mm"]
    grey = calibrate_plane_board(BoardFrames(on, background_images=off), ds.camera, BOARD, sq)
    col = calibrate_plane_board(BoardFrames([p[0] for p in colour_pairs], background_images=[p[1] for p in colour_pairs]),
                                ds.camera, BOARD, sq)
    assert np.degrees(grey.plane.angle_to(truth)) < 0.01
    assert np.degrees(col.plane.angle_to(truth)) < 0.01
    assert len(col.points_cam_mm) >= 0.9 * len(grey.points_cam_mm)  # the stripe kept over the white squares too
    assert "red clipped" in col.plane.meta["stripe_channels"]
    # the laser's own channel alone, as it was taken before, loses the stripe on the white squares
    from lightplane.plane import zhou
    from lightplane.stripe.difference import LaserDifference

    def red_only(image, background, channel=None, region=None):
        return LaserDifference(np.clip(to_gray_float(image, "red") - to_gray_float(background, "red"), 0, None),
                               ("red",), {}, "")

    monkeypatch.setattr(zhou, "laser_difference", red_only)
    views = zhou.find_board_views(BoardFrames([p[0] for p in colour_pairs], background_images=[p[1] for p in colour_pairs]),
                                  ds.camera, BOARD, sq)
    assert sum(map(len, views.stripes)) < 0.7 * len(col.points_cam_mm)
