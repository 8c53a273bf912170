"""Every figure of lightplane, in one module.

matplotlib is imported inside the functions (Agg backend), so nothing else pays for it
and the library's computing modules never import it: the CLI commands, the report
(:mod:`lightplane.report.html`) and the demo call these functions with results computed
elsewhere.

- :func:`intrinsics_residuals` — corner residuals of a camera calibration (``calibrate-camera --plot``);
- :func:`study_factor` — the paper's §3 study, one factor (``lightplane simulate``);
- :func:`point_sigma_map` — the triangulated points' sigma over the image;
- :func:`figure_overlays` / :func:`overlays`, :func:`figure_poses_3d`, :func:`figure_residuals`,
  :func:`figure_uncertainty` — the calibrate-plane report's figures, as PNG bytes;
- :func:`figure_view_coverage`, :func:`figure_view_residuals`, :func:`figure_residual_field`,
  :func:`figure_image_map`, :func:`figure_turntable`, :func:`figure_scans_overlay` — the figures of the
  other calibrations' reports (:mod:`lightplane.report.calibrations`), as PNG bytes.

Files are written atomically (:func:`save_figure`); the ``figure_*`` functions return PNG bytes.
"""

from __future__ import annotations

import io
import math
import os
import tempfile
from pathlib import Path
from typing import Sequence

import numpy as np
from lightplane.core.io import atomic_write, to_gray8, try_read_image
from lightplane.evaluate.study import METHODS
from lightplane.plane.ml import chord_endpoints
from lightplane.plane.triangulate import triangulate
from lightplane.plane.uncertainty import camera_share_status, point_sigma_mm

__all__ = ["save_figure", "intrinsics_residuals", "study_factor", "point_sigma_map", "overlays", "figure_overlays",
           "figure_poses_3d", "figure_residuals", "figure_uncertainty", "point_cloud", "figure_view_coverage",
           "figure_view_residuals", "figure_residual_field", "figure_image_map", "figure_turntable",
           "figure_scans_overlay", "figure_point_sigma"]


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


def save_figure(fig, path: str | os.PathLike, *, force: bool = False, dpi: int | None = None) -> Path:
    """Save a matplotlib figure atomically (format from the suffix, PNG by default) and close it."""
    fmt = Path(path).suffix.lstrip(".").lower() or "png"
    try:
        return atomic_write(path, lambda tmp: fig.savefig(tmp, format=fmt, dpi=dpi), force=force)
    finally:
        _plt().close(fig)


# ----------------------------------------------------------------------------- camera calibration
def intrinsics_residuals(result, path: str | os.PathLike, *, force: bool = True) -> Path:
    """PNG (or the suffix's format) of an :class:`~lightplane.camera.intrinsics.IntrinsicsCalibration`:
    all corner residuals (px) as a scatter and per-view RMS bars."""
    plt = _plt()

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.5))
    for name, r in zip(result.used, result.residuals_px):
        ax1.plot(r[:, 0], r[:, 1], ".", ms=2, alpha=0.6)
    ax1.set_aspect("equal")
    ax1.set_xlabel("residual u (px)")
    ax1.set_ylabel("residual v (px)")
    ax1.set_title(f"Corner residuals, RMS {result.rms_px:.3f} px")
    ax1.grid(True, alpha=0.3)
    labels = [Path(n).name for n in result.used]
    ax2.bar(range(len(labels)), result.per_view_rms_px)
    ax2.set_xticks(range(len(labels)))
    ax2.set_xticklabels(labels, rotation=60, ha="right", fontsize=7)
    ax2.set_ylabel("per-view RMS (px)")
    ax2.set_title("Per-view reprojection error")
    fig.tight_layout()
    return save_figure(fig, path, force=force, dpi=110)


# ----------------------------------------------------------------------------- the paper's §3 study
_PLOT_FLOOR = {"rel_coef_pct": 1e-7, "angle_deg": 1e-7, "tri_rms_mm": 1e-7}
_STYLE = {"paper": dict(color="tab:red", marker="s"), "global": dict(color="tab:orange", marker="^"),
          "ml": dict(color="tab:blue", marker="o"), "crlb": dict(color="black", ls="--", marker="")}


def study_factor(result, path: str | os.PathLike, *, force: bool = False) -> Path:
    """PNG with four panels against the factor: relative coefficient error (%), angle error
    (deg), triangulation RMS over the working volume (mm), and the failure rate (%), for a
    :class:`~lightplane.evaluate.study.StudyResult`."""
    plt = _plt()

    spec = result.factor
    methods = [m for m in (*METHODS, "crlb") if any(r["method"] == m for r in result.rows)]
    fig, axes = plt.subplots(2, 2, figsize=(11, 8), dpi=100)
    panels = [("rel_coef_pct", "relative error of b, c, d (RMS, %)"), ("angle_deg", "normal angle error (RMS, deg)"),
              ("tri_rms_mm", "triangulation error, working volume (RMS, mm)"), ("failed", "failed trials (%): wrong pose chosen, or error")]
    for ax, (key, ylabel) in zip(axes.ravel(), panels):
        for m in methods:
            rows = [r for r in result.rows if r["method"] == m]
            x = np.array([r["level"] for r in rows], dtype=float)
            if key == "failed":
                if m == "crlb":
                    continue
                y = np.array([100.0 * r["failed"] / r["trials"] for r in rows])
            else:
                y = np.array([r[key] for r in rows], dtype=float)
                y = np.where(y > _PLOT_FLOOR.get(key, 0.0), y, np.nan)  # noise-free level: not on a log axis
            ax.plot(x, y, label="Cramér–Rao bound" if m == "crlb" else m, lw=1.5, ms=5, **_STYLE[m])
        if key != "failed":
            ax.set_yscale("log")
        ax.set_xlabel(spec.label)
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.3)
    axes[0, 0].legend()
    fixed = {"placements": f"D = {spec.diameter_mm:g} mm, sigma = {spec.sigma_px:g} px",
             "noise": f"D = {spec.diameter_mm:g} mm, {spec.n_placements} placements",
             "diameter": f"sigma = {spec.sigma_px:g} px, {spec.n_placements} placements"}[spec.name]
    fig.suptitle(f"Paper §3 study — {spec.name} ({fixed}; {result.trials} trials per level, "
                 f"{result.n_rim} rim + {result.n_stripe} stripe points per placement)", fontsize=10)
    fig.tight_layout()

    return save_figure(fig, path, force=force)


# ----------------------------------------------------------------------------- uncertainty
def point_sigma_map(camera, plane, path: str | os.PathLike, *, force: bool = False,
                    distance_mm: tuple[float, float] = (380.0, 520.0), step_px: float = 8.0,
                    covariance: np.ndarray | None = None, title: str | None = None) -> Path:
    """Write a PNG map of the triangulated points' sigma (mm) over the image.

    Every pixel of a ``step_px`` grid is coloured by :func:`lightplane.plane.uncertainty.point_sigma_mm`
    (camera frame; the camera's share included when the files carry it, as the colour bar says); pixels
    whose ray meets the plane outside ``distance_mm`` are greyed out, and contours
    mark the distance to the camera (mm).  Written atomically.
    """

    plt = _plt()
    us = np.arange(0, camera.width, step_px)
    vs = np.arange(0, camera.height, step_px)
    U, V = np.meshgrid(us, vs)
    uv = np.column_stack([U.ravel(), V.ravel()])
    dist = np.linalg.norm(triangulate(camera, plane, uv), axis=1).reshape(U.shape)
    sig = point_sigma_mm(camera, plane, uv, covariance=covariance).reshape(U.shape)
    inside = np.isfinite(dist) & (dist >= distance_mm[0]) & (dist <= distance_mm[1])
    fig, ax = plt.subplots(figsize=(8, 6.4), dpi=100)
    ext = (-0.5, camera.width - 0.5, camera.height - 0.5, -0.5)
    ax.imshow(np.where(inside, np.nan, 1.0), extent=ext, cmap="Greys", vmin=0, vmax=4, interpolation="nearest")
    vmax = np.nanmax(np.where(inside, sig, np.nan)) if np.any(inside) else np.nanmax(sig)
    im = ax.imshow(np.where(inside, sig * 1e3, np.nan), extent=ext, cmap="viridis", vmin=0, vmax=vmax * 1e3,
                   interpolation="nearest")
    finite = np.isfinite(dist)
    if np.any(finite):
        # 50 mm apart (wider when many), only near the working volume: a plane seen edge-on spans metres
        lo = max(float(np.nanmin(dist[finite])), distance_mm[0] - 150.0)
        hi = min(float(np.nanmax(dist[finite])), distance_mm[1] + 150.0)
        step = 50.0 * max(1, math.ceil((hi - lo) / 50.0 / 12))
        levels = np.arange(np.ceil(lo / step) * step, hi, step)
        if len(levels):
            cs = ax.contour(U, V, np.where(finite, dist, np.nan), levels=levels, colors="white", linewidths=0.6)
            ax.clabel(cs, fmt="%d mm", fontsize=7)
    cb = fig.colorbar(im, ax=ax, shrink=0.8)
    with_camera = covariance is None and camera_share_status(camera, plane) is None
    cb.set_label("σ of a triangulated point, camera frame (µm): " +
                 ("plane calibration + camera intrinsics" if with_camera else
                  "plane calibration only (camera's share not included)"))
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")
    ax.set_title(title or f"Point uncertainty, working volume {distance_mm[0]:g}–{distance_mm[1]:g} mm from the camera")
    fig.tight_layout()

    return save_figure(fig, path, force=force)


# ----------------------------------------------------------------------------- calibrate-plane report
def _gray8(img: np.ndarray) -> np.ndarray:
    return to_gray8(img, percentiles=(0.5, 99.8), keep_8bit=False)


def _chord_px(cal, obs) -> np.ndarray | None:
    """(N, 2) distorted px of the chord where the plane cuts the observation's chosen pose."""
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
    return overlays(cal, images, columns=columns, max_images=max_images)[0]


def overlays(cal, images: Sequence | None = None, *, columns: int = 4, max_images: int = 24
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
    """PNG of :func:`point_sigma_map` (µm), None without a covariance."""

    if cal.covariance is None or cal.camera is None:
        return None
    if distance_mm is None:
        d = [float(np.linalg.norm(p.pose.center)) for p in cal.placements if p.used and p.pose is not None]
        # the used targets' range, rounded outwards to 10 mm
        distance_mm = ((math.floor(min(d) / 10) * 10.0, math.ceil(max(d) / 10) * 10.0)
                       if d and max(d) - min(d) > 1 else (380.0, 520.0))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "sigma.png"
        point_sigma_map(cal.camera, cal.plane, path, distance_mm=distance_mm, force=True)
        return path.read_bytes()


def figure_point_sigma(camera, plane, distance_mm: tuple[float, float]) -> bytes:
    """PNG of :func:`point_sigma_map` (µm) for ``camera`` and ``plane`` over ``distance_mm`` from the camera."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "sigma.png"
        point_sigma_map(camera, plane, path, distance_mm=distance_mm, force=True)
        return path.read_bytes()


def point_cloud(points: np.ndarray, path: str | os.PathLike, *, labels: np.ndarray | None = None,
                names: Sequence[str] | None = None, title: str = "", force: bool = True, max_points: int = 60000,
                frame: str = "object frame") -> Path:
    """A point cloud in three views (from above: x-y; from the side: x-z and y-z), mm,
    coloured by ``labels`` (e.g. the laser index, named by ``names``); at most
    ``max_points`` drawn (an even subsample)."""
    plt = _plt()
    p = np.asarray(points, dtype=np.float64)
    lab = np.zeros(len(p), int) if labels is None else np.asarray(labels).astype(int)
    if len(p) > max_points:
        keep = np.linspace(0, len(p) - 1, max_points).astype(int)
        p, lab = p[keep], lab[keep]
    fig, axes = plt.subplots(1, 3, figsize=(13.5, 4.6))
    colours = ["tab:red", "tab:blue", "tab:green", "tab:orange", "tab:purple"]
    for ax, (i, j), t in zip(axes, ((0, 1), (0, 2), (1, 2)), ("from above (x, y)", "side (x, z)", "side (y, z)")):
        for k in np.unique(lab):
            s = lab == k
            name = names[k] if names is not None and k < len(names) else (f"laser {k}" if labels is not None else None)
            ax.scatter(p[s, i], p[s, j], s=0.3, c=colours[k % len(colours)], label=name, alpha=0.5, linewidths=0)
        ax.set_aspect("equal")
        ax.set_xlabel(f"{'xyz'[i]} (mm)")
        ax.set_ylabel(f"{'xyz'[j]} (mm)")
        ax.set_title(t)
        ax.grid(alpha=0.3)
    if labels is not None:
        axes[0].legend(markerscale=20, loc="upper right")
    fig.suptitle(title or f"point cloud ({len(points)} points, {frame})")
    fig.tight_layout()
    return save_figure(fig, path, force=force, dpi=110)


# ----------------------------------------------------------------------------- calibration reports
def _image_axes(ax, width: int, height: int) -> None:
    ax.set_xlim(-0.5, width - 0.5)
    ax.set_ylim(height - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")


def figure_view_coverage(size: tuple[int, int], outlines: Sequence[np.ndarray], tilts_deg: np.ndarray, *,
                         points: Sequence[np.ndarray] = (), title: str = "") -> bytes:
    """PNG: where the board was in the image (one outline per view, px; ``points``: e.g. the stripe
    points, px) and the views' tilts (deg: about the camera's x and y axes, one dot per view)."""
    plt = _plt()
    w, h = int(size[0]), int(size[1])
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11.5, 4.6), gridspec_kw={"width_ratios": [1.5, 1]})
    cmap = plt.get_cmap("viridis")
    n = max(len(outlines), 1)
    for k, o in enumerate(outlines):
        o = np.asarray(o, float).reshape(-1, 2)
        if len(o):
            a1.fill(o[:, 0], o[:, 1], color=cmap(k / n), alpha=0.12)
            a1.plot(np.r_[o[:, 0], o[:1, 0]], np.r_[o[:, 1], o[:1, 1]], "-", color=cmap(k / n), lw=0.8)
    for p in points:
        p = np.asarray(p, float).reshape(-1, 2)
        if len(p):
            a1.plot(p[:, 0], p[:, 1], ".", color="#d02020", ms=1.0)
    _image_axes(a1, w, h)
    a1.set_title(f"Board in the image, {len(outlines)} views (colour: view order)", fontsize=9)
    t = np.asarray(tilts_deg, float).reshape(-1, 2)
    a2.scatter(t[:, 0], t[:, 1], c=np.arange(len(t)), cmap="viridis", s=18)
    lim = max(45.0, float(np.nanmax(np.abs(t))) * 1.1) if len(t) else 45.0
    a2.axhline(0, color="#999", lw=0.6)
    a2.axvline(0, color="#999", lw=0.6)
    for r in (20, 40):
        c = plt.Circle((0, 0), r, fill=False, ls="--", color="#bbb", lw=0.7)
        a2.add_patch(c)
    a2.set_xlim(-lim, lim)
    a2.set_ylim(-lim, lim)
    a2.set_aspect("equal")
    a2.set_xlabel("board tilt about the camera's x axis (deg)")
    a2.set_ylabel("board tilt about the camera's y axis (deg)")
    a2.set_title("Board tilts (dashed: 20 and 40 deg)", fontsize=9)
    a2.grid(alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _png(fig)


def figure_view_residuals(names: Sequence[str], rms: np.ndarray, *, unit: str, ylabel: str, flagged=None,
                          reference: float | None = None, reference_label: str = "") -> bytes:
    """PNG: one bar per view (its RMS residual in ``unit``); ``flagged`` views in red; ``reference``: a
    dashed line (e.g. the median)."""
    plt = _plt()
    x = np.arange(len(names))
    flag = np.zeros(len(names), bool) if flagged is None else np.asarray(flagged, bool)
    fig, ax = plt.subplots(figsize=(max(6.0, 0.18 * len(names) + 3), 3.8))
    ax.bar(x, np.asarray(rms, float), color=np.where(flag, "#d02020", "#1f5fbf"))
    if reference is not None and np.isfinite(reference):
        ax.axhline(reference, color="k", ls="--", lw=0.8, label=reference_label)
        ax.legend(fontsize=7)
    ax.set_xticks(x)
    ax.set_xticklabels([Path(n).name for n in names], rotation=70, ha="right", fontsize=6)
    ax.set_ylabel(f"{ylabel} ({unit})")
    ax.set_title(f"Per view: {ylabel} ({unit}); red: far above the others", fontsize=9)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    return _png(fig)


def figure_residual_field(size: tuple[int, int], uv: np.ndarray, residual: np.ndarray, *, unit: str,
                          cells: int = 16, scale: float = 1.0) -> bytes:
    """PNG: residuals over the image, binned in about ``cells`` x ``cells * h / w`` cells: each cell's
    RMS (colour, ``unit``) and, for 2D residuals (N, 2), the cell's mean residual as an arrow
    (magnified so that the largest spans a cell: a pattern here is what the model misses)."""
    plt = _plt()
    w, h = int(size[0]), int(size[1])
    uv = np.asarray(uv, float).reshape(-1, 2)
    r = np.asarray(residual, float)
    r2 = r.reshape(len(uv), -1)
    nx = max(2, int(cells))
    ny = max(2, int(round(cells * h / w)))
    ix = np.clip((uv[:, 0] / w * nx).astype(int), 0, nx - 1)
    iy = np.clip((uv[:, 1] / h * ny).astype(int), 0, ny - 1)
    cell = iy * nx + ix
    cnt = np.bincount(cell, minlength=nx * ny)
    ss = np.bincount(cell, weights=np.sum(r2 ** 2, axis=1), minlength=nx * ny)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(ss / cnt) * scale
    rms[cnt == 0] = np.nan
    fig, ax = plt.subplots(figsize=(7.5, 5.6))
    im = ax.imshow(rms.reshape(ny, nx), extent=(-0.5, w - 0.5, h - 0.5, -0.5), cmap="magma", interpolation="nearest")
    cb = fig.colorbar(im, ax=ax, shrink=0.8)
    cb.set_label(f"RMS residual per cell ({unit})")
    if r2.shape[1] == 2 and len(uv):
        sums = np.column_stack([np.bincount(cell, weights=r2[:, j], minlength=nx * ny) for j in (0, 1)])
        with np.errstate(invalid="ignore", divide="ignore"):
            mu = sums / cnt[:, None]
        gx, gy = np.meshgrid((np.arange(nx) + 0.5) * w / nx, (np.arange(ny) + 0.5) * h / ny)
        ok = cnt > 0
        big = float(np.nanmax(np.linalg.norm(mu[ok], axis=1))) if ok.any() else 0.0
        if big > 0:
            k = (w / nx) / big
            ax.quiver(gx.ravel()[ok], gy.ravel()[ok], mu[ok, 0] * k, mu[ok, 1] * k, angles="xy", scale_units="xy",
                      scale=1, color="#30d0ff", width=0.003)
            ax.set_title(f"Residuals over the image: cell RMS (colour) and mean (arrows; the longest is "
                         f"{big * scale:.3g} {unit})", fontsize=9)
    else:
        ax.set_title("Residuals over the image: cell RMS", fontsize=9)
    _image_axes(ax, w, h)
    fig.tight_layout()
    return _png(fig)


def figure_image_map(size: tuple[int, int], uv: np.ndarray, values: np.ndarray, *, label: str,
                     title: str, step_px: float, vmax: float | None = None) -> bytes:
    """PNG: ``values`` at the pixel centres ``uv`` of a regular grid of ``step_px`` (e.g. a σ over the
    image), colour bar labelled ``label`` (with its unit); colours end at ``vmax`` when given."""
    plt = _plt()
    w, h = int(size[0]), int(size[1])
    uv = np.asarray(uv, float).reshape(-1, 2)
    nx = int(np.ceil(w / step_px))
    ny = int(np.ceil(h / step_px))
    grid = np.full((ny, nx), np.nan)
    grid[np.clip((uv[:, 1] // step_px).astype(int), 0, ny - 1),
         np.clip((uv[:, 0] // step_px).astype(int), 0, nx - 1)] = values
    fig, ax = plt.subplots(figsize=(7.5, 5.6))
    im = ax.imshow(grid, extent=(-0.5, nx * step_px - 0.5, ny * step_px - 0.5, -0.5), cmap="viridis",
                   interpolation="nearest", vmax=vmax)
    cb = fig.colorbar(im, ax=ax, shrink=0.8)
    cb.set_label(label)
    _image_axes(ax, w, h)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return _png(fig)


def figure_turntable(origins_tt: np.ndarray, used_names: Sequence[str], radius_height_sigma: tuple, *,
                     circle_rms_mm: np.ndarray, pnp_rms_px: np.ndarray) -> bytes:
    """PNG, three panels: the board origins seen from above in the turntable frame (mm, the axis at 0);
    per image the board points' RMS distance from their circles (mm) and the pose's reprojection RMS
    (px); and ``radius_height_sigma`` = ``(radii mm, heights mm, σ (len(heights), len(radii)) mm)``: the
    σ of a point turned half a turn about the calibrated axis."""
    plt = _plt()
    fig, (a1, a2, a3) = plt.subplots(1, 3, figsize=(14, 4.4))
    o = np.asarray(origins_tt, float).reshape(-1, 3)
    a1.scatter(o[:, 0], o[:, 1], c=np.arange(len(o)), cmap="viridis", s=20)
    a1.plot([0], [0], "k+", ms=12)
    a1.set_aspect("equal")
    a1.set_xlabel("x (mm, turntable frame)")
    a1.set_ylabel("y (mm, turntable frame)")
    a1.set_title("Board origins seen from above (+: the axis)", fontsize=9)
    a1.grid(alpha=0.3)
    x = np.arange(len(used_names))
    a2.bar(x - 0.2, np.asarray(circle_rms_mm, float) * 1e3, 0.4, label="board points to their circles (µm)",
           color="#1f5fbf")
    a2b = a2.twinx()
    a2b.bar(x + 0.2, np.asarray(pnp_rms_px, float), 0.4, label="pose reprojection (px)", color="#d08020")
    a2.set_ylabel("circle RMS (µm)")
    a2b.set_ylabel("PnP RMS (px)")
    a2.set_xticks(x)
    a2.set_xticklabels([Path(n).name for n in used_names], rotation=70, ha="right", fontsize=6)
    a2.set_title("Per image: circle RMS (µm, blue), pose RMS (px, orange)", fontsize=9)
    radii, heights, sig = radius_height_sigma
    im = a3.imshow(np.asarray(sig, float) * 1e3, origin="lower", aspect="auto", cmap="viridis",
                   extent=(radii[0], radii[-1], heights[0], heights[-1]))
    cb = fig.colorbar(im, ax=a3)
    cb.set_label("σ of a point turned 180 deg (µm)")
    a3.set_xlabel("distance from the axis (mm)")
    a3.set_ylabel("height above the turntable frame's origin (mm)")
    a3.set_title("Axis uncertainty as a point error", fontsize=9)
    fig.tight_layout()
    return _png(fig)


def figure_scans_overlay(before: Sequence[np.ndarray], after: Sequence[np.ndarray], names: Sequence[str]) -> bytes:
    """PNG: the scans' clouds (turntable frame, mm) from above and from the side, before (given axis,
    start angles 0) and after the refinement, one colour per scan."""
    plt = _plt()
    fig, axes = plt.subplots(2, 2, figsize=(11, 9))
    colours = ["tab:red", "tab:blue", "tab:green", "tab:orange", "tab:purple"]
    for row, clouds, label in ((0, before, "given axis, start angles 0"), (1, after, "refined")):
        for col, (i, j), view in ((0, (0, 1), "from above (x, y)"), (1, (0, 2), "side (x, z)")):
            ax = axes[row, col]
            for k, (p, n) in enumerate(zip(clouds, names)):
                p = np.asarray(p, float).reshape(-1, 3)
                ax.scatter(p[:, i], p[:, j], s=0.4, c=colours[k % len(colours)], label=n, alpha=0.5, linewidths=0)
            ax.set_aspect("equal")
            ax.set_xlabel(f"{'xyz'[i]} (mm)")
            ax.set_ylabel(f"{'xyz'[j]} (mm)")
            ax.set_title(f"{label}: {view}", fontsize=9)
            ax.grid(alpha=0.3)
    axes[0, 0].legend(markerscale=15, fontsize=7)
    fig.tight_layout()
    return _png(fig)
