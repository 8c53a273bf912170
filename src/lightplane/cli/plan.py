"""``lightplane plan``: a placement plan for the circle target before any image is taken."""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Optional

import cv2
import numpy as np
import typer
from rich.table import Table

from lightplane.core.errors import LightplaneError
from lightplane.core.io import atomic_write, dumps_json, provenance
from lightplane.cli._common import CameraFiles, allow_other_camera_option, app, console, err_console, handles_errors, \
    output_file
from lightplane.plan.candidates import PoseLimits
from lightplane.plan.drawing import draw_plan
from lightplane.plan.planner import COVERS, CalibrationPlanner, PlannerOptions
from lightplane.plan.volume import describe_volume, parse_working_volume
from lightplane.simulate.scene import default_plane


def _distance(text: Optional[str]) -> tuple[float, float] | None:
    if text is None:
        return None
    try:
        lo, hi = (float(x) for x in text.split(","))
    except ValueError:
        raise LightplaneError(f"--distance must be NEAR,FAR in mm, got {text!r}") from None
    return lo, hi


def _table(planner: CalibrationPlanner, steps: list) -> Table:
    t = Table(title="placement plan (camera frame; σ: " + planner.figure_name() + ")")
    for col in ("#", "centre x, y, z (mm)", "distance (mm)", "tilt (deg)", "centre in image (px)", "σ after (mm)"):
        t.add_column(col, justify="right")
    for k, s in enumerate(steps):
        c = s.placement.center
        u, v = np.mean(s.outline_px, axis=0)
        t.add_row(str(k + 1), f"{c[0]:.1f}, {c[1]:.1f}, {c[2]:.1f}", f"{s.distance_mm:.0f}", f"{s.tilt_deg:.0f}",
                  f"{u:.0f}, {v:.0f}", f"{s.sigma_after_mm:.4f}")
    return t


@app.command("plan")
@handles_errors
def plan_cmd(
    camera: Path = typer.Option(..., "--camera", help="Camera file (JSON, ROS YAML or OpenCV YAML/XML)."),
    diameter: float = typer.Option(..., "--diameter", help="Target (disc) diameter, mm."),
    working_volume: str = typer.Option(..., "--working-volume", help="Where measurements will be made: "
                                       "box:X0,Y0,Z0,X1,Y1,Z1 (camera frame, mm), image:U0,V0,U1,V1[@NEAR,FAR] "
                                       "(px; mm) or distance:NEAR,FAR (mm)."),
    plane: Optional[Path] = typer.Option(None, "--plane", help="A rough light-plane file (default: the default "
                                         "sensor's plane, docs/conventions.md)."),
    target_sigma: Optional[float] = typer.Option(None, "--target-sigma", help="Stop when the point σ reaches this, mm."),
    percentile: float = typer.Option(100.0, "--percentile", help="Which point σ over the volume: 100 = the worst."),
    frame: Literal["camera", "shape"] = typer.Option("camera", "--frame", help="σ of absolute positions (camera) "
                                                     "or after the best rigid motion (shape)."),
    placements: int = typer.Option(12, "--placements", min=2, help="Placements to plan without --target-sigma "
                                   "(with it: the most allowed)."),
    max_tilt: float = typer.Option(55.0, "--max-tilt", help="Largest tilt of the disc to the line of sight, deg."),
    distance: Optional[str] = typer.Option(None, "--distance", help="NEAR,FAR distances of the disc's centre, mm "
                                           "(default: the working volume's, widened by a radius)."),
    out_png: Optional[Path] = typer.Option(None, "-o", "--out", help="Draw the plan (PNG): ghost outlines."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the plan (poses, outlines, σ) as JSON."),
    allow_other_camera: bool = allow_other_camera_option,
    force: bool = typer.Option(False, "--force", help="Overwrite existing output files."),
) -> None:
    """Plan where to put the circle target: each next placement lowers the point σ over the working volume most."""
    inputs = [camera] + ([plane] if plane is not None else [])
    for out, option, suffixes in ((out_png, "-o", (".png",)), (json_out, "--json", (".json",))):
        if out is not None:
            output_file(out, force, inputs=inputs, option=option, suffixes=suffixes)
    cams = CameraFiles.load(camera, allow_other_camera)
    rough = default_plane() if plane is None else cams.plane(plane)
    vol = parse_working_volume(working_volume, cams.camera, rough)
    limits = PoseLimits(diameter, distance_mm=_distance(distance), max_tilt_deg=max_tilt,
                        tilts_deg=tuple(t for t in (0.0, 25.0, 45.0, 55.0) if t <= max_tilt))
    opts = PlannerOptions(limits, target_sigma_mm=target_sigma, percentile=percentile, frame=frame,
                          max_placements=max(placements, 3))
    planner = CalibrationPlanner(cams.camera, rough, vol, opts)
    steps = planner.plan(None if target_sigma is not None else placements)
    if plane is None:  # after every check: bad input gets its one line alone
        err_console.print("note: no --plane: planning for the default sensor's light plane (docs/conventions.md)")
    console.print(f"working volume: {describe_volume(vol)}")
    console.print(_table(planner, steps))
    note = planner.model.camera_share_note
    console.print(f"σ covers {COVERS}" + ("" if note is None else f"; {note}"))
    verdict = planner.plan_verdict(steps).message
    console.print(verdict)
    cams.warn()
    rec = {"units": "mm, px, deg", "working_volume": describe_volume(vol), "figure": planner.figure_name(),
           "covers": COVERS, "camera_share": note or "included", "verdict": verdict,
           "placements": [s.to_dict() for s in steps],
           "provenance": provenance(inputs, {"diameter_mm": diameter, "working_volume": working_volume,
                                             "target_sigma_mm": target_sigma, "percentile": percentile,
                                             "frame": frame, "placements": placements, "max_tilt_deg": max_tilt,
                                             "distance_mm": distance, **cams.record()})}
    if json_out is not None:
        atomic_write(json_out, dumps_json(rec), force=force)
        console.print(f"wrote {json_out}")
    if out_png is not None:
        img = draw_plan(cams.camera, vol, [s.outline_px for s in steps],
                        [f"{1e3 * s.sigma_after_mm:.1f} um" for s in steps], title=verdict[:110])
        ok, buf = cv2.imencode(".png", img)
        if not ok:
            raise LightplaneError(f"{out_png}: could not encode the PNG")
        atomic_write(out_png, buf.tobytes(), force=force)
        console.print(f"wrote {out_png}")
