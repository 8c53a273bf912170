"""Choosing the circular target in a calibration image: the ellipse the stripe crosses.

A calibration image (paper §2.2, docs/conventions.md §Default sensor) shows the target disc with the laser
stripe crossing it along a chord, and possibly clutter: other circles and holes,
rectangles, a saturated stripe.  The target is

- well supported (complete ellipse edge: detection score),
- salient: among the largest well-supported ellipses (a target is held close to the
  camera; clutter much smaller than the largest candidate is ignored),
- of plausible size (optional ``axis_range_px``),
- crossed by the stripe: inside the (shrunk) ellipse, a narrow bright line (white
  top-hat, robust line fit) covers a chord of at least ``min_chord_fraction`` of
  the ellipse's minor diameter.  With ``stripe_hint`` (stripe centre points, px) the
  hint's points are used instead of the image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lightplane.core.errors import LightplaneError
from lightplane.core.geometry import robust_sigma, tls_line
from lightplane.ellipse.edges import prepare_gray
from lightplane.ellipse.model import Ellipse

__all__ = ["TargetSelection", "StripeCrossing", "select_target", "stripe_crossing", "expected_axis_range_px"]


@dataclass(frozen=True)
class StripeCrossing:
    """Evidence of a bright line crossing an ellipse.

    chord_px : (2, 2) end points (px) of the stripe's chord through the shrunk ellipse, or None.
    coverage : fraction of that chord covered by stripe pixels, in [0, 1].
    chord_fraction : chord length / minor diameter (2 b) of the ellipse.
    n_points : stripe pixels on the fitted line inside the ellipse.
    """

    chord_px: np.ndarray | None
    coverage: float
    chord_fraction: float
    n_points: int

    def crosses(self, min_coverage: float = 0.5, min_chord_fraction: float = 0.3) -> bool:
        return self.chord_px is not None and self.coverage >= min_coverage and self.chord_fraction >= min_chord_fraction


@dataclass(frozen=True)
class TargetSelection:
    """Result of :func:`select_target`.

    ellipse : the chosen :class:`Ellipse`, or None; index : its index in the input list (-1).
    reason : why nothing was chosen ("" when chosen).
    crossing : the stripe evidence of the chosen ellipse (None if nothing was chosen).
    candidates : per input ellipse ``(index, status)``, status one of "chosen", "too small",
        "implausible size", "weak edge", "no stripe", "lower rank".
    """

    ellipse: Ellipse | None
    index: int
    reason: str
    crossing: StripeCrossing | None
    candidates: list = field(default_factory=list)


def _line_ransac(pts: np.ndarray, rng: np.random.Generator, tol_px: float, iters: int = 64):
    """Best line through ``pts`` (N, 2) by RANSAC: ``(point, unit direction, inlier mask)``."""
    n = len(pts)
    best = None
    best_cnt = -1
    for _ in range(iters):
        i, j = rng.integers(0, n, 2)
        d = pts[j] - pts[i]
        ln = math.hypot(d[0], d[1])
        if ln < 3 * tol_px:
            continue
        d = d / ln
        dist = np.abs((pts[:, 0] - pts[i, 0]) * d[1] - (pts[:, 1] - pts[i, 1]) * d[0])
        cnt = int(np.count_nonzero(dist <= tol_px))
        if cnt > best_cnt:
            best_cnt, best = cnt, (pts[i], d)
    if best is None:
        return None
    p0, d = best
    dist = np.abs((pts[:, 0] - p0[0]) * d[1] - (pts[:, 1] - p0[1]) * d[0])
    inl = dist <= tol_px
    # total least squares refit on the inliers
    m, d, _ = tls_line(pts[inl])
    dist = np.abs((pts[:, 0] - m[0]) * d[1] - (pts[:, 1] - m[1]) * d[0])
    return m, d, dist <= tol_px


def _chord(e: Ellipse, p0: np.ndarray, d: np.ndarray) -> tuple[float, float] | None:
    """Intersections (s0 < s1) of the line p0 + s d with the ellipse, as parameters s."""
    c, s = math.cos(e.angle), math.sin(e.angle)
    q = p0 - e.centre
    x0, y0 = c * q[0] + s * q[1], -s * q[0] + c * q[1]
    dx, dy = c * d[0] + s * d[1], -s * d[0] + c * d[1]
    A = dx * dx / e.a ** 2 + dy * dy / e.b ** 2
    B = 2 * (x0 * dx / e.a ** 2 + y0 * dy / e.b ** 2)
    C = x0 * x0 / e.a ** 2 + y0 * y0 / e.b ** 2 - 1
    disc = B * B - 4 * A * C
    if disc <= 0:
        return None
    r = math.sqrt(disc)
    return (-B - r) / (2 * A), (-B + r) / (2 * A)


def _stripe_pixels(gray: np.ndarray, e: Ellipse, shrink: float, outer: float,
                   width_px: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Pixels of a narrow bright line (white top-hat) inside ``e`` scaled by ``shrink`` and in
    the ring between ``e`` scaled by 1.1 and by ``outer``: ``(inside (N, 2), ring (M, 2),
    sampling step px)``.  Large ellipses are searched at half resolution (step 2).
    Each region gets its own robust threshold (a stripe on a dark disc is faint)."""
    import cv2

    h, w = gray.shape
    u0, v0, u1, v1 = e.scaled(outer).bbox()
    cu0, cv0 = max(int(u0) - 1, 0), max(int(v0) - 1, 0)
    cu1, cv1 = min(int(u1) + 2, w), min(int(v1) + 2, h)
    empty = np.zeros((0, 2))
    if cu1 - cu0 < 8 or cv1 - cv0 < 8:
        return empty, empty, 1
    f = 2 if e.b >= 80 and cu1 - cu0 >= 32 and cv1 - cv0 >= 32 else 1
    crop = np.ascontiguousarray(gray[cv0:cv1, cu0:cu1])
    if f > 1:
        crop = cv2.resize(crop, ((cu1 - cu0) // f, (cv1 - cv0) // f), interpolation=cv2.INTER_AREA)
    # smoothing first: a faint stripe (on a dark disc) must stand out of the noise
    crop = cv2.GaussianBlur(crop, (0, 0), 1.5 / f)
    k = int(2 * round(width_px / f) + 1)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    th = cv2.morphologyEx(crop, cv2.MORPH_TOPHAT, kernel)
    vv, uu = np.mgrid[0:crop.shape[0], 0:crop.shape[1]].astype(np.float64)
    uu = cu0 + f * (uu + 0.5) - 0.5  # full-resolution pixel coordinates of the samples
    vv = cv0 + f * (vv + 0.5) - 0.5
    q = np.column_stack([uu.ravel(), vv.ravel()])
    rho = e.algebraic(q).reshape(uu.shape) + 1.0  # normalised radius: 1 on the ellipse
    span = float(np.percentile(crop, 99.5) - np.percentile(crop, 0.5))
    out = []
    for region in (rho <= shrink, (rho >= 1.1) & (rho <= outer)):
        vals = th[region]
        if vals.size < 16:
            out.append(empty)
            continue
        med = float(np.median(vals))
        mad = robust_sigma(vals)
        thr = med + max(5.0 * mad, 0.01 * span, 1.0)
        sel = region & (th > thr)
        out.append(np.column_stack([uu[sel], vv[sel]]))
    return out[0], out[1], f


def _coverage(pts: np.ndarray, m: np.ndarray, d: np.ndarray, s0: float, s1: float, tol: float,
              bin_px: float = 1.0) -> float:
    """Fraction of ``bin_px`` bins of the segment m + s d, s in [s0, s1], holding a point within tol."""
    if len(pts) == 0 or s1 <= s0:
        return 0.0
    dist = np.abs((pts[:, 0] - m[0]) * d[1] - (pts[:, 1] - m[1]) * d[0])
    proj = (pts - m) @ d
    sel = (dist <= tol) & (proj >= s0) & (proj <= s1)
    nb = max(int((s1 - s0) / bin_px), 1)
    bins = np.clip(((proj[sel] - s0) / (s1 - s0) * nb).astype(int), 0, nb - 1)
    return np.unique(bins).size / nb


def stripe_crossing(image: np.ndarray | None, ellipse: Ellipse, *, stripe_hint: np.ndarray | None = None,
                    shrink: float = 0.9, outer: float = 1.4, stripe_width_px: float = 10.0,
                    seed: int = 0) -> StripeCrossing:
    """Measure how a bright line (the laser stripe) crosses ``ellipse``.

    Stripe pixels (white top-hat, kernel about twice ``stripe_width_px``, the widest
    stripe expected) inside the ellipse shrunk by ``shrink`` give a robust line (RANSAC +
    total least squares); the coverage is the fraction of its chord through the shrunk
    ellipse that holds stripe pixels.  When the inside is faint (a stripe on a dark
    disc) the line is fitted to the inside and the surrounding ring (up to ``outer``)
    together, and a stripe seen on both sides of the ellipse along that line counts as
    full coverage of a chord that is at least partly (>= 20 %) seen inside.
    ``stripe_hint``: optional (N, 2) stripe centre points (px) used instead of the image
    (``image`` may then be None).
    """
    rng = np.random.default_rng(seed)
    inner = ellipse.scaled(shrink)
    if stripe_hint is not None:
        pts = np.asarray(stripe_hint, dtype=np.float64).reshape(-1, 2)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        rho = ellipse.algebraic(pts) + 1.0 if len(pts) else np.zeros(0)
        p_in, p_ring = pts[rho <= shrink], pts[(rho >= 1.1) & (rho <= outer)]
        tol, step = 2.0, 1.0
    else:
        if image is None:
            raise LightplaneError("stripe_crossing: give the image or a stripe_hint")
        gray = prepare_gray(image)
        p_in, p_ring, step = _stripe_pixels(gray, ellipse, shrink, outer, stripe_width_px)
        tol = max(2.0, 0.6 * stripe_width_px)
    best = StripeCrossing(None, 0.0, 0.0, int(len(p_in)))
    for pts, use_ring in ((p_in, False), (np.concatenate([p_in, p_ring]), True)):
        if len(pts) < 10:
            continue
        if len(pts) > 4000:
            pts = pts[rng.choice(len(pts), 4000, replace=False)]
        fit = _line_ransac(pts, rng, tol)
        if fit is None:
            continue
        m, d, inl = fit
        ch = _chord(inner, m, d)
        if ch is None:
            continue
        s0, s1 = ch
        cov = _coverage(p_in, m, d, s0, s1, tol, step)
        if use_ring and cov >= 0.2:
            full = _chord(ellipse, m, d)
            far = _chord(ellipse.scaled(outer), m, d)
            if full is not None and far is not None:
                before = _coverage(p_ring, m, d, far[0], full[0], tol, step)
                after = _coverage(p_ring, m, d, full[1], far[1], tol, step)
                if before >= 0.3 and after >= 0.3:
                    cov = 1.0
        if cov > best.coverage:
            chord = np.array([m + s0 * d, m + s1 * d])
            best = StripeCrossing(chord, float(cov), float((s1 - s0) / shrink / (2 * ellipse.b)), int(inl.sum()))
        if best.coverage >= 0.5:
            break
    return best


def expected_axis_range_px(camera, diameter_mm: float, distance_range_mm: tuple[float, float],
                           margin: float = 0.15) -> tuple[float, float]:
    """Range of the image major semi-axis (px) of a disc of ``diameter_mm`` seen at a
    distance in ``distance_range_mm`` (mm) by ``camera`` (``a ~ f r / Z``), widened by
    ``margin`` (relative) for off-axis viewing and lens distortion."""
    if not (diameter_mm > 0 and 0 < distance_range_mm[0] <= distance_range_mm[1]):
        raise LightplaneError(f"diameter_mm and distance_range_mm must be positive, got {diameter_mm}, "
                              f"{distance_range_mm}")
    f = 0.5 * (camera.fx + camera.fy)
    r = 0.5 * diameter_mm
    return (f * r / distance_range_mm[1] * (1 - margin), f * r / distance_range_mm[0] * (1 + margin))


def select_target(image: np.ndarray, ellipses: list[Ellipse], stripe_hint: np.ndarray | None = None, *,
                  axis_range_px: tuple[float, float] | None = None, min_score: float = 0.5,
                  relative_area: float = 0.5, min_chord_fraction: float = 0.3, min_stripe_coverage: float = 0.5,
                  stripe_width_px: float = 10.0) -> TargetSelection:
    """Choose the target ellipse: salient, plausible size, crossed by the stripe.

    Parameters
    ----------
    image : the calibration image (gray or colour, any depth).
    ellipses : candidates, e.g. ``detect_ellipses(image, EllipseDetectionOptions(min_axis_px=...))``.
    stripe_hint : optional (N, 2) stripe centre points (px), e.g. from ``extract_stripe``.
    axis_range_px : optional ``(min, max)`` for the major semi-axis ``a`` (px); for a disc
        of radius r at distance Z, ``a ~ f r / Z`` whatever its tilt: see
        :func:`expected_axis_range_px`.
    min_score : detection score below which a candidate is ignored ("weak edge").
    relative_area : candidates smaller than this fraction of the largest well-supported
        candidate are ignored ("too small": the target is the salient disc).
    min_chord_fraction, min_stripe_coverage : stripe evidence required (chord length
        over minor diameter; covered fraction of the chord).

    Among the candidates left, the one with the largest ``area x score x coverage of
    its stripe chord`` is chosen.  When none is crossed the result has ``ellipse=None``
    and a reason (e.g. "stripe misses the target").
    """
    ellipses = list(ellipses)
    for i, e in enumerate(ellipses):
        if not isinstance(e, Ellipse):
            raise LightplaneError(f"ellipses[{i}] must be an Ellipse, got {type(e).__name__}")
    gray = prepare_gray(image) if stripe_hint is None else None
    status = ["" for _ in ellipses]
    pool = []
    for i, e in enumerate(ellipses):
        if e.score < min_score:
            status[i] = "weak edge"
        elif axis_range_px is not None and not (axis_range_px[0] <= e.a <= axis_range_px[1]):
            status[i] = "implausible size"
        else:
            pool.append(i)
    if not pool:
        return TargetSelection(None, -1, "no plausible ellipse", None, list(enumerate(status)))
    amax = max(ellipses[i].area for i in pool)
    crossed = []
    for i in pool:
        e = ellipses[i]
        if e.area < relative_area * amax:
            status[i] = "too small"
            continue
        cr = stripe_crossing(gray, e, stripe_hint=stripe_hint, stripe_width_px=stripe_width_px)
        if cr.crosses(min_stripe_coverage, min_chord_fraction):
            crossed.append((e.area * e.score * cr.coverage, i, cr))
        else:
            status[i] = "no stripe"
    if not crossed:
        reason = "stripe misses the target" if any(s == "no stripe" for s in status) else "no plausible ellipse"
        return TargetSelection(None, -1, reason, None, list(enumerate(status)))
    crossed.sort(key=lambda x: -x[0])
    _, best, cr = crossed[0]
    for _, i, _ in crossed[1:]:
        status[i] = "lower rank"
    status[best] = "chosen"
    return TargetSelection(ellipses[best], best, "", cr, list(enumerate(status)))
