"""Figures of docs/calibration-guide.md: a Monte-Carlo study on lightplane's default sensor, and renders.

    .venv/bin/python docs/make_figures.py [--trials 40] [--seed 0]

Study (docs/conventions.md §Default sensor: 1280x960, 16 mm lens, light plane 25° oblique crossing the
optical axis at 450 mm): per trial, random target placements
(:func:`lightplane.simulate.scene.sample_placements`), exact rim and stripe pixels
(:func:`~lightplane.simulate.scene.synthetic_observations`) with Gaussian noise of
the size measured on the realistic renders, as white noise carrying the same
information as the measured correlated noise (``benchmarks/bench_uncertainty.py``,
2026-11-24: rim sigma 0.053 px with autocorrelation time tau 1.46 over ~1200 rim
points, i.e. 1000 points at 0.06 px; raw stripe centres 0.126 px with tau 6.1 over
~330 centres, or ~65 averages of ~5 centres at 0.102 px with tau 1.55 as
:func:`lightplane.plane.calibrate.observe_image` gives the solver, i.e. 30 stripe points
at 0.09 px), then
:func:`lightplane.plane.solvers.calibrate_plane_from_points` (``ml``).  Reported: the RMS over
trials of the triangulation error over the working volume 380–520 mm (mm), and the
share of trials that failed (an error was raised, e.g. an unresolved ambiguity, or
the normal is off by more than 0.5°).  Factors: number of placements, tilt range,
distance range, target diameter.  Renders (:mod:`lightplane.simulate.render`): light
and dark polarity side by side; the report's residual plot and uncertainty map.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from lightplane.core.errors import LightplaneError
from lightplane.plane.solvers import calibrate_plane_from_points
from lightplane.simulate.scene import (PlacementOptions, default_camera, default_plane, sample_placements,
                                       synthetic_observations)
from lightplane.plane.uncertainty import rms_triangulation_error_mm, working_volume_grid

OUT = Path(__file__).resolve().parent / "figures"
SIGMA_RIM, SIGMA_STRIPE, N_RIM, N_STRIPE = 0.06, 0.09, 1000, 30


def trial(rng, n=12, tilt=(15.0, 55.0), dist=(380.0, 520.0), diameter=50.0, cam=None, plane=None, vol=None):
    ps = sample_placements(n, rng, PlacementOptions(diameter_mm=diameter, distance_mm=dist, tilt_deg=tilt),
                           camera=cam, plane=plane)
    rims, stripes = [], []
    for p in ps:
        r, s = synthetic_observations(cam, plane, p, n_rim=N_RIM, n_stripe=N_STRIPE)
        rims.append(r + rng.normal(0, SIGMA_RIM, r.shape))
        stripes.append(s + rng.normal(0, SIGMA_STRIPE, s.shape))
    try:
        cal = calibrate_plane_from_points(cam, diameter, rims, stripes, "ml")
    except LightplaneError:
        return np.nan
    if np.degrees(cal.plane.angle_to(plane)) > 0.5:
        return np.nan
    return rms_triangulation_error_mm(cam, cal.plane, plane, vol)


def study(trials: int, seed: int) -> dict:
    cam, plane = default_camera(), default_plane()
    vol = working_volume_grid(cam, plane, distance_mm=(380.0, 520.0))
    kw = dict(cam=cam, plane=plane, vol=vol)
    factors = {
        "placements": ("number of target placements", [3, 4, 6, 8, 12, 16], lambda v: dict(n=v)),
        "tilt": ("tilt range from the line of sight (deg), 4 placements",
                 [(3, 8), (8, 15), (15, 35), (35, 55), (55, 70)], lambda v: dict(tilt=v, n=4)),
        "distance": ("distances of the targets from the camera (mm)",
                     [(380, 420), (430, 470), (480, 520), (380, 520), (330, 570)], lambda v: dict(dist=v)),
        "diameter": ("target diameter (mm)", [20, 30, 40, 50, 70], lambda v: dict(diameter=v)),
    }
    out = {}
    for fi, (name, (label, levels, mk)) in enumerate(factors.items()):
        rows = []
        for k, v in enumerate(levels):
            errs = []
            for t in range(trials):
                rng = np.random.default_rng([seed, fi, k, t])
                try:
                    errs.append(trial(rng, **mk(v), **kw))
                except LightplaneError:  # placements impossible (e.g. a big disc close by)
                    errs.append(np.nan)
            e = np.array(errs)
            ok = np.isfinite(e)
            rows.append({"level": v, "rms_mm": float(np.sqrt(np.mean(e[ok] ** 2))) if ok.any() else None,
                         "failed": int((~ok).sum()), "trials": trials})
            print(f"{name:<10} {str(v):<12} RMS {rows[-1]['rms_mm']} mm, failed {rows[-1]['failed']}/{trials}",
                  flush=True)
        out[name] = {"label": label, "rows": rows}
    return out


def plot_study(res: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for name, d in res.items():
        rows = d["rows"]
        labels = [str(r["level"]).replace("(", "").replace(")", "").replace(", ", "–") for r in rows]
        x = np.arange(len(rows))
        rms = np.array([np.nan if r["rms_mm"] is None else r["rms_mm"] * 1e3 for r in rows])
        fail = np.array([100.0 * r["failed"] / r["trials"] for r in rows])
        fig, ax = plt.subplots(figsize=(6.4, 3.6))
        ax.plot(x, rms, "o-", color="#1f5fbf")
        ax.set_ylabel("RMS triangulation error\nover 380–520 mm (µm)", color="#1f5fbf")
        ax.set_xticks(x)
        ax.set_xticklabels(labels)
        ax.set_xlabel(d["label"])
        ax.set_ylim(0, np.nanmax(rms) * 1.2 if np.any(np.isfinite(rms)) else 1)
        ax2 = ax.twinx()
        ax2.bar(x, fail, 0.35, color="#d02020", alpha=0.35)
        ax2.set_ylabel("failed trials (%)", color="#d02020")
        ax2.set_ylim(0, 100)
        ax.set_title(f"Default sensor, ml, {rows[0]['trials']} trials per level", fontsize=9)
        fig.tight_layout()
        fig.savefig(OUT / f"study_{name}.png", dpi=90)
        plt.close(fig)


def render_figures() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lightplane.plane.calibrate import calibrate_plane
    from lightplane.plane.model import LightPlane
    from lightplane.report.html import figure_residuals, figure_uncertainty
    from lightplane.simulate.render import CircleOptions, render_circle_dataset

    sets = {p: render_circle_dataset(6, 5, CircleOptions(difficulty="realistic", polarity=p)) for p in ("light", "dark")}
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.8))
    for ax, (p, ds) in zip(axes, sets.items()):
        ax.imshow(ds.images[1], cmap="gray", vmin=0, vmax=255)
        ax.set_title(f"polarity '{p}'", fontsize=9)
        ax.set_xlabel("u (px)")
        ax.set_ylabel("v (px)")
    fig.tight_layout()
    fig.savefig(OUT / "polarity.png", dpi=80)
    plt.close(fig)
    ds = sets["light"]
    cal = calibrate_plane(ds.images, ds.camera, 50.0, "ml")
    (OUT / "check_residuals.png").write_bytes(figure_residuals(cal))
    (OUT / "check_uncertainty.png").write_bytes(figure_uncertainty(cal))
    truth = LightPlane.from_dict(ds.truth["plane"])
    print(f"render check: 6 images, angle {np.degrees(cal.plane.angle_to(truth)):.4f} deg")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--trials", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--skip-study", action="store_true")
    args = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    if not args.skip_study:
        res = study(args.trials, args.seed)
        (OUT / "study.json").write_text(json.dumps(res, indent=1, default=str))
        plot_study(res)
    render_figures()


if __name__ == "__main__":
    main()
