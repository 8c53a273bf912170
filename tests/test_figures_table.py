"""benchmarks/figures.py: the Markdown table of the benchmark figures (benchmarks/results/*.json)."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"_bench_{name}", BENCH / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


figures = _load("figures")
results = _load("results")


def _doc(figs: list[dict]) -> dict:
    return {"bench": "bench_demo", "script": "benchmarks/bench_demo.py",
            "machine": {"cpu": "Intel(R) Xeon(R) Gold 6230 CPU @ 2.10GHz", "logical_cores": 4, "affinity_cores": 2},
            "commit": "abc1234", "date": "2025-01-02T03:04:05Z", "command": "python benchmarks/bench_demo.py",
            "figures": figs}


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    d = tmp_path / "results"
    d.mkdir()
    figs = [results.figure("speed", "demo speed", 0.5, "ms", statistic="median of 9 runs",
                           reference=("cv2.GaussianBlur", 2.0, "ms"), target=results.at_most(1.0, "ms")),
            results.figure("radius", "sphere radius", 25.43, "mm", truth=25.4,
                           target=results.within(0.02, "mm", of="error")),
            results.figure("rate", "frames", 450.0, "frames/s", target=results.at_least(500.0, "frames/s"))]
    (d / "bench_demo.json").write_text(json.dumps(_doc(figs)))
    return d


def test_figure_fields():
    f = results.figure("x", "x", 3.0, "ms", reference=("ref", 1.5, "ms"), target=results.at_most(1.0, "x", of="ratio"))
    assert f["ratio"] == pytest.approx(2.0)
    assert f["target"]["met"] is False
    g = results.figure("r", "r", 25.41, "mm", truth=25.4, target=results.within(0.02, "mm", of="error"))
    assert g["error"] == pytest.approx(0.01) and g["target"]["met"] is True
    assert results.figure("b", "b", 1.1, "x", target=results.between(0.85, 1.15, "x"))["target"]["met"] is True
    with pytest.raises(ValueError):
        results.figure("u", "u", 1.0, "ms", target=results.at_most(1.0, "s"))


def test_record_writes_context(tmp_path: Path):
    p = results.record("bench_demo", [results.figure("a", "a", 1.0, "s")], folder=tmp_path)
    doc = json.loads(p.read_text())
    assert p.name == "bench_demo.json"
    assert {"cpu", "logical_cores", "affinity_cores", "python", "numpy", "lightplane", "threads"} <= set(doc["machine"])
    assert doc["date"].endswith("Z") and doc["command"] and doc["figures"][0]["id"] == "a"
    with pytest.raises(ValueError):
        results.record("bench_demo", [results.figure("a", "a", 1.0, "s")] * 2, folder=tmp_path)


def test_table(folder: Path):
    lines = figures.table(folder).splitlines()
    assert lines[0] == figures.HEADER.splitlines()[0]
    assert lines[2:] == [
        "| demo speed | 0.5 ms | cv2.GaussianBlur: 2 ms | 0.25x | <= 1 ms | met | bench_demo.py"
        " | Intel Xeon Gold 6230, 2 cores, 2025-01-02 |",
        "| sphere radius | 25.43 mm (error +0.03) |  |  | error ±0.02 mm | not met | bench_demo.py"
        " | Intel Xeon Gold 6230, 2 cores, 2025-01-02 |",
        "| frames | 450 frames/s |  |  | >= 500 frames/s | not met | bench_demo.py"
        " | Intel Xeon Gold 6230, 2 cores, 2025-01-02 |",
    ]
    assert all(len(line) < 200 for line in lines)
    assert figures.num(-0.000721) == "-0.000721" and figures.num(1234.4) == "1234" and figures.num(0.3333) == "0.333"
    assert figures.quantity(1.04, "x") == "1.04x" and figures.quantity(0.963, "") == "0.963"


def test_headline_rows(folder: Path):
    """The headline table: the first figure with a target, then only the targets not met."""
    lines = figures.table(folder, headline=True).splitlines()[2:]
    assert [line.split(" | ")[0] for line in lines] == ["| demo speed", "| sphere radius", "| frames"]
    doc = json.loads((folder / "bench_demo.json").read_text())
    doc["figures"] = [results.figure("info", "informational", 1.0, "ms")] + [
        results.figure(k, k, v, "ms", target=results.at_most(1.0, "ms")) for k, v in (("a", 2.0), ("b", 0.5), ("c", 3.0))]
    (folder / "bench_demo.json").write_text(json.dumps(doc))
    lines = figures.table(folder, headline=True).splitlines()[2:]
    assert [line.split(" | ")[0] for line in lines] == ["| a", "| c"]


def test_write_and_check(folder: Path, tmp_path: Path, capsys):
    md = tmp_path / "doc.md"
    md.write_text(f"# Title\n\n{figures.BEGIN}\nstale\n{figures.END}\n\nafter\n")
    assert figures.main(["--check", "--results", str(folder), str(md)]) == 1
    assert "+| demo speed | 0.5 ms" in capsys.readouterr().out  # the diff
    assert figures.main(["--results", str(folder), str(md)]) == 0
    text = md.read_text()
    assert text.startswith("# Title\n\n") and text.endswith(f"{figures.END}\n\nafter\n") and "stale" not in text
    assert "| 0.25x |" in text
    assert figures.main(["--check", "--results", str(folder), str(md)]) == 0
    assert figures.main(["--results", str(folder), str(md)]) == 0 and md.read_text() == text  # idempotent


def test_missing_markers_refused(folder: Path, tmp_path: Path, capsys):
    md = tmp_path / "plain.md"
    md.write_text(f"# No figures here\n{figures.BEGIN}\n")
    for argv in (["--check"], []):
        assert figures.main([*argv, "--results", str(folder), str(md)]) == 1
        assert "figures:end" in capsys.readouterr().err
    assert md.read_text() == f"# No figures here\n{figures.BEGIN}\n"


def test_readme_figures_match_the_committed_results():
    """README.md's figures region is what benchmarks/results/*.json generate
    (fix: python benchmarks/figures.py README.md)."""
    assert figures.main(["--check", str(ROOT / "README.md")]) == 0
