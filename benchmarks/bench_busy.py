"""Speed of the profile extractor on busy frames: speckle, texture, clutter, a second line, hot spots.

The speed figures of ``bench_stripe.py`` are measured on a clean stripe; users' frames hold
texture, clutter and speckle.  This benchmark builds a set of busy 1280x960 8-bit frames and
times, on each, against ``cv2.GaussianBlur`` of the same frame in the same round (interleaved;
medians over rounds, then the median over the set), each call with its benchmark's reference
(σ 1.44 px for ``extract_profile`` as in ``bench_stripe.py``, σ 2 px for ``measure_profile`` as in
``bench_measure.py``):

- ``extract_profile`` with default options (width estimated), the axis across the stripe;
- ``measure_profile`` (default arguments: axis from the plane, width estimated) on the rendered
  frames, with their camera and light plane;
- where the time of ``extract_profile`` goes, stage by stage (one thread): the sample-major
  array, the width estimate, the candidate search, the choice between candidates
  (``continuity``), the centres, the image coordinates;
- batched 1280x64 regions of interest (``extract_profiles``, 1000 a call, 50 distinct busy
  regions: a curved stripe with speckle on a textured 20 grey-level background, clutter edges,
  a weaker second line or hot spots in some): profiles/s with 0 and 2 busy background
  processes (``bench_load.start_busy``), width given as ``bench_load`` does.

The set (rendered with :mod:`lightplane.simulate`, cached like ``bench_measure.py``'s renders):
circle-target frames of the ``hard`` difficulty (laser speckle, vignetting, clutter; every
other one with a 3.5x too bright, partly saturated stripe), light and dark targets, and these
variants of each: as rendered; a textured scene (an albedo texture of fine grain and coarse
blotches multiplies the whole frame, stripe included); texture and clutter (high-contrast
bright and dark rectangles and bars); texture and a second, weaker line (0.4 of the stripe's
peak); texture and saturated hot spots (specular blobs clipped at 255); dark and bright objects
(the stripe dims to 0.3 on one, the background rises to ~150 grey levels on the other).  The
real photographs of ``shared/data`` are added where there (Ciclop: the bust and the chessboard
frames; FabScan: three frames of a scan), gray, default options.

Run: ``.venv/bin/python benchmarks/bench_busy.py [--rounds 7] [--cpus 0,1] [--no-load]``.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
BLUR_SIGMA_PX = 1.44          # bench_stripe.py's reference for extract_profile
MEASURE_BLUR_SIGMA_PX = 2.0   # bench_measure.py's reference for measure_profile
ROI_SHAPE = (64, 1280)


# ----------------------------------------------------------------------------- the frames
def texture(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    """An albedo map around 1 (σ 0.3, clipped to 0.3 .. 2.0): fine grain (1 px), small (4 px), medium (16 px) and
    coarse (64 px) value noise."""
    import cv2

    H, W = shape
    t = np.zeros(shape, np.float32)
    for scale, amp in ((1, 0.2), (4, 0.25), (16, 0.3), (64, 0.3)):
        n = rng.normal(0.0, 1.0, (H // scale + 2, W // scale + 2)).astype(np.float32)
        if scale > 1:
            n = cv2.resize(n, (W // scale * scale + 2 * scale, H // scale * scale + 2 * scale),
                           interpolation=cv2.INTER_CUBIC)
        t += amp * n[:H, :W]
    return np.clip(1.0 + 0.3 * t / t.std(), 0.3, 2.0)


def clutter(rng: np.random.Generator, img: np.ndarray, n: int = 10) -> np.ndarray:
    """``img`` with ``n`` sharp-edged bright and dark rectangles and bars (albedo 0.3 .. 2.5)."""
    import cv2

    out = img.copy()
    H, W = img.shape
    for _ in range(n):
        c = rng.uniform([0, 0], [W, H])
        size = rng.uniform(6, 160, 2) if rng.random() < 0.6 else np.array([rng.uniform(3, 8), rng.uniform(80, 400)])
        box = cv2.boxPoints(((float(c[0]), float(c[1])), (float(size[0]), float(size[1])), float(rng.uniform(0, 180))))
        mask = np.zeros((H, W), np.uint8)
        cv2.fillConvexPoly(mask, np.round(box).astype(np.int32), 1)
        out[mask > 0] *= rng.choice([rng.uniform(0.3, 0.6), rng.uniform(1.6, 2.5)])
    return out


def stripe_line(shape, rng, amp: float, width_px: float = 5.5) -> np.ndarray:
    """A roughly vertical Gaussian line (FWHM ``width_px``) of peak ``amp`` at a random column."""
    H, W = shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    u0 = rng.uniform(0.2 * W, 0.8 * W)
    centre = u0 + rng.uniform(-0.15, 0.15) * (v - H / 2) + rng.uniform(-30, 30) * np.sin(v / H * np.pi)
    return amp * np.exp(-0.5 * ((u - centre) / (width_px / 2.3548)) ** 2)


def hot_spots(rng: np.random.Generator, shape, n: int = 6) -> np.ndarray:
    """``n`` specular blobs (σ 3 .. 15 px) of 300 .. 900 grey levels (saturate when added)."""
    H, W = shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    out = np.zeros(shape, np.float32)
    for _ in range(n):
        c = rng.uniform([0, 0], [W, H])
        s = rng.uniform(3, 15)
        out += rng.uniform(300, 900) * np.exp(-0.5 * ((u - c[0]) ** 2 + (v - c[1]) ** 2) / s**2)
    return out


def objects(rng: np.random.Generator, img: np.ndarray) -> np.ndarray:
    """A dark object (albedo 0.3) over the left half's middle, a bright one (the background to ~150
    grey levels) over the right half's."""
    out = img.copy()
    H, W = img.shape
    y0 = int(rng.uniform(0.1, 0.4) * H)
    out[y0:y0 + H // 3, : W // 2] *= 0.3
    y1 = int(rng.uniform(0.4, 0.6) * H)
    region = out[y1:y1 + H // 3, W // 2:]
    region += 150.0 - np.median(region)
    return out


def busy_variants(base: np.ndarray, seed: int) -> dict[str, np.ndarray]:
    """The variants of one rendered frame (see the module doc), 8-bit, with 2 grey levels of noise
    added after each change."""
    rng = np.random.default_rng(seed)
    img = base.astype(np.float32)
    tex = img * texture(rng, img.shape)
    out = {"texture": tex, "texture+clutter": clutter(rng, tex),
           "texture+second line": tex + stripe_line(img.shape, rng, 0.4 * float(np.percentile(base, 99.95))),
           "texture+hot spots": tex + hot_spots(rng, img.shape), "dark and bright objects": objects(rng, img)}
    return {"rendered": base} | {k: np.clip(np.round(v + rng.normal(0.0, 2.0, v.shape)), 0, 255).astype(np.uint8)
                                 for k, v in out.items()}


def rendered_sets():
    """Circle-target data sets (``hard``: speckle, clutter, a saturated stripe in every other image),
    light and dark targets, two images each; cached."""
    from bench_measure import cached

    from lightplane.simulate.render import CircleOptions, render_circle_dataset

    return [(pol, cached(f"busy_circles_{pol}", lambda pol=pol: render_circle_dataset(
        2, 3 if pol == "light" else 4, CircleOptions(difficulty="hard", polarity=pol)))) for pol in ("light", "dark")]


def real_frames() -> list[tuple[str, np.ndarray, str]]:
    """(name, gray frame, axis) of the shared real photographs that are there."""
    from lightplane.core.io import read_image, to_gray_float

    out = []
    cic = SHARED / "ciclop"
    for rel in ("laser_segmentation_object/laser.png", "laser_segmentation_in_pattern/laser-0-255-255-8-x.png"):
        if (cic / rel).is_file():
            out.append((f"Ciclop {Path(rel).stem}", read_image(cic / rel), "rows"))
    fab = SHARED / "fabscan" / "1_1"
    for k in (10, 30, 60):
        f = fab / f"20210213-230202_{k:03d}.jpg"
        if f.is_file():
            out.append((f"FabScan 1_1 frame {k}", read_image(f), "columns"))
    return [(n, np.ascontiguousarray(to_gray_float(im, None, native=True)), ax) if im.ndim == 3 else (n, im, ax)
            for n, im, ax in out]


def busy_frames():
    """The busy set: (name, frame, axis, camera or None, plane or None)."""
    from lightplane.plane.model import LightPlane

    out = []
    for pol, ds in rendered_sets():
        plane = LightPlane.from_dict(ds.truth["plane"])
        for i, base in enumerate(ds.images):
            for kind, img in busy_variants(base, 100 * i + (pol == "dark")).items():
                out.append((f"{pol} target {i}, {kind}", img, "rows", ds.camera, plane))
    out += [(n, im, ax, None, None) for n, im, ax in real_frames()]
    return out


def roi_frame(rng: np.random.Generator, k: int) -> np.ndarray:
    """A busy 1280x64 region of interest: a curved, speckled stripe (FWHM 5 px, peak 120 .. 200)
    near the middle row on a textured 20 grey-level background, sharp clutter edges; every
    third with a weaker second line (0.4), every fifth with hot spots; 2 grey levels of noise."""
    H, W = ROI_SHAPE
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    centre = 0.5 * H + rng.uniform(-4, 4) + 0.004 * (u - W / 2) + 6.0 * np.sin(u / W * np.pi) - 3.0
    speckle = np.clip(1.0 + 0.3 * np.repeat(rng.normal(0, 1, W // 2 + 1), 2)[:W], 0.2, None)
    img = 20.0 + rng.uniform(120, 200) * speckle * np.exp(-0.5 * ((v - centre) / (5.0 / 2.3548)) ** 2)
    img = clutter(rng, img * texture(rng, (H, W)), n=6)
    if k % 3 == 0:
        img += 0.4 * 160 * np.exp(-0.5 * ((v - centre - rng.choice([-18, 18])) / 2.0) ** 2)
    if k % 5 == 0:
        img += hot_spots(rng, (H, W), n=3)
    return np.clip(np.round(img + rng.normal(0, 2.0, (H, W))), 0, 255).astype(np.uint8)


# ----------------------------------------------------------------------------- timing
#: the clock of :func:`interleaved`: wall time, or with ``--cpu-time`` this thread's CPU time
CLOCK = time.perf_counter


def interleaved(fns: dict, rounds: int) -> dict[str, float]:
    """Median seconds (:data:`CLOCK`) of each callable over ``rounds`` rounds, each round calling
    all of them in turn (order reversed every other round)."""
    keys = list(fns)
    for k in keys:
        fns[k]()
    t: dict[str, list[float]] = {k: [] for k in keys}
    for r in range(rounds):
        for k in (keys if r % 2 == 0 else keys[::-1]):
            t0 = CLOCK()
            fns[k]()
            t[k].append(CLOCK() - t0)
    return {k: float(np.median(v)) for k, v in t.items()}


def stages(img: np.ndarray, axis: str, rounds: int) -> dict[str, float]:
    """Seconds of each stage of ``extract_profile(img, axis)`` on one thread (medians over
    ``rounds``); the stage functions are the extractor's own, called one by one."""
    from lightplane.stripe import extract as X
    from lightplane.stripe import kernels as K
    from lightplane.stripe.options import StripeOptions

    opts = StripeOptions()
    gray, _ = X.channel_image(img, None)
    A, setup = X._profile_setup(img, axis, opts, None, parallel=False)
    p = setup["params"]
    w0, w1, w2 = setup["w0"], setup["w1"], setup["w2"]
    S, L = A.shape
    cand = [np.empty(L, np.int64), np.empty(L), np.empty(L, np.int64), np.empty(L)]
    K._candidates_chunk(A, p["sep"], cand[0], cand[1], cand[2], cand[3], np.int64(0), L)
    pos = K.choose_consistent(A, cand[0], cand[1], cand[2], cand[3], p["min_peak"], 5, p["tol"])
    out = [np.empty(L), np.empty((L, 2)), np.empty(L), np.empty(L), np.empty(L), np.empty(L, np.uint8)]
    raw = tuple(out)

    def centres():
        K._centres_range(A, pos, w0, w1, w2, p["xw"], p["qpeak"], p["half"], p["min_peak"], p["max_width"],
                         p["min_cos"], *out, np.int64(0), L)

    centres()
    fns = {
        "sample-major array": lambda: X._lines_array(gray, axis, None),
        "width estimate": lambda: X._profile_setup(img, axis, opts, None, parallel=False),
        "candidates": lambda: K._candidates_chunk(A, p["sep"], cand[0], cand[1], cand[2], cand[3], np.int64(0), L),
        "continuity choice": lambda: K.choose_consistent(A, cand[0], cand[1], cand[2], cand[3], p["min_peak"], 5,
                                                         p["tol"]),
        "centres": centres,
        "image coordinates": lambda: X._profile_finish(img, axis, raw, setup, opts),
        "whole (1 thread)": lambda: X.extract_profile(img, axis, parallel=False),
    }
    t = interleaved(fns, rounds)
    # the width estimate is the part of _profile_setup beyond the array it also makes
    t["width estimate"] = max(0.0, t["width estimate"] - t["sample-major array"])
    return t


def roi_stack(n: int = 1000, distinct: int = 50) -> np.ndarray:
    rng = np.random.default_rng(7)
    rois = [roi_frame(rng, k) for k in range(distinct)]
    return np.stack([rois[i % distinct] for i in range(n)])


def clean_roi_stack(n: int = 1000, distinct: int = 50) -> np.ndarray:
    """``bench_stripe.py``'s clean regions of interest (``bench_stripe.roi_frame``), as many."""
    from bench_stripe import roi_frame as clean_roi

    rng = np.random.default_rng(0)
    rois = [clean_roi(rng) for _ in range(distinct)]
    return np.stack([rois[i % distinct] for i in range(n)])


def roi_rates(stacks: dict[str, np.ndarray], runs: int, levels=(0, 2), cpus=None) -> dict[tuple[str, int], float]:
    """Median profiles/s of ``extract_profiles`` on each stack with ``k`` busy processes (the stacks
    interleaved within each level); ``CLOCK`` is :func:`time.thread_time`: one thread, profiles per
    CPU second."""
    from bench_load import start_busy, stop_busy

    from lightplane.stripe.extract import estimate_width, extract_profiles
    from lightplane.stripe.options import StripeOptions

    opts = {name: StripeOptions(width_px=estimate_width(roi[0], axis="columns")) for name, roi in stacks.items()}
    out = {}
    for k in levels:
        procs = start_busy(k, cpus, 120.0)
        try:
            t = interleaved({name: (lambda roi=roi, o=opts[name]: extract_profiles(roi, options=o))
                             for name, roi in stacks.items()}, runs)
        finally:
            stop_busy(procs)
        for name, roi in stacks.items():
            out[(name, k)] = roi.shape[0] / t[name]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=7, help="interleaved rounds per frame (medians)")
    ap.add_argument("--cpus", default=None, help="comma-separated CPU ids to run on (e.g. 0,1)")
    ap.add_argument("--no-load", action="store_true", help="skip the ROI batch with busy processes")
    ap.add_argument("--no-stages", action="store_true", help="skip the stage breakdown")
    ap.add_argument("--cpu-time", action="store_true",
                    help="time the frames by this thread's CPU time, everything on one thread (extractor, "
                         "measure, blur): ratios that hold on a machine shared with other processes")
    args = ap.parse_args()
    cpus = {int(c) for c in args.cpus.split(",")} if args.cpus else None
    if cpus:
        os.sched_setaffinity(0, cpus)   # before numba starts its threads

    import cv2

    from lightplane.core.threads import describe, serial_kernels
    from lightplane.measure.profile import measure_profile
    from lightplane.stripe.extract import extract_profile
    from results import at_least, at_most, figure, record

    global CLOCK
    frames = busy_frames()
    extract_profile(frames[0][1], frames[0][2])
    serial = contextlib.nullcontext
    if args.cpu_time:
        CLOCK = time.thread_time
        cv2.setNumThreads(1)
        serial = serial_kernels
    print(f"cpus {os.cpu_count()}, load average {os.getloadavg()[0]:.1f}; {describe()}")
    print(f"{len(frames)} frames; per frame medians of {args.rounds} interleaved rounds, ratios to cv2.GaussianBlur "
          f"of the same frame (σ {BLUR_SIGMA_PX} px for extract_profile, {MEASURE_BLUR_SIGMA_PX} px for measure_profile)")
    print(f"{'frame':44s} {'blur ms':>8s} {'profile ms':>10s} {'ratio':>6s} {'measure ms':>10s} {'ratio':>6s} "
          f"{'valid':>6s} {'width px':>8s}")
    r_prof, r_meas, t_blur, t_blur2, t_prof, t_meas = [], [], [], [], [], []
    breakdown: dict[str, list[float]] = {}
    with serial():
        for name, img, axis, cam, plane in frames:
            fns = {"blur": lambda: cv2.GaussianBlur(img, (0, 0), BLUR_SIGMA_PX),
                   "profile": lambda: extract_profile(img, axis)}
            if cam is not None:
                fns["measure"] = lambda: measure_profile(img, cam, plane)
                fns["blur 2"] = lambda: cv2.GaussianBlur(img, (0, 0), MEASURE_BLUR_SIGMA_PX)
            t = interleaved(fns, args.rounds)
            prof = extract_profile(img, axis)
            r_prof.append(t["profile"] / t["blur"])
            t_blur.append(t["blur"])
            t_prof.append(t["profile"])
            meas = ""
            if "measure" in t:
                r_meas.append(t["measure"] / t["blur 2"])
                t_meas.append(t["measure"])
                t_blur2.append(t["blur 2"])
                meas = f"{t['measure'] * 1e3:10.3f} {r_meas[-1]:6.2f}"
            else:
                meas = f"{'':10s} {'':6s}"
            print(f"{name[:44]:44s} {t['blur'] * 1e3:8.3f} {t['profile'] * 1e3:10.3f} {r_prof[-1]:6.2f} {meas} "
                  f"{int(prof.valid.sum()):6d} {prof.width_px:8.2f}", flush=True)
            if not args.no_stages:
                for k, v in stages(img, axis, args.rounds).items():
                    breakdown.setdefault(k, []).append(v)
    clock = "thread CPU time, one thread" if args.cpu_time else "wall time, default threads"
    print(f"\n{clock}; median over {len(frames)} frames: extract_profile / blur {np.median(r_prof):.2f}x (target <= 1.0x), "
          f"measure_profile / blur (σ 2 px) {np.median(r_meas):.2f}x over {len(r_meas)} rendered frames (target <= 1.2x)")
    if breakdown:
        whole = np.array(breakdown["whole (1 thread)"])
        print("\nwhere the time goes (one thread; median over the set, ms, and share of the whole):")
        for k, v in breakdown.items():
            print(f"  {k:22s} {np.median(v) * 1e3:8.3f} ms  {np.median(np.array(v) / whole) * 100:5.1f} %")
    figs = [figure("busy_extract_profile_ratio", f"extract_profile, busy 1280x960 frames (median of {len(frames)})",
                   float(np.median(r_prof)), "x", statistic=f"median over the set of per-frame medians ({clock})",
                   reference=("cv2.GaussianBlur of the same frame (σ 1.44 px)", float(np.median(t_blur)) * 1e3, "ms"),
                   target=at_most(1.0, "x")),
            figure("busy_extract_profile_ms", "extract_profile, busy frames, time", float(np.median(t_prof)) * 1e3,
                   "ms", statistic=f"median over the set ({clock})", reference=("cv2.GaussianBlur", float(np.median(t_blur)) * 1e3,
                                                                      "ms")),
            figure("busy_measure_profile_ratio", f"measure_profile, busy rendered frames (median of {len(r_meas)})",
                   float(np.median(r_meas)), "x", statistic=f"median over the set of per-frame medians ({clock})",
                   reference=("cv2.GaussianBlur of the same frame (σ 2 px)", float(np.median(t_blur2)) * 1e3, "ms"),
                   target=at_most(1.2, "x"))]
    stacks = {"busy": roi_stack(), "clean": clean_roi_stack()}
    levels = (0,) if (args.no_load or args.cpu_time) else (0, 2)
    with serial():
        rates = roi_rates(stacks, 5, levels, cpus)
    unit = "profiles per CPU second, one thread" if args.cpu_time else "profiles/s"
    for k in levels:
        v, ref = rates[("busy", k)], rates[("clean", k)]
        tgt = 10000.0 if k == 0 else 5000.0
        print(f"1280x64 ROIs (extract_profiles, 1000 a call), {k} busy processes: busy {v:8.0f}, clean {ref:8.0f} {unit} "
              f"(busy {v / tgt:.2f}x target, {v / ref:.2f}x the clean ROIs)")
        figs.append(figure(f"busy_roi_profiles_k{k}", f"extract_profiles busy 1280x64 ROIs, {k} busy processes"
                           + (" (one thread, CPU time)" if args.cpu_time else ""), v, "profiles/s",
                           statistic=f"median of 5 calls of 1000 ROIs ({clock})",
                           reference=("bench_stripe's clean ROIs, same run", ref, "profiles/s"),
                           target=at_least(tgt, "profiles/s")))
    record("bench_busy", figs)


if __name__ == "__main__":
    main()
