"""The turntable's two axis estimates against their σ: refused far apart, kept and marked on request."""

from __future__ import annotations

import pytest

from lightplane.core.errors import LightplaneError
from lightplane.motion.turntable import SUSPECT_SIGMAS, _axis_quality


def test_axis_estimates_within_their_sigma_pass():
    rec = _axis_quality(0.02, 0.05, 0.01, 0.05, keep=False)  # 2 σ and 1 σ (FabScan: 1.6 and 2.0)
    assert rec["verdict"] == "ok" and rec["direction_sigmas"] == pytest.approx(2.0)
    assert _axis_quality(0.05, 0.05, 0.01, 0.05, keep=False)["verdict"] == "elevated"  # 5 σ: flagged, kept


def test_axis_estimates_far_apart_refused_unless_kept():
    ang, sd = 0.5, 0.5 / (SUSPECT_SIGMAS + 1)
    with pytest.raises(LightplaneError, match=r"suspect turntable axis: .* 11 and 1 times their combined σ"):
        _axis_quality(ang, 0.05, sd, 0.05, keep=False)
    rec = _axis_quality(ang, 0.05, sd, 0.05, keep=True)
    assert rec["verdict"] == "suspect" and rec["kept_by_request"] and "board moved" in rec["diagnosis"]
