"""``lightplane measure``: stripe frames (images, folder, glob or video) → point cloud (PLY/CSV/NPY)."""

from __future__ import annotations

from pathlib import Path
from typing import List, Literal, Optional

import typer

from ..errors import LightplaneError
from ._common import Channel, app, console, err_console, handles_errors, progress_bar


def parse_vector(text: str, name: str) -> tuple[float, float, float]:
    """'X,Y,Z' → three floats."""
    try:
        v = tuple(float(t) for t in text.split(","))
    except ValueError:
        raise LightplaneError(f"{name} must be X,Y,Z (three numbers), got {text!r}") from None
    if len(v) != 3:
        raise LightplaneError(f"{name} must be X,Y,Z (three numbers), got {text!r}")
    return v  # type: ignore[return-value]


def parse_roi(text: str) -> tuple[int, int, int, int]:
    """'X0,Y0,X1,Y1' (pixel bounds, X1/Y1 exclusive) → (x, y, width, height)."""
    try:
        x0, y0, x1, y1 = (int(t) for t in text.split(","))
    except ValueError:
        raise LightplaneError(f"--roi must be X0,Y0,X1,Y1 (integer px), got {text!r}") from None
    if x1 <= x0 or y1 <= y0:
        raise LightplaneError(f"--roi must have X1 > X0 and Y1 > Y0, got {text!r}")
    return x0, y0, x1 - x0, y1 - y0


@app.command("measure")
@handles_errors
def measure_cmd(
    inputs: List[str] = typer.Argument(..., help="Stripe frames: image files, folders, globs, or one video file."),
    camera: Path = typer.Option(..., "--camera", help="Camera file (JSON, ROS YAML or OpenCV YAML/XML)."),
    plane: Path = typer.Option(..., "--plane", help="Light-plane JSON file (from calibrate-plane)."),
    output: Path = typer.Option(..., "-o", "--output", help="Point-cloud file (.ply, .csv or .npy)."),
    step: Optional[float] = typer.Option(None, "--step", help="Object motion between frames, mm (with --direction)."),
    direction: Optional[str] = typer.Option(None, "--direction", help="Motion direction X,Y,Z in the camera frame (normalised; write --direction=-1,0,0 when it starts with a minus)."),
    positions: Optional[Path] = typer.Option(None, "--positions", help="CSV of the object's position per frame: dx,dy,dz mm "
                                             "(camera frame), or one column along --direction; one row per frame."),
    fmt: Optional[str] = typer.Option(None, "--format", help="ply, csv or npy (default: from the output suffix)."),
    ascii_ply: bool = typer.Option(False, "--ascii", help="ASCII PLY instead of binary."),
    roi: Optional[str] = typer.Option(None, "--roi", help="Region X0,Y0,X1,Y1 in px (X1, Y1 exclusive)."),
    axis: Literal["auto", "columns", "rows"] = typer.Option("auto", "--axis", help="One centre per 'columns', 'rows', or 'auto' (from the plane)."),
    channel: Optional[Channel] = typer.Option(None, "--channel", help="Colour channel of the laser: red, green, blue, gray."),
    stripe_width: Optional[float] = typer.Option(None, "--stripe-width", help="Stripe width (FWHM) px; default: estimated on the first frame."),
    smooth: int = typer.Option(0, "--smooth", help="Smooth the centres along the stripe over N lines (odd >= 5; 0: off)."),
    sigma_along: Optional[float] = typer.Option(
        None, "--sigma-along", help="Gaussian scale along the stripe before its centre is found, px (default: the "
        "stripe's own scale). About twice that averages laser speckle (0.11 -> 0.09 px per centre on speckled "
        "renders) and blurs detail along the stripe over as many lines."),
    workers: Optional[int] = typer.Option(None, "--workers", min=1, help="Worker threads (default: all CPUs)."),
    force: bool = typer.Option(False, "--force", help="Overwrite the output file."),
) -> None:
    """Measure stripe frames into a point cloud; frames placed by the known motion (frame i: p - i*step*direction).

    Without --step/--positions the points stay in the camera frame.  Per point: x, y, z (mm),
    frame, intensity, sigma_mm (from the plane's covariance), u, v (source pixel).
    """
    from ..camera import Camera
    from ..io import check_output
    from ..plane import LightPlane
    from ..pointcloud import cloud_format
    from ..scan import Motion, measure_scan, open_frames

    out = check_output(output, force)
    fmt = cloud_format(out, fmt)
    if ascii_ply and fmt != "ply":
        raise LightplaneError("--ascii applies to PLY output only")
    if step is not None and positions is not None:
        raise LightplaneError("give either --step (with --direction) or --positions, not both")
    dvec = parse_vector(direction, "--direction") if direction is not None else None
    if step is not None:
        if dvec is None:
            raise LightplaneError("--step needs --direction X,Y,Z")
        motion = Motion.linear(step, dvec)
    elif positions is not None:
        motion = Motion.load_positions(positions, dvec)
    else:
        if dvec is not None:
            raise LightplaneError("--direction needs --step or a single-column --positions file")
        motion = Motion.none()
    roi_box = parse_roi(roi) if roi is not None else None
    cam = Camera.load(camera)
    pl = LightPlane.load(plane)
    source = open_frames(inputs)

    with progress_bar("measuring frames", source.n_frames) as update:

        def progress(done: int, total) -> None:
            update(done, total=total)

        s = measure_scan(source, cam, pl, out, fmt=fmt, ascii=ascii_ply, motion=motion, axis=axis, roi=roi_box,
                         width_px=stripe_width, channel=channel, workers=workers, force=force, progress=progress,
                         smooth_lines=smooth, **({} if sigma_along is None else {"sigma_along_px": sigma_along}))

    console.print(f"{s.n_frames} frames ({source.description}), {s.n_points} points "
                  f"({s.n_points / max(s.n_frames_used, 1):.0f} per frame), axis {s.axis}, "
                  f"stripe width {s.width_px:.2f} px, motion {s.motion['kind']}, {s.seconds:.1f} s "
                  f"({s.n_frames / max(s.seconds, 1e-9):.0f} frames/s)")
    if s.skipped:
        from ..io import summarize_reasons

        console.print(f"{s.n_frames_used} of {s.n_frames} frames used, {s.n_skipped} skipped: "
                      + summarize_reasons([(name, reason) for _, name, reason in s.skipped]))
    if s.frames_without_points:
        console.print(f"{s.frames_without_points} frames had no stripe points")
    for w in s.warnings:
        err_console.print(f"warning: {w}")
    if s.skipped:
        err_console.print(f"warning: skipped {s.n_skipped} unreadable frame(s):")
        for idx, name, reason in s.skipped[:10]:
            err_console.print(f"  frame {idx} ({name}): {reason}")
        if s.n_skipped > 10:
            err_console.print(f"  ... and {s.n_skipped - 10} more")
    console.print(f"wrote {s.path} ({s.format}{' ascii' if ascii_ply else ''})")
