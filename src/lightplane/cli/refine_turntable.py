"""``lightplane refine-turntable``: the turntable axis and scans' start angles from two scans of one object."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from lightplane.core.errors import LightplaneError
from lightplane.cli._common import (Channel, allow_other_camera_option, app, console, handles_errors, load_sensor,
                                    output_file, progress_bar, report_folder, report_option, write_report_of)
from lightplane.cli.measure import parse_laser
from lightplane.core.io import provenance
from lightplane.measure.options import MeasureOptions
from lightplane.measure.scan import open_frames, scan_points
from lightplane.measure.sensor import Sensor
from lightplane.motion.model import Motion
from lightplane.motion.turntable_refine import TurntableScan, refine_turntable
from lightplane.report.calibrations import refine_report_inputs
from lightplane.stripe.options import StripeOptions


@app.command("refine-turntable")
@handles_errors
def refine_turntable_cmd(
    sensor: Path = typer.Option(..., "--sensor", help="Sensor file with the planes and the turntable to refine."),
    scan: List[str] = typer.Option(..., "--scan", help="NAME=FRAMES: a laser of the sensor and its scan's frames "
                                   "(folder, glob or video); two or more, of the same object."),
    turntable_step: float = typer.Option(..., "--turntable-step", help="Angle per frame, deg (positive: "
                                         "counter-clockwise seen from above), as for measure."),
    output: Path = typer.Option(..., "-o", "--output", help="Refined sensor file (JSON)."),
    channel: Optional[Channel] = typer.Option(None, "--channel", help="Colour channel of the laser."),
    rotate: Optional[int] = typer.Option(None, "--rotate", help="Rotate image files clockwise by 0/90/180/270 deg "
                                         "(default: the sensor file's)."),
    workers: Optional[int] = typer.Option(None, "--workers", min=1, help="Worker threads (default: all CPUs)."),
    allow_other_camera: bool = allow_other_camera_option,
    report: Optional[Path] = report_option,
    force: bool = typer.Option(False, "--force", help="Overwrite the output file."),
) -> None:
    """Refine the turntable's axis and each scan's start angle so that the scans' clouds agree (planes fixed).

    Example: lightplane refine-turntable --sensor s.json --scan laser0=scans/1_1 --scan laser1=scans/1_2
    --turntable-step=-3.6 -o s2.json

    The first scan starts at 0 deg; the others' start angles are searched over a full turn,
    then refined with the axis (robust point-to-plane distances between the clouds).
    """
    import numpy as np


    output_file(output, force, inputs=[sensor])
    report_folder(report, force)
    sens, cams = load_sensor(sensor, allow_other_camera)
    if sens.turntable is None:
        raise LightplaneError(f"{sensor}: has no turntable to refine (add one with lightplane sensor --turntable)")
    items = [parse_laser(t) for t in scan]
    for name, glob in items:
        sens.plane(name, str(sensor))
        if glob is None:
            raise LightplaneError(f"--scan must be NAME=FRAMES, got {name!r}")
    if len(items) < 2:
        raise LightplaneError("give two scans or more of the same object: --scan NAME=FRAMES --scan NAME=FRAMES")
    rot = sens.rotate_deg if rotate is None else rotate
    scans = []
    for name, glob in items:
        assert glob is not None  # checked above
        src = open_frames([glob], rot)
        with progress_bar(f"measuring {name}", src.n_frames) as update:
            recs, summ = scan_points(src, sens.camera, sens.planes[name], MeasureOptions(StripeOptions(channel=channel)),
                                     motion=Motion.none(), workers=workers,
                                     progress=lambda done, tot: update(done, total=tot))
        pts = np.column_stack([recs["x"], recs["y"], recs["z"]]).astype(np.float64)
        console.print(f"scan {name}: {summ.n_frames} frames, {len(pts)} points"
                      + (f", {summ.n_skipped} frames skipped" if summ.skipped else ""))
        scans.append(TurntableScan(name, pts, recs["frame"].astype(np.float64), turntable_step))
    with progress_bar("searching the start angles", len(scans) - 1) as update:
        r = refine_turntable(sens.turntable, scans, progress=lambda label, i, n: update(i, total=n, label=label))

    def agree(a: dict) -> str:
        return f"median {a['median_mm']:.3f} mm, 90th percentile {a['p90_mm']:.3f} mm"

    console.print(f"agreement (symmetric point-to-surface distance), given axis, start angles 0: {agree(r.before)}")
    console.print(f"  given axis, start angles searched: {agree(r.searched)}")
    console.print(f"  refined axis and start angles: {agree(r.after)}")
    console.print("start angles: " + ", ".join(f"{s.name} {a:.3f} deg" for s, a in zip(scans, r.start_deg)))
    tt = r.turntable
    console.print(f"axis moved {r.axis_moved_deg:.4f} deg, {r.axis_moved_mm:.3f} mm across it; point "
                  f"[{', '.join(f'{v:.3f}' for v in tt.point_mm)}] mm, direction "
                  f"[{', '.join(f'{v:.5f}' for v in tt.direction)}]")
    tt.meta["refined_from_scans"] = {
        "scans": [{"laser": s.name, "frames": g, "start_deg": a} for s, (_, g), a in zip(scans, items, r.start_deg)],
        "step_deg": turntable_step, "agreement_before_mm": r.before, "agreement_searched_mm": r.searched,
        "agreement_after_mm": r.after, "axis_moved_deg": r.axis_moved_deg, "axis_moved_mm": r.axis_moved_mm,
        "note": "planes held fixed; measure each scan with --turntable-start at its start_deg",
        "previous_turntable": sens.turntable.to_dict(),
        "report_inputs": refine_report_inputs(scans, sens.turntable, r)}  # lightplane report sensor.json
    for pl in sens.planes.values():
        pl.meta.update(cams.allowed())
    out = Sensor(sens.camera, sens.planes, tt, sens.flange, sens.rotate_deg, sens.records)
    out.save(output, force=force, provenance=provenance([sensor, *(g for _, g in items)],
                                                        {"turntable_step_deg": turntable_step, "channel": channel,
                                                         "rotate_deg": rot, **cams.record()}))
    cams.warn()
    console.print(f"wrote {output}")
    write_report_of(output, report, force)
