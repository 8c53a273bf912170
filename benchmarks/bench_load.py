"""Speed under controlled load: the same work with 0, 1 and 2 busy background processes.

A sensor PC is never idle.  This benchmark starts ``k`` = 0, 1, 2 background processes
that each keep a core busy (a Python loop, pinned to the same CPUs, killed by the
benchmark after each level and bounded by ``--busy-limit`` seconds on their own), and
times, at each level:

- ``extract_profile(frame)`` on one 1280x960 8-bit frame (the stripe of
  ``bench_stripe.frame``), default arguments: the width estimated, and the width given;
- ``measure`` (:func:`lightplane.measure.scan.measure_scan`, default workers) on a 1000-frame
  scan held in memory: 8 distinct rendered 1280x960 sphere frames
  (``bench_measure.speed_frames``) cycled (``ArrayFrames``), written to a temporary PLY;
  the figure is the time per frame;
- ``calibrate-plane`` (:func:`lightplane.plane.calibrate.calibrate_plane`, default workers,
  ``ml``) on 12 rendered realistic 1280x960 circle-target images;
- batched region-of-interest profiles: :func:`lightplane.stripe.extract.extract_profiles` on a
  stack of 1000 frames of 1280x64 (50 distinct noisy 64-row regions with a stripe near their
  middle, ``bench_stripe.roi_frame``), profiles per second.

Each is compared with the fair-share bound: a machine shared with ``k`` busy processes
owes us ``1 / (k + 1)`` of it, so a time within ``(k + 1) x`` the *idle serial* time
(one thread, measured in the same run at ``k = 0``) is a fair share.  Medians and
maxima are printed, with the numba threading layer, thread counts and the load average
(1 min) before and after, so external load on a shared machine can be seen.

``--cpus 0,1`` confines this process and the busy ones to those CPUs (set before numba
is imported, so its thread count follows), to run the 2-core case on a larger machine.

    .venv/bin/python benchmarks/bench_load.py [--cpus 0,1] [--levels 0,1,2] [--repeat 200] [--quick]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

BUSY_CODE = """
import os, sys, time
cpus = {cpus!r}
if cpus:
    os.sched_setaffinity(0, cpus)
end = time.monotonic() + {limit}
x = 0
while time.monotonic() < end:
    for _ in range(100000):
        x += 1
"""


def start_busy(k: int, cpus, limit_s: float) -> list[subprocess.Popen]:
    code = BUSY_CODE.format(cpus=sorted(cpus) if cpus else None, limit=float(limit_s))
    procs = [subprocess.Popen([sys.executable, "-c", code]) for _ in range(k)]
    time.sleep(0.5 if k else 0.0)  # let them reach the run queue
    return procs


def stop_busy(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        p.kill()
    for p in procs:
        p.wait()


def load() -> str:
    a = os.getloadavg()
    with open("/proc/loadavg") as f:
        runnable = f.read().split()[3]
    return f"load average {a[0]:.2f} / {a[1]:.2f} / {a[2]:.2f} (1/5/15 min), runnable/total {runnable}"


def samples(fn, repeat: int, warm: int = 3) -> np.ndarray:
    for _ in range(warm):
        fn()
    out = np.empty(repeat)
    for i in range(repeat):
        t0 = time.perf_counter()
        fn()
        out[i] = time.perf_counter() - t0
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cpus", default=None, help="comma-separated CPU ids to run on (e.g. 0,1)")
    ap.add_argument("--levels", default="0,1,2", help="numbers of busy background processes")
    ap.add_argument("--repeat", type=int, default=200, help="extract_profile calls per level and variant")
    ap.add_argument("--runs", type=int, default=3, help="measure / calibrate / ROI-batch runs per level")
    ap.add_argument("--frames", type=int, default=1000, help="frames of the measure scan")
    ap.add_argument("--busy-limit", type=float, default=300.0, help="seconds after which a busy process ends itself")
    ap.add_argument("--quick", action="store_true", help="fewer repeats (a smoke run)")
    args = ap.parse_args()
    cpus = None
    if args.cpus:
        cpus = {int(c) for c in args.cpus.split(",")}
        os.sched_setaffinity(0, cpus)   # before numba is imported: its thread count follows the affinity
    if args.quick:
        args.repeat, args.runs, args.frames = 30, 1, 200
    levels = [int(k) for k in args.levels.split(",")]
    if 0 not in levels:
        levels = [0] + levels
    print(f"before: {load()}")

    import cv2

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_measure import cached, speed_frames
    from bench_stripe import frame, roi_frame

    from lightplane.core import threads
    from lightplane.plane.calibrate import PlaneCalibrationOptions, calibrate_plane
    from lightplane.plane.model import LightPlane
    from lightplane.measure.scan import ArrayFrames, measure_scan
    from lightplane.simulate.render import CircleOptions, render_circle_dataset
    from lightplane.measure.options import CloudOutput
    from lightplane.stripe.extract import estimate_width, extract_profile, extract_profiles
    from lightplane.stripe.options import StripeOptions

    rng = np.random.default_rng(0)
    img = frame(rng)
    w_img = estimate_width(img, axis="columns")
    bands = [roi_frame(rng) for _ in range(50)]
    roi = np.stack([bands[i % len(bands)] for i in range(1000)])
    ds = speed_frames()
    plane = LightPlane.from_dict(ds.truth["plane"])
    scan = [ds.images[i % len(ds.images)] for i in range(args.frames)]
    circ = cached("circles12_realistic", lambda: render_circle_dataset(12, 0, CircleOptions(difficulty="realistic")))
    tmp = Path(tempfile.mkdtemp(prefix="bench_load_"))
    out_ply = tmp / "scan.ply"

    def measure(workers=None):
        t0 = time.perf_counter()
        measure_scan(ArrayFrames(scan), ds.camera, plane, out_ply, workers=workers, output=CloudOutput(force=True))
        return (time.perf_counter() - t0) / len(scan)

    def calibrate(workers=None):
        t0 = time.perf_counter()
        calibrate_plane(circ.images, circ.camera, 50.0, options=PlaneCalibrationOptions(workers=workers))
        return time.perf_counter() - t0

    def roi_rate():
        t0 = time.perf_counter()
        extract_profiles(roi, options=StripeOptions(width_px=w_img))
        return roi.shape[0] / (time.perf_counter() - t0)

    extract_profile(img)  # compile / load the kernels, start numba's threads
    extract_profiles(roi[:4], options=StripeOptions(width_px=w_img))
    print(threads.describe())
    print(f"profile frame 1280x960, stripe width {w_img:.2f} px; measure: {len(scan)} frames 1280x960 "
          f"(8 distinct sphere renders); calibrate-plane: 12 images 1280x960; ROI batch: 1000 x 1280x64")

    ref = {}
    res = {}
    for k in levels:
        print(f"-- k = {k} busy processes: {load()}", flush=True)
        procs = start_busy(k, cpus, args.busy_limit)
        try:
            r = {}
            if k == 0:   # idle serial references, same run
                ref["profile, width estimated"] = samples(lambda: extract_profile(img, parallel=False), args.repeat)
                ref["profile, width given"] = samples(
                    lambda: extract_profile(img, options=StripeOptions(width_px=w_img), parallel=False), args.repeat)
                ref["measure, per frame"] = np.array([measure(workers=1) for _ in range(args.runs)])
                ref["calibrate-plane, 12 images"] = np.array([calibrate(workers=1) for _ in range(args.runs)])
            par = []
            r["profile, width estimated"] = samples(lambda: (par.append(threads.profile_parallel(1280, 960)),
                                                             extract_profile(img)), args.repeat)
            r["profile, width given"] = samples(lambda: extract_profile(img, options=StripeOptions(width_px=w_img)),
                                                args.repeat)
            r["measure, per frame"] = np.array([measure() for _ in range(args.runs)])
            r["calibrate-plane, 12 images"] = np.array([calibrate() for _ in range(args.runs)])
            r["roi"] = np.array([roi_rate() for _ in range(max(3, args.runs))])
        finally:
            stop_busy(procs)
        res[k] = r
        print(f"   {threads.describe()}; a single 1280x960 frame took the parallel kernels in "
              f"{100.0 * np.mean(par):.0f} % of the calls")
    print(f"after: {load()}")

    print("\nidle serial references (k = 0, one thread): median / max")
    for name, v in ref.items():
        print(f"  {name:30s} {np.median(v) * 1e3:9.3f} / {np.max(v) * 1e3:9.3f} ms")
    print("\ndefault arguments under load: median / max, and median / fair-share bound (k + 1) x idle serial median "
          "(k = 0: the default against the serial reference)")
    print(f"  {'':30s} " + "  ".join(f"{'k=' + str(k):>34s}" for k in levels))
    for name in ref:
        cells = []
        for k in levels:
            v = res[k][name]
            bound = (k + 1) * float(np.median(ref[name]))
            med = float(np.median(v))
            verdict = "   " if k == 0 else ("ok " if med <= bound else "NOT")   # k = 0: default vs serial
            cells.append(f"{med * 1e3:8.3f} / {np.max(v) * 1e3:8.3f} ms {med / bound:5.2f}x {verdict}")
        print(f"  {name:30s} " + "  ".join(f"{c:>34s}" for c in cells))
    print("\nbatched ROI profiles (extract_profiles, 1000 x 1280x64 per call): median / min profiles/s "
          "(targets: 10,000 idle, 5,000 under load)")
    for k in levels:
        v = res[k]["roi"]
        tgt = 10000.0 if k == 0 else 5000.0
        print(f"  k={k}: {np.median(v):8.0f} / {np.min(v):8.0f} profiles/s  ({np.median(v) / tgt:.2f}x target)")
    from results import at_least, at_most, figure, record

    figs = []
    units = {"calibrate-plane, 12 images": "s"}
    for k in sorted({levels[0], levels[-1]}):
        for name in ref:
            u = units.get(name, "ms")
            scale = 1.0 if u == "s" else 1e3
            v = res[k][name]
            figs.append(figure(f"{name.split(',')[0].replace('-', '_')}_{name.split(', ')[1].replace(' ', '_')}_k{k}",
                               f"{name}, {k} busy processes", float(np.median(v)) * scale, u,
                               statistic=f"median of {len(v)} runs, default arguments",
                               reference=("idle serial (k = 0, 1 thread)", float(np.median(ref[name])) * scale, u),
                               target=at_most(k + 1.0, "x", of="ratio") if k else None))
    for k in levels:
        v = res[k]["roi"]
        figs.append(figure(f"roi_profiles_k{k}", f"extract_profiles 1280x64 ROIs, {k} busy processes", float(np.median(v)),
                           "profiles/s", statistic=f"median of {len(v)} calls of 1000 ROIs",
                           target=at_least(10000.0 if k == 0 else 5000.0, "profiles/s")))
    record("bench_load", figs)
    for f in tmp.iterdir():
        f.unlink()
    tmp.rmdir()
    print(f"cv2 threads at the end {cv2.getNumThreads()}")


if __name__ == "__main__":
    main()
