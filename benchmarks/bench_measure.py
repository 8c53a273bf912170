"""Measurement benchmarks: accuracy on rendered scans, throughput, peak memory of a long scan.

Run: ``.venv/bin/python benchmarks/bench_measure.py [accuracy] [speed] [profile] [memory]`` (all four
by default).  Prints medians with units and the ratio to each target:

- accuracy (renders, :func:`lightplane.simulate.render.render_scan_dataset`), with a light
  plane calibrated by :func:`lightplane.plane.calibrate.calibrate_plane` from rendered circle
  images (``render_circle_dataset(12, options=CircleOptions(difficulty="realistic"))``), not the true plane:
  sphere radius within 0.02 mm of 25.4 mm with RMS residual <= 0.02 mm; gauge step
  10.000 ± 0.02 mm; tilted plane flatness RMS <= 0.015 mm.  All targets are checked on
  ``clean`` scans; on ``realistic`` scans (laser speckle) the radius and the step are,
  while the per-point RMS and flatness are printed for information: speckle puts
  ~0.11 px on each centre, ~0.025 mm of depth at this geometry, above those two
  per-point targets (docs/conventions.md §Noise: 0.1–0.3 px per centre is physics).  The same numbers with the
  true plane are printed alongside (what the calibration costs).
- speed: >= 500 frames/s of 1280x960 8-bit frames from memory (profile + triangulation
  + placement), 2 worker processes; also one process alone.
- profile: one ``measure_profile(image, camera, plane)`` call per 1280x960 frame with
  default arguments (its cache keeps the measurer and its tables per camera, plane and
  shape), against a Gaussian blur of the frame (``cv2.GaussianBlur``, σ 2 px) measured
  interleaved in the same run: medians and ratios; also the uncached call
  (``cache=False``), and the parts (``extract_profile`` alone, the stripe-width
  estimate, one thread) that say where the time goes.
- memory: a 10,000-frame scan written to a PLY in a fresh subprocess: peak RSS of the
  main process (``resource.getrusage``) and of main + workers together (sampled from
  ``/proc``), target < 500 MB.

Renders are cached in ``$LIGHTPLANE_BENCH_CACHE`` (default: the system temp folder).
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from results import at_least, at_most, figure, record, within

#: the run's headline figures (benchmarks/results/bench_measure.json)
FIGURES: list[dict] = []

CACHE = Path(os.environ.get("LIGHTPLANE_BENCH_CACHE", tempfile.gettempdir())) / "lightplane_bench_measure"
SCANS = {"sphere": dict(n_frames=21, step_mm=3.0), "step": dict(n_frames=11, step_mm=4.0),
         "plane": dict(n_frames=11, step_mm=4.0)}


def _code_tag() -> str:
    """Short hash of the package's sources: a pickled data set holds the package's own
    objects (Camera, LightPlane), so a cache written by other code is not reused."""
    import hashlib

    import lightplane

    h = hashlib.sha1()
    for f in sorted(Path(lightplane.__file__).parent.rglob("*.py")):
        h.update(f.read_bytes())
    return h.hexdigest()[:10]


def cache_file(name: str) -> Path:
    """The cache file of a rendered data set, named with the renderer's settings tag and the
    code's hash (stale ones are not reused)."""
    from lightplane.simulate.render import settings_tag

    return CACHE / f"{name}_{settings_tag()}_{_code_tag()}.pkl"


def cached(name: str, make):
    CACHE.mkdir(parents=True, exist_ok=True)
    f = cache_file(name)
    if f.exists():
        with open(f, "rb") as fh:
            return pickle.load(fh)
    obj = make()
    with open(f, "wb") as fh:
        pickle.dump(obj, fh)
    return obj


# ----------------------------------------------------------------------------- fits
def fit_sphere(p: np.ndarray, iters: int = 5) -> tuple[np.ndarray, float, np.ndarray]:
    """Least-squares sphere (centre, radius) with 4-MAD outlier rejection; returns the inlier mask."""
    from scipy.optimize import least_squares

    keep = np.ones(len(p), bool)
    c, r = p.mean(axis=0), 25.0
    for _ in range(iters):
        q = p[keep]
        A = np.column_stack([2 * q, np.ones(len(q))])  # algebraic start
        sol = np.linalg.lstsq(A, np.sum(q * q, axis=1), rcond=None)[0]
        c0, r0 = sol[:3], np.sqrt(sol[3] + sol[:3] @ sol[:3])
        res = least_squares(lambda x: np.linalg.norm(q - x[:3], axis=1) - x[3], np.append(c0, r0))
        c, r = res.x[:3], res.x[3]
        e = np.linalg.norm(p - c, axis=1) - r
        mad = 1.4826 * np.median(np.abs(e[keep]))
        new = np.abs(e) < 4 * mad
        if np.array_equal(new, keep):
            break
        keep = new
    return c, float(r), keep


def fit_plane(p: np.ndarray, iters: int = 5) -> tuple[np.ndarray, float, np.ndarray]:
    """Total-least-squares plane (n, d) with 4-MAD outlier rejection; returns the inlier mask."""
    keep = np.ones(len(p), bool)
    for _ in range(iters):
        q = p[keep]
        m = q.mean(axis=0)
        n = np.linalg.svd(q - m, full_matrices=False)[2][2]
        d = -n @ m
        e = p @ n + d
        mad = 1.4826 * np.median(np.abs(e[keep]))
        new = np.abs(e) < 4 * mad
        if np.array_equal(new, keep):
            break
        keep = new
    return n, float(d), keep


def xyz(rec) -> np.ndarray:
    return np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(np.float64)


# ----------------------------------------------------------------------------- accuracy
def calibrated_plane():
    from lightplane.plane.calibrate import calibrate_plane
    from lightplane.simulate.render import CircleOptions, render_circle_dataset

    ds = cached("circles12_realistic", lambda: render_circle_dataset(12, 0, CircleOptions(difficulty="realistic")))
    t = time.perf_counter()
    cal = calibrate_plane(ds.images, ds.camera, 50.0, method="ml")
    print(f"calibrate_plane (ml) on 12 rendered circle images: {time.perf_counter() - t:.1f} s, "
          f"{sum(1 for p in cal.placements if getattr(p, 'used', True))} placements")
    return cal.plane


def scan(kind: str, plane, ds, options=None):
    from lightplane.measure.options import MeasureOptions
    from lightplane.measure.scan import ArrayFrames, Motion, scan_points

    mo = ds.truth["motion"]
    rec, summ = scan_points(ArrayFrames(ds.images), ds.camera, plane, options or MeasureOptions(),
                            motion=Motion.linear(mo["step_mm"], mo["direction"]), workers=1)
    # the static table (z = 600 mm in the camera frame) is not the object: drop it by its camera-frame depth
    zc = xyz(rec) + np.array(mo["direction"])[None, :] * mo["step_mm"] * rec["frame"][:, None].astype(float)
    obj = zc[:, 2] < 560.0
    return xyz(rec)[obj], summ


def accuracy() -> None:
    from lightplane.measure.options import MeasureOptions

    planes = {}
    try:
        planes["calibrated"] = calibrated_plane()
    except ImportError as e:
        print(f"calibrate_plane unavailable ({e}): using the true plane only")
    print("== clean scans (no speckle, low noise): every target applies ==")
    accuracy_scans("clean", planes)
    print("== realistic scans (laser speckle 25 %, ~0.11 px per centre): the radius and step targets apply; "
          "the per-point RMS and flatness are set by speckle (docs/conventions.md §Noise: 0.1-0.3 px per centre is physics; "
          "~0.23 mm of depth per px here), printed for information ==")
    accuracy_scans("realistic", planes)
    print("== the realistic scans with the centres smoothed along the stripe (measure --smooth 9; info) ==")
    accuracy_scans("realistic", planes, MeasureOptions(smooth_lines=9))


def accuracy_scans(difficulty: str, planes: dict, options=None) -> None:
    from dataclasses import replace

    from lightplane.measure.options import MeasureOptions
    from lightplane.plane.model import LightPlane

    default_run = options is None  # the headline figures: the calibrated plane with measure's defaults
    options = options or MeasureOptions()
    from lightplane.simulate.render import render_scan_dataset

    planes = dict(planes)
    for kind, kw in SCANS.items():
        suffix = "" if difficulty == "realistic" else f"_{difficulty}"
        ds = cached(f"scan_{kind}_{kw['n_frames']}_{kw['step_mm']}{suffix}",
                    lambda: render_scan_dataset(kind, seed=0, difficulty=difficulty, **kw))
        planes.setdefault("true", LightPlane.from_dict(ds.truth["plane"]))
        tp = LightPlane.from_dict(ds.truth["plane"])
        if "calibrated" in planes:
            print(f"[{kind}] calibrated plane vs truth: {np.degrees(planes['calibrated'].angle_to(tp)):.4f} deg, "
                  f"d {planes['calibrated'].d - tp.d:+.4f} mm")
        surf = ds.truth["frames"][0]["surfaces"]
        for label in ("calibrated", "true"):
            if label not in planes:
                continue
            p, summ = scan(kind, planes[label] if label == "calibrated" else tp, ds, options)
            if label == "true":  # what the per-point stripe-width filter (ProfileMeasurer's default) drops
                p_all, _ = scan(kind, tp, ds, replace(options, min_width_ratio=0.0, max_width_ratio=np.inf))
                print(f"  {kind:6s} width filter dropped {len(p_all) - len(p)} of {len(p_all)} object points "
                      f"({100 * (len(p_all) - len(p)) / max(len(p_all), 1):.1f} %)", end="")
                if kind == "sphere":
                    print(f"; without it: radius error {fit_sphere(p_all)[1] - 25.4:+.4f} mm", end="")
                print()
            headline = label == "calibrated" and default_run
            if kind == "sphere":
                c, r, keep = fit_sphere(p)
                e = np.linalg.norm(p[keep] - c, axis=1) - r
                rms = float(np.sqrt(np.mean(e**2)))
                if headline:
                    FIGURES.append(figure(f"sphere_radius_{difficulty}", f"sphere radius, {difficulty} scan", r, "mm",
                                          truth=25.4, target=within(0.02, "mm", of="error"),
                                          statistic=f"fit to {keep.sum()} points, calibrated plane"))
                    FIGURES.append(figure(f"sphere_rms_residual_{difficulty}", f"sphere RMS residual, {difficulty} scan",
                                          rms, "mm", target=at_most(0.02, "mm") if difficulty == "clean" else None,
                                          statistic=f"RMS over {keep.sum()} points, calibrated plane"))
                print(f"  sphere [{label:10s}] {keep.sum()} points ({(~keep).sum()} rejected): radius {r:.4f} mm "
                      f"(error {r - 25.4:+.4f}, target |err| <= 0.02: {abs(r - 25.4) / 0.02:.2f}x), "
                      f"RMS residual {rms:.4f} mm (target <= 0.02: {rms / 0.02:.2f}x), centre error "
                      f"{np.linalg.norm(c - np.asarray(surf['sphere']['center_mm'])):.4f} mm")
            elif kind == "step":
                n_true = np.asarray(surf["base"]["normal"], float)
                db, dt = surf["base"]["d"], surf["top"]["d"]
                on_b = np.abs(p @ n_true + db) < 1.0  # segmentation only: faces 10 mm apart
                on_t = np.abs(p @ n_true + dt) < 1.0
                nb, dbf, kb = fit_plane(p[on_b])
                nt, dtf, kt = fit_plane(p[on_t])
                # common normal from both faces (each centred on itself), then the two offsets along it
                qb, qt = p[on_b][kb], p[on_t][kt]
                n = np.linalg.svd(np.vstack([qb - qb.mean(0), qt - qt.mean(0)]), full_matrices=False)[2][2]
                sep = abs(float(n @ (qb.mean(0) - qt.mean(0))))
                par = np.degrees(np.arccos(min(1.0, abs(nb @ nt))))
                if headline:
                    FIGURES.append(figure(f"gauge_step_{difficulty}", f"gauge step, {difficulty} scan", sep, "mm",
                                          truth=10.0, target=within(0.02, "mm", of="error"),
                                          statistic=f"fit to {kb.sum() + kt.sum()} points, calibrated plane"))
                print(f"  step   [{label:10s}] base {kb.sum()} / top {kt.sum()} points: separation {sep:.4f} mm "
                      f"(error {sep - 10.0:+.4f}, target |err| <= 0.02: {abs(sep - 10) / 0.02:.2f}x), faces parallel "
                      f"to {par:.3f} deg")
            else:
                n, d, keep = fit_plane(p)
                e = p[keep] @ n + d
                rms = float(np.sqrt(np.mean(e**2)))
                if headline:
                    FIGURES.append(figure(f"plane_flatness_{difficulty}", f"plane flatness RMS, {difficulty} scan", rms,
                                          "mm", target=at_most(0.015, "mm") if difficulty == "clean" else None,
                                          statistic=f"RMS over {keep.sum()} points, calibrated plane"))
                print(f"  plane  [{label:10s}] {keep.sum()} points ({(~keep).sum()} rejected): flatness RMS "
                      f"{rms:.4f} mm (target <= 0.015: {rms / 0.015:.2f}x)")


# ----------------------------------------------------------------------------- speed
def speed_frames(n_distinct: int = 8):
    from lightplane.simulate.render import render_scan_dataset

    ds = cached(f"speed_sphere_{n_distinct}", lambda: render_scan_dataset("sphere", n_frames=n_distinct, step_mm=5.0, seed=1))
    return ds


def speed(n_frames: int = 1200, repeats: int = 3) -> None:
    from lightplane.plane.model import LightPlane
    from lightplane.measure.scan import ArrayFrames, FrameProcessor, Motion, iter_scan
    from lightplane.measure.options import MeasureOptions
    from lightplane.stripe.extract import estimate_width
    from lightplane.stripe.options import StripeOptions

    print("== speed (1280x960 uint8 frames from memory; profile + triangulation + placement) ==")
    ds = speed_frames()
    plane = LightPlane.from_dict(ds.truth["plane"])
    width = estimate_width(ds.images[0], axis="rows")
    frames = [ds.images[i % len(ds.images)] for i in range(n_frames)]
    t = time.perf_counter()
    proc = FrameProcessor(ds.camera, plane, Motion.linear(0.1, [1, 0, 0]),
                          MeasureOptions(StripeOptions(width_px=width)))
    proc.measurer.build_lookup()
    print(f"lookup tables: {time.perf_counter() - t:.2f} s (once per scan)")
    for workers in (1, 2):
        n = n_frames if workers > 1 else n_frames // 4
        rates = []
        for _ in range(repeats):
            t = time.perf_counter()
            count = 0
            started = None
            for r in iter_scan(ArrayFrames(frames[:n]), proc, workers=workers):
                count += 1
                if started is None:
                    started = time.perf_counter()  # exclude pool start-up (once per scan)
            rates.append((count - 1) / (time.perf_counter() - started))
        med = float(np.median(rates))
        print(f"workers={workers}: median {med:.0f} frames/s over {repeats} runs of {n} frames "
              f"({', '.join(f'{x:.0f}' for x in rates)}); {1e3 / med:.2f} ms/frame; target 500 frames/s on 2 cores: "
              f"{med / 500:.2f}x" + ("" if workers > 1 else " (one core)"))
        FIGURES.append(figure(f"measure_speed_{workers}_workers", f"measure from memory, {workers} worker"
                              + ("s" if workers > 1 else ""), med, "frames/s",
                              statistic=f"median of {repeats} runs of {n} frames",
                              target=at_least(500.0, "frames/s") if workers > 1 else None))


def profile_speed(repeats: int = 15) -> None:
    import cv2

    from lightplane.measure.profile import clear_profile_cache, measure_profile
    from lightplane.plane.triangulate import profile_axis
    from lightplane.plane.model import LightPlane
    from lightplane.measure.options import MeasureOptions
    from lightplane.stripe.extract import estimate_width, extract_profile
    from lightplane.stripe.options import StripeOptions

    ds = speed_frames()
    cam, plane = ds.camera, LightPlane.from_dict(ds.truth["plane"])
    axis = profile_axis(plane)
    frames = ds.images
    h, w = frames[0].shape[:2]
    width = estimate_width(frames[0], axis=axis)
    extract_profile(frames[0], axis)  # numba's kernels loaded: not part of the first call's figure
    clear_profile_cache()
    t = time.perf_counter()
    measure_profile(frames[0], cam, plane)
    first = 1e3 * (time.perf_counter() - t)
    runs = {
        "blur": lambda im: cv2.GaussianBlur(im, (0, 0), 2.0),
        "measure_profile": lambda im: measure_profile(im, cam, plane),
        "measure_profile cache=False": lambda im: measure_profile(im, cam, plane, cache=False),
        "extract_profile": lambda im: extract_profile(im, axis),
        "estimate_width": lambda im: estimate_width(im, axis=axis),
        "measure_profile width_px, 1 thread": lambda im: measure_profile(
            im, cam, plane, MeasureOptions(StripeOptions(width_px=width), parallel=False)),
    }
    for f in runs.values():
        f(frames[0])
    times = {k: [] for k in runs}
    for _ in range(repeats):
        for im in frames:
            for k, f in runs.items():  # interleaved: the same load on each
                t = time.perf_counter()
                f(im)
                times[k].append(1e3 * (time.perf_counter() - t))
    ref = float(np.median(times["blur"]))
    print(f"== measure_profile per frame ({w}x{h} uint8, {len(frames)} frames x {repeats}, interleaved; wall-clock "
          f"medians; reference: cv2.GaussianBlur sigma 2 of the frame) ==")
    print(f"first call (measurer and the table blocks the stripe needs): {first:.1f} ms; load average "
          f"{os.getloadavg()[0]:.1f}")
    for k, v in times.items():
        med = float(np.median(v))
        print(f"  {k:36s} {med:7.2f} ms (p10 {np.percentile(v, 10):6.2f}, p90 {np.percentile(v, 90):6.2f}); "
              f"ratio to the blur {med / ref:.1f}")
    stat = f"median of {repeats * len(frames)} runs, interleaved"
    for k, fid in (("measure_profile", "measure_profile"), ("measure_profile cache=False", "measure_profile_uncached")):
        FIGURES.append(figure(fid, f"{k}, 1280x960 frame", float(np.median(times[k])), "ms", statistic=stat,
                              reference=("cv2.GaussianBlur sigma 2", ref, "ms")))


# ----------------------------------------------------------------------------- memory
MEMORY_CHILD = r"""
import os, resource, sys, threading, time, numpy as np, pickle
from lightplane.plane.model import LightPlane
from lightplane.measure.options import CloudOutput
from lightplane.measure.scan import FrameSource, Motion, measure_scan

def rss_mb(pid, key="VmRSS:"):
    try:
        for line in open(f"/proc/{pid}/status"):
            if line.startswith(key):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0

def children():
    out = []
    for tid in os.listdir("/proc/self/task"):
        try:
            out += [int(x) for x in open(f"/proc/self/task/{tid}/children").read().split()]
        except OSError:
            pass
    return out

peak = {"total": 0.0}
hwm = {}  # worker pid -> its latest VmHWM (after exec: its own peak, not the forked parent's)
stop = False
def sample():
    while not stop:
        kids = children()
        peak["total"] = max(peak["total"], rss_mb(os.getpid()) + sum(rss_mb(c) for c in kids))
        for c in kids:
            v = rss_mb(c, "VmHWM:")
            if v > 0:
                hwm[c] = v
        time.sleep(0.1)
threading.Thread(target=sample, daemon=True).start()

ds = pickle.load(open(sys.argv[1], "rb"))
N = int(sys.argv[3])
class Cycle(FrameSource):
    n_frames = N
    description = f"{N} frames cycled from memory"
    def items(self):
        for i in range(N):
            yield i, f"frame {i}", ds.images[i % len(ds.images)]
t = time.perf_counter()
s = measure_scan(Cycle(), ds.camera, LightPlane.from_dict(ds.truth["plane"]), sys.argv[2],
                 motion=Motion.linear(0.1, [1, 0, 0]), workers=2, output=CloudOutput(force=True))
dt = time.perf_counter() - t
stop = True
time.sleep(0.2)
me = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
workers = sorted(hwm.values())[-2:]  # pool worker processes, if any (none when threads are used)
print(f"{s.n_frames} {s.n_points} {dt:.1f} {me:.0f} {max(workers, default=0):.0f} {me + sum(workers):.0f} {peak['total']:.0f}")
"""


def memory(n_frames: int = 10_000) -> None:
    from lightplane.measure.scan import kernels_release_gil

    how = "2 worker threads in one process" if kernels_release_gil() else "2 worker processes"
    print(f"== memory ({n_frames}-frame scan to binary PLY, {how}, fresh subprocess) ==")
    speed_frames()
    src = cache_file("speed_sphere_8")
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "cloud.ply"
        r = subprocess.run([sys.executable, "-c", MEMORY_CHILD, str(src), str(out), str(n_frames)],
                           capture_output=True, text=True, timeout=900)
        if r.returncode != 0:
            print(r.stderr)
            raise SystemExit(1)
        n, pts, dt, me, wk, tot, sampled = r.stdout.split()[-7:]
        size = out.stat().st_size / 2**20
    print(f"{n} frames, {pts} points ({size:.0f} MB PLY) in {float(dt):.1f} s ({int(n) / float(dt):.0f} frames/s incl. "
          f"writing); peak RSS: main process {float(me):.0f} MB (getrusage; target < 500 MB: {float(me) / 500:.2f}x), "
          f"worker process peak {float(wk):.0f} MB (VmHWM; 0: threads), main + workers {float(tot):.0f} MB ({float(tot) / 500:.2f}x of "
          f"500 MB; largest simultaneous sum sampled every 0.1 s: {float(sampled):.0f} MB; shared pages count in each)")
    stat = f"peak over a {n}-frame scan"
    FIGURES.append(figure("memory_peak_main", "peak RSS, main process, long scan", float(me), "MB", statistic=stat,
                          target=at_most(500.0, "MB")))
    FIGURES.append(figure("memory_peak_total", "peak RSS, main + workers, long scan", float(tot), "MB",
                          statistic=stat, target=at_most(500.0, "MB")))


def main(argv: list[str]) -> None:
    parts = argv or ["accuracy", "speed", "profile", "memory"]
    from lightplane.core.threads import describe

    print(f"machine: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f} (timings on a shared machine are noisy)")
    print(describe())
    for p in parts:
        {"accuracy": accuracy, "speed": speed, "profile": profile_speed, "memory": memory}[p]()
    record("bench_measure", FIGURES)


if __name__ == "__main__":
    main(sys.argv[1:])
