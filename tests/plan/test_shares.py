"""Information shares of a finished calibration's placements (what calibrate-plane prints)."""

from types import SimpleNamespace

import numpy as np

from lightplane.plane.model import LightPlane
from lightplane.plan.shares import information_shares
from lightplane.simulate.scene import TargetPlacement, default_camera, default_plane, synthetic_observations

CAM, PLANE = default_camera(), default_plane()


def _placement(z, tilt_deg, axis):
    P = np.array([0.0, 0.0, z])
    P[0] = -(PLANE.d + PLANE.normal[2] * z) / PLANE.normal[0]  # on the plane, y = 0
    v = -P / np.linalg.norm(P)
    a = np.radians(tilt_deg)
    return TargetPlacement(P, np.cos(a) * v + np.sin(a) * np.cross(axis, v), 50.0)


def test_shares_sum_to_one_and_follow_the_points():
    """Shares sum to 1; the same place taken twice, once with a tenth of the stripe points, adds less the second
    time; two mirror-image placements add the same."""
    ps = [_placement(400, 35, [0, 1, 0]), _placement(510, 35, [0, 1, 0]), _placement(400, 35, [1, 0, 0]),
          _placement(400, 35, [-1, 0, 0]), _placement(400, 35, [0, 1, 0])]
    images = []
    for k, p in enumerate(ps):
        rim, st = synthetic_observations(CAM, PLANE, p, n_rim=600, n_stripe=20 if k == 4 else 200)
        images.append(SimpleNamespace(index=k, name=f"im{k}", used=True, rim_uv=rim, stripe_uv=st,
                                      placement=SimpleNamespace(pose=p)))
    plane = LightPlane(PLANE.normal, PLANE.d, meta={"noise_model": {"sigma_rim_px": 0.05, "sigma_stripe_px": 0.1}})
    cal = SimpleNamespace(plane=plane, images=images, diameter_mm=50.0)
    s = information_shares(cal, CAM)
    assert sorted(s) == [0, 1, 2, 3, 4] and abs(sum(s.values()) - 1) < 1e-9 and min(s.values()) > 0
    assert s[4] < 0.5 * s[0]
    assert abs(s[2] - s[3]) < 0.05 * s[2]
