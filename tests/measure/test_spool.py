"""PointSpool's temporary files: removed on every way out of a scan, and left-overs of killed runs
removed by the next spool made in their folder."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from lightplane.measure.pointcloud import POINT_DTYPE, SPOOL_PREFIX, STALE_SPOOL_S, PointSpool, remove_stale_spools
from lightplane.measure.scan import ArrayFrames, measure_scan
from lightplane.core.errors import LightplaneError
from lightplane.simulate.scene import default_camera, default_plane


def _spools(folder: Path) -> list[Path]:
    return sorted(folder.glob(f"{SPOOL_PREFIX}*.bin"))


def _records(n: int = 5) -> np.ndarray:
    return np.zeros(n, POINT_DTYPE)


@pytest.mark.parametrize("exc", [RuntimeError, KeyboardInterrupt, LightplaneError])
def test_spool_removed_whatever_ends_the_block(tmp_path: Path, exc):
    with pytest.raises(exc):
        with PointSpool(tmp_path) as spool:
            spool.append(_records())
            assert _spools(tmp_path) == [Path(spool.path)]
            raise exc("stop")
    assert _spools(tmp_path) == []


def test_scan_that_fails_leaves_no_spool(tmp_path: Path, monkeypatch):
    import lightplane.measure.scan as scan

    made = []

    class Recorded(PointSpool):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            made.append(Path(self.path))

    monkeypatch.setattr(scan, "PointSpool", Recorded)
    camera, plane = default_camera(), default_plane()
    good = np.zeros((camera.height, camera.width), np.uint8)
    good[400:405] = 200
    wrong_size = np.zeros((10, 10), np.uint8)   # stops the scan after the first frame went through
    with pytest.raises(LightplaneError, match="10x10|size"):
        measure_scan(ArrayFrames([good, good, wrong_size]), camera, plane, tmp_path / "cloud.ply", workers=1)
    assert len(made) == 1 and made[0].parent == tmp_path   # the scan had its spool ...
    assert _spools(tmp_path) == [] and not (tmp_path / "cloud.ply").exists()   # ... and removed it


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_stale_spools_removed_by_the_next_run(tmp_path: Path):
    from lightplane.measure.pointcloud import _host

    host = _host()
    dead = tmp_path / f"{SPOOL_PREFIX}{host}-{_dead_pid()}-abc123.bin"           # a killed run of this machine
    alive = tmp_path / f"{SPOOL_PREFIX}{host}-{os.getppid()}-def456.bin"         # a running process's: kept
    other = tmp_path / f"{SPOOL_PREFIX}otherhost-{os.getpid()}-ghi789.bin"        # another machine's, fresh: kept
    old = tmp_path / f"{SPOOL_PREFIX}otherhost-12345-jkl012.bin"                  # another machine's, old: removed
    legacy = tmp_path / f"{SPOOL_PREFIX}x1y2z3.bin"                               # the older name, old: removed
    unrelated = tmp_path / "cloud.ply"
    for p in (dead, alive, other, old, legacy, unrelated):
        p.write_bytes(b"\0" * 32)
    t_old = time.time() - STALE_SPOOL_S - 60
    for p in (old, legacy):
        os.utime(p, (t_old, t_old))
    with PointSpool(tmp_path) as spool:
        mine = Path(spool.path)
        assert mine.name.startswith(f"{SPOOL_PREFIX}{host}-{os.getpid()}-")
        assert sorted(_spools(tmp_path)) == sorted([alive, other, mine])
    assert unrelated.exists()
    assert remove_stale_spools(tmp_path, max_age_s=0.0) == [other]   # any age limit applies to unknown owners only
    assert _spools(tmp_path) == [alive]


def test_sigterm_ends_the_command_line_with_its_spool_removed(tmp_path: Path):
    """The command line turns SIGTERM into an exit, so the spool's block ends as on an error."""
    code = (
        "import os, signal, sys\n"
        "import lightplane.cli as cli\n"
        "signal.signal(signal.SIGTERM, cli._exit_on_sigterm)\n"
        "from lightplane.measure.pointcloud import PointSpool\n"
        f"with PointSpool({str(tmp_path)!r}) as s:\n"
        "    os.kill(os.getpid(), signal.SIGTERM)\n"
        "    sys.exit(0)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 128 + signal.SIGTERM, r.stderr
    assert _spools(tmp_path) == []
