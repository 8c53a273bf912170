"""Benchmark: do a board's printed edges move the stripe centres of Zhou's method?

Per target (chessboard 9x6 of 8 mm, circle grid 9x6 of 8 mm with 4 mm dots, ChArUco 8x6 of 11 mm
squares with 8 mm DICT_4X4_50 markers), ``--seeds`` rendered sets of 6 realistic poses crossed by
the stripe, each pose as a dark laser frame (3 % of the ambient light) with a lit pattern frame
(laser off), and as a lit laser frame with its laser-off frame.  Against the exact truth:

- per pose, the mean offset of the stripe centres across the true line (the light plane cut by
  the true board plane, undistorted px): an edge under the stripe moves a whole run of centres
  the same way, which no number of poses averages out;
- the plane of all the sets' poses together (Zhou's method, ``calibrate_plane_board``), its
  normal's angle to the truth (deg) and its stated σ.

Each with the centres kept only on light, even print (``BoardPlaneOptions(reflectance=True)``, the
default: :func:`lightplane.plane.zhou.even_reflectance`) and with every centre kept (the laser-off
frame only subtracted, as before): same images, same run.
Renders are cached under ``--cache`` (default /tmp/lightplane_bench_board_stripe).

    .venv/bin/python benchmarks/bench_board_stripe.py [--seeds 1,2,5]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

N_POSES = 6


def _targets() -> dict:
    from lightplane.camera.targets import Target

    return {"chessboard": Target("chessboard", 9, 6, 8.0), "circles": Target("circles", 9, 6, 8.0, dot_mm=4.0),
            "charuco": Target("charuco", 8, 6, 11.0, 8.0, "DICT_4X4_50")}


def _renders(cache: Path, kind: str, seed: int, dark: bool):
    """(laser frames, lit laser-off frames, true poses [(R, t)], camera, true plane) of one set (cached)."""
    from lightplane.camera.model import Camera
    from lightplane.plane.model import LightPlane
    from lightplane.simulate.render import BoardOptions, render_target_dataset, settings_tag

    f = cache / f"{kind}_n{N_POSES}_s{seed}_{'dark' if dark else 'lit'}_{settings_tag()}.npz"
    if not f.exists():
        ds = render_target_dataset(_targets()[kind], N_POSES, seed, BoardOptions(
            difficulty="realistic", with_stripe=True, laser_off=True, dark_laser=dark))
        v = ds.truth["views"]
        on = [ds.images[ds.names.index(e["file"])] for e in v]
        off = [ds.images[ds.names.index(e["file_laser_off"])] for e in v]
        R = [np.asarray(e["T_cam_board"]["R"], float) for e in v]
        t = [np.asarray(e["T_cam_board"]["t"], float) for e in v]
        f.parent.mkdir(parents=True, exist_ok=True)
        tmp = f.with_suffix(".tmp.npz")
        np.savez_compressed(tmp, on=np.stack(on), off=np.stack(off), R=np.stack(R), t=np.stack(t),
                            camera=json.dumps(ds.camera.to_dict()), plane=json.dumps(ds.truth["plane"]))
        tmp.replace(f)
    z = np.load(f)
    pl = json.loads(str(z["plane"]))
    return (list(z["on"]), list(z["off"]), list(zip(z["R"], z["t"])), Camera.from_dict(json.loads(str(z["camera"]))),
            LightPlane(np.asarray(pl["normal"], float), float(pl["d"])))


def _offsets(cam, plane, poses_true, stripes) -> list[float]:
    """Per pose, the mean offset (undistorted px) of its stripe centres across the true line."""
    out = []
    for (R, t), uv in zip(poses_true, stripes):
        nb = R[:, 2]
        u = np.cross(plane.normal, nb)
        u /= np.linalg.norm(u)
        p0 = np.linalg.solve(np.stack([plane.normal, nb, u]), [-plane.d, nb @ t, u @ t])
        a, b = cam.project(np.stack([p0 - 50 * u, p0 + 50 * u]), distort=False)
        nrm = np.array([a[1] - b[1], b[0] - a[0]]) / np.linalg.norm(b - a)
        out.append(float(np.mean((cam.undistort_points(uv) - a) @ nrm)) if len(uv) else float("nan"))
    return out


def one_target(cache: Path, kind: str, seeds: list[int], dark: bool, reflectance: bool) -> dict:
    from lightplane.plane.zhou import BoardFrames, BoardPlaneOptions, find_board_views, plane_from_board_stripes

    target = _targets()[kind]
    opts = BoardPlaneOptions(reflectance=reflectance)
    offs, poses, stripes = [], [], []
    t0 = time.perf_counter()
    for s in seeds:
        on, off, truth_poses, cam, plane = _renders(cache, kind, s, dark)
        fr = BoardFrames(on, pattern_images=off) if dark else BoardFrames(on, background_images=off)
        v = find_board_views(fr, cam, target, options=opts, min_stripe_points=opts.min_points_per_view)
        used = [int(n.split()[-1]) for n in v.names]
        offs += _offsets(cam, plane, [truth_poses[i] for i in used], v.stripes)
        poses += v.poses
        stripes += v.stripes
    z = plane_from_board_stripes(cam, poses, stripes)
    cov = np.asarray(z.plane.covariance)
    o = np.asarray(offs)
    return {"target": kind, "frames": "dark laser + pattern" if dark else "lit laser + laser-off",
            "reflectance": reflectance, "poses": len(poses), "centres": int(len(z.points_cam_mm)),
            "offset_rms_px": float(np.sqrt(np.nanmean(o**2))), "offset_max_px": float(np.nanmax(np.abs(o))),
            "angle_deg": float(np.degrees(z.plane.angle_to(plane))),
            "sigma_deg": float(np.degrees(np.sqrt(np.trace(cov[:3, :3])))),
            "seconds": time.perf_counter() - t0}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="1,2,5")
    ap.add_argument("--targets", default="chessboard,circles,charuco")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/lightplane_bench_board_stripe"))
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    rows = []
    print(f"{'target':<11} {'frames':<22} {'centres':<11} {'poses':>5} {'centres':>7} {'offset RMS':>11} "
          f"{'max':>9} {'angle':>10} {'sigma':>10}")
    for kind in args.targets.split(","):
        for dark in (True, False):
            for refl in (False, True):
                r = one_target(args.cache, kind, seeds, dark, refl)
                rows.append(r)
                print(f"{kind:<11} {r['frames']:<22} {'even print' if refl else 'all':<11} {r['poses']:>5} "
                      f"{r['centres']:>7} {r['offset_rms_px']:>8.4f} px {r['offset_max_px']:>6.4f} px "
                      f"{r['angle_deg']:>6.4f} deg {r['sigma_deg']:>6.4f} deg", flush=True)
    out_dir = Path(__file__).resolve().parent / "out"
    out_dir.mkdir(exist_ok=True)
    (out_dir / "bench_board_stripe.json").write_text(json.dumps(rows, indent=1))
    record(rows, seeds)


def record(rows: list[dict], seeds: list[int]) -> None:
    from results import at_most, figure, record as rec

    figs = []
    for r in rows:
        if not r["reflectance"]:
            continue
        base = next(b for b in rows if b["target"] == r["target"] and b["frames"] == r["frames"]
                    and not b["reflectance"])
        tag = f"{r['target']}_{'dark' if r['frames'].startswith('dark') else 'lit'}"
        stat = f"{r['poses']} rendered poses ({len(seeds)} sets of {N_POSES}), {r['frames']}"
        figs.append(figure(f"{tag}_centre_offset", f"Zhou, {r['target']}, {r['frames']}: stripe centres' offset "
                           "across the true line, per pose", r["offset_rms_px"], "px", statistic="RMS over " + stat,
                           reference=("every centre kept", base["offset_rms_px"], "px")))
        figs.append(figure(f"{tag}_plane_angle", f"Zhou, {r['target']}, {r['frames']}: plane normal's angle to the "
                           "truth", r["angle_deg"], "deg", statistic=stat + f"; stated sigma {r['sigma_deg']:.4f} deg",
                           reference=("every centre kept", base["angle_deg"], "deg"),
                           target=at_most(0.01, "deg") if r["target"] == "charuco" else None))
    rec("bench_board_stripe", figs)


if __name__ == "__main__":
    main()
