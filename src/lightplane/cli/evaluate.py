"""``lightplane evaluate``: cross-ratio accuracy check of light planes on a board (paper §4.3, Table 2)."""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import List, Literal, Optional

import typer
from rich.table import Table

from lightplane.core.errors import LightplaneError
from lightplane.core.io import atomic_write, dumps_json, expand_inputs, provenance
from lightplane.camera.targets import Target
from lightplane.cli._common import (app, BOARD_OPTIONS, CameraFiles, Channel, allow_other_camera_option, console,
                                    frame_rotation, handles_errors, output_file, progress_bar, takes_target)
from lightplane.cli.calibrate_plane_board import read_laser_frames
from lightplane.evaluate.crossratio import EvaluateOptions, Evaluation, evaluate_images


def _labels(paths: List[Path]) -> list[str]:
    stems = [p.stem for p in paths]
    return stems if len(set(stems)) == len(stems) else [str(p) for p in paths]


@app.command("evaluate")
@handles_errors
@takes_target
def evaluate_cmd(
    images: List[str] = typer.Argument(..., help="Laser-on images of the board (files, folders, globs)."),
    camera: Path = typer.Option(..., "--camera", help="Camera file (JSON, ROS YAML or OpenCV YAML/XML)."),
    plane: List[Path] = typer.Option(..., "--plane", help="Light-plane JSON file to evaluate (repeat to compare)."),
    target: Target = BOARD_OPTIONS,  # --board/--square/... or --target (takes_target)
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write per plane its pairs (dt, dm, delta, mm) and RMS."),
    csv_out: Optional[Path] = typer.Option(None, "--csv", help="Write the table as CSV (mm)."),
    background: Optional[List[str]] = typer.Option(None, "--background", help="Laser-off frames (file, folder or glob; repeat the option): one per image or one for all."),
    lines: Literal["rows", "columns", "auto"] = typer.Option("auto", "--lines", help="Corner lines the stripe crosses: rows, columns or auto."),
    corners_used: Literal["three", "all"] = typer.Option("all", "--corners", help="'three' (the paper's A, B, C) or 'all' corners per line."),
    stripe_width: Optional[float] = typer.Option(None, "--stripe-width", help="Stripe width in px (default: estimated)."),
    channel: Optional[Channel] = typer.Option(None, "--channel", help="Colour channel of the laser: red, green, blue, gray."),
    rotate: Optional[int] = typer.Option(None, "--rotate", help="Rotate every image clockwise by 0/90/180/270 degrees first "
                                         "(default: the rotation the camera file records, else 0)."),
    allow_other_camera: bool = allow_other_camera_option,
    force: bool = typer.Option(False, "--force", help="Overwrite existing output files."),
) -> None:
    """Compare light planes by the cross-ratio on a chessboard: ideal vs measured distances (paper Table 2)."""

    for out, option in ((json_out, "--json"), (csv_out, "--csv")):
        if out is not None:
            output_file(out, force, inputs=[camera, *plane, *images, *(background or [])], option=option)
    if json_out is not None and csv_out is not None and json_out.resolve() == csv_out.resolve():
        raise LightplaneError("--json and --csv must be different files")
    cams = CameraFiles.load(camera, allow_other_camera)
    cam = cams.camera
    rotate = frame_rotation(rotate, camera)
    planes = [cams.plane(p) for p in plane]
    labels = _labels(plane)
    files = expand_inputs(images)
    if not files:
        raise LightplaneError("no images given (no files matched)")
    imgs, _, bgs, bg_files, skipped = read_laser_frames(files, None, background, rotate)
    keep = [k for k, f in enumerate(files) if str(f) not in skipped]
    options = EvaluateOptions(lines=lines, corners_used=corners_used, stripe_width_px=stripe_width, channel=channel)

    with progress_bar("board poses and stripes", len(keep)) as update:
        ev = evaluate_images([imgs[k] for k in keep], cam, planes, board=target, options=options,
                             background_images=None if bgs is None else (bgs if len(bgs) == 1 else
                                                                         [bgs[k] for k in keep]),
                             labels=labels, image_names=[str(files[k]) for k in keep], skipped=skipped,
                             progress=lambda i: update(i + 1))
    _print_evaluation(ev, labels, plane, len(files), target)
    cams.warn()
    opts = {"board": target.spec, "square_mm": target.square_mm, "target": target.to_dict(), "lines": lines, "corners": corners_used,
            "stripe_width_px": stripe_width, "channel": channel, "rotate_deg": rotate, "camera": str(camera),
            "background": [str(f) for f in bg_files], **cams.record()}
    if json_out is not None:
        d = ev.to_dict()
        d["planes"] = {str(p): d["planes"][lab] for p, lab in zip(plane, labels)}
        d["images"] = [str(f) for f in files]
        d["units"] = "mm"
        d["provenance"] = provenance([*files, *plane], opts)
        atomic_write(json_out, dumps_json(d), force=force)
        console.print(f"wrote {json_out}")
    if csv_out is not None:
        atomic_write(csv_out, _csv_table(ev, labels), force=force)
        console.print(f"wrote {csv_out}")


def _print_evaluation(ev: Evaluation, labels: list[str], plane: List[Path], n_files: int, target: Target) -> None:
    """The paper's Table 2 (dm1, dm2, ... and Δ(dt, dm1), ...; short headers keep it within 80 columns), then the
    planes, the crossings, the skipped images and each plane's RMS."""
    used_names = list(ev.view_names)
    t = Table(title="Cross-ratio evaluation, paper Table 2 layout (all distances in mm)", show_edge=False)
    for c in ("No.", "image", "pair", "dt"):
        t.add_column(c, justify="left" if c == "image" else "right")
    for k in range(len(labels)):
        t.add_column(f"dm{k + 1}", justify="right")
    for k in range(len(labels)):
        t.add_column(f"Δ{k + 1}", justify="right")
    for k, (i, j) in enumerate(ev.pairs):
        t.add_row(str(k + 1), Path(used_names[ev.view_index[i]]).stem, f"{i + 1}-{j + 1}", f"{ev.errors[0].dt_mm[k]:.3f}",
                  *[f"{e.dm_mm[k]:.3f}" for e in ev.errors], *[f"{e.delta_mm[k]:+.3f}" for e in ev.errors])
    t.add_section()
    t.add_row("RMS", "", "", "", *[""] * len(labels), *[f"{e.rms_mm:.3f}" for e in ev.errors])
    console.print(t)
    for k, (lab, p) in enumerate(zip(labels, plane)):
        console.print(f"  dm{k + 1}, Δ{k + 1} = dt - dm{k + 1}: {p}")
    console.print(f"{len(ev.ideal_board_mm)} stripe crossings in {len(set(ev.view_index.tolist()))} of {n_files} "
                  f"images, {len(ev.pairs)} pairs (each image's first crossing with the others); "
                  f"board: {target.describe()}")
    for name, why in ev.skipped.items():
        console.print(f"  skipped {Path(name).name}: {why}")
    for lab, e, pe in zip(labels, ev.errors, ev.point_error_mm):
        console.print(f"{lab}: RMS Δ {e.rms_mm:.4f} mm, max |Δ| {e.max_abs_mm:.4f} mm; 3D point error vs the "
                      f"board pose: RMS {float((pe**2).mean() ** 0.5):.4f} mm")


def _csv_table(ev: Evaluation, labels: list[str]) -> str:
    """The table as CSV (mm)."""
    used_names = list(ev.view_names)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["no", "image", "i", "j", "dt_mm", *[f"dm_mm[{lab}]" for lab in labels],
                *[f"delta_mm[{lab}]" for lab in labels]])
    for k, (i, j) in enumerate(ev.pairs):
        w.writerow([k + 1, used_names[ev.view_index[i]], i + 1, j + 1, f"{ev.errors[0].dt_mm[k]:.6f}",
                    *[f"{e.dm_mm[k]:.6f}" for e in ev.errors], *[f"{e.delta_mm[k]:.6f}" for e in ev.errors]])
    w.writerow(["rms", "", "", "", "", *[""] * len(labels), *[f"{e.rms_mm:.6f}" for e in ev.errors]])
    return buf.getvalue()
