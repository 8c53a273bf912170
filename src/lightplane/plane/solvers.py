"""Light-plane calibration from circle-target observations: the candidate chords, the
paper's progressive solver, the global disambiguation and the joint ML refinement's entry
(docs/method.md §Light plane).  Works on points: rim and stripe centres per placement;
:mod:`lightplane.plane.calibrate` gets them from images.  The plane type is
:class:`lightplane.plane.model.LightPlane`.
"""

from __future__ import annotations

from dataclasses import dataclass as _dataclass
from dataclasses import field as _field
from dataclasses import replace as _replace
from functools import cached_property
from typing import Sequence

import numpy as np

from lightplane.camera.model import Camera, as_points
from lightplane.core.errors import LightplaneError
from lightplane.core.geometry import fit_conics, fit_plane_tls, ray_plane, robust_line, sampson_distance
from lightplane.core.threads import with_blas_limited
from lightplane.plane.circle_pose import CirclePose, circle_poses, circle_poses_batch, fit_rim_conic
from lightplane.plane.ml import MLOptions, refine_ml
from lightplane.plane.model import LightPlane

__all__ = [
    "PlacementResult",
    "Ambiguity",
    "PlaneCalibration",
    "calibrate_plane_from_points",
    "check_calibration_args",
    "prepare_placement",
    "PlacementCandidates",
    "estimate_sigma_px",
    "SolverOptions",
]

# =====================================================================================
# Light-plane calibration from a circular target (paper §2.2.3, docs/method.md §Light plane)
# =====================================================================================
#
# Per placement i: rim points -> conic -> two circle poses (paper §2.2.2) -> stripe
# points back-projected onto each candidate target plane -> two candidate 3D chords.
# `paper` follows §2.2.3 (pairs -> candidate planes -> elimination -> progressive
# refit with the 0.1 % rule); `global` picks, over all 2^n choices, the chords that
# best fit one plane; `ml` refines `global` jointly on image residuals (refine.py).
#
# Noise model behind every tolerance (stated once, used by both solvers)
# ----------------------------------------------------------------------
# With isotropic image noise sigma (px) on M rim points and K stripe points of a
# disc of radius r at depth z, tilted by theta from the line of sight, focal length
# f (px), the candidate chord is displaced from its true line mainly through the
# error of the target plane:
#   - depth (scale) error from the apparent radius rho = f r / z:
#       dz ~ z sigma sqrt(2/M) / rho = (z/f) sigma sqrt(2/M) (z/r)
#   - normal error from the axis ratio b/a = cos(theta):
#       dtheta ~ 2 sigma / (rho sqrt(M) sin(theta)), i.e. an offset at the rim of
#       r dtheta / cos(theta) ~ (z/f) sigma sqrt(2/M) sqrt(2) / (sin(theta) cos(theta))
#   - the stripe points' own scatter averaged along the chord: (z/f) sigma / sqrt(K)
# so the chord's RMS offset from the light plane is about
#       tau_i = sigma (z_i/f) sqrt( (2/M_i) [ (z_i/r)^2 + 2 / (sin^2 theta_i cos^2 theta_i) ] + 1/K_i )
# (an upper bound: the factor |n_light . line of sight| <= 1 is dropped because the
# light plane is unknown when tau is needed).  Tests are "normalised": a chord's
# mean-squared distance to a plane divided by tau_i^2 (a chi^2-like number).
# `_KAPPA` (5) is the tolerance in units of tau: a true chord exceeds it with
# negligible probability (Monte Carlo, tests/test_plane_solvers.py: true chords give
# msd/tau^2 ~0.6 on average, < 4 at worst), a wrong chord is typically > 20 tau away
# at 0.2 px (msd/tau^2 > 500) and > 7 tau at 1 px (default geometry).


_KAPPA = 5.0
_TAU_FLOOR_REL = 1e-9  # tau >= 1e-9 * z: rounding of noise-free data (~1e-11 mm) stays below it


@_dataclass(frozen=True)
class PlacementResult:
    """What one target placement contributed.

    Attributes
    ----------
    index : int
        Position in the input lists.
    used : bool
        Whether its chord entered the final plane.
    reason : str
        Why it was used or rejected (both chords fit, neither fits, too few stripe points...).
    candidate : int or None
        Which of the two :func:`~lightplane.plane.circle_pose.circle_poses` solutions was chosen (0/1).
    pose : CirclePose or None
        The chosen (for ``ml``: refined) pose.
    poses : (CirclePose, CirclePose) or None
        Both solutions from the ellipse.
    n_rim, n_stripe : int
        Rim points given; stripe points kept (inliers of the stripe's line).
    rim_rms_px : float
        RMS distance of rim points to the fitted ellipse (or, for ``ml``, to the projected circle), px.
    stripe_rms_px : float
        RMS distance of stripe points to their fitted image line (``ml``: to the projected chord), px.
    chord_rms_mm : float
        RMS distance of the chosen chord's 3D points to the final plane, mm (NaN if unused).
    stripe_inliers : (K,) bool or None
        Which of the stripe points given were kept (on the stripe's line): the points the
        solver used (for the joint refinement, :mod:`lightplane.plane.joint`).
    """

    index: int
    used: bool
    reason: str
    candidate: int | None
    pose: CirclePose | None
    poses: tuple[CirclePose, CirclePose] | None
    n_rim: int
    n_stripe: int
    rim_rms_px: float
    stripe_rms_px: float
    chord_rms_mm: float
    stripe_inliers: np.ndarray | None = _field(default=None, repr=False, compare=False)

    def to_dict(self) -> dict:
        return {
            "index": self.index,
            "used": self.used,
            "reason": self.reason,
            "candidate": self.candidate,
            "pose": None if self.pose is None else self.pose.to_dict(),
            "n_rim": self.n_rim,
            "n_stripe": self.n_stripe,
            "rim_rms_px": _finite_or_none(self.rim_rms_px),
            "stripe_rms_px": _finite_or_none(self.stripe_rms_px),
            "chord_rms_mm": _finite_or_none(self.chord_rms_mm),
        }


@_dataclass(frozen=True)
class Ambiguity:
    """How clearly the chosen chords beat the next-best choice (``global`` method).

    ``best_cost`` and ``second_cost`` are normalised plane-fit costs
    ``J = Σ_i msd_i / tau_i²`` (dimensionless; see the noise model above) of the best
    and second-best assignment over the decided placements; ``ratio = second / best``;
    ``separated`` when ``second_cost - best_cost > κ²`` (κ = 5: the runner-up is worse
    by more than a 5-sigma chord).
    """

    best_cost: float
    second_cost: float
    ratio: float
    separated: bool
    message: str

    def to_dict(self) -> dict:
        return {
            "best_cost": _finite_or_none(self.best_cost),
            "second_cost": _finite_or_none(self.second_cost),
            "ratio": _finite_or_none(self.ratio),
            "separated": self.separated,
            "message": self.message,
        }


@_dataclass(frozen=True)
class PlaneCalibration:
    """Result of :func:`calibrate_plane_from_points` (and of ``calibrate_plane`` on images).

    Attributes
    ----------
    plane : LightPlane
    covariance : (4, 4) or None
        Covariance of ``(a, b, c, d)`` (``ml`` only).
    sigma_px : float
        Image noise sigma (px) estimated from the residuals: for ``paper``/``global``
        pooled over the rim-ellipse and stripe-line fits, for ``ml`` from the joint fit.
        (A ``sigma_px`` passed in is used for the tolerances and kept in ``plane.meta``.)
    placements : tuple of PlacementResult
    method : str
        ``paper``, ``global`` or ``ml``.
    ambiguity : Ambiguity or None
    warnings : tuple of str
    iterations : int
        Paper: placements processed; global: assignments evaluated; ml: solver evaluations.
    """

    plane: LightPlane
    covariance: np.ndarray | None
    sigma_px: float
    placements: tuple
    method: str
    ambiguity: Ambiguity | None
    warnings: tuple
    iterations: int

    @property
    def n_used(self) -> int:
        return sum(p.used for p in self.placements)

    def to_dict(self) -> dict:
        """JSON-ready summary (the plane file's diagnostics)."""
        return {
            "method": self.method,
            "normal": self.plane.normal.tolist(),
            "d": self.plane.d,
            "covariance": None if self.covariance is None else np.asarray(self.covariance).tolist(),
            "sigma_px": _finite_or_none(self.sigma_px),
            "n_used": self.n_used,
            "ambiguity": None if self.ambiguity is None else self.ambiguity.to_dict(),
            "warnings": list(self.warnings),
            "iterations": self.iterations,
            "noise_model": self.plane.meta.get("noise_model"),
            "images": [p.to_dict() for p in self.placements],
        }


def _finite_or_none(x) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None


# ------------------------------------------------------------------- geometry helpers


def _stripe_line(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The stripe's line through (K, 2) undistorted pixels: :func:`lightplane.core.geometry.robust_line`
    (a total-least-squares fit, refitted 3 times on the points within 4 robust sigmas, the upper
    median of the absolute distances, the band never below 1e-9 of the coordinates).

    Returns ``(point (2,), unit normal (2,), inlier mask (K,))``; for fewer than 2 points their
    mean (NaN for none), (1, 0) and all points.
    """
    if len(p) < 2:
        return (p.mean(axis=0) if len(p) else np.full(2, np.nan)), np.array([1.0, 0.0]), np.ones(len(p), bool)
    c, _, nrm, inl = robust_line(p, refits=4, k_mad=4.0, rel_tol=1e-9, upper_median=True)
    return c, nrm, inl


@_dataclass(frozen=True)
class PlacementCandidates:
    """One placement prepared for the solvers: both poses and both candidate chords.

    ``chords[k]`` (K, 3) mm: the stripe inliers back-projected onto candidate k's plane;
    ``tau_unit_mm[k]``: the chord offset scale tau_i (module notes) for sigma = 1 px;
    ``rim_res2``/``stripe_res2``: sums of squared residuals (px²) with their degrees of
    freedom, for the noise estimate.
    """

    index: int
    poses: tuple
    chords: tuple
    stripe_xy: np.ndarray
    stripe_inliers: np.ndarray
    n_rim: int
    rim_rms_px: float
    stripe_rms_px: float
    rim_res2: float
    rim_dof: int
    stripe_res2: float
    stripe_dof: int
    tau_unit_mm: tuple
    usable: bool
    reason: str

    @cached_property
    def chord_ends(self) -> tuple:
        """Per candidate chord, its two ends and their midpoint (3, 3) (:func:`_chord_ends`), computed once
        (the paper method's tests ask for them again and again)."""
        return tuple(_chord_ends(ch) for ch in self.chords)


def _tau_unit(pose, f_px: float, n_rim: int, n_stripe: int) -> float:
    """tau_i for sigma = 1 px (see the module notes), mm."""
    C, N, r = pose.center, pose.normal, pose.radius_mm
    z = float(np.linalg.norm(C))
    cos_t = float(np.clip(-N @ C / z, 0.05, 1.0))
    sin_t = float(np.sqrt(max(1.0 - cos_t**2, 0.05**2)))
    return (z / f_px) * np.sqrt((2.0 / n_rim) * ((z / r) ** 2 + 2.0 / (sin_t * cos_t) ** 2) + 1.0 / n_stripe)


def prepare_placement(camera, radius_mm: float, rim_uv, stripe_uv, index: int,
                      options: SolverOptions | None = None) -> PlacementCandidates:
    """Undistort, fit the rim's ellipse, get both poses and both candidate chords of one placement.

    Raises LightplaneError naming the placement for bad input (empty or too few rim
    points, NaN, rim points that are not an ellipse: farther than ``options.max_rim_rms_px``).
    Too few stripe points (fewer than ``options.min_stripe_points``) do not raise: the placement
    is returned with ``usable=False`` and the reason.  ``options``: :class:`SolverOptions`
    (defaults when omitted).
    """
    opts = SolverOptions() if options is None else options
    return _prepare_placement(camera, radius_mm, rim_uv, stripe_uv, index, opts, _Batched())


@_dataclass(frozen=True)
class _Batched:
    """What :func:`calibrate_plane_from_points` computed for all placements at once: the points
    undistorted (normalised), the rim's conic (undistorted px) and its two poses, or why there are
    none (None: computed by :func:`_prepare_placement` itself)."""

    rim_xy: np.ndarray | None = None
    stripe_xy: np.ndarray | None = None
    conic: np.ndarray | None = None
    poses: tuple | None = None
    pose_problem: str | None = None


@_dataclass(frozen=True)
class _RimPart:
    """One placement's rim: its two poses, point count, residuals to its ellipse and the focal length."""

    poses: tuple
    n_rim: int
    rim_rms_px: float
    rim_res2: float
    rim_dof: int
    f_px: float


def _prepare_placement(camera, radius_mm: float, rim_uv, stripe_uv, index: int, opts: SolverOptions,
                       pre: _Batched) -> PlacementCandidates:
    """:func:`prepare_placement` with what was computed in a batch (``pre``)."""
    name = f"placement {index}"
    rim = as_points(rim_uv, 2, f"{name}: rim points")
    st = as_points(stripe_uv, 2, f"{name}: stripe points")
    if len(rim) < 5:
        raise LightplaneError(f"{name}: needs at least 5 rim points, got {len(rim)}")
    if not np.all(np.isfinite(rim)):
        raise LightplaneError(f"{name}: rim points contain NaN or infinite values")
    if not np.all(np.isfinite(st)):
        raise LightplaneError(f"{name}: stripe points contain NaN or infinite values")
    rp = _rim_part(camera, radius_mm, rim, name, opts.max_rim_rms_px, pre)
    return _stripe_part(camera, st, index, rp, opts.min_stripe_points, pre.stripe_xy)


def _rim_part(camera, radius_mm: float, rim: np.ndarray, name: str, max_rim_rms_px: float, pre: _Batched) -> _RimPart:
    """The rim's ellipse (its residuals checked against ``max_rim_rms_px``) and its two poses."""
    rim_xy = pre.rim_xy if pre.rim_xy is not None else camera.undistort_points(rim, normalized=True)
    rim_und = camera.normalized_to_pixels(rim_xy, distort=False)
    if not np.all(np.isfinite(rim_und)):
        raise LightplaneError(f"{name}: some rim points cannot be undistorted (outside the lens model)")
    conic = pre.conic if pre.conic is not None else fit_rim_conic(rim_und, name=f"{name}: rim points")
    res = sampson_distance(conic, rim_und)  # px
    rim_rms = float(np.sqrt(np.mean(res**2)))
    if not np.isfinite(rim_rms) or rim_rms > max_rim_rms_px:
        raise LightplaneError(
            f"{name}: the rim points are not an ellipse (RMS distance to the best ellipse {rim_rms:.3g} px "
            f"> {max_rim_rms_px} px)"
        )
    if pre.pose_problem is not None:
        raise LightplaneError(f"{name}: conic {pre.pose_problem}")
    poses = pre.poses
    if poses is None:
        try:
            poses = circle_poses(conic, camera.K, radius_mm)
        except LightplaneError as e:
            raise LightplaneError(f"{name}: {e}") from None
    return _RimPart(poses, len(rim), rim_rms, float(np.sum(res**2)), max(len(rim) - 5, 0),
                    float(np.sqrt(camera.fx * camera.fy)))


def _stripe_part(camera, st: np.ndarray, index: int, rp: _RimPart, min_stripe_points: int,
                 stripe_xy: np.ndarray | None) -> PlacementCandidates:
    """The stripe's line (robust, undistorted px) and both candidate chords, or why the placement is unusable."""
    empty = (np.zeros((0, 3)), np.zeros((0, 3)))
    # the rim's part is common to every outcome
    out = PlacementCandidates(index=index, poses=rp.poses, chords=empty, stripe_xy=np.zeros((0, 2)),
                              stripe_inliers=np.zeros(len(st), bool), n_rim=rp.n_rim, rim_rms_px=rp.rim_rms_px,
                              stripe_rms_px=np.nan, rim_res2=rp.rim_res2, rim_dof=rp.rim_dof, stripe_res2=0.0,
                              stripe_dof=0, tau_unit_mm=(np.nan, np.nan), usable=False, reason="")
    if len(st) < min_stripe_points:
        return _replace(out, reason=f"too few stripe points ({len(st)} < {min_stripe_points})")
    if stripe_xy is None:
        stripe_xy = camera.undistort_points(st, normalized=True)
    st_und = camera.normalized_to_pixels(stripe_xy, distort=False)
    ok = np.all(np.isfinite(st_und), axis=1)
    # the chord is a straight line in undistorted pixels: robust line fit, residuals -> noise
    c2, n2, inl = _stripe_line(st_und[ok])
    inliers = np.zeros(len(st), bool)
    inliers[np.flatnonzero(ok)[inl]] = True
    r2 = (st_und[inliers] - c2) @ n2
    n_in = int(inliers.sum())
    st_rms = float(np.sqrt(np.mean(r2**2))) if n_in else np.nan
    out = _replace(out, stripe_inliers=inliers, stripe_rms_px=st_rms, stripe_res2=float(np.sum(r2**2)),
                   stripe_dof=max(n_in - 2, 0))
    if n_in < min_stripe_points:
        return _replace(out, reason=f"too few stripe points on a line ({n_in} < {min_stripe_points})")
    xy = stripe_xy[inliers]
    chords = tuple(ray_plane(xy, p.normal, p.center) for p in rp.poses)
    if any(not np.all(np.isfinite(ch)) for ch in chords):
        return _replace(out, stripe_xy=xy, reason="stripe rays graze a candidate target plane")
    taus = tuple(_tau_unit(p, rp.f_px, rp.n_rim, n_in) for p in rp.poses)
    return _replace(out, chords=chords, stripe_xy=xy, tau_unit_mm=taus, usable=True, reason="")


def estimate_sigma_px(cands: Sequence[PlacementCandidates]) -> float:
    """Pooled noise estimate (px): rim residuals to their ellipses (M - 5 dof each) and
    stripe residuals to their image lines (K - 2 dof each)."""
    ss = sum(c.rim_res2 + c.stripe_res2 for c in cands)
    dof = sum(c.rim_dof + c.stripe_dof for c in cands)
    return float(np.sqrt(ss / dof)) if dof > 0 else float("nan")


def _tau(c: PlacementCandidates, k: int, sigma_px: float) -> float:
    z = float(np.linalg.norm(c.poses[k].center))
    return max(sigma_px * c.tau_unit_mm[k], _TAU_FLOOR_REL * z)


def _msd(points: np.ndarray, n: np.ndarray, d: float) -> float:
    """Mean squared distance (mm²) of (K, 3) points to the plane ``n·x + d = 0``."""
    r = points @ n + d
    return float(np.mean(r * r))


#: the upper triangle of a 3x3 matrix, row by row (the order of the moments' second-order entries)
_IU3 = np.triu_indices(3)


def _moments(points: np.ndarray, w: float, ref: np.ndarray) -> np.ndarray:
    """(10,) weighted moments ``[Σw, Σw p (3), Σw p pᵀ (xx, xy, xz, yy, yz, zz)]`` about ``ref``."""
    q = points - ref
    s1 = w * q.sum(axis=0)
    S2 = w * (q.T @ q)
    return np.concatenate([[w * len(q)], s1, S2[_IU3]])


def _cost_from_moments(M: np.ndarray) -> np.ndarray:
    """Smallest eigenvalue of the centred scatter for (..., 10) moments (the weighted plane-fit cost).

    Closed form for symmetric 3x3 matrices (trigonometric solution of the
    characteristic cubic), vectorised: ~20x faster than batched ``eigvalsh``; its
    absolute error ~1e-16 of the largest eigenvalue is far below the cost gaps that
    matter here.
    """
    m0 = M[..., 0]
    m1 = M[..., 1:4] / m0[..., None]
    xx = M[..., 4] - m0 * m1[..., 0] * m1[..., 0]
    xy = M[..., 5] - m0 * m1[..., 0] * m1[..., 1]
    xz = M[..., 6] - m0 * m1[..., 0] * m1[..., 2]
    yy = M[..., 7] - m0 * m1[..., 1] * m1[..., 1]
    yz = M[..., 8] - m0 * m1[..., 1] * m1[..., 2]
    zz = M[..., 9] - m0 * m1[..., 2] * m1[..., 2]
    q = (xx + yy + zz) / 3.0
    a, b, c = xx - q, yy - q, zz - q
    p1 = xy * xy + xz * xz + yz * yz
    p = np.sqrt((a * a + b * b + c * c + 2.0 * p1) / 6.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        det = a * (b * c - yz * yz) - xy * (xy * c - yz * xz) + xz * (xy * yz - b * xz)
        r = np.where(p > 0, det / (2.0 * p**3), 0.0)
    phi = np.arccos(np.clip(r, -1.0, 1.0)) / 3.0
    lam_min = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    return np.maximum(lam_min, 0.0)


def _fit_assignment(cands, idx, choice, sigma_px, weighted=True):
    """Plane through the chosen chords: weights 1/(K_i tau_i²) (global) or 1 (paper)."""
    pts, ws = [], []
    for i, k in zip(idx, choice):
        ch = cands[i].chords[k]
        pts.append(ch)
        w = 1.0 / (len(ch) * _tau(cands[i], k, sigma_px) ** 2) if weighted else 1.0
        ws.append(np.full(len(ch), w))
    P = np.concatenate(pts)
    W = np.concatenate(ws)
    W = W / W.max()
    n, d, _ = fit_plane_tls(P, W)
    return n, d


@_dataclass(frozen=True)
class _GlobalOutcome:
    normal: np.ndarray
    d: float
    choice: dict            # placement index -> candidate
    decided: dict           # placement index -> bool
    flip_cost: dict         # placement index -> ΔJ of flipping it
    ambiguity: Ambiguity
    evaluated: int
    normal_all: np.ndarray  # plane of the best assignment over all placements, undecided included
    d_all: float


def _plane_from_moments(M: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, float]:
    """Weighted least-squares plane ``(normal, d)`` (camera frame) from (10,) moments about ``ref``
    (:func:`_moments`): the scatter's smallest eigenvector, as :func:`lightplane.core.geometry.plane_scatter`
    finds it from the points (here from their sums, which the search adds up by the thousand)."""
    c = M[1:4] / M[0]
    S = np.zeros((3, 3))
    S[_IU3] = M[4:]
    S = S + np.triu(S, 1).T - M[0] * np.outer(c, c)
    n = np.linalg.eigh(S)[1][:, 0]
    return n, -float(n @ (c + ref))


class _ChordMoments:
    """Weighted moments of every candidate chord, about a common reference point.

    Chord (j, k) (j-th placement of ``idx``, candidate k) has point weights
    ``w = 1 / (K tau²)``, so its weighted sum of squared distances to a plane is its
    normalised cost ``msd / tau²``.  Every plane fit and cost of the global search is
    computed from these (10,) vectors, never from the points again.
    """

    def __init__(self, cands, idx, sigma_px):
        self.idx = list(idx)
        self.ref = np.mean([cands[i].chords[0].mean(axis=0) for i in self.idx], axis=0)  # conditioning
        self.mom = np.zeros((len(self.idx), 2, 10))
        for j, i in enumerate(self.idx):
            for k in (0, 1):
                ch = cands[i].chords[k]
                self.mom[j, k] = _moments(ch, 1.0 / (len(ch) * _tau(cands[i], k, sigma_px) ** 2), self.ref)

    def total(self, bits: np.ndarray) -> np.ndarray:
        """Summed moments (..., 10) for assignments ``bits`` (..., n) in {0, 1}."""
        m = self.mom
        return m[:, 0].sum(axis=0) + np.asarray(bits, dtype=np.float64) @ (m[:, 1] - m[:, 0])

    def plane(self, bits) -> tuple[np.ndarray, float]:
        """Weighted LS plane ``(normal, d)`` (camera frame) of an assignment."""
        return _plane_from_moments(self.total(bits), self.ref)

    def chord_costs(self, n: np.ndarray, d: float) -> np.ndarray:
        """(n, 2) normalised cost ``msd/tau²`` of every candidate chord w.r.t. the plane ``(n, d)``."""
        dr = d + float(n @ self.ref)  # the plane in reference coordinates
        iu = _IU3
        nn = np.outer(n, n)
        nn = (2.0 * nn - np.diag(np.diag(nn)))[iu]  # coefficients of the upper-triangle entries
        m = self.mom
        return m[..., 4:] @ nn + 2.0 * dr * (m[..., 1:4] @ n) + dr * dr * m[..., 0]


def _solve_global(cands, idx, sigma_px, *, max_exhaustive: int = 16, rng=None, n_samples: int = 400) -> _GlobalOutcome:
    """Order-independent choice of one chord per placement (docs/method.md §Global disambiguation, beyond the paper).

    Minimises ``J = Σ_i msd_i / tau_i²`` (the weighted plane-fit cost of the chosen
    chords; tau from the module's noise model) over all 2^n choices: exhaustively
    (one vectorised pass over the moment sums; closed-form 3x3 eigenvalue) up to
    ``max_exhaustive`` placements, beyond that by sampling pairs of chords, assigning
    every placement its closer chord and refitting (twice).  A placement whose flip
    raises J by no more than κ² is "undecided" (both chords fit) and left out.  The
    ambiguity record compares the best and the runner-up assignment over the decided
    placements.
    """
    idx = list(idx)
    n = len(idx)
    cm = _ChordMoments(cands, idx, sigma_px)
    kappa2 = _KAPPA**2
    if n <= max_exhaustive:
        bits_all = (np.arange(2**n)[:, None] >> np.arange(n)[None, :]) & 1
        J = _cost_from_moments(cm.total(bits_all))
        best = int(np.argmin(J))
        bits = bits_all[best]
        flip = {i: float(J[best ^ (1 << j)] - J[best]) for j, i in enumerate(idx)}
        evaluated = len(J)
    else:
        bits, evaluated = _sample_assignment(cm, rng, n_samples)
        J0 = float(_cost_from_moments(cm.total(bits)))
        flips = np.tile(bits, (n, 1))
        flips[np.arange(n), np.arange(n)] ^= 1
        Jf = _cost_from_moments(cm.total(flips))
        flip = {i: float(Jf[j] - J0) for j, i in enumerate(idx)}
    choice = {i: int(bits[j]) for j, i in enumerate(idx)}
    decided = {i: flip[i] > kappa2 for i in idx}
    dec_pos = [j for j, i in enumerate(idx) if decided[i]]
    if len(dec_pos) == n:
        cm_dec = cm
        normal, d = cm.plane(bits)
    elif len(dec_pos) >= 3:
        cm_dec = _ChordMoments(cands, [idx[j] for j in dec_pos], sigma_px)
        normal, d = cm_dec.plane(bits[dec_pos])
    else:
        cm_dec = None
        normal, d = cm.plane(bits)
    # ambiguity over the decided placements: best vs runner-up assignment
    if len(dec_pos) == n and n <= max_exhaustive:
        b1 = float(J[best])
        b2 = float(np.partition(J, 1)[1]) if len(J) > 1 else float("inf")
    elif cm_dec is not None and len(dec_pos) <= max_exhaustive:
        nd = len(dec_pos)
        Jd = _cost_from_moments(cm_dec.total((np.arange(2**nd)[:, None] >> np.arange(nd)[None, :]) & 1))
        part = np.partition(Jd, 1)
        b1, b2 = float(part[0]), float(part[1])
        evaluated += len(Jd)
    elif cm_dec is not None:
        b1 = float(_cost_from_moments(cm_dec.total(bits[dec_pos])))
        b2 = b1 + min(flip[idx[j]] for j in dec_pos)
    else:
        b1, b2 = float("nan"), float("nan")
    sep = bool(np.isfinite(b2) and (b2 - b1) > kappa2)
    ratio = b2 / b1 if b1 > 0 else float("inf")
    msg = (f"best normalised cost {b1:.3g}, runner-up {b2:.3g} (ratio {ratio:.3g}); "
           + ("clearly separated" if sep else f"NOT clearly separated (difference {b2 - b1:.3g} <= {kappa2:g})"))
    n_all, d_all = cm.plane(bits)
    return _GlobalOutcome(normal, d, choice, decided, flip, Ambiguity(b1, b2, float(ratio), sep, msg), evaluated,
                          n_all, d_all)


def _sample_assignment(cm: _ChordMoments, rng, n_samples: int) -> tuple[np.ndarray, int]:
    """Beyond exhaustive search: planes from pairs of chords, each placement assigned its
    closer chord, refit, reassigned (twice); the lowest-cost assignment."""
    rng = np.random.default_rng(0) if rng is None else rng
    n = len(cm.idx)
    pairs = [(a, b) for a in range(n) for b in range(a + 1, n)]
    if len(pairs) * 4 > n_samples:
        sel = rng.choice(len(pairs), size=max(n_samples // 4, 1), replace=False)
        pairs = [pairs[s] for s in sel]
    best, best_J, evaluated = None, np.inf, 0
    for a, b in pairs:
        for ka in (0, 1):
            for kb in (0, 1):
                sub = np.zeros(n, dtype=np.int64)
                sub[a], sub[b] = ka, kb
                # plane of the pair alone: moments of the two chords only
                nrm, d = _plane_from_moments(cm.mom[a, ka] + cm.mom[b, kb], cm.ref)
                for _ in range(3):
                    bits = np.argmin(cm.chord_costs(nrm, d), axis=1)
                    nrm, d = cm.plane(bits)
                J = float(_cost_from_moments(cm.total(bits)))
                evaluated += 1
                if J < best_J:
                    best, best_J = bits.copy(), J
    if best is None:
        raise LightplaneError("global method: no assignment of the chords has a finite cost")
    return best, evaluated


# ------------------------------------------------------------------------ paper
@_dataclass(frozen=True)
class _PaperOutcome:
    normal: np.ndarray
    d: float
    choice: dict      # placement index -> candidate (used placements)
    reasons: dict     # placement index -> reason (all usable placements)
    processed: int
    notes: tuple = ()


def _chord_ends(ch: np.ndarray) -> np.ndarray:
    """(3, 3): the two extreme points of a chord's (K, 3) points along its direction, and their midpoint."""
    c = ch.mean(axis=0)
    q = ch - c
    u = np.linalg.eigh(q.T @ q)[1][:, -1]
    t = q @ u
    e0, e1 = c + t.min() * u, c + t.max() * u
    return np.stack([e0, 0.5 * (e0 + e1), e1])


def _plane_offset_var(cands, support, n, points: np.ndarray, sigma_px) -> float:
    """Predicted variance (mm²) of the offset of a plane fitted to the chords ``support``,
    averaged over ``points`` (3, 3) (ends and middle of the chord under test).

    Each support chord is modelled by its two ends, each with an independent offset
    error of variance ``2 tau_j²`` (a rigid chord error: offset and tilt), so the plane
    ``w = α + β x + γ y`` (plane-local coordinates) has covariance ``(Aᵀ W A)⁻¹`` and
    the variance at a point is ``aᵀ Cov a``.  This accounts for extrapolation: a plane
    from two nearby chords is poorly known far from them.
    """
    e1 = np.cross(n, np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0]))
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    ends = [(cands[i].chord_ends[k][[0, 2]], 1.0 / (2.0 * _tau(cands[i], k, sigma_px) ** 2))
            for i, k in support]
    P = np.concatenate([e for e, _ in ends])
    w = np.repeat([wt for _, wt in ends], 2)
    o = P.mean(axis=0)
    A = np.column_stack([np.ones(len(P)), (P - o) @ e1, (P - o) @ e2])
    Nm = A.T @ (A * w[:, None])
    try:
        cov = np.linalg.inv(Nm)
    except np.linalg.LinAlgError:
        return float("inf")
    T = np.column_stack([np.ones(len(points)), (points - o) @ e1, (points - o) @ e2])
    return float(np.mean(np.einsum("ij,jk,ik->i", T, cov, T)))


def _lies_on(cands, i, k, n, d, support, sigma_px) -> bool:
    """Chord k of placement i lies on the plane ``(n, d)`` fitted to ``support``:
    ``msd <= κ² (tau_i² + var_plane)``, ``var_plane`` from :func:`_plane_offset_var`."""
    ch = cands[i].chords[k]
    var_plane = _plane_offset_var(cands, support, n, cands[i].chord_ends[k], sigma_px)
    return _msd(ch, n, d) <= _KAPPA**2 * (_tau(cands[i], k, sigma_px) ** 2 + var_plane)


def _solve_paper(cands, idx, sigma_px, *, rel_change: float = 1e-3, strict: bool = True) -> _PaperOutcome:
    """Paper §2.2.3 in input order.

    Initial determination: the first two usable placements give four chords; a pair
    (one chord of each) is *coplanar* when, for the plane fitted to both,
    ``Σ msd_j / tau_j² <= κ²``.  Each later placement keeps the candidate planes on
    which one of its chords *lies* (``msd <= κ² (tau_i² + var_plane)``, ``var_plane``
    the fitted plane's predicted offset variance at that chord, see
    :func:`_plane_offset_var`); a placement that fits no candidate is
    rejected ("neither chord fits"), one whose chords both fit a candidate supports it
    without a chord.  If no pair of the first two is coplanar, the second is replaced
    by the next placement.  When one candidate is left, the progressive refinement adds
    the unambiguous chords of the placements seen so far and then of each further
    placement (one chord fits: added and refit; both or neither: rejected with that
    reason), stopping when ``‖Δ(a, b, c, d)‖ / ‖(a, b, c, d)‖ < 0.1 %`` (the paper's
    rule) or the placements run out.  Plain (unweighted) least squares, as the paper.

    ``strict=False`` (simulation studies): instead of giving up, the lowest-cost pair
    is taken when no pair is coplanar, and the best-supported, lowest-cost candidate
    when several different ones survive; ``notes`` says so.
    """
    idx = list(idx)
    reasons: dict = {}
    notes: list = []
    if len(idx) < 2:
        raise LightplaneError("paper method: fewer than 2 usable placements")
    rest = idx[1:]  # the placements not yet seen, in order (the steps below take them from the front)
    cand_planes = _initial_planes(cands, idx[0], rest, sigma_px, strict, reasons, notes)
    cand_planes, seen = _eliminate_planes(cands, cand_planes, rest, sigma_px, reasons)
    if len(cand_planes) > 1:
        cand_planes = [_one_candidate_plane(cands, cand_planes, sigma_px, strict, notes)]
    support, n_, d_, refined = _refine_progressively(cands, cand_planes[0], rest, sigma_px, rel_change, reasons)
    choice = dict(support)
    for i, _ in support:
        reasons.setdefault(i, "used")
    return _PaperOutcome(n_, d_, choice, reasons, 2 + seen + refined, tuple(notes))


def _initial_planes(cands, first, rest: list, sigma_px, strict: bool, reasons: dict, notes: list) -> list:
    """Initial determination (:func:`_solve_paper`): the candidate planes through a coplanar pair of chords
    of ``first`` and of the next placement taken from ``rest``, the next one again while none is coplanar.
    Each candidate: ``dict(n, d, support=[(i, k)], pending=[i], cost)``."""
    cand_planes: list = []
    best_pair = None
    while rest and not cand_planes:
        second = rest.pop(0)
        for k1 in (0, 1):
            for k2 in (0, 1):
                sup = [(first, k1), (second, k2)]
                n_, d_ = _fit_assignment(cands, [first, second], [k1, k2], sigma_px, weighted=False)
                J = sum(_msd(cands[i].chords[k], n_, d_) / _tau(cands[i], k, sigma_px) ** 2 for i, k in sup)
                cp = {"n": n_, "d": d_, "support": sup, "pending": [], "cost": J}
                if J <= _KAPPA**2:
                    cand_planes.append(cp)
                if best_pair is None or J < best_pair["cost"]:
                    best_pair = cp
        if not cand_planes:
            assert best_pair is not None  # set by the first pair tried
            if not strict:
                cand_planes = [best_pair]
                notes.append(f"no coplanar pair of chords (best normalised cost {best_pair['cost']:.3g} > "
                             f"{_KAPPA**2:g}); the lowest-cost pair was taken")
                break
            reasons[second] = f"rejected: no chord coplanar with a chord of placement {first}"
    if not cand_planes:
        raise LightplaneError(f"paper method: no chord of any placement is coplanar with a chord of placement {first}")
    return cand_planes


def _eliminate_planes(cands, cand_planes: list, rest: list, sigma_px, reasons: dict) -> tuple[list, int]:
    """Steps 3/4 (:func:`_solve_paper`): the placements taken from ``rest`` keep the candidate planes one of
    their chords lies on, until one is left.  Returns the survivors and the placements seen."""
    seen = 0
    while len(cand_planes) > 1 and rest:
        i = rest.pop(0)
        seen += 1
        survivors = []
        for cp in cand_planes:
            fits = [_lies_on(cands, i, k, cp["n"], cp["d"], cp["support"], sigma_px) for k in (0, 1)]
            if fits[0] and fits[1]:
                cp["pending"].append(i)
                survivors.append(cp)
            elif fits[0] or fits[1]:
                cp["support"].append((i, 0 if fits[0] else 1))
                survivors.append(cp)
        if survivors:
            cand_planes = survivors
        else:
            reasons[i] = "rejected: neither chord lies on any candidate plane"
    return cand_planes, seen


def _one_candidate_plane(cands, cand_planes: list, sigma_px, strict: bool, notes: list) -> dict:
    """Several candidate planes survive all placements.  They are the same plane in practice when each one's
    support chords lie on the best-supported one (e.g. a face-on first placement whose two chords nearly
    coincide); otherwise the ambiguity is real: an error, or with ``strict=False`` the best-supported,
    lowest-cost candidate."""
    cand_planes.sort(key=lambda cp: -len(cp["support"]))
    best = cand_planes[0]
    for other in cand_planes[1:]:
        if not all(_lies_on(cands, i, k, best["n"], best["d"], best["support"], sigma_px)
                   for i, k in other["support"]):
            if not strict:
                top = [cp for cp in cand_planes if len(cp["support"]) == len(best["support"])]
                for cp in top:
                    cp["cost"] = sum(_msd(cands[i].chords[k], cp["n"], cp["d"]) / _tau(cands[i], k, sigma_px) ** 2
                                     for i, k in cp["support"])
                best = min(top, key=lambda cp: cp["cost"])
                notes.append(f"{len(cand_planes)} different candidate planes remained; the best-supported, "
                             "lowest-cost one was taken (ambiguous)")
                break
            raise LightplaneError(
                f"paper method: {len(cand_planes)} different candidate light planes remain after all placements: "
                "the placements cannot resolve the ambiguity (add placements with different tilts)"
            )
    return best


def _refine_progressively(cands, cp: dict, rest: list, sigma_px, rel_change: float,
                          reasons: dict) -> tuple[list, np.ndarray, float, int]:
    """The progressive refinement (:func:`_solve_paper`) of the candidate plane ``cp``: first the placements
    seen during elimination that were ambiguous, then those of ``rest``; each one whose chord alone lies on
    the plane is added and the plane refitted, until it changes by less than ``rel_change``.
    Returns ``(support [(i, k)], normal, d, placements processed)``."""
    support = list(cp["support"])
    n_, d_ = cp["n"], cp["d"]
    queue = list(cp["pending"]) + rest
    sup_idx = [i for i, _ in support]
    sup_ch = [k for _, k in support]
    if len(support) > 2:
        n_, d_ = _fit_assignment(cands, sup_idx, sup_ch, sigma_px, weighted=False)
    converged = False
    processed = 0
    for i in queue:
        if converged:
            reasons[i] = "not used: the plane had converged (change < 0.1 %)"
            continue
        processed += 1
        fits = [_lies_on(cands, i, k, n_, d_, support, sigma_px) for k in (0, 1)]
        if fits[0] and fits[1]:
            reasons[i] = "rejected: both chords lie on the plane (ambiguous)"
            continue
        if not (fits[0] or fits[1]):
            reasons[i] = "rejected: neither chord lies on the plane"
            continue
        k = 0 if fits[0] else 1
        support.append((i, k))
        sup_idx.append(i)
        sup_ch.append(k)
        n_new, d_new = _fit_assignment(cands, sup_idx, sup_ch, sigma_px, weighted=False)
        if n_new @ n_ < 0:
            n_new, d_new = -n_new, -d_new
        old = np.append(n_, d_)
        change = np.linalg.norm(np.append(n_new, d_new) - old) / np.linalg.norm(old)
        n_, d_ = n_new, d_new
        converged = bool(change < rel_change)
    return support, n_, d_, processed


# ------------------------------------------------------------------ public entry
def check_calibration_args(method: str, camera, diameter_mm) -> float:
    """Check the arguments every light-plane calibration shares; return the diameter (mm)."""
    if method not in ("ml", "global", "paper"):
        raise LightplaneError(f"method must be 'ml', 'global' or 'paper', got {method!r}")
    if not isinstance(camera, Camera):
        raise LightplaneError(f"camera must be a Camera, got {type(camera).__name__}")
    try:
        diameter = float(diameter_mm)
    except (TypeError, ValueError):
        raise LightplaneError(f"diameter_mm must be a number, got {diameter_mm!r}") from None
    if not (np.isfinite(diameter) and diameter > 0):
        raise LightplaneError(f"diameter_mm must be positive, got {diameter_mm}")
    return diameter


@_dataclass(frozen=True)
class SolverOptions:
    """Options of the plane solvers (:func:`calibrate_plane_from_points`).

    The defaults are what every command uses.  Checked on construction.

    - ``sigma_px``: image noise sigma (px) for the tolerances; estimated from the
      rim-ellipse and stripe-line residuals when None.
    - ``min_stripe_points``: placements with fewer stripe points (after the robust
      line fit) are rejected.
    - ``max_rim_rms_px``: rim points farther than this (RMS, px) from their best
      ellipse are "not an ellipse".
    - ``min_normal_spread_deg``: the chosen target normals must spread by more than
      this (max pairwise angle), or the two-fold ambiguity cannot be resolved.
    - ``max_exhaustive``: ``global``: exhaustive search up to this many placements,
      sampling beyond (random generator seeded with ``seed``).
    - ``strict``: True (default): undecided placements (both chords fit) are left
      out, an unresolvable ambiguity or placements too alike raise.  False (for
      simulation studies, e.g. the paper's two-placement runs): always return the
      lowest-cost answer, undecided placements included, with warnings saying what
      was ambiguous.
    - ``paper_rel_change``: ``paper``: the stopping rule, relative change of
      ``(a, b, c, d)`` (the paper's 0.1 %).
    - ``ml`` (:class:`~lightplane.plane.ml.MLOptions`): ``ml``: options of
      :func:`lightplane.plane.ml.refine_ml` (``noise``, ``correlated``, ``huber_c``,
      ``rounds``, ``max_iter``, ``dispersion``).  The noise model it found (rim and stripe
      sigmas in px, their correlation factors along the curves, outliers, the images'
      dispersion and whether the covariance includes it) is kept in ``plane.meta["noise_model"]``.
    """

    sigma_px: float | None = None
    min_stripe_points: int = 10
    max_rim_rms_px: float = 3.0
    min_normal_spread_deg: float = 5.0
    max_exhaustive: int = 16
    strict: bool = True
    paper_rel_change: float = 1e-3
    seed: int = 0
    ml: MLOptions = _field(default_factory=MLOptions)

    def __post_init__(self):
        if self.sigma_px is not None and not (np.isfinite(self.sigma_px) and self.sigma_px >= 0):
            raise LightplaneError(f"sigma_px must be >= 0, got {self.sigma_px}")
        if not isinstance(self.ml, MLOptions):
            raise LightplaneError(f"ml must be MLOptions, got {type(self.ml).__name__}")


@with_blas_limited
def calibrate_plane_from_points(camera, diameter_mm: float, rims: Sequence[np.ndarray], stripes: Sequence[np.ndarray],
                                method: str = "ml", options: SolverOptions | None = None, *,
                                min_placements: int = 3) -> PlaneCalibration:
    """Calibrate the light plane from rim and stripe points of a circular target (paper §2.2, docs/method.md §Light plane).

    Parameters
    ----------
    camera : Camera
    diameter_mm : float
        Target diameter, mm, > 0.
    rims : list of (M_i, 2)
        Per placement, distorted pixel points on the target's rim (ellipse edge).
    stripes : list of (K_i, 2)
        Per placement, distorted pixel stripe centres on the target.
    method : ``"ml"`` (default), ``"global"`` or ``"paper"``
        ``paper``: §2.2.3's initial determination and progressive refinement (0.1 %
        rule; tolerances in :func:`_solve_paper`).  ``global``: order-independent
        choice of one chord per placement minimising the normalised plane-fit cost
        over all 2^n choices (exhaustive up to ``max_exhaustive`` placements, pair
        sampling with greedy assignment beyond).  ``ml``: ``global`` then the joint
        maximum-likelihood refinement (:func:`lightplane.plane.ml.refine_ml`) with covariance.
    options : SolverOptions, optional
        The solver's knobs (:class:`SolverOptions`, meanings there; defaults when omitted).
    min_placements : int
        Fewest usable placements accepted (default 3; >= 2).  Two are what the paper's
        §3 study uses: then only the coplanarity of the true pair of chords resolves
        the ambiguity, with no independent check.

    Tolerances (derived from the noise, see the notes above ``PlacementResult``):
    a candidate chord's expected RMS offset from the light plane is

        tau_i = sigma (z_i/f) sqrt((2/M_i) [(z_i/r)² + 2/(sin²θ_i cos²θ_i)] + 1/K_i)

    (M_i rim and K_i stripe points, disc radius r at depth z_i tilted by θ_i, f in
    px).  A chord *lies on* a plane when ``msd_i <= κ² (tau_i² + tau_plane²)``, two
    chords are *coplanar* when ``Σ msd_j / tau_j² <= κ²`` for the plane through both,
    (``tau_plane²``: the fitted plane's predicted offset variance at the chord,
    extrapolation included), and ``global`` calls a placement decided when flipping its chord raises the
    normalised cost ``J = Σ msd_i / tau_i²`` by more than κ²; κ = 5.  Checked by Monte
    Carlo: true chords give ``msd/tau²`` of ~0.6 on average and < 4 at worst, wrong
    ones > 50 at 1 px noise and > 500 at 0.2 px.

    Returns
    -------
    PlaneCalibration

    Raises
    ------
    LightplaneError
        Bad input (naming the placement), fewer than 3 usable placements, placements
        too alike, or an unresolvable ambiguity (paper method).
    """
    diameter = check_calibration_args(method, camera, diameter_mm)
    opts = SolverOptions() if options is None else options
    if not isinstance(opts, SolverOptions):
        raise LightplaneError(f"options must be SolverOptions, got {type(opts).__name__}")
    rims, stripes, min_placements = _checked_point_sets(rims, stripes, min_placements)
    r = 0.5 * diameter
    cands = _prepare_placements(camera, r, rims, stripes, opts)
    sigma_est = estimate_sigma_px(cands)
    sigma = float(opts.sigma_px) if opts.sigma_px is not None else sigma_est
    usable = [c.index for c in cands if c.usable]
    if len(usable) < min_placements:
        why = "; ".join(f"placement {c.index}: {c.reason}" for c in cands if not c.usable)
        raise LightplaneError(f"only {len(usable)} usable placements, need at least {min_placements} ({why})")
    ch = _choose_chords(cands, usable, sigma, method, opts)
    used = sorted(ch.choice)
    if len(used) < min_placements:
        why = "; ".join(f"placement {i}: {ch.reasons[i]}" for i in sorted(ch.reasons))
        raise LightplaneError(f"only {len(used)} placements could be used ({why}), need at least {min_placements}")
    warnings = list(ch.warnings) + _spread_warnings(cands, used, ch.choice, opts)
    fit = _Final(LightPlane(ch.normal, ch.d, meta={"method": method}), None, sigma_est, ch.iterations,
                 {i: cands[i].poses[ch.choice[i]] for i in used}, {c.index: c.rim_rms_px for c in cands},
                 {c.index: c.stripe_rms_px for c in cands}, None)
    if method == "ml":
        fit = _refined(camera, r, (rims, stripes), cands, used, LightPlane(ch.normal, ch.d), fit, opts.ml, warnings)
    results = _placement_results(cands, ch, fit, method)
    warnings.extend(f"placement {c.index} not used: {c.reason}" for c in cands if not c.usable)
    meta: dict = {"method": method, "sigma_px": fit.sigma_px, "n_used": len(used)}
    if fit.noise_model is not None:
        meta["noise_model"] = fit.noise_model
    if opts.sigma_px is not None:
        meta["sigma_px_assumed"] = float(opts.sigma_px)
    plane = LightPlane(fit.plane.normal, fit.plane.d, fit.covariance, meta=meta)
    return PlaneCalibration(plane=plane, covariance=fit.covariance, sigma_px=fit.sigma_px, placements=tuple(results),
                            method=method, ambiguity=ch.ambiguity, warnings=tuple(warnings),
                            iterations=int(fit.iterations))


@_dataclass(frozen=True)
class _Final:
    """The plane from the chosen chords (refined for ``ml``): its covariance (``ml``), the noise sigma,
    the solver's count, and by placement the final pose and the rim's and stripe's residual RMS (px);
    the ML refinement's noise model."""

    plane: LightPlane
    covariance: np.ndarray | None
    sigma_px: float
    iterations: int
    poses: dict
    rim_rms: dict
    stripe_rms: dict
    noise_model: dict | None


def _refined(camera, r: float, points: tuple, cands, used: list, start: LightPlane, fit: _Final,
             ml_options: MLOptions, warnings: list) -> _Final:
    """The joint ML refinement (:func:`lightplane.plane.ml.refine_ml`) of the plane and poses of the used
    placements from ``start`` (the plane of the chosen chords) and ``fit``'s poses; ``points``: all rim
    and stripe points (the stripes' inliers are used)."""
    rims, stripes = points
    res = refine_ml(camera, r, [rims[i] for i in used], [np.asarray(stripes[i], float)[cands[i].stripe_inliers]
                                                         for i in used], start, [fit.poses[i] for i in used],
                    ml_options)
    if not getattr(res, "converged", True):
        warnings.append(f"the maximum-likelihood refinement stopped after {res.iterations} iterations "
                        "without converging")
    plane = LightPlane(res.plane.normal, res.plane.d, res.covariance, meta={"method": "ml"})
    poses, rim_rms, st_rms = dict(fit.poses), dict(fit.rim_rms), dict(fit.stripe_rms)
    for j, i in enumerate(used):
        poses[i] = res.poses[j]
        rim_rms[i] = float(res.rim_rms_px[j])
        st_rms[i] = float(res.stripe_rms_px[j])
    return _Final(plane, plane.covariance, float(res.sigma_px), int(res.iterations), poses, rim_rms, st_rms,
                  _noise_model(res))


def _checked_point_sets(rims, stripes, min_placements) -> tuple[list, list, int]:
    """The rim and stripe point sets as (N, 2) arrays, one pair per placement, checked; ``min_placements`` as an int."""
    rims, stripes = list(rims), list(stripes)
    if len(rims) != len(stripes):
        raise LightplaneError(f"rims and stripes must have one entry per placement, got {len(rims)} and {len(stripes)}")
    if int(min_placements) < 2:
        raise LightplaneError(f"min_placements must be >= 2, got {min_placements}")
    min_placements = int(min_placements)
    if len(rims) < min_placements:
        raise LightplaneError(f"need at least {min_placements} placements, got {len(rims)}")

    def _pts(a, what):
        return np.zeros((0, 2)) if np.size(a) == 0 else as_points(a, 2, what)

    rims = [_pts(a, f"placement {i}: rim points") for i, a in enumerate(rims)]
    stripes = [_pts(a, f"placement {i}: stripe points") for i, a in enumerate(stripes)]
    for i, (rm, st) in enumerate(zip(rims, stripes)):
        if len(rm) == 0:
            raise LightplaneError(f"placement {i}: no rim points")
        if not (np.all(np.isfinite(rm)) and np.all(np.isfinite(st))):
            raise LightplaneError(f"placement {i}: rim or stripe points contain NaN or infinite values")
    return rims, stripes, min_placements


def _prepare_placements(camera, r: float, rims: list, stripes: list, opts: SolverOptions) -> list:
    """:func:`prepare_placement` of every placement, the undistortion, ellipse fits and circle poses
    of all placements in one vectorised pass each."""
    # undistort everything at once (one vectorised call), then split per placement
    sizes = [len(a) for pair in zip(rims, stripes) for a in pair]
    xy_all = camera.undistort_points(np.concatenate([a for pair in zip(rims, stripes) for a in pair]), normalized=True)
    parts = np.split(xy_all, np.cumsum(sizes)[:-1])
    K = camera.K
    rim_und = [parts[2 * i] @ K[:2, :2].T + K[:2, 2] for i in range(len(rims))]
    conics, fit_problems = fit_conics(rim_und)
    for i, why in enumerate(fit_problems):
        if why is not None:
            raise LightplaneError(f"placement {i}: rim points: {why}")
    centers, normals, pose_problems = circle_poses_batch(conics, K, r)
    centers.setflags(write=False)  # the poses below are read-only views
    normals.setflags(write=False)
    cands = []
    for i, (rm, st) in enumerate(zip(rims, stripes)):
        poses = None
        if pose_problems[i] is None:
            poses = tuple(CirclePose(centers[i, j], normals[i, j], r) for j in range(2))
        pre = _Batched(rim_xy=parts[2 * i], stripe_xy=parts[2 * i + 1], conic=conics[i], poses=poses,
                       pose_problem=pose_problems[i])
        cands.append(_prepare_placement(camera, r, rm, st, i, opts, pre))
    return cands


@_dataclass(frozen=True)
class _Chords:
    """The chosen chords (:func:`_choose_chords`): the plane through them, which candidate of each used
    placement, every placement's reason, the solver's count, the ambiguity (``global``) and warnings."""

    normal: np.ndarray
    d: float
    choice: dict
    reasons: dict
    iterations: int
    ambiguity: Ambiguity | None
    warnings: tuple


def _choose_chords(cands, usable: list, sigma: float, method: str, opts: SolverOptions) -> _Chords:
    """One chord per usable placement by the ``paper`` or the ``global`` method (``ml`` starts from ``global``)."""
    strict = opts.strict
    reasons: dict = {c.index: c.reason for c in cands if not c.usable}
    if method == "paper":
        out = _solve_paper(cands, usable, sigma, strict=strict, rel_change=opts.paper_rel_change)
        reasons.update(out.reasons)
        return _Chords(out.normal, out.d, out.choice, reasons, out.processed, None, tuple(out.notes))
    warnings = []
    g = _solve_global(cands, usable, sigma, max_exhaustive=opts.max_exhaustive, rng=np.random.default_rng(opts.seed))
    normal, d = g.normal, g.d
    choice = {i: g.choice[i] for i in usable if g.decided[i] or not strict}
    for i in usable:
        why = f"both chords fit the plane (flipping it costs {g.flip_cost[i]:.3g} <= {_KAPPA**2:g})"
        reasons[i] = "used" if g.decided[i] else (f"rejected: {why}" if strict else f"used, undecided: {why}")
    if not strict and not all(g.decided[i] for i in usable):
        normal, d = g.normal_all, g.d_all
        warnings.append("undecided placements kept (strict=False): "
                        + ", ".join(str(i) for i in usable if not g.decided[i]))
    if not g.ambiguity.separated:
        warnings.append("ambiguous choice of chords: " + g.ambiguity.message)
    return _Chords(normal, d, choice, reasons, g.evaluated, g.ambiguity, tuple(warnings))


def _spread_warnings(cands, used: list, choice: dict, opts: SolverOptions) -> list:
    """The chosen target normals must spread by more than ``min_normal_spread_deg``: an error
    (strict) or a warning."""
    normals = np.array([cands[i].poses[choice[i]].normal for i in used])
    spread = float(np.degrees(np.arccos(np.clip(np.min(normals @ normals.T), -1.0, 1.0))))
    if spread <= opts.min_normal_spread_deg and not opts.strict:
        return [f"placements too alike: all target normals within {spread:.2f} deg of each other"]
    if spread <= opts.min_normal_spread_deg:
        raise LightplaneError(
            f"placements too alike: all target normals within {spread:.2f} deg of each other "
            f"(need > {opts.min_normal_spread_deg} deg to resolve the two-fold pose ambiguity); tilt the target differently"
        )
    return []


def _noise_model(res) -> dict:
    """The plane file's ``noise_model``: what the ML refinement found about the noise."""
    noise_model = {k: _finite_or_none(float(getattr(res, k))) for k in
                   ("sigma_rim_px", "sigma_stripe_px", "tau_rim", "tau_stripe", "image_dispersion",
                    "image_dispersion_expected")
                   if hasattr(res, k)}
    if hasattr(res, "n_outliers"):
        noise_model["n_outliers"] = int(res.n_outliers)
    if hasattr(res, "dispersion_applied"):
        noise_model["image_dispersion_applied"] = bool(res.dispersion_applied)
        d = noise_model.get("image_dispersion")
        noise_model["image_dispersion_factor"] = max(float(d), 1.0) if res.dispersion_applied and d else 1.0
    return noise_model


def _placement_results(cands, ch: _Chords, fit: _Final, method: str) -> list:
    """Every placement's :class:`PlacementResult`."""
    poses_final, rim_rms, st_rms, plane = fit.poses, fit.rim_rms, fit.stripe_rms, fit.plane
    results = []
    for c in cands:
        i = c.index
        k = ch.choice.get(i)
        if c.usable:
            kk = k if k is not None else 0
            if k is not None and method == "ml":
                xy = c.stripe_xy
                chord = ray_plane(xy, poses_final[i].normal, poses_final[i].center)
            else:
                chord = c.chords[kk]
            chord_rms = float(np.sqrt(_msd(chord, plane.normal, plane.d))) if k is not None else np.nan
        else:
            chord_rms = np.nan
        results.append(PlacementResult(
            index=i, used=k is not None, reason=ch.reasons.get(i, "used"), candidate=k,
            pose=poses_final.get(i), poses=c.poses, n_rim=c.n_rim, n_stripe=int(c.stripe_inliers.sum()),
            rim_rms_px=float(rim_rms[i]), stripe_rms_px=float(st_rms[i]), chord_rms_mm=chord_rms,
            stripe_inliers=c.stripe_inliers))
    return results
