"""``lightplane calibrate-plane``: the light plane from images of a circular target (paper §2.2)."""

from __future__ import annotations

from pathlib import Path
from typing import List, Literal, Optional

import numpy as np
import typer
from rich.table import Table

from lightplane.core.errors import LightplaneError
from lightplane.core.io import check_output, expand_inputs, provenance
from lightplane.cli._common import (Channel, app, board_option, console, handles_errors, laser_option, output_file,
                                    progress_bar, square_option)
from lightplane.camera.model import Camera
from lightplane.cli._common import target_from_options
from lightplane.plane.calibrate import ObserveOptions, PlaneCalibrationOptions, uncertainty_summary
from lightplane.plan.shares import LITTLE, information_shares
from lightplane.plane.joint import JointCameraImages, calibrate_light_planes
from lightplane.plane.ml import dispersion_factor
from lightplane.plane.sheet import circle_stripe_points, sheet_record
from lightplane.plane.uncertainty import (camera_param_names, camera_params, camera_uncertainty_summary,
    joint_dispersion_phrase)
from lightplane.report.html import write_report
from lightplane.stripe.lasers import output_paths, parse_lasers


@app.command("calibrate-plane")
@handles_errors
def calibrate_plane_cmd(
    images: List[str] = typer.Argument(..., help="Images of the circular target with the stripe across it "
                                                 "(files, folders or glob patterns)."),
    camera: Optional[Path] = typer.Option(None, "--camera", help="Camera file: lightplane JSON, ROS YAML or OpenCV "
                                                                 "YAML/XML (or --joint-camera)."),
    diameter: float = typer.Option(..., "--diameter", help="Target diameter in mm."),
    output: Path = typer.Option(..., "-o", "--output", help="Light-plane file to write (JSON)."),
    method: Literal["ml", "global", "paper"] = typer.Option("ml", "--method", help="ml (default: joint maximum likelihood, with covariance), "
                                                     "global (order-independent) or paper (progressive, §2.2.3)."),
    report: Optional[Path] = typer.Option(None, "--report", help="Folder for the HTML report (index.html)."),
    channel: Optional[Channel] = typer.Option(None, "--channel", help="Laser colour channel: red, green, blue or gray."),
    near: float = typer.Option(200.0, "--near", help="Nearest target distance expected, mm (plausible ellipse size)."),
    far: float = typer.Option(1500.0, "--far", help="Farthest target distance expected, mm."),
    workers: Optional[int] = typer.Option(None, "--workers", min=1, help="Parallel worker threads (default: all cores)."),
    laser: Optional[List[str]] = laser_option,
    force: bool = typer.Option(False, "--force", help="Overwrite an existing plane file / report."),
    joint_camera: Optional[str] = typer.Option(
        None, "--joint-camera", help="Chessboard images (folder or glob) to calibrate the camera from, jointly with "
                                     "the plane: intrinsics, board poses, target poses and plane in one maximum-"
                                     "likelihood problem (needs --board, --square, --camera-out; instead of --camera)."),
    board: Optional[str] = board_option,
    square: Optional[float] = square_option,
    camera_out: Optional[Path] = typer.Option(None, "--camera-out", help="With --joint-camera: the camera file to "
                                              "write (JSON, with the joint covariance of the intrinsics)."),
    keep_suspect: bool = typer.Option(False, "--keep-suspect", help="Write the plane even when images' stripe "
                                      "points lie far beyond their stripe noise from it (marked in its 'quality')."),
) -> None:
    """Calibrate the light plane from images of a flat circular target (Wang & Li 2022).

    Several lasers: one --laser NAME=SELECTOR per laser, e.g. --laser left=red --laser right=green
    when both stripes cross the disc in the same images (colour images), or --laser a=frames:'*_a.png'
    --laser b=frames:'*_b.png' for separate frames; one plane file per laser.

    --joint-camera 'boards/*.png' --board 9x7 --square 8 --camera-out cam.json: the camera is
    calibrated from the chessboards (as calibrate-camera), the plane from the circle images with
    it, then both are refined jointly (the circle images inform the intrinsics too); the camera
    file gets the refined intrinsics and their covariance, the plane file the refined plane.
    """

    if not (diameter > 0):
        raise LightplaneError(f"--diameter must be positive, got {diameter} mm")
    if not (0 < near < far):
        raise LightplaneError(f"need 0 < --near < --far, got {near} and {far} mm")
    files = expand_inputs(images)
    if not files:
        raise LightplaneError(f"no images found in {' '.join(images)}")
    for f in files:  # a mistyped name stops here; a folder, an unreadable or truncated file is skipped with its reason
        if not f.exists():
            raise LightplaneError(f"{f}: no such file")
    joint = _joint_inputs(joint_camera, board, square, camera, camera_out, output, method, laser, force)
    if joint is None and camera is None:
        raise LightplaneError("give --camera FILE (or --joint-camera GLOB with --board, --square and --camera-out)")
    sels = parse_lasers(laser, channel)
    outputs, reports = _checked_outputs(output, report, sels, force, [*files, camera])
    cam = None if camera is None else Camera.load(camera)  # None: --joint-camera calibrates it
    opts = PlaneCalibrationOptions(observe=ObserveOptions(distance_range_mm=(near, far), channel=channel),
                                   workers=workers, keep_suspect=keep_suspect)
    first = ("chessboard images", len(joint[0])) if joint is not None else ("images", len(files))
    with progress_bar(*first) as update:
        run = calibrate_light_planes([str(f) for f in files], cam, diameter, method, opts, lasers=sels,
                                     joint_camera=None if joint is None else
                                     JointCameraImages([str(f) for f in joint[0]], joint[1]),
                                     progress=lambda stage, i, n: update(i, total=n, label=stage))
    results = _print_run(run, joint, sels)
    options: dict = {"camera": None if camera is None else str(camera), "diameter_mm": diameter, "method": method,
               "channel": channel, "distance_range_mm": [near, far], "keep_suspect": keep_suspect}
    if sels is not None:
        options["lasers"] = [x.to_dict() for x in sels]
    inputs = [*map(str, files)] + ([str(camera)] if camera is not None else [])
    if joint is not None:
        options.update({"joint_camera": joint_camera, "board": joint[1].spec, "square_mm": joint[1].square_mm,
                        "camera_out": str(camera_out)})
        inputs += [str(f) for f in joint[0]]
    prov = provenance(inputs, options)
    if run.joint is not None and run.intrinsics is not None:
        assert camera_out is not None  # checked by _joint_inputs
        _save_joint_camera(run.joint, run.intrinsics, camera_out, force, prov)
    for name, cal in run.planes.items():
        sheet, line = sheet_record(cal.plane, circle_stripe_points(cal))
        console.print(f"  {line}")
        # report_inputs: what `lightplane report` needs to rebuild the report from this file alone
        extra = {**({"laser": name} if name is not None else {}), **cal.to_dict(), "uncertainty": results[name],
                 "provenance": prov, "report_inputs": cal.report_inputs(), **sheet}
        cal.plane.save(outputs[name], force=force, extra=extra)
        console.print(f"wrote {outputs[name]}")
    if report is not None:
        for name, cal in run.planes.items():
            rep = reports[name]
            if name is not None and len(reports) > 1:
                rep.parent.mkdir(exist_ok=True)
            path = write_report(rep, cal, force=force, provenance=prov)
            console.print(f"wrote {path}")


def _checked_outputs(output: Path, report: Path | None, sels, force: bool, inputs: list) -> tuple[dict, dict]:
    """The plane file and report folder of each laser, every one checked before any work (not an input, not a
    folder...): nothing is written on bad input."""
    names: list[str | None] = [x.name for x in sels] if sels else [None]
    outputs: dict[str | None, Path] = {None: output}
    if sels:
        outputs = {n: f for n, f in output_paths(output, [x.name for x in sels]).items()}
    reports = {n: (report if n is None or len(names) == 1 else report / n) for n in names} if report is not None else {}
    if len(set(map(str, outputs.values()))) < len(outputs):
        raise LightplaneError(f"-o {output}: the lasers' plane files would have the same name")
    for out in outputs.values():
        output_file(out, force, inputs=inputs)
    if report is not None:
        if report.exists() and not report.is_dir():
            raise LightplaneError(f"{report}: exists and is not a folder")
        if not report.exists() and not report.parent.is_dir():
            raise LightplaneError(f"{report}: its parent folder {report.parent} does not exist")
        for rep in reports.values():
            if rep.exists() and not rep.is_dir():
                raise LightplaneError(f"{rep}: exists and is not a folder")
            if rep.exists():
                check_output(rep / "index.html", force)
    return outputs, reports


def _print_run(run, joint, sels) -> dict:
    """The camera (joint), the two-step and joint results and every laser's plane on the console; returns
    each plane's uncertainty summary."""
    if run.intrinsics is not None and joint is not None:
        intr, (board_files, target) = run.intrinsics, joint
        cam = intr.camera
        console.print(f"camera from {len(intr.used)} of {len(board_files)} chessboard views ({target.spec}): "
                      f"fx {cam.fx:.2f} px, fy {cam.fy:.2f} px, cx {cam.cx:.2f} px, cy {cam.cy:.2f} px, "
                      f"RMS reprojection {intr.rms_px:.3f} px")
        for name, why in intr.skipped.items():
            console.print(f"  skipped {name}: {why}")
        console.print("[bold]two-step[/bold] (camera from the chessboards alone, then the plane with it):")
        _print_calibration(run.two_step, cam)
        _print_joint(intr.camera, run.joint)
        console.print("[bold]joint refinement[/bold]:")
    results: dict[str | None, dict] = {}
    for name, cal in run.planes.items():
        if name is not None:
            sel = next(x for x in sels if x.name == name)
            console.print(f"[bold]laser {name}[/bold] ({sel.text}): {cal.n_used} of {len(cal.images)} images used")
        results[name] = _print_calibration(cal, run.camera)
    if sels is not None and len(sels) > 1:
        for line in shared_pose_lines(run.planes):
            console.print(line)
    return results


def _save_joint_camera(jc, intr, camera_out: Path, force: bool, prov: dict) -> None:
    """The joint camera file: the refined intrinsics with their covariance and the joint refinement's record."""
    r = jc.result
    jc.camera.save_json(camera_out, force=force, extra={
        "calibration": {**intr.to_dict(), "joint_refinement": {
            "covariance_covers": "the corner noise (from the camera calibration's residuals) and the rim and "
                                 "stripe noise of the circle images (the plane calibration's noise model), board "
                                 "and target poses and the plane marginalised"
                                 + (", " + joint_dispersion_phrase(r.dispersion) if r.dispersion_applied else ""),
            "joint_dispersion": r.dispersion, "joint_dispersion_applied": r.dispersion_applied,
            "target_images_used": [o.source for o in jc.plane_cal.images if o.used],
            "corner_rms_px": r.corner_rms_px, "rim_rms_px": r.rim_rms_px, "stripe_rms_px": r.stripe_rms_px,
            "cost_start": r.cost_start, "cost": r.cost, "evaluations": r.nfev, "converged": r.converged}},
        "provenance": prov})
    console.print(f"wrote {camera_out}")


def shared_pose_lines(cals: dict) -> list[str]:
    """How far apart the lasers' solves put the same target placement (images used by two lasers)."""
    import numpy as np

    names = list(cals)
    out = []
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            pa = {o.source: o.placement.pose for o in cals[a].images if o.used and o.placement is not None}
            pb = {o.source: o.placement.pose for o in cals[b].images if o.used and o.placement is not None}
            both = [k for k in pa if k in pb and pa[k] is not None and pb[k] is not None]
            if not both:
                continue
            dc = [float(np.linalg.norm(pa[k].center - pb[k].center)) for k in both]
            dn = [float(np.degrees(np.arccos(np.clip(pa[k].normal @ pb[k].normal, -1, 1)))) for k in both]
            out.append(f"target poses of the {len(both)} placements lasers {a} and {b} share: centres "
                       f"{np.median(dc):.4f} mm apart (median; max {max(dc):.4f} mm), normals {np.median(dn):.4f} "
                       f"deg (max {max(dn):.4f} deg)")
    return out


def _shares(cal, cam, unc: dict) -> dict[int, float]:
    """Each used image's information share (:func:`lightplane.plan.shares.information_shares`), also put in
    ``unc`` (the plane file's uncertainty record) by image name; empty where it does not apply."""
    try:
        shares = information_shares(cal, cam)
    except (LightplaneError, np.linalg.LinAlgError):  # another method, one placement, a singular set
        return {}
    if unc:
        unc["information_share"] = {o.name: shares[o.index] for o in cal.images if o.index in shares}
        unc.setdefault("covers", {})["information_share"] = (
            "each used placement's share of the plane's variance reduction over the working volume (Fisher "
            "information of its rim and stripe points, their noise and correlation from the residuals); they sum to 1")
    return shares


def _print_calibration(cal, cam) -> dict:
    """The plane, its uncertainty and the per-image table on the console; returns the uncertainty summary."""
    unc = uncertainty_summary(cal, cam)
    a, b, c = cal.plane.normal
    console.print(f"Light plane ({cal.method}, camera frame, mm): {a:+.6f} x {b:+.6f} y {c:+.6f} z "
                  f"{cal.plane.d:+.4f} = 0")
    if unc:
        console.print(f"  σ normal {unc['normal_sigma_deg'][0]:.4f} deg / {unc['normal_sigma_deg'][1]:.4f} deg "
                      f"(principal directions), σ offset {unc['d_sigma_mm']:.4f} mm (plane calibration's image noise)")
        if "normal_sigma_with_camera_deg" in unc:
            console.print(f"  with the camera's share: σ normal {unc['normal_sigma_with_camera_deg'][0]:.4f} deg / "
                          f"{unc['normal_sigma_with_camera_deg'][1]:.4f} deg, σ offset "
                          f"{unc['d_sigma_with_camera_mm']:.4f} mm")
        if "point_sigma_axis_mm" in unc:
            console.print(f"  σ of a measured point at the working distance {unc['working_distance_mm']:.0f} mm: "
                          f"{unc['point_sigma_axis_mm']:.4f} mm (camera frame; plane calibration only: "
                          f"{unc['point_sigma_axis_plane_only_mm']:.4f} mm)")
        if "point_sigma_rms_mm" in unc:
            lo, hi = unc["distance_range_mm"]
            console.print(f"  RMS point σ over the targets' range {lo:.0f}–{hi:.0f} mm: camera frame "
                          f"{unc['point_sigma_rms_mm']:.4f} mm, shape {unc['shape_sigma_rms_mm']:.4f} mm "
                          f"(plane calibration only: {unc['plane_only_sigma_rms_mm']:.4f} mm)")
            console.print(f"  ({unc['covers']['which']})")
        if unc["camera_share"] != "included":
            console.print(f"  note: {unc['camera_share']}")
    else:
        console.print("  (no covariance with this method; use --method ml for the uncertainty)")
    nm = cal.plane.meta.get("noise_model") or {}
    if nm.get("sigma_rim_px") is not None and nm.get("sigma_stripe_px") is not None:
        console.print(f"  image noise σ: rim {nm['sigma_rim_px']:.3f} px, stripe {nm['sigma_stripe_px']:.3f} px "
                      f"(correlation along the curves ×{nm.get('tau_rim', 1):.1f} / ×{nm.get('tau_stripe', 1):.1f}, "
                      f"counted in σ above)")
        if nm.get("image_dispersion") is not None:
            f = dispersion_factor(nm)
            applied = (f"×{f:.2f} in the covariance" + (", never below 1" if f != nm["image_dispersion"] else "")
                       if nm.get("image_dispersion_applied") else "not in the covariance")
            console.print(f"  images' dispersion ×{nm['image_dispersion']:.2f} in variance (errors shared within an "
                          f"image, from the residuals; {applied})")
    console.print(f"  image noise σ {cal.sigma_px:.3f} px (pooled); {cal.n_used} of {len(cal.images)} images used; "
                  f"{cal.seconds:.2f} s")
    shares = _shares(cal, cam, unc)
    t = Table(show_edge=False, title="Per image: RMS residuals of rim and stripe points (px), stripe centres, "
                                     "chord's RMS distance to the plane (µm), share of the information over the "
                                     "working volume (%)", title_justify="left")
    t.add_column("image", no_wrap=True)
    t.add_column("status", no_wrap=True)
    t.add_column("reason", overflow="fold")
    for col in ("rim px", "stripe px", "points", "chord µm", "info %"):
        t.add_column(col, justify="right", no_wrap=True)
    for o in cal.images:
        p = o.placement
        t.add_row(o.name, o.status, o.reason or "",
                  "–" if p is None else f"{p.rim_rms_px:.3f}", "–" if p is None else f"{p.stripe_rms_px:.3f}",
                  str(len(o.stripe_raw_uv)),
                  "–" if p is None or not p.used else f"{p.chord_rms_mm * 1e3:.1f}",
                  f"{100 * shares[o.index]:.1f}" if o.index in shares else "–")
    console.print(t)
    if shares:
        even = 1.0 / len(shares)
        little = [f"{o.name} {100 * shares[o.index]:.1f} %" for o in cal.images
                  if o.index in shares and shares[o.index] < LITTLE * even]
        console.print(f"  placements that added little (under {100 * LITTLE * even:.1f} % of the information over "
                      f"the working volume, half an even share): {', '.join(little) if little else 'none'}")
    for w in cal.warnings:
        console.print(f"  warning: {w}")
    return unc


def _joint_inputs(joint_camera, board, square, camera, camera_out, output, method, laser, force):
    """``(board files, target)`` for --joint-camera, checked before any work; None without it."""
    if joint_camera is None:
        given = [n for n, v in (("--board", board), ("--square", square), ("--camera-out", camera_out)) if v is not None]
        if given:
            raise LightplaneError(f"{', '.join(given)}: only with --joint-camera")
        return None
    if camera is not None:
        raise LightplaneError("give either --camera or --joint-camera, not both")
    if camera_out is None:
        raise LightplaneError("--joint-camera needs --camera-out FILE (the refined camera)")
    if method != "ml":
        raise LightplaneError(f"--joint-camera needs --method ml (got {method})")
    if laser:
        raise LightplaneError("--joint-camera works with one laser (no --laser)")
    if board is None or square is None:
        raise LightplaneError("--joint-camera needs --board COLSxROWS and --square MM")
    target = target_from_options(board, square)
    if target.kind != "chessboard":
        raise LightplaneError(f"--joint-camera: a chessboard is needed, got {target.kind}")
    files = expand_inputs([joint_camera])
    if not files:
        raise LightplaneError(f"--joint-camera: no images found in {joint_camera}")
    if Path(camera_out).resolve() == Path(output).resolve():
        raise LightplaneError("--camera-out and -o name the same file")
    output_file(camera_out, force, inputs=files, option="--camera-out")
    return files, target


def _print_joint(cam0, jc) -> None:
    """What the joint refinement changed in the intrinsics and their uncertainty."""
    import numpy as np

    cam = jc.camera
    names = camera_param_names(cam)
    a, b = camera_params(cam0), camera_params(cam)
    sa = np.sqrt(np.clip(np.diag(cam0.covariance), 0, None)) if cam0.covariance is not None else np.full(len(a), np.nan)
    sb = np.sqrt(np.clip(np.diag(cam.covariance), 0, None))
    console.print("[bold]joint refinement[/bold] of the intrinsics with the circle images "
                  f"({jc.result.nfev} evaluations; corner RMS {jc.result.corner_rms_px:.4f} px, rim "
                  f"{jc.result.rim_rms_px:.4f} px, stripe {jc.result.stripe_rms_px:.4f} px):")
    unit = {"fx": "px", "fy": "px", "cx": "px", "cy": "px"}
    parts = [f"{n} {x:.4g} → {y:.4g} (σ {s0:.2g} → {s1:.2g}{' ' + unit[n] if n in unit else ''})"
             for n, x, y, s0, s1 in zip(names, a, b, sa, sb) if s1 > 0]
    console.print("  " + "; ".join(parts))
    r = jc.result
    console.print(f"  joint dispersion ×{r.dispersion:.2f} in variance (each view's and image's pull on the intrinsics "
                  f"and the plane against their noise model; {'in' if r.dispersion_applied else 'not in'} both "
                  "covariances)")
    dist = jc.plane_cal.plane.point_on_axis()[2]
    if np.isfinite(dist) and dist > 0 and cam0.covariance is not None:
        u0, u1 = camera_uncertainty_summary(cam0, dist), camera_uncertainty_summary(cam, dist)
        console.print(f"  σ of a ray at {dist:.0f} mm (RMS over the image): chessboards alone "
                      f"{u0['ray_sigma_mm_rms']:.4f} mm, with the circle images {u1['ray_sigma_mm_rms']:.4f} mm")
