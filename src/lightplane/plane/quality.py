"""Does a light plane agree with its own stripe noise?  (docs/calibration-guide.md §Suspect planes)

Each calibration image (a board pose, a disc placement) gives stripe points on a flat target:
their image is a straight line in undistorted pixels, and the RMS distance of the centres from
their own line is the image's *stripe noise* (px).  Moving a centre by 1 px across the stripe
moves its point on the target, and so its distance from the light plane, by ``g`` mm (per
point, from the target's pose); the residual RMS the stripe noise explains is
``noise_px · RMS(g)``, the image's *predicted* residual.  An image whose points lie much farther
from the plane than that contradicts the noise model.

Two levels, per image (:data:`SUSPECT_RATIO`, :data:`SUSPECT_FLOOR`):

- *elevated*: residual RMS > ``SUSPECT_RATIO`` x predicted but below the floor: the whole stripe of
  the image sits off the common plane by a fraction of a millimetre (a board-pose error, a stripe
  biased along a row of corners).  Kept, named in a warning; the jackknife covariance over the
  images already sees such per-image offsets.  FabScan's boards: 6 of 27 poses, 4-18x, 0.07-0.29 mm.
- *suspect*: residual RMS > ``SUSPECT_RATIO`` x predicted **and** > ``SUSPECT_FLOOR`` x the target's
  scale (a board's square or dot pitch, a disc's diameter): points that are not the laser's line
  on this target (a laser-off frame whose texture was taken for the stripe, the board pose of
  another frame).  The calibration is refused, naming the images, unless the caller keeps it.

When some images are suspect, the plane the others agree on is found first (every pair of images
proposes a plane; the one most images agree with wins), so that a bad image does not make the good
ones look bad; the images are then judged against that plane.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations
from pathlib import Path
from typing import Sequence

import numpy as np

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.core.geometry import fit_plane_tls, ray_plane, tls_line

__all__ = ["SUSPECT_RATIO", "SUSPECT_FLOOR", "StripeImage", "ImageResidual", "PlaneQuality", "stripe_image",
           "plane_quality", "check_plane_quality", "working_volume", "MIN_TRIANGULATION_DEG", "MIN_SPREAD_RATIO",
           "MAX_NORMAL_SIGMA_DEG", "plane_geometry"]

#: an image's residual RMS over its predicted (stripe-noise) residual beyond which it is elevated or suspect
SUSPECT_RATIO = 5.0
#: a suspect image's residual RMS is also above this fraction of the target's scale (square, pitch, diameter)
SUSPECT_FLOOR = 0.1
#: centres per pixel of the stripe's length below which its points are "few and scattered"
SCATTERED_COVERAGE = 0.25


@dataclass(frozen=True)
class StripeImage:
    """One image's stripe points on its flat target: ``points_mm`` (N, 3) camera frame, on the
    target plane through ``target_point_mm`` with ``target_normal``; ``uv_undistorted`` (N, 2) px."""

    name: str
    points_mm: np.ndarray
    uv_undistorted: np.ndarray
    target_normal: np.ndarray
    target_point_mm: np.ndarray


def stripe_image(camera: Camera, name: str, points_mm: np.ndarray, target_normal, target_point_mm) -> StripeImage:
    """A :class:`StripeImage` from stripe points already on the target (camera frame, mm)."""
    p = np.asarray(points_mm, np.float64).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1) & (p[:, 2] > 0)] if len(p) else p
    uv = (p[:, :2] / p[:, 2:]) @ camera.K[:2, :2].T + camera.K[:2, 2] if len(p) else np.zeros((0, 2))
    return StripeImage(str(name), p, uv, np.asarray(target_normal, np.float64).ravel(),
                       np.asarray(target_point_mm, np.float64).ravel())


@dataclass(frozen=True)
class ImageResidual:
    """One image against a plane: points, residual RMS and mean (mm), stripe noise (px), the
    residual RMS it predicts (mm), centres per px of the stripe's length, and the verdict
    (``"ok"``, ``"elevated"`` or ``"suspect"``)."""

    name: str
    n_points: int
    rms_mm: float
    mean_mm: float
    noise_px: float
    predicted_mm: float
    coverage: float
    verdict: str

    @property
    def ratio(self) -> float:
        return self.rms_mm / self.predicted_mm if self.predicted_mm > 0 else float("inf")

    def describe(self) -> str:
        ratio = f"{self.ratio:.0f}x" if np.isfinite(self.ratio) else "far beyond"
        return (f"{Path(self.name).name}: {self.rms_mm:.3g} mm RMS off the plane (mean {self.mean_mm:+.3g} mm), "
                f"{ratio} the {self.predicted_mm:.2g} mm its stripe noise ({self.noise_px:.2f} px) predicts")

    def cause(self, background_per_image: bool = False) -> str:
        if self.coverage < SCATTERED_COVERAGE or self.n_points < 30:
            return "few, scattered stripe points: a laser-off frame among the images, or texture taken for the stripe?"
        why = "a line off the plane: a laser-off frame whose texture was taken for the stripe, the board pose of "
        why += "another frame" + (" (are the --background frames in the images' order?)" if background_per_image else "")
        return why + ", or another laser's stripe?"

    def to_dict(self) -> dict:
        return {"image": self.name, "n_points": self.n_points, "residual_rms_mm": self.rms_mm,
                "residual_mean_mm": self.mean_mm, "stripe_noise_px": self.noise_px,
                "predicted_rms_mm": self.predicted_mm,
                "ratio": None if not np.isfinite(self.ratio) else self.ratio, "verdict": self.verdict}


@dataclass(frozen=True)
class _Prepared:
    """What an image's verdict needs besides the plane: its points, how 1 px across the stripe
    moves each (``delta_mm`` (N, 3)), its stripe noise and coverage."""

    image: StripeImage
    delta_mm: np.ndarray
    noise_px: float
    coverage: float


def _prepare(img: StripeImage, camera: Camera) -> _Prepared:
    p, uv = img.points_mm, img.uv_undistorted
    m, direction, nrm = tls_line(uv)
    noise = float(np.sqrt(np.mean(((uv - m) @ nrm) ** 2)))
    step = 0.1  # px across the stripe (the mapping is smooth: a small step is its derivative)
    xy = np.column_stack([uv + step * nrm, np.ones(len(uv))]) @ np.linalg.inv(camera.K).T
    delta = (ray_plane(xy[:, :2] / xy[:, 2:], img.target_normal, img.target_point_mm) - p) / step
    span = float(np.ptp((uv - m) @ direction))
    return _Prepared(img, delta, noise, len(p) / max(span, 1.0))


def _residual(pr: _Prepared, normal: np.ndarray, d: float, floor_mm: float) -> ImageResidual:
    """Image ``pr`` against the plane ``normal · X + d = 0``."""
    p = pr.image.points_mm
    r = p @ normal + d
    predicted = pr.noise_px * float(np.sqrt(np.nanmean((pr.delta_mm @ normal) ** 2)))
    rms = float(np.sqrt(np.mean(r**2)))
    over = rms > SUSPECT_RATIO * predicted
    verdict = "suspect" if over and rms > floor_mm else ("elevated" if over else "ok")
    return ImageResidual(pr.image.name, len(p), rms, float(np.mean(r)), pr.noise_px, predicted, pr.coverage, verdict)


@dataclass(frozen=True)
class PlaneQuality:
    """How a plane's images agree with their stripe noise (:func:`plane_quality`).

    ``images``: each image against the reference plane (``reference``: its ``(normal, d)``): the
    plane the agreeing images span when ``consensus`` (two thirds of the images or more agree on
    one), else the plane under test; ``floor_mm``: the suspect floor.  ``verdict``: ``"ok"``,
    ``"elevated"`` (some images above their noise, under the floor: kept with a warning) or
    ``"suspect"``.
    """

    images: tuple[ImageResidual, ...]
    floor_mm: float
    reference: tuple[np.ndarray, float]
    consensus: bool = True

    @property
    def suspect(self) -> tuple[ImageResidual, ...]:
        return tuple(r for r in self.images if r.verdict == "suspect")

    @property
    def elevated(self) -> tuple[ImageResidual, ...]:
        return tuple(r for r in self.images if r.verdict == "elevated")

    @property
    def verdict(self) -> str:
        return "suspect" if self.suspect else ("elevated" if self.elevated else "ok")

    def warnings(self) -> list[str]:
        """One line per elevated image (kept)."""
        return [f"{r.describe()} (kept: under the {self.floor_mm:.2g} mm floor; a board-pose error or a "
                "stripe biased along the board's pattern?)" for r in self.elevated]

    def diagnosis(self, background_per_image: bool = False) -> str:
        """One sentence naming the suspect images, how far off they are and the likely cause."""
        bad = self.suspect
        if not bad:
            return ""
        n = len(self.images)
        head = (f"the stripe points of {len(bad)} of {n} images contradict their stripe noise (more than "
                f"{SUSPECT_RATIO:g}x the predicted residual and over {self.floor_mm:.2g} mm)")
        head += (f", measured from the plane the other {n - len(bad)} agree on" if self.consensus
                 else "; no two thirds of the images agree on one plane")
        parts = [f"{r.describe()}; {r.cause(background_per_image)}" for r in bad[:4]]
        more = f"; and {len(bad) - 4} more" if len(bad) > 4 else ""
        return head + ": " + "; ".join(parts) + more

    def to_dict(self, kept: bool = False) -> dict:
        return {"verdict": self.verdict, "kept_by_request": bool(kept and self.suspect),
                "suspect_ratio": SUSPECT_RATIO, "floor_mm": self.floor_mm, "consensus": self.consensus,
                "images": [r.to_dict() for r in self.images]}


def plane_quality(camera: Camera, normal, d: float, images: Sequence[StripeImage], scale_mm: float) -> PlaneQuality:
    """Every image's stripe points against the plane ``normal · X + d = 0`` and their stripe noise.

    ``scale_mm``: the target's scale (square or dot pitch, disc diameter); the suspect floor is
    :data:`SUSPECT_FLOOR` times it.  When some image is suspect, the plane that most images
    agree with (proposed by every pair of images, refitted on those that agree) becomes the
    reference when two thirds of the images or more agree with it, and every image is judged
    against it.
    """
    n, d = np.asarray(normal, np.float64), float(d)
    floor = SUSPECT_FLOOR * float(scale_mm)
    prep = [_prepare(im, camera) for im in images if len(im.points_mm) >= 3]
    res = [_residual(p, n, d, floor) for p in prep]
    if not any(r.verdict == "suspect" for r in res) or len(prep) < 3:
        return PlaneQuality(tuple(res), floor, (n, d))
    best: tuple = (0, 0.0, None)
    for i, j in combinations(range(len(prep)), 2):
        try:
            ni, di, _ = fit_plane_tls(np.vstack([prep[i].image.points_mm, prep[j].image.points_mm]))
        except ValueError:
            continue
        rr = [_residual(p, ni, di, floor) for p in prep]
        agree = [r.verdict != "suspect" for r in rr]
        cost = sum(r.rms_mm for r, a in zip(rr, agree) if a)
        if sum(agree) > best[0] or (sum(agree) == best[0] and cost < best[1]):
            best = (sum(agree), cost, agree)
    agree = best[2]
    if agree is not None and 3 * best[0] >= 2 * len(prep):
        nr, dr, _ = fit_plane_tls(np.vstack([p.image.points_mm for p, a in zip(prep, agree) if a]))
        ref = [_residual(p, nr, dr, floor) for p in prep]
        if 3 * sum(r.verdict != "suspect" for r in ref) >= 2 * len(prep):
            return PlaneQuality(tuple(ref), floor, (nr, float(dr)))
    return PlaneQuality(tuple(res), floor, (n, d), consensus=False)


def check_plane_quality(quality: PlaneQuality, *, keep: bool, background_per_image: bool = False) -> dict:
    """The plane file's ``quality`` record, or LightplaneError with the diagnosis when some image is
    suspect and ``keep`` is False (with ``keep`` the record says ``kept_by_request`` and holds the
    diagnosis)."""
    if quality.suspect and not keep:
        raise LightplaneError(f"suspect light plane: {quality.diagnosis(background_per_image)}; remove those "
                              "images, or keep the plane as it is with --keep-suspect")
    rec = quality.to_dict(kept=keep)
    if quality.suspect:
        rec["diagnosis"] = quality.diagnosis(background_per_image)
    return rec


def working_volume(points_mm: np.ndarray) -> dict:
    """The plane file's ``working_volume``: where its calibration points lie (camera frame, mm): their
    depth range and centre, which a measurement reads (:mod:`lightplane.measure.profile`)."""
    p = np.asarray(points_mm, np.float64).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1)]
    return {"depth_mm": [float(p[:, 2].min()), float(p[:, 2].max())], "centre_mm": p.mean(axis=0).tolist(),
            "n_points": int(len(p)), "from": "the calibration's stripe points"}


#: a camera that sees the light plane at less than this angle (its line of sight to the calibration
#: points against the plane) measures depth poorly: the depth error grows as 1 / sin(angle)
MIN_TRIANGULATION_DEG = 10.0
#: stripes that spread across their own direction by less than this fraction of their length leave the
#: plane's tilt about that direction weakly determined
MIN_SPREAD_RATIO = 0.2
#: a plane whose normal's σ exceeds this (deg) is not a result
MAX_NORMAL_SIGMA_DEG = 5.0


def plane_geometry(points_mm: np.ndarray, image_index: np.ndarray, normal, d: float,
                   covariance: np.ndarray | None = None) -> dict:
    """What the calibration images' placements can determine of a light plane: the plane file's ``geometry``.

    ``points_mm`` (N, 3) the stripe points of all images (camera frame) and ``image_index`` (N,) the image
    of each.  In the plane, the points' extent along their main direction (``length_mm``, 4 x the RMS
    spread: the full length of a uniform spread) and across it (``width_mm``); the angle between the
    images' stripes (``stripe_angle_spread_deg``); the angle at which the camera looks at the plane at
    the points' centre (``triangulation_deg``); the normal's σ (deg) from ``covariance``.  ``warnings``
    say in words what is weakly determined and what to do; ``refusal`` (one sentence, or None) what
    the placements cannot determine at all: a normal σ over :data:`MAX_NORMAL_SIGMA_DEG` from stripes
    spread across their direction by less than :data:`MIN_SPREAD_RATIO` of their length (a σ that
    large from well-spread stripes is the images' fault, which :func:`plane_quality` judges).
    """
    p = np.asarray(points_mm, np.float64).reshape(-1, 3)
    idx = np.asarray(image_index).ravel()
    n = np.asarray(normal, np.float64).ravel()
    c = p.mean(axis=0)
    q = (p - c) - np.outer((p - c) @ n, n)  # in the plane
    lam = np.linalg.eigvalsh(q.T @ q / max(len(q), 1))
    length, width = 4.0 * np.sqrt(max(lam[2], 0.0)), 4.0 * np.sqrt(max(lam[1], 0.0))
    dirs = []
    for k in np.unique(idx):
        pk = q[idx == k]
        if len(pk) >= 3:
            U = np.linalg.eigh((pk - pk.mean(0)).T @ (pk - pk.mean(0)))[1]
            dirs.append(U[:, 2])
    ang = [np.degrees(np.arccos(min(1.0, abs(float(a @ b))))) for i, a in enumerate(dirs) for b in dirs[i + 1:]]
    tri = float(np.degrees(np.arcsin(min(1.0, abs(float(n @ c)) / max(float(np.linalg.norm(c)), 1e-300)))))
    sig = None
    if covariance is not None:
        sig = float(np.degrees(np.sqrt(max(np.trace(np.asarray(covariance)[:3, :3]), 0.0))))
    n_images = int(len(np.unique(idx)))
    spread_deg = float(max(ang, default=0.0))
    warnings: list[str] = []
    out: dict = {"length_mm": float(length), "width_mm": float(width), "stripe_angle_spread_deg": spread_deg,
                 "triangulation_deg": tri, "normal_sigma_deg": sig, "n_images": n_images, "warnings": warnings,
                 "refusal": None}
    if width < MIN_SPREAD_RATIO * length:
        warnings.append(
            f"the stripes of the {n_images} images spread {width:.3g} mm across them against {length:.3g} mm "
            f"along (at most {spread_deg:.1f} deg between them): the plane's tilt about their "
            "direction rests on that spread; move or turn the target between images (nearer and farther, tilted "
            "both ways) so that the stripes cover the working area")
    if tri < MIN_TRIANGULATION_DEG:
        warnings.append(
            f"the camera sees the light plane at {tri:.1f} deg (its line of sight to the calibration points against "
            f"the plane): depth errors grow as 1 / sin of it ({1 / max(np.sin(np.radians(tri)), 1e-9):.0f}x the "
            "image error's size); mount the camera 20-40 deg off the laser plane")
    if sig is not None and not sig <= MAX_NORMAL_SIGMA_DEG and width < MIN_SPREAD_RATIO * length:
        out["refusal"] = (f"the light plane is not determined by these {n_images} images (normal σ {sig:.3g} deg): "
                          f"their stripes spread {width:.3g} mm across their direction against {length:.3g} mm along it; "
                          "move or turn the target between images so that the stripes cover the working area")
    return out
