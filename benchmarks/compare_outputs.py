"""Compare two folders written by record_outputs.sh: every file bit for bit, JSON files value by value with the
run's own timings and provenance left out.  Prints each difference; exits 1 when there is one."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

#: keys that record when and how fast a run went, not what it computed
VOLATILE = {"seconds", "provenance", "created_utc", "elapsed_s", "wall_s", "cpu_s", "timings", "time_s"}


def _diff(a, b, where: str, out: list[str]) -> None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if k in VOLATILE or "seconds" in k:
                continue
            if k not in a or k not in b:
                out.append(f"{where}/{k}: only in {'second' if k not in a else 'first'}")
            else:
                _diff(a[k], b[k], f"{where}/{k}", out)
    elif isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b)):
            _diff(x, y, f"{where}[{i}]", out)
    elif a != b:
        out.append(f"{where}: {str(a)[:80]} != {str(b)[:80]}")


def main(first: str, second: str) -> int:
    a, b = Path(first), Path(second)
    out: list[str] = []
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    for rel in files:
        pa, pb = a / rel, b / rel
        if not pb.exists():
            out.append(f"{rel}: missing in {b}")
        elif rel.suffix == ".json":
            _diff(json.loads(pa.read_text()), json.loads(pb.read_text()), str(rel), out)
        elif rel.suffix == ".npy":
            if not np.array_equal(np.load(pa), np.load(pb), equal_nan=True):
                out.append(f"{rel}: arrays differ")
        elif rel.suffix in (".html", ".log", ".txt"):
            continue  # reports carry timings; their numbers come from the JSON files compared above
        elif pa.read_bytes() != pb.read_bytes():
            out.append(f"{rel}: bytes differ")
    print("\n".join(out) if out else f"identical: {len(files)} files")
    return 1 if out else 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:3]))
