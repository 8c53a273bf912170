"""What a camera calibration's views can determine, and whether its result agrees with its own corner
noise (docs/calibration-guide.md §What the views determine).

Three checks, in the order :func:`lightplane.camera.intrinsics.calibrate_camera` makes them:

- *before solving*: how much perspective each view shows (:func:`perspective_px`: how far the board's
  image departs from the affine image a face-on board would give).  The focal length is seen only
  through perspective: boards seen face-on in every view leave it undetermined (Zhang's method is
  degenerate), and the calibration is refused with what to do instead of a meaningless number;
- *after solving*: the boards' tilts against the line of sight (:func:`board_tilts`) and the focal
  length's relative standard deviation; a camera whose focal length is not determined, or that is not
  a camera (a focal length that is not positive), is refused the same way.  Views whose reprojection
  RMS is far above the others' are dropped with their reason (:func:`outlier_views`);
- *the corner noise*: each saddle-fit corner's covariance from its own image
  (:func:`lightplane.camera.corners.corner_noise`) predicts the reprojection RMS a right model gives;
  a calibration far above it contradicts its noise model (a wrong board, a board that moved or bent
  in some views, a lens model that does not fit) and is refused unless the caller keeps it
  (:func:`corner_noise_check`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from lightplane.core.errors import LightplaneError

__all__ = ["TILT_ADVICE", "MIN_PERSPECTIVE_NOISE", "MAX_FOCAL_REL_STD", "OUTLIER_RATIO", "OUTLIER_FLOOR_PX",
           "NOISE_RATIO", "NOISE_FLOOR_PX", "perspective_px", "board_tilts", "degenerate_views_message",
           "focal_length_problem", "outlier_views", "CornerNoiseCheck", "corner_noise_check"]

#: what to do when the views do not determine the focal length
TILT_ADVICE = ("tilt the board 20-40 deg against the line of sight in several directions (left, right, up, down), "
               "so that its far side looks visibly smaller than its near side")
#: every view's perspective (px) below this many times the corners' noise: the focal length is not observable
MIN_PERSPECTIVE_NOISE = 3.0
#: the corners' noise assumed where none is measured (px): a good sub-pixel corner
DEFAULT_CORNER_NOISE_PX = 0.05
#: a focal length whose standard deviation exceeds this fraction of its value is not determined
MAX_FOCAL_REL_STD = 0.05
#: a view whose reprojection RMS is over this many times the views' median (and over the floor) is an outlier
OUTLIER_RATIO = 3.0
OUTLIER_FLOOR_PX = 0.3
#: a calibration whose reprojection RMS is over this many times what its corner noise predicts, and
#: over the floor, contradicts its noise model
NOISE_RATIO = 3.0
NOISE_FLOOR_PX = 0.05


def perspective_px(object_points: np.ndarray, image_points: np.ndarray) -> float:
    """How much perspective one view of a planar board shows (px): the RMS distance between the board's
    image under the homography fitted to its points and the best affine image of the board (what a
    board seen face-on, or from far away, gives).  About ``L tan(tilt) · L / Z`` for a board of
    image half-size ``L`` px tilted by ``tilt`` at distance ``Z`` (in units of its size); 0 for a
    face-on board, whatever the focal length.  Needs no camera model (lens distortion, smooth and
    symmetric about the image centre, adds little)."""
    import cv2

    xy = np.asarray(object_points, np.float64).reshape(-1, 3)[:, :2]
    uv = np.asarray(image_points, np.float64).reshape(-1, 2)
    if len(xy) < 4:
        return float("nan")
    H, _ = cv2.findHomography(xy, uv, 0)
    if H is None:
        return float("nan")
    ph = np.column_stack([xy, np.ones(len(xy))]) @ H.T
    with np.errstate(all="ignore"):
        q = ph[:, :2] / ph[:, 2:]
    X = np.column_stack([xy, np.ones(len(xy))])
    aff, *_ = np.linalg.lstsq(X, q, rcond=None)
    return float(np.sqrt(np.mean(np.sum((X @ aff - q) ** 2, axis=1))))


def board_tilts(object_points: Sequence[np.ndarray], rvecs: Sequence, tvecs: Sequence) -> tuple[np.ndarray, np.ndarray]:
    """Each view's board tilt against the line of sight to its centre (deg) and the direction in the
    image about which it is tilted (deg, 0-180: the tilt axis's angle from the image's u axis)."""
    import cv2

    tilt, axis = [], []
    for o, rv, tv in zip(object_points, rvecs, tvecs):
        R = cv2.Rodrigues(np.asarray(rv, np.float64).reshape(3, 1))[0]
        c = R @ np.asarray(o, np.float64).reshape(-1, 3).mean(axis=0) + np.ravel(tv)
        n = R[:, 2]
        los = -c / max(np.linalg.norm(c), 1e-300)
        cosang = abs(float(n @ los))
        tilt.append(float(np.degrees(np.arccos(min(1.0, cosang)))))
        ax = np.cross(n if n @ los > 0 else -n, los)
        axis.append(float(np.degrees(np.arctan2(ax[1], ax[0])) % 180.0))
    return np.asarray(tilt), np.asarray(axis)


def degenerate_views_message(perspective: Sequence[float], noise_px: float | None, n_views: int) -> str | None:
    """The refusal (one sentence) when no view shows perspective beyond :data:`MIN_PERSPECTIVE_NOISE`
    times the corners' noise ``noise_px`` (None: :data:`DEFAULT_CORNER_NOISE_PX`), else None."""
    p = np.asarray(perspective, np.float64)
    p = p[np.isfinite(p)]
    noise = float(noise_px) if noise_px is not None and np.isfinite(noise_px) and noise_px > 0 \
        else DEFAULT_CORNER_NOISE_PX
    if p.size == 0 or float(p.max()) >= MIN_PERSPECTIVE_NOISE * noise:
        return None
    return (f"the focal length cannot be determined from these {n_views} views: the board is seen face-on in every "
            f"one (its perspective, how far its image departs from a flat affine copy, is at most {p.max():.3g} px, "
            f"under {MIN_PERSPECTIVE_NOISE:g}x the corners' noise of {noise:.2g} px), and only perspective tells "
            f"a near large board from a far small one; {TILT_ADVICE}")


def focal_length_problem(fx: float, fy: float, std: dict, tilts_deg: Sequence[float] | np.ndarray,
                         perspective: Sequence[float] | np.ndarray) -> str | None:
    """Why a solved calibration's focal length is not a result (one sentence), or None: a focal length
    that is not finite and positive, or whose std exceeds :data:`MAX_FOCAL_REL_STD` of it; the
    sentence gives the views' perspective (:func:`perspective_px`), the boards' tilts as solved and
    what to do."""
    t = np.asarray(tilts_deg, np.float64)
    t = t[np.isfinite(t)]
    p = np.asarray(perspective, np.float64)
    p = p[np.isfinite(p)]
    n_views = len(p)
    tilts = (f"the boards show {p.min():.2g}-{p.max():.2g} px of perspective" if p.size else "")
    tilts += (f" (tilted {t.min():.1f}-{t.max():.1f} deg against the line of sight as solved, itself uncertain)"
              if t.size else "")
    if not (np.isfinite(fx) and np.isfinite(fy) and fx > 0 and fy > 0):
        return (f"the focal length is not determined by these {n_views} views (the solve ends at fx = {fx:.4g}, "
                f"fy = {fy:.4g} px, not a camera): {tilts}; {TILT_ADVICE}")
    rel = max(float(std.get("fx", 0.0)) / fx, float(std.get("fy", 0.0)) / fy)
    if not np.isfinite(rel) or rel > MAX_FOCAL_REL_STD:
        return (f"the focal length is not determined by these {n_views} views (fx = {fx:.1f} ± {std.get('fx', np.nan):.3g} "
                f"px, {100 * rel:.0f} % of it): {tilts}, too little to tell the board's distance from its size; "
                f"{TILT_ADVICE}")
    return None


def outlier_views(names: Sequence[str], per_view_rms_px: Sequence[float],
                  predicted_px: Sequence[float] | None = None) -> dict[str, str]:
    """The views whose reprojection RMS is over :data:`OUTLIER_RATIO` times the views' median and over a
    floor, each with its reason (name -> reason); none among fewer than 3 views.  The floor: where the
    view's corner noise predicts its RMS (``predicted_px``, NaN where unknown), :data:`NOISE_RATIO`
    times that and at least :data:`NOISE_FLOOR_PX`; else :data:`OUTLIER_FLOOR_PX`."""
    rms = np.asarray(per_view_rms_px, np.float64).ravel()
    if len(rms) < 3:
        return {}
    pred = np.full(len(rms), np.nan) if predicted_px is None else np.asarray(predicted_px, np.float64).ravel()
    floor = np.where(np.isfinite(pred), np.maximum(NOISE_RATIO * pred, NOISE_FLOOR_PX), OUTLIER_FLOOR_PX)
    med = float(np.median(rms))
    return {str(n): (f"reprojection RMS {r:.2g} px, {r / med:.1f}x the views' median {med:.2g} px"
                     + (f" and {r / p:.0f}x what its corners' noise predicts" if np.isfinite(p) else "")
                     + ": its corners do not follow the others' (a misdetected, blurred or moved board?)")
            for n, r, p, f in zip(names, rms, pred, floor) if r > OUTLIER_RATIO * med and r > f}


@dataclass(frozen=True)
class CornerNoiseCheck:
    """A calibration's reprojection RMS against what its corners' own noise predicts.

    ``rms_px``: the calibration's RMS; ``predicted_px``: the RMS its corners' covariances
    (:func:`lightplane.camera.corners.corner_noise`) predict for a right model, its degrees of freedom
    accounted; ``views``: per view ``(name, rms_px, predicted_px)``; ``kept``: refused but kept on request.
    """

    rms_px: float
    predicted_px: float
    views: tuple[tuple[str, float, float], ...]
    n_corners: int
    kept: bool = False

    @property
    def ratio(self) -> float:
        return self.rms_px / self.predicted_px if self.predicted_px > 0 else float("inf")

    @property
    def suspect_views(self) -> tuple[tuple[str, float, float], ...]:
        """The views whose own RMS is over :data:`NOISE_RATIO` x their prediction and over the floor."""
        return tuple(v for v in self.views if v[1] > NOISE_RATIO * v[2] and v[1] > NOISE_FLOOR_PX)

    @property
    def suspect(self) -> bool:
        """The whole calibration, or some view of it, far above its corners' noise."""
        return (self.ratio > NOISE_RATIO and self.rms_px > NOISE_FLOOR_PX) or bool(self.suspect_views)

    def worst_views(self, n: int = 3) -> list[tuple[str, float, float]]:
        return sorted(self.views, key=lambda v: -(v[1] / v[2] if v[2] > 0 else np.inf))[:n]

    def diagnosis(self) -> str:
        """One sentence: how far the calibration is above its corner noise, the worst views, the likely causes."""
        worst = "; ".join(f"{Path(n).name} {r:.3g} px ({r / p:.0f}x its {p:.2g} px)" for n, r, p in self.worst_views())
        even = 2 * len(self.suspect_views) > len(self.views)
        cause = ("in every view alike: a lens model that does not fit this lens (try --model rational), a board that is "
                 "not flat, or board dimensions that do not match the board" if even
                 else "in some views: a board that moved during the exposure or was bent, or a misdetected board there")
        return (f"reprojection RMS {self.rms_px:.3g} px is {self.ratio:.1f}x the {self.predicted_px:.2g} px that the "
                f"corners' own noise predicts ({self.n_corners} corners; each corner's precision from its fit to the "
                f"image), {len(self.suspect_views)} of {len(self.views)} views over {NOISE_RATIO:g}x their own; "
                f"worst views: {worst}; the excess is {cause}")

    def to_dict(self) -> dict:
        return {"rms_px": self.rms_px, "predicted_rms_px": self.predicted_px, "ratio": self.ratio,
                "suspect_ratio": NOISE_RATIO, "floor_px": NOISE_FLOOR_PX,
                "verdict": "suspect" if self.suspect else "ok", "kept_by_request": bool(self.kept and self.suspect),
                "suspect_views": [n for n, _, _ in self.suspect_views],
                "predicted_from": "each saddle-fit corner's covariance from its own image (fit residual through "
                                  "the fit's Jacobian), independent of the calibration",
                "views": [{"image": n, "rms_px": r, "predicted_rms_px": p} for n, r, p in self.views],
                **({"diagnosis": self.diagnosis()} if self.suspect else {})}


def corner_noise_check(names: Sequence[str], residuals_px: Sequence[np.ndarray],
                       covariances: Sequence[np.ndarray | None], n_params: int) -> CornerNoiseCheck | None:
    """The :class:`CornerNoiseCheck` of a calibration: its views' residuals (N_v, 2) px and their corners'
    covariances (N_v, 2, 2) px² (None or NaN: unknown), ``n_params`` the parameters solved (intrinsics
    and 6 per view).  None unless every view has covariances for half its corners or more (a
    prediction from a few views' corners would not speak for the others)."""
    views, tr_all, r2_all = [], [], []
    for n, r, C in zip(names, residuals_px, covariances):
        if C is None:
            return None
        tr = np.trace(np.asarray(C, np.float64), axis1=1, axis2=2)
        ok = np.isfinite(tr) & (tr > 0)
        if ok.sum() < 0.5 * len(tr):
            return None
        r2 = np.sum(np.asarray(r, np.float64) ** 2, axis=1)
        views.append((str(n), float(np.sqrt(np.mean(r2))), float(np.sqrt(np.mean(tr[ok])))))
        tr_all.append(tr[ok])
        r2_all.append(r2)
    if not views:
        return None
    n_obs = 2 * sum(len(r) for r in r2_all)
    dof = max(n_obs - int(n_params), 1) / n_obs
    predicted = float(np.sqrt(np.mean(np.concatenate(tr_all)) * dof))
    rms = float(np.sqrt(np.mean(np.concatenate(r2_all))))
    views = [(n, r, p * np.sqrt(dof)) for n, r, p in views]
    return CornerNoiseCheck(rms, predicted, tuple(views), n_obs // 2)


def check_corner_noise(check: CornerNoiseCheck | None, keep: bool) -> CornerNoiseCheck | None:
    """``check`` marked kept, or LightplaneError with its diagnosis when it is suspect and not ``keep``."""
    if check is None:
        return None
    if check.suspect and not keep:
        raise LightplaneError(f"suspect camera calibration: {check.diagnosis()}; fix the cause, or keep the "
                              "calibration as it is with --keep-suspect")
    return CornerNoiseCheck(check.rms_px, check.predicted_px, check.views, check.n_corners, kept=keep)
