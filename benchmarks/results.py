"""Machine-readable benchmark results: ``benchmarks/results/<bench>.json``.

Every ``bench_*.py`` ends with ``record(bench, figures)``: the machine, the git commit, the
UTC date, the command line and the run's headline figures, each made by :func:`figure`::

    figure("extract_profile_ms", "extract_profile 1280x960", 0.8, "ms", statistic="median of 200 runs",
           reference=("cv2.GaussianBlur", 1.1, "ms"), target=at_most(1.0, "ms"))

A figure holds a stable ``id``, a short ``label``, ``value`` and ``unit``; where it applies a
same-run ``reference`` (``label``, ``value``, ``unit``) and the ``ratio`` value / reference, a
``target`` (``op`` one of ``<=``, ``>=``, ``±`` (absolute value at most), ``between``; ``value``,
``unit``, ``of``: what it applies to, ``value``, ``error`` or ``ratio``; and ``met``), ``truth`` and
``error`` (value - truth) for accuracy figures, and the ``statistic``.  ``benchmarks/figures.py``
turns the files into the Markdown table of the README.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
ROOT = HERE.parent


# ----------------------------------------------------------------------------- targets
def at_most(value: float, unit: str, of: str = "value") -> dict:
    """The bar: the figure (or its ``error`` or ``ratio``) at most ``value``."""
    return {"op": "<=", "value": float(value), "unit": unit, "of": of}


def at_least(value: float, unit: str, of: str = "value") -> dict:
    """The bar: the figure (or its ``error`` or ``ratio``) at least ``value``."""
    return {"op": ">=", "value": float(value), "unit": unit, "of": of}


def within(value: float, unit: str, of: str = "value") -> dict:
    """The bar: the absolute value of the figure (or its ``error`` or ``ratio``) at most ``value``."""
    return {"op": "±", "value": float(value), "unit": unit, "of": of}


def between(lo: float, hi: float, unit: str, of: str = "value") -> dict:
    """The bar: the figure (or its ``error`` or ``ratio``) in ``[lo, hi]``."""
    return {"op": "between", "value": [float(lo), float(hi)], "unit": unit, "of": of}


def _met(target: dict, x: float) -> bool:
    op, v = target["op"], target["value"]
    if op == "<=":
        return x <= v
    if op == ">=":
        return x >= v
    if op == "±":
        return abs(x) <= v
    if op == "between":
        return v[0] <= x <= v[1]
    raise ValueError(f"unknown target op {op!r}")


def _num(x) -> float | None:
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def figure(id: str, label: str, value: float, unit: str, *, statistic: str | None = None,
           reference: tuple[str, float, str] | None = None, target: dict | None = None,
           truth: float | None = None) -> dict:
    """One figure (see the module doc); ``ratio``, ``error`` and ``target['met']`` are computed here."""
    f: dict = {"id": id, "label": label, "value": _num(value), "unit": unit}
    if reference is not None:
        rl, rv, ru = reference
        f["reference"] = {"label": rl, "value": _num(rv), "unit": ru}
        if ru == unit and f["value"] is not None and f["reference"]["value"]:
            f["ratio"] = f["value"] / f["reference"]["value"]
    if truth is not None:
        f["truth"] = float(truth)
        f["error"] = None if f["value"] is None else f["value"] - f["truth"]
    if target is not None:
        t = dict(target)
        of = t.get("of", "value")
        x = f.get(of)
        if of in ("value", "error") and t["unit"] != unit:
            raise ValueError(f"{id}: the target's unit {t['unit']!r} is not the figure's {unit!r}")
        t["met"] = None if x is None else bool(_met(t, x))
        f["target"] = t
    if statistic:
        f["statistic"] = statistic
    return f


# ----------------------------------------------------------------------------- context
def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith(("model name", "hardware", "cpu model")):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _version(module: str) -> str | None:
    try:
        from importlib.metadata import PackageNotFoundError, version
    except ImportError:  # pragma: no cover
        return None
    names = {"opencv": ("opencv-python-headless", "opencv-python", "opencv-contrib-python-headless",
                        "opencv-contrib-python")}.get(module, (module,))
    for n in names:
        try:
            return version(n)
        except PackageNotFoundError:
            continue
    return None


def machine() -> dict:
    """The machine and the software the figures were measured with."""
    try:
        affinity = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        affinity = None
    try:
        from lightplane.version import __version__ as lp_version
    except ImportError:
        lp_version = None
    try:
        from lightplane.core.threads import describe

        threads = describe()
    except Exception as e:  # noqa: BLE001 - the record must not fail on it
        threads = f"unavailable ({e})"
    try:
        import cv2

        opencv = cv2.__version__
    except ImportError:
        opencv = _version("opencv")
    return {"cpu": _cpu_model(), "logical_cores": os.cpu_count(), "affinity_cores": affinity,
            "platform": platform.platform(), "python": platform.python_version(),
            "numpy": _version("numpy"), "scipy": _version("scipy"), "opencv": opencv, "numba": _version("numba"),
            "lightplane": lp_version, "threads": threads}


def git_commit() -> str | None:
    """``git rev-parse --short HEAD``, with ``-dirty`` when tracked files differ from it."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return head + ("-dirty" if dirty else "")


def command_line() -> str:
    script = Path(sys.argv[0]).resolve() if sys.argv and sys.argv[0] else None
    if script is not None and script.is_file():
        try:
            arg0 = str(script.relative_to(ROOT))
        except ValueError:
            arg0 = str(script)
        return shlex.join(["python", arg0, *sys.argv[1:]])
    return shlex.join(["python", *sys.argv])


def record(bench: str, figures: list[dict], folder: Path | None = None) -> Path:
    """Write ``<folder>/<bench>.json`` (default ``benchmarks/results``): context and ``figures``; returns the path."""
    folder = RESULTS if folder is None else Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    ids = [f["id"] for f in figures]
    dup = {i for i in ids if ids.count(i) > 1}
    if dup:
        raise ValueError(f"{bench}: figure ids repeated: {sorted(dup)}")
    doc = {"bench": bench, "script": f"benchmarks/{bench}.py", "machine": machine(), "commit": git_commit(),
           "date": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"), "command": command_line(),
           "figures": figures}
    path = folder / f"{bench}.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(doc, indent=1, ensure_ascii=False) + "\n")
    tmp.replace(path)
    print(f"results: {len(figures)} figures written to {path}")
    return path
