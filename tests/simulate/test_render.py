"""Self-consistency of the renderer against its exact ground truth.

The probes below are written here, independently of the renderer: a disc edge is
located along an image row (or column) by the area (first-moment) method, which is
exact for a straight step edge blurred by any symmetric PSF and integrated over the
pixel; the stripe's ridge by the intensity centroid across the stripe.  The truth
(rim conic, chord) is recomputed here from the placement's centre, normal and radius.
"""

from __future__ import annotations

import numpy as np
import pytest

from lightplane.simulate.scene import default_camera, default_plane, sample_placements
from lightplane.simulate.render import CircleOptions, render_circle_image

SHEET_SIGMA_MM = 0.35


def _conic_from_truth(camera, tp):
    """Rim conic (undistorted px) from centre, normal, radius: C = H^-T diag(1,1,-r²) H^-1."""
    n = tp.normal
    ref = np.eye(3)[int(np.argmin(np.abs(n)))]
    e1 = np.cross(ref, n)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    H = camera.K @ np.column_stack([e1, e2, tp.center])
    Hi = np.linalg.inv(H)
    C = Hi.T @ np.diag([1.0, 1.0, -tp.radius_mm**2]) @ Hi
    return C / np.linalg.norm(C)


def _edge_residuals(img, C, stripe_uv, *, half=5, axis=0):
    """Signed distances (px) from moment-located edge points to the conic, along rows (axis=0) or columns."""
    I = img.astype(np.float64) if axis == 0 else img.T.astype(np.float64)
    Cm = C if axis == 0 else C[[1, 0, 2]][:, [1, 0, 2]]  # swap u and v
    res = []
    for v in range(I.shape[0]):
        # conic restricted to the row: a u² + b u + c = 0
        a = Cm[0, 0]
        b = 2 * (Cm[0, 1] * v + Cm[0, 2])
        c = Cm[1, 1] * v * v + 2 * Cm[1, 2] * v + Cm[2, 2]
        disc = b * b - 4 * a * c
        if disc <= 0:
            continue
        for ue in ((-b - np.sqrt(disc)) / (2 * a), (-b + np.sqrt(disc)) / (2 * a)):
            grad = 2 * (Cm[:2, :2] @ [ue, v] + Cm[:2, 2])
            nrm = grad / np.linalg.norm(grad)
            if abs(nrm[0]) < 0.8:  # edge too oblique to this row
                continue
            if np.min(np.hypot(stripe_uv[:, 0] - (ue if axis == 0 else v), stripe_uv[:, 1] - (v if axis == 0 else ue))) < 25:
                continue
            u0, u1 = int(round(ue)) - half, int(round(ue)) + half
            if u0 - 4 < 0 or u1 + 4 >= I.shape[1]:
                continue
            left, right = I[v, u0 - 4:u0], I[v, u1 + 1:u1 + 5]
            if np.ptp(left) > 0 or np.ptp(right) > 0:
                continue  # not flat (something else nearby)
            L, R = left[0], right[0]
            xe = u0 - 0.5 + np.sum((I[v, u0:u1 + 1] - R) / (L - R))
            res.append((xe - ue) * abs(nrm[0]))
    return np.array(res)


def _stripe_residuals(img, camera, plane, tp, chord):
    """Distances (px) from the intensity centroid of each row's stripe profile on the disc to the projected chord."""
    ends = camera.project(chord, distort=False)
    line_n = np.array([-(ends[1, 1] - ends[0, 1]), ends[1, 0] - ends[0, 0]])
    line_n /= np.linalg.norm(line_n)
    C = _conic_from_truth(camera, tp)
    I = img.astype(np.float64)
    res = []
    for v in range(int(np.ceil(ends[:, 1].min())), int(np.floor(ends[:, 1].max())) + 1):
        t = (v - ends[0, 1]) / (ends[1, 1] - ends[0, 1])
        us = ends[0, 0] + t * (ends[1, 0] - ends[0, 0])
        # stripe width in px along the row: sheet sigma over d(distance to plane)/du on the disc
        pts = []
        for u in (us - 1, us + 1):
            ray = camera.rays(np.array([[u, v]]))[0]
            pts.append(ray * (tp.normal @ tp.center) / (tp.normal @ ray))
        dd = abs(plane.signed_distance(np.array(pts)) @ [-0.5, 0.5])
        half = int(np.ceil(5 * SHEET_SIGMA_MM / dd)) + 2
        us_win = np.arange(int(round(us)) - half, int(round(us)) + half + 1)
        # the whole window, 4 px more and 4 rows up and down, inside the rim (the conic is negative inside)
        q = np.array([[u, v + dv, 1.0] for u in (us_win[0] - 4, us_win[-1] + 4) for dv in (-4, 0, 4)])
        if np.any(np.einsum("ij,jk,ik->i", q, C, q) >= 0):
            continue
        prof = I[v, us_win]
        base = np.median(np.concatenate([prof[:2], prof[-2:]]))
        w = prof - base
        uc = np.sum(us_win * w) / np.sum(w)
        res.append((uc - us) * abs(line_n[0]))
    return np.array(res)


@pytest.fixture(scope="module")
def clean_pinhole_render():
    cam = default_camera().pinhole()
    plane = default_plane()
    tp = sample_placements(1, np.random.default_rng(5), camera=cam, plane=plane)[0]
    img = render_circle_image(cam, plane, tp, np.random.default_rng(1), CircleOptions(difficulty="clean", noise=False))
    # the same scene, laser off: the stripe's light (wide where the sheet grazes a surface) off the rim
    dark = render_circle_image(cam, plane, tp, np.random.default_rng(1), CircleOptions(difficulty="clean", noise=False),
                               laser=False)
    return cam, plane, tp, img, dark


def test_disc_edge_on_truth_conic(clean_pinhole_render):
    cam, plane, tp, _, img = clean_pinhole_render
    C = _conic_from_truth(cam, tp)
    # the conic recomputed here agrees with the one the truth file stores
    assert np.allclose(np.abs(C), np.abs(tp.conic(cam)), atol=1e-12)
    stripe_uv = cam.project(tp.chord(plane)[0] + np.linspace(0, 1, 200)[:, None] * (tp.chord(plane)[1] - tp.chord(plane)[0]), distort=False)
    res = np.concatenate([_edge_residuals(img, C, stripe_uv, axis=0), _edge_residuals(img, C, stripe_uv, axis=1)])
    print("edge points", res.size, "rms", np.sqrt(np.mean(res**2)), "mean", res.mean(), "max", np.abs(res).max())
    assert res.size > 200
    assert np.sqrt(np.mean(res**2)) <= 0.03


def test_stripe_ridge_on_truth_chord(clean_pinhole_render):
    cam, plane, tp, img, _ = clean_pinhole_render
    res = _stripe_residuals(img, cam, plane, tp, tp.chord(plane))
    print("stripe points", res.size, "rms", np.sqrt(np.mean(res**2)), "mean", res.mean(), "max", np.abs(res).max())
    assert res.size > 100
    assert np.sqrt(np.mean(res**2)) <= 0.03


def test_disc_edge_through_distorted_camera():
    """Same probe on a render through the distorted camera: edge points lie on the distorted rim."""
    cam = default_camera()
    plane = default_plane()
    tp = sample_placements(1, np.random.default_rng(11), camera=cam, plane=plane)[0]
    img = render_circle_image(cam, plane, tp, np.random.default_rng(2), CircleOptions(difficulty="clean", noise=False),
                              laser=False)
    I = img.astype(np.float64)
    rim = cam.project(tp.rim_points(40000))  # dense distorted rim polyline (segments ~0.04 px)
    chord = tp.chord(plane)
    stripe_uv = cam.project(chord[0] + np.linspace(0, 1, 200)[:, None] * (chord[1] - chord[0]))
    res = []
    nxt = np.roll(rim, -1, axis=0)
    for v in range(int(rim[:, 1].min()) + 1, int(rim[:, 1].max())):
        k = np.nonzero((rim[:, 1] - v) * (nxt[:, 1] - v) < 0)[0]
        for i in k:
            a, b = rim[i], nxt[i]
            ue = a[0] + (v - a[1]) * (b[0] - a[0]) / (b[1] - a[1])
            tangent = (b - a) / np.linalg.norm(b - a)
            n_u = abs(tangent[1])  # |u component of the normal|
            if n_u < 0.8 or np.min(np.hypot(*(stripe_uv - [ue, v]).T)) < 25:
                continue
            u0, u1 = int(round(ue)) - 5, int(round(ue)) + 5
            left, right = I[v, u0 - 4:u0], I[v, u1 + 1:u1 + 5]
            if np.ptp(left) > 0 or np.ptp(right) > 0:
                continue
            xe = u0 - 0.5 + np.sum((I[v, u0:u1 + 1] - right[0]) / (left[0] - right[0]))
            res.append((xe - ue) * n_u)
    res = np.array(res)
    print("distorted edge points", res.size, "rms", np.sqrt(np.mean(res**2)), "mean", res.mean(), "max", np.abs(res).max())
    assert res.size > 200
    assert np.sqrt(np.mean(res**2)) <= 0.03


def test_settings_tag_follows_the_image_formation_settings(monkeypatch):
    """Benchmark caches are named with it: any change of a level's settings must change it."""
    import dataclasses

    from lightplane.simulate import render as r

    tag = r.settings_tag()
    assert len(tag) == 8 and tag == r.settings_tag()
    changed = dict(r._IMAGING)
    changed["realistic"] = dataclasses.replace(changed["realistic"], sheet_sigma_mm=changed["realistic"].sheet_sigma_mm + 0.01)
    monkeypatch.setattr(r, "_IMAGING", changed)
    assert r.settings_tag() != tag
