"""Benchmark of ellipse detection and refinement.

1. Real photographs: the 40 ELSDc calibration-pattern images (../shared/data/
   elsdc-calibration-patterns): precision, recall and F-measure at IoU >= 0.8 (area
   overlap, pooled, duplicates are false positives), median time per image.
2. Renders: median time of detection + refinement (and of target selection) per
   1280x960 calibration image (lightplane.simulate.render, "realistic"); target <= 60 ms.
3. The time and F-measure of ``cv2.ximgproc.findEllipses`` (opencv-contrib; not a
   project dependency, it conflicts with opencv-python-headless) in the same run: in
   this process if ``cv2.ximgproc`` is importable, else through another interpreter
   given by ``--ximgproc-python PATH`` (e.g. a throwaway venv with
   opencv-contrib-python-headless), on the same images.

4. Default detection against OpenCV's LSD: ``detect_ellipses(image)`` with default
   arguments (the scale picked by ``auto_downscale`` from the image and
   ``min_axis_px``) and ``cv2.createLineSegmentDetector().detect`` on the same
   1280x960 renders, interleaved, medians of CPU and wall time; target: ratio <= 1.0.
   Also the full-resolution search (``downscale=1``, the former default) for reference.

5. Curvature bias of the refined rim (realistic renders, light and dark targets): mean
   signed distance of the edge points to the true conic (px, < 0 inside), the circle
   pose's depth error (mm) and the refinement time, with and without
   ``correct_curvature`` (target: |bias| <= 0.002 px).

Times are medians of process CPU time (all threads), which other processes' load on a
shared machine does not inflate, and of wall time for the renders.

Run: ``.venv/bin/python benchmarks/bench_ellipse.py [--quick] [--ximgproc-python PATH]``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from lightplane.ellipse import (
    Ellipse,
    EllipseDetectionOptions,
    EllipseRefinementOptions,
    MatchCounts,
    detect_ellipses,
    match_ellipses,
    read_ellipse_labels,
    refine_ellipse,
    select_target,
)
from lightplane.core.io import read_image
from results import at_least, at_most, figure, record, within

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "elsdc-calibration-patterns"
TARGET_MS = 60.0
TARGET_F = 0.95


_XIMGPROC_SCRIPT = r"""
import json, sys, time
import cv2, numpy as np
out = {}
for path in json.loads(sys.argv[1]):
    img = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
    cpu = []
    for _ in range(int(sys.argv[2])):
        c0 = time.process_time()
        r = cv2.ximgproc.findEllipses(img, scoreThreshold=0.7, reliabilityThreshold=0.5, centerDistanceThreshold=0.05)
        cpu.append(time.process_time() - c0)
    out[path] = {"cpu_s": cpu, "ellipses": [] if r is None else r.reshape(-1, r.shape[-1]).tolist()}
print(json.dumps(out))
"""


def _external_findellipses(python: str, paths: list[str], repeats: int) -> dict:
    """Run findEllipses in another interpreter (one with opencv-contrib) on image files."""
    import json
    import subprocess

    res = subprocess.run([python, "-c", _XIMGPROC_SCRIPT, json.dumps(paths), str(repeats)],
                         capture_output=True, text=True, check=True)
    return json.loads(res.stdout)


def _to_ellipses(rows) -> list[Ellipse]:
    out = []
    for x, y, a, b, _score, theta_rad in (r[:6] for r in rows):  # semi-axes, radians
        try:
            out.append(Ellipse.from_params((x, y), a, b, theta_rad))
        except Exception:  # degenerate output of the reference detector
            pass
    return out


def _findellipses(img: np.ndarray) -> list[Ellipse]:
    """cv2.ximgproc.findEllipses (scoreThreshold 0.7, reliabilityThreshold 0.5, centerDistanceThreshold 0.05)."""
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


def bench_real(quick: bool, ext_python: str | None) -> list[dict]:
    if not (DATA / "images").is_dir():
        print(f"real images: {DATA} absent, skipped")
        return []
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
        found = detect_ellipses(img, EllipseDetectionOptions(min_axis_px=1.5))
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
    stat = f"{len(paths)} ELSDc photographs, IoU >= 0.8"
    figs = [figure("elsdc_f_measure", "detect_ellipses F-measure, ELSDc photos", total.f_measure, "",
                   statistic=stat, target=at_least(TARGET_F, "")),
            figure("elsdc_precision", "detect_ellipses precision, ELSDc photos", total.precision, "", statistic=stat),
            figure("elsdc_recall", "detect_ellipses recall, ELSDc photos", total.recall, "", statistic=stat),
            figure("elsdc_cpu_ms", "detect_ellipses CPU per ELSDc photo", 1e3 * np.median(times), "ms",
                   statistic=f"median over {len(paths)} images")]
    if not has_ximgproc and ext_python:
        ext = _external_findellipses(ext_python, [str(p) for p in paths], 1)
        for p in paths:
            r = ext[str(p)]
            ref_times.append(r["cpu_s"][0])
            labels = read_ellipse_labels(DATA / "ground_truth" / (p.stem + ".txt"))
            ref_total = ref_total + match_ellipses(_to_ellipses(r["ellipses"]), labels, iou_min=0.8)
    if ref_times:
        print(f"  cv2.ximgproc.findEllipses: precision {ref_total.precision:.4f}  recall {ref_total.recall:.4f}  "
              f"F {ref_total.f_measure:.4f}  median {1e3 * np.median(ref_times):.1f} ms CPU/image "
              f"(ratio ours/theirs {np.median(times) / np.median(ref_times):.2f})")
        figs[-1] = figure("elsdc_cpu_ms", "detect_ellipses CPU per ELSDc photo", 1e3 * np.median(times), "ms",
                          statistic=f"median over {len(paths)} images",
                          reference=("cv2.ximgproc.findEllipses", 1e3 * np.median(ref_times), "ms"))
    else:
        print("  cv2.ximgproc.findEllipses: not importable here (opencv-contrib is not a dependency; "
              "see --ximgproc-python)")
    return figs


def bench_render(quick: bool, ext_python: str | None) -> list[dict]:
    try:
        from lightplane.simulate.render import CircleOptions, render_circle_dataset
    except ImportError:
        print("renders: lightplane.simulate.render not available, skipped")
        return []
    n = 3 if quick else 6
    ds = render_circle_dataset(n, 7, CircleOptions(difficulty="realistic", polarity="light"))
    cam = ds.camera
    det_ms, ref_ms, sel_ms, tot_ms, cpu_ms = [], [], [], [], []
    for img in ds.images:
        for _ in range(3):
            c0 = time.process_time()
            t0 = time.perf_counter()
            found = detect_ellipses(img, EllipseDetectionOptions(min_axis_px=40))
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
    ref_cpu = []
    try:
        import cv2

        if hasattr(cv2, "ximgproc") and hasattr(cv2.ximgproc, "findEllipses"):
            for img in ds.images:
                for _ in range(3):
                    c0 = time.process_time()
                    _findellipses(img)
                    ref_cpu.append(time.process_time() - c0)
        elif ext_python:
            import tempfile

            import cv2

            with tempfile.TemporaryDirectory() as tmp:
                paths = []
                for i, img in enumerate(ds.images):
                    paths.append(str(Path(tmp) / f"render_{i}.png"))
                    cv2.imwrite(paths[-1], img)
                ext = _external_findellipses(ext_python, paths, 3)
                ref_cpu = [t for p in paths for t in ext[p]["cpu_s"]]
    except Exception as exc:  # the reference is optional
        print(f"  cv2.ximgproc.findEllipses: failed ({exc})")
    stat = f"median of {len(tot_ms)} runs ({n} renders x 3)"
    ref_fig = None
    if ref_cpu:
        ref = 1e3 * float(np.median(ref_cpu))
        print(f"  cv2.ximgproc.findEllipses on the same renders: {ref:.1f} ms CPU median "
              f"(ours / theirs = {cpu / ref:.2f})")
        ref_fig = ("cv2.ximgproc.findEllipses, CPU", ref, "ms")
    return [figure("render_detect_refine_wall", "ellipse detection + refinement, render, wall", med, "ms",
                   statistic=stat, target=at_most(TARGET_MS, "ms")),
            figure("render_detect_refine_cpu", "ellipse detection + refinement, render, CPU", cpu, "ms",
                   statistic=stat, target=at_most(TARGET_MS, "ms"), reference=ref_fig)]


def bench_default_vs_lsd(quick: bool) -> list[dict]:
    try:
        from lightplane.simulate.render import CircleOptions, render_circle_dataset
    except ImportError:
        print("default detection vs LSD: lightplane.simulate.render not available, skipped")
        return []
    import cv2

    from lightplane.ellipse.detect import auto_downscale

    n = 3 if quick else 6
    ds = render_circle_dataset(n, 7, CircleOptions(difficulty="realistic", polarity="light"))
    lsd = cv2.createLineSegmentDetector()
    grays = [img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) for img in ds.images]
    runs = {"lsd": lambda g: lsd.detect(g), "default": lambda g: detect_ellipses(g),
            "full": lambda g: detect_ellipses(g, EllipseDetectionOptions(downscale=1))}
    cpu = {k: [] for k in runs}
    wall = {k: [] for k in runs}
    for f in runs.values():
        f(grays[0])  # warm-up
    for _ in range(3):
        for g in grays:
            for k, f in runs.items():  # interleaved: the same load on each
                c0, t0 = time.process_time(), time.perf_counter()
                f(g)
                cpu[k].append(1e3 * (time.process_time() - c0))
                wall[k].append(1e3 * (time.perf_counter() - t0))
    h, w = grays[0].shape
    med = {k: (float(np.median(cpu[k])), float(np.median(wall[k]))) for k in runs}
    print(f"default detect_ellipses(image) vs cv2.createLineSegmentDetector().detect ({n} realistic renders {w}x{h}, "
          f"3 runs each, interleaved; default scale 1/{auto_downscale((h, w), 3.0)}):")
    for k, label in (("lsd", "LSD (reference)"), ("default", "detect_ellipses defaults"),
                     ("full", "detect_ellipses downscale=1")):
        c, t = med[k]
        print(f"  {label:28s} {c:6.1f} ms CPU, {t:6.1f} ms wall (median); ratio to LSD {c / med['lsd'][0]:.2f} CPU, "
              f"{t / med['lsd'][1]:.2f} wall" + (" (target <= 1.0)" if k == "default" else ""))
    stat = f"median of {3 * n} runs, interleaved"
    return [figure("detect_default_vs_lsd_cpu", "detect_ellipses defaults, 1280x960 render, CPU", med["default"][0],
                   "ms", statistic=stat, reference=("cv2 LSD detect, CPU", med["lsd"][0], "ms"),
                   target=at_most(1.0, "x", of="ratio"))]


def bench_curvature_bias(quick: bool) -> list[dict]:
    try:
        from lightplane.simulate.render import CircleOptions, render_circle_dataset
    except ImportError:
        print("curvature bias: lightplane.simulate.render not available, skipped")
        return []
    figs = []
    from lightplane.plane.circle_pose import circle_poses

    n = 3 if quick else 6
    print(f"curvature bias of the refined rim (realistic renders, {n} images per polarity; target |bias| <= 0.002 px):")
    for polarity in ("light", "dark"):
        ds = render_circle_dataset(n, 11, CircleOptions(difficulty="realistic", polarity=polarity))
        cam = ds.camera
        rows = {False: [], True: []}
        for img, tr in zip(ds.images, ds.truth["images"]):
            sel = select_target(img, detect_ellipses(img, EllipseDetectionOptions(min_axis_px=40)))
            if sel.ellipse is None:
                continue
            C = Ellipse.from_conic(np.array(tr["target"]["conic_undistorted_px"])).conic  # interior < 0
            c_true = np.array(tr["target"]["center_mm"])
            for corr in (False, True):
                c0 = time.process_time()
                r = refine_ellipse(img, sel.ellipse, cam, options=EllipseRefinementOptions(correct_curvature=corr))
                cpu = time.process_time() - c0
                h = np.column_stack([r.edge_points_undistorted, np.ones(r.n_inliers)])
                d = np.einsum("ni,ij,nj->n", h, C, h) / np.linalg.norm(2 * h @ C[:, :2], axis=1)
                best = min(circle_poses(r.conic, cam.K, 0.5 * tr["target"]["diameter_mm"]),
                           key=lambda p: np.linalg.norm(p.center - c_true))
                rows[corr].append((float(np.mean(d)), float(np.linalg.norm(best.center) - np.linalg.norm(c_true)),
                                   1e3 * cpu, r.blur_sigma_px))
        for corr in (False, True):
            a = np.array(rows[corr])
            bias = float(np.mean(a[:, 0]))
            print(f"  {polarity:5s} correct_curvature={str(corr):5s}: edge bias {bias:+.4f} px "
                  f"(ratio to 0.002: {abs(bias) / 0.002:.2f}), depth error {np.mean(a[:, 1]):+.4f} mm, "
                  f"refine {np.median(a[:, 2]):.1f} ms CPU median, blur estimate {np.mean(a[:, 3]):.3f} px "
                  f"(PSF 0.9 px with the pixel footprint: 0.945)")
            if corr:
                figs.append(figure(f"rim_bias_{polarity}", f"refined rim bias, {polarity} target, corrected", bias,
                                   "px", statistic=f"mean over the edge points of {len(a)} renders",
                                   target=within(0.002, "px")))
    return figs


def _load() -> str:
    try:
        import os

        return "%.1f" % os.getloadavg()[0]
    except OSError:
        return "?"


def main() -> None:
    quick = "--quick" in sys.argv
    ext_python = None
    if "--ximgproc-python" in sys.argv:
        ext_python = sys.argv[sys.argv.index("--ximgproc-python") + 1]
    import cv2

    print(f"OpenCV {cv2.__version__}, {cv2.getNumThreads()} threads")
    figs = bench_real(quick, ext_python)
    figs += bench_render(quick, ext_python)
    figs += bench_default_vs_lsd(quick)
    figs += bench_curvature_bias(quick)
    record("bench_ellipse", figs)


if __name__ == "__main__":
    main()
