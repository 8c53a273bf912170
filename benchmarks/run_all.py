"""Run every benchmark in this folder, one after the other (``make bench``).

Each benchmark prints medians with units and the ratio to its target; run them on a
quiet machine (2 cores is the reference).  ``python benchmarks/run_all.py NAME...``
runs only the named ones (e.g. ``stripe measure``).

Each benchmark also writes its headline figures to ``benchmarks/results/<bench>.json``
(``results.record``); ``python benchmarks/figures.py README.md`` then rewrites the README's
table of figures from them (``--check``: only compare).
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main(argv: list[str]) -> int:
    scripts = sorted(HERE.glob("bench_*.py"))
    if argv:
        scripts = [s for s in scripts if s.stem.removeprefix("bench_") in argv]
    failed = []
    for s in scripts:
        print(f"==== {s.name}", flush=True)
        t = time.perf_counter()
        r = subprocess.run([sys.executable, str(s)])
        print(f"==== {s.name}: exit {r.returncode}, {time.perf_counter() - t:.0f} s\n", flush=True)
        if r.returncode:
            failed.append(s.name)
    if failed:
        print("failed: " + ", ".join(failed))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
