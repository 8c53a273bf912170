"""The guide as a page runs it: points in, plain JSON out, until the stop."""

import json

import numpy as np
import pytest

from lightplane.core.errors import LightplaneError
from lightplane.plan.candidates import PoseLimits
from lightplane.plan.planner import PlannerOptions
from lightplane.plan.session import GuideSession
from lightplane.plan.volume import region_volume
from lightplane.simulate.scene import TargetPlacement, default_camera, default_plane, synthetic_observations

CAM, PLANE = default_camera(), default_plane()


def test_session_summaries_until_the_stop():
    vol = region_volume(CAM, PLANE, None, distance_mm=(380, 520), step_px=48)
    g = GuideSession(CAM, PLANE, vol, PlannerOptions(PoseLimits(50.0, distance_mm=(380, 520)),
                                                     target_sigma_mm=0.008, max_placements=12))
    rng = np.random.default_rng(5)
    s = g.summary()
    for _ in range(12):
        json.dumps(s)  # plain JSON values
        if s["verdict"]["status"] != "continue":
            break
        sug = s["suggestion"]
        assert len(sug["outline_px"]) == 72 and sug["sigma_after_mm"] <= sug["sigma_now_mm"]
        p = TargetPlacement(sug["centre_mm"], sug["normal"], 50.0)
        z = p.center[2]
        rim, st = synthetic_observations(CAM, PLANE, p, n_rim=int(2 * np.pi * 25 * CAM.fx / z),
                                         n_stripe=int(40 * CAM.fx / z), sigma_px=0.1, rng=rng)
        s = g.accept_points(rim, st)
    assert s["verdict"]["status"] == "reached" and s["suggestion"] is None
    assert len(s["history_sigma_mm"]) == s["n_placements"] and s["history_sigma_mm"][-1] <= 0.008
    assert s["coverage"]["n"] == s["n_placements"]
    with pytest.raises(LightplaneError, match="not taken"):
        g.accept_image(np.zeros((960, 1280), np.uint8))
