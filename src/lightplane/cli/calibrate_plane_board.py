"""``lightplane calibrate-plane-board``: Zhou's planar-target light-plane calibration (the baseline)."""

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
from lightplane.cli._common import (app, BOARD_OPTIONS, Channel, console, handles_errors, laser_option, output_file,
                                    progress_bar, report_folders, report_option, takes_target, write_report_of)
from lightplane.camera.model import Camera
from lightplane.cli._common import err_console, frame_rotation
from lightplane.core.io import try_read_image
from lightplane.plane.zhou import BoardFrames, BoardPlaneOptions, calibrate_plane_boards
from lightplane.plane.sheet import board_stripe_points, sheet_record
from lightplane.report.calibrations import board_plane_report_inputs
from lightplane.stripe.lasers import LaserSelector, output_paths, parse_lasers


def check_background(files: list[Path], bg_files: list[Path], option: str = "--background") -> None:
    """An option takes one value: ``--background a.png b.png`` would make b.png a laser image."""
    both = sorted(set(map(Path.resolve, files)) & set(map(Path.resolve, bg_files)))
    if both:
        raise LightplaneError(f"{both[0]} is both a laser image and a {option} frame (give {option} once per "
                              "file, or one folder or quoted glob)")


def pair_pattern_frames(files: list[Path], pattern_files: list[Path] | None, cycle: str | None
                        ) -> tuple[list[Path], list[Path | None] | None]:
    """Laser frames and, for each, the pattern frame of its pose.

    ``cycle`` (e.g. ``P,L,-``): the images, in order, repeat this sequence of roles per pose
    (P the lit pattern frame, L a laser frame to use, - a frame to leave out).
    ``pattern_files``: one lit frame per pose; the laser frames, in order, are shared out
    evenly, the first k to the first pattern frame and so on.  A pose whose last group of
    frames lacks its pattern frame gets None for it (that image is skipped with its reason).
    """
    if cycle is not None and pattern_files:
        raise LightplaneError("give either --pattern or --cycle, not both")
    if cycle is not None:
        roles = [r.strip().upper() for r in cycle.split(",")]
        if roles.count("P") != 1 or "L" not in roles or set(roles) - {"P", "L", "-"}:
            raise LightplaneError(f"--cycle must list one P (pattern frame), one or more L (laser frames) and any "
                                  f"- (left out), e.g. P,L,- ; got {cycle!r}")
        lasers, patterns = [], []
        for g in range(0, len(files), len(roles)):
            group = files[g:g + len(roles)]  # the last one may be incomplete
            pat = group[roles.index("P")] if roles.index("P") < len(group) else None
            for f, r in zip(group, roles):
                if r == "L":
                    lasers.append(f)
                    patterns.append(pat)
        return lasers, patterns
    if pattern_files:
        if len(files) % len(pattern_files):
            raise LightplaneError(f"--pattern: {len(files)} laser frames cannot be shared out evenly over "
                                  f"{len(pattern_files)} pattern frames (the same number of laser frames per pose)")
        k = len(files) // len(pattern_files)
        return files, [pattern_files[i // k] for i in range(len(files))]
    return files, None


def laser_slots(n_files: int, pattern_files: list[Path] | None, cycle: str | None) -> list[int] | None:
    """For each laser frame of :func:`pair_pattern_frames` (same order), which laser frame of its
    pose it is (1, 2, ...): the K-th ``L`` of ``--cycle``, or the K-th of the laser frames shared
    out to each ``--pattern`` frame; None without either (no poses with several laser frames)."""
    if cycle is not None:
        roles = [r.strip().upper() for r in cycle.split(",")]
        out = []
        for g in range(0, n_files, len(roles)):  # as pair_pattern_frames goes through the groups
            for i, r in enumerate(roles):
                if r == "L" and g + i < n_files:
                    out.append(roles[:i + 1].count("L"))
        return out
    if pattern_files:
        k = n_files // len(pattern_files)
        return [i % k + 1 for i in range(n_files)]
    return None


def select_laser_frames(sels, lasers: list[Path], slots: list[int] | None, cycle: str | None,
                        pattern_files) -> dict[str, list[int]]:
    """Per ``--laser`` selector, the indices of its laser frames (``frames:`` and ``cycle:`` parts)."""
    out = {}
    for s in sels:
        if s.cycle is not None:
            if slots is None:
                raise LightplaneError(f"--laser {s.describe()}: cycle:K needs --cycle or --pattern (the laser frames "
                                      "of each board pose)")
            if s.cycle > max(slots, default=0):
                per = "--cycle " + cycle if cycle is not None else f"--pattern ({max(slots, default=0)} per pattern frame)"
                raise LightplaneError(f"--laser {s.describe()}: {per} has only {max(slots, default=0)} laser frame(s) "
                                      "per pose")
        idx = [j for j, f in enumerate(lasers) if s.takes_file(f) and (s.cycle is None or (slots or [])[j] == s.cycle)]
        if not idx:
            raise LightplaneError(f"--laser {s.describe()}: none of the {len(lasers)} laser frames is one of its frames")
        out[s.name] = idx
    return out


def read_frames(files: list[Path], rotate: int, cache: dict) -> list:
    """Each file read once (``cache``: path -> image or reason); None stands for an unreadable one."""
    out = []
    for f in files:
        if f is None:
            out.append(None)
            continue
        if f not in cache:
            img, reason = try_read_image(f, rotate_deg=rotate)
            cache[f] = img if img is not None else reason
        out.append(cache[f] if not isinstance(cache[f], str) else None)
    return out


def read_laser_frames(lasers: list[Path], patterns: list | None, background: list[str] | None, rotate: int,
                      cycle: str | None = None):
    """Read the laser images, their pattern frames and the ``--background`` frames, each file once.

    Returns ``(images, patterns, backgrounds, background_files, skipped)``: an unreadable laser,
    pattern or background frame (or a laser frame without its pattern frame) makes that laser
    image skipped with the reason (``skipped``: name -> reason; its array is None); a single
    shared ``--background`` frame that cannot be read is an error.
    """
    bg_files = expand_inputs(background) if background else []
    if background and not bg_files:
        raise LightplaneError("no background images given (no files matched)")
    check_background(lasers, bg_files)
    if bg_files and len(bg_files) not in (1, len(lasers)):
        raise LightplaneError(f"--background: give one laser-off frame or one per image ({len(lasers)}), "
                              f"got {len(bg_files)}")
    cache: dict = {}
    imgs = read_frames(lasers, rotate, cache)
    pats = read_frames(patterns, rotate, cache) if patterns is not None else None
    bgs = read_frames(bg_files, rotate, cache) if bg_files else None
    if bgs is not None and len(bgs) == 1 and bgs[0] is None:
        raise LightplaneError(f"{bg_files[0]}: {cache[bg_files[0]]}")
    skipped = {}
    for k, f in enumerate(lasers):
        if patterns is not None and patterns[k] is None:
            skipped[str(f)] = f"no matching pattern frame (the last --cycle {cycle} is incomplete)"
        for what, g in (("", f), ("pattern frame ", patterns[k] if patterns else None),
                        ("background ", bg_files[k] if len(bg_files) > 1 else None)):
            if g is not None and isinstance(cache.get(g), str) and str(f) not in skipped:
                skipped[str(f)] = f"{what}{Path(g).name + ': ' if what else ''}{cache[g]}"
    return imgs, pats, bgs, bg_files, skipped


@app.command("calibrate-plane-board")
@handles_errors
@takes_target
def calibrate_plane_board_cmd(
    images: List[str] = typer.Argument(..., help="Laser images of the board, one pose each, or with --pattern / "
                                       "--cycle several per pose (files, folders, globs)."),
    camera: Path = typer.Option(..., "--camera", help="Camera file (JSON, ROS YAML or OpenCV YAML/XML)."),
    target: Target = BOARD_OPTIONS,  # --board/--square/... or --target (takes_target)
    output: Path = typer.Option(..., "-o", "--output", help="Light-plane JSON file to write."),
    background: Optional[List[str]] = typer.Option(None, "--background", help="Laser-off frames (file, folder or glob; "
                                                   "repeat the option): one per image, same order, or one for all."),
    pattern: Optional[List[str]] = typer.Option(None, "--pattern", help="Lit board frames (laser off), one per pose, "
                                                "in which the board is found (repeat the option per file, or give one folder or "
                                                "quoted glob); the laser images (possibly dark) are shared out over "
                                                "them in order, the same number per pose."),
    cycle: Optional[str] = typer.Option(None, "--cycle", help="The images repeat this sequence of frames per pose: "
                                        "P the lit pattern frame, L a laser frame, - a frame left out; e.g. P,L,- "
                                        "(FabScan's laser 0) or P,-,L (its laser 1)."),
    stripe_width: Optional[float] = typer.Option(None, "--stripe-width", help="Stripe width in px (default: estimated)."),
    channel: Optional[Channel] = typer.Option(None, "--channel", help="Colour channel of the laser: red, green, blue, gray."),
    rotate: Optional[int] = typer.Option(None, "--rotate", help="Rotate every image clockwise by 0/90/180/270 degrees first "
                                         "(default: the rotation the camera file records, else 0)."),
    laser: Optional[List[str]] = laser_option,
    force: bool = typer.Option(False, "--force", help="Overwrite an existing output file."),
    keep_suspect: bool = typer.Option(False, "--keep-suspect", help="Write the plane even when images' stripe "
                                      "points lie far beyond their stripe noise from it (marked in its 'quality')."),
    board_margin: Optional[float] = typer.Option(None, "--board-margin", metavar="MM",
                                                 help="The board's white margin beyond its printed pattern, mm "
                                                 "(stripe points are taken there too, only where the lit board "
                                                 "shows it; default: as far as the image shows the board; 0: the "
                                                 "pattern only)."),
    report: Optional[Path] = report_option,
) -> None:
    """Calibrate the light plane with a planar board in two or more poses (Zhou's method, the paper's baseline).

    Several lasers: one --laser NAME=SELECTOR each, e.g. FabScan's frames (lit board, laser 0, laser 1
    per turntable position): --cycle P,L,L --laser laser0=cycle:1 --laser laser1=cycle:2; one plane file
    per laser (-o plane.json: plane_laser0.json, plane_laser1.json).
    """

    sels = parse_lasers(laser, channel)
    outputs: dict[str | None, Path] = {None: output}
    if sels:
        outputs = {n: f for n, f in output_paths(output, [x.name for x in sels]).items()}
    if len(set(map(str, outputs.values()))) < len(outputs):
        raise LightplaneError(f"-o {output}: the lasers' plane files would have the same name")
    for out in outputs.values():
        output_file(out, force, inputs=[camera, *images, *(pattern or []), *(background or [])])
    reports = report_folders(report, list(outputs), force)  # several lasers: one folder each inside --report
    cam = Camera.load(camera)
    rotate = frame_rotation(rotate, camera)
    files = expand_inputs(images)
    if not files:
        raise LightplaneError("no images given (no files matched)")
    pattern_files = expand_inputs(pattern) if pattern else None
    if pattern and not pattern_files:
        raise LightplaneError("no pattern frames given (no files matched --pattern)")
    if background and (pattern or cycle):
        raise LightplaneError("--background is for laser-on images of a lit board; with --pattern / --cycle the "
                              "board is found in the pattern frames")
    if pattern_files:
        check_background(files, pattern_files, "--pattern")
    lasers, patterns = pair_pattern_frames(files, pattern_files, cycle)
    if len(lasers) < 2:
        raise LightplaneError(f"Zhou's method needs at least 2 board poses (images), got {len(lasers)}")
    chosen: dict[str | None, list[int]] = {None: list(range(len(lasers)))}
    if sels is not None:
        slots = laser_slots(len(files), pattern_files, cycle)
        chosen = {n: i for n, i in select_laser_frames(sels, lasers, slots, cycle, pattern_files).items()}
    imgs, pats, bgs, bg_files, skipped = read_laser_frames(lasers, patterns, background, rotate, cycle)
    by_name: dict[str | None, LaserSelector] = {x.name: x for x in sels or []}
    frames = BoardFrames(imgs, pattern_images=pats, background_images=bgs, names=[str(f) for f in lasers],
                         skipped=skipped)
    with progress_bar("board poses and stripes") as update:
        results = calibrate_plane_boards(frames, cam, target, {n: (i, by_name.get(n)) for n, i in chosen.items()},
                                         BoardPlaneOptions(stripe_width_px=stripe_width, channel=channel,
                                                           keep_suspect=keep_suspect, board_margin_mm=board_margin),
                                         progress=lambda label, i, n: update(i, total=n, label=label))
    opts = {"board": target.spec, "square_mm": target.square_mm, "target": target.to_dict(),
            "stripe_width_px": stripe_width, "channel": channel, "rotate_deg": rotate,
            "background": [str(f) for f in bg_files], "pattern": [str(f) for f in pattern_files or []],
            "cycle": cycle, "camera": str(camera), "keep_suspect": keep_suspect, "board_margin_mm": board_margin}
    if sels is not None:
        opts["lasers"] = [x.to_dict() for x in sels]
    for lname, res in results.items():
        if lname is not None:
            console.print(f"[bold]laser {lname}[/bold] ({by_name[lname].text}): {len(chosen[lname])} laser frames")
        _print_board_result(res, target)
    for lname, res in results.items():
        idx = chosen[lname]
        inputs = list(dict.fromkeys([*(lasers[k] for k in idx), *(patterns[k] for k in idx if patterns
                                                                    and patterns[k] is not None)]))
        sheet, line = sheet_record(res.plane, board_stripe_points(res))
        console.print(f"  {line}")
        extra: dict = {"provenance": provenance(inputs, opts), **sheet,
                       "report_inputs": board_plane_report_inputs(res, cam)}  # lightplane report plane.json
        if lname is not None:
            extra = {"laser": lname, **extra}
        res.plane.save(outputs[lname], force=force, extra=extra)
        console.print(f"wrote {outputs[lname]}")
    if report is not None:
        report.mkdir(exist_ok=True)
    for lname in results:
        write_report_of(outputs[lname], reports[lname], force)


def _print_board_result(res, target) -> None:
    """The plane, its uncertainty and the per-image table of one Zhou calibration on the console."""
    pl = res.plane
    cov = pl.covariance
    assert cov is not None  # Zhou's fit always gives the plane its covariance
    sd = np.sqrt(np.diag(cov))
    t = Table(title="Light plane, Zhou's planar-target method (camera frame)", show_edge=False)
    columns: tuple[tuple[str, JustifyMethod], ...] = (("coefficient", "left"), ("value", "right"),
                                                      ("± std", "right"), ("unit", "left"))
    for c, j in columns:
        t.add_column(c, justify=j)
    for name, v, s, u in zip("abcd", pl.coefficients, sd, ("-", "-", "-", "mm")):
        t.add_row(name, f"{v:+.6f}" if u == "-" else f"{v:+.4f}", f"{s:.2g}", u)
    console.print(t)
    sigma_deg = float(np.degrees(np.sqrt(np.trace(cov[:3, :3]))))
    console.print(f"normal direction σ ≈ {sigma_deg:.4f} deg (covariance: {pl.meta['covariance_method']})")
    console.print(f"{len(res.points_cam_mm)} stripe points from {len(set(res.view_index.tolist()))} board poses, "
                  f"residual RMS {res.residual_rms_mm:.4f} mm; board: {target.describe()}")
    v = Table(title="Per image used", show_edge=False)
    for c in ("image", "stripe points", "pose RMS (px)", "residual RMS (mm)", "board distance (mm)"):
        v.add_column(c, justify="left" if c == "image" else "right")
    for im in pl.meta["images"]:
        r = im.get("residual_rms_mm")
        v.add_row(Path(im["name"]).name, str(im["n_stripe_points"]) + ("" if im["used"] else " (unused)"),
                  f"{im['reprojection_rms_px']:.3f}", "-" if r is None else f"{r:.4f}",
                  f"{np.linalg.norm(im['t_cam_board_mm']):.1f}")
    console.print(v)
    for name, why in pl.meta["skipped"].items():  # one line each: reasons are long, tables cut them
        console.print(f"skipped {Path(name).name}: {why}")
    if pl.meta.get("stripe_channels"):
        console.print(f"note: {pl.meta['stripe_channels']}")
    print_quality(pl.meta.get("quality"), res.quality)
    g = pl.meta.get("geometry") or {}
    if g:
        console.print(f"Placements: stripes {g['length_mm']:.3g} mm long, spread {g['width_mm']:.3g} mm across; camera "
                      f"sees the plane at {g['triangulation_deg']:.1f} deg")
    for w in g.get("warnings", []):
        err_console.print(f"warning: {w}")


def print_quality(rec: dict | None, quality) -> None:
    """Warnings for images above their stripe noise, and for a suspect plane kept on request."""
    if quality is not None:
        for w in quality.warnings():
            err_console.print(f"warning: {w}")
    if rec and rec.get("kept_by_request"):
        err_console.print(f"warning: kept by --keep-suspect (marked in the file's quality): {rec.get('diagnosis')}")
