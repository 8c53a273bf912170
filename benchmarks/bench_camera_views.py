"""Benchmark: how many chessboard views make the camera's share of a point's uncertainty small?

For the default sensor (docs/conventions.md §Default sensor: 16 mm lens, 1280x960 px, light
plane at 25° crossing the axis at 450 mm) and two boards (9x7 and 15x11 inner corners,
8 mm squares), ``N`` views posed as the calibration capture (350–650 mm, tilted 25–55°,
covering the image): exact corner projections plus white noise of ``--corner-px`` (the
covariance scales linearly with it: ``calibrate-camera`` prints a calibration's own
value), calibrated by ``cv2.calibrateCamera`` (5 coefficients) with
:func:`lightplane.camera.intrinsics.intrinsics_covariance`; the plane from 12 synthetic circle
placements (0.05 px rim and stripe noise) with the camera's share propagated.  Per
design: the RMS over the image of a ray's direction sigma (deg, and mm across the ray at
300 / 450 / 600 mm), and over the working volume 380–520 mm the camera-frame and shape
point sigmas with the camera's share, against the plane-only figure.  Median over
``--seeds`` pose draws.

    .venv/bin/python benchmarks/bench_camera_views.py [--corner-px 0.01] [--seeds 3]
"""

from __future__ import annotations

from dataclasses import replace
import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

from lightplane import Camera
from lightplane.plane.calibrate import propagate_camera
from lightplane.camera.intrinsics import intrinsics_covariance
from lightplane.plane.model import CameraDependence, LightPlane
from lightplane.plane.solvers import calibrate_plane_from_points
from lightplane.simulate.scene import default_camera, default_plane, sample_placements, synthetic_observations
from lightplane.simulate.render import CALIBRATION_CAPTURE as CC
from lightplane.simulate.render import board_corners, sample_board_poses
from lightplane.plane.uncertainty import image_grid, ray_sigma_rad, volume_sigma, working_volume_grid
from results import figure, record


def one(board, n_views, corner_px, seed):
    rng = np.random.default_rng(seed)
    true = default_camera()
    poses = sample_board_poses(n_views, rng, replace(CC, board=board, square_mm=8.0), camera=true)
    obj = board_corners(board, 8.0).astype(np.float32)
    ip = [(true.project(obj.astype(float) @ R.T + t) + corner_px * rng.standard_normal((len(obj), 2)))
          .astype(np.float32) for R, t in poses]
    _, K, d, rv, tv = cv2.calibrateCamera([obj] * len(ip), ip, (1280, 960), None, None,
                                          criteria=(3, 100, 1e-12))
    d = d.ravel()[:5]
    c = intrinsics_covariance([obj] * len(ip), ip, rv, tv, K, d, noise="white")  # white noise injected
    cam = Camera(K, d, 1280, 960, covariance=c.covariance, covariance_params=c.params)
    plane_true = default_plane()
    obs = [synthetic_observations(true, plane_true, p, n_rim=120, n_stripe=80, sigma_px=0.05, rng=rng)
           for p in sample_placements(12, rng, camera=true, plane=plane_true)]

    def solve(cm):
        return calibrate_plane_from_points(cm, 50.0, [o[0] for o in obs], [o[1] for o in obs], method="ml").plane

    pl = solve(cam)
    plane = LightPlane(pl.normal, pl.d, pl.covariance, meta={CameraDependence.KEY: propagate_camera(solve, cam, pl).to_dict()})
    ray = float(np.sqrt(np.mean(ray_sigma_rad(cam, image_grid(cam)) ** 2)))
    vs = volume_sigma(cam, plane, working_volume_grid(cam, plane))
    return {"ray_deg": float(np.degrees(ray)), **{f"ray_mm_{z}": ray * z for z in (300, 450, 600)},
            "frame_mm": vs.camera_frame_mm, "shape_mm": vs.shape_mm, "plane_only_mm": vs.plane_only_mm}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--corner-px", type=float, default=0.01)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--views", default="8,16,30,60")
    args = ap.parse_args()
    t0 = time.perf_counter()
    rows = []
    print(f"corner noise {args.corner_px} px (scale every camera figure linearly with yours); medians of "
          f"{args.seeds} pose draws; plane from 12 synthetic placements at 0.05 px")
    print(f"{'board':<6} {'views':>5} {'ray deg':>8} {'mm@300':>7} {'mm@450':>7} {'mm@600':>7} "
          f"{'frame mm':>9} {'shape mm':>9} {'plane-only mm':>13}")
    for board in ((9, 7), (15, 11)):
        for n in (int(v) for v in args.views.split(",")):
            rs = [one(board, n, args.corner_px, 100 * n + s) for s in range(args.seeds)]
            med = {k: float(np.median([r[k] for r in rs])) for k in rs[0]}
            rows.append({"board": list(board), "views": n, **med})
            print(f"{board[0]}x{board[1]:<4} {n:>5} {med['ray_deg']:>8.5f} {med['ray_mm_300']:>7.4f} "
                  f"{med['ray_mm_450']:>7.4f} {med['ray_mm_600']:>7.4f} {med['frame_mm']:>9.4f} "
                  f"{med['shape_mm']:>9.4f} {med['plane_only_mm']:>13.4f}", flush=True)
    print(f"({time.perf_counter() - t0:.0f} s)")
    record("bench_camera_views", [
        figure(f"frame_sigma_{r['board'][0]}x{r['board'][1]}_{r['views']}_views",
               f"point sigma, camera frame, {r['board'][0]}x{r['board'][1]} board, {r['views']} views",
               r["frame_mm"], "mm", statistic=f"median of {args.seeds} pose draws, corner noise {args.corner_px} px",
               reference=("plane-only sigma", r["plane_only_mm"], "mm"))
        for r in rows])
    out = Path(__file__).resolve().parent / "out"
    out.mkdir(exist_ok=True)
    (out / "bench_camera_views.json").write_text(json.dumps({"corner_px": args.corner_px, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
