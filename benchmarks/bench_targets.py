"""Benchmark: camera intrinsics from rendered views of every calibration target kind.

Renders (cached under ``benchmarks/out/renders``, named by
:func:`lightplane.simulate.render.settings_tag`) ``N_VIEWS`` realistic views of each target of
:data:`lightplane.simulate.render.TARGET_CAPTURES` — chessboard 15x11 of 8 mm (the same renders
as bench_calibrate.py's), circle grid 11x8 of 11 mm pitch (5.5 mm dots), asymmetric grid 6x11 of
9 mm (4.5 mm dots), ChArUco 11x8 squares of 12 mm with 9 mm DICT_4X4_50 markers — posed as
:data:`CALIBRATION_CAPTURE` (25–55° tilt, 350–650 mm, over the whole image), then calibrates
the camera (k3 fixed) and compares fx, fy, cx, cy with the renderer's camera.

- ``library``: :func:`lightplane.camera.intrinsics.calibrate_camera` with a
  :class:`lightplane.camera.targets.Target` (its own detection; circle centres corrected for the
  perspective bias; the printed dot diameter given);
- ``opencv``: plain OpenCV (``findChessboardCorners`` + ``cornerSubPix``, ``findCirclesGrid``,
  ``aruco.CharucoDetector``) with the object points of the board-frame conventions.

Target: every intrinsic within 3 of OpenCV's sigmas (``calibrateCameraExtended``) of the truth.
Also printed: the perspective bias of the dot centres in the renders (|ellipse centre - projected
centre|, px) and, for the library, the RMS shift its circle-centre correction applied.

    .venv/bin/python benchmarks/bench_targets.py [--views 30] [--seed 1] [--targets charuco,...]
                                                 [--methods library,opencv]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

CACHE = Path(__file__).resolve().parent / "out" / "renders"
N_VIEWS = 30
SIGMA_BAR = 3.0
NAMES = ("fx", "fy", "cx", "cy")


def _render(kind: str, n: int, seed: int) -> Path:
    from lightplane.simulate.render import (TARGET_CAPTURES, BoardOptions, render_chessboard_dataset, render_target_dataset,
                                            settings_tag)

    if kind == "chessboard":  # bench_calibrate.py's renders (the same images)
        out = CACHE / f"boards_capture_realistic_n{n}_s{seed}_{settings_tag()}"
        make = lambda: render_chessboard_dataset(n, seed, BoardOptions(difficulty="realistic"))  # noqa: E731
    else:
        out = CACHE / f"target_{kind}_realistic_n{n}_s{seed}_{settings_tag()}"
        make = lambda: render_target_dataset(TARGET_CAPTURES[kind], n, seed, BoardOptions(difficulty="realistic"))  # noqa: E731
    if not (out / "truth.json").exists():
        print(f"rendering {out.name} ...", flush=True)
        t0 = time.perf_counter()
        make().save(out, force=True)
        print(f"  {time.perf_counter() - t0:.0f} s", flush=True)
    return out


def _opencv_points(kind: str, spec, img: np.ndarray):
    """(object points (M, 3), image points (M, 2)) found by plain OpenCV, or None."""
    import cv2

    from lightplane.simulate.render import _charuco_layout, target_object_points

    obj = target_object_points(spec)
    if kind == "chessboard":
        ok, c = cv2.findChessboardCorners(img, (spec.cols, spec.rows),
                                          flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not ok:
            return None
        c = cv2.cornerSubPix(img, c, (5, 5), (-1, -1), (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4))
        return obj, c.reshape(-1, 2)
    if kind in ("circles", "acircles"):
        flags = cv2.CALIB_CB_SYMMETRIC_GRID if kind == "circles" else cv2.CALIB_CB_ASYMMETRIC_GRID
        ok, c = cv2.findCirclesGrid(img, (spec.cols, spec.rows), flags=flags)
        return (obj, c.reshape(-1, 2)) if ok else None
    det = cv2.aruco.CharucoDetector(_charuco_layout(spec)["board"])
    cc, cid, _, _ = det.detectBoard(img)
    if cid is None or len(cid) < 6:
        return None
    return obj[cid.ravel()], cc.reshape(-1, 2)


def _calibrate_opencv(kind: str, spec, images: list[np.ndarray]) -> dict:
    import cv2

    objs, pts = [], []
    for img in images:
        r = _opencv_points(kind, spec, img)
        if r is not None:
            objs.append(r[0].astype(np.float32))
            pts.append(r[1].astype(np.float32).reshape(-1, 1, 2))
    h, w = images[0].shape[:2]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    rms, K, dist, *_rest = cv2.calibrateCameraExtended(objs, pts, (w, h), None, None, flags=cv2.CALIB_FIX_K3,
                                                       criteria=crit)
    std = np.asarray(_rest[2]).ravel()
    return {"used": len(objs), "rms": float(rms), "K": K, "std": dict(zip(NAMES, std[:4])), "shift": None}


def _calibrate_library(spec, images: list[np.ndarray]) -> dict:
    import cv2

    from lightplane.camera.intrinsics import CameraCalibrationOptions, calibrate_camera
    from lightplane.camera.targets import Target

    dot = spec.dot_diameter_mm  # the printed dots' diameter, as a user knows it
    target = Target(spec.kind, spec.cols, spec.rows, spec.square_mm, spec.marker_mm, spec.dictionary, dot)
    ic = calibrate_camera(images, target, options=CameraCalibrationOptions(flags=cv2.CALIB_FIX_K3))
    shift = ic.options.get("circle_centre_correction_px")
    return {"used": len(ic.used), "rms": ic.rms_px, "K": ic.camera.K, "std": {k: ic.std[k] for k in NAMES},
            "shift": shift}


def main() -> int:
    from lightplane.camera.model import Camera
    from lightplane.core.io import read_image
    from lightplane.simulate.render import TARGET_CAPTURES, target_spec

    ap = argparse.ArgumentParser()
    ap.add_argument("--views", type=int, default=N_VIEWS)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--targets", default=",".join(TARGET_CAPTURES))
    ap.add_argument("--methods", default="library,opencv")
    args = ap.parse_args()
    if hasattr(os, "getloadavg"):
        print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    CACHE.mkdir(parents=True, exist_ok=True)
    methods = [m for m in args.methods.split(",") if m]
    try:
        import lightplane.camera.targets  # noqa: F401
    except ImportError:
        if "library" in methods:
            print("lightplane.camera.targets is not there yet: plain OpenCV only")
            methods = [m for m in methods if m != "library"]
    print(f"Camera intrinsics (k3 fixed) from {args.views} rendered realistic views per target (seed {args.seed}); "
          f"error vs the renderer's camera in px and in OpenCV sigmas; bar |error| <= {SIGMA_BAR:g} sigma")
    hdr = (f"{'target':<11} {'method':<8} {'used':>5} {'rms px':>7}  " + "  ".join(f"{n + ' err (sig)':>19}" for n in NAMES)
           + f"  {'bias px':>13}  verdict")
    print(hdr)
    print("-" * len(hdr))
    rows, failed = [], False
    for kind in [k for k in args.targets.split(",") if k]:
        spec = target_spec(TARGET_CAPTURES[kind])
        folder = _render(kind, args.views, args.seed)
        truth = json.loads((folder / "truth.json").read_text())
        cam = Camera.load(folder / "camera.json")
        images = [read_image(folder / v["file"]) for v in truth["views"]]
        bias = np.concatenate([np.asarray(v["centre_bias_px"]) for v in truth["views"]]) \
            if "centre_bias_px" in truth["views"][0] else None
        btxt = "-" if bias is None else f"{np.mean(bias):.3f}/{np.max(bias):.3f}"
        for method in methods:
            t0 = time.perf_counter()
            try:
                r = _calibrate_library(spec, images) if method == "library" else _calibrate_opencv(kind, spec, images)
            except Exception as e:  # noqa: BLE001 - a benchmark row, not a crash
                print(f"{kind:<11} {method:<8} failed: {e}")
                failed = True
                continue
            dt = time.perf_counter() - t0
            K = r["K"]
            est = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
            err = {n: float(est[n] - getattr(cam, n)) for n in NAMES}
            sig = {n: err[n] / r["std"][n] for n in NAMES}
            ok = all(abs(s) <= SIGMA_BAR for s in sig.values())
            failed |= not ok
            print(f"{kind:<11} {method:<8} {r['used']:>2}/{len(images):<2} {r['rms']:>7.4f}  "
                  + "  ".join(f"{err[n]:>+7.3f} ({sig[n]:>+5.1f}/{r['std'][n]:.3f})" for n in NAMES)
                  + f"  {btxt:>13}  {'PASS' if ok else 'FAIL'} ({max(abs(s) for s in sig.values()):.1f} sig max; "
                  + f"{dt:.0f} s)" + ("" if r["shift"] is None else f" centre correction {r['shift']:.3f} px RMS"))
            rows.append({"target": kind, "method": method, "used": r["used"], "rms_px": r["rms"], "error_px": err,
                         "std_px": r["std"], "error_sigma": sig, "pass": ok,
                         "centre_bias_px": None if bias is None else {"mean": float(np.mean(bias)),
                                                                      "max": float(np.max(bias))}})
    print("(bias px: the dots' perspective bias in the renders, |ellipse centre - projected centre|, mean/max; "
          "sig: error / OpenCV std, then the std)")
    (CACHE.parent / "bench_targets.json").write_text(json.dumps(rows, indent=1))
    from results import at_most, figure, record

    record("bench_targets", [
        figure(f"{r['target']}_{r['method']}_worst_sigma", f"intrinsics from {r['target']} views, {r['method']}: "
               "worst error", max(abs(s) for s in r["error_sigma"].values()), "sigma",
               statistic=f"worst of fx, fy, cx, cy over OpenCV's sigma, {r['used']} views",
               target=at_most(SIGMA_BAR, "sigma"))
        for r in rows])
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
