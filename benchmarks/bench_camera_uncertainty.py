"""Benchmark: is the predicted point uncertainty honest when the camera is calibrated too?

``--sets`` independent data sets, each: its own 16 rendered chessboard views (9x7 inner
corners, 8 mm squares, realistic imaging, the calibration capture's poses) to calibrate
the camera (``calibrate_camera``, default options: 5 coefficients, saddle-fit corners),
then its own 12 rendered realistic circle images (50 mm target) to calibrate the plane
(``ml``) with that camera, the plane's dependence on the intrinsics propagated
(:func:`lightplane.calibrate.propagate_camera`).  Against the exact truth (the default
camera and plane of the renderer), over the working volume 380–520 mm
(``lightplane.shapes.plane_accuracy``): the RMS error of the triangulated points in the
camera frame and after the best rigid alignment (shape), against the predicted RMS sigma
of each (all sources, and the plane-only figure); also the normal angle and the offset
at the optical axis, predicted vs actual.  Honest: predicted / actual within 25 %.

Renders are cached as compressed .npz under ``--cache`` (default /tmp/lightplane_bench_camera_unc).

    .venv/bin/python benchmarks/bench_camera_uncertainty.py [--sets 20]
    .venv/bin/python benchmarks/bench_camera_uncertainty.py --render-only --sets 20   # fill the cache
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

BOARD = (9, 7)
SQUARE_MM = 8.0
N_BOARDS = 16
N_CIRCLES = 12


def _chessboards(cache: Path, k: int, n: int = N_BOARDS) -> list:
    from lightplane.simulate.render import render_chessboard_dataset, settings_tag

    f = cache / f"boards_{BOARD[0]}x{BOARD[1]}_n{n}_s{1000 + k}_{settings_tag()}.npz"
    if f.exists():
        return list(np.load(f)["images"])
    ds = render_chessboard_dataset(n=n, seed=1000 + k, board=BOARD, square_mm=SQUARE_MM, difficulty="realistic")
    _save(f, ds.images)
    return list(ds.images)


def _circles(cache: Path, k: int, n: int = N_CIRCLES) -> list:
    from lightplane.simulate.render import render_circle_dataset, settings_tag

    f = cache / f"circles_n{n}_s{2000 + k}_{settings_tag()}.npz"
    if f.exists():
        return list(np.load(f)["images"])
    ds = render_circle_dataset(n=n, seed=2000 + k, difficulty="realistic")
    _save(f, ds.images)
    return list(ds.images)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sets", type=int, default=20)
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/lightplane_bench_camera_unc"))
    ap.add_argument("--render-only", action="store_true")
    ap.add_argument("--summary", action="store_true", help="only summarise the sets already in out/")
    ap.add_argument("--fresh", action="store_true", help="forget the sets already in out/")
    args = ap.parse_args()
    if args.render_only:
        for k in range(args.first, args.first + args.sets):
            t0 = time.perf_counter()
            _chessboards(args.cache, k)
            _circles(args.cache, k)
            print(f"set {k} rendered in {time.perf_counter() - t0:.0f} s", flush=True)
        return
    run(args)


def _save(f: Path, images) -> None:
    f.parent.mkdir(parents=True, exist_ok=True)
    tmp = f.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, images=np.stack(images))
    tmp.replace(f)


def one_set(cache: Path, k: int) -> dict:
    """Calibrate camera and plane from set ``k``; errors against the truth and predicted sigmas."""
    from lightplane.calibrate import observe_images, solve_observations
    from lightplane.intrinsics import calibrate_camera
    from lightplane.measure import triangulate
    from lightplane.shapes import rigid_align
    from lightplane.simulate.geometry import default_camera, default_plane
    from lightplane.uncertainty import volume_sigma, working_volume_grid

    t0 = time.perf_counter()
    cam_true, plane_true = default_camera(), default_plane()
    res = calibrate_camera(_chessboards(cache, k), BOARD, SQUARE_MM)
    cam = res.camera
    obs = observe_images(_circles(cache, k), cam, 50.0, workers=2)
    cal = solve_observations(obs, cam, 50.0, "ml")
    plane = cal.plane
    vol = working_volume_grid(cam_true, plane_true, distance_mm=(380.0, 520.0))
    est = triangulate(cam, plane, vol.uv)
    e = est - vol.points
    ok = np.all(np.isfinite(e), axis=1)
    frame = float(np.sqrt(np.mean(np.sum(e[ok] ** 2, axis=1))))
    shape = rigid_align(est[ok], vol.points[ok]).rms_mm
    pred = volume_sigma(cam, plane, vol)
    C = np.asarray(plane.covariance)
    Cc = np.asarray(plane.meta["camera_jacobian"]["covariance_camera"])
    h = np.append(plane_true.point_on_axis(), 1.0)
    p_true = np.r_[cam_true.fx, cam_true.fy, cam_true.cx, cam_true.cy, cam_true.dist]
    p_est = np.r_[cam.fx, cam.fy, cam.cx, cam.cy, cam.dist]
    return {
        "set": k, "views": len(res.used), "images_used": cal.n_used, "corner_sigma_px": res.options["covariance_sigma_px"],
        "frame_mm": frame, "shape_mm": shape,
        "pred_frame_mm": pred.camera_frame_mm, "pred_shape_mm": pred.shape_mm, "pred_plane_only_mm": pred.plane_only_mm,
        "angle_deg": float(np.degrees(plane.angle_to(plane_true))),
        "offset_mm": float(plane.signed_distance(plane_true.point_on_axis()[None])[0]),
        "pred_angle_deg": float(np.degrees(np.sqrt(np.trace((C + Cc)[:3, :3])))),
        "pred_angle_plane_only_deg": float(np.degrees(np.sqrt(np.trace(C[:3, :3])))),
        "pred_offset_mm": float(np.sqrt(h @ (C + Cc) @ h)), "pred_offset_plane_only_mm": float(np.sqrt(h @ C @ h)),
        "cx_err_px": float(p_est[2] - p_true[2]), "cy_err_px": float(p_est[3] - p_true[3]),
        "cx_sigma_px": float(np.sqrt(cam.covariance[2, 2])), "cy_sigma_px": float(np.sqrt(cam.covariance[3, 3])),
        "intrinsics_mahalanobis2": float((p_est - p_true) @ np.linalg.pinv(cam.covariance) @ (p_est - p_true)),
        "seconds": time.perf_counter() - t0,
    }


def summarise(rows: list[dict]) -> dict:
    a = {k: np.array([r[k] for r in rows], float) for k in rows[0] if k != "set"}
    rms = {k: float(np.sqrt(np.mean(v**2))) for k, v in a.items()}
    out = {"sets": len(rows)}
    for name, act, pred in (("camera frame", "frame_mm", "pred_frame_mm"), ("shape", "shape_mm", "pred_shape_mm"),
                            ("camera frame, plane-only sigma", "frame_mm", "pred_plane_only_mm"),
                            ("normal angle", "angle_deg", "pred_angle_deg"),
                            ("offset at the axis", "offset_mm", "pred_offset_mm"),
                            ("offset, plane-only sigma", "offset_mm", "pred_offset_plane_only_mm")):
        out[name] = {"actual_rms": rms[act], "predicted_rms": rms[pred], "ratio": rms[pred] / rms[act]}
    # sampling tolerance of an RMS over n sets of a ~1-dof error: relative sd ~ 1/sqrt(2n)
    out["rms_relative_sd"] = float(1 / np.sqrt(2 * len(rows)))
    out["mean_intrinsics_mahalanobis2"] = float(np.mean(a["intrinsics_mahalanobis2"]))
    out["median_seconds_per_set"] = float(np.median(a["seconds"]))
    return out


def run(args) -> None:
    out_dir = Path(__file__).resolve().parent / "out"
    out_dir.mkdir(exist_ok=True)
    log = out_dir / "bench_camera_uncertainty.jsonl"
    rows = [json.loads(line) for line in log.read_text().splitlines()] if log.exists() and not args.fresh else []
    done = {r["set"] for r in rows}
    if not args.summary:
        for k in range(args.first, args.first + args.sets):
            if k in done:
                continue
            r = one_set(args.cache, k)
            rows.append(r)
            with log.open("a") as f:
                f.write(json.dumps(r) + "\n")
            print(f"set {k}: camera frame {r['frame_mm']:.4f} mm (predicted {r['pred_frame_mm']:.4f}), shape "
                  f"{r['shape_mm']:.4f} mm (predicted {r['pred_shape_mm']:.4f}), plane-only sigma "
                  f"{r['pred_plane_only_mm']:.4f} mm; {r['seconds']:.0f} s", flush=True)
    s = summarise(rows)
    print(f"\n{s['sets']} independent sets (each: {N_BOARDS} chessboard views {BOARD[0]}x{BOARD[1]}, "
          f"{N_CIRCLES} circle images, realistic renders), working volume 380-520 mm")
    print(f"{'quantity':<32} {'actual RMS':>11} {'predicted':>10} {'pred/act':>8}")
    for name in ("camera frame", "shape", "camera frame, plane-only sigma", "normal angle", "offset at the axis",
                 "offset, plane-only sigma"):
        v = s[name]
        unit = "deg" if "angle" in name else "mm"
        print(f"{name:<32} {v['actual_rms']:>8.4f} {unit:<3}{v['predicted_rms']:>9.4f} {v['ratio']:>8.2f}")
    print(f"sampling sd of an RMS over {s['sets']} sets: ~{100 * s['rms_relative_sd']:.0f} %; "
          f"mean Mahalanobis² of the intrinsics' error {s['mean_intrinsics_mahalanobis2']:.1f} (9 expected)")
    (out_dir / "bench_camera_uncertainty.json").write_text(json.dumps({"summary": s, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
