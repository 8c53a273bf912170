"""The benchmark figures as a Markdown table, written between two marker lines of a Markdown file.

Reads every ``benchmarks/results/*.json`` (written by the benchmarks through ``results.record``)
and replaces what lies between the lines ``<!-- figures:begin -->`` and ``<!-- figures:end -->``
with one table row per figure: the figure, its value with unit, the same-run reference and the
ratio to it, the target and whether it is met, the benchmark script, the machine and the date.

    python benchmarks/figures.py README.md            # rewrite the region
    python benchmarks/figures.py --check README.md    # exit 1 (with a diff) if it differs
    python benchmarks/figures.py --results DIR FILE   # another results folder

``<!-- figures:begin targets -->`` instead of the first marker: only the figures that have a target;
``<!-- figures:begin headline -->``: per results file its first figure with a target, and every
figure whose target is not met.

Exits 1 with a message when a file lacks the markers (or holds them out of order).
"""

from __future__ import annotations

import argparse
import difflib
import json
import re
import sys
from pathlib import Path

BEGIN = "<!-- figures:begin -->"
BEGIN_TARGETS = "<!-- figures:begin targets -->"  # only the figures that have a target
# per results file its first figure with a target, and every figure whose target is not met
BEGIN_HEADLINE = "<!-- figures:begin headline -->"
END = "<!-- figures:end -->"
RESULTS = Path(__file__).resolve().parent / "results"

HEADER = ("| Figure | Value | Same-run reference | Ratio | Target | Met | Benchmark | Machine, date |\n"
          "|---|---|---|---|---|---|---|---|")


class MarkersMissing(ValueError):
    """The Markdown file does not hold the two marker lines, in order, once each."""


def num(x: float | None) -> str:
    """A number in 3 significant digits (whole numbers from 100 up), without an exponent unless it is tiny or huge."""
    if x is None:
        return "n/a"
    x = float(x)
    if x == 0:
        return "0"
    a = abs(x)
    if a >= 1e6 or a < 1e-4:
        return f"{x:.2e}"
    if a >= 1000:
        return f"{x:.0f}"
    return f"{x:.3g}" if a < 100 else f"{x:.0f}"


def quantity(x: float | None, unit: str) -> str:
    """A number and its unit (``x``, a ratio, written on the number)."""
    return num(x) + ("x" if unit == "x" else f" {unit}" if unit else "")


def cell(text: str) -> str:
    """A table cell: one line, with ``|`` escaped."""
    return " ".join(str(text).split()).replace("|", "\\|")


def machine_name(m: dict) -> str:
    """A short machine name: the CPU model without trademarks and clock, and the usable cores."""
    cpu = m.get("cpu") or "?"
    cpu = re.sub(r"\((R|TM|tm|r)\)", "", cpu)
    cpu = re.sub(r"\s*@.*$", "", cpu)
    cpu = re.sub(r"\b(CPU|Processor|\d+-Core)\b", "", cpu)
    cpu = " ".join(cpu.split())
    cores = m.get("affinity_cores") or m.get("logical_cores")
    return f"{cpu}, {cores} cores" if cores else cpu


def target_text(t: dict | None) -> tuple[str, str]:
    """(the target, met / not met) of a figure."""
    if not t:
        return "", ""
    of = {"value": "", "error": "error ", "ratio": "ratio "}.get(t.get("of", "value"), t.get("of", "") + " ")
    unit = t.get("unit", "")
    if t["op"] == "between":
        lo, hi = t["value"]
        text = f"{of}{num(lo)}–{quantity(hi, unit)}"
    elif t["op"] == "±":
        text = f"{of}±{quantity(t['value'], unit)}"
    else:
        text = f"{of}{t['op']} {quantity(t['value'], unit)}"
    met = {True: "met", False: "not met", None: "n/a"}[t.get("met")]
    return text, met


def rows(doc: dict, targets_only: bool = False, headline: bool = False) -> list[str]:
    """The table rows of one results file (only those with a target when ``targets_only``; with
    ``headline``, the first figure with a target and every other whose target is not met)."""
    where = f"{machine_name(doc.get('machine', {}))}, {str(doc.get('date', ''))[:10]}"
    script = Path(doc.get("script") or f"{doc.get('bench', '?')}.py").name
    out = []
    first = True
    for f in doc.get("figures", []):
        if (targets_only or headline) and not f.get("target"):
            continue
        if headline and not first and f["target"].get("met") is not False:
            continue
        first = False
        value = quantity(f.get("value"), f.get("unit", ""))
        if "truth" in f and f.get("value") is not None:  # more digits, and the error against the truth
            err = f.get("error")
            value = f"{f['value']:.5g} {f.get('unit', '')}".strip() + ("" if err is None else
                                                                       f" (error {'+' if err >= 0 else ''}{num(err)})")
        ref = f.get("reference")
        ref_text = f"{ref['label']}: {quantity(ref.get('value'), ref.get('unit', ''))}" if ref else ""
        ratio = f"{num(f['ratio'])}x" if f.get("ratio") is not None else ""
        tgt, met = target_text(f.get("target"))
        out.append("| " + " | ".join(cell(c) for c in (f.get("label", f.get("id", "?")), value, ref_text, ratio,
                                                         tgt, met, script, where)) + " |")
    return out


def table(results: Path = RESULTS, targets_only: bool = False, headline: bool = False) -> str:
    """The whole table (header and one row per figure, the files in name order; only the figures with a
    target when ``targets_only``; the headline figures of :func:`rows` with ``headline``), no trailing
    newline."""
    lines = [HEADER]
    for p in sorted(Path(results).glob("*.json")):
        lines += rows(json.loads(p.read_text()), targets_only, headline)
    return "\n".join(lines)


def _region(text: str) -> tuple[int, int]:
    """(the end of the BEGIN line, the start of the END line) in ``text``."""
    lines = text.splitlines(keepends=True)
    b = [i for i, line in enumerate(lines) if line.strip() in (BEGIN, BEGIN_TARGETS, BEGIN_HEADLINE)]
    e = [i for i, line in enumerate(lines) if line.strip() == END]
    if len(b) != 1 or len(e) != 1 or e[0] <= b[0]:
        raise MarkersMissing(f"needs the lines {BEGIN!r} and {END!r}, once each, in that order "
                             f"(found {len(b)} and {len(e)})")
    start = sum(len(line) for line in lines[:b[0] + 1])
    stop = sum(len(line) for line in lines[:e[0]])
    return start, stop


def fill(text: str, body: str) -> str:
    """``text`` with the region between the markers replaced by ``body``."""
    start, stop = _region(text)
    head = text[:start] if text[:start].endswith("\n") else text[:start] + "\n"
    return head + "\n" + body + "\n\n" + text[stop:]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("markdown", nargs="+", type=Path, help="Markdown file(s) holding the marker lines")
    ap.add_argument("--check", action="store_true", help="only compare; exit 1 with a diff when it differs")
    ap.add_argument("--results", type=Path, default=RESULTS, help="folder of the results/*.json files")
    args = ap.parse_args(argv)
    status = 0
    for md in args.markdown:
        text = md.read_text()
        try:
            marks = {line.strip() for line in text.splitlines()}
            new = fill(text, table(args.results, targets_only=BEGIN_TARGETS in marks, headline=BEGIN_HEADLINE in marks))
        except MarkersMissing as e:
            print(f"{md}: {e}", file=sys.stderr)
            status = 1
            continue
        if new == text:
            print(f"{md}: figures up to date")
        elif args.check:
            sys.stdout.writelines(difflib.unified_diff(text.splitlines(keepends=True), new.splitlines(keepends=True),
                                                       f"{md} (now)", f"{md} (from the results)"))
            print(f"{md}: the figures differ from the results; run: python benchmarks/figures.py {md}",
                  file=sys.stderr)
            status = 1
        else:
            md.write_text(new)
            print(f"{md}: figures written")
    return status


if __name__ == "__main__":
    sys.exit(main())
