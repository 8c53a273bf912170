"""Benchmark and Monte-Carlo check of the joint ML refinement.

1. Speed: ``refine_ml`` and ``calibrate_plane_from_points(method="ml")`` (global + ML)
   on 12 placements x (200 rim + 300 stripe points), default sensor with distortion,
   sigma 0.1 px.  Target: ML <= 150 ms (2 cores).  Median wall and CPU times.
2. Accuracy (``--trials``, default 200): default sensor geometry WITHOUT distortion
   (docs/conventions.md §Default sensor, pinhole), sigma 0.1 px on rim and stripe points, 12 placements of a 50 mm
   disc drawn afresh per trial.  For paper / global / ml: RMS plane-angle error and RMS
   triangulation error over the working volume (380–520 mm), as ratios to the
   Cramér–Rao bound (RMS of the per-trial bounds); disambiguation failures; and ml's
   predicted sigma (its own covariance) against the Monte-Carlo RMS.
   Targets: ml within 1.15x the CRLB; predicted sigma within 15 % of the MC RMS;
   global <= paper.

    .venv/bin/python benchmarks/bench_ml.py [--repeats 20] [--trials 200] [--seed 0]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from lightplane.core.errors import LightplaneError
from lightplane.plane.solvers import calibrate_plane_from_points
from lightplane.plane.ml import crlb, refine_ml
from lightplane.simulate.scene import default_camera, default_plane, sample_placements, synthetic_observations
from lightplane.plane.uncertainty import rms_point_sigma_mm, rms_triangulation_error_mm, working_volume_grid
from results import at_most, between, figure, record

TARGET_MS = 150.0


def _angle(a, b) -> float:
    return float(np.arctan2(np.linalg.norm(np.cross(a, b)), abs(a @ b)))


def _median_ms(fn, repeats: int) -> tuple[float, float]:
    fn()  # warm-up
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return 1e3 * float(np.median(wall)), 1e3 * float(np.median(cpu))


def speed(repeats: int) -> list[dict]:
    rng = np.random.default_rng(2024)
    cam, plane = default_camera(), default_plane()
    ps = sample_placements(12, rng, camera=cam, plane=plane)
    obs = [synthetic_observations(cam, plane, p, sigma_px=0.1, rng=rng) for p in ps]
    rims, sts = [o[0] for o in obs], [o[1] for o in obs]
    g = calibrate_plane_from_points(cam, 50.0, rims, sts, method="global")
    poses = [p.pose for p in g.placements]
    w, c = _median_ms(lambda: refine_ml(cam, 25.0, rims, sts, g.plane, poses), repeats)
    print(f"refine_ml, 12 x (200 + 300) points:           median {w:6.1f} ms wall, {c:6.1f} ms CPU"
          f"  -> {w / TARGET_MS:.2f}x the {TARGET_MS:g} ms target")
    stat = f"median of {repeats} runs"
    figs = [figure("refine_ml_wall", "refine_ml, 12 placements, wall", w, "ms", statistic=stat,
                   target=at_most(TARGET_MS, "ms")),
            figure("refine_ml_cpu", "refine_ml, 12 placements, CPU", c, "ms", statistic=stat,
                   target=at_most(TARGET_MS, "ms"))]
    w, c = _median_ms(lambda: calibrate_plane_from_points(cam, 50.0, rims, sts, method="ml"), repeats)
    print(f"calibrate_plane_from_points(method='ml'):     median {w:6.1f} ms wall, {c:6.1f} ms CPU"
          f"  -> {w / TARGET_MS:.2f}x the {TARGET_MS:g} ms target")
    figs.append(figure("plane_solver_ml_wall", "plane solver global + ml, wall", w, "ms", statistic=stat,
                       target=at_most(TARGET_MS, "ms")))
    res = refine_ml(cam, 25.0, rims, sts, g.plane, poses)
    print(f"  (solver evaluations: {res.iterations}; sigma estimate {res.sigma_px:.4f} px for 0.1 px injected)")
    return figs


def accuracy(trials: int, seed: int) -> list[dict]:
    cam, plane = default_camera(distortion=False), default_plane()
    vol = working_volume_grid(cam, plane, step_px=32.0)
    sigma = 0.1
    methods = ("paper", "global", "ml")
    ang2 = {m: [] for m in methods}
    tri2 = {m: [] for m in methods}
    fails = {m: 0 for m in methods}
    wrong = {m: 0 for m in methods}  # trials with a wrongly chosen pose
    unused = {m: 0 for m in methods}  # placements left out (paper: stopped by the 0.1 % rule; undecided)
    b_ang2, b_tri2, p_ang2, p_tri2 = [], [], [], []
    t0 = time.perf_counter()
    for t in range(trials):
        rng = np.random.default_rng([seed, t])
        ps = sample_placements(12, rng, camera=cam, plane=plane)
        obs = [synthetic_observations(cam, plane, p, sigma_px=sigma, rng=rng) for p in ps]
        rims, sts = [o[0] for o in obs], [o[1] for o in obs]
        for m in methods:
            try:
                res = calibrate_plane_from_points(cam, 50.0, rims, sts, method=m)
            except LightplaneError:
                fails[m] += 1
                continue
            # disambiguation: a used placement whose chosen pose is not the true one (normal off > 1 deg)
            if any(pr.used and _angle(pr.pose.normal, truth.normal) > np.radians(1.0)
                   for pr, truth in zip(res.placements, ps)):
                wrong[m] += 1
            unused[m] += sum(not pr.used for pr in res.placements)
            ang2[m].append(_angle(res.plane.normal, plane.normal) ** 2)
            tri2[m].append(rms_triangulation_error_mm(cam, res.plane, plane, vol) ** 2)
            if m == "ml":
                p_ang2.append(np.trace(res.covariance[:3, :3]))
                p_tri2.append(rms_point_sigma_mm(cam, res.plane, vol) ** 2)
        b = crlb(cam, 25.0, ps, plane, 200, 300, sigma)
        b_ang2.append(np.trace(b[:3, :3]))
        b_tri2.append(rms_point_sigma_mm(cam, plane, vol, covariance=b) ** 2)
    dt = time.perf_counter() - t0
    b_ang, b_tri = np.sqrt(np.mean(b_ang2)), np.sqrt(np.mean(b_tri2))
    se = 1 / np.sqrt(2 * trials)
    print(f"\nMonte Carlo: {trials} trials ({dt:.0f} s), pinhole default sensor, sigma {sigma} px, "
          f"12 placements, 50 mm disc (RMS standard error <= {100 * se:.1f} %)")
    print(f"CRLB: angle {np.degrees(b_ang) * 3600:.3f} arcsec, triangulation {1e3 * b_tri:.3f} µm (RMS over the volume)")
    print(f"{'method':8s} {'angle RMS':>14s} {'x CRLB':>7s} {'tri RMS':>11s} {'x CRLB':>7s} {'errors':>7s} {'wrong pose':>10s} {'unused':>7s}")
    for m in methods:
        a, tr = np.sqrt(np.mean(ang2[m])), np.sqrt(np.mean(tri2[m]))
        print(f"{m:8s} {np.degrees(a) * 3600:10.3f} asec {a / b_ang:7.3f} {1e3 * tr:8.3f} µm {tr / b_tri:7.3f} "
              f"{fails[m]:7d} {wrong[m]:10d} {unused[m] / max(1, trials - fails[m]):7.2f}")
    a, tr = np.sqrt(np.mean(ang2["ml"])), np.sqrt(np.mean(tri2["ml"]))
    pa, pt = np.sqrt(np.mean(p_ang2)), np.sqrt(np.mean(p_tri2))
    print(f"ml predicted sigma / MC RMS: angle {pa / a:.3f}, triangulation {pt / tr:.3f}  (target within 1 ± 0.15)")
    ok = (a / b_ang <= 1.15 and tr / b_tri <= 1.15 and abs(pa / a - 1) <= 0.15 and abs(pt / tr - 1) <= 0.15)
    print("ML targets met" if ok else "ML targets NOT met")
    stat = f"RMS over {trials} Monte-Carlo trials"
    return [figure("ml_angle_rms", "ml plane angle error", np.degrees(a) * 3600, "arcsec", statistic=stat,
                   reference=("Cramér-Rao bound", np.degrees(b_ang) * 3600, "arcsec"),
                   target=at_most(1.15, "x", of="ratio")),
            figure("ml_triangulation_rms", "ml triangulation error", 1e3 * tr, "µm", statistic=stat,
                   reference=("Cramér-Rao bound", 1e3 * b_tri, "µm"), target=at_most(1.15, "x", of="ratio")),
            figure("ml_predicted_angle_sigma", "ml predicted angle sigma", np.degrees(pa) * 3600, "arcsec",
                   statistic=stat, reference=("Monte-Carlo RMS", np.degrees(a) * 3600, "arcsec"),
                   target=between(0.85, 1.15, "x", of="ratio")),
            figure("ml_predicted_triangulation_sigma", "ml predicted triangulation sigma", 1e3 * pt, "µm",
                   statistic=stat, reference=("Monte-Carlo RMS", 1e3 * tr, "µm"),
                   target=between(0.85, 1.15, "x", of="ratio"))]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    if hasattr(os, "getloadavg"):
        print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs (wall times inflate under load)")
    figs = speed(args.repeats)
    if args.trials > 0:
        figs += accuracy(args.trials, args.seed)
    record("bench_ml", figs)


if __name__ == "__main__":
    main()
