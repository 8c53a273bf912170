"""Guided against random placements of the circle target: placements to a target sigma, and the stop's honesty.

Run: ``.venv/bin/python benchmarks/bench_plan.py [--runs 24] [--renders 3] [--target 0.005]``.

The default sensor (docs/conventions.md §Default sensor) with its true camera; the working
volume is the stripe's whole image region at 380–520 mm; the target figure is the worst
point's camera-frame sigma over it.  Each run starts from a rough plane (the truth turned by
~1° and shifted by ~3 mm) and adds placements until :class:`lightplane.plan.CalibrationPlanner`
says its predicted figure is at most the target (at least 3 placements; 40 at most):

- guided: a scripted user puts the disc where :meth:`CalibrationPlanner.suggest` says, off by
  a placement error of 3 mm (each axis) and 3° (the normal, about a random axis), redrawn
  while the displaced disc breaks the limits;
- random: :func:`lightplane.simulate.scene.sample_placements` under the same limits
  (centre 380–520 mm, tilt 0–55°, chord >= 0.4 of the diameter, rim 20 px inside the image, the disc at
  30° or more to the light sheet).

Observations: the exact observation model (every run): rim points 1 per px of the rim's
image, white noise 0.053 px; stripe points 1 per px of the chord's image, white noise
0.27 px (the realistic renders' 0.11 px with their autocorrelation time of ~6 along the
stripe, as one white equivalent); every run's points are drawn anew.  ``--renders N``: N
guided and N random runs on full renders (:func:`lightplane.simulate.render.render_circle_image`,
realistic, found by :func:`lightplane.plane.calibrate.observe_image`).  The actual error at
the stop: the distance between the points triangulated with the solved plane and with the
true one, at the working-volume pixel the planner predicts worst, and its RMS over the volume.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results import between, at_most, figure, record  # noqa: E402

from lightplane.core.errors import LightplaneError  # noqa: E402
from lightplane.plane.calibrate import observe_image  # noqa: E402
from lightplane.plane.model import LightPlane  # noqa: E402
from lightplane.plane.triangulate import triangulate_normalized  # noqa: E402
from lightplane.plan.candidates import PoseLimits, is_feasible  # noqa: E402
from lightplane.plan.planner import CalibrationPlanner, NoiseModel, PlannerOptions  # noqa: E402
from lightplane.plan.volume import region_volume  # noqa: E402
from lightplane.simulate.render import render_circle_image  # noqa: E402
from lightplane.simulate.scene import (PlacementOptions, TargetPlacement, default_camera, default_plane,  # noqa: E402
                                       sample_placements, synthetic_observations)

CAM, TRUE = default_camera(), default_plane()
DIAMETER, DIST, MAX_TILT = 50.0, (380.0, 520.0), 55.0
SIGMA_RIM, SIGMA_STRIPE = 0.053, 0.27
LIMITS = PoseLimits(DIAMETER, distance_mm=DIST, max_tilt_deg=MAX_TILT)
RANDOM = PlacementOptions(DIAMETER, DIST, (0.0, MAX_TILT), 0.4, 20.0)
MAX_PLACEMENTS = 40
ROOT = Path(__file__).resolve().parents[1]


def rough_plane(rng: np.random.Generator) -> LightPlane:
    """The truth turned by ~1° about a random axis and shifted by ~3 mm."""
    axis = rng.normal(size=3)
    axis -= (axis @ TRUE.normal) * TRUE.normal
    n = TRUE.normal + np.radians(1.0) * axis / np.linalg.norm(axis)
    return LightPlane(n, TRUE.d + rng.normal(0, 3.0))


def user_places(p: TargetPlacement, rng: np.random.Generator) -> TargetPlacement:
    """Where a user puts the disc when told ``p``: 3 mm per axis, 3° of the normal off (redrawn while infeasible)."""
    for _ in range(50):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        a = np.radians(rng.normal(0, 3.0))
        n = p.normal * np.cos(a) + np.cross(axis, p.normal) * np.sin(a) + axis * (axis @ p.normal) * (1 - np.cos(a))
        q = TargetPlacement(p.center + rng.normal(0, 3.0, 3), n, DIAMETER)
        if is_feasible(CAM, TRUE, q, LIMITS, DIST):
            return q
    return p


def random_placement(rng: np.random.Generator) -> TargetPlacement:
    """A random placement under the guide's limits (the sampler's draws, those meeting the sheet at 30° or more)."""
    while True:
        p = sample_placements(1, rng, RANDOM, camera=CAM, plane=TRUE)[0]
        if is_feasible(CAM, TRUE, p, LIMITS, DIST):
            return p


def exact_observation(p: TargetPlacement, rng: np.random.Generator):
    per = np.sum(np.linalg.norm(np.diff(CAM.project(p.rim_points(360)), axis=0), axis=1))
    ch = p.chord(TRUE)
    chord_px = np.linalg.norm(np.diff(CAM.project(ch), axis=0))
    rim, _ = synthetic_observations(CAM, TRUE, p, n_rim=int(per), n_stripe=2, sigma_px=SIGMA_RIM, rng=rng)
    _, st = synthetic_observations(CAM, TRUE, p, n_rim=8, n_stripe=int(chord_px), sigma_px=SIGMA_STRIPE, rng=rng)
    return rim, st


def rendered_observation(p: TargetPlacement, rng: np.random.Generator):
    o = observe_image(render_circle_image(CAM, TRUE, p, rng), CAM, DIAMETER)
    if not o.ok:
        raise LightplaneError(o.reason)
    return o.rim_uv, o.stripe_uv


def run(strategy: str, seed: int, target: float, rendered: bool) -> dict:
    rng = np.random.default_rng(1000 * seed + (1 if strategy == "random" else 0))
    vol = region_volume(CAM, TRUE, None, distance_mm=DIST, step_px=32)
    opts = PlannerOptions(LIMITS, target_sigma_mm=target, max_placements=MAX_PLACEMENTS,
                          noise=NoiseModel(SIGMA_RIM, SIGMA_STRIPE))
    pl = CalibrationPlanner(CAM, rough_plane(rng), vol, opts)
    observe = rendered_observation if rendered else exact_observation
    curve, skipped = [], 0
    t0 = time.perf_counter()
    while len(pl.accepted) < MAX_PLACEMENTS:
        if strategy == "guided":
            p = user_places(pl.suggest().placement, rng)
        else:
            p = random_placement(rng)
        try:
            st = pl.add(*observe(p, rng))
        except LightplaneError:
            skipped += 1  # a render whose target or stripe was not found: the user takes another
            if skipped > 10:
                break
            continue
        curve.append(st.sigma_mm)
        if st.solved and len(pl.accepted) >= opts.min_placements and st.sigma_mm <= target:
            break
    st = pl.state()
    xy = CAM.undistort_points(pl.model.uv, normalized=True)
    e = np.linalg.norm(triangulate_normalized(pl.plane, xy).points - triangulate_normalized(TRUE, xy).points, axis=1)
    sig = pl.model.sigma(pl.information())
    k = int(np.argmax(sig))
    return {"strategy": strategy, "seed": seed, "rendered": rendered, "n": len(pl.accepted),
            "reached": bool(st.sigma_mm <= target), "predicted_worst_mm": float(sig[k]),
            "actual_at_worst_mm": float(e[k]), "actual_max_mm": float(e.max()),
            "predicted_rms_mm": float(np.sqrt(np.mean(sig**2))), "actual_rms_mm": float(np.sqrt(np.mean(e**2))),
            "curve_mm": curve, "skipped": skipped, "seconds": time.perf_counter() - t0}


def _ratio(runs: list[dict], a: str, b: str) -> float:
    return float(np.sqrt(np.mean([r[a] ** 2 for r in runs])) / np.sqrt(np.mean([r[b] ** 2 for r in runs])))


def draw(runs: list[dict], target: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    for s, c in (("guided", "C0"), ("random", "C1")):
        rs = [r for r in runs if r["strategy"] == s and not r["rendered"]]
        for r in rs:
            ax[0].plot(np.arange(1, len(r["curve_mm"]) + 1), 1e3 * np.array(r["curve_mm"]), color=c, alpha=0.25, lw=0.8)
        ax[0].plot([], [], color=c, label=f"{s} (median {np.median([r['n'] for r in rs]):g} placements)")
    ax[0].axhline(1e3 * target, color="k", ls="--", lw=0.8)
    ax[0].set(yscale="log", ylim=(1e3 * target / 3, 1e3 * target * 30), xlabel="placements",
              ylabel="predicted worst-point σ (µm)", title="σ over the working volume after each placement")
    ax[0].legend(fontsize=8)
    ex = [r for r in runs if not r["rendered"]]
    z = np.array([r["actual_at_worst_mm"] / r["predicted_worst_mm"] for r in ex])
    ax[1].hist(z, bins=np.linspace(0, 3.5, 15), density=True, color="0.7",
               label=f"exact observation model ({len(z)} runs)")
    t = np.linspace(0, 3.5, 200)
    ax[1].plot(t, 2 * np.exp(-0.5 * t**2) / np.sqrt(2 * np.pi), "k", lw=1, label="|N(0, 1)|: an honest σ")
    zr = [r["actual_at_worst_mm"] / r["predicted_worst_mm"] for r in runs if r["rendered"]]
    if zr:
        ax[1].plot(zr, np.full(len(zr), 0.03), "v", color="C3", label=f"full renders ({len(zr)} runs)")
    ax[1].set(xlabel="actual error / predicted σ, at the worst point, at the stop", ylabel="density",
              title="at the stop: actual error in units of the predicted σ")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def figures(runs: list[dict], target: float, n_runs: int) -> list[dict]:
    ex = [r for r in runs if not r["rendered"]]
    g = [r["n"] for r in ex if r["strategy"] == "guided"]
    rn = [r["n"] for r in ex if r["strategy"] == "random"]
    stat = (f"median over {n_runs} runs each, exact observation model, target {target:g} mm worst-point "
            "camera-frame sigma over the working volume")
    figs = [figure("plan_guided_placements", "guided placements to the target sigma", float(np.median(g)),
                   "placements", statistic=stat, reference=("random feasible placements", float(np.median(rn)),
                                                            "placements"), target=at_most(0.6, "x", of="ratio")),
            figure("plan_guided_reached", "guided runs that reached the target", 100.0 * np.mean(
                [r["reached"] for r in ex if r["strategy"] == "guided"]), "%", statistic=stat),
            figure("plan_random_reached", "random runs that reached the target within 40", 100.0 * np.mean(
                [r["reached"] for r in ex if r["strategy"] == "random"]), "%", statistic=stat)]
    stop = [r for r in ex if r["reached"]]
    figs.append(figure("plan_stop_actual_worst", "actual error at the predicted-worst point at the stop",
                       1e3 * np.sqrt(np.mean([r["actual_at_worst_mm"] ** 2 for r in stop])), "µm",
                       statistic=f"RMS over the {len(stop)} stopped runs (guided and random)",
                       reference=("predicted sigma there", 1e3 * np.sqrt(np.mean([r["predicted_worst_mm"] ** 2
                                                                                   for r in stop])), "µm"),
                       target=between(0.75, 1.25, "x", of="ratio")))
    figs.append(figure("plan_stop_actual_rms", "actual RMS error over the working volume at the stop",
                       1e3 * np.sqrt(np.mean([r["actual_rms_mm"] ** 2 for r in stop])), "µm",
                       statistic=f"RMS over the {len(stop)} stopped runs",
                       reference=("predicted RMS sigma", 1e3 * np.sqrt(np.mean([r["predicted_rms_mm"] ** 2
                                                                                 for r in stop])), "µm")))
    rendered = {s: [r for r in runs if r["rendered"] and r["strategy"] == s] for s in ("guided", "random")}
    for s, rr in rendered.items():
        if rr:
            # the guided figure against the random runs of the same renders (the bar of the exact model's runs)
            ref = dict(reference=("random feasible placements, full renders",
                                  float(np.median([r["n"] for r in rendered["random"]])), "placements"),
                       target=at_most(0.6, "x", of="ratio")) if s == "guided" and rendered["random"] else {}
            figs.append(figure(f"plan_render_{s}_placements", f"{s} placements to the target, full renders",
                               float(np.median([r["n"] for r in rr])), "placements",
                               statistic=f"median of {len(rr)} runs on realistic renders", **ref))
            figs.append(figure(f"plan_render_{s}_actual_worst", f"{s}, full renders: actual error at the "
                               "predicted-worst point", 1e3 * np.sqrt(np.mean([r["actual_at_worst_mm"] ** 2
                                                                               for r in rr])), "µm",
                               statistic=f"RMS over {len(rr)} runs",
                               reference=("predicted sigma there", 1e3 * np.sqrt(np.mean(
                                   [r["predicted_worst_mm"] ** 2 for r in rr])), "µm")))
    return figs


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=24)
    ap.add_argument("--renders", type=int, default=3)
    ap.add_argument("--target", type=float, default=0.005, help="target worst-point sigma, mm")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    ap.add_argument("--redraw", action="store_true", help="only redraw the figure from docs/figures/plan_runs.json")
    a = ap.parse_args(argv)
    if a.redraw:
        draw(json.loads((ROOT / "docs" / "figures" / "plan_runs.json").read_text()), a.target,
             ROOT / "docs" / "figures" / "plan_benchmark.png")
        return
    runs = []
    for seed in range(a.runs):
        for s in ("guided", "random"):
            runs.append(run(s, seed, a.target, False))
            r = runs[-1]
            print(f"{s:6s} seed {seed:2d}: {r['n']:2d} placements, predicted {1e3 * r['predicted_worst_mm']:.2f} µm, "
                  f"actual {1e3 * r['actual_at_worst_mm']:.2f} µm ({r['seconds']:.1f} s)", flush=True)
    for seed in range(a.renders):
        for s in ("guided", "random"):
            runs.append(run(s, 100 + seed, a.target, True))
            r = runs[-1]
            print(f"render {s:6s} seed {seed}: {r['n']:2d} placements, predicted {1e3 * r['predicted_worst_mm']:.2f} "
                  f"µm, actual {1e3 * r['actual_at_worst_mm']:.2f} µm, {r['skipped']} not found "
                  f"({r['seconds']:.1f} s)", flush=True)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (ROOT / "docs" / "figures" / "plan_runs.json").write_text(json.dumps(runs, indent=0) + "\n")
    draw(runs, a.target, ROOT / "docs" / "figures" / "plan_benchmark.png")
    record("bench_plan", figures(runs, a.target, a.runs), out)


if __name__ == "__main__":
    main()
