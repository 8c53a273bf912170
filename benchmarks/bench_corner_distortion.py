"""Saddle corners under lens distortion: bent edges (the default) against straight ones, with exact truth.

The blurred-saddle corner fit (``lightplane.camera.corners.fit_corners``) models the two board edges
through a corner; a wide lens bends them across the fit's window and straight model edges pull the
corner towards the image centre.  By default the model's edges are bent as the board's own grid
lines are at the corner (``CornerFitOptions(bent_edges=True)``); ``bent_edges=False`` is the straight
model, the fit before.  On the same renders, in one run:

1. the corners of every view against the renderer's exact ones (``corners_px``), as
   ``calibrate_camera`` finds them (findChessboardCornersSB, cornerSubPix, Förstner, the saddle fit):
   RMS error, and the mean error along the outward radius by distance from the principal point;
2. the time of that detection per view (CPU time of this process, the minimum over ``--repeats``,
   straight and bent interleaved), and of the saddle fit alone;
3. ``calibrate_camera`` with the defaults (after a first calibration it fits, in that camera's lens
   frame, the corners whose windows its lens bends, and solves again): every intrinsic parameter's
   error over its sigma (the full covariance), the worst of them, with the bent edges (the default)
   and with straight ones (the default before); on the distorted sets also without the lens-frame
   refit (``intrinsics.LENS_REFIT_BEND_PX`` set to infinity), with bent edges (what they give alone)
   and with straight ones (the saddle fit's pull on the intrinsics).

Sets: ``rational`` (``lens_camera("rational")``: 6 mm, ~64 px of barrel distortion at the image
corners; boards at 180–330 mm to fill it; 8 coefficients), ``fisheye`` (2.6 mm equidistant, boards at
110–200 mm), ``plumb_bob`` (the default 16 mm camera, the 30-view calibration capture of
``bench_calibrate.py``, 5 coefficients), and the narrow-lens sets of ``bench_camera_uncertainty.py``
(``narrow<k>``: 16 views of 9x7 corners, seed 1000 + k, the default camera).  All realistic imaging,
15x11 corners of 8 mm where not said.  Renders and exact corners are cached under ``--cache``.

    .venv/bin/python benchmarks/bench_corner_distortion.py [--sets rational,fisheye,plumb_bob] [--narrow 4]
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

import lightplane.camera.corners as corners_module
import lightplane.camera.intrinsics as intrinsics_module
from lightplane.camera.corners import CornerFitOptions, _detect_board, fit_corners
from lightplane.camera.intrinsics import CameraCalibrationOptions, calibrate_camera
from lightplane.camera.lens import coeff_names
from lightplane.simulate.render import CALIBRATION_CAPTURE, BoardOptions, render_chessboard_dataset, settings_tag
from lightplane.simulate.scene import default_camera, lens_camera
from results import at_most, figure, record, within

RADIUS_BINS_PX = (0.0, 200.0, 400.0, 600.0, 2000.0)
#: the corners "at large radius": the wide lens bends their windows' edges by ~0.1 px and more
LARGE_RADIUS_PX = 400.0


@dataclass
class BoardSet:
    """One set of rendered views: the camera, its lens model, the board, images and exact corners."""

    name: str
    camera: object
    model: str
    board: tuple
    square_mm: float
    images: list
    corners: list


def _render(name: str, cache: Path) -> BoardSet:
    """The set ``name`` (see the module doc), rendered once and cached (images and exact corners)."""
    cap, n, seed, cam, model = CALIBRATION_CAPTURE, 20, 1, default_camera(), "plumb_bob"
    if name == "rational":
        cam, model, cap = lens_camera("rational"), "rational", replace(cap, distance_mm=(180.0, 330.0))
    elif name == "fisheye":
        cam, model, cap = lens_camera("fisheye"), "fisheye", replace(cap, distance_mm=(110.0, 200.0))
    elif name == "plumb_bob":
        n = 30
    elif name.startswith("narrow"):
        n, seed, cap = 16, 1000 + int(name.removeprefix("narrow")), replace(cap, board=(9, 7), square_mm=8.0)
    else:
        raise SystemExit(f"unknown set {name!r}")
    f = cache / f"{name}_{cap.board[0]}x{cap.board[1]}_n{n}_s{seed}_{settings_tag()}.npz"
    if not f.exists():
        print(f"rendering {f.name} ...", flush=True)
        ds = render_chessboard_dataset(n, seed, BoardOptions(difficulty="realistic", capture=cap), camera=cam)
        cache.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(f, images=np.stack(ds.images),
                            corners=np.stack([np.asarray(v["corners_px"]) for v in ds.truth["views"]]))
    d = np.load(f)
    return BoardSet(name, cam, model, cap.board, cap.square_mm, list(d["images"]), list(d["corners"]))


@contextlib.contextmanager
def corner_default(bent: bool, refit: bool = True):
    """``calibrate_camera`` (and ``_detect_board``) with the saddle model's edges bent or straight, and
    with or without the refit in the lens frame of a first calibration."""
    options, bend = corners_module.CornerFitOptions, intrinsics_module.LENS_REFIT_BEND_PX
    corners_module.CornerFitOptions = functools.partial(options, bent_edges=bent)  # type: ignore[misc]
    intrinsics_module.LENS_REFIT_BEND_PX = bend if refit else np.inf
    try:
        yield
    finally:
        corners_module.CornerFitOptions = options  # type: ignore[misc]
        intrinsics_module.LENS_REFIT_BEND_PX = bend


def corner_errors(s: BoardSet, repeats: int) -> dict:
    """Section 1 and 2 for one set: per variant the corners' errors (N, 2) px, their error along the
    outward radius and radius (N,), and per view the detection's and the saddle fit's CPU time (s)."""
    out: dict = {v: {"err": [], "radial": [], "r": [], "detect_s": [], "fit_s": []} for v in ("straight", "bent")}
    centre = np.array([s.camera.cx, s.camera.cy])
    for img, truth in zip(s.images, s.corners):
        times = {v: np.full((repeats, 2), np.inf) for v in out}
        found = {}
        for k in range(repeats):
            for v, bent in (("straight", False), ("bent", True)):
                with corner_default(bent):
                    t0 = time.process_time()
                    c, q, _, _ = _detect_board(img, s.board, True, "saddle")
                    t1 = time.process_time()
                    if c is not None:
                        fit_corners(img, c, s.board, CornerFitOptions(bent_edges=bent))
                    times[v][k] = (t1 - t0, time.process_time() - t1)
                found[v] = q
        for v, q in found.items():
            if q is None:
                continue
            tr = truth if np.abs(q - truth).max() < np.abs(q - truth[::-1]).max() else truth[::-1]
            e, o = q - tr, tr - centre
            r = np.linalg.norm(o, axis=1)
            out[v]["err"].append(e)
            out[v]["radial"].append(np.sum(e * o, axis=1) / r)
            out[v]["r"].append(r)
            out[v]["detect_s"].append(times[v][:, 0].min())
            out[v]["fit_s"].append(times[v][:, 1].min())
    return {v: {k: (np.concatenate(x) if k in ("err", "radial", "r") else np.asarray(x)) for k, x in d.items()}
            for v, d in out.items()}


def calibration_errors(s: BoardSet, bent: bool, refit: bool = True) -> dict:
    """Section 3: ``calibrate_camera``'s errors over sigma per parameter, the worst, the time."""
    with corner_default(bent, refit):
        t0 = time.process_time()
        cal = calibrate_camera(s.images, s.board, s.square_mm, options=CameraCalibrationOptions(model=s.model))
        dt = time.process_time() - t0
    cam = s.camera
    truth = np.concatenate([[cam.fx, cam.fy, cam.cx, cam.cy], cam.dist])
    est = np.concatenate([[cal.camera.fx, cal.camera.fy, cal.camera.cx, cal.camera.cy], cal.camera.dist])
    z = {}
    for nm, t, e in zip(("fx", "fy", "cx", "cy") + coeff_names(s.model), truth, est):
        sd = cal.std.get(nm, float("nan"))
        if 0 < sd < np.inf:  # held parameters (0) and undetermined ones (inf: the rational k's) left out
            z[nm] = (e - t) / sd
    worst = max(z, key=lambda k: abs(z[k]))
    return {"z": z, "worst": worst, "worst_sigma": abs(z[worst]), "rms_px": cal.rms_px, "cpu_s": dt,
            "refit": cal.options.get("lens_frame_refit_corners"), "views": len(cal.used)}


def _bias_line(d: dict) -> str:
    parts = []
    for lo, hi in zip(RADIUS_BINS_PX[:-1], RADIUS_BINS_PX[1:]):
        m = (d["r"] >= lo) & (d["r"] < hi)
        if m.sum() >= 10:
            se = d["radial"][m].std(ddof=1) / np.sqrt(m.sum())
            parts.append(f"{lo:.0f}-{hi:.0f} px: {d['radial'][m].mean():+.4f} ± {se:.4f} ({m.sum()})")
    return "; ".join(parts)


def _far(d: dict) -> tuple[float, float, int]:
    """Mean radial error at r >= LARGE_RADIUS_PX, its standard error, the number of corners."""
    m = d["r"] >= LARGE_RADIUS_PX
    x = d["radial"][m]
    return float(x.mean()), float(x.std(ddof=1) / np.sqrt(max(x.size, 1))), int(x.size)


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


def report_set(s: BoardSet, ce: dict, cals: dict) -> dict:
    """Print one set's rows; its numbers for the figures."""
    print(f"{s.name}: {s.model}, {len(s.images)} views of {s.board[0]}x{s.board[1]} corners, {s.camera!r}")
    for v in ("straight", "bent"):
        d = ce[v]
        print(f"  corners, {v} edges: RMS {_rms(d['err']):.5f} px over {len(d['r'])}; mean error along the "
              f"outward radius: {_bias_line(d)}; detection {np.sum(d['detect_s']):.2f} s CPU "
              f"(saddle fit alone {np.sum(d['fit_s']):.2f} s)")
    for key, c in cals.items():
        print(f"  calibrate_camera, {key}: worst {c['worst']} {c['worst_sigma']:.2f} sigma, RMS {c['rms_px']:.4f} px, "
              f"{c['refit']} corners refitted in the lens frame, {c['cpu_s']:.1f} s CPU; "
              + ", ".join(f"{k} {v:+.2f}" for k, v in c["z"].items()))
    det = np.sum(ce["bent"]["detect_s"]) / np.sum(ce["straight"]["detect_s"])
    fit = np.sum(ce["bent"]["fit_s"]) / np.sum(ce["straight"]["fit_s"])
    print(f"  time bent / straight: detection {det:.3f}, saddle fit alone {fit:.3f}")
    return {"rms": {v: _rms(ce[v]["err"]) for v in ce}, "far": {v: _far(ce[v]) for v in ce},
            "detect_s": {v: float(np.sum(ce[v]["detect_s"])) for v in ce},
            "fit_s": {v: float(np.sum(ce[v]["fit_s"])) for v in ce}, "cal": cals, "views": len(ce["bent"]["detect_s"])}


def figures(res: dict) -> list[dict]:
    """The headline figures: per distorted set the worst parameter and the bias at large radius
    (bent against straight), the narrow sets' corner RMS and worst parameter, the detection time."""
    figs = []
    for name, r in res.items():
        if name.startswith("narrow"):
            continue
        new, old = r["cal"]["default"], r["cal"]["straight edges, lens-frame refit"]
        figs.append(figure(f"{name}_worst_sigma", f"{name} renders: intrinsics' worst error, default corners",
                           new["worst_sigma"], "sigma",
                           reference=("straight saddle edges, lens-frame refit", old["worst_sigma"], "sigma"),
                           statistic=f"worst |error| / sigma over the parameters, {new['views']} views; without "
                                     f"the refit {r['cal']['bent edges, no refit']['worst_sigma']:.2f} sigma, "
                                     f"straight edges {r['cal']['straight edges, no refit']['worst_sigma']:.2f}",
                           target=at_most(3.0, "sigma")))
        (mb, sb, nb), (ms, _, _) = r["far"]["bent"], r["far"]["straight"]
        if nb >= 20:
            figs.append(figure(f"{name}_corner_bias_far", f"{name} renders: corner error along the radius at "
                               f">= {LARGE_RADIUS_PX:.0f} px", mb, "px", reference=("straight saddle edges", ms, "px"),
                               statistic=f"mean over {nb} corners against the exact ones; target 4 standard errors",
                               target=within(4 * sb, "px")))
    narrow = [r for n, r in res.items() if n.startswith("narrow") or n == "plumb_bob"]
    if narrow:
        new = float(np.mean([r["cal"]["default"]["worst_sigma"] for r in narrow]))
        old = float(np.mean([r["cal"]["straight edges, lens-frame refit"]["worst_sigma"] for r in narrow]))
        figs.append(figure("narrow_worst_sigma", "narrow lens: intrinsics' worst error, default corners", new, "sigma",
                           reference=("straight saddle edges, lens-frame refit", old, "sigma"),
                           statistic=f"worst |error| / sigma over the parameters, mean over {len(narrow)} sets",
                           target=at_most(3.0, "sigma")))
        new = float(np.sqrt(np.mean([r["rms"]["bent"] ** 2 for r in narrow])))
        old = float(np.sqrt(np.mean([r["rms"]["straight"] ** 2 for r in narrow])))
        figs.append(figure("narrow_corner_rms", "narrow lens: corner error RMS, default corners", new, "px",
                           reference=("straight saddle edges", old, "px"),
                           statistic=f"RMS over {len(narrow)} sets' corners against the exact ones",
                           target=at_most(1.02, "x", of="ratio")))
    new = sum(r["detect_s"]["bent"] for r in res.values())
    old = sum(r["detect_s"]["straight"] for r in res.values())
    views = sum(r["views"] for r in res.values())
    figs.append(figure("corner_detection_time", "chessboard corner detection, default corners (CPU)", new, "s",
                       reference=("straight saddle edges", old, "s"),
                       statistic=f"CPU time summed over {views} views of every set (min of the repeats)",
                       target=at_most(1.10, "x", of="ratio")))
    return figs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sets", default="rational,fisheye,plumb_bob")
    ap.add_argument("--narrow", type=int, default=4, help="narrow-lens sets of bench_camera_uncertainty.py")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/lightplane_bench_corner_distortion"))
    a = ap.parse_args()
    names = [n for n in a.sets.split(",") if n] + [f"narrow{k}" for k in range(a.narrow)]
    sets = [_render(n, a.cache) for n in names]
    fit_corners(sets[0].images[0], sets[0].corners[0], sets[0].board)  # compile or load the kernels
    res = {}
    for s in sets:
        ce = corner_errors(s, a.repeats)
        cals = {"default": calibration_errors(s, True),
                "straight edges, lens-frame refit": calibration_errors(s, False)}
        if not s.name.startswith("narrow"):
            cals["bent edges, no refit"] = calibration_errors(s, True, refit=False)
            cals["straight edges, no refit"] = calibration_errors(s, False, refit=False)
        res[s.name] = report_set(s, ce, cals)
    narrow = {n: r for n, r in res.items() if n.startswith("narrow")}
    if narrow:
        for key in ("default", "straight edges, lens-frame refit"):
            w = [r["cal"][key]["worst_sigma"] for r in narrow.values()]
            print(f"narrow sets, calibrate_camera {key}: worst |error| / sigma {np.round(w, 2).tolist()}, "
                  f"mean {np.mean(w):.2f}")
    record("bench_corner_distortion", figures(res))


if __name__ == "__main__":
    main()
