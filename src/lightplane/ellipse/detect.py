"""Ellipse detection with arc-support line segments (docs/method.md §Ellipse; Lu, Xia, Shao, Fu,
"Arc-support line segments revisited: an efficient high-quality ellipse detection",
IEEE TIP 29, 2020 — the paper's RALS detector).

Pipeline (one function per stage, all on arrays):

1. **Arc-support segments** (Lu §III-A): OpenCV's LSD segments, each oriented by its
   gradient polarity so that the brighter side is on its left-hand normal
   ``n = (-d_y, d_x)``.  On a convex edge every segment then turns the same way as
   the next, and the sign of the turn says whether the interior is darker (-1) or
   brighter (+1) than the outside.
2. **Arc-support groups** (Lu §III-B): a segment is linked to the segment whose head is
   nearest its tail (continuity) if the direction turns by a small angle with the
   group's sign (convexity); chains of >= 2 segments are groups.
3. **Initial candidates** (Lu §III-C): *local* — a direct ellipse fit (Halir–Flusser) on
   each salient group (angular span large enough); *global* — pairs of groups of the
   same polarity that satisfy the region condition (each group lies on the interior
   side of the other's chord, and on the side its normal says the interior is), fitted
   together and kept when both groups support the fit (adaptive inlier criterion).
4. **Clustering** (Lu §III-D): duplicates merged hierarchically — centres first, then
   orientations within a centre cluster, then semi-axes.
5. **Verification** (Lu §III-E): each cluster's ellipse is refitted on sub-pixel edge
   points along its normals and kept when the edge support (inlier ratio: samples
   with an edge of the right polarity and direction within 1 px) and the angular
   coverage are high enough; score = inlier ratio x coverage.  Samples outside the
   image are left out of both (an ellipse cut by the border is judged on its visible
   part, at least half of it); a final non-maximum suppression removes duplicates.

Large ellipses and large images are searched on a reduced image (``downscale``, from
``min_axis_px`` and the image size, :func:`auto_downscale`):
detection only needs to be close enough for :func:`refine_ellipse`.

Supplementary candidates (documented deviation): ellipses of contours of a locally
adaptive threshold, both polarities.  LSD finds no segments on ellipses only a few
pixels across (the real calibration photographs hold hundreds); these candidates
go through the same clustering and verification, so they add recall without
bypassing the arc-support evidence test.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lightplane.core.errors import LightplaneError
from lightplane.ellipse.edges import Gradients, edge_peaks_along_normals, gradients, prepare_gray, to_uint8
from lightplane.ellipse.model import Ellipse

__all__ = ["EllipseDetectionOptions", "detect_ellipses", "auto_downscale", "arc_support_segments", "arc_groups"]

_POLARITY = {None: 0, 0: 0, "any": 0, "dark": -1, "light": 1, -1: -1, 1: 1}


# --------------------------------------------------------------------------
# 1. arc-support segments
# --------------------------------------------------------------------------

def arc_support_segments(gray8: np.ndarray, grad: Gradients, *, lsd_scale: float = 0.8,
                         min_length_px: float = 3.0, min_grad: float = 4.0) -> np.ndarray:
    """LSD segments oriented by gradient polarity.

    Returns ``(N, 4)`` float64 ``x1, y1, x2, y2`` px, oriented so that the image gradient
    points along the left-hand normal ``(-d_y, d_x)`` of the direction ``d`` (from point 1
    to point 2).  Segments shorter than ``min_length_px`` or on weak/ambiguous gradients
    (mean gradient along the normal < ``min_grad`` grey levels per px) are dropped.
    """
    import cv2

    if min(gray8.shape) < 8:
        return np.zeros((0, 4))
    lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD, lsd_scale)
    lines = lsd.detect(gray8)[0]
    if lines is None:
        return np.zeros((0, 4))
    L = lines.reshape(-1, 4).astype(np.float64)
    d = L[:, 2:] - L[:, :2]
    ln = np.hypot(d[:, 0], d[:, 1])
    keep = ln >= min_length_px
    L, d, ln = L[keep], d[keep], ln[keep]
    if len(L) == 0:
        return np.zeros((0, 4))
    d /= ln[:, None]
    nrm = np.column_stack([-d[:, 1], d[:, 0]])
    h, w = grad.gx.shape
    proj = np.zeros(len(L))
    tot = np.zeros(len(L))
    for f in (0.2, 0.4, 0.6, 0.8):
        p = L[:, :2] + f * (L[:, 2:] - L[:, :2])
        iu = np.clip(np.rint(p[:, 0]).astype(int), 0, w - 1)
        iv = np.clip(np.rint(p[:, 1]).astype(int), 0, h - 1)
        gx, gy = grad.gx[iv, iu], grad.gy[iv, iu]
        proj += gx * nrm[:, 0] + gy * nrm[:, 1]
        tot += np.hypot(gx, gy)
    flip = proj < 0
    L[flip] = L[flip][:, [2, 3, 0, 1]]
    strong = (np.abs(proj) >= 0.8 * tot) & (np.abs(proj) / 4 >= min_grad)
    return L[strong]


# --------------------------------------------------------------------------
# 2. arc-support groups
# --------------------------------------------------------------------------

def arc_groups(segs: np.ndarray, *, max_turn_rad: float = math.radians(60),
               min_turn_rad: float = math.radians(1.0)) -> list[tuple[np.ndarray, int]]:
    """Link oriented segments into arc-support groups.

    Segment j follows segment i when j's head is within ``gap`` of i's tail (continuity,
    ``gap = clip(0.5 min(len_i, len_j), 2, 8)`` px) and the direction turns by an angle in
    ``[min_turn_rad, max_turn_rad]`` with the sign of the group (convexity).  Each
    segment has at most one successor and one predecessor (the nearest link wins).
    Returns a list of ``(segment indices in order, sign)``; sign +1: interior brighter.
    """
    from scipy.spatial import cKDTree

    n = len(segs)
    if n < 2:
        return []
    head, tail = segs[:, :2], segs[:, 2:]
    d = tail - head
    ln = np.hypot(d[:, 0], d[:, 1])
    d = d / ln[:, None]
    pairs = cKDTree(tail).query_ball_tree(cKDTree(head), 8.0)
    ii = np.repeat(np.arange(n), [len(p) for p in pairs])
    jj = np.fromiter((j for p in pairs for j in p), dtype=int, count=len(ii))
    keep = ii != jj
    ii, jj = ii[keep], jj[keep]
    gap = np.hypot(*(tail[ii] - head[jj]).T)
    tol = np.clip(0.5 * np.minimum(ln[ii], ln[jj]), 2.0, 8.0)
    cross = d[ii, 0] * d[jj, 1] - d[ii, 1] * d[jj, 0]
    dot = np.sum(d[ii] * d[jj], axis=1)
    turn = np.arctan2(cross, dot)
    near = gap <= tol
    groups: list[tuple[np.ndarray, int]] = []
    for sign in (1, -1):
        ok = near & (sign * turn >= min_turn_rad) & (sign * turn <= max_turn_rad)
        oi, oj, og = ii[ok], jj[ok], gap[ok]
        succ = np.full(n, -1)
        pred = np.full(n, -1)
        for k in np.argsort(og, kind="stable"):  # nearest links first
            i, j = oi[k], oj[k]
            if succ[i] < 0 and pred[j] < 0:
                succ[i] = j
                pred[j] = i
        seen = np.zeros(n, bool)
        starts = [i for i in np.nonzero((pred < 0) & (succ >= 0))[0]]
        loops = [i for i in np.nonzero((pred >= 0) & (succ >= 0))[0]]
        for s0 in starts + loops:  # closed loops (every member has a predecessor): cut anywhere
            if seen[s0]:
                continue
            chain = [s0]
            seen[s0] = True
            j = succ[s0]
            total = 0.0
            while j >= 0 and not seen[j]:
                # a convex closed curve turns by 2 pi: a chain that turns further has left it
                total += abs(math.atan2(d[chain[-1], 0] * d[j, 1] - d[chain[-1], 1] * d[j, 0], d[chain[-1]] @ d[j]))
                if total > 2 * math.pi:
                    break
                chain.append(j)
                seen[j] = True
                j = succ[j]
            if len(chain) >= 2:
                groups.append((np.array(chain), sign))
    return groups


def _group_points(segs: np.ndarray, idx: np.ndarray, step_px: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """Points every ~``step_px`` along the group's segments, and each point's position in the chain."""
    pts, owner = [], []
    for k, i in enumerate(idx):
        x1, y1, x2, y2 = segs[i]
        m = max(2, int(math.hypot(x2 - x1, y2 - y1) / step_px) + 1)
        f = np.linspace(0, 1, m)
        pts.append(np.column_stack([x1 + f * (x2 - x1), y1 + f * (y2 - y1)]))
        owner.append(np.full(m, k))
    return np.concatenate(pts), np.concatenate(owner)


# --------------------------------------------------------------------------
# 3. initial candidates
# --------------------------------------------------------------------------

class _Group:
    """An arc-support group: its points (sampled along its segments), polarity sign,
    total turn ``span`` (rad), end points, middle point and normal (towards the brighter side)."""

    __slots__ = ("pts", "seg_of_pt", "turns", "sign", "span", "head", "tail", "mid", "normal", "length")

    def __init__(self, segs: np.ndarray, idx: np.ndarray, sign: int):
        self.pts, self.seg_of_pt = _group_points(segs, idx)
        self.sign = sign
        d = segs[idx, 2:] - segs[idx, :2]
        self.turns = np.abs(np.arctan2(d[:-1, 0] * d[1:, 1] - d[:-1, 1] * d[1:, 0], np.sum(d[:-1] * d[1:], axis=1)))
        self.span = float(self.turns.sum())
        self.head = segs[idx[0], :2]
        self.tail = segs[idx[-1], 2:]
        k = idx[len(idx) // 2]
        self.mid = 0.5 * (segs[k, :2] + segs[k, 2:])
        dm = segs[k, 2:] - segs[k, :2]
        dm = dm / np.linalg.norm(dm)
        self.normal = np.array([-dm[1], dm[0]])
        self.length = float(np.sum(np.hypot(d[:, 0], d[:, 1])))


def _params_from_rect(rect) -> tuple[float, float, float, float, float] | None:
    """(cx, cy, a, b, angle) with a >= b from OpenCV's RotatedRect, None if degenerate."""
    (cx, cy), (w, h), ang = rect
    a, b, th = 0.5 * w, 0.5 * h, math.radians(ang)
    if b > a:
        a, b, th = b, a, th + math.pi / 2
    if not (b > 0 and math.isfinite(a) and math.isfinite(cx) and math.isfinite(cy)):
        return None
    return (cx, cy, a, b, th % math.pi)


def _param_distance(p, uv: np.ndarray) -> np.ndarray:
    """Sampson distance (px) of points ``uv`` (N, 2) to the ellipse ``p = (cx, cy, a, b, angle)``."""
    cx, cy, a, b, th = p[:5]
    c, s = math.cos(th), math.sin(th)
    d0, d1 = uv[:, 0] - cx, uv[:, 1] - cy
    x, y = c * d0 + s * d1, -s * d0 + c * d1
    f = x * x / (a * a) + y * y / (b * b) - 1.0
    g = 2.0 * np.sqrt(x * x / a ** 4 + y * y / b ** 4)
    return f / np.maximum(g, 1e-12)


def _fit_candidate(pts: np.ndarray, min_axis_px: float, max_axis_px: float):
    """Direct least-squares ellipse (cv2.fitEllipseDirect, Fitzgibbon's constraint) on
    candidate points, as ``(cx, cy, a, b, angle)``, or None outside the size limits."""
    import cv2

    try:
        p = _params_from_rect(cv2.fitEllipseDirect(pts.astype(np.float32)))
    except cv2.error:
        return None
    if p is None:
        return None
    a, b = p[2], p[3]
    if not (min_axis_px <= b and a <= max_axis_px and b >= 0.08 * a):
        return None
    return p


def _initial_candidates(segs: np.ndarray, groups: list[tuple[np.ndarray, int]], *, min_axis_px: float,
                        max_axis_px: float, polarity: int) -> list[tuple]:
    """Lu §III-C: the candidates ``(cx, cy, a, b, angle, sign)`` of the groups of ``polarity``
    (0: both): local fits of salient groups, then fits of admissible pairs of groups."""
    G = [_Group(segs, idx, s) for idx, s in groups if polarity == 0 or s == polarity]
    cands = _local_candidates(G, min_axis_px, max_axis_px)
    if len(G) >= 2:
        cands += _pair_candidates(G, min_axis_px, max_axis_px)
    return cands


def _local_candidates(G: list[_Group], min_axis_px: float, max_axis_px: float) -> list[tuple]:
    """Fits of the salient groups (angular span large enough) on their own."""
    cands: list[tuple] = []  # (cx, cy, a, b, angle, sign)
    # local: salient groups.  A chain may have picked up a stray segment at an end (a
    # stripe's straight edge meeting the rim): fits without one or two end segments are
    # tried when the whole chain does not fit.
    min_span = math.radians(70)
    for g in G:
        if g.span < min_span or len(g.pts) < 6:
            continue
        L = len(g.turns) + 1
        for i0, i1 in ((0, L), (1, L), (0, L - 1), (1, L - 1), (2, L), (0, L - 2)):
            if i1 - i0 < 2 or g.turns[i0:i1 - 1].sum() < min_span:
                continue
            sel = (g.seg_of_pt >= i0) & (g.seg_of_pt < i1)
            e = _fit_candidate(g.pts[sel], min_axis_px, max_axis_px)
            if e is not None and np.mean(np.abs(_param_distance(e, g.pts[sel]))) < 1.0:
                cands.append((*e, g.sign))
                break
    return cands


def _pair_candidates(G: list[_Group], min_axis_px: float, max_axis_px: float) -> list[tuple]:
    """Fits of the admissible pairs of groups (:func:`_admissible_pairs`), kept when both groups
    support the fit (adaptive inlier criterion)."""
    cands: list[tuple] = []
    ii, jj = _admissible_pairs(G, min_axis_px, max_axis_px)
    for i, j in zip(ii, jj):
        pts = np.concatenate([G[i].pts, G[j].pts])
        e = _fit_candidate(pts, min_axis_px, max_axis_px)
        if e is None:
            continue
        # adaptive inlier criterion: both groups must lie on the fitted ellipse
        di = np.abs(_param_distance(e, G[i].pts))
        dj = np.abs(_param_distance(e, G[j].pts))
        thr = max(1.0, 0.03 * e[3])
        if np.mean(di < thr) >= 0.8 and np.mean(dj < thr) >= 0.8:
            cands.append((*e, G[i].sign))
    return cands


def _admissible_pairs(G: list[_Group], min_axis_px: float, max_axis_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Pairs ``(i, j)``, i < j, of groups (at least 2) under the polarity and region conditions: the
    same polarity, each group on the interior side of the other's chord and facing it, at a
    distance that two arcs of one ellipse can have, not both complete, each among the other's
    nearest admissible partners."""
    m = len(G)
    sign = np.array([g.sign for g in G])
    head = np.array([g.head for g in G])
    tail = np.array([g.tail for g in G])
    mid = np.array([g.mid for g in G])
    nrm = np.array([g.normal for g in G])
    # interior direction of each group = sign * normal (normal points to the brighter side)
    inward = nrm * sign[:, None]
    # chord line of group i: points x with (x - head_i) . cn_i, cn_i the chord normal pointing inward
    ch = tail - head
    cn = np.column_stack([-ch[:, 1], ch[:, 0]])
    cn_len = np.maximum(np.hypot(cn[:, 0], cn[:, 1]), 1e-9)
    cn = cn / cn_len[:, None]
    flipc = np.sum(cn * inward, axis=1) < 0
    cn[flipc] *= -1

    def side(i_line, pts):  # signed distance of pts (for each j) from chord of i, inward positive
        return np.sum((pts[None, :, :] - head[:, None, :]) * cn[:, None, :], axis=2)

    tol = 2.0
    ok = (sign[:, None] == sign[None, :])
    ok &= side(None, mid) > -tol
    ok &= side(None, head) > -tol
    ok &= side(None, tail) > -tol
    ok &= ok.T
    # each group's interior direction points towards the other group
    dv = mid[None, :, :] - mid[:, None, :]  # from i to j
    ok &= np.sum(dv * inward[:, None, :], axis=2) > 0
    ok &= ok.T
    dist = np.hypot(dv[..., 0], dv[..., 1])
    # two arcs of one ellipse are at most 2a apart; the arcs' radius of curvature
    # (length / turn) bounds a (a <= 2 R for the axis ratios we accept)
    radius = np.array([g.length / max(g.span, 1e-3) for g in G])
    rmax = np.maximum(radius[:, None], radius[None, :])
    ok &= dist <= np.minimum(4.0 * rmax, 2 * max_axis_px)
    ok &= dist >= 0.5 * min_axis_px
    # complete arcs need no partner
    full = np.array([g.span >= math.radians(300) for g in G])
    ok &= ~(full[:, None] & full[None, :])
    # each group pairs with its nearest admissible partners only
    dd = np.where(ok, dist, np.inf)
    k = min(6, m - 1)
    near_k = np.argpartition(dd, k - 1, axis=1)[:, :k] if k > 0 else np.zeros((m, 0), int)
    sel = np.zeros_like(ok)
    sel[np.arange(m)[:, None], near_k] = True
    ok &= sel | sel.T
    ok = np.triu(ok, 1)
    ii, jj = np.nonzero(ok)
    return ii, jj


# --------------------------------------------------------------------------
# supplementary candidates: adaptive-threshold contours
# --------------------------------------------------------------------------

def _contour_candidates(gray8: np.ndarray, *, min_axis_px: float, max_axis_px: float,
                        polarity: int) -> list[tuple]:
    import cv2

    h, w = gray8.shape
    blur = cv2.GaussianBlur(gray8, (0, 0), 0.8)
    out: list[tuple] = []
    block = int(min(max(2 * max_axis_px, 31), 2 * (min(h, w) // 2) - 1)) | 1
    block = max(block, 3)
    for sign in (-1, 1):
        if polarity != 0 and sign != polarity:
            continue
        mode = cv2.THRESH_BINARY_INV if sign < 0 else cv2.THRESH_BINARY
        bw = cv2.adaptiveThreshold(blur, 255, cv2.ADAPTIVE_THRESH_MEAN_C, mode, block, 5 if sign < 0 else -5)
        contours, _ = cv2.findContours(bw, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
        for c in contours:
            if len(c) < 8 or len(c) > 8 * max_axis_px:
                continue
            area = cv2.contourArea(c)
            if area < 4:
                continue
            hull = cv2.convexHull(c)
            ha = cv2.contourArea(hull)
            if ha <= 0 or area / ha < 0.85:
                continue
            pts = c.reshape(-1, 2)
            # an ellipse cut by the image border: fit only the points off the border
            on_border = (pts[:, 0] <= 0) | (pts[:, 1] <= 0) | (pts[:, 0] >= w - 1) | (pts[:, 1] >= h - 1)
            cut = bool(on_border.any())
            if cut:
                pts = pts[~on_border]
                if len(pts) < 8:
                    continue
            try:
                e = _params_from_rect(cv2.fitEllipse(pts.astype(np.float32)))
            except cv2.error:
                continue
            if e is None:
                continue
            cx, cy, ea, eb, th = e
            # pixel-centre contour lies half a pixel inside the foreground
            ea, eb = ea + 0.5, eb + 0.5
            if not (min_axis_px <= eb and ea <= max_axis_px and eb >= 0.08 * ea):
                continue
            if not cut and abs(area + 0.5 * len(c) - math.pi * ea * eb) > 0.25 * math.pi * ea * eb:
                continue
            out.append((cx, cy, ea, eb, th, sign))
    return out


# --------------------------------------------------------------------------
# 4. clustering
# --------------------------------------------------------------------------

def _leader_cluster(values: np.ndarray, tol: np.ndarray, circular: float | None = None) -> np.ndarray:
    """Greedy leader clustering (a one-pass stand-in for mean shift with a flat kernel).

    ``values`` (N, k) in priority order; the first unassigned item leads a cluster that
    takes every unassigned item within the leader's tolerance ``tol`` (N, k) on every
    coordinate (``circular``: period of a wrapped coordinate).  Returns labels (N,).
    """
    n = len(values)
    labels = np.full(n, -1)
    c = 0
    for i in range(n):
        if labels[i] >= 0:
            continue
        free = np.nonzero(labels < 0)[0]
        dv = values[free] - values[i]
        if circular is not None:
            dv = (dv + circular / 2) % circular - circular / 2
        members = free[np.all(np.abs(dv) <= tol[i], axis=1)]
        labels[members] = c
        labels[i] = c
        c += 1
    return labels


def _centre_cluster(cen: np.ndarray, tol: np.ndarray) -> np.ndarray:
    """Leader clustering of centres (N, 2) with a k-d tree (items in priority order)."""
    from scipy.spatial import cKDTree

    tree = cKDTree(cen)
    labels = np.full(len(cen), -1)
    c = 0
    for i in range(len(cen)):
        if labels[i] >= 0:
            continue
        nb = np.asarray(tree.query_ball_point(cen[i], float(tol[i])), dtype=int)
        nb = nb[labels[nb] < 0]
        labels[nb] = c
        labels[i] = c
        c += 1
    return labels


def cluster_candidates(cands: list[tuple]) -> tuple[np.ndarray, np.ndarray]:
    """Merge duplicate candidates ``(cx, cy, a, b, angle, sign)``: centres, then
    orientations, then semi-axes (Lu §III-D), each level a leader clustering.

    Returns ``(P (K, 5) cx, cy, a, b, angle; S (K,) signs)``, one row per cluster
    (medians of centres and semi-axes, circular mean of the doubled angle).
    """
    if not cands:
        return np.zeros((0, 5)), np.zeros(0, int)
    P = np.asarray(cands, dtype=np.float64)
    S = P[:, 5].astype(int)
    cen = P[:, :2]
    ab = P[:, 2:4]
    ang = P[:, 4]
    order = np.argsort(-ab[:, 1])
    out: list[tuple] = []
    lab_c = _centre_cluster(cen[order], np.maximum(1.0, 0.1 * ab[order, 1]))
    members = np.split(order[np.argsort(lab_c, kind="stable")], np.cumsum(np.bincount(lab_c))[:-1])
    for mc in members:
        if len(mc) == 1:
            i = mc[0]
            out.append((*P[i, :5], S[i]))
            continue
        for s in np.unique(S[mc]):
            ms = mc[S[mc] == s]
            roundish = ab[ms, 1] / ab[ms, 0] > 0.9
            # orientation is meaningless for near-circles: give them a wide tolerance
            tol_o = np.where(roundish, math.pi, math.radians(10))
            lab_o = _leader_cluster(ang[ms][:, None], tol_o[:, None], circular=math.pi)
            for o in range(lab_o.max() + 1):
                mo = ms[lab_o == o]
                lab_a = _leader_cluster(ab[mo], np.maximum(1.0, 0.1 * ab[mo]))
                for q in range(lab_a.max() + 1):
                    mq = mo[lab_a == q]
                    if len(mq) == 1:
                        out.append((*P[mq[0], :5], s))
                        continue
                    cc = np.median(cen[mq], axis=0)
                    aa, bb = np.median(ab[mq], axis=0)
                    an = 0.5 * math.atan2(np.mean(np.sin(2 * ang[mq])), np.mean(np.cos(2 * ang[mq])))
                    out.append((cc[0], cc[1], aa, bb, an % math.pi, s))
    R = np.array(out, dtype=np.float64)
    return R[:, :5], R[:, 5].astype(int)


# --------------------------------------------------------------------------
# 5. verification
# --------------------------------------------------------------------------

def _samples(P: np.ndarray, max_n: int = 720) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points on K ellipses ``P`` (K, >=5: cx, cy, a, b, angle), about one per px of perimeter.

    Returns ``(p (M, 2), outward normals (M, 2), owner (M,), t (M,), counts (K,))``.
    """
    a, b = P[:, 2], P[:, 3]
    h = ((a - b) / (a + b)) ** 2
    per = math.pi * (a + b) * (1 + 3 * h / (10 + np.sqrt(4 - 3 * h)))
    cnt = np.clip(np.rint(per), 24, max_n).astype(int)
    owner = np.repeat(np.arange(len(P)), cnt)
    start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    t = 2 * math.pi * (np.arange(owner.size) - start[owner]) / cnt[owner]
    cx, cy, aa, bb, th = (P[owner, i] for i in range(5))
    c, s = np.cos(th), np.sin(th)
    x, y = aa * np.cos(t), bb * np.sin(t)
    p = np.column_stack([cx + c * x - s * y, cy + s * x + c * y])
    nx, ny = bb * np.cos(t), aa * np.sin(t)
    nr = np.column_stack([c * nx - s * ny, s * nx + c * ny])
    nr /= np.linalg.norm(nr, axis=1, keepdims=True)
    return p, nr, owner, t, cnt


def _support_batch(grad: Gradients, edges: np.ndarray, P: np.ndarray, S: np.ndarray, *, n_bins: int = 36,
                   max_angle_rad: float = math.radians(22.5)) -> tuple[np.ndarray, np.ndarray]:
    """Edge support of K ellipses (Lu §III-E): ``(inlier ratio (K,), angular coverage (K,))``.

    A sample on the ellipse is an inlier when an edge pixel (Canny) lies within 1.4 px
    along the normal and its gradient is within ``max_angle_rad`` of the normal with the
    ellipse's polarity ``S`` (+1 interior brighter: gradient inward).  Coverage is the
    fraction of ``n_bins`` equal parametric-angle sectors holding an inlier.
    """
    K = len(P)
    if K == 0:
        return np.zeros(0), np.zeros(0)
    h, w = edges.shape
    p, nr, owner, t, cnt = _samples(P)
    pol = S[owner].astype(np.float64)
    cosmax = math.cos(max_angle_rad)
    inl = np.zeros(len(p), bool)
    # samples outside the image are unknown, not missing: an ellipse cut by the border is
    # judged on its visible part (at least half of it must be visible)
    seen = (p[:, 0] >= 1) & (p[:, 0] <= w - 2) & (p[:, 1] >= 1) & (p[:, 1] <= h - 2)
    for off in (0.0, -0.7, 0.7, -1.4, 1.4):
        q = p + off * nr
        iu = np.rint(q[:, 0]).astype(int)
        iv = np.rint(q[:, 1]).astype(int)
        inside = (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h)
        iu, iv = np.clip(iu, 0, w - 1), np.clip(iv, 0, h - 1)
        gx, gy = grad.gx[iv, iu], grad.gy[iv, iu]
        c = -pol * (gx * nr[:, 0] + gy * nr[:, 1]) / np.maximum(np.hypot(gx, gy), 1e-9)
        inl |= edges[iv, iu] & inside & (c >= cosmax)
    inl &= seen
    n_seen = np.bincount(owner, weights=seen, minlength=K)
    ratio = np.bincount(owner, weights=inl, minlength=K) / np.maximum(n_seen, 1)
    nb = np.minimum(cnt, n_bins)  # small ellipses have fewer samples than sectors
    bins = owner * n_bins + np.minimum((t * (nb[owner] / (2 * math.pi))).astype(int), nb[owner] - 1)
    occupied = np.unique(bins[inl])
    visible = np.unique(bins[seen])
    cov = np.bincount(occupied // n_bins, minlength=K) / np.maximum(np.bincount(visible // n_bins, minlength=K), 1)
    too_hidden = n_seen < 0.5 * cnt
    ratio[too_hidden] = 0.0
    cov[too_hidden] = 0.0
    return ratio, cov


def _edge_map(gray8: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.Canny(cv2.GaussianBlur(gray8, (0, 0), 1.0), 20, 50, L2gradient=True) > 0


def _refit_batch(grad: Gradients, P: np.ndarray, S: np.ndarray, min_mag: float) -> tuple[np.ndarray, np.ndarray]:
    """Refit K candidates on sub-pixel edge points along their normals (two passes, the
    second with a narrower band).  Returns ``(P_new (K, 5), ok (K,))``."""
    import cv2

    P = P[:, :5].copy()
    valid = np.ones(len(P), bool)
    for second in (False, True):
        idx = np.nonzero(valid)[0]
        if idx.size == 0:
            break
        Q = P[idx]
        p, nr, owner, _, cnt = _samples(Q)
        band = 1.5 if second else np.clip(0.25 * Q[owner, 3], 1.5, 3.0)
        uv, ok, _ = edge_peaks_along_normals(grad, p, nr, S[idx][owner], band_px=band, step_px=0.5,
                                             min_mag=min_mag, max_angle_rad=math.radians(30))
        nok = np.bincount(owner, weights=ok, minlength=len(idx))
        hh, ww = grad.gx.shape
        seen = (p[:, 0] >= 1) & (p[:, 0] <= ww - 2) & (p[:, 1] >= 1) & (p[:, 1] <= hh - 2)
        n_vis = np.bincount(owner, weights=seen, minlength=len(idx))  # visible samples only
        bounds = np.concatenate([[0], np.cumsum(cnt)])
        for k, i in enumerate(idx):
            if nok[k] < max(8, 0.4 * n_vis[k]) or n_vis[k] < 0.5 * cnt[k]:
                valid[i] = False
                continue
            sl = slice(bounds[k], bounds[k + 1])
            pts = uv[sl][ok[sl]].astype(np.float32)
            try:
                q = _params_from_rect(cv2.fitEllipseDirect(pts))
            except cv2.error:
                q = None
            if q is None or abs(q[2] - Q[k, 2]) > max(2.0, 0.3 * Q[k, 2]) \
                    or math.hypot(q[0] - Q[k, 0], q[1] - Q[k, 1]) > max(2.0, 0.3 * Q[k, 3]):
                valid[i] = False
                continue
            P[i] = q
    return P, valid


def _iou_approx(e1: Ellipse, e2: Ellipse, n: int = 24) -> float:
    """Area IoU on a grid over the union's bounding box (n x n samples)."""
    b1, b2 = e1.bbox(), e2.bbox()
    u0, v0 = min(b1[0], b2[0]), min(b1[1], b2[1])
    u1, v1 = max(b1[2], b2[2]), max(b1[3], b2[3])
    uu, vv = np.meshgrid(np.linspace(u0, u1, n), np.linspace(v0, v1, n))
    q = np.column_stack([uu.ravel(), vv.ravel()])
    i1, i2 = e1.contains(q), e2.contains(q)
    un = np.sum(i1 | i2)
    return float(np.sum(i1 & i2) / un) if un else 0.0


# --------------------------------------------------------------------------
# public entry point
# --------------------------------------------------------------------------

def _detect_arrays(gray8: np.ndarray, *, min_axis_px: float, max_axis_px: float, pol: int,
                   min_inlier_ratio: float, min_coverage: float, use_contours: bool,
                   lsd_scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Stages 1–5 on one 8-bit image: ``(P (K, 5), S (K,), inlier ratio (K,), coverage (K,))``."""
    grad = gradients(gray8.astype(np.float32), 0.8, with_magnitude=False)
    segs = arc_support_segments(gray8, grad, lsd_scale=lsd_scale)
    groups = arc_groups(segs)
    cands = _initial_candidates(segs, groups, min_axis_px=min_axis_px, max_axis_px=max_axis_px, polarity=pol)
    if use_contours:
        cands += _contour_candidates(gray8, min_axis_px=min_axis_px, max_axis_px=max_axis_px, polarity=pol)
    P0, S0 = cluster_candidates(cands)
    empty = (np.zeros((0, 5)), np.zeros(0, int), np.zeros(0), np.zeros(0))
    if len(P0) == 0:
        return empty
    P1, ok = _refit_batch(grad, P0, S0, min_mag=3.0)
    ok &= (P1[:, 3] >= min_axis_px) & (P1[:, 2] <= max_axis_px)
    P1, S1 = P1[ok], S0[ok]
    if len(P1) == 0:
        return empty
    ratio, cov = _support_batch(grad, _edge_map(gray8), P1, S1)
    good = (ratio >= min_inlier_ratio) & (cov >= min_coverage)
    return P1[good], S1[good], ratio[good], cov[good]


#: the smallest semi-minor axis (px) the detector is asked to find on the image it works on:
#: the ELSDc photographs' bar (F >= 0.95) is met with ``min_axis_px=1.5`` at full resolution
MIN_WORKING_AXIS_PX = 1.5
#: images with more pixels than this (1 MiP; 1280x960 is 1.2) are searched reduced, when the
#: expected ellipses allow it.  The cost: ellipses that end up 1.5-3 px across on the reduced
#: image are found less often (ELSDc photographs with the default ``min_axis_px`` searched at
#: half size: recall 0.900 against 0.918, ``benchmarks/bench_ellipse.py``; they are 1024x768,
#: below this size, and searched at full size)
MAX_WORKING_PIXELS = 1024 * 1024
#: ellipses at least this large (semi-minor, on the reduced image) are searched reduced whatever the image size
LARGE_AXIS_PX = 10.0
MAX_DOWNSCALE = 4


def auto_downscale(shape: tuple[int, int], min_axis_px: float) -> int:
    """The reduction factor :func:`detect_ellipses` uses by default: 1, 2 or 4.

    The largest power of two (at most :data:`MAX_DOWNSCALE`) that keeps the smallest
    expected ellipse (semi-minor axis ``min_axis_px``) at least :data:`LARGE_AXIS_PX`
    across on the reduced image; and, for an image of more than
    :data:`MAX_WORKING_PIXELS` pixels, also the smallest power of two that brings it to
    that size, as long as the smallest expected ellipse keeps
    :data:`MIN_WORKING_AXIS_PX` there.  The search then costs about the same on any
    image, below OpenCV's LSD on the full one (``benchmarks/bench_ellipse.py``).

    >>> auto_downscale((960, 1280), 3.0), auto_downscale((960, 1280), 1.5), auto_downscale((768, 1024), 3.0)
    (2, 1, 1)
    >>> auto_downscale((960, 1280), 40.0), auto_downscale((240, 320), 40.0)
    (4, 4)
    """
    h, w = int(shape[0]), int(shape[1])

    def largest(floor: float) -> int:
        f = 1
        while 2 * f <= MAX_DOWNSCALE and min_axis_px / (2 * f) >= floor:
            f *= 2
        return f

    f = largest(LARGE_AXIS_PX)
    if h * w > MAX_WORKING_PIXELS:
        f_img = 1
        while (h // f_img) * (w // f_img) > MAX_WORKING_PIXELS and 2 * f_img <= MAX_DOWNSCALE:
            f_img *= 2
        f = max(f, min(f_img, largest(MIN_WORKING_AXIS_PX)))
    return f


@dataclass(frozen=True)
class EllipseDetectionOptions:
    """Options of :func:`detect_ellipses` (checked on construction).

    min_axis_px, max_axis_px : range of the semi-axes (px), the minor one >= ``min_axis_px``;
        ``max_axis_px`` None: half the image's smaller side.
    max_count : keep at most this many (best scores first); None: all.
    polarity : ``"dark"`` (interior darker than the surround), ``"light"``, or None (both).
    min_inlier_ratio, min_coverage : verification thresholds (Lu §III-E).
    use_contours : add adaptive-threshold contour candidates; None: only when
        ``min_axis_px < 12`` (LSD misses ellipses a few pixels across).
    downscale : run the pipeline on an image reduced by this integer factor (area
        averaging) and scale the ellipses back; None: from the image size and
        ``min_axis_px`` (:func:`auto_downscale`): large targets and large images need no
        full-resolution search, and :func:`refine_ellipse` does the metrology at full
        resolution.
    lsd_scale : LSD's own image scale (OpenCV default 0.8).
    """

    min_axis_px: float = 3.0
    max_axis_px: float | None = None
    max_count: int | None = None
    polarity: str | int | None = None
    min_inlier_ratio: float = 0.7
    min_coverage: float = 0.7
    use_contours: bool | None = None
    downscale: int | None = None
    lsd_scale: float = 0.8

    def __post_init__(self) -> None:
        if self.polarity not in _POLARITY:
            raise LightplaneError(f"polarity must be None, 'dark' or 'light', got {self.polarity!r}")
        if self.max_count is not None and not int(self.max_count) >= 1:
            raise LightplaneError(f"max_count must be >= 1 or None, got {self.max_count}")


def detect_ellipses(image: np.ndarray, options: EllipseDetectionOptions | None = None) -> list[Ellipse]:
    """Detect ellipses in a gray or colour, 8-/16-bit/float image (docs/method.md §Ellipse, RALS).

    ``image``: (H, W) or (H, W, 3) array; ``options``: :class:`EllipseDetectionOptions` (None:
    the defaults): the semi-axes' range, how many, the polarity, the verification thresholds,
    the contour candidates, the reduction and LSD's scale.

    Returns a list of :class:`Ellipse` sorted by decreasing score (inlier ratio x
    coverage); empty for blank, noise-only or tiny images.  Each ellipse carries the
    polarity it was verified with (+1 interior brighter, -1 darker).
    """
    import cv2

    opts = EllipseDetectionOptions() if options is None else options
    pol = _POLARITY[opts.polarity]
    gray = prepare_gray(image)
    h, w = gray.shape
    if min(h, w) < 8:
        return []
    max_axis_px = 0.5 * min(h, w) if opts.max_axis_px is None else opts.max_axis_px
    min_axis_px = max(float(opts.min_axis_px), 1.0)
    if not (math.isfinite(min_axis_px) and max_axis_px >= min_axis_px):
        raise LightplaneError(f"max_axis_px ({max_axis_px}) must be >= min_axis_px ({min_axis_px})")
    use_contours = min_axis_px < 12 if opts.use_contours is None else opts.use_contours
    f = max(int(opts.downscale), 1) if opts.downscale is not None else auto_downscale((h, w), min_axis_px)
    if min(h, w) // f < 16:
        f = 1
    # from the input itself: the same 8-bit image as from ``gray`` (to_gray8 converts it the same way;
    # 8-bit input is kept as it is) without re-checking and re-scanning the float copy
    gray8 = to_uint8(image)
    if int(gray8.max()) - int(gray8.min()) < 8:
        return []
    if f > 1:
        gray8 = cv2.resize(gray8, (w // f, h // f), interpolation=cv2.INTER_AREA)
    P, S, ratio, cov = _detect_arrays(gray8, min_axis_px=min_axis_px / f, max_axis_px=max_axis_px / f, pol=pol,
                                      min_inlier_ratio=opts.min_inlier_ratio, min_coverage=opts.min_coverage,
                                      use_contours=use_contours, lsd_scale=opts.lsd_scale)
    if f > 1:  # pixel centres: u_full = f * (u_small + 0.5) - 0.5
        P = P.copy()
        P[:, :2] = f * (P[:, :2] + 0.5) - 0.5
        P[:, 2:4] *= f
    return _suppress_duplicates(_ellipses(P, S, ratio, cov), opts.max_count)


def _ellipses(P: np.ndarray, S: np.ndarray, ratio: np.ndarray, cov: np.ndarray) -> list[Ellipse]:
    """The detections ``P`` (K, 5: cx, cy, a, b, angle) as :class:`Ellipse` (degenerate ones left out),
    with their polarity ``S``, inlier ratio, coverage and score (their product)."""
    found: list[Ellipse] = []
    for k in range(len(P)):
        try:
            found.append(Ellipse.from_params(P[k, :2], P[k, 2], P[k, 3], P[k, 4],
                                             score=float(ratio[k] * cov[k]), inlier_ratio=float(ratio[k]),
                                             coverage=float(cov[k]), polarity=int(S[k])))
        except LightplaneError:
            continue
    return found


def _suppress_duplicates(found: list[Ellipse], max_count: int | None) -> list[Ellipse]:
    """Final non-maximum suppression (duplicates that survived clustering): best scores first,
    at most ``max_count``."""
    found.sort(key=lambda e: (-e.score, -e.a))
    kept: list[Ellipse] = []
    kc = np.zeros((len(found), 2))
    kb = np.zeros(len(found))
    for e in found:
        n = len(kept)
        close = np.nonzero(np.hypot(kc[:n, 0] - e.centre[0], kc[:n, 1] - e.centre[1])
                           < np.maximum(2.0, 0.3 * np.minimum(kb[:n], e.b)))[0]
        if any(kept[k].polarity == e.polarity and _iou_approx(kept[k], e) > 0.7 for k in close):
            continue
        kc[n], kb[n] = e.centre, e.b
        kept.append(e)
        if max_count is not None and len(kept) >= max_count:
            break
    return kept
