"""``lightplane simulate``: the paper's §3 simulation study (placements, noise, diameter)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import typer
from rich.table import Table

from lightplane.core.errors import LightplaneError
from lightplane.cli._common import app, console, handles_errors, progress_bar
from lightplane.core.io import check_output, provenance, write_json
from lightplane.evaluate.study import n_trials_total, run_factor, write_csv
from lightplane.report.plots import study_factor

_FACTOR_NAMES = ("placements", "noise", "diameter")


@app.command("simulate")
@handles_errors
def simulate_cmd(
    factor: Literal["placements", "noise", "diameter", "all"] = typer.Argument(..., help="Which study: placements, noise, diameter, or all."),
    out: Path = typer.Option(..., "--out", help="Output folder (created if missing) for CSV, PNG and study.json."),
    trials: int = typer.Option(100, "--trials", min=1, help="Random trials per level (fresh placements and noise)."),
    seed: int = typer.Option(0, "--seed", min=0, help="Random seed (results are reproducible for a given seed)."),
    n_rim: int = typer.Option(200, "--rim-points", min=5, help="Rim points per placement."),
    n_stripe: int = typer.Option(300, "--stripe-points", min=10, help="Stripe points per placement."),
    force: bool = typer.Option(False, "--force", help="Overwrite existing output files."),
) -> None:
    """Reproduce the paper's simulation study (§3) with the paper, global and ml methods and the Cramér–Rao bound.

    Geometry of the paper (f = 25 mm, plane 0.9336 y - 0.3584 z + 140.04 = 0); noise in
    pixels on rim and stripe points.  Writes <factor>.csv and <factor>.png per factor and
    study.json (all rows and provenance).
    """

    factors = list(_FACTOR_NAMES) if factor == "all" else [factor]
    if out.exists() and not out.is_dir():
        raise LightplaneError(f"{out}: exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    targets = [out / f"{f}.{ext}" for f in factors for ext in ("csv", "png")] + [out / "study.json"]
    for target in targets:  # refuse before the long run, not after it
        check_output(target, force)

    results = {}
    with progress_bar("simulating", n_trials_total(factors, trials), remaining=True) as update:
        for f in factors:
            update(label=f"simulating: {f}")
            res = run_factor(f, trials=trials, seed=seed, n_rim=n_rim, n_stripe=n_stripe,
                             progress=lambda k: update(advance=k))
            write_csv(res, out / f"{f}.csv", force=force)
            study_factor(res, out / f"{f}.png", force=force)
            results[f] = res

    for f, res in results.items():
        spec = res.factor
        t = Table(title=f"{f}: RMS normal angle error (deg), failed trials in brackets", show_edge=False)
        t.add_column(spec.label)
        for m in ("paper", "global", "ml", "crlb"):
            t.add_column("Cramér–Rao bound" if m == "crlb" else m, justify="right")
        for level in spec.levels:
            cells = []
            for m in ("paper", "global", "ml", "crlb"):
                row = next(r for r in res.rows if r["level"] == level and r["method"] == m)
                txt = f"{row['angle_deg']:.3g}"
                if m != "crlb" and row["failed"]:
                    txt += f" \\[{row['failed']}]"
                cells.append(txt)
            t.add_row(f"{level:g}", *cells)
        console.print(t)
        console.print(f"(triangulation and coefficient errors in {out / (f + '.csv')}; plots in {out / (f + '.png')})")
    write_json(out / "study.json", {
        "study": "Wang & Li 2022 §3 simulation (paper geometry; noise in px on rim and stripe points)",
        "factors": {f: {"levels": list(r.factor.levels), "variable": r.factor.variable, "rows": r.rows}
                    for f, r in results.items()},
        "provenance": provenance([], {"factor": factor, "trials": trials, "seed": seed, "rim_points": n_rim,
                                      "stripe_points": n_stripe}),
    }, force=force)
    console.print(f"wrote {out / 'study.json'}")
