"""Lens models end to end on renders: a Scheimpflug sensor and a rational-model wide lens.

For each rig (``lightplane.simulate.scene.lens_camera``: ``tilted`` = the default 16 mm
lens with its sensor tilted 4.52° so that the default light plane is the plane in focus;
``rational`` = a 6 mm lens, 44° x 33°, ~64 px of barrel distortion at the corners, 8
coefficients), all with the renderer's exact truth:

1. intrinsics from ``--boards`` rendered chessboards (the calibration capture, its boards
   brought closer for the wide lens so that they fill its field) with
   ``calibrate_camera(options=CameraCalibrationOptions(model=...))`` and its default corners: every parameter's error in units of
   its sigma (target: within 3 sigma) -- the sigma of the full covariance (board poses
   marginalised) and, beside it, OpenCV's ``stdDeviationsIntrinsics`` -- and the
   over-parameterisation warnings, if any.  Why OpenCV's sigma can be far too small: it is
   ``sqrt(diag(pinv(JᵀJ)) σ²)`` of the full normal matrix (intrinsics and every pose, unscaled),
   inverted by ``cv2.invert(..., DECOMP_EIG)`` (``DECOMP_SVD`` in OpenCV 5's Schur solver), a
   pseudo-inverse that drops the eigenvalues below ~2 ε Σλ; where a model's parameters trade
   against each other (the sensor tilt against p1, p2 and the principal point) the weakest
   direction falls under that cut and its variance is dropped.  The benchmark prints the
   smallest eigenvalue, the cut, and OpenCV's sigma reproduced by that pseudo-inverse beside the
   exact inverse (= the covariance's sigma).  Rig ``tilted_centred``: the Scheimpflug sensor
   behind a lens without tangential distortion, calibrated with ``CALIB_ZERO_TANGENT_DIST``
   (``calibrate-camera --model tilted --zero-tangent``): the tilt is then determined.  Rig
   ``tilted_held``: the Scheimpflug rig with its tilt held at the true value (``--tilt``, as a
   mechanical design would give it): the principal point is then determined;
2. the light plane from 12 rendered circle images (realistic, ``ml``) with the true camera:
   normal angle, offset at the axis, RMS triangulation error over 380–520 mm
   (targets 0.01°, 0.02 mm, 0.02 mm: the plumb-bob sets' bars);
3. a rendered sphere scan (radius 25.4 mm, realistic, the true camera and plane): the fitted
   radius (target within 0.02 mm) and the RMS residual;

and, as the reference measured in the same run, the same three with the plumb-bob default
camera (``--reference``).  ``--calibrated-plane``: also the plane from the same circle images with
each rig's calibrated camera, its triangulation error in the camera frame and after the best
rigid alignment (the calibrated Scheimpflug camera's frame is turned against the true one: its
rays are compared with the true ones as they are and after the best rotation,
``rays_up_to_rotation``; bench_scheimpflug_views.py says why).

    .venv/bin/python benchmarks/bench_lens_models.py [--boards 20] [--rigs tilted,rational] [--reference]
                                                     [--calibrated-plane]
"""

from __future__ import annotations

from dataclasses import replace
import argparse
import time

import numpy as np

import cv2

from lightplane import Camera
from lightplane.plane.calibrate import calibrate_plane
from lightplane.camera.intrinsics import CameraCalibrationOptions, free_parameters, calibrate_camera, rays_up_to_rotation
from lightplane.camera.targets import board_object_points
from lightplane.camera.lens import coeff_names
from lightplane.measure.scan import ArrayFrames, Motion, scan_points
from lightplane.evaluate.shapes import fit_sphere, plane_accuracy
from lightplane.simulate.scene import default_plane, lens_camera, scheimpflug_camera
from lightplane.simulate.render import (CALIBRATION_CAPTURE, BoardOptions, CircleOptions, render_chessboard_dataset,
                                        render_circle_dataset,
                                        render_scan_dataset)
from results import at_most, figure, record, within

#: chessboard distances per rig (mm): the wide lens sees the board small at the default 350–650 mm
BOARD_DISTANCE_MM = {"tilted": None, "plumb_bob": None, "rational": (180.0, 330.0), "thin_prism": None}


def rig_camera(rig: str) -> tuple[Camera, str, int]:
    """The rig's true camera, its lens model and the extra calibration flags."""
    if rig == "tilted_centred":  # the Scheimpflug sensor behind a lens without tangential distortion
        return scheimpflug_camera(dist=(-0.08, 0.12, 0.0, 0.0, 0.0)), "tilted", cv2.CALIB_ZERO_TANGENT_DIST
    if rig == "tilted_held":  # the Scheimpflug rig, its tilt held at the true value (calibrate-camera --tilt)
        return lens_camera("tilted"), "tilted", 0
    return lens_camera(rig), rig, 0


def opencv_sigma_check(cal, flags: int) -> str:
    """OpenCV's sigma reproduced: the full normal matrix JᵀJ (free intrinsics, then 6 pose parameters
    per view, OpenCV's order and units) at the solution, its pseudo-inverse by cv2.invert(DECOMP_EIG)
    against its exact inverse."""
    cam = cal.camera
    dist = cam.dist
    free = np.flatnonzero(free_parameters(dist.size, flags))
    obj = board_object_points("chessboard", *cal.board, cal.square_mm)
    p, nv = free.size, len(cal.rvecs)
    blocks, res = [], []
    for i, (uv, rv, tv) in enumerate(zip(cal.corners_uv, cal.rvecs, cal.tvecs)):
        proj, jac = cv2.projectPoints(obj, rv, tv, cam.K, dist)
        J = np.zeros((2 * len(obj), p + 6 * nv))
        J[:, :p] = jac[:, 6:10 + dist.size][:, free]
        J[:, p + 6 * i:p + 6 * i + 6] = jac[:, :6]
        blocks.append(J)
        res.append((uv - proj.reshape(-1, 2)).ravel())
    J, r = np.vstack(blocks), np.concatenate(res)
    JtJ = J.T @ J
    s2 = r @ r / (J.shape[0] - p)  # OpenCV's denominator: 2 N - free parameters (poses included)
    lam = np.linalg.eigvalsh(JtJ)
    _, pinv = cv2.invert(JtJ, flags=cv2.DECOMP_EIG)
    exact = np.linalg.inv(JtJ)
    names = np.array(("fx", "fy", "cx", "cy") + coeff_names(cam.model))[free]
    parts = [f"{n} {np.sqrt(max(pinv[j, j], 0) * s2):.3g} / {np.sqrt(max(exact[j, j], 0) * s2):.3g}"
             for j, n in enumerate(names) if n in ("fx", "cx", "cy", "p1", "taux", "tauy", "k1")]
    return (f"normal matrix JᵀJ ({JtJ.shape[0]} parameters): eigenvalues {lam.min():.3g} .. {lam.max():.3g}, "
            f"OpenCV's pseudo-inverse cut ~2 eps sum = {2 * np.finfo(float).eps * lam.sum():.3g}; sigma by "
            f"cv2.invert(DECOMP_EIG) / by the exact inverse: " + ", ".join(parts))


def intrinsics(rig: str, n: int, seed: int, refine="saddle") -> dict:
    cam, model, flags = rig_camera(rig)
    cap = CALIBRATION_CAPTURE
    dist = BOARD_DISTANCE_MM.get(model)
    ds = render_chessboard_dataset(n, seed, BoardOptions(
        difficulty="realistic", capture=cap if dist is None else replace(cap, distance_mm=dist)), camera=cam)
    t0 = time.perf_counter()
    held = (float(np.rad2deg(cam.dist[12])), float(np.rad2deg(cam.dist[13]))) if rig == "tilted_held" else None
    cal = calibrate_camera(ds.images, cap.board, cap.square_mm, options=CameraCalibrationOptions(
        model=model, flags=flags, tilt_deg=held, refine=True if refine == "saddle" else refine))
    dt = time.perf_counter() - t0
    truth = np.concatenate([[cam.fx, cam.fy, cam.cx, cam.cy], cam.dist])
    est = np.concatenate([[cal.camera.fx, cal.camera.fy, cal.camera.cx, cal.camera.cy], cal.camera.dist])
    names = ("fx", "fy", "cx", "cy") + coeff_names(model)
    rows, undetermined = [], []
    for nm, t, e in zip(names, truth, est):
        s = cal.std.get(nm, float("nan"))
        if not s > 0:  # held fixed by the model's flags (e.g. k4..s4 of the tilted calibration)
            continue
        if not np.isfinite(s):  # not determined by the views at all (IntrinsicsCovariance.undetermined)
            undetermined.append(f"    {nm:5s} truth {t: .6g}  estimate {e: .6g}  error {e - t:+.3g}  not determined "
                                f"(std inf; OpenCV's sigma {cal.std_opencv.get(nm, float('nan')):.3g})")
            continue
        rows.append((nm, t, e, s, (e - t) / s, cal.std_opencv.get(nm, float("nan"))))
    worst = max(abs(r[4]) for r in rows)
    worst_k = max(abs(r[4]) for r in rows if r[0] in ("fx", "fy", "cx", "cy"))
    with np.errstate(invalid="ignore", divide="ignore"):  # OpenCV's sigma can be 0 or NaN (see the module doc)
        worst_cv = float(np.nanmax([abs(r[2] - r[1]) / r[5] for r in rows]))
        worst_cv_k = float(np.nanmax([abs(r[2] - r[1]) / r[5] for r in rows if r[0] in ("fx", "fy", "cx", "cy")]))
    print(f"  intrinsics from {len(cal.used)}/{n} rendered chessboards ({dt:.1f} s, RMS {cal.rms_px:.4f} px), "
          f"model {model}, flags {flags}, corners {cal.options['refine']} "
          f"({cal.options['lens_frame_refit_corners']} refitted in the lens frame): "
          f"worst |error| = {worst_k:.2f} sigma of the covariance over fx, fy, cx, cy and {worst:.2f} over all "
          f"(target <= 3); {worst_cv_k:.2f} and {worst_cv:.2f} of OpenCV's sigma")
    for nm, t, e, s, z, so in rows:
        with np.errstate(invalid="ignore", divide="ignore"):
            print(f"    {nm:5s} truth {t: .6g}  estimate {e: .6g}  error {e - t:+.3g}  sigma {s:.3g}  -> {z:+.2f} sigma"
                  f"  (OpenCV's sigma {so:.3g}: {(e - t) / so:+.2f})")
    for line in undetermined:
        print(line)
    v, u = np.mgrid[0:cam.height:16, 0:cam.width:16]
    uv = np.column_stack([u.ravel(), v.ravel()]).astype(float)
    back = cam.project(cal.camera.rays(uv) * 400.0)
    dmap = np.linalg.norm(back - uv, axis=1)
    turned = rays_up_to_rotation(cam, cal.camera)
    print(f"    the calibrated camera's rays through the true camera: RMS {np.sqrt(np.mean(dmap ** 2)):.4f} px, "
          f"max {dmap.max():.4f} px over the image; after the best rotation of its frame ({turned.rotation_deg:.4f} "
          f"deg): RMS {turned.rotated_rms_px:.4f} px, max {turned.rotated_max_px:.4f} px")
    print("    " + opencv_sigma_check(cal, cal.flags))
    for w in cal.warnings:
        print(f"    warning: {w}")
    return {"worst_sigma": worst, "worst_sigma_K": worst_k, "worst_opencv_sigma": worst_cv,
            "warnings": list(cal.warnings), "camera": cal.camera}


def plane(model: str, seed: int, camera: Camera | None = None) -> dict:
    """The plane from the circle images with the true camera, or with ``camera`` (a calibrated one:
    then also the triangulation error after the best rigid alignment, which a rotation of the
    camera frame does not change)."""
    cam, pl = lens_camera(model), default_plane()
    ds = render_circle_dataset(12, seed, CircleOptions(difficulty="realistic"), camera=cam, plane=pl)
    use = cam if camera is None else camera
    t0 = time.perf_counter()
    cal = calibrate_plane(ds.images, use, 50.0, "ml")
    dt = time.perf_counter() - t0
    acc = plane_accuracy(cal.plane, use, pl, cam)
    used = len(cal.placements)
    which = "true camera" if camera is None else "the calibrated camera"
    print(f"  light plane from 12 rendered circle images (ml, {which}, {dt:.1f} s, {used} used): "
          f"angle {acc['angle_deg']:.4f} deg (<= 0.01), offset {acc['offset_mm']:+.4f} mm (<= 0.02), "
          f"triangulation RMS {acc['tri_rms_mm']:.4f} mm (<= 0.02), after the best rigid alignment "
          f"{acc['tri_rms_aligned_mm']:.4f} mm")
    return acc


def sphere(model: str, seed: int, frames: int) -> dict:
    cam, pl = lens_camera(model), default_plane()
    ds = render_scan_dataset("sphere", n_frames=frames, step_mm=41 * 1.5 / frames, seed=seed, difficulty="realistic",
                             camera=cam, plane=pl)
    mo = ds.truth["motion"]
    rec, _ = scan_points(ArrayFrames(ds.images), cam, pl, motion=Motion.linear(mo["step_mm"], mo["direction"]))
    p = np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(float)
    c_true = np.asarray(ds.truth["frames"][0]["surfaces"]["sphere"]["center_mm"], float)
    near = np.abs(np.linalg.norm(p - c_true, axis=1) - 25.4) < 1.0
    fit = fit_sphere(p[near])
    err = fit.radius_mm - 25.4
    print(f"  sphere scan ({frames} frames, {int(near.sum())} points on the sphere): radius {fit.radius_mm:.4f} mm, "
          f"error {err:+.4f} mm (<= 0.02), centre off by {np.linalg.norm(fit.center_mm - c_true):.4f} mm, "
          f"RMS residual {fit.rms_mm:.4f} mm")
    return {"radius_error_mm": err}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--boards", type=int, default=20)
    ap.add_argument("--rigs", default="tilted,rational,tilted_centred")
    ap.add_argument("--frames", type=int, default=41)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--reference", action="store_true", help="also the plumb-bob default camera")
    ap.add_argument("--refine", default="saddle", help="corner refinement: saddle (default), forstner")
    ap.add_argument("--skip", default="", help="comma list of parts to skip: intrinsics, plane, sphere")
    ap.add_argument("--calibrated-plane", action="store_true",
                    help="also the plane with each rig's calibrated camera (after the intrinsics)")
    a = ap.parse_args()
    rigs = a.rigs.split(",") + (["plumb_bob"] if a.reference else [])
    skip = set(a.skip.split(",")) - {""}
    figs = []
    for rig in rigs:
        cam = rig_camera(rig)[0]
        print(f"{rig}: {cam!r}")
        if "intrinsics" not in skip:
            res = intrinsics(rig, a.boards, a.seed + 1, a.refine)
            figs.append(figure(f"{rig}_intrinsics_worst_sigma", f"{rig} lens: intrinsics' worst error", res["worst_sigma"],
                               "sigma", statistic=f"worst parameter over its sigma, {a.boards} rendered boards",
                               target=at_most(3.0, "sigma")))
            if a.calibrated_plane and rig not in ("tilted_centred", "tilted_held"):
                plane(rig, a.seed, res["camera"])
        if rig in ("tilted_centred", "tilted_held"):  # the plane and the scan: the tilted rig's
            continue
        if "plane" not in skip:
            acc = plane(rig, a.seed)
            figs.append(figure(f"{rig}_plane_tri_rms", f"{rig} lens: plane triangulation RMS", acc["tri_rms_mm"], "mm",
                               statistic="12 circle images, true camera, RMS over 380-520 mm",
                               target=at_most(0.02, "mm")))
        if "sphere" not in skip:
            sph = sphere(rig, a.seed, a.frames)
            figs.append(figure(f"{rig}_sphere_radius", f"{rig} lens: sphere radius", 25.4 + sph["radius_error_mm"], "mm",
                               truth=25.4, statistic=f"{a.frames}-frame rendered scan",
                               target=within(0.02, "mm", of="error")))
    record("bench_lens_models", figs)


if __name__ == "__main__":
    main()
