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

With ``--renders N``: also N rendered data sets of each kind (10 circle-target images,
realistic; 10 chessboard poses with the stripe, realistic), flat and bent, calibrated by the
command's own path (lightplane.plane.calibrate.calibrate_plane, lightplane.plane.zhou.calibrate_plane_board,
exact camera) and scored the same way.

    .venv/bin/python benchmarks/bench_sheet.py [--trials 40] [--sag 0.05] [--renders 2]
"""

from __future__ import annotations

import argparse

import numpy as np

from lightplane.plane.calibrate import calibrate_plane
from lightplane.plane.sheet import (board_stripe_points, circle_stripe_points, fit_sheet, sheet_points_sigma_mm,
                                    triangulate_sheet)
from lightplane.plane.zhou import BoardFrames, calibrate_plane_board
from lightplane.plane.triangulate import points_sigma_mm, triangulate_normalized
from lightplane.plane.zhou import fit_plane
from lightplane.simulate.render import (BoardOptions, CircleOptions, render_chessboard_dataset, render_circle_dataset,
                                        sheet_tilt_for_sag)
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


def _render_trial(kind: str, seed: int, tilt: float, field: np.ndarray) -> dict:
    """One rendered data set calibrated and scored as :func:`_trial`."""
    if kind == "board":
        ds = render_chessboard_dataset(10, seed, BoardOptions(difficulty="realistic", with_stripe=True, laser_off=True,
                                                              sheet_tilt_deg=tilt))
        on = [im for im, nm in zip(ds.images, ds.names) if not nm.endswith("_off.png")]
        off = [im for im, nm in zip(ds.images, ds.names) if nm.endswith("_off.png")]
        b = ds.truth["board"]
        zc = calibrate_plane_board(BoardFrames(on, background_images=off), ds.camera, tuple(b["inner_corners"]),
                                   b["square_mm"])
        plane, pts = zc.plane, board_stripe_points(zc)
    else:
        ds = render_circle_dataset(10, seed, CircleOptions(difficulty="realistic", sheet_tilt_deg=tilt))
        cal = calibrate_plane(ds.images, ds.camera, 50.0)
        plane, pts = cal.plane, circle_stripe_points(cal)
    fit = fit_sheet(plane, pts)
    xy = field[:, :2] / field[:, 2:]
    return {"plane_rms": float(np.sqrt(np.mean(np.sum((triangulate_normalized(plane, xy).points - field)**2, 1)))),
            "sheet_rms": float(np.sqrt(np.mean(np.sum((triangulate_sheet(fit.sheet, xy) - field)**2, 1)))),
            "z": fit.test.z, "curved": fit.test.curved, "sag": fit.test.sag_mm}


def _render_figures(n: int, tilt: float, sag: float, fields: dict) -> list[dict]:
    figs = []
    for kind in ("circle", "board"):
        runs = {k: [_render_trial(kind, s, k, fields[k]) for s in range(n)] for k in (0.0, tilt)}
        for k in (0.0, tilt):
            print(kind, "bent" if k else "flat", [{a: round(float(b), 5) for a, b in r.items()} for r in runs[k]])
        flat = float(np.sqrt(np.mean([r["plane_rms"]**2 for r in runs[0.0]])))
        stat = f"RMS over {n} rendered data sets of 10 images (realistic)"
        figs += [
            figure(f"sheet_render_{kind}_false_alarm", f"{kind} renders, flat sheet: called curved",
                   float(sum(r["curved"] for r in runs[0.0])), f"of {n}", statistic="count"),
            figure(f"sheet_render_{kind}_detection", f"{kind} renders, sheet bent {sag:g} mm: called curved",
                   float(sum(r["curved"] for r in runs[tilt])), f"of {n}", statistic="count"),
            figure(f"sheet_render_{kind}_curved_tri_rms", f"{kind} renders: curved model on a sheet bent {sag:g} mm",
                   float(np.sqrt(np.mean([r["sheet_rms"]**2 for r in runs[tilt]]))), "mm", statistic=stat,
                   reference=("flat plane on a flat sheet", flat, "mm"), target=at_most(1.2, "x", of="ratio")),
            figure(f"sheet_render_{kind}_flat_on_curved_tri_rms", f"{kind} renders: flat plane on a sheet bent {sag:g} mm",
                   float(np.sqrt(np.mean([r["plane_rms"]**2 for r in runs[tilt]]))), "mm", statistic=stat,
                   reference=("flat plane on a flat sheet", flat, "mm")),
        ]
    return figs


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--trials", type=int, default=40)
    ap.add_argument("--sag", type=float, default=0.05, help="the curved sheet's sag at the field's edge, mm")
    ap.add_argument("--renders", type=int, default=0, help="rendered data sets of each kind (0: none)")
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
    if args.renders:
        figs += _render_figures(args.renders, tilt, args.sag, fields)
    record("bench_sheet", figs)


if __name__ == "__main__":
    main()
