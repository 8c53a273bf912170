"""Pairing laser frames with the pattern frame of their pose (--pattern, --cycle)."""

from __future__ import annotations

from pathlib import Path

import pytest

from lightplane.cli.calibrate_plane_board import pair_pattern_frames
from lightplane.core.errors import LightplaneError

F = [Path(f"f{i:02d}.png") for i in range(9)]


def test_cycle_fabscan_order():
    """Pattern, laser 0, laser 1 per position: P,L,- picks laser 0, P,-,L laser 1."""
    lasers, patterns = pair_pattern_frames(F, None, "P,L,-")
    assert lasers == [F[1], F[4], F[7]] and patterns == [F[0], F[3], F[6]]
    lasers, patterns = pair_pattern_frames(F, None, "p, -, l")
    assert lasers == [F[2], F[5], F[8]] and patterns == [F[0], F[3], F[6]]
    lasers, patterns = pair_pattern_frames(F, None, "P,L,L")
    assert lasers == [F[1], F[2], F[4], F[5], F[7], F[8]] and patterns == [F[0], F[0], F[3], F[3], F[6], F[6]]


def test_cycle_incomplete_last_pose_has_no_pattern():
    lasers, patterns = pair_pattern_frames(F[:8], None, "L,-,P")  # the last pose lacks its P
    assert lasers == [F[0], F[3], F[6]] and patterns == [F[2], F[5], None]


@pytest.mark.parametrize("cycle", ["L,L", "P,P,L", "P,X,L", "P"])
def test_bad_cycles(cycle):
    with pytest.raises(LightplaneError, match="--cycle"):
        pair_pattern_frames(F, None, cycle)


def test_pattern_files_shared_out_in_order():
    lasers, patterns = pair_pattern_frames(F[:6], [Path("a.png"), Path("b.png")], None)
    assert lasers == F[:6] and patterns == [Path("a.png")] * 3 + [Path("b.png")] * 3
    with pytest.raises(LightplaneError, match="evenly"):
        pair_pattern_frames(F[:5], [Path("a.png"), Path("b.png")], None)
    with pytest.raises(LightplaneError, match="not both"):
        pair_pattern_frames(F, [Path("a.png")], "P,L")
    assert pair_pattern_frames(F, None, None) == (F, None)
