"""Benchmark of ellipse detection and refinement (issue 5).

1. Real photographs: the 40 ELSDc calibration-pattern images (../shared/data/
   elsdc-calibration-patterns): precision, recall and F-measure at IoU >= 0.8 (area
   overlap, pooled, duplicates are false positives), median time per image.
2. Renders: median time of detection + refinement (and of target selection) per
   1280x960 calibration image (lightplane.simulate.render, "realistic"); target <= 60 ms.
3. If ``cv2.ximgproc`` is importable (opencv-contrib; not a project dependency), the
   time and F-measure of ``cv2.ximgproc.findEllipses`` in the same run.

Run: ``.venv/bin/python benchmarks/bench_ellipse.py [--quick]``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from lightplane.ellipse import (
    Ellipse,
    MatchCounts,
    detect_ellipses,
    match_ellipses,
    read_ellipse_labels,
    refine_ellipse,
    select_target,
)
from lightplane.io import read_image

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "elsdc-calibration-patterns"
TARGET_MS = 60.0
TARGET_F = 0.95


def _findellipses(img: np.ndarray) -> list[Ellipse]:
    """cv2.ximgproc.findEllipses with the parameters of OpenCV's own sample."""
    import cv2

    res = cv2.ximgproc.findEllipses(img, scoreThreshold=0.7, reliabilityThreshold=0.5, centerDistanceThreshold=0.05)
    out = []
    if res is None:
        return out
    for x, y, a, b, _score, theta_rad in res.reshape(-1, res.shape[-1])[:, :6]:  # semi-axes, radians
        try:
            out.append(Ellipse.from_params((x, y), a, b, theta_rad))
        except Exception:  # degenerate output of the reference detector
            pass
    return out


def bench_real(quick: bool) -> None:
    if not (DATA / "images").is_dir():
        print(f"real images: {DATA} absent, skipped")
        return
    paths = sorted((DATA / "images").glob("*.pgm"))
    if quick:
        paths = paths[::4]
    total = MatchCounts(0, 0, 0)
    times = []
    ref_total, ref_times = MatchCounts(0, 0, 0), []
    try:
        import cv2

        has_ximgproc = hasattr(cv2, "ximgproc") and hasattr(cv2.ximgproc, "findEllipses")
    except ImportError:
        has_ximgproc = False
    for p in paths:
        img = read_image(p)
        labels = read_ellipse_labels(DATA / "ground_truth" / (p.stem + ".txt"))
        t0 = time.process_time()
        found = detect_ellipses(img, min_axis_px=1.5)
        times.append(time.process_time() - t0)
        total = total + match_ellipses(found, labels, iou_min=0.8)
        if has_ximgproc:
            t0 = time.process_time()
            ref = _findellipses(img)
            ref_times.append(time.process_time() - t0)
            ref_total = ref_total + match_ellipses(ref, labels, iou_min=0.8)
    print(f"real photographs ({len(paths)} images, {total.tp + total.fn} labelled ellipses), IoU >= 0.8:")
    print(f"  detect_ellipses: precision {total.precision:.4f}  recall {total.recall:.4f}  "
          f"F {total.f_measure:.4f} (target >= {TARGET_F}, ratio {total.f_measure / TARGET_F:.3f})  "
          f"TP {total.tp} FP {total.fp} FN {total.fn}  median {1e3 * np.median(times):.1f} ms CPU/image")
    if has_ximgproc:
        print(f"  cv2.ximgproc.findEllipses: precision {ref_total.precision:.4f}  recall {ref_total.recall:.4f}  "
              f"F {ref_total.f_measure:.4f}  median {1e3 * np.median(ref_times):.1f} ms CPU/image")
    else:
        print("  cv2.ximgproc.findEllipses: not importable here (opencv-contrib is not a dependency)")


def bench_render(quick: bool) -> None:
    try:
        from lightplane.simulate.render import render_circle_dataset
    except ImportError:
        print("renders: lightplane.simulate.render not available, skipped")
        return
    n = 3 if quick else 6
    ds = render_circle_dataset(n, seed=7, difficulty="realistic", polarity="light")
    cam = ds.camera
    det_ms, ref_ms, sel_ms, tot_ms, cpu_ms = [], [], [], [], []
    for img in ds.images:
        for _ in range(3):
            c0 = time.process_time()
            t0 = time.perf_counter()
            found = detect_ellipses(img, min_axis_px=40)
            t1 = time.perf_counter()
            c1 = time.process_time()
            sel = select_target(img, found)
            t2 = time.perf_counter()
            c2 = time.process_time()
            target = sel.ellipse if sel.ellipse is not None else found[0]
            refine_ellipse(img, target, cam)
            t3 = time.perf_counter()
            c3 = time.process_time()
            det_ms.append(1e3 * (t1 - t0))
            sel_ms.append(1e3 * (t2 - t1))
            ref_ms.append(1e3 * (t3 - t2))
            tot_ms.append(1e3 * ((t1 - t0) + (t3 - t2)))
            cpu_ms.append(1e3 * ((c1 - c0) + (c3 - c2)))
    h, w = ds.images[0].shape[:2]
    med = float(np.median(tot_ms))
    print(f"renders ({n} images {w}x{h}, 3 runs each):")
    print(f"  detection {np.median(det_ms):.1f} ms + refinement {np.median(ref_ms):.1f} ms = {med:.1f} ms median "
          f"(target <= {TARGET_MS:.0f} ms, ratio {med / TARGET_MS:.2f}); target selection {np.median(sel_ms):.1f} ms")
    cpu = float(np.median(cpu_ms))
    print(f"  CPU time of detection + refinement (all threads; immune to other processes' load): {cpu:.1f} ms median "
          f"(ratio {cpu / TARGET_MS:.2f}); load average now {_load()}")


def _load() -> str:
    try:
        import os

        return "%.1f" % os.getloadavg()[0]
    except OSError:
        return "?"


def main() -> None:
    quick = "--quick" in sys.argv
    import cv2

    print(f"OpenCV {cv2.__version__}, {cv2.getNumThreads()} threads")
    bench_real(quick)
    bench_render(quick)


if __name__ == "__main__":
    main()
