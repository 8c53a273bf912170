"""The paper's simulation study (§3; docs/method.md §Simulation study): accuracy against placements, noise and diameter.

Geometry: :func:`~lightplane.simulate.scene.paper_camera` (f = 25 mm, no
distortion) and :func:`~lightplane.simulate.scene.paper_plane`
(``0.9336 y − 0.3584 z + 140.04 = 0``), discs placed at
:data:`~lightplane.simulate.scene.PAPER_DISTANCE_MM` with the stripe across them.
The paper's noise unit is ambiguous ("mm"); here it is isotropic Gaussian noise of
``sigma_px`` **pixels** on every rim point and every stripe centre.

Factors (the paper's ranges):

- ``placements``: 2–7 placements, D = 50 mm, sigma 0.4 px;
- ``noise``: sigma 0–1 px in steps of 0.1, D = 50 mm, 2 placements;
- ``diameter``: D = 10–70 mm in steps of 10, sigma 0.6 px, 2 placements.

For every trial, random placements (the same at every level of a factor, so the curves
show the factor's effect rather than fresh geometry; noise drawn per level and trial;
results do not depend on the order of evaluation) are calibrated with the ``paper``,
``global`` and ``ml`` methods of :func:`lightplane.plane.solvers.calibrate_plane_from_points`
(``min_placements=2, strict=False``: the paper's two-placement runs resolve the
ambiguity by the coplanarity of the true pair alone), and the Cramér–Rao bound of the
same trial (:func:`lightplane.plane.ml.crlb`) is computed.  Reported per level and
method: the relative errors of the plane coefficients ``b, c, d`` (the paper's
measure; ``a`` = 0 in the paper's plane, so it has no relative error), the normal's
angle error (deg), the offset error ``|Δd|`` (mm) and the RMS triangulation error over
the working volume (mm) — RMS over the trials that succeeded — and the number of
trials that failed: the disambiguation chose the wrong circle pose for a used
placement (``wrong_choice``; judged against the truth), an error was raised, or the
answer is gross (angle error > ``GROSS_DEG``).  With two placements the ambiguity
rests on the coplanarity of the two true chords alone, so at high noise or small
diameters a wrong pair is sometimes more coplanar than the true one.
"""

from __future__ import annotations

import csv
import io
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.plane.model import LightPlane
from lightplane.core.io import atomic_write
from lightplane.plane.ml import crlb
from lightplane.plane.solvers import SolverOptions, calibrate_plane_from_points
from lightplane.plane.triangulate import triangulate_normalized
from lightplane.plane.uncertainty import point_jacobian, working_volume_grid
from lightplane.simulate.scene import (PAPER_DISTANCE_MM, PlacementOptions, paper_camera, paper_plane, sample_placements,
    synthetic_observations)

__all__ = ["FACTORS", "METHODS", "GROSS_DEG", "FactorSpec", "StudyResult", "run_factor", "write_csv",
           "n_trials_total"]

METHODS = ("paper", "global", "ml")
#: An answer whose normal is off by more than this (deg) chose a wrong chord: counted as failed.
GROSS_DEG = 5.0


@dataclass(frozen=True)
class FactorSpec:
    """One factor of the study: which variable, its levels, and the fixed settings."""

    name: str
    variable: str  # "n_placements", "sigma_px" or "diameter_mm"
    levels: tuple
    n_placements: int
    sigma_px: float
    diameter_mm: float
    label: str  # x-axis label with units

    def settings(self, level) -> tuple[int, float, float]:
        n, s, dmm = self.n_placements, self.sigma_px, self.diameter_mm
        if self.variable == "n_placements":
            n = int(level)
        elif self.variable == "sigma_px":
            s = float(level)
        else:
            dmm = float(level)
        return n, s, dmm


FACTORS: dict[str, FactorSpec] = {
    "placements": FactorSpec("placements", "n_placements", tuple(range(2, 8)), 0, 0.4, 50.0,
                             "number of target placements"),
    "noise": FactorSpec("noise", "sigma_px", tuple(round(0.1 * k, 1) for k in range(11)), 2, 0.0, 50.0,
                        "noise sigma on rim and stripe points (px)"),
    "diameter": FactorSpec("diameter", "diameter_mm", tuple(range(10, 71, 10)), 2, 0.6, 0.0,
                           "target diameter (mm)"),
}

_METRICS = ("rel_b_pct", "rel_c_pct", "rel_d_pct", "rel_coef_pct", "angle_deg", "offset_mm", "tri_rms_mm")


@dataclass(frozen=True)
class StudyResult:
    """Rows of one factor: one per (level, method), methods plus ``crlb``.

    ``rows``: list of dicts with ``factor, level, method, trials, failed`` and, per
    metric in ``rel_b_pct, rel_c_pct, rel_d_pct, rel_coef_pct, angle_deg, offset_mm,
    tri_rms_mm``, the RMS over successful trials (``<metric>``) and the median
    (``<metric>_median``); for ``crlb`` the bound's RMS prediction (no median).
    """

    factor: FactorSpec
    rows: list = field(default_factory=list)
    trials: int = 0
    seed: int = 0
    n_rim: int = 200
    n_stripe: int = 300


def n_trials_total(factors: Sequence[str], trials: int) -> int:
    """Number of trial steps (for a progress bar)."""
    return sum(len(FACTORS[f].levels) for f in factors) * int(trials)


def _wrong_choice(res, placements) -> bool:
    """Whether a used placement got the wrong one of its two circle poses: the chosen
    candidate's normal is farther from the true normal than the other candidate's."""
    for pr, truth in zip(res.placements, placements):
        if not pr.used or pr.poses is None or pr.candidate is None:
            continue
        mine = pr.poses[pr.candidate].normal
        other = pr.poses[1 - pr.candidate].normal
        if abs(mine @ truth.normal) < abs(other @ truth.normal):
            return True
    return False


def _errors(est: LightPlane, true: LightPlane, vol_xy: np.ndarray) -> dict:
    ce, ct = est.coefficients, true.coefficients
    rel = np.abs(ce[1:] - ct[1:]) / np.abs(ct[1:]) * 100.0
    a = triangulate_normalized(est, vol_xy).points
    b = triangulate_normalized(true, vol_xy).points
    tri = float(np.sqrt(np.nanmean(np.sum((a - b) ** 2, axis=1))))
    # angle via the cross product: accurate also for tiny angles (arccos is not)
    ang = float(np.degrees(np.arctan2(np.linalg.norm(np.cross(est.normal, true.normal)),
                                      abs(est.normal @ true.normal))))
    return {"rel_b_pct": rel[0], "rel_c_pct": rel[1], "rel_d_pct": rel[2],
            "rel_coef_pct": float(np.sqrt(np.mean(rel**2))), "angle_deg": ang,
            "offset_mm": abs(ce[3] - ct[3]), "tri_rms_mm": tri}


def _bound(cov: np.ndarray, true: LightPlane, vol_xy: np.ndarray) -> dict:
    """Per-trial variances predicted by a 4x4 covariance of (a, b, c, d)."""
    ct = true.coefficients
    var = np.diag(cov)
    rel2 = var[1:] / ct[1:] ** 2 * 1e4
    J = point_jacobian(true, vol_xy)
    tri2 = float(np.nanmean(np.trace(J @ cov @ np.swapaxes(J, 1, 2), axis1=1, axis2=2)))
    return {"rel_b_pct": rel2[0], "rel_c_pct": rel2[1], "rel_d_pct": rel2[2], "rel_coef_pct": float(np.mean(rel2)),
            "angle_deg": float(np.trace(cov[:3, :3])) * np.degrees(1) ** 2, "offset_mm": var[3], "tri_rms_mm": tri2}


def _score_methods(camera: Camera, plane: LightPlane, diam: float, rims: list, stripes: list, placements: list,
                   methods: Sequence[str], vol_xy: np.ndarray) -> dict:
    """One trial's outcome per method: its errors (:func:`_errors`), ``"failed"`` (an error raised, or a
    gross answer) or ``"wrong"`` (a used placement with the wrong one of its two poses)."""
    out: dict = {}
    for m in methods:
        try:
            res = calibrate_plane_from_points(camera, diam, rims, stripes, method=m,
                                              options=SolverOptions(strict=False), min_placements=2)
        except LightplaneError:
            out[m] = "failed"
            continue
        if _wrong_choice(res, placements):
            out[m] = "wrong"
            continue
        e = _errors(res.plane, plane, vol_xy)
        out[m] = "failed" if e["angle_deg"] > GROSS_DEG else e
    return out


def _level_rows(base: dict, methods: Sequence[str], trials: int, per: dict, failed: dict, wrong: dict,
                bounds: list) -> list[dict]:
    """The rows of one level: per method the RMS and median of each metric over its good trials, and the bound."""
    rows = []
    for m in methods:
        row = dict(base, method=m, trials=trials, failed=failed[m] + wrong[m], wrong_choice=wrong[m])
        for key in _METRICS:
            v = np.array([e[key] for e in per[m]], dtype=float)
            row[key] = float(np.sqrt(np.mean(v**2))) if len(v) else float("nan")
            row[key + "_median"] = float(np.median(v)) if len(v) else float("nan")
        rows.append(row)
    row = dict(base, method="crlb", trials=trials, failed=0, wrong_choice=0)
    for key in _METRICS:
        row[key] = float(np.sqrt(np.mean([b[key] for b in bounds])))
        row[key + "_median"] = float("nan")
    rows.append(row)
    return rows


def run_factor(factor: str, *, trials: int = 40, seed: int = 0, n_rim: int = 200, n_stripe: int = 300,
               camera: Camera | None = None, plane: LightPlane | None = None,
               methods: Sequence[str] = METHODS, progress: Callable[[int], None] | None = None) -> StudyResult:
    """Run one factor of the paper's §3 study.

    Parameters
    ----------
    factor : ``"placements"``, ``"noise"`` or ``"diameter"`` (:data:`FACTORS`).
    trials : int
        Random trials per level (fresh placements and noise each).
    seed : int
        Trial ``t`` draws its placements from ``default_rng([seed, factor index, t])``
        (the same at every level: common random numbers) and its noise from
        ``default_rng([seed, factor index, t, k + 1])`` at level ``k``.
    n_rim, n_stripe : int
        Points per placement on the rim and on the stripe.
    camera, plane
        Default: the paper's (:func:`paper_camera`, :func:`paper_plane`).
    progress : callable(int), optional
        Called with 1 after every trial.
    """

    if factor not in FACTORS:
        raise LightplaneError(f"factor must be one of {', '.join(FACTORS)}, got {factor!r}")
    if int(trials) < 1:
        raise LightplaneError(f"trials must be >= 1, got {trials}")
    for m in methods:
        if m not in METHODS:
            raise LightplaneError(f"method must be one of {', '.join(METHODS)}, got {m!r}")
    spec = FACTORS[factor]
    camera = paper_camera() if camera is None else camera
    plane = paper_plane() if plane is None else plane
    vol = working_volume_grid(camera, plane, distance_mm=PAPER_DISTANCE_MM, step_px=32.0)
    vol_xy = camera.undistort_points(vol.uv, normalized=True)
    f_index = list(FACTORS).index(factor)
    rows = []
    for k, level in enumerate(spec.levels):
        n_pl, sigma, diam = spec.settings(level)
        per: dict[str, list[dict]] = {m: [] for m in methods}
        failed = {m: 0 for m in methods}  # an error raised, or a gross answer
        wrong = {m: 0 for m in methods}  # a used placement with the wrong one of its two poses
        bounds = []
        for t in range(int(trials)):
            # common random numbers: trial t draws its placements from the same stream at
            # every level (the first n of them for the placements factor), so the curves
            # show the factor's effect, not a fresh draw of geometry at each level
            rng_geo = np.random.default_rng([int(seed), f_index, t])
            rng = np.random.default_rng([int(seed), f_index, t, k + 1])
            n_draw = max(spec.levels) if spec.variable == "n_placements" else n_pl
            placements = sample_placements(n_draw, rng_geo, PlacementOptions(diameter_mm=diam,
                                                                              distance_mm=PAPER_DISTANCE_MM),
                                           camera=camera, plane=plane)[:n_pl]
            obs = [synthetic_observations(camera, plane, p, n_rim=n_rim, n_stripe=n_stripe, sigma_px=sigma, rng=rng)
                   for p in placements]
            rims = [o[0] for o in obs]
            stripes = [o[1] for o in obs]
            for m, e in _score_methods(camera, plane, diam, rims, stripes, placements, methods, vol_xy).items():
                if e == "failed":
                    failed[m] += 1
                elif e == "wrong":
                    wrong[m] += 1
                else:
                    per[m].append(e)
            if sigma > 0:
                cov = crlb(camera, 0.5 * diam, placements, plane, n_rim, n_stripe, sigma)
                bounds.append(_bound(cov, plane, vol_xy))
            else:
                bounds.append({key: 0.0 for key in _METRICS})
            if progress is not None:
                progress(1)
        base = {"factor": factor, "level": level, "n_placements": n_pl, "sigma_px": sigma, "diameter_mm": diam}
        rows += _level_rows(base, methods, int(trials), per, failed, wrong, bounds)
    return StudyResult(spec, rows, int(trials), int(seed), int(n_rim), int(n_stripe))


_COLUMNS = ["factor", "level", "n_placements", "sigma_px", "diameter_mm", "method", "trials", "failed",
            "wrong_choice"] + [
    c for key in _METRICS for c in (key, key + "_median")]


def csv_text(result: StudyResult) -> str:
    """The rows as CSV text (units in the column names; RMS and ``_median`` per metric)."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=_COLUMNS, lineterminator="\n")
    w.writeheader()
    for row in result.rows:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    return buf.getvalue()


def write_csv(result: StudyResult, path: str | os.PathLike, *, force: bool = False) -> Path:
    """Write :func:`csv_text` atomically."""
    return atomic_write(path, csv_text(result), force=force)
