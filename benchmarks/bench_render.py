"""Benchmark of the renderer: a 12-image 1280x960 realistic circle set.

Target: under 30 s on 2 cores.  Prints the median of several runs (after one
warm-up that compiles or loads the numba kernels), the per-image time and the
ratio to the target.  Also times one 15-board chessboard set and a 41-frame sphere
scan for information.

    .venv/bin/python benchmarks/bench_render.py [--runs 5]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

from results import at_most, figure, record

TARGET_S = 30.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5, help="timed runs (median reported)")
    ap.add_argument("--extra", action="store_true", help="also time chessboard and scan sets")
    args = ap.parse_args()

    import numba

    from lightplane.simulate.render import CircleOptions, render_chessboard_dataset, render_circle_dataset, render_scan_dataset

    print(f"cores: {os.cpu_count()}, numba threads: {numba.get_num_threads()}")
    render_circle_dataset(1, 99, CircleOptions(difficulty="realistic"))  # warm-up (JIT / cache load, ray maps)
    times = []
    for k in range(args.runs):
        t0 = time.perf_counter()
        ds = render_circle_dataset(12, k, CircleOptions(difficulty="realistic"))
        times.append(time.perf_counter() - t0)
        assert len(ds.images) == 12
    med = statistics.median(times)
    print(f"circle set, 12 images 1280x960, realistic: median {med:.2f} s over {args.runs} runs "
          f"(min {min(times):.2f} s, max {max(times):.2f} s), {med / 12:.3f} s per image")
    print(f"target {TARGET_S:.0f} s: ratio {med / TARGET_S:.3f} ({'PASS' if med < TARGET_S else 'FAIL'})")
    figs = [figure("render_circle_set_12", "render 12 circle images 1280x960", med, "s",
                   statistic=f"median of {args.runs} runs", target=at_most(TARGET_S, "s"))]
    if args.extra:
        t0 = time.perf_counter()
        render_chessboard_dataset(n=15, seed=0)
        print(f"chessboard set, 15 boards: {time.perf_counter() - t0:.2f} s")
        t0 = time.perf_counter()
        render_scan_dataset("sphere", seed=0)
        print(f"sphere scan, 41 frames: {time.perf_counter() - t0:.2f} s")
    record("bench_render", figs)


if __name__ == "__main__":
    main()
