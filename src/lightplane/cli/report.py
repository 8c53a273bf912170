"""``lightplane report``: rebuild the HTML report of ``calibrate-plane`` from its plane file alone."""

from __future__ import annotations

from pathlib import Path

import typer

from lightplane.cli._common import app, console, handles_errors
from lightplane.report.html import rebuild_report


@app.command("report")
@handles_errors
def report_cmd(
    plane: Path = typer.Argument(..., help="Light-plane file written by calibrate-plane (JSON)."),
    out: Path = typer.Option(..., "--out", help="Folder for the HTML report (index.html)."),
    force: bool = typer.Option(False, "--force", help="Overwrite an existing report."),
) -> None:
    """Rebuild the calibrate-plane HTML report from the plane file (the points, poses and residuals it stores).

    Image thumbnails come from the image files named in the plane file when they still
    exist; otherwise the points are drawn on a blank canvas of the image's size.
    """
    path = rebuild_report(plane, out, force=force)
    console.print(f"wrote {path}")
