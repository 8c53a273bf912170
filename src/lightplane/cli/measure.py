"""``lightplane measure``: stripe frames (images, folder, glob or video) → point cloud (PLY/CSV/NPY)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import List, Literal, Optional

import typer

from lightplane.core.errors import LightplaneError
from lightplane.cli._common import (Channel, CameraFiles, allow_other_camera_option, app, console, err_console,
                                    frame_rotation, handles_errors, load_sensor, output_file, progress_bar)
from lightplane.camera.model import Camera
from lightplane.core.io import summarize_reasons
from lightplane.measure.options import DEPTH_FACTOR, CloudOutput, MeasureOptions
from lightplane.measure.profile import working_depth
from lightplane.measure.scan import measure_scan, open_frames
from lightplane.measure.sensor import Sensor, measure_lasers
from lightplane.motion.model import Motion, load_rigid
from lightplane.plane.model import LightPlane
from lightplane.plane.uncertainty import camera_share_status
from lightplane.stripe.options import StripeOptions


def parse_vector(text: str, name: str) -> tuple[float, float, float]:
    """'X,Y,Z' → three floats."""
    try:
        v = tuple(float(t) for t in text.split(","))
    except ValueError:
        raise LightplaneError(f"{name} must be X,Y,Z (three numbers), got {text!r}") from None
    if len(v) != 3:
        raise LightplaneError(f"{name} must be X,Y,Z (three numbers), got {text!r}")
    return v


def parse_roi(text: str) -> tuple[int, int, int, int]:
    """'X0,Y0,X1,Y1' (pixel bounds, X1/Y1 exclusive) → (x, y, width, height)."""
    try:
        x0, y0, x1, y1 = (int(t) for t in text.split(","))
    except ValueError:
        raise LightplaneError(f"--roi must be X0,Y0,X1,Y1 (integer px), got {text!r}") from None
    if x1 <= x0 or y1 <= y0:
        raise LightplaneError(f"--roi must have X1 > X0 and Y1 > Y0, got {text!r}")
    return x0, y0, x1 - x0, y1 - y0


MOTION_HELP = """Measure stripe frames into a point cloud, every frame placed by the scan's motion.

Motion, one rigid transform per frame (without one the points stay in the camera frame):

  linear, constant step:  --step 0.5 --direction=-1,0,0
  linear, encoder log:    --positions enc.csv  (dx,dy,dz mm)
  turntable, constant:    --turntable tt.json --turntable-step 3.6
  turntable, angles:      --turntable tt.json --turntable-angles a.csv
  turntable, encoder:     ... --turntable-angles enc.csv --counts-per-rev 6400
  robot, camera poses:    --poses poses.csv  (x,y,z,qx,qy,qz,qw)
  robot, flange poses:    --poses flange.csv --flange hand_eye.json

Turntable angles (deg) are right-handed about the axis, which points up: positive turns the object counter-clockwise seen from above; the cloud is in the turntable's frame. Poses: one CSV row per frame, the camera's pose in the object frame (T_object_cam, mm, unit quaternion); with --flange the flange's pose, composed with T_flange_cam.

A sensor file (lightplane sensor, import-fabscan) gives the camera, the named planes and the turntable or flange transform; one frame sequence per laser, one merged cloud with a laser attribute:

  measure --sensor s.json --laser laser0='a/*.jpg' --laser laser1='b/*.jpg' --turntable-step -3.6 -o both.ply

  measure frames/ --sensor s.json --laser laser0 --turntable-step 3.6 -o one.ply

  measure frames/ --camera cam.json --plane plane.json --step 0.5 --direction=-1,0,0 -o part.ply

Per point: x, y, z (mm), frame, intensity, sigma_mm (camera frame: the plane's covariance and, when the camera file has one, the camera's share), u, v (source pixel); with --sensor also laser (its index; the names are in the file's comments).
"""


def parse_laser(text: str) -> tuple[str, str | None]:
    """'NAME=GLOB' or 'NAME' → (name, glob or None)."""
    name, sep, glob = text.partition("=")
    name = name.strip()
    if not name:
        raise LightplaneError(f"--laser must be NAME or NAME=FRAMES, got {text!r}")
    return name, (glob.strip() or None) if sep else None


def sigma_line(camera, plane) -> str:
    """What the per-point ``sigma_mm`` of a cloud measured with ``plane`` covers (one line)."""
    if plane.covariance is None:
        return "per-point sigma_mm: NaN (the plane file has no covariance)"
    why_not = camera_share_status(camera, plane)
    return "per-point sigma_mm: camera frame; " + (
        "plane calibration and camera intrinsics (their correlation included)" if why_not is None else
        f"the plane calibration only: {why_not}") + "; the stripe centre's own noise is not included"


@dataclass(frozen=True)
class MotionArgs:
    """The measure command's motion options, one form at most (checked on construction; see
    ``lightplane measure --help``)."""

    step: float | None = None
    direction: str | None = None
    positions: Path | None = None
    turntable: Path | None = None
    turntable_step: float | None = None
    turntable_angles: Path | None = None
    turntable_start: float | None = None
    counts_per_rev: float | None = None
    poses: Path | None = None
    flange: Path | None = None

    def __post_init__(self) -> None:
        forms = [n for n, v in (("--step", self.step), ("--positions", self.positions),
                                ("--turntable-step", self.turntable_step),
                                ("--turntable-angles", self.turntable_angles), ("--poses", self.poses)) if v is not None]
        if len(forms) > 1:
            raise LightplaneError(f"give one motion, not {' and '.join(forms)}")
        dvec = self.direction_vector
        if dvec is not None and not ({"--step", "--positions"} & set(forms)):
            raise LightplaneError("--direction needs --step or a single-column --positions file")
        if (self.turntable is not None or self.turntable_start is not None or self.counts_per_rev is not None) and not (
                {"--turntable-step", "--turntable-angles"} & set(forms)):
            raise LightplaneError("--turntable/--turntable-start/--counts-per-rev need --turntable-step DEG or "
                                  "--turntable-angles CSV")
        if self.flange is not None and self.poses is None:
            raise LightplaneError("--flange needs --poses (the flange's pose per frame)")

    @property
    def direction_vector(self) -> tuple[float, float, float] | None:
        return parse_vector(self.direction, "--direction") if self.direction is not None else None


def motion_from_options(args: MotionArgs, cams: CameraFiles, sensor: Sensor | None = None) -> Motion:
    """The :class:`lightplane.motion.model.Motion` named by the measure options; the turntable (checked
    against the camera of ``cams``) and the flange transform from ``sensor`` when the options give none."""
    dvec = args.direction_vector
    if args.step is not None:
        if dvec is None:
            raise LightplaneError("--step needs --direction X,Y,Z")
        return Motion.linear(args.step, dvec)
    if args.positions is not None:
        return Motion.load_positions(args.positions, dvec)
    if args.turntable_step is not None or args.turntable_angles is not None:
        if args.turntable is not None:
            table = cams.turntable(args.turntable)
        elif sensor is not None and sensor.turntable is not None:
            table = sensor.turntable
        else:
            raise LightplaneError("a turntable motion needs the axis: --turntable tt.json (from calibrate-turntable) "
                                  "or a sensor file with a turntable")
        start = 0.0 if args.turntable_start is None else args.turntable_start
        if args.turntable_step is not None:
            return Motion.turntable(table, args.turntable_step, start_deg=start)
        assert args.turntable_angles is not None  # one of the two, above
        return Motion.load_turntable_angles(args.turntable_angles, table, counts_per_rev=args.counts_per_rev,
                                            start_deg=start)
    if args.poses is not None:
        fl = load_rigid(args.flange) if args.flange is not None else None if sensor is None else sensor.flange
        return Motion.load_poses(args.poses, flange=fl)
    return Motion.none()


@app.command("measure", help=MOTION_HELP)
@handles_errors
def measure_cmd(
    inputs: Optional[List[str]] = typer.Argument(None, help="Stripe frames: image files, folders, globs, or one video "
                                                 "file (with --sensor: the frames of the one --laser NAME)."),
    camera: Optional[Path] = typer.Option(None, "--camera", help="Camera file (JSON, ROS YAML or OpenCV YAML/XML)."),
    plane: Optional[Path] = typer.Option(None, "--plane", help="Light-plane JSON file (from calibrate-plane)."),
    sensor: Optional[Path] = typer.Option(None, "--sensor", help="Sensor file (lightplane sensor / import-fabscan): "
                                          "camera, named planes, turntable; instead of --camera/--plane."),
    laser: Optional[List[str]] = typer.Option(None, "--laser", help="With --sensor: NAME=FRAMES (a folder, glob or "
                                              "video per laser; repeat for each laser), or NAME with the frames as "
                                              "arguments."),
    output: Path = typer.Option(..., "-o", "--output", help="Point-cloud file (.ply, .csv or .npy)."),
    step: Optional[float] = typer.Option(None, "--step", help="Linear: object motion between frames, mm (with --direction)."),
    direction: Optional[str] = typer.Option(None, "--direction", help="Linear: motion direction X,Y,Z in the camera frame (normalised; write --direction=-1,0,0 when it starts with a minus)."),
    positions: Optional[Path] = typer.Option(None, "--positions", help="Linear: CSV of the object's position per frame: dx,dy,dz mm "
                                             "(camera frame), or one column along --direction; one row per frame."),
    turntable: Optional[Path] = typer.Option(None, "--turntable", help="Turntable file (from calibrate-turntable), "
                                             "for --turntable-step/--turntable-angles."),
    turntable_step: Optional[float] = typer.Option(None, "--turntable-step", help="Turntable: angle per frame, deg "
                                                   "(positive: counter-clockwise seen from above)."),
    turntable_angles: Optional[Path] = typer.Option(None, "--turntable-angles", help="Turntable: CSV with angle_deg "
                                                    "(or counts, with --counts-per-rev) per frame."),
    turntable_start: Optional[float] = typer.Option(None, "--turntable-start", help="Turntable: angle of the first "
                                                    "frame, deg (default 0)."),
    counts_per_rev: Optional[float] = typer.Option(None, "--counts-per-rev", help="Turntable encoder counts per "
                                                   "revolution (default: the turntable file's)."),
    poses: Optional[Path] = typer.Option(None, "--poses", help="Poses: CSV x,y,z,qx,qy,qz,qw per frame, the camera's "
                                         "pose in the object frame (T_object_cam, mm, unit quaternion)."),
    flange: Optional[Path] = typer.Option(None, "--flange", help="With --poses: JSON with T_flange_cam (the camera in "
                                          "the robot flange's frame); the poses are then the flange's."),
    rotate: Optional[int] = typer.Option(None, "--rotate", help="Rotate every image file clockwise by 0/90/180/270 "
                                         "degrees first (default: the rotation the sensor or camera file records, else 0)."),
    fmt: Optional[str] = typer.Option(None, "--format", help="ply, csv or npy (default: from the output suffix; "
                                     "given, it must agree with a .ply/.csv/.npy suffix)."),
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
    keep_outliers: bool = typer.Option(False, "--keep-outliers", help="Keep points outside the calibrated working "
                                       "volume or with a sigma beyond 100x the calibration's (dropped and counted by default)."),
    crop: bool = typer.Option(False, "--crop", help="Keep only the points inside the calibrated working volume: "
                              "the depth range of the plane's calibration points exactly (by default twice as wide "
                              "each way), the others dropped and counted."),
    allow_other_camera: bool = allow_other_camera_option,
    background: Optional[str] = typer.Option(None, "--background", help="Laser-off frames (a file, folder or "
                                             "quoted glob): one for every frame, or one per frame in name order; "
                                             "each is subtracted from its frame (ambient light, a static scene), and centres next to a "
                                             "printed edge along the stripe are dropped and counted."),
    force: bool = typer.Option(False, "--force", help="Overwrite the output file."),
) -> None:
    inputs = list(inputs or [])
    if background is not None and sensor is not None:
        raise LightplaneError("--background goes with --camera/--plane; with --sensor, subtract the laser-off "
                              "frames before measuring")
    if crop and keep_outliers:
        raise LightplaneError("--crop drops the points outside the working volume, --keep-outliers keeps them: "
                              "give one")
    output_file(output, force, inputs=[camera, plane, sensor, positions, turntable, turntable_angles, poses, flange,
                                       *inputs, *(parse_laser(t)[1] for t in laser or []), background])
    CloudOutput(fmt=fmt, ascii=ascii_ply, force=force).target(output)  # the format, before any work
    sens: Sensor | None = None
    lasers: list[tuple[str, str | None]] = []
    rot = 0 if rotate is None else rotate
    if sensor is not None:
        if camera is not None or plane is not None:
            raise LightplaneError("give either --sensor or --camera/--plane, not both")
        sens, lasers, cams = _sensor_lasers(sensor, laser, inputs, allow_other_camera)
        rot = sens.rotate_deg if rotate is None else rotate
    else:
        cams, pl = _single_camera(camera, plane, laser, inputs, allow_other_camera)
        rot = frame_rotation(rotate, camera)
    cam = cams.camera
    if crop:
        _check_crop({n: sens.planes[n] for n, _ in lasers} if sens is not None else {str(plane): pl})
    motion = motion_from_options(MotionArgs(step=step, direction=direction, positions=positions, turntable=turntable,
                                            turntable_step=turntable_step, turntable_angles=turntable_angles,
                                            turntable_start=turntable_start, counts_per_rev=counts_per_rev,
                                            poses=poses, flange=flange), cams, sens)
    laser_off = () if background is None else (f"laser-off frames: {background}",)
    output_opts = CloudOutput(fmt=fmt, ascii=ascii_ply, force=force, comments=(*cams.comments(), *laser_off))
    out = Path(output)
    options = MeasureOptions(StripeOptions(width_px=stripe_width, channel=channel, sigma_along_px=sigma_along),
                             axis=axis, roi=parse_roi(roi) if roi is not None else None, smooth_lines=smooth,
                             keep_outliers=keep_outliers, depth_factor=1.0 if crop else DEPTH_FACTOR)
    if sens is not None:
        scans = [(name, open_frames([glob] if glob is not None else inputs, rot), sens.planes[name])
                 for name, glob in lasers]
        total = sum(src.n_frames or 0 for _, src, _ in scans) or None
        with progress_bar("measuring frames", total) as update:
            ls = measure_lasers(scans, cam, out, options, motion=motion, output=output_opts, workers=workers,
                                progress=lambda done, tot: update(done, total=tot))
        _print_lasers(ls, cam, sens, lasers)
        cams.warn()
        console.print(f"wrote {ls.path} ({ls.format}{' ascii' if ascii_ply else ''})")
        return

    source = open_frames(inputs, rot, background=None if background is None else [background])
    with progress_bar("measuring frames", source.n_frames) as update:
        s = measure_scan(source, cam, pl, out, options, motion=motion, output=output_opts, workers=workers,
                         progress=lambda done, tot: update(done, total=tot))
    _print_scan(s, source.description)
    console.print(sigma_line(cam, pl))
    cams.warn()
    console.print(f"wrote {s.path} ({s.format}{' ascii' if ascii_ply else ''})")


def _check_crop(planes: dict) -> None:
    """--crop needs each plane's calibrated working volume (recorded by lightplane's calibrations)."""
    for name, pl in planes.items():
        if working_depth(pl)[0] is None:
            raise LightplaneError(f"--crop: plane {name} records no working volume (not calibrated by lightplane?): "
                                  "nothing to crop to")


def _sensor_lasers(sensor: Path, laser: list[str] | None, inputs: list[str],
                   allow_other: bool) -> tuple[Sensor, list, CameraFiles]:
    """The sensor file (its planes checked against its camera), its lasers to measure, ``(name, frames
    glob or None)``: every one named in the file; each with its frames, or one laser with the frames as
    arguments."""
    if not laser:
        raise LightplaneError("--sensor needs --laser NAME (frames as arguments) or --laser NAME=FRAMES per laser")
    sens, cams = load_sensor(sensor, allow_other)
    lasers = [parse_laser(t) for t in laser]
    for name, _ in lasers:
        sens.plane(name, str(sensor))  # every laser named must be in the sensor file
    with_glob = [g for _, g in lasers if g is not None]
    if with_glob and len(with_glob) != len(lasers):
        raise LightplaneError("give every --laser as NAME=FRAMES, or a single --laser NAME with the frames as arguments")
    if not with_glob:
        if len(lasers) != 1:
            raise LightplaneError("several lasers need their frames each: --laser NAME=FRAMES")
        if not inputs:
            raise LightplaneError(f"no frames for laser {lasers[0][0]}: give them as arguments or --laser NAME=FRAMES")
        lasers = [(lasers[0][0], None)]
    elif inputs:
        raise LightplaneError("frames given both as arguments and in --laser NAME=FRAMES")
    return sens, lasers, cams


def _single_camera(camera: Path | None, plane: Path | None, laser: list[str] | None, inputs: list[str],
                   allow_other: bool) -> tuple[CameraFiles, LightPlane]:
    """The camera and the plane (checked against it) of a measurement with --camera and --plane (no
    sensor file)."""
    if laser:
        raise LightplaneError("--laser needs --sensor")
    if camera is None or plane is None:
        raise LightplaneError("give --camera and --plane, or --sensor with --laser")
    if not inputs:
        raise LightplaneError("no input given (image files, a folder, a glob or a video file)")
    cams = CameraFiles.load(camera, allow_other)
    return cams, cams.plane(plane)


def _print_lasers(ls, cam: Camera, sens: Sensor, lasers: list) -> None:
    """What :func:`measure_lasers` did, per laser."""
    for name, nf, nu, npts, skipped, ax, w in ls.lasers:
        width = "estimated per frame" if w is None else f"{w:.2f} px"
        console.print(f"laser {name}: {nf} frames, {npts} points ({npts / max(nu, 1):.0f} per frame), axis {ax}, "
                      f"stripe width {width}" + (f", {len(skipped)} frames skipped" if skipped else ""))
        for idx, fname, reason in skipped[:10]:
            err_console.print(f"warning: laser {name}: skipped frame {idx} ({fname}): {reason}")
    for name, dr in ls.dropped:
        if dr.totals:
            err_console.print(f"warning: laser {name}: {dr.summary()} (per frame in the file's comments)")
    console.print(f"{ls.n_points} points, motion {ls.motion['kind']}, {ls.seconds:.1f} s")
    for name, _ in lasers:
        console.print(f"laser {name}: " + sigma_line(cam, sens.planes[name]))


def _print_scan(s, description: str) -> None:
    """What :func:`measure_scan` did: frames, points, skipped frames, warnings."""
    console.print(f"{s.n_frames} frames ({description}), {s.n_points} points "
                  f"({s.n_points / max(s.n_frames_used, 1):.0f} per frame), axis {s.axis}, "
                  f"stripe width {s.width_px:.2f} px, motion {s.motion['kind']}, {s.seconds:.1f} s "
                  f"({s.n_frames / max(s.seconds, 1e-9):.0f} frames/s)")
    if s.skipped:
        console.print(f"{s.n_frames_used} of {s.n_frames} frames used, {s.n_skipped} skipped: "
                      + summarize_reasons([(name, reason) for _, name, reason in s.skipped]))
    if s.frames_without_points:
        console.print(f"{s.frames_without_points} frames had no stripe points")
    if s.dropped.totals:
        err_console.print(f"warning: {s.dropped.summary()} (per frame in the file's comments)")
    for w in s.warnings:
        err_console.print(f"warning: {w}")
    if s.skipped:
        err_console.print(f"warning: skipped {s.n_skipped} unreadable frame(s):")
        for idx, name, reason in s.skipped[:10]:
            err_console.print(f"  frame {idx} ({name}): {reason}")
        if s.n_skipped > 10:
            err_console.print(f"  ... and {s.n_skipped - 10} more")
