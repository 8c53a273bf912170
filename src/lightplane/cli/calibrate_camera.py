"""``lightplane calibrate-camera``: Zhang intrinsic calibration from images of a planar target."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import List, Optional

import numpy as np
import typer
from rich.console import JustifyMethod
from rich.table import Table

from lightplane.core.errors import LightplaneError
from lightplane.core.io import expand_inputs, provenance
from lightplane.camera.targets import Target
from lightplane.cli._common import (app, BOARD_OPTIONS, console, handles_errors, output_file, progress_bar,
                                    report_folder, report_option, takes_target, write_report_of)
from lightplane.camera.intrinsics import (CameraCalibrationOptions, IntrinsicsCalibration, calibrate_camera,
                                          opencv_std_ratio)
from lightplane.camera.lens import MODELS, coeff_names
from lightplane.plane.uncertainty import camera_uncertainty_summary
from lightplane.report.calibrations import camera_report_inputs
from lightplane.report.plots import intrinsics_residuals


#: Corner refinement recorded by calibrate_camera -> (what the summary says, the function in the provenance).
_CORNER_METHODS = {"saddle": ("blurred-saddle model fit", "fit_corners"),
                   "forstner": ("Förstner (gradient orthogonality)", "refine_corners")}


@app.command("calibrate-camera")
@handles_errors
@takes_target
def calibrate_camera_cmd(
    images: List[str] = typer.Argument(..., help="Images of the board (files, folders or glob patterns)."),
    target: Target = BOARD_OPTIONS,  # --board/--square/... or --target (takes_target)
    output: Path = typer.Option(..., "-o", "--output", help="Camera file to write (.json; .yaml for ROS, .xml for OpenCV)."),
    rotate: int = typer.Option(0, "--rotate", help="Rotate every image clockwise by 0/90/180/270 degrees first."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Write a residual plot (PNG/PDF/SVG)."),
    fix_k3: bool = typer.Option(False, "--fix-k3", help="Keep k3 = 0 (advisable for narrow lenses, where k3 is "
                                "poorly determined)."),
    zero_tangent: bool = typer.Option(False, "--zero-tangent", help="Keep p1 = p2 = 0 (only if the lens has no "
                                      "tangential distortion: otherwise the principal point is biased)."),
    model: str = typer.Option("plumb_bob", "--model", help="Lens model: plumb_bob (5 coefficients), rational (8), "
                              "thin_prism (12), tilted (the plumb bob + tauX, tauY: a Scheimpflug sensor) or "
                              "fisheye (cv2.fisheye, 4)."),
    tilt: Optional[str] = typer.Option(None, "--tilt", help="With --model tilted: hold the sensor tilt at "
                                       "TAUX,TAUY degrees (e.g. the mechanical design's). Through a narrow lens the "
                                       "views do not separate the tilt from the principal point; held, the "
                                       "principal point is determined relative to it."),
    distance: Optional[float] = typer.Option(None, "--distance", help="Working distance (mm) at which to state "
                                             "the camera's uncertainty (default: the boards' median distance)."),
    report: Optional[Path] = report_option,
    force: bool = typer.Option(False, "--force", help="Overwrite existing output files."),
    keep_suspect: bool = typer.Option(False, "--keep-suspect", help="Write the camera even when its reprojection "
                                      "RMS is far above what its corners' own noise predicts (marked in its "
                                      "'corner_noise_check')."),
    keep_outlier_views: bool = typer.Option(False, "--keep-outlier-views", help="Keep views whose reprojection RMS "
                                            "is far above the others' (by default they are dropped, each with "
                                            "its reason, and the camera solved again)."),
) -> None:
    """Calibrate the camera's intrinsics and lens distortion (Zhang; OpenCV)."""
    options = replace(_calibration_options(model, fix_k3, zero_tangent, tilt, rotate), keep_suspect=keep_suspect,
                      drop_outlier_views=not keep_outlier_views)
    if distance is not None and not distance > 0:
        raise LightplaneError(f"--distance must be positive, got {distance} mm")
    if report is not None and output.suffix.lower() not in (".json", ""):
        raise LightplaneError(f"--report reads the calibration from a JSON camera file; -o {output} is not one")
    report_folder(report, force)
    files = _checked_files(images, output, plot, force)
    with progress_bar("finding corners", len(files)) as update:
        def step(i: int, n: int) -> None:  # once every image is read, the solve runs (lens-frame refit, covariance)
            update(i, label="finding corners" if i < n else "solving (corners refitted in the lens frame, covariance)")

        result = calibrate_camera([str(f) for f in files], target, options=options, progress=step)
    detector = _print_intrinsics(result, target)
    cu = _print_uncertainty(result, distance)
    _write(result, output, plot, force, _extra(result, cu, files, target, options, detector))
    write_report_of(output, report, force)


def _calibration_options(model: str, fix_k3: bool, zero_tangent: bool, tilt: str | None,
                         rotate: int) -> CameraCalibrationOptions:
    """The command line's options as the library's, with the command line's messages for bad ones."""
    import cv2

    if model not in MODELS:
        raise LightplaneError(f"--model {model!r} is not a lens model (plumb_bob, rational, thin_prism, tilted, fisheye)")
    if model == "fisheye" and (fix_k3 or zero_tangent):
        raise LightplaneError("--fix-k3 / --zero-tangent apply to OpenCV's standard models, not to --model fisheye")
    tilt_deg = None
    if tilt is not None:
        if model != "tilted":
            raise LightplaneError(f"--tilt holds the sensor tilt of --model tilted, not of --model {model}")
        try:
            tilt_deg = tuple(float(x) for x in tilt.split(","))
        except ValueError:
            tilt_deg = ()
        if len(tilt_deg) != 2:
            raise LightplaneError(f"--tilt must be TAUX,TAUY in degrees (e.g. 0,4.5), got {tilt!r}")
    flags = (cv2.CALIB_FIX_K3 if fix_k3 else 0) | (cv2.CALIB_ZERO_TANGENT_DIST if zero_tangent else 0)
    return CameraCalibrationOptions(flags=flags, model=model, rotate_deg=rotate,
                                    tilt_deg=None if tilt_deg is None else (tilt_deg[0], tilt_deg[1]))


def _checked_files(images: List[str], output: Path, plot: Optional[Path], force: bool) -> list[Path]:
    """The image files, the outputs checked (writable, not there unless ``force``)."""
    files = expand_inputs(images)
    if not files:
        raise LightplaneError("no images given (no files matched)")
    output_file(output, force, inputs=files)
    if plot is not None:
        output_file(plot, force, inputs=files, option="--plot")
    if len(files) == 1 and not files[0].exists():  # a single missing file: say so (several: skipped one by one)
        raise LightplaneError(f"{files[0]}: no such file")
    return files


def _print_intrinsics(result: IntrinsicsCalibration, target: Target) -> str:
    """Print the intrinsics, their std, the warnings, the corners and the views; the detector's name."""
    cam = result.camera
    t = Table(title=f"Camera intrinsics (Zhang, OpenCV; lens model {cam.model})", show_edge=False)
    t.add_column("parameter")
    t.add_column("value", justify="right")
    t.add_column("± std", justify="right")
    t.add_column("unit")
    values = [cam.fx, cam.fy, cam.cx, cam.cy, *cam.dist]
    assert cam.model is not None  # a Camera names its model on construction
    for name, v in zip(("fx", "fy", "cx", "cy") + coeff_names(cam.model), values):
        unit = "px" if name in ("fx", "fy", "cx", "cy") else "-"
        sd = result.std.get(name, float("nan"))
        t.add_row(name, f"{v:.6g}" if unit == "-" else f"{v:.3f}",
                  "fixed" if sd == 0 else "not determined" if sd == float("inf") else f"{sd:.2g}", unit)
    console.print(t)
    console.print("± std: " + ("from the Jacobian of the reprojection (cv2.fisheye gives none), board poses "
                               "marginalised" if cam.model == "fisheye" else "OpenCV's (calibrateCameraExtended)"
                               if cam.model == "plumb_bob" else "from the full covariance, board poses marginalised")
                  + ", corner noise estimated from the residuals"
                  + (" times the views' dispersion" if result.options.get("covariance_noise") == "views" else "")
                  + ("; OpenCV's scaled by it" if cam.model == "plumb_bob"
                     and result.options.get("covariance_noise") == "views" else "")
                  + "; covers the corner noise only")
    ratio = opencv_std_ratio(result)
    if cam.model != "plumb_bob" and ratio is not None and ratio[1] > 2.0:
        console.print(f"note: OpenCV's own stdDeviationsIntrinsics are up to {ratio[1]:.3g}x smaller ({ratio[0]}): "
                      "its pseudo-inverse of the normal matrix drops the directions in which the parameters "
                      "trade against each other; not shown")
    for w in result.warnings:
        console.print(f"[bold yellow]warning:[/] {w}")
    console.print(f"RMS reprojection error: {result.rms_px:.4f} px over {len(result.used)} views "
                  f"({cam.width}x{cam.height} px); board: {target.describe()}")
    detector = _print_corners(result, target)
    _print_views(result)
    for line in result.diagnostics_lines():
        console.print(line)
    return detector


def _print_corners(result: IntrinsicsCalibration, target: Target) -> str:
    """Print how the corners (dots) were found; the detector's name for the provenance."""
    if target.kind == "chessboard":
        label, refiner = _CORNER_METHODS.get(str(result.options.get("refine")), ("cornerSubPix only", "none"))
        blur = result.options.get("median_blur_px", float("nan"))
        refit = int(result.options.get("lens_frame_refit_corners") or 0)
        console.print(f"Corners: {label}" + (f"; median edge blur {blur:.2f} px" if np.isfinite(blur) else "")
                      + (f"; {refit} fitted again in the lens frame of a first calibration (edges bent by the lens)"
                         if refit else ""))
        return f"findChessboardCornersSB+cornerSubPix+{refiner}"
    if target.kind == "charuco":
        console.print("Corners: cv2.aruco.CharucoDetector, then cornerSubPix inside the marker gap; "
                      "partial views used")
        return "CharucoDetector+cornerSubPix"
    o = result.options
    console.print(f"Dots: findCirclesGrid, darkness-weighted centroids moved to the projected circle centres "
                  f"(dot {o['dot_mm']:.2f} mm; RMS shift {o['circle_centre_correction_px']:.3f} px)")
    return "findCirclesGrid+weighted-centroid+perspective-correction"


def _print_views(result: IntrinsicsCalibration) -> None:
    """Print each used view's RMS error (worst first) and every image skipped with its reason."""
    v = Table(title="Per image used: RMS reprojection error, worst first", show_edge=False)
    columns: tuple[tuple[str, JustifyMethod], ...] = (("image", "left"), ("points", "right"), ("RMS px", "right"))
    for c, j in columns:
        v.add_column(c, justify=j)
    npts = dict(zip(result.used, (len(c) for c in result.corners_uv)))
    for name, e in result.ranked_views():
        v.add_row(Path(name).name, str(npts[name]), f"{e:.4f}")
    console.print(v)
    for name, why in result.skipped.items():  # one line each: reasons are long, tables cut them
        console.print(f"skipped {Path(name).name}: {why}")


def _print_uncertainty(result: IntrinsicsCalibration, distance: float | None) -> dict:
    """Print the camera's uncertainty at the working distance (default: the boards' median distance);
    its summary (:func:`camera_uncertainty_summary`)."""
    cam = result.camera
    work_mm = float(distance if distance is not None else result.options["median_board_distance_mm"])
    cu = camera_uncertainty_summary(cam, work_mm)
    if cu["included"]:
        o = result.options
        disp = (f", times the views' dispersion {o['covariance_dispersion']:.2f} (corner errors correlated within "
                f"a view)" if o.get("covariance_noise") == "views" else "")
        console.print(f"Camera uncertainty (full covariance of {', '.join(cam.covariance_params or ())}; corner noise "
                      f"{o['covariance_sigma_px']:.3f} px from the residuals{disp}, board poses marginalised): "
                      f"a ray's direction σ {cu['ray_sigma_deg_rms']:.4f} deg RMS over the image "
                      f"(max {cu['ray_sigma_deg_max']:.4f} deg), i.e. {cu['ray_sigma_mm_rms']:.4f} mm "
                      f"(max {cu['ray_sigma_mm_max']:.4f} mm) across the ray at {work_mm:.0f} mm"
                      + (" (the boards' median distance)" if distance is None else ""))
    else:
        console.print(f"Camera uncertainty: not available ({cu['note']})")
    return cu


def _extra(result: IntrinsicsCalibration, cu: dict, files: list[Path], target: Target,
           options: CameraCalibrationOptions, detector: str) -> dict:
    """The camera file's extra entries: the calibration, the camera's uncertainty and the provenance."""
    import cv2

    cam = result.camera
    return {
        "calibration": result.to_dict(),
        "camera_uncertainty": cu,
        "report_inputs": camera_report_inputs(result),  # lightplane report camera.json
        "provenance": provenance(files, {"board": target.spec, "square_mm": target.square_mm,
                                         "target": target.to_dict(), "rotate_deg": options.rotate_deg,
                                         "flags": result.flags, "fix_k3": bool(options.flags & cv2.CALIB_FIX_K3),
                                         "zero_tangent": bool(options.flags & cv2.CALIB_ZERO_TANGENT_DIST),
                                         "tilt_deg_held": None if options.tilt_deg is None else list(options.tilt_deg),
                                         "model": cam.model, "detector": detector,
                                         "solver": "fisheye.calibrate" if cam.model == "fisheye"
                                         else "calibrateCameraExtended"}),
    }


def _write(result: IntrinsicsCalibration, output: Path, plot: Optional[Path], force: bool, extra: dict) -> None:
    """Write the camera file (JSON with ``extra``; ROS / OpenCV without) and the residual plot."""
    cam = result.camera
    suffix = output.suffix.lower()
    if suffix == ".json" or suffix == "":
        cam.save_json(output, force=force, extra=extra)
    else:
        cam.save(output, force=force)
        if cam.covariance is not None:
            console.print("note: ROS / OpenCV camera files have no field for the intrinsics' covariance: "
                          "written without it (save as .json to keep it)")
    console.print(f"wrote {output}")
    if plot is not None:
        intrinsics_residuals(result, plot, force=True)
        console.print(f"wrote {plot}")
