"""Speed of the stripe extractors on 1280x960 8-bit frames (docs/method.md §Stripe centres).

Run: ``.venv/bin/python benchmarks/bench_stripe.py [--repeat N]``.  Prints the median
(and the minimum, which shows what the code does when the shared machine is not
busy: numba's OpenMP threads wait for each other when another process holds a
core, so medians on a loaded 2-core machine can be many times the minimum; the
1-thread rows do not suffer from that) in ms per frame, frames/s, and the ratio to the target, beside
``cv2.GaussianBlur`` of the same frame timed in the same run (a reference for how
fast this machine is right now).  Targets: ``extract_profile`` <= 1 ms per 1280x960
frame (>= 1000 profiles/s), >= 3000 profiles/s on a 1280x128 region,
``extract_stripe`` <= 8 ms per frame; batched 1280x64 regions of interest
(``extract_profiles``) >= 10,000 profiles/s (0.1 ms a frame).  The threading
layer and thread counts are printed first (``lightplane.core.threads.describe``).
"""

from __future__ import annotations

import argparse
import os
import time

import cv2
import numpy as np

from lightplane.stripe.extract import extract_profile, extract_profiles, extract_stripe
from lightplane.stripe.options import StripeOptions, StripePointsOptions
from results import at_most, figure, record

#: the rows recorded in benchmarks/results (row name -> figure id)
HEADLINE = {
    "extract_profile numba 1280x960": "extract_profile_1280x960",
    "extract_profile numba 1280x960, width estimated": "extract_profile_1280x960_width_estimated",
    "extract_profile numba 1280x128": "extract_profile_1280x128",
    "extract_profile numba 1280x960, 1 thread": "extract_profile_1280x960_1_thread",
    "extract_profiles, 500 x 1280x64 ROI, per frame": "extract_profiles_roi_1280x64",
    "extract_profiles, batch of 8 1280x960, per frame": "extract_profiles_batch_1280x960",
    "extract_stripe 1280x960": "extract_stripe_1280x960",
    "extract_stripe 1280x960, width estimated": "extract_stripe_1280x960_width_estimated",
}


def frame(rng: np.random.Generator, H: int = 960, W: int = 1280, width_px: float = 5.0) -> np.ndarray:
    """A slightly tilted, slightly curved Gaussian stripe, noise 2 grey levels, 8-bit."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    centre = 0.5 * H + 0.05 * (u - W / 2) + 40.0 * np.sin(u / W * np.pi)
    s = width_px / 2.3548
    img = 10.0 + 200.0 * np.exp(-0.5 * ((v - centre) / s) ** 2) + rng.normal(0.0, 2.0, (H, W))
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def roi_frame(rng: np.random.Generator, H: int = 64, W: int = 1280, width_px: float = 5.0) -> np.ndarray:
    """A 1280x64 region of interest: a slightly tilted, slightly curved stripe near its middle row,
    noise 2 grey levels, 8-bit (the stripe model of :func:`frame`)."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    centre = 0.5 * H + rng.uniform(-4, 4) + 0.004 * (u - W / 2) + 6.0 * np.sin(u / W * np.pi) - 3.0
    s = width_px / 2.3548
    img = 10.0 + 200.0 * np.exp(-0.5 * ((v - centre) / s) ** 2) + rng.normal(0.0, 2.0, (H, W))
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def timeit(fn, repeat: int) -> tuple[float, float]:
    fn()  # warm up (numba compilation, caches)
    t = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        t.append(time.perf_counter() - t0)
    return float(np.median(t)) * 1e3, float(np.min(t)) * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=200)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    img = frame(rng)
    band = np.ascontiguousarray(img[416:544])          # 1280x128 region around the stripe
    import numba

    from lightplane.core.threads import describe

    threads = numba.get_num_threads()
    extract_profile(img, options=StripeOptions(width_px=5.0), parallel=True)   # the first parallel kernel fixes numba's threading layer
    print(f"cpus {os.cpu_count()}, load average {os.getloadavg()[0]:.1f}; {describe()}")
    rows = []
    blur = timeit(lambda: cv2.GaussianBlur(img, (0, 0), 1.44), args.repeat)
    rows.append(("cv2.GaussianBlur 1280x960 (reference)", blur, None))
    rows.append(("extract_profile numba 1280x960", timeit(lambda: extract_profile(img,
                                                                                  options=StripeOptions(width_px=5.0)), args.repeat), 1.0))
    rows.append(("extract_profile numba 1280x960, width estimated",
                 timeit(lambda: extract_profile(img), args.repeat), 1.0))
    rows.append(("extract_profile numba 1280x128", timeit(lambda: extract_profile(band,
                                                                                  options=StripeOptions(width_px=5.0)), args.repeat),
                 1000.0 / 3000.0))
    rows.append(("extract_profile numba 1280x960, parallel=False",
                 timeit(lambda: extract_profile(img, options=StripeOptions(width_px=5.0), parallel=False), args.repeat), 1.0))
    rows.append(("extract_profile numba 1280x128, parallel=False",
                 timeit(lambda: extract_profile(band, options=StripeOptions(width_px=5.0), parallel=False), args.repeat), 1000.0 / 3000.0))
    roi = np.stack([roi_frame(rng) for _ in range(20)] * 25)   # 500 x 1280x64
    med, mn = timeit(lambda: extract_profiles(roi, options=StripeOptions(width_px=5.0)), max(5, args.repeat // 20))
    rows.append(("extract_profiles, 500 x 1280x64 ROI, per frame", (med / 500, mn / 500), 0.1))
    stack = np.stack([frame(rng) for _ in range(8)])
    med, mn = timeit(lambda: extract_profiles(stack, options=StripeOptions(width_px=5.0)), max(5, args.repeat // 10))
    rows.append(("extract_profiles, batch of 8 1280x960, per frame", (med / 8, mn / 8), 1.0))
    rows.append(("extract_profile numpy 1280x960",
                 timeit(lambda: extract_profile(img, options=StripeOptions(width_px=5.0, backend="numpy")), max(5, args.repeat // 20)), None))
    rows.append(("extract_stripe 1280x960", timeit(lambda: extract_stripe(img, StripePointsOptions(width_px=5.0)), max(10, args.repeat // 5)), 8.0))
    rows.append(("extract_stripe 1280x960, width estimated",
                 timeit(lambda: extract_stripe(img), max(10, args.repeat // 5)), 8.0))
    try:  # the same with one numba thread: robust when the machine is shared
        numba.set_num_threads(1)
        rows.append(("extract_profile numba 1280x960, 1 thread",
                     timeit(lambda: extract_profile(img, options=StripeOptions(width_px=5.0)), args.repeat), 1.0))
        rows.append(("extract_profile numba 1280x128, 1 thread",
                     timeit(lambda: extract_profile(band, options=StripeOptions(width_px=5.0)), args.repeat), 1000.0 / 3000.0))
        rows.append(("extract_stripe 1280x960, 1 numba thread",
                     timeit(lambda: extract_stripe(img, StripePointsOptions(width_px=5.0)), max(10, args.repeat // 5)), 8.0))
        numba.set_num_threads(threads)
    except Exception:  # pragma: no cover
        pass
    print(f"{'':50s} {'median ms':>10s} {'min ms':>8s} {'frames/s':>9s} {'target ms':>10s} {'median/target':>14s}")
    for name, (med, mn), target in rows:
        tgt = f"{target:10.3f} {med / target:14.2f}" if target else f"{'':10s} {'':14s}"
        print(f"{name:50s} {med:10.3f} {mn:8.3f} {1000.0 / med:9.0f} {tgt}")
    ref = ("cv2.GaussianBlur 1280x960", blur[0], "ms")
    stat = {"extract_profiles, 500 x 1280x64 ROI, per frame": f"median of {max(5, args.repeat // 20)} runs / 500",
            "extract_profiles, batch of 8 1280x960, per frame": f"median of {max(5, args.repeat // 10)} runs / 8"}
    record("bench_stripe", [
        figure(HEADLINE[name], name.replace(" numba", "").replace(", per frame", ""), med, "ms",
               statistic=stat.get(name, f"median of {max(10, args.repeat // 5) if 'stripe' in name else args.repeat}"
                                        " runs"),
               reference=ref, target=at_most(target, "ms"))
        for name, (med, _mn), target in rows if name in HEADLINE])


if __name__ == "__main__":
    main()
