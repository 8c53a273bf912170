"""``lightplane calibrate-camera``: Zhang intrinsic calibration from chessboard images."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from ..errors import LightplaneError
from ..io import check_output, expand_inputs, provenance
from ._common import app, console, handles_errors, parse_board


#: Corner refinement recorded by calibrate_camera -> (what the summary says, the function in the provenance).
_CORNER_METHODS = {"saddle": ("blurred-saddle model fit", "fit_corners"),
                   "forstner": ("Förstner (gradient orthogonality)", "refine_corners")}


@app.command("calibrate-camera")
@handles_errors
def calibrate_camera_cmd(
    images: List[str] = typer.Argument(..., help="Chessboard images (files, folders or glob patterns)."),
    board: str = typer.Option(..., "--board", help="Inner corners, COLSxROWS (e.g. 9x6)."),
    square: float = typer.Option(..., "--square", help="Square size in mm."),
    output: Path = typer.Option(..., "-o", "--output", help="Camera file to write (.json; .yaml for ROS, .xml for OpenCV)."),
    rotate: int = typer.Option(0, "--rotate", help="Rotate every image clockwise by 0/90/180/270 degrees first."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Write a residual plot (PNG/PDF/SVG)."),
    fix_k3: bool = typer.Option(False, "--fix-k3", help="Keep k3 = 0 (advisable for narrow lenses, where k3 is "
                                "poorly determined)."),
    zero_tangent: bool = typer.Option(False, "--zero-tangent", help="Keep p1 = p2 = 0 (only if the lens has no "
                                      "tangential distortion: otherwise the principal point is biased)."),
    force: bool = typer.Option(False, "--force", help="Overwrite existing output files."),
) -> None:
    """Calibrate the camera's intrinsics and lens distortion (Zhang; OpenCV)."""
    import cv2

    from ..intrinsics import INTRINSIC_NAMES, calibrate_camera, plot_residuals

    cols, rows = parse_board(board)
    if square <= 0:
        raise LightplaneError(f"--square must be positive, got {square} mm")
    files = expand_inputs(images)
    if not files:
        raise LightplaneError("no images given (no files matched)")
    check_output(output, force)
    if plot is not None:
        check_output(plot, force)
    for f in files:  # fail early, before the long corner search, on a missing file
        if not f.is_file():
            raise LightplaneError(f"{f}: no such file")

    with Progress(TextColumn("finding corners"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console, transient=True) as bar:
        task = bar.add_task("corners", total=len(files))
        flags = (cv2.CALIB_FIX_K3 if fix_k3 else 0) | (cv2.CALIB_ZERO_TANGENT_DIST if zero_tangent else 0)
        result = calibrate_camera([str(f) for f in files], (cols, rows), square, rotate_deg=rotate, flags=flags,
                                  progress=lambda i, n: bar.update(task, completed=i))

    cam = result.camera
    t = Table(title="Camera intrinsics (Zhang, OpenCV)", show_edge=False)
    t.add_column("parameter")
    t.add_column("value", justify="right")
    t.add_column("± std", justify="right")
    t.add_column("unit")
    values = [cam.fx, cam.fy, cam.cx, cam.cy, *cam.dist]
    for name, v in zip(INTRINSIC_NAMES, values):
        unit = "px" if name in ("fx", "fy", "cx", "cy") else "-"
        t.add_row(name, f"{v:.6g}" if unit == "-" else f"{v:.3f}", f"{result.std.get(name, float('nan')):.2g}", unit)
    console.print(t)
    console.print(f"RMS reprojection error: {result.rms_px:.4f} px over {len(result.used)} views "
                  f"({cam.width}x{cam.height} px)")
    label, refiner = _CORNER_METHODS.get(str(result.options.get("refine")), ("cornerSubPix only", "none"))
    blur = result.options.get("median_blur_px")
    console.print(f"Corners: {label}" + (f"; median edge blur {blur:.2f} px" if blur is not None else ""))
    console.print("Per-view RMS, worst first:")
    for name, e in result.ranked_views():
        console.print(f"  {e:.4f} px  {name}")
    if result.not_found:
        console.print(f"Board not found in {len(result.not_found)} view(s): " + ", ".join(result.not_found))

    extra = {
        "calibration": result.to_dict(),
        "provenance": provenance(files, {"board": f"{cols}x{rows}", "square_mm": square, "rotate_deg": rotate,
                                         "flags": result.flags, "fix_k3": fix_k3, "zero_tangent": zero_tangent,
                                         "detector": f"findChessboardCornersSB+cornerSubPix+{refiner}",
                                         "solver": "calibrateCameraExtended"}),
    }
    suffix = output.suffix.lower()
    if suffix == ".json" or suffix == "":
        cam.save_json(output, force=force, extra=extra)
    else:
        cam.save(output, force=force)
    console.print(f"wrote {output}")
    if plot is not None:
        plot_residuals(result, str(plot))
        console.print(f"wrote {plot}")
