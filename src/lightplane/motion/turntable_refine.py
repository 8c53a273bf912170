"""Turntable self-calibration from scans: refine the axis and the scans' start angles.

Two scans of the same object on a turntable (two lasers, or two passes) give two clouds
in the turntable frame; an error in the axis (or an unknown start angle of a scan) makes
them disagree.  With the light planes held fixed, :func:`refine_turntable` moves the axis
(direction: 2 dof, a point across it: 2 dof) and every scan's start angle after the first
(1 dof each) so that the clouds agree:

1. a coarse search of each start angle (a full turn, then finer) against the first
   scan's cloud, by the median nearest-neighbour distance;
2. a joint refinement, ICP-like: each round pairs a subsample of every cloud with the
   local planes of the other (k nearest neighbours, normal by PCA; symmetric), and
   ``scipy.optimize.least_squares`` minimises the point-to-plane distances with a robust
   loss (soft-L1 scaled by the MAD-based sigma of the round's distances), the pairs
   held fixed within the round.

The agreement is the symmetric point-to-surface distance (each cloud's points to the
local planes of the other), its median and 90th percentile, in mm.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from lightplane.core.errors import LightplaneError
from lightplane.core.geometry import robust_sigma
from lightplane.motion.model import Turntable

__all__ = ["TurntableScan", "RefineResult", "table_points", "agreement", "refine_turntable"]

K_NEIGHBOURS = 10
N_SAMPLE = 3000
ROUNDS = 8


@dataclass(frozen=True, eq=False)
class TurntableScan:
    """One scan: camera-frame points (N, 3) mm, the frame index of each, the angle per frame (deg)."""

    name: str
    points_cam: np.ndarray
    frames: np.ndarray
    step_deg: float

    def __post_init__(self) -> None:
        p = np.asarray(self.points_cam, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3 or len(p) != len(self.frames):
            raise LightplaneError(f"scan {self.name}: points must be (N, 3) with one frame index each")
        if not (np.isfinite(self.step_deg) and self.step_deg != 0):
            raise LightplaneError(f"scan {self.name}: the turntable step must be a finite non-zero angle (deg)")


@dataclass
class RefineResult:
    turntable: Turntable
    start_deg: list[float]
    before: dict            # agreement with the given axis and start angles 0
    searched: dict          # with the given axis and the searched start angles
    after: dict             # refined
    axis_moved_deg: float
    axis_moved_mm: float    # how far the new axis passes from the old one's point (across the axis)
    rounds: list = field(default_factory=list)


def _frame_basis(point: np.ndarray, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return Turntable(point, direction).basis()


def table_points(scan: TurntableScan, point: np.ndarray, direction: np.ndarray, start_deg: float,
                 idx: np.ndarray | None = None) -> np.ndarray:
    """``scan``'s points in the turntable frame of the axis (point, direction), the first frame at ``start_deg``.

    The same transform as :meth:`lightplane.motion.model.Motion.transform` of a turntable motion, vectorised.
    """
    o, B = _frame_basis(point, direction)
    p = scan.points_cam if idx is None else scan.points_cam[idx]
    f = scan.frames if idx is None else scan.frames[idx]
    q = (p - o) @ B
    a = -np.deg2rad(start_deg + f * scan.step_deg)
    c, s = np.cos(a), np.sin(a)
    return np.column_stack([c * q[:, 0] - s * q[:, 1], s * q[:, 0] + c * q[:, 1], q[:, 2]])


def _local_planes(cloud: np.ndarray, tree: cKDTree, query: np.ndarray, k: int):
    """Nearest-neighbour distance, neighbour indices (M, k) and PCA normals (M, 3) at ``query``."""
    k = min(k, len(cloud))
    d, j = tree.query(query, k=k)
    j = j.reshape(len(query), k)
    nb = cloud[j]
    c = nb.mean(axis=1)
    cov = np.einsum("mki,mkj->mij", nb - c[:, None], nb - c[:, None])
    _, vec = np.linalg.eigh(cov)
    return np.asarray(d).reshape(len(query), k)[:, 0], j, vec[:, :, 0], c


def _surface_distances(a: np.ndarray, b: np.ndarray, k: int = K_NEIGHBOURS) -> np.ndarray:
    """|distance| of each point of ``a`` to the local plane of ``b`` at its nearest neighbours."""
    _, _, n, c = _local_planes(b, cKDTree(b), a, k)
    return np.abs(np.einsum("mi,mi->m", a - c, n))


def agreement(clouds: list[np.ndarray], rng: np.random.Generator | None = None, n: int = 20000) -> dict:
    """Symmetric point-to-surface distances between the first cloud and each other (mm): median, p90, count."""
    rng = np.random.default_rng(0) if rng is None else rng
    d = []
    for other in clouds[1:]:
        for a, b in ((clouds[0], other), (other, clouds[0])):
            sel = rng.choice(len(a), size=min(n, len(a)), replace=False)
            d.append(_surface_distances(a[sel], b))
    dd = np.concatenate(d)
    return {"median_mm": float(np.median(dd)), "p90_mm": float(np.percentile(dd, 90)), "n": int(dd.size)}


def _search_start(ref: np.ndarray, scan: TurntableScan, point, direction, rng) -> float:
    """The start angle (deg) of ``scan`` that brings its cloud closest to ``ref`` (median NN distance)."""
    tree = cKDTree(ref)
    sel = rng.choice(len(scan.points_cam), size=min(N_SAMPLE, len(scan.points_cam)), replace=False)

    def cost(a: float) -> float:
        return float(np.median(tree.query(table_points(scan, point, direction, a, sel))[0]))

    best = min(np.arange(0.0, 360.0, 2.0), key=cost)
    for span, step in ((2.0, 0.25), (0.25, 0.025)):
        best = min(best + np.arange(-span, span + 1e-9, step), key=cost)
    return float(best % 360.0)


def _perp_basis(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    h = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    u = np.cross(d, h)
    u /= np.linalg.norm(u)
    return u, np.cross(d, u)


def refine_turntable(table: Turntable, scans: list[TurntableScan], *, k: int = K_NEIGHBOURS,
                     n_sample: int = N_SAMPLE, rounds: int = ROUNDS, search: bool = True,
                     start_deg: list[float] | None = None, seed: int = 0,
                     progress: Callable[[str, int, int], None] | None = None) -> RefineResult:
    """Refine ``table``'s axis and the start angles of ``scans[1:]`` (``scans[0]`` starts at 0 deg).

    ``progress(label, done, total)``: after each step (the start-angle search per scan, each round).
    """
    def report(label: str, done: int, total: int) -> None:
        if progress is not None:
            progress(label, done, total)

    if len(scans) < 2:
        raise LightplaneError("refining the turntable needs two scans of the same object (or more)")
    for s in scans:
        if len(s.points_cam) < 10 * k:
            raise LightplaneError(f"scan {s.name}: {len(s.points_cam)} points, too few to refine the turntable")
    rng = np.random.default_rng(seed)
    p0, d0 = table.point_mm.astype(np.float64), table.direction.astype(np.float64)
    u1, u2 = _perp_basis(d0)
    starts = [0.0] * len(scans) if start_deg is None else [float(a) for a in start_deg]

    def clouds(point, direction, st) -> list[np.ndarray]:
        return [table_points(s, point, direction, a) for s, a in zip(scans, st)]

    before = agreement(clouds(p0, d0, starts))
    if search:
        ref = table_points(scans[0], p0, d0, starts[0])
        found = [starts[0]]
        for i, s in enumerate(scans[1:]):
            found.append(_search_start(ref, s, p0, d0, rng))
            report("searching the start angles", i + 1, len(scans) - 1)
        starts = found
    searched = agreement(clouds(p0, d0, starts))

    def unpack(x):
        d = d0 + x[0] * u1 + x[1] * u2
        d = d / np.linalg.norm(d)
        return p0 + x[2] * u1 + x[3] * u2, d, [starts[0], *(starts[1:] + x[4:])]

    x = np.zeros(4 + len(scans) - 1)
    samples = [rng.choice(len(s.points_cam), size=min(n_sample, len(s.points_cam)), replace=False) for s in scans]
    log = []
    for r in range(rounds):
        point, direction, st = unpack(x)
        full = clouds(point, direction, st)
        pairs = []  # (scan a, its sample, scan b, neighbour indices in b, normals)
        dist = []
        for i in range(1, len(scans)):
            for a, b in ((0, i), (i, 0)):
                qa = full[a][samples[a]]
                nn, j, nrm, c = _local_planes(full[b], cKDTree(full[b]), qa, k)
                res = np.einsum("mi,mi->m", qa - c, nrm)
                pairs.append((a, b, j, nrm, nn))
                dist.append(res)
        sigma = max(robust_sigma(np.concatenate(dist), center=False), 1e-4)
        # pairs too far apart (parts only one scan sees) are left out
        keep = [np.abs(dd) < 5.0 * sigma + 0.0 for dd in dist]
        flat = [np.unique(pr[2][kp].ravel()) for pr, kp in zip(pairs, keep)]

        def residuals(xx, pairs=pairs, keep=keep, flat=flat):
            point, direction, st = unpack(xx)
            out = []
            for (a, b, j, nrm, _), kp, fl in zip(pairs, keep, flat):
                qa = table_points(scans[a], point, direction, st[a], samples[a][kp])
                pb = np.empty((len(scans[b].points_cam), 3))
                pb[fl] = table_points(scans[b], point, direction, st[b], fl)
                c = pb[j[kp]].mean(axis=1)
                out.append(np.einsum("mi,mi->m", qa - c, nrm[kp]))
            return np.concatenate(out)

        sol = least_squares(residuals, x, loss="soft_l1", f_scale=sigma, x_scale=np.r_[1e-3, 1e-3, 1.0, 1.0,
                            np.full(len(scans) - 1, 1e-2)], method="trf")
        step = np.abs(sol.x - x)
        x = sol.x
        log.append({"round": r + 1, "sigma_mm": sigma, "pairs": int(sum(int(kp.sum()) for kp in keep))})
        report("refining the axis and start angles (rounds)", r + 1, rounds)
        if r > 0 and np.all(step[:2] < 1e-5) and np.all(step[2:4] < 1e-3) and np.all(step[4:] < 1e-3):
            break
    point, direction, st = unpack(x)
    after = agreement(clouds(point, direction, st))
    # the board calibration's records (estimates, jackknife...) describe the old axis: not carried over
    new = Turntable.from_axis(point, direction, covariance=None, camera=table.camera,
                              counts_per_rev=table.counts_per_rev)
    moved_deg = float(np.degrees(np.arccos(min(1.0, abs(float(new.direction @ d0))))))
    v = p0 - new.point_mm
    moved_mm = float(np.linalg.norm(v - (v @ new.direction) * new.direction))
    return RefineResult(new, [float(a % 360.0) for a in st], before, searched, after, moved_deg, moved_mm, log)
