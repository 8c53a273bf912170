"""Batch measurement on a Dask LocalCluster (``lightplane measure-batch``) against the single-process ``measure``.

Run: ``.venv/bin/python benchmarks/bench_batch.py [--frames N] [--chunk-frames N] [--repeats N]``.

The same PNG files on disk (1280x960, 8-bit: ``--distinct`` rendered sphere frames
repeated as hard links up to ``--frames`` files, so reading and decoding are part of
the work in every path) are measured by

- ``measure``: :func:`lightplane.measure.scan.measure_scan`, 2 threads in one process (the
  command's default on 2 cores), to an NPY file;
- ``batch`` with 1 and with 2 single-threaded worker processes (a LocalCluster of each
  size started once, outside the timing; a warm-up run first), ``--chunk-frames`` per
  task, to a fresh output folder each run (the client's planning, the per-scan prepare
  task and manifest.json are inside the timing).

The three variants run interleaved, repeat after repeat, so that a busy machine weighs on
them alike.

Prints medians of ``--repeats`` runs in frames/s, the scaling ratio 2 workers / 1
worker, and the ratio 2 workers / threaded ``measure`` against the target >= 0.8.
Also checks that the batch points equal ``measure``'s bit for bit.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

TARGET = 0.8


def make_frames(root: Path, n_frames: int, n_distinct: int) -> tuple[Path, Path, Path]:
    from lightplane import LightPlane
    from lightplane.simulate.render import render_scan_dataset

    src = root / "distinct"
    if not (src / "camera.json").is_file():
        ds = render_scan_dataset("sphere", n_frames=n_distinct, step_mm=3.0, seed=5)
        ds.save(src, force=True)
        LightPlane.from_dict(ds.truth["plane"]).save(root / "plane.json", force=True)
    names = sorted(src.glob("*.png"))
    frames = root / f"frames{n_frames}"
    if not frames.is_dir() or len(list(frames.glob("*.png"))) != n_frames:
        shutil.rmtree(frames, ignore_errors=True)
        frames.mkdir()
        for i in range(n_frames):
            os.link(names[i % len(names)], frames / f"f{i:06d}.png")
    return frames, src / "camera.json", root / "plane.json"


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--distinct", type=int, default=8)
    ap.add_argument("--chunk-frames", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args(argv)

    from distributed import Client

    from lightplane import Camera, LightPlane
    from lightplane.measure.batch import BatchOptions, local_cluster, measure_batch, read_points
    from lightplane.measure.scan import Motion, measure_scan, open_frames

    root = Path(os.environ.get("LIGHTPLANE_BENCH_CACHE", tempfile.gettempdir())) / "lightplane_bench_batch"
    root.mkdir(parents=True, exist_ok=True)
    frames, cam_path, plane_path = make_frames(root, a.frames, a.distinct)
    manifest = root / "manifest.csv"
    manifest.write_text(f"id,input,camera,plane,step,direction\nscan,{frames},{cam_path},{plane_path},3.0,-1;0;0\n")
    cam, plane = Camera.load(cam_path), LightPlane.load(plane_path)
    work = Path(tempfile.mkdtemp(prefix="bench_batch_", dir=root))
    print(f"{a.frames} frames 1280x960 PNG ({a.distinct} distinct), chunks of {a.chunk_frames}, "
          f"median of {a.repeats}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}")

    def measure_once(k: int) -> float:
        out = work / f"ref{k}.npy"
        t = time.perf_counter()
        measure_scan(open_frames([frames]), cam, plane, out, motion=Motion.linear(3.0, (-1, 0, 0)), workers=2,
                     executor="thread")
        return time.perf_counter() - t

    clients, starts = {}, {}
    for n in (1, 2):
        t = time.perf_counter()
        clients[n] = Client(local_cluster(n))
        starts[n] = time.perf_counter() - t

    def batch_once(n: int, k: int) -> float:
        out = work / f"b{n}-{k}"
        t = time.perf_counter()
        r = measure_batch(manifest, out, batch=BatchOptions(chunk_frames=a.chunk_frames), client=clients[n])
        dt = time.perf_counter() - t
        assert not r.failed, r.failed
        return dt

    times: dict = {"measure": [], 1: [], 2: []}
    try:
        measure_once(-1)  # warm-up: numba cache, lookup tables in every process
        for n in (1, 2):
            batch_once(n, -1)
        for k in range(a.repeats):  # interleaved, so that the machine's load weighs on every variant alike
            times["measure"].append(measure_once(k))
            for n in (1, 2):
                times[n].append(batch_once(n, k))
        ref = np.load(work / "ref0.npy")
        identical = all(read_points(work / f"b{n}-0", "scan").tobytes() == ref.tobytes() for n in (1, 2))
    finally:
        for c in clients.values():
            cluster = c.cluster
            c.close()
            cluster.close()
    results = {"measure (2 threads)": a.frames / statistics.median(times["measure"]),
               "batch 1 worker": a.frames / statistics.median(times[1]),
               "batch 2 worker": a.frames / statistics.median(times[2])}
    print(f"measure, 1 process, 2 threads: {results['measure (2 threads)']:6.0f} frames/s")
    for n in (1, 2):
        print(f"batch, {n} worker process{'es' if n > 1 else '  '}:   {results[f'batch {n} worker']:6.0f} frames/s "
              f"(cluster start {starts[n]:.1f} s, not included)")
    scaling = results["batch 2 worker"] / results["batch 1 worker"]
    ratio = results["batch 2 worker"] / results["measure (2 threads)"]
    print(f"scaling 2 workers / 1 worker: {scaling:.2f}x")
    print(f"batch 2 workers / measure threaded: {ratio:.2f}x (target >= {TARGET}: "
          f"{'met' if ratio >= TARGET else 'NOT met'})")
    print(f"points identical to measure: {identical}; load {os.getloadavg()[0]:.1f}")
    shutil.rmtree(work, ignore_errors=True)
    from results import at_least, figure, record

    stat = f"median of {a.repeats} runs of {a.frames} PNG frames"
    ref = ("measure, 2 threads", results["measure (2 threads)"], "frames/s")
    record("bench_batch", [
        figure("batch_2_workers", "measure-batch, 2 worker processes", results["batch 2 worker"], "frames/s",
               statistic=stat, reference=ref, target=at_least(TARGET, "x", of="ratio")),
        figure("batch_1_worker", "measure-batch, 1 worker process", results["batch 1 worker"], "frames/s",
               statistic=stat, reference=ref)])
    return 0 if identical else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
