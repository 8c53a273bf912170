"""``lightplane calibrate-turntable``, ``lightplane sensor``, ``lightplane import-fabscan``."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import numpy as np
import typer
from rich.console import JustifyMethod
from rich.table import Table

from lightplane.core.errors import LightplaneError
from lightplane.core.io import expand_inputs, provenance
from lightplane.camera.targets import Target
from lightplane.cli._common import (app, BOARD_OPTIONS, CameraFiles, allow_other_camera_option, console, err_console,
                                    frame_rotation, handles_errors, output_file, progress_bar, report_folder,
                                    report_option, takes_target, write_report_of)
from lightplane.camera.model import Camera
from lightplane.core.io import read_json, rotation_code, try_read_image
from lightplane.measure.sensor import Sensor, check_name, import_fabscan, plane_name
from lightplane.motion.model import load_rigid
from lightplane.motion.turntable import calibrate_turntable


@app.command("calibrate-turntable")
@handles_errors
@takes_target
def calibrate_turntable_cmd(
    images: List[str] = typer.Argument(..., help="Images of a board standing on the turntable, the table turned "
                                       "between them (files, folders, globs)."),
    camera: Path = typer.Option(..., "--camera", help="Camera file (calibrated in the frame the images are read in)."),
    target: Target = BOARD_OPTIONS,  # --board/--square/... or --target (takes_target)
    output: Path = typer.Option(..., "-o", "--output", help="Turntable JSON file to write."),
    rotate: Optional[int] = typer.Option(None, "--rotate", help="Rotate every image clockwise by 0/90/180/270 "
                                         "degrees first (default: the rotation the camera or sensor file records, else 0)."),
    board_height: Optional[float] = typer.Option(None, "--board-height", help="Height of the board's lowest row "
                                                 "of points above the table's top, mm: puts the turntable frame's "
                                                 "origin on the table (default: at the board's level)."),
    force: bool = typer.Option(False, "--force", help="Overwrite an existing output file."),
    keep_suspect: bool = typer.Option(False, "--keep-suspect", help="Write the axis even when its two estimates "
                                      "are more than 10 σ apart (marked in the file's quality)."),
    report: Optional[Path] = report_option,
) -> None:
    """The turntable's axis (camera frame) from a board on the table at several angles.

    Example: lightplane calibrate-turntable views/ --camera cam.json --board 9x6 --square 8 -o turntable.json

    Poses by solvePnP; the axis from the circles the board points turn on, checked against
    the rotations between the poses; uncertainty by a leave-one-image-out jackknife.
    """

    output_file(output, force, inputs=[camera, *images])
    report_folder(report, force)
    cam = Camera.load(camera)
    rotate = frame_rotation(rotate, camera)
    files = expand_inputs(images)
    if not files:
        raise LightplaneError("no images given (no files matched)")
    imgs, skipped = [], {}
    for f in files:
        img, why = try_read_image(f, rotate_deg=rotate)
        imgs.append(img)
        if img is None:
            skipped[str(f)] = why
        else:
            cam.check_image(img, str(f))
    with progress_bar("board poses", len(files)) as update:
        cal = calibrate_turntable(imgs, cam, target, names=[str(f) for f in files], reasons=skipped,
                                  board_height_mm=board_height, progress=lambda i: update(i + 1),
                                  keep_suspect=keep_suspect)
    tt = cal.turntable
    m = tt.meta
    t = Table(title="Turntable axis (camera frame)", show_edge=False)
    columns: tuple[tuple[str, JustifyMethod], ...] = (("estimate", "left"),
                                                      ("point at the board's level x, y, z (mm)", "right"),
                                                      ("direction (up)", "right"))
    for c, j in columns:
        t.add_column(c, justify=j)
    for name, key in (("circles (result)", "circles"), ("rotations", "rotations"), ("board origins", "board_origins")):
        e = m["estimates"][key]
        t.add_row(name, ", ".join(f"{v:+.3f}" for v in e["point_mm"]), ", ".join(f"{v:+.5f}" for v in e["direction"]))
    console.print(t)
    a, j = m["agreement"], m["jackknife"]
    console.print(f"circles vs rotations: {a['angle_deg']:.4f} deg apart, axes {a['distance_mm']:.4f} mm apart "
                  f"(jackknife σ circles {j['sigma_direction_deg_circles']:.4f} deg / "
                  f"{j['sigma_point_mm_circles']:.4f} mm, rotations {j['sigma_direction_deg_rotations']:.4f} deg / "
                  f"{j['sigma_point_mm_rotations']:.4f} mm): " + ("agree" if cal.agrees else "DISAGREE"))
    console.print(f"axis σ: direction {cal.sigma_direction_deg:.4f} deg, position across the axis "
                  f"{cal.sigma_point_mm:.4f} mm ({j['covers']})")
    console.print(f"{m['n_images']} images used, table turned {m['angle_span_deg']:.1f} deg in all "
                  f"({m['sense_of_the_images']} in the order given); board points' RMS distance from their circles "
                  f"{m['circle_rms_mm']:.4f} mm")
    v = Table(title="Per image", show_edge=False)
    for c in ("image", "angle (deg)", "PnP RMS (px)", "circle RMS (mm)"):
        v.add_column(c, justify="left" if c == "image" else "right")
    for im in cal.images:
        if im["used"]:
            v.add_row(Path(im["name"]).name, f"{im['angle_deg']:.3f}", f"{im['pnp_rms_px']:.3f}",
                      f"{im['circle_rms_mm']:.4f}")
    console.print(v)
    for name, why in cal.skipped.items():
        console.print(f"skipped {Path(name).name}: {why}")
    if not cal.agrees:
        err_console.print("warning: the two axis estimates differ by more than 3 σ (board moved on the table, or a "
                          "poor camera calibration?)")
    console.print(f"turntable frame's origin {', '.join(f'{v:+.3f}' for v in tt.point_mm)} mm: {m['origin']}")
    opts = {"board": target.spec, "target": target.to_dict(), "rotate_deg": rotate, "camera": str(camera),
            "board_height_mm": board_height, "keep_suspect": keep_suspect}
    tt.save(output, force=force, extra={"provenance": provenance(files, opts)})
    console.print(f"wrote {output}")
    write_report_of(output, report, force)


def _camera_record(path: Path, allow_other: bool) -> tuple[CameraFiles, dict]:
    cams = CameraFiles.load(path, allow_other)
    rec = {"source": str(path)}
    if path.suffix.lower() == ".json":
        d = read_json(path, "camera file")
        if "provenance" in d:
            rec["provenance"] = d["provenance"]
    return cams, rec


@app.command("sensor")
@handles_errors
def sensor_cmd(
    output: Path = typer.Option(..., "-o", "--output", help="Sensor JSON file to write."),
    camera: Path = typer.Option(..., "--camera", help="Camera file."),
    plane: List[str] = typer.Option(..., "--plane", help="NAME=PLANE.json (repeat per laser); a bare PLANE.json "
                                    "takes its name from the file's 'laser' field (else laser0, laser1...)."),
    turntable: Optional[Path] = typer.Option(None, "--turntable", help="Turntable file (from calibrate-turntable)."),
    flange: Optional[Path] = typer.Option(None, "--flange", help="JSON with T_flange_cam (camera in the robot "
                                          "flange's frame)."),
    rotate: int = typer.Option(0, "--rotate", help="Frames are read rotated clockwise by 0/90/180/270 degrees "
                               "(the frame the camera was calibrated in)."),
    allow_other_camera: bool = allow_other_camera_option,
    force: bool = typer.Option(False, "--force", help="Overwrite an existing output file."),
) -> None:
    """Assemble a sensor file: camera, named planes, turntable or flange transform.

    Example: lightplane sensor -o sensor.json --camera cam.json --plane laser0=p0.json --plane laser1=p1.json --turntable turntable.json

    Every plane and the turntable must have been calibrated with the camera given (refused
    otherwise); --allow-other-camera joins them anyway and records that in the sensor file.
    """

    inputs = [camera, *[p.partition("=")[2] or p for p in plane], *(x for x in (turntable, flange) if x is not None)]
    output_file(output, force, inputs=inputs)
    rotation_code(rotate)
    if turntable is not None and flange is not None:
        raise LightplaneError("give a turntable or a flange transform, not both")
    cams, cam_rec = _camera_record(camera, allow_other_camera)
    cam = cams.camera
    planes = {}
    for i, item in enumerate(plane):
        name, sep, path = item.partition("=")
        if not sep:
            name, path = "", item
        pl = cams.plane(path)
        name = check_name(name.strip() or plane_name(pl, f"laser{i}"))
        if name in planes:
            raise LightplaneError(f"--plane: laser {name!r} given twice")
        pl.meta.setdefault("source", str(path))
        pl.meta.update(cams.allowed())
        planes[name] = pl
    tt = None
    if turntable is not None:
        tt = cams.turntable(turntable)
        tt.meta.setdefault("source", str(turntable))
        tt.meta.update(cams.allowed())
    fl = load_rigid(flange) if flange is not None else None
    recs = {"camera": cam_rec}
    if fl is not None:
        recs["flange"] = {"source": str(flange)}
    s = Sensor(cam, planes, tt, fl, rotate, recs)
    s.save(output, force=force, provenance=provenance(inputs, {"rotate_deg": rotate, **cams.record()}))
    cams.warn()
    console.print(f"sensor: camera {cam.width}x{cam.height} px, lasers {', '.join(planes)}"
                  + (", turntable" if tt is not None else "") + (", flange transform" if fl is not None else "")
                  + (f", frames rotated {rotate} deg" if rotate else ""))
    console.print(f"wrote {output}")


@app.command("import-fabscan")
@handles_errors
def import_fabscan_cmd(
    config: Path = typer.Argument(..., help="FabScanPi configuration (fabscan-config.json)."),
    output: Path = typer.Option(..., "-o", "--output", help="Sensor JSON file to write."),
    force: bool = typer.Option(False, "--force", help="Overwrite an existing output file."),
) -> None:
    """Read a FabScanPi configuration into a sensor file (planes laser0, laser1...).

    Example: lightplane import-fabscan fabscan-config.json -o sensor.json

    FabScan's frame rotation (rotate/hflip/vflip) is recorded, so measure --sensor reads
    the frames as FabScan does; its platform pose becomes the turntable axis.
    """
    output_file(output, force, inputs=[config])
    s = import_fabscan(config)
    s.save(output, force=force, provenance=provenance([config], {"importer": "fabscan"}))
    c = s.camera
    console.print(f"camera {c.width}x{c.height} px (frames rotated {s.rotate_deg} deg clockwise), fx {c.fx:.3f} px, "
                  f"fy {c.fy:.3f} px")
    for n, p in s.planes.items():
        console.print(f"plane {n}: {p!r}")
    if s.turntable is not None:
        tt = s.turntable
        counts = "counts per turn not given" if tt.counts_per_rev is None else f"{tt.counts_per_rev:g} counts per turn"
        console.print(f"turntable axis: point {np.round(tt.point_mm, 3).tolist()} mm, direction "
                      f"{np.round(tt.direction, 5).tolist()}, {counts}")
    console.print(f"wrote {output}")
