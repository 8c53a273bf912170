"""Self-contained HTML report of a light-plane calibration from images (issue 7).

One file, ``index.html``, that opens offline: the figures are PNGs (matplotlib)
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
- the uncertainty map (:func:`lightplane.uncertainty.plot_point_sigma_map`, µm).

Computation and presentation apart: the report only reads an
:class:`~lightplane.calibrate.ImagePlaneCalibration` (and, for the overlays, the
images it names).
"""

from __future__ import annotations

import base64
import html
import io
import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from .errors import LightplaneError

__all__ = ["Section", "write_report", "render_report_html", "figure_overlays", "figure_poses_3d",
           "figure_residuals", "figure_uncertainty", "load_report_inputs", "rebuild_report"]


@dataclass(frozen=True)
class Section:
    """An extra section of the report: a title, key/value rows, optional raw HTML and PNG figures.

    ``figures``: list of ``(png_bytes, caption)``.
    """

    title: str
    rows: Sequence[tuple[str, str]] = ()
    html: str = ""
    figures: Sequence[tuple[bytes, str]] = field(default_factory=list)


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    _plt().close(fig)
    return buf.getvalue()


def _gray8(img: np.ndarray) -> np.ndarray:
    from .io import to_gray_float

    g = to_gray_float(img)
    lo, hi = float(np.percentile(g, 0.5)), float(np.percentile(g, 99.8))
    return np.clip((g - lo) / max(hi - lo, 1e-9) * 255.0, 0, 255).astype(np.uint8)


def _chord_px(cal, obs) -> np.ndarray | None:
    """(N, 2) distorted px of the chord where the plane cuts the observation's chosen pose."""
    from .refine import chord_endpoints

    p = obs.placement
    if p is None or p.pose is None or cal.camera is None:
        return None
    ends = chord_endpoints(cal.plane, p.pose.center, p.pose.normal, p.pose.radius_mm)
    if ends is None:
        return None
    s = np.linspace(0.0, 1.0, 50)[:, None]
    return cal.camera.project(ends[0] + s * (ends[1] - ends[0]))


def _overlay_image(entry, o) -> tuple[np.ndarray | None, bool]:
    """``(image, blank)`` for observation ``o`` from ``entry`` (an array, a file path or None):
    the image, or — when it cannot be read or no longer has the recorded size — a blank
    canvas of the recorded size (``blank`` True), or ``(None, True)`` without a size."""
    from .io import try_read_image

    img = None
    if isinstance(entry, np.ndarray):
        img = entry
    elif isinstance(entry, (str, os.PathLike)) and not str(entry).startswith("image["):
        img, _ = try_read_image(entry)
    shape = tuple(o.shape[:2]) if len(o.shape) >= 2 else ()
    if img is not None and (not shape or tuple(img.shape[:2]) == shape):
        return img, False
    if not shape:
        return None, True
    return np.full(shape, 40, np.uint8), True


def figure_overlays(cal, images: Sequence | None = None, *, columns: int = 4, max_images: int = 24) -> bytes:
    """PNG: per image, a crop around the target with the ellipse, rim points, stripe points and chord.

    ``images``: optional entries in the order of ``cal.images``, each an array, a file path or
    None (default: the files named there).  An image that cannot be read (or whose size
    changed) is replaced by a blank canvas of the recorded size, and its title says so.
    """
    return _overlays(cal, images, columns=columns, max_images=max_images)[0]


def _overlays(cal, images: Sequence | None = None, *, columns: int = 4, max_images: int = 24
              ) -> tuple[bytes, list[str]]:
    """:func:`figure_overlays` and the names of the images drawn on a blank canvas."""
    plt = _plt()
    obs = list(cal.images)[:max_images]
    n = max(len(obs), 1)
    cols = min(columns, n)
    rows = int(math.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 3.0 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.set_visible(False)
    blanks = []
    for k, o in enumerate(obs):
        ax = axes.ravel()[k]
        ax.set_visible(True)
        entry = o.source if images is None else (images[k] if k < len(images) else None)
        img, blank = _overlay_image(entry, o)
        if img is None:
            ax.set_title(f"{o.name}: image not available", fontsize=7)
            blanks.append(o.name)
            continue
        if blank:
            blanks.append(o.name)
        g = np.full(img.shape[:2], 40, np.uint8) if blank else _gray8(img)
        h, w = g.shape
        if o.ellipse is not None:
            u0, v0, u1, v1 = o.ellipse.bbox()
            pad = 0.15 * max(u1 - u0, v1 - v0)
            u0, v0 = max(int(u0 - pad), 0), max(int(v0 - pad), 0)
            u1, v1 = min(int(u1 + pad), w - 1), min(int(v1 + pad), h - 1)
        else:
            u0, v0, u1, v1 = 0, 0, w - 1, h - 1
        ax.imshow(g[v0:v1 + 1, u0:u1 + 1], cmap="gray", extent=(u0 - 0.5, u1 + 0.5, v1 + 0.5, v0 - 0.5),
                  interpolation="nearest", **({"vmin": 0, "vmax": 255} if blank else {}))
        if o.ellipse is not None:
            e = o.ellipse.points(180)
            ax.plot(np.r_[e[:, 0], e[:1, 0]], np.r_[e[:, 1], e[:1, 1]], "-", color="#00c8ff", lw=0.8)
        if len(o.rim_uv):
            r = o.rim_uv[:: max(1, len(o.rim_uv) // 150)]
            ax.plot(r[:, 0], r[:, 1], ".", color="#ffd000", ms=1.5)
        pts = o.stripe_raw_uv if len(o.stripe_raw_uv) else o.stripe_uv
        if len(pts):
            s = pts[:: max(1, len(pts) // 150)]
            ax.plot(s[:, 0], s[:, 1], ".", color="#ff3030", ms=1.5)
        ch = _chord_px(cal, o) if o.used else None
        if ch is not None:
            ax.plot(ch[:, 0], ch[:, 1], "-", color="#30ff60", lw=0.9)
        ax.set_xlim(u0 - 0.5, u1 + 0.5)
        ax.set_ylim(v1 + 0.5, v0 - 0.5)
        status = "used" if o.used else f"rejected: {o.reason}"
        title = f"{o.name}\n{status}"[:90] + ("\n(image not found: blank canvas)" if blank else "")
        ax.set_title(title, fontsize=7, color="black" if o.used else "#b00000")
        ax.tick_params(labelsize=6)
        ax.set_xlabel("u (px)", fontsize=6)
        ax.set_ylabel("v (px)", fontsize=6)
    fig.suptitle("Targets: ellipse (cyan), rim edge points (yellow), stripe points (red), "
                 "chord of the calibrated plane on the chosen pose (green)", fontsize=9)
    fig.tight_layout()
    return _png(fig), blanks


def _disc(center, normal, r, n=60) -> np.ndarray:
    normal = np.asarray(normal, float)
    ref = np.eye(3)[int(np.argmin(np.abs(normal)))]
    e1 = np.cross(normal, ref)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    t = np.linspace(0, 2 * np.pi, n)
    return np.asarray(center) + r * (np.outer(np.cos(t), e1) + np.outer(np.sin(t), e2))


def figure_poses_3d(cal, plane_true=None) -> bytes:
    """PNG: 3D view (mm, camera frame) of the target poses (used: blue, both
    candidates of undecided ones: grey) and the calibrated plane's patch over the targets."""
    plt = _plt()
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    fig = plt.figure(figsize=(7.5, 6.0))
    ax = fig.add_subplot(111, projection="3d")
    pts = []
    ends = []
    from .refine import chord_endpoints

    for p in cal.placements:
        if p.pose is None:
            continue
        poses = [p.pose] if p.used else [q for q in (p.poses or ()) if q is not None]
        for q in poses:
            ring = _disc(q.center, q.normal, q.radius_mm)
            ax.plot(ring[:, 0], ring[:, 2], -ring[:, 1], "-", color="#1f5fbf" if p.used else "#999999", lw=1.0)
            pts.append(q.center)
        if p.used:
            e = chord_endpoints(cal.plane, p.pose.center, p.pose.normal, p.pose.radius_mm)
            if e is not None:
                ends.append(e)
                ax.plot(e[:, 0], e[:, 2], -e[:, 1], "-", color="#d02020", lw=1.5)
    if ends:
        E = np.vstack(ends)
        n = cal.plane.normal
        ref = np.eye(3)[int(np.argmin(np.abs(n)))]
        b1 = np.cross(n, ref)
        b1 /= np.linalg.norm(b1)
        b2 = np.cross(n, b1)
        c = E.mean(axis=0)
        q = np.column_stack([(E - c) @ b1, (E - c) @ b2])
        try:
            from scipy.spatial import ConvexHull

            hull = q[ConvexHull(q).vertices] * 1.15
        except Exception:  # noqa: BLE001 - degenerate hull: a bounding box instead
            lo, hi = q.min(axis=0) * 1.15, q.max(axis=0) * 1.15
            hull = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
        poly = c + hull[:, :1] * b1 + hull[:, 1:] * b2
        ax.add_collection3d(Poly3DCollection([list(zip(poly[:, 0], poly[:, 2], -poly[:, 1]))], alpha=0.18,
                                             facecolor="#ff6060", edgecolor="#d02020"))
        pts.extend(poly)
    if not pts:
        pts = [np.zeros(3)]
    P = np.array(pts)
    mid = 0.5 * (P.min(axis=0) + P.max(axis=0))
    half = 0.5 * float(np.max(P.max(axis=0) - P.min(axis=0)))
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[2] - half, mid[2] + half)
    ax.set_zlim(-mid[1] - half, -mid[1] + half)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("z (mm, optical axis)")
    ax.set_zlabel("−y (mm, up)")
    ax.set_title("Target poses in the camera frame (blue; grey: both candidates of unused placements),\n"
                 "chords on the calibrated light plane (red) and its patch over the targets", fontsize=9)
    ax.view_init(elev=22, azim=-60)
    fig.tight_layout()
    return _png(fig)


def figure_residuals(cal) -> bytes:
    """PNG: per image, the RMS residuals of the rim and stripe points (px) and the chord's
    RMS distance to the plane (µm)."""
    plt = _plt()
    obs = [o for o in cal.images if o.placement is not None]
    names = [o.name for o in obs]
    x = np.arange(len(obs))
    rim = np.array([o.placement.rim_rms_px for o in obs], float)
    st = np.array([o.placement.stripe_rms_px for o in obs], float)
    ch = np.array([o.placement.chord_rms_mm for o in obs], float) * 1e3
    used = np.array([o.used for o in obs], bool)
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(max(6.0, 0.55 * len(obs) + 2), 5.6), sharex=True)
    a1.bar(x - 0.2, rim, 0.4, label="rim points to the projected circle", color="#1f5fbf")
    a1.bar(x + 0.2, st, 0.4, label="stripe points to the projected chord", color="#d02020")
    if cal.sigma_px and np.isfinite(cal.sigma_px):
        a1.axhline(cal.sigma_px, color="k", lw=0.8, ls="--", label=f"estimated noise σ = {cal.sigma_px:.3f} px")
    a1.set_ylabel("RMS residual (px)")
    a1.legend(fontsize=7)
    a2.bar(x, np.where(used, ch, np.nan), 0.5, color="#444444")
    a2.set_ylabel("chord RMS distance\nto the plane (µm)")
    a2.set_xticks(x)
    a2.set_xticklabels(names, rotation=60, ha="right", fontsize=7)
    a2.set_xlabel("image")
    a1.set_title(f"Residuals per image (method {cal.method})", fontsize=9)
    fig.tight_layout()
    return _png(fig)


def figure_uncertainty(cal, distance_mm: tuple[float, float] | None = None) -> bytes | None:
    """PNG of :func:`lightplane.uncertainty.plot_point_sigma_map` (µm), None without a covariance."""
    from .uncertainty import plot_point_sigma_map

    if cal.covariance is None or cal.camera is None:
        return None
    if distance_mm is None:
        d = [float(np.linalg.norm(p.pose.center)) for p in cal.placements if p.used and p.pose is not None]
        # the used targets' range, rounded outwards to 10 mm
        distance_mm = ((math.floor(min(d) / 10) * 10.0, math.ceil(max(d) / 10) * 10.0)
                       if d and max(d) - min(d) > 1 else (380.0, 520.0))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "sigma.png"
        plot_point_sigma_map(cal.camera, cal.plane, path, distance_mm=distance_mm, force=True)
        return path.read_bytes()


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
    (:func:`lightplane.io.provenance`), shown at the foot (default: ``cal.plane.meta``'s).
    """
    from .calibrate import uncertainty_summary

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
                                         f"correlation factors {nm.get('tau_rim', 1):.1f} / {nm.get('tau_stripe', 1):.1f}"))
    if unc:
        rows += [("normal σ (two principal directions)",
                  f"{unc['normal_sigma_deg'][0]:.4f} deg, {unc['normal_sigma_deg'][1]:.4f} deg"),
                 ("offset d σ", f"{unc['d_sigma_mm']:.4f} mm")]
        if "working_distance_mm" in unc:
            rows.append(("working distance (plane on the optical axis)", f"{unc['working_distance_mm']:.1f} mm"))
        if "point_sigma_axis_mm" in unc:
            rows.append(("σ of a triangulated point there (plane calibration only)",
                         f"{unc['point_sigma_axis_mm'] * 1e3:.2f} µm"))
        if "point_sigma_rms_mm" in unc:
            lo, hi = unc["distance_range_mm"]
            rows.append((f"RMS point σ over the targets' range {lo:.0f}–{hi:.0f} mm",
                         f"{unc['point_sigma_rms_mm'] * 1e3:.2f} µm"))
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
    parts = [f"<!DOCTYPE html><html lang=en><head><meta charset=utf-8><title>{html.escape(title or 'lightplane report')}"
             f"</title><style>{_CSS}</style></head><body>",
             f"<h1>{html.escape(title or 'Light-plane calibration report')}</h1>",
             "<h2>Result</h2>", _kv(rows)]
    if cal.warnings:
        parts.append("<ul>" + "".join(f"<li class=warn>{html.escape(w)}</li>" for w in cal.warnings) + "</ul>")
    # per-image table
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
    parts += ["<h2>Images</h2>", "<table>" + head + "".join(trs) + "</table>"]
    if figures:
        png, blanks = _overlays(cal, images)
        parts += ["<h2>Targets and stripes</h2>", _img_tag(png, "Per-image overlays (axes in px)")]
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
                      "correlated along the curves); it does not include the noise of the measured stripe centre "
                      "itself, errors of the camera intrinsics, systematic edge or stripe biases, a wrong "
                      "diameter or a non-flat target.</p>",
                      _img_tag(u, "Point σ map (µm) over the image (px)")]
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


def write_report(out_dir: str | os.PathLike, cal, *, images: Sequence | None = None, plane_true=None,
                 extra_sections: Sequence[Section] = (), title: str | None = None, force: bool = False,
                 provenance: dict | None = None) -> Path:
    """Write ``out_dir/index.html`` (self-contained) for ``cal`` (an ImagePlaneCalibration); returns its path.

    Refuses to overwrite an existing ``index.html`` without ``force``; written atomically.
    """
    from .io import atomic_write, check_output

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise LightplaneError(f"{out}: exists and is not a folder")
    if not getattr(cal, "images", None):
        raise LightplaneError("the report needs a calibration from images (lightplane.calibrate.calibrate_plane)")
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

    ``cal``: the :class:`~lightplane.calibrate.ImagePlaneCalibration` rebuilt from the file's
    ``report_inputs``; ``images``: per image, the file it was read from when that file still
    exists (its name as given to the calibration, relative to the current folder, or else to
    the plane file's folder), otherwise None; ``provenance``: the file's ``provenance``.
    Raises :class:`LightplaneError` for a file without stored inputs (an older plane file, or
    one not made from images).
    """
    from .calibrate import ImagePlaneCalibration
    from .io import read_json
    from .plane import LightPlane

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
