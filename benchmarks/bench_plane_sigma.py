"""Benchmark: is the light plane's own σ honest, for the circle method and for Zhou's boards?

``--sets`` independent data sets (the renders of ``bench_camera_uncertainty.py``, from its cache:
each 16 realistic 9x7 chessboard views for the camera and 12 realistic circle images, 50 mm
target; and, for Zhou's method, ``--boards`` realistic 9x6 chessboard poses crossed by the
stripe with their laser-off frames).  Each plane is calibrated twice, with the renderer's exact
camera (the plane's own σ alone) and with the camera calibrated from the set's chessboards (its
covariance carried into the plane); against the exact truth over the working volume 380-520 mm
(:func:`lightplane.evaluate.shapes.plane_accuracy`'s grid), the RMS error of the triangulated
points in the camera frame and after the best rigid alignment (shape), against the predicted RMS σ.

Honest: predicted / actual within 10 % with the exact camera and within 20 % with a calibrated
one.  The ratio of two RMS over a few tens of sets is itself uncertain: the sets are resampled
(bootstrap, 2000 draws) and the ratio's 16-84 % interval and sd are given with it.  Columns for
the circle method: the default covariance (the images' dispersion, never below 1), the images'
dispersion as estimated (also below 1) and the noise model alone (same estimates, other σ).

Renders, camera calibrations and circle observations are cached under ``--cache`` (default
/tmp/lightplane_bench_camera_unc, shared with bench_camera_uncertainty.py).

    .venv/bin/python benchmarks/bench_plane_sigma.py [--sets 24] [--boards 10]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import bench_camera_uncertainty as bcu

DIAMETER_MM = 50.0


def _camera(cache: Path, k: int):
    """The camera calibrated from set ``k``'s chessboards (cached as its JSON)."""
    from lightplane.camera.intrinsics import calibrate_camera
    from lightplane.camera.model import Camera
    from lightplane.simulate.render import settings_tag

    f = cache / f"camera_{bcu.BOARD[0]}x{bcu.BOARD[1]}_n{bcu.N_BOARDS}_s{1000 + k}_{settings_tag()}.json"
    if f.exists():
        return Camera.load(f)
    cam = calibrate_camera(bcu._chessboards(cache, k), bcu.BOARD, bcu.SQUARE_MM).camera
    cam.save_json(f, force=True)
    return cam


def _observations(cache: Path, k: int, cam) -> list:
    """The circle images' observations of set ``k`` (cached records)."""
    from lightplane.plane.calibrate import ImageObservation, PlaneCalibrationOptions, observe_images
    from lightplane.simulate.render import settings_tag

    f = cache / f"obs_circles_n{bcu.N_CIRCLES}_s{2000 + k}_{settings_tag()}.json"
    if f.exists():
        return [ImageObservation.from_record(r) for r in json.loads(f.read_text())]
    obs = observe_images(bcu._circles(cache, k), cam, DIAMETER_MM, PlaneCalibrationOptions(workers=1))
    f.write_text(json.dumps([o.to_record() for o in obs]))
    return obs


def _board_frames(cache: Path, k: int, n: int):
    """Set ``k``'s ``n`` chessboard poses crossed by the stripe: (laser frames, laser-off frames, truth plane)."""
    from lightplane.simulate.render import BoardOptions, render_chessboard_dataset, settings_tag

    f = cache / f"zhou_9x6_n{n}_s{3000 + k}_{settings_tag()}.npz"
    if not f.exists():
        ds = render_chessboard_dataset(n, 3000 + k, BoardOptions(difficulty="realistic", with_stripe=True,
                                                                 laser_off=True))
        on = [im for im, v in zip(ds.images, ds.names) if not v.endswith("_off.png")]
        off = [im for im, v in zip(ds.images, ds.names) if v.endswith("_off.png")]
        f.parent.mkdir(parents=True, exist_ok=True)
        tmp = f.with_suffix(".tmp.npz")
        np.savez_compressed(tmp, on=np.stack(on), off=np.stack(off))
        tmp.replace(f)
    z = np.load(f)
    return list(z["on"]), list(z["off"])


def _errors(cam, plane, cam_true, plane_true, vol, prefix: str) -> dict:
    """Actual camera-frame and shape RMS error against the truth over ``vol`` and their predicted σ."""
    from lightplane.evaluate.shapes import rigid_align
    from lightplane.plane.triangulate import triangulate
    from lightplane.plane.uncertainty import volume_sigma

    est = triangulate(cam, plane, vol.uv)
    e = est - vol.points
    ok = np.all(np.isfinite(e), axis=1)
    pred = volume_sigma(cam, plane, vol)
    return {prefix + "frame_mm": float(np.sqrt(np.mean(np.sum(e[ok] ** 2, axis=1)))),
            prefix + "shape_mm": rigid_align(est[ok], vol.points[ok]).rms_mm,
            prefix + "pred_frame_mm": pred.camera_frame_mm, prefix + "pred_shape_mm": pred.shape_mm,
            prefix + "covers": pred.covers}


def _rescaled(plane, f: float):
    """The plane with its own covariance (not the camera's share) times ``f``: same estimate, other σ."""
    from lightplane.plane.model import LightPlane

    return LightPlane(plane.normal, plane.d, f * np.asarray(plane.covariance), meta=dict(plane.meta))


def _circle_rows(obs, cam, cam_true, plane_true, vol) -> dict:
    """The circle method (ml) with the exact and the calibrated camera; the dispersion variants."""
    from lightplane.plane.calibrate import solve_observations
    from lightplane.plane.ml import dispersion_factor

    row: dict = {}
    for pre, c in (("exact_", cam_true), ("cal_", cam)):
        t0 = time.perf_counter()
        pl = solve_observations(obs, c, DIAMETER_MM, "ml").plane
        nm = pl.meta.get("noise_model") or {}
        f, raw = dispersion_factor(nm), float(nm.get("image_dispersion") or 1.0)
        row[pre + "image_dispersion"], row[pre + "dispersion_factor"] = raw, f
        row.update(_errors(c, pl, cam_true, plane_true, vol, "ml_" + pre))
        row.update(_errors(c, _rescaled(pl, raw / f), cam_true, plane_true, vol, "mlraw_" + pre))
        row.update(_errors(c, _rescaled(pl, 1.0 / f), cam_true, plane_true, vol, "mlmodel_" + pre))
        row[pre + "ml_seconds"] = time.perf_counter() - t0
    return row


def _zhou_rows(on, off, cam, cam_true, plane_true, vol) -> dict:
    """Zhou's method with the exact and the calibrated camera."""
    from lightplane.plane.zhou import BoardFrames, BoardPlaneOptions, calibrate_plane_board

    row: dict = {}
    for pre, c in (("exact_", cam_true), ("cal_", cam)):
        t0 = time.perf_counter()
        z = calibrate_plane_board(BoardFrames(on, background_images=off), c, (9, 6), 8.0,
                                  BoardPlaneOptions(keep_suspect=True))
        row.update(_errors(c, z.plane, cam_true, plane_true, vol, "zhou_" + pre))
        row["zhou_" + pre + "poses"] = int(len(set(z.view_index.tolist())))
        row["zhou_" + pre + "seconds"] = time.perf_counter() - t0
    return row


def one_set(cache: Path, k: int, boards: int) -> dict:
    from lightplane.plane.uncertainty import working_volume_grid
    from lightplane.simulate.scene import default_camera, default_plane

    cam_true, plane_true = default_camera(), default_plane()
    vol = working_volume_grid(cam_true, plane_true, distance_mm=(380.0, 520.0))
    cam = _camera(cache, k)
    row: dict = {"set": k}
    row.update(_circle_rows(_observations(cache, k, cam), cam, cam_true, plane_true, vol))
    if boards:
        on, off = _board_frames(cache, k, boards)
        row.update(_zhou_rows(on, off, cam, cam_true, plane_true, vol))
    return row


#: (label, prefix) of the columns.
VARIANTS = (("circle method (ml), exact camera", "ml_exact_"), ("circle method (ml), calibrated camera", "ml_cal_"),
            ("ml, exact camera, images' dispersion as estimated", "mlraw_exact_"),
            ("ml, calibrated camera, images' dispersion as estimated", "mlraw_cal_"),
            ("ml, exact camera, noise model alone", "mlmodel_exact_"),
            ("ml, calibrated camera, noise model alone", "mlmodel_cal_"),
            ("Zhou, exact camera", "zhou_exact_"), ("Zhou, calibrated camera", "zhou_cal_"))


def _ratio_spread(act: np.ndarray, pred: np.ndarray, draws: int = 2000) -> dict:
    """RMS(pred) / RMS(act) over the sets and its bootstrap spread (sets resampled)."""
    rng = np.random.default_rng(0)
    n = len(act)
    idx = rng.integers(0, n, (draws, n))
    r = np.sqrt(np.mean(pred[idx] ** 2, axis=1) / np.mean(act[idx] ** 2, axis=1))
    return {"actual_rms": float(np.sqrt(np.mean(act**2))), "predicted_rms": float(np.sqrt(np.mean(pred**2))),
            "ratio": float(np.sqrt(np.mean(pred**2) / np.mean(act**2))), "ratio_sd": float(np.std(r)),
            "ratio_p16": float(np.percentile(r, 16)), "ratio_p84": float(np.percentile(r, 84))}


def summarise(rows: list[dict]) -> dict:
    out: dict = {"sets": len(rows)}
    for label, pre in VARIANTS:
        if not all(pre + "frame_mm" in r for r in rows):
            continue
        out[label] = {q: _ratio_spread(np.array([r[pre + q + "_mm"] for r in rows]),
                                       np.array([r[pre + "pred_" + q + "_mm"] for r in rows]))
                      for q in ("frame", "shape")}
        out[label]["covers"] = rows[0][pre + "covers"]
    for pre in ("exact_", "cal_"):
        v = np.array([r[pre + "image_dispersion"] for r in rows])
        out[pre + "image_dispersion"] = {"mean": float(np.mean(v)), "sd": float(np.std(v, ddof=1)),
                                         "below_1": int(np.sum(v < 1))}
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sets", type=int, default=24)
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--boards", type=int, default=10, help="Zhou's board poses per set (0: the circle method only)")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/lightplane_bench_camera_unc"))
    ap.add_argument("--fresh", action="store_true", help="forget the sets already in out/")
    ap.add_argument("--name", default="bench_plane_sigma", help="name of the result files in out/")
    args = ap.parse_args()
    out_dir = Path(__file__).resolve().parent / "out"
    out_dir.mkdir(exist_ok=True)
    log = out_dir / f"{args.name}.jsonl"
    rows = [json.loads(x) for x in log.read_text().splitlines()] if log.exists() and not args.fresh else []
    done = {r["set"] for r in rows}
    for k in range(args.first, args.first + args.sets):
        if k in done:
            continue
        t0 = time.perf_counter()
        r = one_set(args.cache, k, args.boards)
        rows.append(r)
        with log.open("a") as f:
            f.write(json.dumps(r) + "\n")
        print(f"set {k}: ml exact camera shape {r['ml_exact_shape_mm']:.4f} mm (predicted "
              f"{r['ml_exact_pred_shape_mm']:.4f}), dispersion {r['exact_image_dispersion']:.2f}; "
              f"{time.perf_counter() - t0:.0f} s", flush=True)
    rows = [r for r in rows if args.first <= r["set"] < args.first + args.sets]
    s = summarise(rows)
    report(s, args)
    (out_dir / f"{args.name}.json").write_text(json.dumps({"summary": s, "rows": rows}, indent=1))
    record(s, args)


def report(s: dict, args) -> None:
    print(f"\n{s['sets']} independent sets (realistic renders; working volume 380-520 mm); ratio = predicted / "
          f"actual RMS, with its bootstrap sd and 16-84 % interval over the sets")
    print(f"{'variant':<56} {'quantity':<13} {'actual':>9} {'predicted':>10} {'ratio':>6} {'sd':>5} {'16-84 %':>12}")
    for label, _ in VARIANTS:
        if label not in s:
            continue
        for q, name in (("frame", "camera frame"), ("shape", "shape")):
            v = s[label][q]
            print(f"{label:<56} {name:<13} {v['actual_rms']:>6.4f} mm {v['predicted_rms']:>7.4f} mm "
                  f"{v['ratio']:>6.2f} {v['ratio_sd']:>5.2f} {v['ratio_p16']:>5.2f}-{v['ratio_p84']:.2f}")
    for pre, label in (("exact_", "exact camera"), ("cal_", "calibrated camera")):
        v = s[pre + "image_dispersion"]
        print(f"images' dispersion as estimated ({label}): mean {v['mean']:.2f}, sd {v['sd']:.2f}, "
              f"below 1 in {v['below_1']} of {s['sets']} sets")
    for label, _ in VARIANTS:
        if label in s and not label.startswith("ml,"):
            print(f"what the sigma covers ({label}, first set): {s[label]['covers']}")


def record(s: dict, args) -> None:
    from results import between, figure, record as rec

    figs = []
    for label, pre, lo, hi in (("circle method (ml), exact camera", "ml_exact", 0.9, 1.1),
                               ("circle method (ml), calibrated camera", "ml_cal", 0.8, 1.2),
                               ("Zhou, exact camera", "zhou_exact", 0.9, 1.1),
                               ("Zhou, calibrated camera", "zhou_cal", 0.8, 1.2)):
        if label not in s:
            continue
        for q, name in (("frame", "camera frame"), ("shape", "shape")):
            v = s[label][q]
            figs.append(figure(f"{pre}_{q}_predicted", f"{label}: predicted {name} point sigma", v["predicted_rms"],
                               "mm", statistic=f"RMS over {s['sets']} sets, 380-520 mm; bootstrap sd of the ratio "
                               f"{v['ratio_sd']:.2f}", reference=(f"actual {name} error", v["actual_rms"], "mm"),
                               target=between(lo, hi, "x", of="ratio")))
    rec(args.name, figs)


if __name__ == "__main__":
    main()
