"""Ellipse detection with arc-support line segments (SPEC §5.1; Lu, Xia, Shao, Fu,
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
   coverage are high enough; score = inlier ratio x coverage.

Supplementary candidates (documented deviation): ellipses of contours of a locally
adaptive threshold, both polarities.  LSD finds no segments on ellipses only a few
pixels across (the real calibration photographs hold hundreds); these candidates
go through the same clustering and verification, so they add recall without
bypassing the arc-support evidence test.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import LightplaneError
from .edges import Gradients, gradients, normal_edge_points, prepare_gray, to_uint8
from .model import Ellipse, fit_ellipse_direct, fit_ellipse_geometric, sampson_distance

__all__ = ["detect_ellipses", "arc_support_segments", "arc_groups"]

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
    segment has at most one successor and one predecessor (the nearest).
    Returns a list of ``(segment indices in order, sign)``; sign +1: interior brighter.
    """
    n = len(segs)
    if n < 2:
        return []
    head, tail = segs[:, :2], segs[:, 2:]
    d = tail - head
    ln = np.hypot(d[:, 0], d[:, 1])
    d = d / ln[:, None]
    gap = np.hypot(tail[:, None, 0] - head[None, :, 0], tail[:, None, 1] - head[None, :, 1])  # (i tail, j head)
    tol = np.clip(0.5 * np.minimum(ln[:, None], ln[None, :]), 2.0, 8.0)
    cross = d[:, None, 0] * d[None, :, 1] - d[:, None, 1] * d[None, :, 0]
    dot = d[:, None, 0] * d[None, :, 0] + d[:, None, 1] * d[None, :, 1]
    turn = np.arctan2(cross, dot)
    near = (gap <= tol)
    np.fill_diagonal(near, False)
    groups: list[tuple[np.ndarray, int]] = []
    for sign in (1, -1):
        ok = near & (sign * turn >= min_turn_rad) & (sign * turn <= max_turn_rad)
        cost = np.where(ok, gap, np.inf)
        succ = np.argmin(cost, axis=1)
        succ[~np.isfinite(cost[np.arange(n), succ])] = -1
        # keep each successor's nearest predecessor only
        pred = np.full(n, -1)
        best = np.full(n, np.inf)
        for i in np.argsort(cost[np.arange(n), np.maximum(succ, 0)]):
            j = succ[i]
            if j >= 0 and pred[j] < 0:
                pred[j] = i
                best[j] = cost[i, j]
        succ = np.full(n, -1)
        for j in range(n):
            if pred[j] >= 0:
                succ[pred[j]] = j
        seen = np.zeros(n, bool)
        starts = [i for i in range(n) if pred[i] < 0 and succ[i] >= 0]
        for s0 in starts:
            chain = [s0]
            seen[s0] = True
            j = succ[s0]
            while j >= 0 and not seen[j]:
                chain.append(j)
                seen[j] = True
                j = succ[j]
            groups.append((np.array(chain), sign))
        # closed loops (every member has a predecessor): cut anywhere
        for i in range(n):
            if not seen[i] and succ[i] >= 0:
                chain = [i]
                seen[i] = True
                j = succ[i]
                while j >= 0 and not seen[j]:
                    chain.append(j)
                    seen[j] = True
                    j = succ[j]
                if len(chain) >= 2:
                    groups.append((np.array(chain), sign))
    return groups


def _group_points(segs: np.ndarray, idx: np.ndarray, step_px: float = 1.5) -> np.ndarray:
    pts = []
    for i in idx:
        x1, y1, x2, y2 = segs[i]
        m = max(2, int(math.hypot(x2 - x1, y2 - y1) / step_px) + 1)
        f = np.linspace(0, 1, m)
        pts.append(np.column_stack([x1 + f * (x2 - x1), y1 + f * (y2 - y1)]))
    return np.concatenate(pts)


# --------------------------------------------------------------------------
# 3. initial candidates
# --------------------------------------------------------------------------

class _Group:
    __slots__ = ("pts", "sign", "span", "head", "tail", "mid", "normal", "length")

    def __init__(self, segs: np.ndarray, idx: np.ndarray, sign: int):
        self.pts = _group_points(segs, idx)
        self.sign = sign
        d0 = segs[idx[0], 2:] - segs[idx[0], :2]
        d1 = segs[idx[-1], 2:] - segs[idx[-1], :2]
        turn = 0.0
        for a, b in zip(idx[:-1], idx[1:]):
            da = segs[a, 2:] - segs[a, :2]
            db = segs[b, 2:] - segs[b, :2]
            turn += abs(math.atan2(da[0] * db[1] - da[1] * db[0], da @ db))
        self.span = turn
        self.head = segs[idx[0], :2]
        self.tail = segs[idx[-1], 2:]
        k = idx[len(idx) // 2]
        self.mid = 0.5 * (segs[k, :2] + segs[k, 2:])
        dm = segs[k, 2:] - segs[k, :2]
        dm = dm / np.linalg.norm(dm)
        self.normal = np.array([-dm[1], dm[0]])  # towards the brighter side
        self.length = float(np.sum(np.hypot(*(segs[idx, 2:] - segs[idx, :2]).T)))
        del d0, d1


def _fit_candidate(pts: np.ndarray, min_axis_px: float, max_axis_px: float) -> Ellipse | None:
    C = fit_ellipse_direct(pts)
    if C is None:
        return None
    try:
        e = Ellipse.from_conic(C)
    except LightplaneError:
        return None
    if not (min_axis_px <= e.b and e.a <= max_axis_px and e.b >= 0.08 * e.a):
        return None
    return e


def _initial_candidates(segs: np.ndarray, groups: list[tuple[np.ndarray, int]], *, min_axis_px: float,
                        max_axis_px: float, polarity: int, shape: tuple[int, int]) -> list[tuple[Ellipse, int]]:
    G = [_Group(segs, idx, s) for idx, s in groups if polarity == 0 or s == polarity]
    cands: list[tuple[Ellipse, int]] = []
    # local: salient groups
    for g in G:
        if g.span >= math.radians(70) and len(g.pts) >= 6:
            e = _fit_candidate(g.pts, min_axis_px, max_axis_px)
            if e is not None and np.mean(np.abs(sampson_distance(e.conic, g.pts))) < 1.0:
                cands.append((e, g.sign))
    # global: pairs of groups under polarity and region conditions
    m = len(G)
    if m >= 2:
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
        for i, j in zip(ii, jj):
            pts = np.concatenate([G[i].pts, G[j].pts])
            e = _fit_candidate(pts, min_axis_px, max_axis_px)
            if e is None:
                continue
            # adaptive inlier criterion: both groups must lie on the fitted ellipse
            di = np.abs(sampson_distance(e.conic, G[i].pts))
            dj = np.abs(sampson_distance(e.conic, G[j].pts))
            thr = max(1.0, 0.03 * e.b)
            if np.mean(di < thr) >= 0.8 and np.mean(dj < thr) >= 0.8:
                cands.append((e, G[i].sign))
    return cands


# --------------------------------------------------------------------------
# supplementary candidates: adaptive-threshold contours
# --------------------------------------------------------------------------

def _contour_candidates(gray8: np.ndarray, *, min_axis_px: float, max_axis_px: float,
                        polarity: int) -> list[tuple[Ellipse, int]]:
    import cv2

    h, w = gray8.shape
    blur = cv2.GaussianBlur(gray8, (0, 0), 0.8)
    out: list[tuple[Ellipse, int]] = []
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
            try:
                e = Ellipse.from_cv_rotated_rect(cv2.fitEllipse(c))
            except (LightplaneError, cv2.error):
                continue
            if not (min_axis_px <= e.b + 0.5 and e.a <= max_axis_px and e.b >= 0.08 * e.a):
                continue
            # pixel-centre contour lies half a pixel inside the foreground
            try:
                e = Ellipse.from_params(e.centre, e.a + 0.5, e.b + 0.5, e.angle)
            except LightplaneError:
                continue
            if abs(area + 0.5 * len(c) - e.area) > 0.25 * e.area:
                continue
            out.append((e, sign))
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


def cluster_candidates(cands: list[tuple[Ellipse, int]]) -> list[tuple[Ellipse, int]]:
    """Merge duplicate candidates: centres, then orientations, then semi-axes (Lu §III-D)."""
    if not cands:
        return []
    E = [c[0] for c in cands]
    S = np.array([c[1] for c in cands])
    cen = np.array([e.centre for e in E])
    ab = np.array([[e.a, e.b] for e in E])
    ang = np.array([e.angle for e in E])
    order = np.argsort(-ab[:, 1])
    out: list[tuple[Ellipse, int]] = []
    lab_c = _centre_cluster(cen[order], np.maximum(1.0, 0.1 * ab[order, 1]))
    for c in np.unique(lab_c):
        mc = order[lab_c == c]
        for s in np.unique(S[mc]):
            ms = mc[S[mc] == s]
            roundish = ab[ms, 1] / ab[ms, 0] > 0.9
            # orientation is meaningless for near-circles: give them a wide tolerance
            tol_o = np.where(roundish, math.pi, math.radians(10))
            lab_o = _leader_cluster(ang[ms][:, None], tol_o[:, None], circular=math.pi)
            for o in np.unique(lab_o):
                mo = ms[lab_o == o]
                lab_a = _leader_cluster(ab[mo], np.maximum(1.0, 0.1 * ab[mo]))
                for q in np.unique(lab_a):
                    mq = mo[lab_a == q]
                    cc = np.median(cen[mq], axis=0)
                    aa, bb = np.median(ab[mq], axis=0)
                    # circular mean of the doubled angle
                    an = 0.5 * math.atan2(np.mean(np.sin(2 * ang[mq])), np.mean(np.cos(2 * ang[mq])))
                    try:
                        out.append((Ellipse.from_params(cc, aa, bb, an), int(s)))
                    except LightplaneError:
                        pass
    return out


# --------------------------------------------------------------------------
# 5. verification
# --------------------------------------------------------------------------

def _support(grad: Gradients, edges: np.ndarray, e: Ellipse, sign: int, *, n_bins: int = 36,
             max_angle_rad: float = math.radians(22.5)) -> tuple[float, float, int]:
    """(inlier ratio, angular coverage, polarity) of ellipse ``e`` against the edge map.

    A sample on the ellipse is an inlier when an edge pixel lies within 1 px along the
    normal and its gradient is within ``max_angle_rad`` of the normal, with the polarity.
    """
    h, w = edges.shape
    n = int(min(max(24, round(e.perimeter)), 720))
    t = np.linspace(0, 2 * math.pi, n, endpoint=False)
    p = e.points_at(t)
    nr = e.normals_at(t)
    cosmax = math.cos(max_angle_rad)
    inl_pos = np.zeros(n, bool)
    inl_neg = np.zeros(n, bool)
    for off in (0.0, -0.7, 0.7, -1.4, 1.4):
        q = p + off * nr
        iu = np.rint(q[:, 0]).astype(int)
        iv = np.rint(q[:, 1]).astype(int)
        inside = (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h)
        iu, iv = np.clip(iu, 0, w - 1), np.clip(iv, 0, h - 1)
        ed = edges[iv, iu] & inside
        gx, gy = grad.gx[iv, iu], grad.gy[iv, iu]
        c = (gx * nr[:, 0] + gy * nr[:, 1]) / np.maximum(np.hypot(gx, gy), 1e-9)
        inl_neg |= ed & (c >= cosmax)  # gradient outward: interior darker
        inl_pos |= ed & (c <= -cosmax)
    if sign == 0:
        sign = -1 if inl_neg.sum() >= inl_pos.sum() else 1
    inl = inl_neg if sign < 0 else inl_pos
    bins = (np.arange(n) * n_bins) // n
    cov = np.unique(bins[inl]).size / n_bins
    return float(inl.mean()), float(cov), sign


def _edge_map(gray8: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.Canny(cv2.GaussianBlur(gray8, (0, 0), 1.0), 20, 50, L2gradient=True) > 0


def _refit(grad: Gradients, e: Ellipse, sign: int, min_mag: float) -> Ellipse | None:
    """Refit a candidate on sub-pixel edge points along its normals (one or two passes)."""
    for band in (min(3.0, max(1.5, 0.25 * e.b)), 1.5):
        n = int(min(max(24, round(e.perimeter)), 720))
        uv, _, _ = normal_edge_points(grad, e, n=n, band_px=band, step_px=0.5, polarity=sign,
                                      min_mag=min_mag, max_angle_rad=math.radians(30))
        if len(uv) < max(8, 0.4 * n):
            return None
        C = fit_ellipse_direct(uv)
        if C is None:
            return None
        try:
            e2 = Ellipse.from_conic(C)
        except LightplaneError:
            return None
        if abs(e2.a - e.a) > max(2.0, 0.3 * e.a) or np.hypot(*(e2.centre - e.centre)) > max(2.0, 0.3 * e.b):
            return None
        e = e2
    return e


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

def detect_ellipses(image: np.ndarray, *, min_axis_px: float = 3.0, max_axis_px: float | None = None,
                    max_count: int | None = None, polarity: str | int | None = None,
                    min_inlier_ratio: float = 0.7, min_coverage: float = 0.7,
                    use_contours: bool = True, lsd_scale: float | None = None) -> list[Ellipse]:
    """Detect ellipses in a gray or colour, 8-/16-bit/float image (SPEC §5.1, RALS).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array.
    min_axis_px, max_axis_px : range of the semi-axes (px); ``max_axis_px`` defaults to
        half the image's smaller side.
    max_count : keep at most this many (best scores first).
    polarity : ``"dark"`` (interior darker than the surround), ``"light"``, or None (both).
    min_inlier_ratio, min_coverage : verification thresholds (Lu §III-E).
    use_contours : add adaptive-threshold contour candidates (small ellipses).
    lsd_scale : LSD's image scale (default 0.8; 0.5 when ``min_axis_px >= 15`` for speed).

    Returns a list of :class:`Ellipse` sorted by decreasing score (inlier ratio x
    coverage); empty for blank, noise-only or tiny images.  Each ellipse carries the
    polarity it was verified with.
    """
    if polarity not in _POLARITY:
        raise LightplaneError(f"polarity must be None, 'dark' or 'light', got {polarity!r}")
    pol = _POLARITY[polarity]
    gray = prepare_gray(image)
    h, w = gray.shape
    if min(h, w) < 8:
        return []
    if max_axis_px is None:
        max_axis_px = 0.5 * min(h, w)
    min_axis_px = max(float(min_axis_px), 1.0)
    if max_axis_px < min_axis_px:
        raise LightplaneError(f"max_axis_px ({max_axis_px}) must be >= min_axis_px ({min_axis_px})")
    gray8 = to_uint8(gray)
    if int(gray8.max()) - int(gray8.min()) < 8:
        return []
    g8f = gray8.astype(np.float32)
    grad = gradients(g8f, 1.0)
    if lsd_scale is None:
        lsd_scale = 0.5 if min_axis_px >= 15 else 0.8
    segs = arc_support_segments(gray8, grad, lsd_scale=lsd_scale)
    groups = arc_groups(segs)
    cands = _initial_candidates(segs, groups, min_axis_px=min_axis_px, max_axis_px=max_axis_px,
                                polarity=pol, shape=(h, w))
    if use_contours:
        cands += _contour_candidates(gray8, min_axis_px=min_axis_px, max_axis_px=max_axis_px, polarity=pol)
    clusters = cluster_candidates(cands)
    edges = _edge_map(gray8)
    grad_fine = gradients(g8f, 0.7)
    found: list[Ellipse] = []
    for e, s in clusters:
        e2 = _refit(grad_fine, e, s, min_mag=3.0)
        if e2 is None or not (min_axis_px <= e2.b and e2.a <= max_axis_px):
            continue
        ratio, cov, s2 = _support(grad, edges, e2, s)
        if ratio < min_inlier_ratio or cov < min_coverage:
            continue
        found.append(Ellipse.from_params(e2.centre, e2.a, e2.b, e2.angle, score=ratio * cov,
                                         inlier_ratio=ratio, coverage=cov, polarity=s2))
    # final non-maximum suppression: duplicates that survived clustering
    found.sort(key=lambda e: (-e.score, -e.a))
    kept: list[Ellipse] = []
    for e in found:
        dup = False
        for k in kept:
            if k.polarity == e.polarity and np.hypot(*(k.centre - e.centre)) < max(2.0, 0.3 * min(k.b, e.b)) \
                    and _iou_approx(k, e) > 0.7:
                dup = True
                break
        if not dup:
            kept.append(e)
        if max_count is not None and len(kept) >= max_count:
            break
    return kept
