"""Self-contained HTML report of a light-plane calibration from images.

One file, ``index.html``, that opens offline: the figures are PNGs (:mod:`lightplane.report.plots`)
embedded as base64, no scripts, no external style sheets.  Contents:

- the plane with its uncertainty (normal sigma in deg, offset sigma in mm, point
  sigma at the working distance in mm), the method, warnings, and — on simulated
  data — the errors against the truth;
- per-image table: used or rejected with the reason, rim/stripe residuals (px),
  stripe points, chord distance to the plane (µm);
- per-image overlays: the target's ellipse, the rim edge points, the stripe points,
  and the chord where the calibrated plane cuts the chosen target pose (px axes);
- a 3D view of the target poses, the camera and the plane (mm axes);
- residual plots (px and µm);
- the uncertainty map (:func:`lightplane.report.plots.point_sigma_map`, µm).

Computation and presentation apart: the report only reads an
:class:`~lightplane.plane.calibrate.ImagePlaneCalibration` (and, for the overlays, the
images it names).
"""

from __future__ import annotations

import base64
import html
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from lightplane.core.errors import LightplaneError
from lightplane.report.plots import figure_overlays, figure_poses_3d, figure_residuals, figure_uncertainty
from lightplane.report.plots import overlays as _overlays
from lightplane.core.io import atomic_write, check_output, read_json
from lightplane.plane.calibrate import ImagePlaneCalibration, uncertainty_summary
from lightplane.plane.model import LightPlane
from lightplane.plane.ml import dispersion_factor

__all__ = ["Section", "write_report", "render_report_html", "figure_overlays", "figure_poses_3d",
           "figure_residuals", "figure_uncertainty", "load_report_inputs", "rebuild_report"]  # figure_*: from lightplane.report.plots


@dataclass(frozen=True)
class Section:
    """An extra section of the report: a title, key/value rows, optional raw HTML and PNG figures.

    ``figures``: list of ``(png_bytes, caption)``.
    """

    title: str
    rows: Sequence[tuple[str, str]] = ()
    html: str = ""
    figures: Sequence[tuple[bytes, str]] = field(default_factory=list)


# ----------------------------------------------------------------------------- HTML
_CSS = """
body{font-family:sans-serif;max-width:1100px;margin:1em auto;padding:0 1em;color:#222}
h1{font-size:1.4em} h2{font-size:1.15em;border-bottom:1px solid #ccc;margin-top:1.6em}
table{border-collapse:collapse;font-size:0.85em;margin:0.5em 0}
td,th{border:1px solid #ccc;padding:2px 6px;text-align:left}
th{background:#f0f0f0} tr.rejected td{color:#a00000}
td.num{text-align:right;font-family:monospace}
img{max-width:100%;border:1px solid #ddd;margin:0.3em 0}
.warn{color:#a05000} .small{font-size:0.8em;color:#666}
"""


def _img_tag(png: bytes, caption: str) -> str:
    b64 = base64.b64encode(png).decode("ascii")
    return (f'<figure><img alt="{html.escape(caption)}" src="data:image/png;base64,{b64}">'
            f"<figcaption class=small>{html.escape(caption)}</figcaption></figure>")


def _kv(rows) -> str:
    return "<table>" + "".join(f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(str(v))}</td></tr>"
                               for k, v in rows) + "</table>"


def _f(x, fmt: str) -> str:
    try:
        x = float(x)
    except (TypeError, ValueError):
        return "–"
    return format(x, fmt) if math.isfinite(x) else "–"


def render_report_html(cal, *, images: Sequence | None = None, plane_true=None,
                       extra_sections: Sequence[Section] = (), title: str | None = None,
                       figures: bool = True, provenance: dict | None = None) -> str:
    """The report page as one HTML string (figures embedded).

    ``images``: see :func:`figure_overlays`; ``provenance``: what produced the plane
    (:func:`lightplane.core.io.provenance`), shown at the foot (default: ``cal.plane.meta``'s).
    """
    parts = [f"<!DOCTYPE html><html lang=en><head><meta charset=utf-8><title>{html.escape(title or 'lightplane report')}"
             f"</title><style>{_CSS}</style></head><body>",
             f"<h1>{html.escape(title or 'Light-plane calibration report')}</h1>",
             "<h2>Result</h2>", _kv(_result_rows(cal, plane_true))]
    if cal.warnings:
        parts.append("<ul>" + "".join(f"<li class=warn>{html.escape(w)}</li>" for w in cal.warnings) + "</ul>")
    parts += ["<h2>Images</h2>", _images_table(cal)]
    if figures:
        parts += _figure_parts(cal, images, plane_true)
    for s in extra_sections:
        parts.append(f"<h2>{html.escape(s.title)}</h2>")
        if s.rows:
            parts.append(_kv(s.rows))
        if s.html:
            parts.append(s.html)
        for png, cap in s.figures:
            parts.append(_img_tag(png, cap))
    prov = provenance
    if prov is None:
        prov = cal.plane.meta.get("provenance") if isinstance(cal.plane.meta, dict) else None
    parts.append(f"<p class=small>lightplane report; {html.escape(str(prov or ''))}</p></body></html>")
    return "\n".join(parts)


def _result_rows(cal, plane_true) -> list[tuple[str, str]]:
    """The result table: the plane, the method, the images, the noise, the uncertainty, the truth."""
    cam = cal.camera
    unc = uncertainty_summary(cal, cam) if cam is not None else {}
    a, b, c = cal.plane.normal
    rows = [("plane (camera frame, mm)", f"{a:+.6f} x {b:+.6f} y {c:+.6f} z {cal.plane.d:+.4f} = 0"),
            ("method", cal.method),
            ("images used", f"{cal.n_used} of {len(cal.images)}"),
            ("target diameter", f"{cal.diameter_mm:g} mm"),
            ("estimated image noise σ", f"{_f(cal.sigma_px, '.3f')} px")]
    nm = cal.plane.meta.get("noise_model") or {}
    if nm.get("sigma_rim_px") is not None and nm.get("sigma_stripe_px") is not None:
        rows.append(("noise model (ML)", f"rim {nm['sigma_rim_px']:.3f} px, stripe {nm['sigma_stripe_px']:.3f} px; "
                                         f"correlation factors {nm.get('tau_rim', 1):.1f} / {nm.get('tau_stripe', 1):.1f}"
                                         + (f"; images' dispersion {nm['image_dispersion']:.2f}"
                                            + (f" (x{dispersion_factor(nm):.2f} applied)"
                                               if nm.get("image_dispersion_applied") else " (not applied)")
                                            if nm.get("image_dispersion") is not None else "")))
    if unc:
        rows += _uncertainty_rows(unc)
    else:
        rows.append(("uncertainty", f"not available for method '{cal.method}' (use 'ml')"))
    if cal.ambiguity is not None:
        rows.append(("ambiguity of the chord choice", cal.ambiguity.message or
                     f"best {cal.ambiguity.best_cost:.3g}, second {cal.ambiguity.second_cost:.3g}"))
    if plane_true is not None:
        ang = math.degrees(cal.plane.angle_to(plane_true))
        off = float(cal.plane.signed_distance(plane_true.point_on_axis()[None])[0])
        rows += [("vs truth: normal angle", f"{ang:.4f} deg"),
                 ("vs truth: offset at the optical axis", f"{off:+.4f} mm")]
    return rows


def _uncertainty_rows(unc: dict) -> list[tuple[str, str]]:
    """The rows of :func:`lightplane.plane.calibrate.uncertainty_summary`'s entries."""
    rows = [("normal σ (two principal directions)",
             f"{unc['normal_sigma_deg'][0]:.4f} deg, {unc['normal_sigma_deg'][1]:.4f} deg"),
            ("offset d σ", f"{unc['d_sigma_mm']:.4f} mm")]
    if "working_distance_mm" in unc:
        rows.append(("working distance (plane on the optical axis)", f"{unc['working_distance_mm']:.1f} mm"))
    if "normal_sigma_with_camera_deg" in unc:
        rows += [("with the camera's share: normal σ",
                  f"{unc['normal_sigma_with_camera_deg'][0]:.4f} deg, {unc['normal_sigma_with_camera_deg'][1]:.4f} deg"),
                 ("with the camera's share: offset d σ", f"{unc['d_sigma_with_camera_mm']:.4f} mm")]
    if "point_sigma_axis_mm" in unc:
        rows.append(("σ of a triangulated point there (camera frame; all sources the files carry)",
                     f"{unc['point_sigma_axis_mm'] * 1e3:.2f} µm (plane calibration only: "
                     f"{unc['point_sigma_axis_plane_only_mm'] * 1e3:.2f} µm)"))
    if "point_sigma_rms_mm" in unc:
        lo, hi = unc["distance_range_mm"]
        cov = unc["covers"]
        rows += [(f"RMS point σ over the targets' range {lo:.0f}–{hi:.0f} mm, camera frame",
                  f"{unc['point_sigma_rms_mm'] * 1e3:.2f} µm — {cov['point_sigma_rms_mm']}"),
                 ("RMS shape σ there (after the best rigid motion)",
                  f"{unc['shape_sigma_rms_mm'] * 1e3:.2f} µm — {cov['shape_sigma_rms_mm']}"),
                 ("RMS point σ, plane calibration only", f"{unc['plane_only_sigma_rms_mm'] * 1e3:.2f} µm"),
                 ("which σ applies", cov["which"])]
    if unc.get("camera_share", "included") != "included":
        rows.append(("camera's share", unc["camera_share"]))
    return rows


def _images_table(cal) -> str:
    """The per-image table: status, reason, points, residuals, pose candidate, distance, time."""
    head = ("<tr><th>#</th><th>image</th><th>status</th><th>reason</th><th>rim points</th>"
            "<th>stripe centres (solver points)</th><th>rim RMS (px)</th><th>stripe RMS (px)</th><th>chord to plane RMS (µm)</th>"
            "<th>pose candidate</th><th>distance (mm)</th><th>time (s)</th></tr>")
    trs = []
    for o in cal.images:
        p = o.placement
        dist = float(np.linalg.norm(p.pose.center)) if (p is not None and p.pose is not None) else float("nan")
        trs.append(
            f"<tr class={'used' if o.used else 'rejected'}><td class=num>{o.index}</td><td>{html.escape(o.name)}</td>"
            f"<td>{o.status}</td><td>{html.escape(o.reason or '')}</td><td class=num>{len(o.rim_uv)}</td>"
            f"<td class=num>{len(o.stripe_raw_uv)} ({len(o.stripe_uv) if p is None else p.n_stripe})</td>"
            f"<td class=num>{_f(None if p is None else p.rim_rms_px, '.3f')}</td>"
            f"<td class=num>{_f(None if p is None else p.stripe_rms_px, '.3f')}</td>"
            f"<td class=num>{_f(None if p is None else p.chord_rms_mm * 1e3, '.1f')}</td>"
            f"<td class=num>{'–' if p is None or p.candidate is None else p.candidate}</td>"
            f"<td class=num>{_f(dist, '.1f')}</td><td class=num>{o.seconds:.2f}</td></tr>")
    return "<table>" + head + "".join(trs) + "</table>"


def _figure_parts(cal, images: Sequence | None, plane_true) -> list[str]:
    """The figures: overlays, 3D poses, residuals, the point σ map."""
    png, blanks = _overlays(cal, images)
    parts = ["<h2>Targets and stripes</h2>", _img_tag(png, "Per-image overlays (axes in px)")]
    if blanks:
        parts.append("<p class=small>Image not found (or changed since the calibration): "
                     + html.escape(", ".join(blanks)) + "; its points are drawn on a blank canvas "
                     "of the image's size.</p>")
    parts += ["<h2>Target poses and light plane</h2>",
              _img_tag(figure_poses_3d(cal, plane_true), "3D view, camera frame (mm)")]
    if any(o.placement is not None for o in cal.images):
        parts += ["<h2>Residuals</h2>", _img_tag(figure_residuals(cal), "Residuals per image (px, µm)")]
    u = figure_uncertainty(cal)
    if u is not None:
        parts += ["<h2>Uncertainty of measured points</h2>",
                  "<p class=small>σ (µm) of a point triangulated at each pixel, from the plane's covariance "
                  "only: it covers the image noise of the calibration images (rim and stripe, white or "
                  "correlated along the curves, and errors shared within an image where the plane file applies "
                  "the images' dispersion); it does not include the noise of the measured stripe centre "
                  "itself, errors of the camera intrinsics, systematic edge or stripe biases, a wrong "
                  "diameter or a non-flat target.</p>",
                  _img_tag(u, "Point σ map (µm) over the image (px)")]
    return parts


def write_report(out_dir: str | os.PathLike, cal, *, images: Sequence | None = None, plane_true=None,
                 extra_sections: Sequence[Section] = (), title: str | None = None, force: bool = False,
                 provenance: dict | None = None) -> Path:
    """Write ``out_dir/index.html`` (self-contained) for ``cal`` (an ImagePlaneCalibration); returns its path.

    Refuses to overwrite an existing ``index.html`` without ``force``; written atomically.
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise LightplaneError(f"{out}: exists and is not a folder")
    if not getattr(cal, "images", None):
        raise LightplaneError("the report needs a calibration from images (lightplane.plane.calibrate.calibrate_plane)")
    target = out / "index.html"
    if out.exists():
        check_output(target, force)
    elif not out.parent.is_dir():
        raise LightplaneError(f"{out}: its parent folder {out.parent} does not exist")
    text = render_report_html(cal, images=images, plane_true=plane_true, extra_sections=extra_sections, title=title,
                              provenance=provenance)
    out.mkdir(exist_ok=True)
    path = atomic_write(target, text, force=force)
    os.chmod(path, 0o644)  # a page to share: readable like any other file (mkstemp makes it 0600)
    return path


# ----------------------------------------------------------------------------- from a plane file
def load_report_inputs(plane_file: str | os.PathLike):
    """``(cal, images, provenance)`` stored in a plane file written by ``calibrate-plane``.

    ``cal``: the :class:`~lightplane.plane.calibrate.ImagePlaneCalibration` rebuilt from the file's
    ``report_inputs``; ``images``: per image, the file it was read from when that file still
    exists (its name as given to the calibration, relative to the current folder, or else to
    the plane file's folder), otherwise None; ``provenance``: the file's ``provenance``.
    Raises :class:`LightplaneError` for a file without stored inputs (an older plane file, or
    one not made from images).
    """

    path = Path(plane_file)
    d = read_json(path, "plane file")
    plane = LightPlane.from_dict(d, source=str(path))
    inputs = d.get("report_inputs")
    if not isinstance(inputs, dict):
        raise LightplaneError(f"{path}: has no stored calibration inputs (written by an older lightplane, or not by "
                              "calibrate-plane): run calibrate-plane again with --report")
    cal = ImagePlaneCalibration.from_report_inputs(plane, inputs, source=str(path))
    images: list = []
    for o in cal.images:
        found = None
        if not o.source.startswith("image["):
            for cand in (Path(o.source), path.parent / o.source):
                if cand.is_file():
                    found = str(cand)
                    break
        images.append(found)
    return cal, images, d.get("provenance")


def rebuild_report(plane_file: str | os.PathLike, out_dir: str | os.PathLike, *, force: bool = False) -> Path:
    """Write ``out_dir/index.html``, the report of ``calibrate-plane``, from its plane file alone.

    Image thumbnails come from the image files when they still exist; otherwise the points are
    drawn on a blank canvas of the recorded image size and the report says so.
    """
    cal, images, prov = load_report_inputs(plane_file)
    return write_report(out_dir, cal, images=images, provenance=prov, force=force)
