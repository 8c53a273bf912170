"""Chessboard corners by the blurred-saddle fit (:func:`lightplane.camera.corners.fit_corners`).

Ground truth: an affine chessboard (corners at ``origin + i a + j b``, edges at 69° to
each other, not 90°) blurred by a Gaussian and integrated over the pixel box, computed
exactly from its Fourier series (no supersampling, so no sub-pixel quantisation of the
edges).  An affine chessboard is point-symmetric about every corner, like the blurred
saddle, but its blurred corners are not the erf product the fit uses: the tests check
that this misfit does not move the corners.
"""

from __future__ import annotations

import numpy as np
import pytest

from lightplane.core.errors import LightplaneError
from lightplane.camera.corners import CornerFitOptions, fit_corners

A_PX = np.array([26.0, 4.0])  # board step along a row, px
B_PX = np.array([-12.0, 21.0])  # along a column: the edges meet at 69°
SHAPE = (150, 220)
BOARD = (6, 5)


def affine_board(origin, blur_px, *, contrast=100.0, mean=120.0):
    """(H, W) float image of the affine chessboard with corners ``origin + i a + j b``,
    blurred by a Gaussian of ``blur_px`` and averaged over each pixel's box, at the pixel
    centres.  Series of the two square waves, each term attenuated by the Gaussian's and the
    box's transfer functions (terms below 1e-13 dropped)."""
    h, w = SHAPE
    A = np.column_stack([A_PX, B_PX])
    Ainv = np.linalg.inv(A)
    yy, xx = np.mgrid[0:h, 0:w]
    ij = Ainv @ np.stack([xx.ravel() - origin[0], yy.ravel() - origin[1]])  # board coordinates
    img = np.zeros(ij.shape[1])
    f_max = np.sqrt(30.0 / (2 * np.pi**2)) / blur_px  # cycles/px where the Gaussian falls below e^-30
    k_max = [int(2 * f_max * np.linalg.norm(A[:, c])) + 2 for c in (0, 1)]
    for k1 in range(1, k_max[0] + 1, 2):
        for k2 in range(1, k_max[1] + 1, 2):
            # sgn sin(pi i) sgn sin(pi j) = sum 16/(pi^2 k1 k2) sin(pi k1 i) sin(pi k2 j)
            for sign in (1, -1):
                m = 0.5 * np.array([k1, -sign * k2])  # cycles per board unit
                f = Ainv.T @ m  # cycles per pixel
                att = np.exp(-2 * np.pi**2 * blur_px**2 * (f @ f)) * np.sinc(f[0]) * np.sinc(f[1])
                if abs(att) < 1e-13:
                    continue
                img += sign * 8.0 / (np.pi**2 * k1 * k2) * att * np.cos(2 * np.pi * (m @ ij))
    return (mean + 0.5 * contrast * img).reshape(h, w)


def truth_corners(origin):
    ii, jj = np.meshgrid(np.arange(1, BOARD[0] + 1), np.arange(1, BOARD[1] + 1))  # row-major
    return np.asarray(origin) + ii.ravel()[:, None] * A_PX + jj.ravel()[:, None] * B_PX


@pytest.fixture(scope="module")
def boards():
    rng = np.random.default_rng(3)
    origins = [np.array([55.0, 0.0]) + rng.uniform(0, 1, 2) for _ in range(3)]
    return [(o, affine_board(o, 0.9)) for o in origins]


def test_series_image_is_the_board():
    origin = np.array([55.3, 0.4])
    img = affine_board(origin, 0.9)
    t = truth_corners(origin)
    assert t.min() > 15 and t[:, 0].max() < SHAPE[1] - 15 and t[:, 1].max() < SHAPE[0] - 15
    # far from the edges the series gives the two flat levels; the centre of a square is one of them
    centre = np.round(t[0] + 0.5 * (A_PX + B_PX)).astype(int)
    assert abs(abs(img[centre[1], centre[0]] - 120.0) - 50.0) < 1e-6
    # point symmetry about a corner: I(q + u) = I(q - u) for integer-pixel q
    q = np.array([110.0, 70.0])
    img_sym = affine_board(q - 2 * A_PX - 3 * B_PX, 0.9)
    u = np.array([[3, 1], [-5, 4], [7, -2], [0, 6]])
    assert np.allclose(img_sym[70 + u[:, 1], 110 + u[:, 0]], img_sym[70 - u[:, 1], 110 - u[:, 0]], atol=1e-9)


@pytest.mark.parametrize("blur_px", [0.9, 0.6])
def test_unbiased_on_skewed_saddles(boards, blur_px):
    """Noise-free: the corners at any sub-pixel phase to 1e-3 px (measured: 2e-5 px at a
    blur of 0.9 px, 3e-4 at 0.6, where the pixel sampling starts to alias), with the edges bent as
    the grid's lines are (the default; the bends measured on the fitted corners, whatever the
    start's) as with straight ones."""
    rng = np.random.default_rng(4)
    for origin, img in boards if blur_px == 0.9 else boards[:1]:
        if blur_px != 0.9:
            img = affine_board(origin, blur_px)
        t = truth_corners(origin)
        start = t + rng.uniform(-0.25, 0.25, t.shape)
        for options in (None, CornerFitOptions(bent_edges=False)):
            q = fit_corners(img, start, BOARD, options)
            assert np.abs(q - t).max() < (1e-4 if blur_px == 0.9 else 1e-3)


def test_shading_gradient_does_not_pull(boards):
    """A multiplicative brightness gradient (vignetting: 16 % across the image) is odd about
    each corner; the model's gradient terms take it (measured max error 1.5e-4 px)."""
    yy, xx = np.mgrid[0:SHAPE[0], 0:SHAPE[1]]
    shade = 1.0 + 2e-3 * (xx - 110) - 1.5e-3 * (yy - 75)
    for origin, img in boards:
        t = truth_corners(origin)
        q = fit_corners(img * shade, t + 0.15, BOARD)
        assert np.abs(q - t).max() < 5e-4


def test_noise_8bit(boards):
    """Gaussian noise of 2 grey levels on a contrast of 100, quantised to 8 bits: 10 draws of
    30 corners.  Measured 0.012 px RMS (no bias); the tolerance is 1.5x that, the bias 4 sigma
    of the mean.  The float copy of the same 8-bit image gives the same corners."""
    rng = np.random.default_rng(5)
    origin, img = boards[0]
    t = truth_corners(origin)
    errs = []
    for _ in range(10):
        noisy = np.clip(np.rint(img + rng.normal(0.0, 2.0, img.shape)), 0, 255).astype(np.uint8)
        start = t + rng.uniform(-0.2, 0.2, t.shape)
        q = fit_corners(noisy, start, BOARD)
        errs.append(q - t)
    e = np.concatenate(errs)
    rms = np.sqrt(np.mean(np.sum(e**2, axis=1)))
    assert rms < 0.018
    assert np.all(np.abs(e.mean(axis=0)) < 4 * (rms / np.sqrt(2)) / np.sqrt(len(e)))
    assert np.allclose(fit_corners(noisy.astype(np.float32), start, BOARD), q, atol=1e-9)


def test_failures_keep_the_input(boards):
    origin, img = boards[0]
    t = truth_corners(origin)
    start = t + 0.1
    img = img.copy()
    # corner 8: its neighbourhood painted flat (no saddle to fit)
    c = np.round(t[8]).astype(int)
    img[c[1] - 12:c[1] + 13, c[0] - 12:c[0] + 13] = 120.0
    # corner 20: started 0.4 of the spacing off, it would have to move too far
    start[20] = t[20] + 0.4 * 24.0 * np.array([0.6, 0.8])
    q = fit_corners(img, start, BOARD)
    assert np.array_equal(q[8], start[8]) and np.array_equal(q[20], start[20])
    # the corners whose windows miss the flat patch, and whose grid directions do not come
    # from the displaced corner, are fitted as usual
    far = (np.linalg.norm(t - t[8], axis=1) > 45.0) & (np.linalg.norm(t - t[20], axis=1) > 30.0)
    assert far.sum() >= 12
    assert np.abs(q[far] - t[far]).max() < 1e-3


def test_bad_input():
    img = np.zeros((50, 60))
    good = np.tile([[20.0, 20.0]], (4, 1)) + np.array([[0, 0], [10, 0], [0, 10], [10, 10]])
    with pytest.raises(LightplaneError, match="corners_uv"):
        fit_corners(img, good[:3], (2, 2))
    with pytest.raises(LightplaneError, match="gray"):
        fit_corners(np.zeros((50, 60, 3)), good, (2, 2))
    with pytest.raises(LightplaneError, match="board"):
        fit_corners(img, good, (1, 4))
    bad = good.copy()
    bad[1, 0] = np.nan
    with pytest.raises(LightplaneError, match="non-finite"):
        fit_corners(img, bad, (2, 2))


def test_corners_near_the_image_border():
    """Corners 9-18 px from the top edge, closer than the window radius (18 px): the window
    shrinks to stay inside the image, and symmetric, so they stay unbiased (measured max
    error 3e-5 px, noise-free; with the window cut by the border instead: 8e-4 px)."""
    origin = np.array([55.4, -15.3])
    img = affine_board(origin, 0.9)
    t = truth_corners(origin)
    near = t[:, 1] < 18
    assert 3 <= near.sum() and t[:, 1].min() > 6
    q = fit_corners(img, t + 0.1, BOARD)
    assert np.abs(q - t).max() < 2e-4
