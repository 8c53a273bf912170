"""core.jit: lightplane's kernel cache folder, its notice on compilation, no process-wide setting.

Each test runs Python in a subprocess with an empty ``LIGHTPLANE_CACHE_DIR`` and two small kernels
declared with ``njit_cached`` in a module of its own (compiling lightplane's real kernels from cold
takes tens of seconds: benchmarks/bench_first_run.py does that)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from lightplane.core import jit
from lightplane.version import __version__

KERNELS = '''
import numpy as np
from lightplane.core.jit import njit_cached


@njit_cached(error_model="numpy")
def scale(x, k):
    return x * k


@njit_cached
def total(a):
    s = 0.0
    for i in range(a.shape[0]):
        s += scale(a[i], 2.0)
    return s
'''

SCRIPT = '''
import json, os, sys
sys.path.insert(0, sys.argv[1])
before = dict(os.environ)
import numba
numba_cache_dir = numba.config.CACHE_DIR
if sys.argv[2] == "full":
    import lightplane  # the public API: every kernel module
import numpy as np
from lightplane.core import jit
import tiny_kernels as T
told = []
jit.set_compile_listener(lambda: told.append(1) or print(jit.compile_notice(), file=sys.stderr))
idx_before = [str(p) for p in jit.index_files(T.total)]
value = T.total(np.arange(4.0))
print(json.dumps({"env_changed": sorted(k for k in set(before) | set(os.environ) if before.get(k) != os.environ.get(k)),
                  "numba_cache_dir_same": numba.config.CACHE_DIR == numba_cache_dir,
                  "told": len(told), "compiled": jit.compiled_count(), "value": value,
                  "index_before": idx_before, "index_after": [str(p) for p in jit.index_files(T.total)],
                  "folder": str(jit.kernel_cache_dir())}))
'''


def _run(tmp_path: Path, cache: Path, source: str = KERNELS, full: bool = False) -> tuple[dict, str]:
    if not (tmp_path / "tiny_kernels.py").exists() or (tmp_path / "tiny_kernels.py").read_text() != source:
        (tmp_path / "tiny_kernels.py").write_text(source)
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", jit.CACHE_ENV)}
    env[jit.CACHE_ENV] = str(cache)
    r = subprocess.run([sys.executable, "-c", SCRIPT, str(tmp_path), "full" if full else "jit"], env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1]), r.stderr


def test_cache_folder_notice_once_then_warm(tmp_path: Path):
    cache = tmp_path / "cache"
    out, err = _run(tmp_path, cache, full=True)
    assert out["value"] == 12.0
    # the kernels' cache files are in LIGHTPLANE_CACHE_DIR/numba/<version>/..., nowhere near the sources
    assert Path(out["folder"]) == cache / "numba" / __version__
    assert out["index_before"] == [] and len(out["index_after"]) == 1
    assert Path(out["index_after"][0]).is_relative_to(cache / "numba" / __version__)
    assert sorted(p.name.split("-")[0] for p in cache.rglob("tiny_kernels.*.nbi")) == \
        ["tiny_kernels.scale", "tiny_kernels.total"]
    assert not list(tmp_path.glob("__pycache__/*.nbi"))
    # cold: two kernels compiled, one notice
    assert out["compiled"] == 2 and out["told"] == 1
    assert err.count("compiling lightplane's kernels") == 1
    # importing lightplane (all its kernel modules) set no environment variable, numba's own cache untouched
    assert out["env_changed"] == [] and out["numba_cache_dir_same"]
    # warm: loaded from the folder, nothing compiled, no notice
    again, err2 = _run(tmp_path, cache)
    assert again["compiled"] == 0 and again["told"] == 0 and again["value"] == 12.0
    assert "compiling" not in err2


def test_source_stamp_is_the_content_not_the_time(tmp_path: Path):
    cache = tmp_path / "cache"
    _run(tmp_path, cache)
    os.utime(tmp_path / "tiny_kernels.py", (1.0, 1.0))   # a reinstall: same content, another time stamp
    out, _ = _run(tmp_path, cache)
    assert out["compiled"] == 0
    out, _ = _run(tmp_path, cache, KERNELS.replace("x * k", "k * x"))   # changed source: compiled again
    assert out["compiled"] == 2 and out["told"] == 1


def test_cache_root_follows_the_environment(monkeypatch, tmp_path: Path):
    monkeypatch.setenv(jit.CACHE_ENV, str(tmp_path / "x"))
    assert jit.kernel_cache_dir() == tmp_path / "x" / "numba" / __version__
    monkeypatch.delenv(jit.CACHE_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    if sys.platform.startswith("linux"):
        assert jit.cache_root() == tmp_path / "xdg" / "lightplane"


def test_every_kernel_is_cached_by_lightplane():
    import lightplane  # noqa: F401  (every kernel module)

    kernels = jit.cached_kernels()
    assert len(kernels) >= 50
    assert all(type(k._cache).__name__ == "_KernelCache" for k in kernels)
