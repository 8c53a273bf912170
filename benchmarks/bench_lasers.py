"""Benchmark of the several-lasers calibration on two-laser circle renders.

Renders (cached under ``benchmarks/out/renders``) 12 realistic images of the default
sensor's disc with two lasers whose stripes cross on it: the default laser in the red
channel and :func:`lightplane.simulate.render.second_laser_plane` (turned 90 degrees about
the optical axis) in the green one.  Then:

- ``calibrate_planes`` with ``--laser laser0=red --laser laser1=green``: each plane against
  the exact truth (normal angle, offset at the optical axis, RMS triangulation error over
  380-520 mm, predicted sigma), the one-laser bars of bench_calibrate (0.01 deg, 0.02 mm,
  0.02 mm);
- the same placements: how far apart the two solves put each target pose;
- each laser alone, from one-channel copies of the images (``calibrate_plane`` on the red or
  the green channel as a gray image): the planes the two-laser run gives must be as good.
- time of the two-laser run against the two one-laser runs (the ellipse found once).

    .venv/bin/python benchmarks/bench_lasers.py [--seed 3] [--n 12]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from lightplane.plane.calibrate import PlaneCalibrationOptions, calibrate_plane, calibrate_planes
from lightplane.camera.model import Camera
from lightplane.cli.calibrate_plane import shared_pose_lines
from lightplane.core.io import read_image
from lightplane.stripe.lasers import parse_lasers
from lightplane.plane.model import LightPlane
from lightplane.evaluate.shapes import plane_accuracy
from results import at_most, figure, record, within

CACHE = Path(__file__).resolve().parent / "out" / "renders"
BARS = {"angle_deg": 0.01, "offset_mm": 0.02, "tri_rms_mm": 0.02}


def _render(n: int, seed: int) -> Path:
    from lightplane.simulate.render import CircleOptions, render_circle_dataset, second_laser_plane, settings_tag

    out = CACHE / f"circle2_realistic_n{n}_s{seed}_{settings_tag()}"
    if not (out / "truth.json").exists():
        print(f"rendering {out.name} ...", flush=True)
        render_circle_dataset(n, seed, CircleOptions(difficulty="realistic",
                                                    more_planes=(second_laser_plane(),))).save(out, force=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--n", type=int, default=12)
    args = ap.parse_args()
    CACHE.mkdir(parents=True, exist_ok=True)
    folder = _render(args.n, args.seed)
    truth = json.loads((folder / "truth.json").read_text())
    cam = Camera.load(folder / "camera.json")
    files = [folder / im["file"] for im in truth["images"]]
    planes = {las["name"]: LightPlane.from_dict(las["plane"]) for las in truth["lasers"]}
    sels = parse_lasers(["laser0=red", "laser1=green"])
    t = time.perf_counter()
    cals = calibrate_planes(files, cam, 50.0, sels, options=PlaneCalibrationOptions(workers=1))
    t_two = time.perf_counter() - t
    imgs = [read_image(f) for f in files]
    alone, t_alone = {}, 0.0
    for name, ch in (("laser0", 2), ("laser1", 1)):
        t = time.perf_counter()
        alone[name] = calibrate_plane([np.ascontiguousarray(im[:, :, ch]) for im in imgs], cam, 50.0,
                                      options=PlaneCalibrationOptions(workers=1))
        t_alone += time.perf_counter() - t
    print(f"{args.n} realistic two-laser renders (seed {args.seed}); angle deg, offset mm at the optical axis, "
          f"triangulation RMS mm over 380-520 mm, predicted sigma mm; bars {BARS}")
    hdr = f"{'laser':<8} {'run':<22} {'used':>5} {'angle':>8} {'offset':>8} {'tri RMS':>8} {'sigma':>8}  verdict"
    print(hdr)
    print("-" * len(hdr))
    figs = []
    for name, true in planes.items():
        for label, cal in (("two lasers, same images", cals[name]), ("alone (its channel)", alone[name])):
            acc = plane_accuracy(cal.plane, cam, true, cam)
            ok = all(abs(acc[k]) <= v for k, v in BARS.items())
            sig = acc.get("point_sigma_rms_mm")
            print(f"{name:<8} {label:<22} {cal.n_used:>2}/{len(cal.images):<2} {acc['angle_deg']:8.4f} "
                  f"{acc['offset_mm']:+8.4f} {acc['tri_rms_mm']:8.4f} {sig if sig is None else f'{sig:8.4f}'}  "
                  f"{'meets the bars' if ok else 'MISSES a bar'}")
            if cal is cals[name]:
                stat = f"{cal.n_used} of {len(cal.images)} two-laser images"
                figs += [figure(f"{name}_tri_rms", f"{name} of two, triangulation RMS", acc["tri_rms_mm"], "mm",
                                statistic=stat + ", RMS over 380-520 mm", target=at_most(BARS["tri_rms_mm"], "mm")),
                         figure(f"{name}_angle", f"{name} of two, normal angle error", acc["angle_deg"], "deg",
                                statistic=stat, target=at_most(BARS["angle_deg"], "deg")),
                         figure(f"{name}_offset", f"{name} of two, offset error at the axis", acc["offset_mm"], "mm",
                                statistic=stat, target=within(BARS["offset_mm"], "mm"))]
    for line in shared_pose_lines(cals):
        print(line)
    print(f"time, 1 worker: both lasers at once {t_two:.2f} s; each alone {t_alone:.2f} s in all "
          f"(ratio {t_two / t_alone:.2f})")
    figs.append(figure("two_lasers_time", "calibrate_planes, two lasers at once, 1 worker", t_two, "s",
                       statistic="one run", reference=("each laser alone, summed", t_alone, "s")))
    record("bench_lasers", figs)


if __name__ == "__main__":
    main()
