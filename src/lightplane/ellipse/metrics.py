"""Scoring ellipse detections against labelled ellipses (area-overlap IoU, F-measure).

The protocol of the ELSDc / RALS evaluations: a detection matches a label when their
area IoU is at least ``iou_min``; each label matches at most one detection (greedy by
IoU), so duplicates count as false positives; precision and recall are pooled.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lightplane.ellipse.model import Ellipse

__all__ = ["ellipse_iou", "match_ellipses", "MatchCounts", "read_ellipse_labels"]


def ellipse_iou(e1: Ellipse, e2: Ellipse, *, samples_per_px: float = 4.0, max_samples: int = 400) -> float:
    """Area IoU of two ellipses, by sampling their union's bounding box on a regular grid
    (``samples_per_px`` per pixel, at most ``max_samples`` per side: error << 1 %)."""
    b1, b2 = e1.bbox(), e2.bbox()
    u0, v0 = min(b1[0], b2[0]), min(b1[1], b2[1])
    u1, v1 = max(b1[2], b2[2]), max(b1[3], b2[3])
    if min(b1[2], b2[2]) < max(b1[0], b2[0]) or min(b1[3], b2[3]) < max(b1[1], b2[1]):
        return 0.0
    nu = int(min(max(8, (u1 - u0) * samples_per_px), max_samples))
    nv = int(min(max(8, (v1 - v0) * samples_per_px), max_samples))
    uu, vv = np.meshgrid(np.linspace(u0, u1, nu), np.linspace(v0, v1, nv))
    q = np.column_stack([uu.ravel(), vv.ravel()])
    i1, i2 = e1.contains(q), e2.contains(q)
    un = np.count_nonzero(i1 | i2)
    return float(np.count_nonzero(i1 & i2) / un) if un else 0.0


@dataclass(frozen=True)
class MatchCounts:
    """True positives, false positives (duplicates included), false negatives."""

    tp: int
    fp: int
    fn: int

    def __add__(self, o: "MatchCounts") -> "MatchCounts":
        return MatchCounts(self.tp + o.tp, self.fp + o.fp, self.fn + o.fn)

    @property
    def precision(self) -> float:
        return self.tp / (self.tp + self.fp) if self.tp + self.fp else 1.0

    @property
    def recall(self) -> float:
        return self.tp / (self.tp + self.fn) if self.tp + self.fn else 1.0

    @property
    def f_measure(self) -> float:
        p, r = self.precision, self.recall
        return 2 * p * r / (p + r) if p + r else 0.0


def match_ellipses(detected: list[Ellipse], truth: list[Ellipse], iou_min: float = 0.8) -> MatchCounts:
    """One-to-one greedy matching by IoU >= ``iou_min``; returns the counts."""
    pairs = []
    for i, d in enumerate(detected):
        for j, t in enumerate(truth):
            if np.hypot(*(d.centre - t.centre)) > max(d.a, t.a):
                continue
            iou = ellipse_iou(d, t)
            if iou >= iou_min:
                pairs.append((iou, i, j))
    pairs.sort(reverse=True)
    used_d, used_t = set(), set()
    for _, i, j in pairs:
        if i not in used_d and j not in used_t:
            used_d.add(i)
            used_t.add(j)
    tp = len(used_d)
    return MatchCounts(tp, len(detected) - tp, len(truth) - tp)


def read_ellipse_labels(path) -> list[Ellipse]:
    """Labels in the ELSDc format: one ``xc,yc,a,b,theta`` (px, rad) per line."""
    out = []
    with open(path) as f:
        for line in f:
            line = line.strip()
            if not line:
                continue
            xc, yc, a, b, th = (float(x) for x in line.replace(" ", ",").split(",") if x)
            out.append(Ellipse.from_params((xc, yc), a, b, th))
    return out
