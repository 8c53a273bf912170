"""Turntable benchmarks: the axis from rendered board views, and a sphere scan on the table.

Run: ``.venv/bin/python benchmarks/bench_turntable.py [clean] [realistic]`` (both by default), or
``... bench_turntable.py fabscan MERGED.ply FIGURE.png``: the FabScan worked example of the
README (the merged two-laser cloud of ``measure --sensor``): the figure of the object, and
how far the two lasers' clouds are apart (nearest-neighbour distances, median and 90th
percentile, after the best turn of laser 1's cloud about the axis: the two scans start at
different table angles).

Per difficulty (renders of :mod:`lightplane.simulate.turntable`, lightplane's default sensor):

- the axis by :func:`lightplane.motion.turntable.calibrate_turntable` from 9 views of a 9x6
  chessboard (8 mm) standing on the table, turned over 80 deg: angle and distance to the
  true axis, the two estimates' agreement and the jackknife σ;
- a 36-frame scan per laser (two lasers, 10 deg per frame) of a 20 mm sphere 12 mm off
  the axis, placed by the true axis and by the calibrated one, with the true planes:
  fitted radius error, centre error, RMS residual; the two lasers' clouds against each
  other (each laser's points to the other laser's fitted sphere, RMS; bar 0.02 mm on
  clean renders); radius bar 0.02 mm.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from lightplane import LightPlane
from lightplane.motion.model import Motion, Turntable
from lightplane.measure.scan import ArrayFrames, scan_points
from lightplane.evaluate.shapes import fit_sphere
from lightplane.simulate.turntable import TurntableScanOptions, render_turntable_board, render_turntable_scan
from lightplane.camera.targets import parse_target
from lightplane.motion.turntable import calibrate_turntable
from results import at_most, figure, record, within

N_FRAMES = 36


def _axis_errors(est: Turntable, true: Turntable) -> tuple[float, float]:
    ang = float(np.degrees(np.arccos(np.clip(est.direction @ true.direction, -1, 1))))
    off = est.point_mm - true.point_mm
    off -= (off @ true.direction) * true.direction
    return ang, float(np.linalg.norm(off))


def run(difficulty: str) -> list[dict]:
    t0 = time.perf_counter()
    board = render_turntable_board(angles_deg=np.linspace(-40, 40, 9), seed=11, difficulty=difficulty)
    cal = calibrate_turntable(board.images, board.camera, parse_target("chessboard:9x6", 8.0), names=board.names)
    true = Turntable.from_dict(board.truth["turntable"])
    ang, off = _axis_errors(cal.turntable, true)
    j = cal.turntable.meta["jackknife"]
    print(f"[{difficulty}] axis from {len(board.images)} board views: direction {ang:.4f} deg, position {off:.4f} mm "
          f"from the truth (jackknife σ {j['sigma_direction_deg_circles']:.4f} deg, {j['sigma_point_mm_circles']:.4f} mm);"
          f" circles vs rotations {cal.agreement_deg:.4f} deg / {cal.agreement_mm:.4f} mm apart"
          f" ({'agree' if cal.agrees else 'disagree'}); PnP RMS "
          f"{np.median([im['pnp_rms_px'] for im in cal.images]):.3f} px median")
    stat = f"{len(board.images)} board views, {difficulty} renders"
    figs = [figure(f"axis_direction_{difficulty}", f"turntable axis direction error, {difficulty}", ang, "deg",
                   statistic=stat),
            figure(f"axis_position_{difficulty}", f"turntable axis position error, {difficulty}", off, "mm",
                   statistic=stat)]
    scan = render_turntable_scan(N_FRAMES, 12, TurntableScanOptions(difficulty=difficulty))
    T = scan.truth
    o_t, B_t = true.basis()
    c_cam = o_t + B_t @ np.asarray(T["sphere"]["center_turntable_mm"])  # the sphere's centre at angle 0, camera frame
    for label, table in (("true axis", true), ("calibrated axis", cal.turntable)):
        motion = Motion.turntable(table, T["step_deg"])
        o, B = table.basis()
        z_table = float((o_t - o) @ B[:, 2])  # the table's top in this frame (its origin sits where the board was)
        centre = B.T @ (c_cam - o)
        fits, pts = [], []
        for li, name in enumerate(T["lasers"]):
            plane = LightPlane.from_dict(T["lasers"][name]["plane"])
            rec, _ = scan_points(ArrayFrames(scan.images[li * N_FRAMES:(li + 1) * N_FRAMES]), scan.camera, plane,
                                 motion=motion, workers=2)
            p = np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(float)
            p = p[p[:, 2] > z_table + 1.0]
            f = fit_sphere(p)
            fits.append(f)
            pts.append(p)
            c = f.center_mm - centre  # the true centre in this axis' frame
            print(f"[{difficulty}] {label}, {name}: {len(p)} points, radius error {f.radius_mm - 20.0:+.4f} mm "
                  f"(bar 0.02), centre error {np.linalg.norm(c):.4f} mm, RMS residual {f.rms_mm:.4f} mm, "
                  f"inliers {f.n_inliers / len(p):.3f}")
            if table is cal.turntable:
                figs.append(figure(f"sphere_radius_{difficulty}_{name}", f"turntable sphere radius, {difficulty}, {name}",
                                   f.radius_mm, "mm", truth=20.0, target=within(0.02, "mm", of="error"),
                                   statistic=f"fit to {len(p)} points, calibrated axis"))
        cross = [float(np.sqrt(np.mean((np.linalg.norm(p - o.center_mm, axis=1) - o.radius_mm) ** 2)))
                 for p, o in ((pts[0], fits[1]), (pts[1], fits[0]))]
        print(f"[{difficulty}] {label}: laser0 points to laser1's sphere RMS {cross[0]:.4f} mm, laser1 to laser0's "
              f"{cross[1]:.4f} mm (bar 0.02 on clean renders); centres {np.linalg.norm(fits[0].center_mm - fits[1].center_mm):.4f} mm apart")
        if table is cal.turntable:
            figs.append(figure(f"lasers_cross_rms_{difficulty}", f"turntable laser0 points to laser1's sphere, {difficulty}",
                               cross[0], "mm", statistic="RMS, calibrated axis",
                               target=at_most(0.02, "mm") if difficulty == "clean" else None))
    print(f"[{difficulty}] {time.perf_counter() - t0:.0f} s")
    return figs


def fabscan(cloud: str, figure: str) -> None:
    from scipy.spatial import cKDTree

    from lightplane.motion.model import rotation_about
    from lightplane.report.plots import point_cloud
    from lightplane.measure.pointcloud import read_cloud

    r = read_cloud(cloud)
    p = np.column_stack([r["x"], r["y"], r["z"]]).astype(float)
    # the object and the table's top: within 60 mm of the axis, below the wall's stripe (z > 95 mm)
    keep = (np.hypot(p[:, 0], p[:, 1]) < 60) & (p[:, 2] > -3) & (p[:, 2] < 95)
    point_cloud(p[keep], figure, labels=r["laser"][keep], names=["laser0 (scan 1_1)", "laser1 (scan 1_2)"],
                title=f"FabScan: both lasers' scans in the turntable frame ({np.count_nonzero(keep)} points)",
                max_points=80000)
    obj = keep & (p[:, 2] > 3) & (np.hypot(p[:, 0], p[:, 1]) < 45)
    a, b = p[obj & (r["laser"] == 0)], p[obj & (r["laser"] == 1)]
    tree = cKDTree(a)
    coarse = min((float(np.median(tree.query(b[::8] @ rotation_about([0, 0, 1], np.deg2rad(f)).T)[0])), f)
                 for f in np.arange(0.0, 360.0, 2.0))
    fine = []
    for f in np.arange(coarse[1] - 2, coarse[1] + 2.01, 0.1):
        d, _ = tree.query(b @ rotation_about([0, 0, 1], np.deg2rad(f)).T)
        fine.append((float(np.median(d)), float(np.percentile(d, 90)), float(f)))
    med, p90, f = min(fine)
    d0, _ = tree.query(b)
    print(f"laser0 {len(a)} / laser1 {len(b)} object points; as measured: NN median {np.median(d0):.2f} mm, "
          f"90th percentile {np.percentile(d0, 90):.2f} mm; laser1's cloud turned {f:.1f} deg about the axis: "
          f"median {med:.2f} mm, 90th percentile {p90:.2f} mm; wrote {figure}")


def main(argv: list[str]) -> None:
    if argv and argv[0] == "fabscan":
        fabscan(argv[1], argv[2])
        return
    figs = []
    for d in argv or ["clean", "realistic"]:
        figs += run(d)
    record("bench_turntable", figs)


if __name__ == "__main__":
    main(sys.argv[1:])
