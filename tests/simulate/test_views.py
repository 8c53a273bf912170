"""Single views of the scan scenes: lasers add their light, a laser-off view shows no stripe, the truth
places the object where the scan data sets do."""

from __future__ import annotations

import numpy as np
import pytest

from lightplane.live.simulated import scaled_camera
from lightplane.simulate.render import RenderOptions
from lightplane.simulate.scene import default_camera, default_plane
from lightplane.simulate.turntable import default_turntable, mirrored_plane
from lightplane.simulate.views import render_stage_view, render_turntable_view

EXACT = RenderOptions(difficulty="clean", noise=False)


def test_lasers_add_their_light():
    cam = scaled_camera(default_camera(), 0.25)
    plane = default_plane()
    table = default_turntable(plane)
    planes = [plane, mirrored_plane(plane, table.point_mm)]
    views = {on: render_turntable_view(cam, planes, table, 30.0, on, options=EXACT)[0].astype(int)
             for on in ((False, False), (True, False), (False, True), (True, True))}
    off, a, b, both = views[(False, False)], views[(True, False)], views[(False, True)], views[(True, True)]
    assert off.max() < 20 and a.max() > 40 and b.max() > 40
    lit = (a - off > 10) | (b - off > 10)
    # the light of both is the sum of each one's above the unlit scene (each view has its own sub-pixel
    # sample jitter, which moves a few grey levels between neighbouring pixels but not the total)
    assert not (both[lit] >= 255).any()
    total = lambda img: float((img - off)[lit].sum())  # noqa: E731
    assert total(both) == pytest.approx(total(a) + total(b), rel=0.01)
    _, truth = render_turntable_view(cam, planes, table, 30.0, (True, False), options=EXACT)
    c = truth["sphere"]["center_mm"]
    assert abs(np.linalg.norm(c - table.point_mm) ** 2 - 12.0**2 - 20.0**2) < 1e-6  # 12 mm off the axis, on the top


def test_stage_view_truth_moves_with_the_offset():
    cam = scaled_camera(default_camera(), 0.25)
    plane = default_plane()
    off = np.array([3.0, 0.0, -1.0])
    img, truth = render_stage_view(cam, [plane], "sphere", off, (True,), options=EXACT)
    assert np.allclose(truth["surfaces"]["sphere"]["center_mm"], np.array([0.0, 0.0, 470.0]) + off)
    assert img.shape == (cam.height, cam.width) and img.max() > 40
