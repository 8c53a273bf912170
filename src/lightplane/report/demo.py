"""The demo: the whole chain on a synthetic data set with exact ground truth.

Stages (each runs if its part of lightplane exists, else it is reported as skipped):

1. the sensor: lightplane's default camera and light plane (docs/conventions.md §Default sensor), the truth;
2. render a data set (:mod:`lightplane.simulate.render`): chessboards for the camera,
   circle-target images for the light plane, chessboards with the stripe for the
   cross-ratio check and Zhou's method, a sphere scan — two processes in parallel;
3. calibrate the camera from the rendered chessboards (Zhang, :mod:`lightplane.camera.intrinsics`);
4. calibrate the light plane from the circle images (:func:`lightplane.plane.calibrate.calibrate_plane`,
   ``ml``, with ``global`` and ``paper`` from the same observations) and compare with the truth
   (:func:`lightplane.evaluate.shapes.plane_accuracy`);
5. Zhou's planar-target plane from the striped chessboards (:mod:`lightplane.plane.zhou`);
6. the cross-ratio evaluation of both planes side by side (paper §4.3, :mod:`lightplane.evaluate.crossratio`);
7. measure the scan (:func:`lightplane.measure.profile.measure_profile`): fit the sphere
   (:func:`lightplane.evaluate.shapes.fit_sphere`);
8. write the report (:mod:`lightplane.report.html`) and ``summary.json``.

Everything lands in ``out``: ``data/`` (the renders, with ``truth.json``),
``camera.json``, ``plane.json``, ``plane_zhou.json``, the scan's cloud ``scan_points.ply`` (and
``scan_points.npy``), ``report/index.html``, ``summary.json``.
"""

from __future__ import annotations

import time
import traceback
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.evaluate.shapes import fit_sphere, plane_accuracy
from lightplane.camera.intrinsics import CameraCalibrationOptions, calibrate_camera
from lightplane.core.io import provenance, provenance as _prov, read_image, write_json
from lightplane.evaluate.crossratio import evaluate_images
from lightplane.measure.pointcloud import make_records, write_cloud
from lightplane.measure.profile import ProfileMeasurer
from lightplane.plane.model import LightPlane
from lightplane.plane.calibrate import PlaneCalibrationOptions, observe_images, solve_observations, uncertainty_summary
from lightplane.plane.zhou import BoardFrames, calibrate_plane_board
from lightplane.report.html import Section, write_report
from lightplane.simulate import render as R
from lightplane.simulate import render_core
from lightplane.core import jit
from lightplane.simulate.scene import default_camera, default_plane

__all__ = ["run_demo", "DEMO_SETTINGS"]

#: Sizes of the rendered data set (kept small: the demo runs in about a minute on 2 cores).
DEMO_SETTINGS = {
    "chessboards": 30,
    "circles": 12,
    "circle_difficulty": "realistic",
    "circle_polarity": "light",
    "striped_boards": 6,
    "scan_kind": "sphere",
    "scan_frames": 31,
    "scan_step_mm": 2.0,
    "diameter_mm": 50.0,
    "board": (9, 6),  # the striped boards (Zhou's method, cross ratios)
    "square_mm": 8.0,
    # the camera's chessboards: the calibration capture of lightplane.simulate.render
    # (CALIBRATION_CAPTURE: 15x11 corners of 8 mm, tilted 25-55 deg, over the whole image),
    # which fixes cx, cy to ~0.3 / 0.2 px (OpenCV std, 30 views) where 12 views of the small
    # 9x6 board left them 1-4 px off (0.1 mm per px at 450 mm in the camera frame)
    "camera_board": (15, 11),
    "camera_square_mm": 8.0,
}


# ----------------------------------------------------------------------------- rendering
def _render_job(kind: str, folder: str, seed: int, settings: dict) -> list[str]:
    """Render one data set into ``folder`` (runs in a worker process)."""
    if kind == "chessboards":
        capture = replace(R.CALIBRATION_CAPTURE, board=settings["camera_board"], square_mm=settings["camera_square_mm"])
        ds = R.render_chessboard_dataset(settings["chessboards"], seed + 1,
                                         R.BoardOptions(difficulty="realistic", capture=capture))
    elif kind == "circles":
        ds = R.render_circle_dataset(settings["circles"], seed,
                                     R.CircleOptions(difficulty=settings["circle_difficulty"],
                                                     polarity=settings["circle_polarity"],
                                                     diameter_mm=settings["diameter_mm"]))
    elif kind == "striped_boards":
        capture = replace(R.STRIPE_CAPTURE, board=settings["board"], square_mm=settings["square_mm"])
        ds = R.render_chessboard_dataset(settings["striped_boards"], seed + 2,
                                         R.BoardOptions(difficulty="realistic", capture=capture, with_stripe=True))
    elif kind == "scan":
        ds = R.render_scan_dataset(settings["scan_kind"], n_frames=settings["scan_frames"],
                                   step_mm=settings["scan_step_mm"], seed=seed + 3)
    else:  # pragma: no cover
        raise ValueError(kind)
    ds.save(folder, force=True)
    return list(ds.names)


def _load_set(folder: Path):
    import json

    truth = json.loads((folder / "truth.json").read_text())
    key = "views" if "views" in truth else ("frames" if "frames" in truth else "images")
    files = [folder / e["file"] for e in truth[key]]
    return truth, files, [read_image(f) for f in files]


class _Stages:
    """Runs the demo's stages, each guarded: a missing module or a failure is reported, not fatal."""

    def __init__(self, say, summary: dict):
        self.say = say
        self.summary = summary
        self.summary.setdefault("stages", {})

    def run(self, name: str, fn, *args, **kw):
        t0 = time.perf_counter()
        try:
            out = fn(*args, **kw)
        except ImportError as e:
            self.say(f"    [skipped] {name}: its module is not available ({e})")
            self.summary["stages"][name] = {"status": "skipped", "reason": f"module not available: {e}"}
            return None
        except LightplaneError as e:
            self.say(f"    [failed] {name}: {e}")
            self.summary["stages"][name] = {"status": "failed", "reason": str(e)}
            return None
        except Exception as e:  # noqa: BLE001 - the demo reports every stage, whatever happens
            self.say(f"    [failed] {name}: {type(e).__name__}: {e}")
            self.summary["stages"][name] = {"status": "failed", "reason": f"{type(e).__name__}: {e}",
                                            "traceback": traceback.format_exc(limit=4)}
            return None
        dt = time.perf_counter() - t0
        self.summary["stages"][name] = {"status": "ok", "seconds": round(dt, 2)}
        return out


def run_demo(out: Path, *, force: bool = False, seed: int = 0, console=None, workers: int | None = None,
             settings: dict | None = None) -> dict:
    """Run the demo into folder ``out``; returns a summary dict (also written as ``summary.json``).

    ``settings`` overrides entries of :data:`DEMO_SETTINGS` (e.g. smaller counts for tests).
    Refuses a non-empty ``out`` without ``force``.
    """

    t_start = time.perf_counter()
    cfg = dict(DEMO_SETTINGS)
    cfg.update(settings or {})
    say = console.print if console is not None else print
    out = _demo_folder(Path(out), force)
    summary: dict = {"provenance": provenance([], {"seed": seed, **{k: v for k, v in cfg.items()}})}
    camera_true = default_camera()
    run = _Run(out, cfg, seed, workers, say, summary, _Stages(say, summary), camera_true, default_plane(), camera_true)
    _stage_sensor(run)
    rendered = _stage_render(run)
    if "chessboards" in rendered:
        _stage_camera(run)
    summary["camera_source"] = run.camera_source
    cal = _stage_plane(run) if "circles" in rendered else None
    zhou = evaluation = None
    if "striped_boards" in rendered:
        zhou = _stage_zhou(run)
        evaluation = _stage_evaluate(run, cal, zhou)
    if "scan" in rendered:
        _stage_scan(run, cal.plane if cal is not None else (zhou.plane if zhou is not None else None))
    if cal is not None:
        _stage_report(run, cal, evaluation)
    summary["seconds"] = round(time.perf_counter() - t_start, 1)
    write_json(out / "summary.json", summary, force=True)
    say(f"done in {summary['seconds']:.0f} s; wrote {out / 'summary.json'}")
    return summary


def _demo_folder(out: Path, force: bool) -> Path:
    """Check and create the demo's folder: a folder, empty unless ``force``, its parent existing."""
    if out.exists() and not out.is_dir():
        raise LightplaneError(f"{out}: exists and is not a folder")
    if out.exists() and any(out.iterdir()) and not force:
        raise LightplaneError(f"{out}: folder exists and is not empty (use --force to replace the demo's files)")
    if not out.parent.is_dir():
        raise LightplaneError(f"{out}: its parent folder {out.parent} does not exist")
    out.mkdir(parents=True, exist_ok=True)
    return out


@dataclass
class _Run:
    """The demo's state as its stages run: where it writes, its settings, its summary, the truth, and the
    camera the later stages use (the true one until the camera stage calibrates one)."""

    out: Path
    cfg: dict
    seed: int
    workers: int | None
    say: Callable
    summary: dict
    st: _Stages
    camera_true: Camera
    plane_true: LightPlane
    camera: Camera
    camera_source: str = "truth (camera stage skipped)"

    @property
    def data(self) -> Path:
        return self.out / "data"


def _stage_sensor(run: _Run) -> None:
    """1. the sensor: the true camera and light plane, saved and summarised."""
    camera_true, plane_true, say = run.camera_true, run.plane_true, run.say
    camera_true.save_json(run.out / "camera_true.json", force=True)
    plane_true.save(run.out / "plane_true.json", force=True)
    say(f"[1] sensor (truth): {camera_true}")
    say(f"    light plane: {plane_true}, crosses the optical axis at z = {plane_true.point_on_axis()[2]:.1f} mm")
    run.summary["truth"] = {"camera": camera_true.to_dict() if hasattr(camera_true, "to_dict") else None,
                            "plane": plane_true.to_dict()}


def _stage_render(run: _Run) -> dict:
    """2. render the data sets (in worker processes); returns the names written per data set."""
    cfg, data = run.cfg, run.data
    data.mkdir(exist_ok=True)
    jobs = {"chessboards": cfg["chessboards"], "circles": cfg["circles"], "striped_boards": cfg["striped_boards"],
            "scan": cfg["scan_frames"]}
    jobs = {k: v for k, v in jobs.items() if v}
    run.say(f"[2] rendering {', '.join(f'{v} {k}' for k, v in jobs.items())} (1280x960, ray-traced, noise) ...")
    if jit.is_cold((render_core.render_modes, render_core.probe_corners, render_core.undistort_grid)):
        jit.notify_compiling()   # the worker processes compile the renderer: say so here, where it is seen

    def render_all():
        import importlib

        importlib.import_module("lightplane.simulate.render")  # ImportError -> stage skipped

        n_workers = 2 if run.workers is None else max(1, int(run.workers))
        done = {}
        if n_workers == 1:
            for k in jobs:
                done[k] = _render_job(k, str(data / k), run.seed, cfg)
        else:
            import multiprocessing as mp

            # spawn, not fork: forking after OpenMP code ran (numba, OpenCV) aborts the child
            with ProcessPoolExecutor(max_workers=n_workers, mp_context=mp.get_context("spawn")) as pool:
                # longest first
                futs = {k: pool.submit(_render_job, k, str(data / k), run.seed, cfg)
                        for k in sorted(jobs, key=lambda k: -jobs[k])}
                for k, f in futs.items():
                    done[k] = f.result()
        return done

    rendered = run.st.run("render", render_all) or {}
    if rendered:
        run.say(f"    wrote {sum(len(v) for v in rendered.values())} images under {data} "
                f"({run.summary['stages']['render']['seconds']:.1f} s)")
    return rendered


def _stage_camera(run: _Run) -> None:
    """3. calibrate the camera from the rendered chessboards (the later stages then use it)."""
    cfg, camera_true = run.cfg, run.camera_true

    def calib_camera():
        import cv2

        truth, files, imgs = _load_set(run.data / "chessboards")
        ic = calibrate_camera(imgs, tuple(cfg["camera_board"]), cfg["camera_square_mm"], names=[f.name for f in files],
                              options=CameraCalibrationOptions(flags=cv2.CALIB_FIX_K3))
        return ic

    run.say(f"[3] calibrating the camera from {cfg['chessboards']} rendered chessboards ...")
    ic = run.st.run("camera", calib_camera)
    if ic is None:
        return
    camera = run.camera = ic.camera
    run.camera_source = "calibrated from rendered chessboards"
    camera.save_json(run.out / "camera.json", force=True)
    errs = {"fx_px": camera.fx - camera_true.fx, "fy_px": camera.fy - camera_true.fy,
            "cx_px": camera.cx - camera_true.cx, "cy_px": camera.cy - camera_true.cy}
    run.summary["camera"] = {"rms_px": ic.rms_px, "views": len(ic.used), "error_vs_truth_px": errs,
                             "std_px": {k: ic.std[k] for k in ("fx", "fy", "cx", "cy")}}
    run.say(f"    RMS reprojection {ic.rms_px:.3f} px over {len(ic.used)} views; vs truth (OpenCV std): "
            + ", ".join(f"{k[:-3]} {v:+.2f} ({ic.std[k[:-3]]:.2f}) px" for k, v in errs.items()))


def _stage_plane(run: _Run):
    """4. the light plane from the circle images (``ml``, with ``global`` and ``paper`` from the same
    observations), saved and compared with the truth; returns the ``ml`` calibration (None if it failed)."""
    cfg, camera, data, say = run.cfg, run.camera, run.data, run.say
    say(f"[4] calibrating the light plane from {cfg['circles']} circle-target images "
        f"({cfg['diameter_mm']:g} mm disc) (camera: {run.camera_source}) ...")

    def calib_plane():
        _, files, _ = _load_set(data / "circles")
        t0 = time.perf_counter()
        obs = observe_images(files, camera, cfg["diameter_mm"], PlaneCalibrationOptions(workers=run.workers))
        cals = {m: solve_observations(obs, camera, cfg["diameter_mm"], m,
                                      seconds=time.perf_counter() - t0 if m == "ml" else 0.0)
                for m in ("ml", "global", "paper")}
        return cals, uncertainty_summary(cals["ml"], camera)

    res = run.st.run("plane", calib_plane)
    if res is None:
        return None
    cals, unc = res
    cal = cals["ml"]

    cal.plane.save(run.out / "plane.json", force=True, extra={
        **cal.to_dict(), "uncertainty": unc,
        "provenance": _prov([str(data / "circles")], {"method": "ml", "diameter_mm": cfg["diameter_mm"]}),
        "report_inputs": cal.report_inputs()})  # `lightplane report plane.json` rebuilds the report
    run.summary["plane"] = {"ml": cal.to_dict(), "uncertainty": unc, "accuracy": {}}
    rej = [f"{o.name} ({o.reason})" for o in cal.images if not o.used]
    say(f"    {cal.n_used} of {len(cal.images)} images used" + (f"; rejected: {', '.join(rej)}" if rej else "")
        + f"; {cal.seconds:.2f} s")
    say(f"    plane: {cal.plane}")
    if unc:
        _say_uncertainty(say, unc)
    say("    vs truth  method   angle (deg)  offset (mm)  triangulation RMS (mm, camera frame / rigidly aligned)")
    for m, c in cals.items():
        acc = plane_accuracy(c.plane, camera, run.plane_true, run.camera_true)
        run.summary["plane"]["accuracy"][m] = acc
        say(f"              {m:<7}  {acc['angle_deg']:10.4f}  {acc['offset_mm']:+11.4f}  "
            f"{acc['tri_rms_mm']:.4f} / {acc['tri_rms_aligned_mm']:.4f}")
    return cal


def _say_uncertainty(say, unc: dict) -> None:
    say(f"    sigma: normal {unc['normal_sigma_deg'][0]:.4f} deg, offset {unc['d_sigma_mm']:.4f} mm, "
        f"point at {unc.get('working_distance_mm', float('nan')):.0f} mm "
        f"{unc.get('point_sigma_axis_mm', float('nan')) * 1e3:.1f} µm (camera frame)")
    if "shape_sigma_rms_mm" in unc:
        say(f"    RMS point sigma over the targets' range: camera frame "
            f"{unc['point_sigma_rms_mm'] * 1e3:.1f} µm, shape {unc['shape_sigma_rms_mm'] * 1e3:.1f} µm, "
            f"plane calibration only {unc['plane_only_sigma_rms_mm'] * 1e3:.1f} µm; the camera's share "
            + ("included" if unc["camera_share"] == "included" else "not included"))


def _stage_zhou(run: _Run):
    """5. Zhou's planar-target plane from the striped chessboards; returns it (None if it failed)."""
    cfg, camera = run.cfg, run.camera
    run.say(f"[5] Zhou's planar-target plane from {cfg['striped_boards']} rendered chessboards with the stripe ...")

    def zhou_stage():
        _, files, imgs = _load_set(run.data / "striped_boards")
        return calibrate_plane_board(BoardFrames(imgs, names=[f.name for f in files]), camera, tuple(cfg["board"]),
                                     cfg["square_mm"])

    zhou = run.st.run("zhou", zhou_stage)
    if zhou is not None:
        zhou.plane.save(run.out / "plane_zhou.json", force=True)
        acc = plane_accuracy(zhou.plane, camera, run.plane_true, run.camera_true)
        run.summary["zhou"] = {"plane": zhou.plane.to_dict(), "accuracy": acc,
                               "residual_rms_mm": zhou.residual_rms_mm}
        run.say(f"    plane: {zhou.plane}; vs truth: angle {acc['angle_deg']:.4f} deg, offset "
                f"{acc['offset_mm']:+.4f} mm, triangulation {acc['tri_rms_aligned_mm']:.4f} mm (aligned)")
    return zhou


def _stage_evaluate(run: _Run, cal, zhou):
    """6. the cross-ratio evaluation of the calibrated planes side by side; returns it (None if none ran)."""
    planes, labels = [], []
    if cal is not None:
        planes.append(cal.plane)
        labels.append("circle target (ml)")
    if zhou is not None:
        planes.append(zhou.plane)
        labels.append("Zhou (chessboard)")
    if not planes:
        return None
    run.say("[6] cross-ratio evaluation on the striped chessboards (paper §4.3) ...")
    cfg = run.cfg

    def eval_stage():
        _, files, imgs = _load_set(run.data / "striped_boards")
        return evaluate_images(imgs, run.camera, planes, board=tuple(cfg["board"]), square_mm=cfg["square_mm"],
                               labels=labels, image_names=[f.name for f in files])

    evaluation = run.st.run("evaluate", eval_stage)
    if evaluation is not None:
        run.summary["evaluation"] = {lab: e.to_dict() for lab, e in zip(evaluation.labels, evaluation.errors)}
        for lab, e in zip(evaluation.labels, evaluation.errors):
            run.say(f"    {lab:<20} {len(evaluation.pairs)} distances, RMS Δ = {e.rms_mm:.4f} mm, "
                    f"max |Δ| = {e.max_abs_mm:.4f} mm")
    return evaluation


def _stage_scan(run: _Run, plane_for_scan: LightPlane | None) -> None:
    """7. measure the scan with the calibrated plane and fit the sphere."""
    cfg, say = run.cfg, run.say
    if plane_for_scan is None:
        say("[7] scan: skipped (no calibrated plane)")
        run.summary["stages"]["scan"] = {"status": "skipped", "reason": "no calibrated plane"}
        return
    say(f"[7] measuring the rendered {cfg['scan_kind']} scan ({cfg['scan_frames']} frames, "
        f"{cfg['scan_step_mm']:g} mm steps) with the calibrated plane ...")
    scan_result = run.st.run("scan", _measure_scan, run.data / "scan", run.camera, plane_for_scan, run.out)
    if scan_result is not None:
        run.summary["scan"] = scan_result
        if "sphere" in scan_result:
            s = scan_result["sphere"]
            say(f"    {scan_result['n_points']} points; sphere radius {s['radius_mm']:.4f} mm "
                f"(true {scan_result['true_radius_mm']:.4f} mm, error {scan_result['radius_error_mm']:+.4f} mm), "
                f"fit RMS {s['rms_mm']:.4f} mm over {s['n_inliers']} points")


def _measure_scan(folder: Path, camera: Camera, plane: LightPlane, out: Path) -> dict:
    """The scan's cloud (motion removed, saved as ``scan_points.ply`` with every point's frame, σ and pixel,
    and as ``scan_points.npy``, x y z only) and the sphere fitted to it."""
    truth, files, imgs = _load_set(folder)
    meas = ProfileMeasurer(camera, plane)
    pts, recs = [], []
    for k, (img, fr) in enumerate(zip(imgs, truth["frames"])):
        prof = meas(img)
        p = prof.points[prof.valid] - np.asarray(fr["offset_mm"], dtype=np.float64)
        pts.append(p)
        recs.append(make_records(p, frame=k, intensity=prof.intensity[prof.valid], sigma_mm=prof.sigma_mm[prof.valid],
                                 uv=prof.uv[prof.valid]))
    cloud = np.vstack(pts) if pts else np.zeros((0, 3))
    write_cloud(out / "scan_points.ply", np.concatenate(recs) if recs else make_records(cloud, frame=0), force=True,
                comments=["lightplane point cloud: x y z in mm (camera frame, object at frame 0: the motion removed)",
                          f"demo scan: {folder}"])
    # the static table behind (z = 600 mm) smears out once motion is removed: keep the object
    sph = truth["frames"][0]["surfaces"].get("sphere")
    res: dict = {"n_points": int(len(cloud))}
    if sph is not None:
        c0 = np.asarray(sph["center_mm"]) - np.asarray(truth["frames"][0]["offset_mm"])
        near = np.linalg.norm(cloud - c0, axis=1) < sph["radius_mm"] + 5.0
        fit = fit_sphere(cloud[near]).to_dict()
        res.update({"sphere": fit, "true_radius_mm": sph["radius_mm"],
                    "radius_error_mm": fit["radius_mm"] - sph["radius_mm"]})
    np.save(out / "scan_points.npy", cloud)
    return res


def _stage_report(run: _Run, cal, evaluation) -> None:
    """8. write the report."""
    run.say("[8] writing the report ...")

    def report_stage():
        sections = [Section("Demo summary", rows=_summary_rows(run.summary))]
        if evaluation is not None:
            sections.append(Section("Cross-ratio evaluation (paper §4.3, Table-2 layout)",
                                    html=_evaluation_table(evaluation)))
        return write_report(run.out / "report", cal, plane_true=run.plane_true, extra_sections=sections, force=True,
                            title="lightplane demo: circle-target calibration on rendered images")

    path = run.st.run("report", report_stage)
    if path is not None:
        run.say(f"    {path}")
        run.summary["report"] = str(path)


def _evaluation_table(ev) -> str:
    """HTML table: per pair the reference distance dt and, per plane, dm and Δ = dt − dm (mm)."""
    import html as _html

    head = "<tr><th>pair</th><th>dt (mm)</th>" + "".join(
        f"<th>dm {_html.escape(lab)} (mm)</th><th>Δ {_html.escape(lab)} (mm)</th>" for lab in ev.labels) + "</tr>"
    rows = []
    for k, (i, j) in enumerate(ev.pairs):
        cells = "".join(f"<td class=num>{e.dm_mm[k]:.4f}</td><td class=num>{e.delta_mm[k]:+.4f}</td>"
                        for e in ev.errors)
        rows.append(f"<tr><td>{i}–{j}</td><td class=num>{ev.errors[0].dt_mm[k]:.4f}</td>{cells}</tr>")
    rms = "".join(f"<td></td><td class=num><b>{e.rms_mm:.4f}</b></td>" for e in ev.errors)
    rows.append(f"<tr><td><b>RMS Δ</b></td><td></td>{rms}</tr>")
    return "<table>" + head + "".join(rows) + "</table>"


def _summary_rows(summary: dict) -> list[tuple[str, str]]:
    rows = []
    cam = summary.get("camera")
    if cam:
        e = cam["error_vs_truth_px"]
        rows.append(("camera (Zhang, rendered chessboards)",
                     f"RMS {cam['rms_px']:.3f} px, {cam['views']} views; fx {e['fx_px']:+.2f} px, "
                     f"cx {e['cx_px']:+.2f} px, cy {e['cy_px']:+.2f} px vs truth"))
    pl = summary.get("plane")
    if pl:
        for m, acc in pl["accuracy"].items():
            rows.append((f"circle-target plane, {m}, vs truth",
                         f"angle {acc['angle_deg']:.4f} deg, offset {acc['offset_mm']:+.4f} mm, triangulation RMS "
                         f"{acc['tri_rms_mm']:.4f} mm (camera frame) / {acc['tri_rms_aligned_mm']:.4f} mm (aligned)"))
    z = summary.get("zhou")
    if z:
        acc = z["accuracy"]
        rows.append(("Zhou's plane vs truth", f"angle {acc['angle_deg']:.4f} deg, offset {acc['offset_mm']:+.4f} mm, "
                     f"triangulation RMS {acc['tri_rms_aligned_mm']:.4f} mm (aligned)"))
    ev = summary.get("evaluation")
    if ev:
        for lab, e in ev.items():
            rows.append((f"cross-ratio check, {lab}", f"RMS Δ {e.get('rms_mm', float('nan')):.4f} mm"))
    sc = summary.get("scan")
    if sc and "sphere" in sc:
        rows.append(("sphere scan", f"radius {sc['sphere']['radius_mm']:.4f} mm (true {sc['true_radius_mm']:.4f} mm), "
                     f"fit RMS {sc['sphere']['rms_mm']:.4f} mm"))
    for name, s in summary.get("stages", {}).items():
        if s["status"] != "ok":
            rows.append((f"stage {name}", f"{s['status']}: {s.get('reason', '')}"))
    return rows
