"""HTML reports of the camera, board-plane, turntable and turntable-refinement calibrations.

Each report is one self-contained ``index.html`` (figures embedded as PNG, no scripts), built from
the calibration's result file alone, the way :func:`lightplane.report.html.rebuild_report` builds
the circle target's: the commands' ``--report DIR`` and ``lightplane report FILE --out DIR`` write
the same page.  Each page opens with a verdict line (what the calibration is good for and what
limits it, in words with units), then:

- **camera** (``calibrate-camera``): where the board was in the image and how it was tilted, the
  residuals per view and over the image, the σ of a ray's direction over the image;
- **board plane** (``calibrate-plane-board``, Zhou's method): the boards and stripe points in the
  image, the boards' tilts, the stripe points' distance to the plane per board and over the
  image, the σ of a triangulated point over the image;
- **turntable** (``calibrate-turntable``): the board origins around the axis, per image the board
  points' circle residuals and the poses' reprojection error, the axis σ as a point error;
- **turntable refinement** (``refine-turntable``): the scans' agreement before and after, their
  clouds overlaid.

What a report needs beyond the result itself is stored in the file under ``report_inputs``
(:func:`camera_report_inputs`, :func:`board_plane_report_inputs`, :func:`refine_report_inputs`);
the turntable file's own records suffice for its report.
"""

from __future__ import annotations

import html
import math
import os
from pathlib import Path
from typing import Sequence

import numpy as np

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.core.io import atomic_write, check_output, read_json
from lightplane.motion.model import Turntable
from lightplane.motion.turntable_refine import table_points
from lightplane.plane.model import LightPlane
from lightplane.plane.uncertainty import image_grid, point_sigma_mm, ray_sigma_rad
from lightplane.report.html import _CSS, Section, _img_tag, _kv, rebuild_report
from lightplane.report.plots import (figure_image_map, figure_point_sigma, figure_residual_field,
                                     figure_scans_overlay, figure_turntable, figure_view_coverage,
                                     figure_view_residuals)

__all__ = ["REPORT_KINDS", "report_kind", "camera_report_inputs", "board_plane_report_inputs",
           "refine_report_inputs", "calibration_report_html", "write_calibration_report", "OUTLIER_FACTOR"]

#: the result files a report is built from, by kind
REPORT_KINDS = ("plane", "camera", "board_plane", "turntable", "refine")

#: a view whose RMS residual exceeds this many times the views' median is flagged in the reports
OUTLIER_FACTOR = 3.0

#: stripe points per board kept in a plane file's report inputs (an even subsample)
MAX_STRIPE_POINTS = 300
#: points per scan kept in a refined sensor file's report inputs (an even subsample)
MAX_SCAN_POINTS = 4000


# ----------------------------------------------------------------------------- what the files store
def _r(a, nd: int) -> list:
    return np.round(np.asarray(a, np.float64), nd).tolist()


def camera_report_inputs(result) -> dict:
    """What a camera file keeps for its report: per used view its corners (px), residuals (px) and
    board pose (``rvec``, ``tvec_mm``), from an :class:`~lightplane.camera.intrinsics.IntrinsicsCalibration`."""
    views = []
    for i, name in enumerate(result.used):
        views.append({"name": str(name), "corners_uv": _r(result.corners_uv[i], 3),
                      "residuals_px": _r(result.residuals_px[i], 4), "rvec": _r(result.rvecs[i], 7),
                      "tvec_mm": _r(result.tvecs[i], 4), "rms_px": float(result.per_view_rms_px[i])})
    return {"kind": "camera", "version": 1, "views": views}


def board_plane_report_inputs(calibration, camera: Camera, max_points: int = MAX_STRIPE_POINTS) -> dict:
    """What a board-plane file keeps for its report, from a :class:`~lightplane.plane.zhou.ZhouCalibration`:
    per board its outline in the image (px), its pose, and up to ``max_points`` of its stripe points
    (px) with their signed distance to the plane (mm)."""
    views = []
    for k, pose in enumerate(calibration.poses):
        sel = calibration.view_index == k
        P, r = calibration.points_cam_mm[sel], calibration.residual_mm[sel]
        pick = np.unique(np.linspace(0, len(P) - 1, min(len(P), max_points)).astype(int)) if len(P) else \
            np.zeros(0, int)
        views.append({"name": str(pose.name or f"pose {k}"), "outline_uv": _r(_hull(pose.corners_uv), 2),
                      "R_cam_board": _r(pose.R_cam_board, 7), "t_cam_board_mm": _r(pose.t_cam_board, 4),
                      "stripe_uv": _r(camera.project(P[pick]) if len(pick) else np.zeros((0, 2)), 3),
                      "residual_mm": _r(r[pick], 6), "n_points": int(sel.sum()),
                      "rms_mm": float(np.sqrt(np.mean(r ** 2))) if sel.any() else None})
    return {"kind": "board_plane", "version": 1, "views": views}


def refine_report_inputs(scans: Sequence, table_before: Turntable, result,
                         max_points: int = MAX_SCAN_POINTS) -> dict:
    """What a refined sensor file keeps for its report: up to ``max_points`` of each scan's points in
    the turntable frame (mm) with the given axis and start angles 0, and with the refined ones."""
    before, after = [], []
    tt = result.turntable
    for s, a in zip(scans, result.start_deg):
        pick = np.unique(np.linspace(0, len(s.points_cam) - 1, min(len(s.points_cam), max_points)).astype(int))
        before.append(_r(table_points(s, table_before.point_mm, table_before.direction, 0.0, pick), 2))
        after.append(_r(table_points(s, tt.point_mm, tt.direction, a, pick), 2))
    return {"kind": "refine", "version": 1, "names": [s.name for s in scans], "before_mm": before, "after_mm": after}


# ----------------------------------------------------------------------------- geometry helpers
def _hull(uv) -> np.ndarray:
    """The convex hull of image points (its corners in order), or the points when degenerate."""
    p = np.asarray(uv, np.float64).reshape(-1, 2)
    p = p[np.all(np.isfinite(p), axis=1)]
    if len(p) < 3:
        return p
    try:
        from scipy.spatial import ConvexHull

        return p[ConvexHull(p).vertices]
    except Exception:  # noqa: BLE001 - collinear points: no hull, the points themselves
        return p


def _tilts(normals: np.ndarray) -> np.ndarray:
    """(N, 2) tilt (deg) of board normals about the camera's x and y axes (0: facing the camera)."""
    n = np.asarray(normals, np.float64).reshape(-1, 3)
    n = np.where(n[:, 2:3] > 0, -n, n)  # towards the camera
    return np.degrees(np.column_stack([np.arctan2(n[:, 1], -n[:, 2]), np.arctan2(n[:, 0], -n[:, 2])]))


def _rodrigues(rvec) -> np.ndarray:
    r = np.asarray(rvec, np.float64).ravel()
    th = float(np.linalg.norm(r))
    if th < 1e-12:
        return np.eye(3)
    k = r / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K


def _coverage(size: tuple[int, int], outlines: Sequence[np.ndarray], cells: int = 64) -> float:
    """The fraction of the image inside at least one outline (on a ``cells``-wide grid)."""
    import cv2

    w, h = size
    s = cells / float(w)
    mask = np.zeros((max(1, int(round(h * s))), cells), np.uint8)
    for o in outlines:
        o = np.asarray(o, np.float64).reshape(-1, 2)
        if len(o) >= 3:
            cv2.fillPoly(mask, [np.round(o * s).astype(np.int32)], 1)
    return float(mask.mean())


def _flagged(rms: np.ndarray) -> np.ndarray:
    med = float(np.median(rms)) if len(rms) else float("nan")
    return np.asarray(rms, float) > OUTLIER_FACTOR * med if np.isfinite(med) and med > 0 else np.zeros(len(rms), bool)


def _tilt_phrase(tilts: np.ndarray) -> tuple[float, float]:
    """(largest tilt, spread of the tilt directions) in deg."""
    t = np.asarray(tilts, float).reshape(-1, 2)
    total = np.hypot(t[:, 0], t[:, 1])
    return float(total.max()) if len(t) else 0.0, float(np.ptp(t[:, 0]) + np.ptp(t[:, 1])) if len(t) else 0.0


# ----------------------------------------------------------------------------- the page
def _page(title: str, verdict: str, rows, warnings: Sequence[str], sections: Sequence[Section],
          provenance) -> str:
    parts = [f"<!DOCTYPE html><html lang=en><head><meta charset=utf-8><title>{html.escape(title)}</title>"
             f"<style>{_CSS}.verdict{{font-size:1.05em;background:#f4f8ff;border-left:4px solid #1f5fbf;"
             f"padding:0.5em 0.8em}}</style></head><body>",
             f"<h1>{html.escape(title)}</h1>", f"<p class=verdict>{html.escape(verdict)}</p>",
             "<h2>Result</h2>", _kv(rows)]
    if warnings:
        parts.append("<ul>" + "".join(f"<li class=warn>{html.escape(str(w))}</li>" for w in warnings) + "</ul>")
    for s in sections:
        parts.append(f"<h2>{html.escape(s.title)}</h2>")
        if s.rows:
            parts.append(_kv(s.rows))
        if s.html:
            parts.append(s.html)
        for png, cap in s.figures:
            parts.append(_img_tag(png, cap))
    parts.append(f"<p class=small>lightplane report; {html.escape(str(provenance or ''))}</p></body></html>")
    return "\n".join(parts)


def _table(head: Sequence[str], rows: Sequence[Sequence], flagged: "Sequence[bool] | np.ndarray" = ()) -> str:
    out = ["<table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>"]
    for k, r in enumerate(rows):
        cls = " class=rejected" if k < len(flagged) and flagged[k] else ""
        out.append(f"<tr{cls}>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>")
    return "".join(out) + "</table>"


def _skipped_table(skipped: dict) -> Section | None:
    if not skipped:
        return None
    return Section(f"Images not used ({len(skipped)})",
                   html=_table(("image", "reason"), [(Path(str(n)).name, why) for n, why in skipped.items()]))


def _head(quality: dict | None, good: str) -> str:
    """The verdict's opening words from a result file's ``quality`` record: ``good`` when it is ok, guarded
    when its checks were above their noise, a warning when it was kept against them."""
    v = (quality or {}).get("verdict") if isinstance(quality, dict) else None
    rest = good.removeprefix("Good ")  # "for ..."
    if v == "elevated":
        return "Usable with care (its checks lie above their noise) " + rest
    if v == "suspect":
        return "Not reliable (kept against its checks) " + rest
    return good


def _f_or_dash(x, fmt: str) -> str:
    return "–" if x is None or not np.isfinite(x) else format(x, fmt)


def _limits(good: str, limits: list[str], fine: str) -> str:
    if limits:
        return good + " What limits it: " + "; ".join(limits) + "."
    return good + " " + fine


# ----------------------------------------------------------------------------- camera
def _length(mm: float) -> str:
    """A length with the unit that reads best: µm below 1 mm, else mm."""
    return f"{mm * 1e3:.1f} µm" if abs(mm) < 1.0 else f"{mm:.2f} mm"


def _camera_verdict(cal: dict, names: list, rms: np.ndarray, figures: tuple, tilts: np.ndarray, cover: float) -> str:
    """The camera report's verdict: what the calibration is good for, then what limits it."""
    all_rms, dist, ray_deg, ray_mm = figures
    where = f"at about {dist:.0f} mm from the camera (the boards' median distance)"
    sigma = (f"; a ray's direction σ {ray_deg:.4f} deg RMS over the image, i.e. {_length(ray_mm)} across the ray at "
             f"{dist:.0f} mm" if np.isfinite(ray_deg) else "")
    head = "Good for measuring" if not ray_deg > 0.5 else "Not yet good for measuring"
    good = f"{head} {where}: RMS reprojection {all_rms:.3f} px over {len(names)} views{sigma}."
    limits = [str(w) for w in cal.get("warnings") or []]
    if ray_deg > 0.05:
        limits.append(f"a ray's direction is uncertain by {ray_deg:.3f} deg RMS: more views, tilted 20–40 deg and "
                      "covering the whole image, narrow it")
    max_tilt, _ = _tilt_phrase(tilts)
    span_x, span_y = (float(np.ptp(tilts[:, 0])), float(np.ptp(tilts[:, 1]))) if len(tilts) else (0.0, 0.0)
    if max_tilt < 10.0:
        limits.append(f"the boards face the camera (largest tilt {max_tilt:.1f} deg), so the focal length is "
                      "barely observable: tilt the board 20–40 deg in several directions")
    elif min(span_x, span_y) < 10.0:
        axis = "x" if span_x < span_y else "y"
        limits.append(f"the board turned about one axis only (its tilts about the camera's {axis} axis span "
                      f"{min(span_x, span_y):.0f} deg): tilt it about the other axis too")
    if cover < 0.5:
        limits.append(f"the boards cover {100 * cover:.0f} % of the image: the lens distortion near the edges and "
                      "corners is extrapolated; place the board there too")
    flag = _flagged(rms)
    worst = int(np.argmax(rms)) if len(rms) else 0
    if flag.any() and not any(Path(names[worst]).name in w for w in limits):
        limits.append(f"{int(flag.sum())} view(s) with residuals over {OUTLIER_FACTOR:g}x the median "
                      f"({Path(names[worst]).name}: {rms[worst]:.3f} px against {np.median(rms):.3f} px)")
    fx = (cal.get("std") or {}).get("fx")
    if cal.get("std") and fx is None:
        limits.append("the focal length is not determined by these views")
    return _limits(good, limits, f"Nothing obvious limits it: the boards cover {100 * cover:.0f} % of the image "
                   f"and tilt up to {max_tilt:.0f} deg.")


def _camera_page(d: dict, camera: Camera) -> tuple[str, str, list, list, list]:
    views = d["report_inputs"]["views"]
    cal = d.get("calibration") or {}
    names = [v["name"] for v in views]
    rms = np.array([v["rms_px"] for v in views], float)
    size = (camera.width, camera.height)
    outlines = [_hull(v["corners_uv"]) for v in views]
    normals = np.array([_rodrigues(v["rvec"])[:, 2] for v in views]).reshape(-1, 3)
    tilts = _tilts(normals)
    cu = d.get("camera_uncertainty") or {}
    dist = float(cu.get("distance_mm") or np.median([np.linalg.norm(v["tvec_mm"]) for v in views]))
    cover = _coverage(size, outlines)
    flag = _flagged(rms)
    all_rms = float(camera.rms_px) if camera.rms_px is not None else float(np.sqrt(np.mean(rms ** 2)))
    grid = image_grid(camera, max(camera.width, camera.height) / 48.0)
    ray = ray_sigma_rad(camera, grid) if camera.covariance is not None else None
    if cu.get("included"):
        ray_deg, ray_mm = float(cu["ray_sigma_deg_rms"]), float(cu["ray_sigma_mm_rms"])
    elif ray is not None and np.all(np.isfinite(ray)):
        r_rms = float(np.sqrt(np.mean(ray ** 2)))
        ray_deg, ray_mm = math.degrees(r_rms), r_rms * dist
    else:
        ray_deg = ray_mm = float("nan")
    verdict = _camera_verdict(cal, names, rms, (all_rms, dist, ray_deg, ray_mm), tilts, cover)
    max_tilt = _tilt_phrase(tilts)[0]
    rows = [("camera", f"{camera.width}x{camera.height} px, lens model {camera.model}, fx {camera.fx:.2f} px, "
                       f"fy {camera.fy:.2f} px, cx {camera.cx:.2f} px, cy {camera.cy:.2f} px"),
            ("RMS reprojection", f"{all_rms:.4f} px over {len(views)} views"),
            ("views' coverage of the image", f"{100 * cover:.0f} %"),
            ("board tilts", f"up to {max_tilt:.1f} deg"),
            ("median board distance", f"{dist:.1f} mm")]
    std = cal.get("std") or {}
    if std:
        rows.append(("± std (px, distortion unitless)", ", ".join(
            f"{k} {'not determined' if v is None else format(v, '.3g')}" for k, v in std.items())))
        rows.append(("the std cover", str(cal.get("std_covers", ""))))
    sections = [Section("Coverage of the views", figures=[(figure_view_coverage(size, outlines, tilts),
                                                           "Board outlines over the image (px) and tilts (deg)")]),
                Section("Residuals per view", figures=[(figure_view_residuals(
                    names, rms, unit="px", ylabel="RMS reprojection error", flagged=flag,
                    reference=float(np.median(rms)), reference_label="median of the views"), "Per view (px)")],
                    html=_table(("view", "corners", "RMS (px)", "tilt x, y (deg)", "distance (mm)"),
                                [(Path(n).name, len(v["corners_uv"]), f"{r:.4f}", f"{t[0]:+.1f}, {t[1]:+.1f}",
                                  f"{np.linalg.norm(v['tvec_mm']):.1f}")
                                 for n, v, r, t in zip(names, views, rms, tilts)], flag)),
                Section("Residuals over the image", figures=[(figure_residual_field(
                    size, np.vstack([np.reshape(v["corners_uv"], (-1, 2)) for v in views]),
                    np.vstack([np.reshape(v["residuals_px"], (-1, 2)) for v in views]), unit="px"),
                    "Corner residuals binned over the image (px)")])]
    if ray is not None:
        sections.append(Section("Uncertainty over the image", html=(
            "<p class=small>σ across the ray at the boards' median distance: the intrinsics' and distortion's "
            "covariance from this calibration (corner noise estimated from its residuals); not the corner "
            "detector's biases, nor a lens model that does not fit.</p>"),
            figures=[(figure_image_map(size, grid, ray * dist * 1e3, step_px=max(camera.width, camera.height) / 48.0,
                                       label=f"σ across the ray at {dist:.0f} mm (µm; colours end at the 95th "
                                             f"percentile)", vmax=float(np.nanpercentile(ray * dist * 1e3, 95)),
                                       title="σ of a ray's direction, as a distance at the boards' median distance"),
                      "Ray σ map (µm at the working distance) over the image (px)")]))
    sk = _skipped_table(cal.get("views_skipped") or {})
    if sk is not None:
        sections.append(sk)
    return "Camera calibration report", verdict, rows, [], sections


# ----------------------------------------------------------------------------- board plane
def _recorded_camera(rec: dict) -> Camera:
    return Camera(np.asarray(rec["K"], np.float64), np.asarray(rec["dist"], np.float64), int(rec["width"]),
                  int(rec["height"]), model=rec.get("model"))


def _board_plane_limits(d: dict, views: list, tilts: np.ndarray, rms_um: np.ndarray, names: list,
                        depth_mm: tuple) -> tuple[list[str], dict]:
    """What limits a board plane (the verdict's second half), and each image's ratio of its distance to the
    plane to what its stripe noise predicts (from the file's ``quality``)."""
    limits = []
    lo, hi = depth_mm
    used = [v for v in views if v["n_points"] > 0]
    flag = _flagged(rms_um)
    if len(used) < 4:
        limits.append(f"only {len(used)} boards: the σ comes from the fit residuals and ignores the boards' pose "
                      "errors (optimistic); use 4 or more")
    q = d.get("quality") or {}
    if isinstance(q, dict) and q.get("verdict") not in (None, "ok"):
        bad = [im for im in q.get("images") or [] if im.get("verdict") not in (None, "ok")]
        if bad:
            ratios = [float(im["ratio"]) for im in bad]
            limits.append(f"{len(bad)} board(s) lie {min(ratios):.0f}–{max(ratios):.0f}x further from the plane than "
                          f"their stripe noise predicts ({', '.join(Path(str(im['image'])).name for im in bad)}): "
                          "board-pose errors or stripes biased along the pattern")
        else:
            limits.append(f"quality {q.get('verdict')}")
    if hi - lo < 0.1 * max(hi, 1.0):
        limits.append(f"the stripe points span only {hi - lo:.0f} mm in depth: the plane is extrapolated beyond it; "
                      "place the board nearer and farther")
    ratio = {str(im.get("image")): float(im["ratio"]) for im in (q.get("images") or []) if "ratio" in im} \
        if isinstance(q, dict) else {}
    spread = _tilt_phrase(tilts)[1]
    if spread < 10.0:
        limits.append(f"the boards' orientations differ by {spread:.0f} deg in all: tilt the board between poses")
    if flag.any():
        worst = int(np.nanargmax(rms_um))
        limits.append(f"board {Path(names[worst]).name}'s stripe points lie {rms_um[worst]:.0f} µm RMS from the "
                      f"plane, over {OUTLIER_FACTOR:g}x the median ({np.nanmedian(rms_um):.0f} µm)")
    skipped = d.get("skipped") or {}
    if skipped:
        limits.append(f"{len(skipped)} of {len(skipped) + len(views)} images not used (listed below)")
    return limits, ratio


def _board_plane_page(d: dict, plane: LightPlane) -> tuple[str, str, list, list, list]:
    views = d["report_inputs"]["views"]
    camera = _recorded_camera(d["camera"])
    size = (camera.width, camera.height)
    used = [v for v in views if v["n_points"] > 0]
    names = [v["name"] for v in used]
    rms_um = np.array([(v["rms_mm"] or np.nan) * 1e3 for v in used], float)
    uv = np.vstack([np.reshape(v["stripe_uv"], (-1, 2)) for v in used]) if used else np.zeros((0, 2))
    res = np.concatenate([np.asarray(v["residual_mm"], float) for v in used]) if used else np.zeros(0)
    outlines = [np.reshape(v["outline_uv"], (-1, 2)) for v in views]
    R = [np.asarray(v["R_cam_board"], float) for v in views]
    tilts = _tilts(np.array([r[:, 2] for r in R]))
    depth = np.array([v["t_cam_board_mm"][2] for v in views], float)
    wv = d.get("working_volume") or {}
    lo, hi = (wv.get("depth_mm") or [float(depth.min()), float(depth.max())])
    sig = point_sigma_mm(camera, plane, uv) if plane.covariance is not None and len(uv) else np.zeros(0)
    flag = _flagged(rms_um)  # as _board_plane_limits flags them
    n_pts = int(sum(v["n_points"] for v in used))
    fit_um = float(d.get("residual_rms_mm", np.sqrt(np.mean(res ** 2)) if len(res) else np.nan)) * 1e3
    good = (_head(d.get("quality"), f"Good for triangulating points {lo:.0f}–{hi:.0f} mm from the camera (where its "
                  "stripe points lie)")
            + (f": a point's σ there {np.sqrt(np.nanmean(sig ** 2)) * 1e3:.1f} µm RMS (the plane's covariance, "
               f"{d.get('covariance_method', '')}; the camera's share not included)" if len(sig) else "")
            + f"; the plane fits its {n_pts} stripe points on {len(used)} boards to {fit_um:.1f} µm RMS.")
    limits, ratio = _board_plane_limits(d, views, tilts, rms_um, names, (lo, hi))
    max_tilt = _tilt_phrase(tilts)[0]
    skipped = d.get("skipped") or {}
    verdict = _limits(good, limits, f"Nothing obvious limits it: {len(used)} boards over {hi - lo:.0f} mm of "
                      f"depth, tilted up to {max_tilt:.0f} deg.")
    a, b, c = plane.normal
    rows = [("plane (camera frame, mm)", f"{a:+.6f} x {b:+.6f} y {c:+.6f} z {plane.d:+.4f} = 0"),
            ("method", "Zhou (board poses, stripe points on the boards)"),
            ("boards used", f"{len(used)} of {len(views) + len(skipped)} images"),
            ("stripe points to the plane", f"{fit_um:.1f} µm RMS over {n_pts} points"),
            ("covariance", str(d.get("covariance_method", "–"))),
            ("depth range of the stripe points", f"{lo:.1f}–{hi:.1f} mm")]
    sections = [Section("Coverage of the views", figures=[(figure_view_coverage(
                    size, outlines, tilts, points=[np.reshape(v["stripe_uv"], (-1, 2)) for v in used]),
                    "Board outlines and stripe points (red) over the image (px); tilts (deg)")]),
                Section("Residuals per board", figures=[(figure_view_residuals(
                    names, rms_um, unit="µm", ylabel="stripe points to the plane, RMS", flagged=flag,
                    reference=float(np.nanmedian(rms_um)) if len(rms_um) else None,
                    reference_label="median of the boards"), "Per board (µm)")],
                    html=_table(("image", "stripe points", "RMS to the plane (µm)", "× its stripe noise's prediction",
                                 "tilt x, y (deg)", "depth (mm)"),
                                [(Path(v["name"]).name, v["n_points"], "–" if v["rms_mm"] is None else
                                  f"{v['rms_mm'] * 1e3:.1f}", _f_or_dash(ratio.get(v["name"]), ".1f"),
                                  f"{t[0]:+.1f}, {t[1]:+.1f}", f"{z:.1f}")
                                 for v, t, z in zip(views, tilts, depth)],
                                [ratio.get(v["name"], 0.0) > 5.0 for v in views])),
                Section("Residuals over the image", figures=[(figure_residual_field(size, uv, res, unit="µm",
                                                                                   scale=1e3),
                                                             "Stripe points' distance to the plane, binned (µm)")])]
    if plane.covariance is not None:
        sections.append(Section("Uncertainty of measured points", html=(
            "<p class=small>σ of a point triangulated at each pixel from the plane's covariance ("
            + html.escape(str(d.get("covariance_method", ""))) + "); it does not include the camera's share, the "
            "stripe centre's own noise, or systematic errors of the board poses.</p>"),
            # the map greys out pixels beyond a distance range: the stripe points' depths, widened to distances
            figures=[(figure_point_sigma(camera, plane, (math.floor(0.95 * lo), math.ceil(1.15 * hi))),
                      "Point σ map (µm) over the image (px)")]))
    sk = _skipped_table(skipped)
    if sk is not None:
        sections.append(sk)
    return "Board light-plane calibration report (Zhou)", verdict, rows, [], sections


# ----------------------------------------------------------------------------- turntable
def _turn_sigma(tt: Turntable, radii: np.ndarray, heights: np.ndarray) -> np.ndarray | None:
    """σ (mm) of a point at (radius, 0, height) in the turntable frame turned half a turn about the axis,
    from the axis's covariance (first order); None without one."""
    if tt.covariance is None:
        return None
    C = np.asarray(tt.covariance, np.float64)
    o, B = tt.basis()
    p0, d0 = tt.point_mm.astype(np.float64), tt.direction.astype(np.float64)

    def turned(x, p, dvec):
        dvec = dvec / np.linalg.norm(dvec)
        v = x - p
        return p + 2 * (v @ dvec) * dvec - v  # rotation by 180 deg about (p, d)

    out = np.zeros((len(heights), len(radii)))
    for i, h in enumerate(heights):
        for j, r in enumerate(radii):
            x = o + B @ np.array([r, 0.0, h])
            J = np.zeros((3, 6))
            for k in range(6):
                e = np.zeros(6)
                e[k] = 1e-4 if k < 3 else 1e-6
                J[:, k] = (turned(x, p0 + e[:3], d0 + e[3:]) - turned(x, p0 - e[:3], d0 - e[3:])) / (2 * e[k])
            out[i, j] = math.sqrt(max(float(np.trace(J @ C @ J.T)), 0.0))
    return out


def _turntable_page(d: dict, tt: Turntable) -> tuple[str, str, list, list, list]:
    imgs = [im for im in d.get("images") or [] if im.get("used")]
    if not imgs:
        raise LightplaneError("the turntable file records no images (not written by calibrate-turntable): "
                              "nothing to report")
    o, B = tt.basis()
    T = np.array([im["t_cam_board_mm"] for im in imgs], float)
    local = (T - o) @ B
    names = [im["name"] for im in imgs]
    circ = np.array([im["circle_rms_mm"] for im in imgs], float)
    pnp = np.array([im["pnp_rms_px"] for im in imgs], float)
    rmax = float(np.max(np.hypot(local[:, 0], local[:, 1])))
    radii = np.linspace(0.0, max(1.5 * rmax, 10.0), 16)
    heights = np.linspace(float(local[:, 2].min()) - 50.0, float(local[:, 2].max()) + 100.0, 12)
    sig = _turn_sigma(tt, radii, heights)
    j, a = d.get("jackknife") or {}, d.get("agreement") or {}
    sd = float(np.hypot(j.get("sigma_direction_deg_circles", np.nan), 0.0))
    sp = float(j.get("sigma_point_mm_circles", np.nan))
    span = float(d.get("angle_span_deg", np.nan))
    r_ref = max(round(rmax / 10.0) * 10.0, 10.0)
    good = (_head(d.get("quality"), f"Good for merging turntable scans of objects within about {1.5 * rmax:.0f} mm "
                  "of the axis")
            + f": the axis σ {sd:.4f} deg in direction and {sp:.4f} mm across it "
            f"({j.get('covers', 'leave-one-image-out')})")
    if sig is not None:
        k = int(np.argmin(np.abs(radii - r_ref)))
        h0 = int(np.argmin(np.abs(heights - float(np.median(local[:, 2])))))
        good += f"; a point {radii[k]:.0f} mm from the axis turned half a turn moves by σ {sig[h0, k] * 1e3:.0f} µm"
    good += "."
    limits = []
    q = d.get("quality") or {}
    if q.get("verdict") not in (None, "ok"):
        limits.append(f"the axis from the board circles and the one from the rotations are "
                      f"{a.get('angle_deg', float('nan')):.3f} deg and {a.get('distance_mm', float('nan')):.3f} mm "
                      f"apart ({q.get('direction_sigmas', float('nan')):.1f} and "
                      f"{q.get('position_sigmas', float('nan')):.1f} times their σ: {q.get('verdict')})")
    if span < 90.0:
        limits.append(f"the table turned {span:.0f} deg in all: turn it further (90 deg or more) for a firmer axis")
    if len(imgs) < 8:
        limits.append(f"{len(imgs)} images: the jackknife σ rests on few poses")
    flag = _flagged(circ)
    if flag.any():
        w = int(np.argmax(circ))
        limits.append(f"{Path(names[w]).name}'s board points lie {circ[w] * 1e3:.0f} µm from their circles, over "
                      f"{OUTLIER_FACTOR:g}x the median ({np.median(circ) * 1e3:.0f} µm)")
    verdict = _limits(good, limits, f"Nothing obvious limits it: {len(imgs)} images over {span:.0f} deg.")
    rows = [("axis point (camera frame)", ", ".join(f"{v:+.3f}" for v in tt.point_mm) + " mm"),
            ("axis direction (up)", ", ".join(f"{v:+.5f}" for v in tt.direction)),
            ("images used", f"{len(imgs)}, table turned {span:.1f} deg ({d.get('sense_of_the_images', '')})"),
            ("board points to their circles", f"{float(d.get('circle_rms_mm', np.nan)) * 1e3:.1f} µm RMS"),
            ("circles vs rotations", f"{a.get('angle_deg', float('nan')):.4f} deg, "
                                     f"{a.get('distance_mm', float('nan')):.4f} mm apart"),
            ("axis σ", f"direction {sd:.4f} deg, across the axis {sp:.4f} mm")]
    cam = Camera.from_dict(tt.camera) if isinstance(tt.camera, dict) else None
    sections = [Section("Board positions and residuals", figures=[(figure_turntable(
        local, names, (radii, heights, sig if sig is not None else np.full((len(heights), len(radii)), np.nan)),
        circle_rms_mm=circ, pnp_rms_px=pnp), "Board origins from above (mm), residuals per image (µm, px), "
        "axis σ as a point error (µm)")],
        html=_table(("image", "angle (deg)", "PnP RMS (px)", "circle RMS (µm)"),
                    [(Path(n).name, f"{im['angle_deg']:.3f}", f"{im['pnp_rms_px']:.3f}",
                      f"{im['circle_rms_mm'] * 1e3:.1f}") for n, im in zip(names, imgs)], flag))]
    if cam is not None:
        uv = cam.project(T)
        sections.insert(0, Section("Coverage of the views", figures=[(figure_view_coverage(
            (cam.width, cam.height), [], np.zeros((0, 2)), points=[uv]),
            "Board origins in the image (px, red)")]))
    sk = _skipped_table(d.get("skipped") or {})
    if sk is not None:
        sections.append(sk)
    return "Turntable calibration report", verdict, rows, [], sections


# ----------------------------------------------------------------------------- refinement
def _refine_page(d: dict) -> tuple[str, str, list, list, list]:
    rf = d["turntable"]["refined_from_scans"]
    b, s, a = rf["agreement_before_mm"], rf["agreement_searched_mm"], rf["agreement_after_mm"]
    good = (f"The scans agree to {a['median_mm']:.3f} mm median and {a['p90_mm']:.3f} mm at the 90th percentile "
            f"(symmetric point-to-surface distance) with the refined axis and start angles, against "
            f"{b['median_mm']:.3f} / {b['p90_mm']:.3f} mm with the given axis and start angles 0: good for merging "
            f"these scans at that level.")
    limits = ["the refined axis has no covariance: the scans' agreement is its only check"]
    if a["median_mm"] > 0.98 * s["median_mm"]:
        limits.append("refining the axis did not improve on the searched start angles")
    if rf["axis_moved_deg"] > 1.0 or rf["axis_moved_mm"] > 2.0:
        limits.append(f"the axis moved {rf['axis_moved_deg']:.2f} deg and {rf['axis_moved_mm']:.2f} mm: check the "
                      "board calibration of the turntable and that the scans share the set-up")
    verdict = _limits(good, limits, "")
    rows = [("scans", ", ".join(f"{sc['laser']} ({sc['frames']}): start {sc['start_deg']:.3f} deg"
                                for sc in rf["scans"])),
            ("angle per frame", f"{rf['step_deg']:g} deg"),
            ("agreement, given axis, start angles 0", f"median {b['median_mm']:.3f} mm, 90th pct {b['p90_mm']:.3f} mm"),
            ("agreement, start angles searched", f"median {s['median_mm']:.3f} mm, 90th pct {s['p90_mm']:.3f} mm"),
            ("agreement, refined", f"median {a['median_mm']:.3f} mm, 90th pct {a['p90_mm']:.3f} mm"),
            ("axis moved", f"{rf['axis_moved_deg']:.4f} deg, {rf['axis_moved_mm']:.3f} mm across it"),
            ("σ", "none: the refinement gives no covariance")]
    sections = []
    ri = rf.get("report_inputs")
    if isinstance(ri, dict):
        sections.append(Section("The scans before and after", figures=[(figure_scans_overlay(
            ri["before_mm"], ri["after_mm"], ri["names"]), "Scans in the turntable frame (mm), one colour each")]))
    return "Turntable refinement report", verdict, rows, [], sections


# ----------------------------------------------------------------------------- dispatch
def report_kind(d: dict, source: str = "file") -> str:
    """Which report a result file gives (:data:`REPORT_KINDS`); LightplaneError for a file without one."""
    if not isinstance(d, dict):
        raise LightplaneError(f"{source}: not a lightplane result file")
    kind = d.get("kind")
    if kind == "lightplane sensor":
        tt = d.get("turntable")
        if isinstance(tt, dict) and isinstance(tt.get("refined_from_scans"), dict):
            return "refine"
        if isinstance(tt, dict) and tt.get("images"):
            return "turntable"
        raise LightplaneError(f"{source}: a sensor file without a calibrated or refined turntable: report its parts "
                              "from their own files (camera, planes, turntable)")
    if kind == "turntable":
        return "turntable"
    inputs = d.get("report_inputs")
    if "normal" in d:
        if d.get("method") == "zhou":
            if not isinstance(inputs, dict):
                raise LightplaneError(f"{source}: has no stored report inputs (written by an older lightplane): "
                                      "run calibrate-plane-board again")
            return "board_plane"
        return "plane"
    if "K" in d:
        if not isinstance(inputs, dict):
            raise LightplaneError(f"{source}: has no stored report inputs (written by an older lightplane, or not "
                                  "by calibrate-camera): run calibrate-camera again")
        return "camera"
    raise LightplaneError(f"{source}: not a camera, plane, turntable or sensor file of lightplane")


def calibration_report_html(path: str | os.PathLike) -> str:
    """The report page of the camera, board-plane, turntable or sensor file ``path`` (not of
    ``calibrate-plane``'s plane files: :func:`lightplane.report.html.rebuild_report`)."""
    p = Path(path)
    d = read_json(p, "result file")
    kind = report_kind(d, str(p))
    if kind == "camera":
        parts = _camera_page(d, Camera.load(p))
    elif kind == "board_plane":
        parts = _board_plane_page(d, LightPlane.from_dict(d, source=str(p)))
    elif kind == "turntable":
        tdict = d["turntable"] if d.get("kind") == "lightplane sensor" else d
        parts = _turntable_page(tdict, Turntable.from_dict(tdict, str(p)))
    elif kind == "refine":
        parts = _refine_page(d)
    else:
        raise LightplaneError(f"{p}: a calibrate-plane file: use lightplane.report.html.rebuild_report")
    title, verdict, rows, warnings, sections = parts
    prov = d.get("provenance") or (d.get("turntable") or {}).get("provenance")
    return _page(f"{title}: {p.name}", verdict, rows, warnings, sections, prov)


def write_calibration_report(path: str | os.PathLike, out_dir: str | os.PathLike, *, force: bool = False) -> Path:
    """Write ``out_dir/index.html``, the report of the result file ``path`` (any kind of
    :data:`REPORT_KINDS`); refuses to overwrite without ``force``; written atomically."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise LightplaneError(f"{out}: exists and is not a folder")
    target = out / "index.html"
    if out.exists():
        check_output(target, force)
    elif not out.parent.is_dir():
        raise LightplaneError(f"{out}: its parent folder {out.parent} does not exist")
    if report_kind(read_json(Path(path), "result file"), str(path)) == "plane":
        return rebuild_report(path, out, force=force)
    text = calibration_report_html(path)
    out.mkdir(exist_ok=True)
    written = atomic_write(target, text, force=force)
    os.chmod(written, 0o644)  # a page to share: readable like any other file
    return written
