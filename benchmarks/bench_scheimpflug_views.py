"""Which views determine a Scheimpflug sensor's tilt?  Exact corners plus Gaussian noise.

The tilted model (OpenCV's, ``calibrate-camera --model tilted``) with free principal point and
tangential distortion, for the Scheimpflug rig of ``bench_lens_models.py``
(``scheimpflug_camera()``: 16 mm lens, 1280x960 px of 3.75 µm, sensor tilted 4.52°, the default
light plane in focus).  Corners: the true camera's projection of a 15x11 board (8 mm squares) plus
Gaussian noise of ``--noise`` px (0.006 px: the saddle fit's on realistic renders), so that the
view design is the only thing that changes.  For each design:

1. at the truth, the full normal matrix JᵀJ (free intrinsics and 6 pose parameters per view, OpenCV's
   order and units): its smallest eigenvalue over OpenCV's pseudo-inverse cut 2 ε Σλ (``cv2.invert``
   with ``DECOMP_EIG`` / ``DECOMP_SVD`` drops eigenvalues at or below it: measured, a diagonal
   ``(1, x)`` keeps ``x`` from ~4.44e-16 (1 + x) up), how many eigenvalues fall under it, and the sigma
   of fx, cx, cy, tauY from the exact inverse (the covariance) and from OpenCV's pseudo-inverse;
2. ``--seeds`` calibrations on noisy corners (``cv2.calibrateCameraExtended`` + the scipy polish of
   ``calibrate_camera``): the worst |error| in units of the covariance's sigma and of the
   ``stdDeviationsIntrinsics`` OpenCV returned, and the calibrated camera's rays against the true
   camera's over the whole image, as they are and after the best rotation of its frame
   (``rays_up_to_rotation``).

Designs: the calibration capture (20 views, tilts 25–55°, 350–650 mm, centres over the central
80 %), the same with 60 views, stronger tilts (40–70°), a wide tilt range (10–65°), distances
300–900 mm, and a smaller 9x6 board moved over the whole image including its corners (40 views,
300–500 mm); then the capture through shorter lenses (12, 8, 6 mm: the same sensor, tilt for the
same plane in focus, distances scaled), and the capture with the tilt or the principal point held
(the gauge fixed), the plumb bob (tilt held at 0) and the tilt held 0.1° off the truth.

    .venv/bin/python benchmarks/bench_scheimpflug_views.py [--noise 0.006] [--seeds 3]
"""

from __future__ import annotations

from dataclasses import replace
import argparse

import numpy as np

import cv2

from lightplane import Camera
from lightplane.camera.intrinsics import free_parameters, _polish, calibration_flags, intrinsics_covariance, rays_up_to_rotation
from lightplane.camera.targets import board_object_points
from lightplane.simulate.scene import scheimpflug_camera
from lightplane.simulate.render import CALIBRATION_CAPTURE, sample_board_poses
from results import at_most, figure, record

#: the numbers behind the last normal_matrix / calibrate line (for benchmarks/results)
LAST: dict = {}

NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4",
         "taux", "tauy")
CAP = CALIBRATION_CAPTURE
DESIGNS = {
    "capture (20 views)": dict(n=20),
    "capture, 60 views": dict(n=60),
    "stronger tilts 40-70 deg": dict(n=20, tilt=(40.0, 70.0)),
    "tilts 10-65 deg": dict(n=20, tilt=(10.0, 65.0)),
    "distances 300-900 mm": dict(n=20, dist=(300.0, 900.0)),
    "9x6 board over the whole image incl. corners (40)": dict(n=40, board=(9, 6), centre=1.0, dist=(300.0, 500.0)),
}


def poses(cam: Camera, n: int, seed: int, board=CAP.board, dist=CAP.distance_mm, tilt=CAP.tilt_deg,
          centre=CAP.centre_frac):
    return sample_board_poses(n, np.random.default_rng(seed),
                              replace(CAP, board=board, distance_mm=dist, tilt_deg=tilt, centre_frac=centre), camera=cam)


def normal_matrix(cam: Camera, views, board, flags: int, noise: float) -> str:
    """Part 1: OpenCV's cut against the smallest eigenvalue, sigma exact / OpenCV's pseudo-inverse."""
    obj = board_object_points("chessboard", *board, CAP["square_mm"])
    free = np.flatnonzero(free_parameters(14, flags))
    p, nv = free.size, len(views)
    J = np.zeros((2 * len(obj) * nv, p + 6 * nv))
    for i, (R, t) in enumerate(views):
        _, jac = cv2.projectPoints(obj, cv2.Rodrigues(R)[0], t.reshape(3, 1), cam.K, cam.dist)
        rows = slice(2 * len(obj) * i, 2 * len(obj) * (i + 1))
        J[rows, :p] = jac[:, 6:][:, free]
        J[rows, p + 6 * i:p + 6 * i + 6] = jac[:, :6]
    A = J.T @ J
    lam = np.linalg.eigvalsh(A)
    cut = 2 * np.finfo(float).eps * lam.sum()
    _, pinv = cv2.invert(A, flags=cv2.DECOMP_EIG)
    dg = np.sqrt(np.diag(A))
    exact = np.linalg.inv(A / np.outer(dg, dg)) / np.outer(dg, dg)
    names = [NAMES[k] for k in free]
    parts = [f"{n} {np.sqrt(exact[j, j]) * noise:.3g} / {np.sqrt(max(pinv[j, j], 0.0)) * noise:.3g}"
             for j, n in enumerate(names) if n in ("fx", "cx", "cy", "tauy")]
    LAST["lambda_over_cut"] = float(lam.min() / cut)
    return (f"lambda_min / cut = {lam.min() / cut:.3g} ({int(np.sum(lam <= cut))} under the cut); "
            f"sigma exact / OpenCV's: " + ", ".join(parts) + " (px, rad)")


def calibrate(cam: Camera, views, board, flags: int, noise: float, seed: int, guess: Camera | None = None):
    """Part 2: one calibration on noisy corners; the worst |error| / sigma (covariance, OpenCV), the rays."""
    obj = board_object_points("chessboard", *board, CAP["square_mm"]).astype(np.float32)
    rng = np.random.default_rng(seed)
    objs = [obj] * len(views)
    ims = [(cam.project(obj.astype(float) @ R.T + t) + rng.normal(0.0, noise, (len(obj), 2)))
           .astype(np.float32).reshape(-1, 1, 2) for R, t in views]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    K0 = None if guess is None else guess.K.copy()
    d0 = None if guess is None else guess.dist.copy()
    out = cv2.calibrateCameraExtended(objs, ims, cam.size, K0, d0,
                                      flags=flags | (cv2.CALIB_USE_INTRINSIC_GUESS if guess is not None else 0),
                                      criteria=crit)
    out = _polish(objs, ims, out, flags)
    rms, K, dist, rv, tv, std_cv = out[:6]
    dist = np.ravel(dist)
    model = "tilted" if dist.size == 14 else "plumb_bob"
    est = Camera(K, dist, cam.width, cam.height, model=model)
    cmp = rays_up_to_rotation(cam, est)
    line = f"RMS {rms:.4f} px; "
    if model == "tilted":
        sd = intrinsics_covariance(objs, ims, rv, tv, K, dist, flags).std()
        truth = np.concatenate([[cam.fx, cam.fy, cam.cx, cam.cy], cam.dist])
        e = np.concatenate([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], dist])
        sc = np.ravel(std_cv)
        z = {n: (a - b) / sd[n] for n, a, b in zip(NAMES, e, truth) if sd[n] > 0}
        zc = {n: (a - b) / s for n, a, b, s in zip(NAMES, e, truth, sc) if s > 0}
        w, wc = max(z, key=lambda n: abs(z[n])), max(zc, key=lambda n: abs(zc[n]))
        LAST.update(worst_sigma=float(abs(z[w])), worst_sigma_opencv=float(abs(zc[wc])))
        line += (f"worst |error| {abs(z[w]):.2f} sigma of the covariance ({w}), {abs(zc[wc]):.3g} of OpenCV's ({wc}); "
                 f"cx {e[2] - truth[2]:+.2f} px (sigma {sd['cx']:.3g}, OpenCV's {sc[2]:.3g}); ")
    else:
        line += f"cx {K[0, 2] - cam.cx:+.1f} px, p2 {dist[3]:+.2e}; "
    return line + (f"rays vs the truth: RMS {cmp.rms_px:.3f}, max {cmp.max_px:.3f} px; after a rotation of "
                   f"{cmp.rotation_deg:.4f} deg: RMS {cmp.rotated_rms_px:.4f}, max {cmp.rotated_max_px:.4f} px")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--noise", type=float, default=0.006, help="corner noise, px (per coordinate)")
    ap.add_argument("--seeds", type=int, default=3)
    a = ap.parse_args()
    cam = scheimpflug_camera()
    _, flags = calibration_flags("tilted", 0)
    print(f"Scheimpflug rig: {cam!r}; tilted model, p1 p2 k3 free; corner noise {a.noise} px")
    print("view designs (the same lens):")
    figs = []
    for name, kw in DESIGNS.items():
        board = kw.get("board", CAP["board"])
        v = poses(cam, kw["n"], 1, board=board, dist=kw.get("dist", CAP["distance_mm"]),
                  tilt=kw.get("tilt", CAP["tilt_deg"]), centre=kw.get("centre", CAP["centre_frac"]))
        print(f"  {name}: {normal_matrix(cam, v, board, flags, a.noise)}")
        if name == "capture (20 views)":
            figs.append(figure("capture_lambda_over_cut", "Scheimpflug capture: smallest eigenvalue / OpenCV's cut",
                               LAST["lambda_over_cut"], "x", statistic="at the truth, 20 views"))
        for s in range(a.seeds):
            print(f"    seed {s}: {calibrate(cam, v, board, flags, a.noise, s)}")
            if name == "capture (20 views)" and s == 0:
                figs += [figure("capture_worst_sigma", "Scheimpflug capture: worst error, covariance sigma",
                                LAST["worst_sigma"], "sigma", statistic=f"seed 0, corner noise {a.noise} px",
                                target=at_most(3.0, "sigma")),
                         figure("capture_worst_sigma_opencv", "Scheimpflug capture: worst error, OpenCV's sigma",
                                LAST["worst_sigma_opencv"], "sigma", statistic=f"seed 0, corner noise {a.noise} px")]
    print("shorter lenses (the capture, distances scaled by f / 16 mm):")
    for f in (12.0, 8.0, 6.0):
        c = scheimpflug_camera(f_mm=f)
        k = f / 16.0
        v = poses(c, 20, 1, dist=(CAP["distance_mm"][0] * k, CAP["distance_mm"][1] * k))
        print(f"  {f:.0f} mm (tilt {np.rad2deg(c.dist[13]):.2f} deg, field half-diagonal "
              f"{np.rad2deg(np.arctan(np.hypot(640, 480) / c.fx)):.1f} deg): {normal_matrix(c, v, CAP['board'], flags, a.noise)}")
        print(f"    seed 0: {calibrate(c, v, CAP['board'], flags, a.noise, 0)}")
    print("the gauge fixed (the capture, 16 mm):")
    v = poses(cam, 20, 1)
    for name, fl in (("tilt held", flags | cv2.CALIB_FIX_TAUX_TAUY),
                     ("principal point held", flags | cv2.CALIB_FIX_PRINCIPAL_POINT)):
        print(f"  {name}: {normal_matrix(cam, v, CAP['board'], fl, a.noise)}")
    fixed = flags | cv2.CALIB_FIX_TAUX_TAUY
    print(f"  tilt held at the truth: {calibrate(cam, v, CAP['board'], fixed, a.noise, 0, guess=cam)}")
    off = cam.dist.copy()
    off[13] += np.deg2rad(0.1)
    print(f"  tilt held 0.1 deg off the truth: "
          f"{calibrate(cam, v, CAP['board'], fixed, a.noise, 0, guess=Camera(cam.K, off, 1280, 960, model='tilted'))}")
    print(f"  plumb bob (no tilt at all), noise-free corners: {calibrate(cam, v, CAP['board'], 0, 0.0, 0)}")
    print(f"  plumb bob, noisy corners: {calibrate(cam, v, CAP['board'], 0, a.noise, 0)}")
    record("bench_scheimpflug_views", figs)


if __name__ == "__main__":
    main()
