"""Scans of rendered objects (exact truth from the renderer) measured end to end with the true plane.

A few frames per object keep this fast; benchmarks/bench_measure.py runs the full scans
with a plane calibrated from rendered circle images.  ``clean`` renders (no speckle) test
the pipeline's own accuracy; ``realistic`` ones add laser speckle, whose per-point centre
noise (~0.11 px per centre, docs/conventions.md §Noise) sets a floor of ~0.025 mm per point on these scenes.
"""

from __future__ import annotations

import numpy as np
import pytest

from lightplane import LightPlane
from lightplane.measure.options import MeasureOptions
from lightplane.measure.scan import ArrayFrames, Motion, scan_points
from lightplane.simulate.render import render_scan_dataset


def measured(kind: str, difficulty: str, n_frames: int, step_mm: float, options=(MeasureOptions(),)):
    """Points (frame 0 coordinates) for each of the scan options ``options``, and the truth's surfaces."""
    ds = render_scan_dataset(kind, n_frames=n_frames, step_mm=step_mm, seed=3, difficulty=difficulty)
    mo = ds.truth["motion"]
    out = []
    for opts in options:
        rec, summ = scan_points(ArrayFrames(ds.images), ds.camera, LightPlane.from_dict(ds.truth["plane"]), opts,
                                motion=Motion.linear(mo["step_mm"], mo["direction"]))
        out.append(np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(float))
        assert summ.n_frames == n_frames and not summ.skipped
    return (*out, ds.truth["frames"][0]["surfaces"])


def near(p, n, d, gate_mm=1.0):
    return np.abs(p @ np.asarray(n, float) + d) < gate_mm


def inliers(q: np.ndarray, k: float = 4.0, iters: int = 5) -> np.ndarray:
    """Points of ``q`` within k MADs of their total-least-squares plane (drops the step's edge points)."""
    keep = np.ones(len(q), bool)
    for _ in range(iters):
        m = q[keep].mean(axis=0)
        n = np.linalg.svd(q[keep] - m, full_matrices=False)[2][2]
        e = (q - m) @ n
        keep = np.abs(e) < k * 1.4826 * np.median(np.abs(e[keep]))
    return q[keep]


def plane_rms(q: np.ndarray) -> float:
    m = q.mean(axis=0)
    n = np.linalg.svd(q - m, full_matrices=False)[2][2]
    return float(np.sqrt(np.mean(((q - m) @ n) ** 2)))


@pytest.fixture(scope="module")
def tilted_plane_clean():
    return measured("plane", "clean", 4, 8.0)


def test_tilted_plane_clean_is_flat_and_in_place(tilted_plane_clean):
    p, surf = tilted_plane_clean
    on = near(p, surf["plane"]["normal"], surf["plane"]["d"])
    assert on.sum() > 2000  # ~700 stripe rows per frame on the plane, the rest on the table
    q = p[on]
    assert plane_rms(q) < 0.005  # measured ~0.002 mm (the flatness bar: 0.015)
    # and where the truth says (mapped back to frame 0 by the motion): mean offset well under 0.01 mm
    assert abs(np.mean(q @ np.asarray(surf["plane"]["normal"], float) + surf["plane"]["d"])) < 0.01


def sphere_fit(q: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    from scipy.optimize import least_squares

    fit = least_squares(lambda x: np.linalg.norm(q - x[:3], axis=1) - x[3], np.append(q.mean(0), 20.0))
    return fit.x[:3], float(fit.x[3]), np.linalg.norm(q - fit.x[:3], axis=1) - fit.x[3]


def test_sphere_clean_radius_and_residual():
    p, p_all, surf = measured("sphere", "clean", 7, 4.0,
                              (MeasureOptions(), MeasureOptions(min_width_ratio=0.0, max_width_ratio=np.inf)))
    c_true = np.asarray(surf["sphere"]["center_mm"], float)
    on = np.abs(np.linalg.norm(p - c_true, axis=1) - 25.4) < 1.0
    on_all = np.abs(np.linalg.norm(p_all - c_true, axis=1) - 25.4) < 1.0
    assert on.sum() > 1500
    q, q_all = p[on], p_all[on_all]
    _, r, res = sphere_fit(q)
    _, r_all, _ = sphere_fit(q_all)
    assert np.sqrt(np.mean(res**2)) < 0.005  # measured ~0.002 mm
    # points seen obliquely near the limb come out inside (the sheet's footprint on a steep curved surface
    # is foreshortened unevenly; ~0.005 mm at 60-70 deg with the renders' 0.2 mm sheet): their stripe is
    # narrower than the frame's typical one and the width filter (default) drops them (~9% of the sphere
    # points here), which brings the radius closer (-0.0127 -> -0.0101 mm here, 7 frames, no outlier
    # rejection); facing the camera the points are on the true sphere either way
    assert 0.05 * len(q_all) < len(q_all) - len(q) < 0.3 * len(q_all)
    assert abs(r - 25.4) < abs(r_all - 25.4) - 0.0015 and abs(r - 25.4) < 0.02

    def view_cos(x):
        normal = (x - c_true) / np.linalg.norm(x - c_true, axis=1)[:, None]
        return -np.sum(normal * x / np.linalg.norm(x, axis=1)[:, None], axis=1)

    assert np.sum(view_cos(q) < 0.3) < 0.05 * np.sum(view_cos(q_all) < 0.3)  # beyond ~73 deg: (nearly) all dropped
    facing = view_cos(q) > 0.7
    assert facing.sum() > 500
    assert abs(np.median(np.linalg.norm(q[facing] - c_true, axis=1) - 25.4)) < 0.01


def test_gauge_step_realistic():
    p, surf = measured("step", "realistic", 4, 8.0)
    n = np.asarray(surf["base"]["normal"], float)
    base, top = inliers(p[near(p, n, surf["base"]["d"])]), inliers(p[near(p, n, surf["top"]["d"])])
    assert len(base) > 500 and len(top) > 500
    # separation along the common normal of both faces (fitted, not the truth's)
    nf = np.linalg.svd(np.vstack([base - base.mean(0), top - top.mean(0)]), full_matrices=False)[2][2]
    sep = abs(float(nf @ (base.mean(0) - top.mean(0))))
    assert abs(sep - 10.0) < 0.02  # measured -0.003 mm; speckle noise averages over ~1000 points per face
    assert plane_rms(base) < 0.045 and plane_rms(top) < 0.045  # speckle: ~0.028 mm per point
