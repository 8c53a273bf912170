"""``lightplane demo``: run the whole chain on an embedded synthetic data set."""

from __future__ import annotations

from pathlib import Path

import typer

from lightplane.cli._common import app, console, handles_errors
from lightplane.report.demo import run_demo


@app.command("demo")
@handles_errors
def demo_cmd(
    out: Path = typer.Option(Path("demo-out"), "--out", help="Folder for the data set, results and report."),
    force: bool = typer.Option(False, "--force", help="Replace the files of an earlier demo in that folder."),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed of the synthetic data set."),
) -> None:
    """Render a synthetic data set and run every stage of lightplane on it."""
    run_demo(out, force=force, seed=seed, console=console)
