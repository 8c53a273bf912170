"""Benchmark of the curved light sheet (a cone from a tilted fan lens) against the flat plane.

Exact observation model (lightplane.simulate.sheet, no images): 12 circle-target placements of
the default sensor, one stripe point per pixel along each chord with 0.1 px of noise across the
stripe, each image's target pose off by 0.01 deg of tilt and 0.01 mm along its normal.  The same
draws on a flat sheet and on a cone bent 0.05 mm at the field's edge.  Per calibration: the flat
plane (total least squares through the points, lightplane.plane.zhou.fit_plane) and the curved
sheet over it (lightplane.plane.sheet.fit_sheet); each triangulates the exact rays of a grid of
points on the true sheet over the field (depth 380-520 mm) and is scored against them (RMS mm).

Figures: the flatness test's false-alarm rate on the flat sheet and its detection rate on the
curved one; the triangulation error of the curved model on the curved sheet against the flat
model on the flat sheet (target ratio <= 1.2) and of the flat model on the curved sheet.

    .venv/bin/python benchmarks/bench_sheet.py [--trials 40] [--sag 0.05]
"""

from __future__ import annotations

import argparse

import numpy as np

from lightplane.plane.sheet import fit_sheet, sheet_points_sigma_mm, triangulate_sheet
from lightplane.plane.triangulate import points_sigma_mm, triangulate_normalized
from lightplane.plane.zhou import fit_plane
from lightplane.simulate.render import sheet_tilt_for_sag
from lightplane.simulate.sheet import SheetObservation, sheet_field_points, sheet_stripe_points
from results import at_most, figure, record


def _trial(seed: int, tilt: float, field: np.ndarray, obs: SheetObservation) -> dict:
    pts = sheet_stripe_points(12, np.random.default_rng(seed), tilt, obs)
    plane = fit_plane(np.vstack(pts))
    fit = fit_sheet(plane, pts)
    xy = field[:, :2] / field[:, 2:]
    e_plane = np.linalg.norm(triangulate_normalized(plane, xy).points - field, axis=1)
    e_sheet = np.linalg.norm(triangulate_sheet(fit.sheet, xy) - field, axis=1)
    return {"plane_rms": float(np.sqrt(np.mean(e_plane**2))), "sheet_rms": float(np.sqrt(np.mean(e_sheet**2))),
            "plane_sigma": float(np.sqrt(np.mean(points_sigma_mm(plane, xy)**2))),
            "sheet_sigma": float(np.sqrt(np.mean(sheet_points_sigma_mm(fit.sheet, xy)**2))),
            "z": fit.test.z, "curved": fit.test.curved, "sag": fit.test.sag_mm}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--trials", type=int, default=40)
    ap.add_argument("--sag", type=float, default=0.05, help="the curved sheet's sag at the field's edge, mm")
    args = ap.parse_args()
    obs = SheetObservation()
    tilt = sheet_tilt_for_sag(args.sag)
    fields = {0.0: sheet_field_points(0.0), tilt: sheet_field_points(tilt)}
    runs = {k: [_trial(s, k, fields[k], obs) for s in range(args.trials)] for k in (0.0, tilt)}

    def rms(k: float, key: str) -> float:
        return float(np.sqrt(np.mean([r[key]**2 for r in runs[k]])))

    fa = float(np.mean([r["curved"] for r in runs[0.0]]))
    det = float(np.mean([r["curved"] for r in runs[tilt]]))
    flat_ref = rms(0.0, "plane_rms")
    stat = f"RMS over {args.trials} simulated calibrations (exact observation model)"
    for k, label in ((0.0, "flat"), (tilt, "curved")):
        print(f"{label}: plane {rms(k, 'plane_rms'):.4f} mm (predicted {rms(k, 'plane_sigma'):.4f}), sheet "
              f"{rms(k, 'sheet_rms'):.4f} mm (predicted {rms(k, 'sheet_sigma'):.4f}); called curved "
              f"{np.mean([r['curved'] for r in runs[k]]):.3f}; sag {np.mean([r['sag'] for r in runs[k]]):+.4f} mm")
    figs = [
        figure("sheet_false_alarm", "flatness test on a flat sheet: called curved", 100 * fa, "%",
               statistic=f"fraction of {args.trials} simulated calibrations, |z| >= 3", target=at_most(5.0, "%")),
        figure("sheet_detection", f"flatness test on a sheet bent {args.sag:g} mm: called curved", 100 * det, "%",
               statistic=f"fraction of {args.trials} simulated calibrations"),
        figure("sheet_curved_tri_rms", f"curved model on a sheet bent {args.sag:g} mm: triangulation RMS",
               rms(tilt, "sheet_rms"), "mm", statistic=stat,
               reference=("flat plane on a flat sheet", flat_ref, "mm"), target=at_most(1.2, "x", of="ratio")),
        figure("sheet_flat_on_curved_tri_rms", f"flat plane on a sheet bent {args.sag:g} mm: triangulation RMS",
               rms(tilt, "plane_rms"), "mm", statistic=stat, reference=("flat plane on a flat sheet", flat_ref, "mm")),
        figure("sheet_curved_sigma_ratio", "curved model: predicted point sigma / actual RMS",
               rms(tilt, "sheet_sigma") / rms(tilt, "sheet_rms"), "x", statistic=stat),
    ]
    record("bench_sheet", figs)


if __name__ == "__main__":
    main()
