"""``lightplane report``: rebuild a calibration's HTML report from its result file alone."""

from __future__ import annotations

from pathlib import Path

import typer

from lightplane.cli._common import app, console, handles_errors, progress_bar
from lightplane.report.calibrations import write_calibration_report


@app.command("report")
@handles_errors
def report_cmd(
    result: Path = typer.Argument(..., help="Result file of a calibration: a camera file (calibrate-camera), a "
                                  "plane file (calibrate-plane, calibrate-plane-board), a turntable file "
                                  "(calibrate-turntable) or a sensor file (refine-turntable)."),
    out: Path = typer.Option(..., "--out", help="Folder for the HTML report (index.html)."),
    force: bool = typer.Option(False, "--force", help="Overwrite an existing report."),
) -> None:
    """Rebuild the HTML report of a calibration from its result file (the points, poses and residuals it stores).

    The report opens with a verdict (what the calibration is good for, what limits it), then the
    coverage of the views, the residuals per view and over the image, and the σ map. Image
    thumbnails of calibrate-plane come from the image files named in the plane file when they
    still exist; otherwise the points are drawn on a blank canvas of the image's size.
    """
    with progress_bar("writing the report"):
        path = write_calibration_report(result, out, force=force)
    console.print(f"wrote {path}")
