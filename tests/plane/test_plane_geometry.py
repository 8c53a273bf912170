"""What a light plane's calibration images can determine (lightplane.plane.quality.plane_geometry)."""

from __future__ import annotations

import numpy as np

from lightplane.plane.quality import MIN_TRIANGULATION_DEG, plane_geometry
from lightplane.plane.zhou import fit_plane


def _stripes(offsets_mm, angles_deg, rng, tilt_deg=25.0, z0=450.0, noise=0.02):
    """Stripe segments (60 mm, 50 points each) on the plane through (0, 0, z0) containing the camera's y
    axis and turned ``tilt_deg`` from the optical axis: each at ``offset`` across and ``angle`` from y."""
    t = np.radians(tilt_deg)
    e_y, e_in = np.array([0.0, 1.0, 0.0]), np.array([np.sin(t), 0.0, np.cos(t)])  # in the plane
    n = np.cross(e_y, e_in)
    pts, idx = [], []
    for k, (off, ang) in enumerate(zip(offsets_mm, angles_deg)):
        a = np.radians(ang)
        s = np.linspace(-30, 30, 50)
        along = np.cos(a) * e_y + np.sin(a) * e_in
        p = np.array([0.0, 0.0, z0]) + off * e_in + s[:, None] * along + rng.normal(0, noise, (50, 1)) * n
        pts.append(p)
        idx.append(np.full(50, k))
    return np.vstack(pts), np.concatenate(idx)


def test_well_spread_stripes_determine_the_plane():
    rng = np.random.default_rng(0)
    p, i = _stripes([-40, -10, 20, 45], [0, 15, -10, 5], rng)
    pl = fit_plane(p)
    g = plane_geometry(p, i, pl.normal, pl.d, pl.covariance)
    assert g["warnings"] == [] and g["refusal"] is None
    assert abs(g["triangulation_deg"] - 25) < 2.0  # the plane 25 deg off the optical axis
    assert g["width_mm"] > 0.2 * g["length_mm"] and g["stripe_angle_spread_deg"] > 20


def test_stripes_along_one_line_are_explained():
    """Four images whose stripes lie within 0.5 mm of one line: a warning saying what to do; with the
    plane's covariance that wide, a refusal in words instead of a meaningless plane."""
    rng = np.random.default_rng(1)
    p, i = _stripes([0.0, 0.2, -0.2, 0.1], [0.0, 0.1, -0.1, 0.0], rng, noise=0.05)
    pl = fit_plane(p)
    g = plane_geometry(p, i, pl.normal, pl.d, pl.covariance)
    assert any("move or turn the target" in w for w in g["warnings"])
    g = plane_geometry(p, i, pl.normal, pl.d, np.diag([0.01, 0.01, 0.01, 1.0]))  # normal σ ~10 deg
    assert g["refusal"] is not None and "not determined" in g["refusal"]


def test_grazing_view_of_the_plane_is_named():
    """A plane seen nearly edge-on from the camera: the triangulation angle and its cost in words."""
    rng = np.random.default_rng(2)
    p, i = _stripes([-40, -10, 20, 45], [0, 15, -10, 5], rng, tilt_deg=5.0)
    pl = fit_plane(p)
    g = plane_geometry(p, i, pl.normal, pl.d, pl.covariance)
    assert g["triangulation_deg"] < MIN_TRIANGULATION_DEG
    assert any("sees the light plane at" in w and "20-40 deg" in w for w in g["warnings"])
