"""Light-plane calibration from images of a circular target (paper §2.2; docs/method.md §Overview to §Light plane).

The user's main job: images of a flat circular target of known diameter, each with
the laser stripe crossing it, and a calibrated camera in; the light plane with its
uncertainty and per-image diagnostics out.

Per image (in parallel across cores, :func:`observe_image`):

1. read it (PNG, JPEG, BMP, TIFF; 8/16-bit; gray or colour) and check its size
   against the camera;
2. detect ellipses (arc-support segments, docs/method.md §Ellipse) of a plausible size for a disc
   of ``diameter_mm`` seen at ``distance_range_mm``, and choose the target: the
   salient ellipse the stripe crosses (:func:`lightplane.ellipse.select_target`);
3. refine it to sub-pixel edge points (:func:`lightplane.ellipse.refine_ellipse`);
   edge points where the stripe meets the rim are dropped (the stripe's light
   shifts the edge there);
4. extract the stripe's centre points (Steger, docs/method.md §Stripe centres) inside the ellipse shrunk
   by a margin (the rim's intensity step biases the stripe centres next to it), and
   keep those on the stripe's line through the target.

Then all placements go to :func:`lightplane.plane.solvers.calibrate_plane_from_points`
(``paper``, ``global`` or ``ml``; docs/method.md §Light plane) with the rim edge points and the stripe
points, both in distorted pixels.  Every image's outcome is recorded: used, or
rejected with its reason (no target ellipse, no stripe crossing it, too few stripe
points, or the solver's reason); a file that cannot be read (truncated, corrupt, not an
image) is skipped the same way, with its reason, rather than stopping the calibration.
"""

from __future__ import annotations

import math
import os
import time
from concurrent.futures import Executor, ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, cast, Sequence

import numpy as np

from lightplane.camera.model import Camera, camera_record
from lightplane.core.errors import LightplaneError
from lightplane.core.geometry import default_workers, ray_plane, robust_line, robust_sigma, tls_line
from lightplane.plane.model import CameraDependence, LightPlane
from lightplane.plane.solvers import (PlacementResult, PlaneCalibration, SolverOptions, calibrate_plane_from_points,
                            check_calibration_args)
from lightplane.core.io import to_gray_float, too_few_images_message, try_read_image
from lightplane.core.threads import enter_serial, frames_across_threads
from lightplane.ellipse import (Ellipse, EllipseDetectionOptions, RefinedEllipse, detect_ellipses, expected_axis_range_px,
    refine_ellipse, select_target, stripe_crossing)
from lightplane.plane.circle_pose import CirclePose
from lightplane.plane.ml import dispersion_factor
from lightplane.plane.quality import (PlaneQuality, check_plane_quality, plane_geometry, plane_quality, stripe_image,
                                      working_volume)
from lightplane.plane.solvers import Ambiguity
from lightplane.plane.uncertainty import (WHICH_SIGMA, camera_param_names, camera_params, camera_share_status,
    camera_steps, camera_with_params, plane_noise_covers, point_sigma_mm, volume_sigma, working_volume_grid)
from lightplane.stripe.extract import extract_stripe
from lightplane.stripe.lasers import LaserSelector, no_stripe_message
from lightplane.stripe.options import StripePointsOptions
from lightplane.core.threads import with_blas_limited

__all__ = ["ObserveOptions", "PlaneCalibrationOptions", "ImageObservation", "ImagePlaneCalibration", "observe_image", "observe_image_lasers", "observe_images",
           "solve_observations", "calibrate_plane", "calibrate_planes", "stripe_width_along", "uncertainty_summary",
           "default_workers", "propagate_camera", "placement_quality", "stripe_line_scatter_px"]

@dataclass(frozen=True, eq=False)
class ImageObservation:
    """What one calibration image gave (before and after the plane solver).

    Attributes
    ----------
    index : position in the input list.
    source : file path, or ``"image[i]"`` for an array.
    ok : True when a target and enough stripe points were found (the image went to the solver).
    reason : why the image was skipped ("" when ``ok``), e.g. "no target ellipse found",
        "not a readable image (truncated)".
    used : True when its chord entered the final plane (set after the solver).
    shape : (H, W) of the image (``()`` when the file could not be read).
    ellipse : the target's image ellipse (distorted px) or None.
    conic_undistorted : (3, 3) the refined rim conic in undistorted px, or None.
    rim_uv : (M, 2) sub-pixel rim edge points, distorted px (empty if none).
    stripe_uv : (K, 2) stripe points on the target given to the solver, distorted px: averages
        of ``stripe_bin`` consecutive centres (see :func:`observe_image`) (empty if none).
    stripe_raw_uv : (K', 2) all stripe centre points kept on the target, distorted px.
    stripe_bin : centres averaged per solver point (1: none).
    chord_px : (2, 2) the stripe's chord through the ellipse as found by target selection, or None.
    rim_fit_rms_px : RMS distance of the rim points to their refined conic (px).
    n_candidates : ellipses detected in the image.
    placement : the solver's :class:`~lightplane.plane.solvers.PlacementResult` (``index`` = image index) or None.
    seconds : wall time spent on the image (reading included), s.
    """

    index: int
    source: str
    ok: bool
    reason: str
    used: bool = False
    shape: tuple = ()
    ellipse: Ellipse | None = None
    conic_undistorted: np.ndarray | None = field(default=None, repr=False)
    rim_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)), repr=False)
    stripe_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)), repr=False)
    stripe_raw_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)), repr=False)
    stripe_bin: int = 1
    chord_px: np.ndarray | None = field(default=None, repr=False)
    rim_fit_rms_px: float = float("nan")
    n_candidates: int = 0
    placement: PlacementResult | None = None
    seconds: float = 0.0

    @property
    def status(self) -> str:
        """``"used"`` or ``"skipped"`` (see ``reason``)."""
        return "used" if self.used else "skipped"

    @property
    def name(self) -> str:
        return Path(self.source).name if not self.source.startswith("image[") else self.source

    def to_dict(self) -> dict:
        """JSON-ready per-image diagnostics (the plane file's ``images`` entries)."""
        p = self.placement
        e = self.ellipse
        return {
            "index": self.index,
            "file": self.source,
            "status": self.status,
            "reason": self.reason if not self.used else "used",
            "n_rim": int(len(self.rim_uv)),
            "n_stripe": int(len(self.stripe_uv)) if p is None else int(p.n_stripe),
            "n_stripe_centres": int(len(self.stripe_raw_uv)),
            "stripe_bin": int(self.stripe_bin),
            "rim_fit_rms_px": _num(self.rim_fit_rms_px),
            "rim_residual_rms_px": None if p is None else _num(p.rim_rms_px),
            "stripe_residual_rms_px": None if p is None else _num(p.stripe_rms_px),
            "chord_rms_mm": None if p is None else _num(p.chord_rms_mm),
            "candidate": None if p is None else p.candidate,
            "pose": None if (p is None or p.pose is None) else p.pose.to_dict(),
            "ellipse_px": None if e is None else {"centre": [float(e.centre[0]), float(e.centre[1])],
                                                  "a": float(e.a), "b": float(e.b),
                                                  "angle_deg": float(np.degrees(e.angle))},
            "seconds": round(float(self.seconds), 4),
        }


    def to_record(self) -> dict:
        """Everything :mod:`lightplane.report.html` draws for this image, points included (exact; the
        plane file's ``report_inputs.images`` entries); :meth:`from_record` reads it back."""
        e = self.ellipse
        return {
            "index": int(self.index), "source": self.source, "ok": bool(self.ok), "reason": self.reason,
            "used": bool(self.used), "shape": [int(x) for x in self.shape],
            "ellipse": None if e is None else {"centre": [float(e.centre[0]), float(e.centre[1])],
                                               "a": float(e.a), "b": float(e.b), "angle_rad": float(e.angle)},
            "conic_undistorted": None if self.conic_undistorted is None else _pack(self.conic_undistorted),
            "rim_uv": _pack(self.rim_uv), "stripe_uv": _pack(self.stripe_uv),
            "stripe_raw_uv": _pack(self.stripe_raw_uv), "stripe_bin": int(self.stripe_bin),
            "chord_px": None if self.chord_px is None else _pack(self.chord_px),
            "rim_fit_rms_px": _num(self.rim_fit_rms_px), "n_candidates": int(self.n_candidates),
            "placement": None if self.placement is None else _placement_record(self.placement),
            "seconds": float(self.seconds),
        }

    @classmethod
    def from_record(cls, r: dict) -> "ImageObservation":
        """The observation :meth:`to_record` wrote."""
        e = r.get("ellipse")
        ell = None if e is None else Ellipse.from_params(e["centre"], e["a"], e["b"], e["angle_rad"])
        opt = {k: (None if r.get(k) is None else _unpack(r[k])) for k in ("conic_undistorted", "chord_px")}
        p = r.get("placement")
        return cls(index=int(r["index"]), source=str(r["source"]), ok=bool(r["ok"]), reason=str(r["reason"]),
                   used=bool(r["used"]), shape=tuple(int(x) for x in r["shape"]), ellipse=ell,
                   rim_uv=_unpack(r["rim_uv"]), stripe_uv=_unpack(r["stripe_uv"]),
                   stripe_raw_uv=_unpack(r["stripe_raw_uv"]), stripe_bin=int(r["stripe_bin"]),
                   rim_fit_rms_px=_nan(r.get("rim_fit_rms_px")), n_candidates=int(r.get("n_candidates", 0)),
                   placement=None if p is None else _placement_from_record(p), seconds=float(r["seconds"]), **opt)


# The stored inputs of the report (the plane file's ``report_inputs``): arrays as exact float64
# (little-endian, base64), so that a rebuilt report draws the very same points.
REPORT_INPUTS_VERSION = 1


def _pack(a) -> dict:
    import base64

    a = np.ascontiguousarray(a, dtype="<f8")
    return {"shape": list(a.shape), "float64_base64": base64.b64encode(a.tobytes()).decode("ascii")}


def _unpack(d: dict) -> np.ndarray:
    import base64

    shape = tuple(int(x) for x in d["shape"])
    a = np.frombuffer(base64.b64decode(d["float64_base64"], validate=True), dtype="<f8")
    return a.reshape(shape).astype(np.float64)


def _nan(x) -> float:
    return float("nan") if x is None else float(x)


def _pose_record(q) -> dict | None:
    return None if q is None else {"center_mm": [float(x) for x in q.center], "normal": [float(x) for x in q.normal],
                                   "radius_mm": float(q.radius_mm)}


def _pose_from_record(r):
    if r is None:
        return None
    return CirclePose(np.asarray(r["center_mm"], np.float64), np.asarray(r["normal"], np.float64),
                      float(r["radius_mm"]))


def _placement_record(p) -> dict:
    return {"index": int(p.index), "used": bool(p.used), "reason": p.reason, "candidate": p.candidate,
            "pose": _pose_record(p.pose), "poses": None if p.poses is None else [_pose_record(q) for q in p.poses],
            "n_rim": int(p.n_rim), "n_stripe": int(p.n_stripe), "rim_rms_px": _num(p.rim_rms_px),
            "stripe_rms_px": _num(p.stripe_rms_px), "chord_rms_mm": _num(p.chord_rms_mm)}


def _placement_from_record(r: dict):
    poses = r.get("poses")
    return PlacementResult(index=int(r["index"]), used=bool(r["used"]), reason=str(r["reason"]),
                           candidate=None if r.get("candidate") is None else int(r["candidate"]),
                           pose=_pose_from_record(r.get("pose")),
                           poses=None if poses is None else tuple(_pose_from_record(q) for q in poses),
                           n_rim=int(r["n_rim"]), n_stripe=int(r["n_stripe"]), rim_rms_px=_nan(r.get("rim_rms_px")),
                           stripe_rms_px=_nan(r.get("stripe_rms_px")), chord_rms_mm=_nan(r.get("chord_rms_mm")))


def _num(x) -> float | None:
    try:
        x = float(x)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


@dataclass(frozen=True)
class ImagePlaneCalibration(PlaneCalibration):
    """A :class:`~lightplane.plane.solvers.PlaneCalibration` computed from images, with per-image diagnostics.

    Extra attributes
    ----------------
    images : tuple of :class:`ImageObservation`, one per input image, in input order.
        ``placements`` (inherited) holds the solver's results of the images that reached
        it, with ``index`` = the image's index.
    camera : the :class:`~lightplane.camera.model.Camera` used.
    diameter_mm : target diameter, mm.
    seconds : wall time of the whole calibration, s.
    """

    images: tuple = ()
    camera: Camera | None = None
    diameter_mm: float = float("nan")
    seconds: float = 0.0

    @property
    def n_images(self) -> int:
        return len(self.images)

    def to_dict(self) -> dict:
        d = super().to_dict()
        d["images"] = [o.to_dict() for o in self.images]
        d["diameter_mm"] = self.diameter_mm
        d["n_images"] = self.n_images
        d["seconds"] = round(float(self.seconds), 3)
        return d

    def report_inputs(self) -> dict:
        """What :mod:`lightplane.report.html` needs to rebuild the report from the plane file alone
        (stored as its ``report_inputs``): the camera, the solver's summary and, per image, its
        name, size, ellipse, rim and stripe points, poses and residuals (not the image itself).
        :meth:`from_report_inputs` reads it back."""
        a = self.ambiguity
        return {
            "version": REPORT_INPUTS_VERSION,
            "camera": None if self.camera is None else self.camera.to_dict(),
            "method": self.method, "sigma_px": _num(self.sigma_px), "iterations": int(self.iterations),
            "covariance": None if self.covariance is None else _pack(self.covariance),
            "ambiguity": None if a is None else {"best_cost": _num(a.best_cost), "second_cost": _num(a.second_cost),
                                                 "ratio": _num(a.ratio), "separated": bool(a.separated),
                                                 "message": a.message},
            "warnings": list(self.warnings), "diameter_mm": float(self.diameter_mm), "seconds": float(self.seconds),
            "images": [o.to_record() for o in self.images],
        }

    @classmethod
    def from_report_inputs(cls, plane, inputs: dict, source: str = "plane file") -> "ImagePlaneCalibration":
        """The calibration :meth:`report_inputs` stored, around ``plane`` (a
        :class:`~lightplane.plane.model.LightPlane`); raises :class:`LightplaneError` on a malformed record."""
        try:
            version = int(inputs.get("version", 0))
            if version != REPORT_INPUTS_VERSION:
                raise LightplaneError(f"{source}: report_inputs version {version} is not supported "
                                      f"(this lightplane reads version {REPORT_INPUTS_VERSION})")
            images = tuple(ImageObservation.from_record(r) for r in inputs["images"])
            a = inputs.get("ambiguity")
            amb = None if a is None else Ambiguity(_nan(a.get("best_cost")), _nan(a.get("second_cost")),
                                                   _nan(a.get("ratio")), bool(a["separated"]), str(a["message"]))
            cam = inputs.get("camera")
            cov = inputs.get("covariance")
            return cls(plane=plane, covariance=None if cov is None else _unpack(cov),
                       sigma_px=_nan(inputs.get("sigma_px")),
                       placements=tuple(o.placement for o in images if o.placement is not None),
                       method=str(inputs["method"]), ambiguity=amb, warnings=tuple(inputs.get("warnings", ())),
                       iterations=int(inputs.get("iterations", 0)), images=images,
                       camera=None if cam is None else Camera.from_dict(cam, source=f"{source}: camera"),
                       diameter_mm=float(inputs["diameter_mm"]), seconds=float(inputs.get("seconds", 0.0)))
        except LightplaneError:
            raise
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            raise LightplaneError(f"{source}: field 'report_inputs' is malformed ({type(e).__name__}: {e})") from None


# ------------------------------------------------------------------------ per image
def _load(source, index: int) -> tuple[np.ndarray | None, str, str]:
    """``(image, name, "")``, or ``(None, name, reason)`` for a file that cannot be read."""
    if isinstance(source, np.ndarray):
        return source, f"image[{index}]", ""
    if isinstance(source, (str, os.PathLike)):
        img, reason = try_read_image(source)
        return img, str(source), reason
    raise LightplaneError(f"images[{index}] must be a file path or an image array, got {type(source).__name__}")


def _line_distance(uv: np.ndarray, p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    d = p1 - p0
    n = np.array([-d[1], d[0]]) / max(float(np.hypot(*d)), 1e-12)
    return (uv - p0) @ n


def _bin_along_line(uv: np.ndarray, k: int, min_bins: int = 12) -> tuple[np.ndarray, int]:
    """Averages of ``k`` consecutive points (ordered along their principal direction); ``k``
    is lowered so that at least ``min_bins`` averages remain.  Returns ``(points, k)``."""
    n = len(uv)
    k = int(max(1, min(k, n // min_bins if n >= min_bins else 1)))
    if k == 1:
        return uv, 1
    m, direction, _ = tls_line(uv)
    order = np.argsort((uv - m) @ direction)
    nb = n // k
    # spread the remainder: bins of k or k+1 points covering all points
    edges = np.linspace(0, n, nb + 1).round().astype(int)
    s = uv[order]
    out = np.array([s[a:b].mean(axis=0) for a, b in zip(edges[:-1], edges[1:])])
    return out, k


def _full_scale(img: np.ndarray) -> float:
    return 65535.0 if img.dtype == np.uint16 else (255.0 if img.dtype == np.uint8 or float(np.max(img)) > 1.0 else 1.0)


def _distance_inside(e, uv: np.ndarray) -> np.ndarray:
    """Approximate distance (px) of points inside ellipse ``e`` to its rim (first order in 1 - rho)."""
    d = uv - e.centre
    c, s = math.cos(e.angle), math.sin(e.angle)
    x = c * d[:, 0] + s * d[:, 1]
    y = -s * d[:, 0] + c * d[:, 1]
    rho = np.sqrt((x / e.a) ** 2 + (y / e.b) ** 2)
    g = np.hypot(x / e.a**2, y / e.b**2) / np.maximum(rho, 1e-9)  # |grad rho|
    return (1.0 - rho) / np.maximum(g, 1e-12)


def _robust_line(uv: np.ndarray, tol_px: float) -> np.ndarray:
    """Inlier mask of the total-least-squares line through ``uv`` with MAD rejection (>= tol_px)."""
    return robust_line(uv, refits=3, k_mad=4.0, min_tol=tol_px, center=True, min_points=3)[3]


def stripe_width_along(gray: np.ndarray, p0: np.ndarray, p1: np.ndarray, *, n: int = 24,
                       half_px: float = 25.0) -> tuple[float, float]:
    """Full width at half maximum (px) and height of a bright line along the segment ``p0``–``p1`` (px).

    Profiles across the segment at ``n`` positions of its middle 80 %, sampled every
    0.5 px (bilinear) up to ``half_px`` on each side; per profile the half level between
    the peak (within 8 px of the segment) and the lower of the two side backgrounds
    (median of the outer quarter).  Returns the medians of the widths (px) and of the
    peak heights above the background (grey levels); NaNs when no profile has a peak.
    Used instead of a whole-image estimate, which a bright target disc inflates.
    """
    import cv2

    d = np.asarray(p1, float) - np.asarray(p0, float)
    L = float(np.hypot(*d))
    if L < 4:
        return float("nan"), float("nan")
    d /= L
    nrm = np.array([-d[1], d[0]])
    s = np.linspace(0.1, 0.9, n) * L
    t = np.arange(-half_px, half_px + 0.25, 0.5)
    pts = p0 + s[:, None, None] * d + t[None, :, None] * nrm  # (n, T, 2)
    prof = cv2.remap(np.ascontiguousarray(gray, dtype=np.float32), pts[..., 0].astype(np.float32),
                     pts[..., 1].astype(np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    q = len(t) // 4
    centre = np.abs(t) <= 8.0
    widths, heights = [], []
    for row in prof:
        bg = min(float(np.median(row[:q])), float(np.median(row[-q:])))
        k = int(np.argmax(np.where(centre, row, -np.inf)))
        peak = float(row[k])
        if peak - bg < 5.0 / 255.0 * max(float(np.max(gray)), 1.0):
            continue
        half = bg + 0.5 * (peak - bg)
        i = k
        while i > 0 and row[i] > half:
            i -= 1
        j = k
        while j < len(row) - 1 and row[j] > half:
            j += 1
        if i == 0 or j == len(row) - 1:
            continue
        # linear interpolation of the two half-level crossings
        left = t[i] + (half - row[i]) / (row[i + 1] - row[i]) * 0.5
        right = t[j - 1] + (row[j - 1] - half) / (row[j - 1] - row[j]) * 0.5
        widths.append(right - left)
        heights.append(peak - bg)
    if not widths:
        return float("nan"), float("nan")
    return float(np.median(widths)), float(np.median(heights))


@dataclass(frozen=True)
class ObserveOptions:
    """Options of the per-image observation (:func:`observe_image`, :func:`observe_image_lasers`).

    Checked on construction; ``distance_range_mm`` is kept as two floats.

    - ``distance_range_mm``: (near, far) distances (mm) at which the target may be: the
      target's major semi-axis must lie in ``f r / far .. f r / near`` (+-15 %).
    - ``channel``: colour channel of the laser (``"red"``...) or None (weighted gray).
    - ``stripe_width_px``: stripe FWHM (px); estimated when None.
    - ``margin_px``: stripe points closer than this to the rim are dropped (the rim's
      intensity step biases them); default ``max(4, 1.5 FWHM)``.
    - ``min_stripe_points``: fewer stripe centres on the target's chord -> rejected.
    - ``stripe_bin``: ``"auto"`` or an int k >= 1: the solver gets the averages of k consecutive
      stripe centres along the chord (at least 12 of them); ``"auto"`` takes
      ``k = (sigma_stripe / sigma_rim)²`` (robust line-fit scatter over the rim fit's RMS).
      History: the joint ML refinement once weighed rim and stripe points with one common
      sigma, and this averaging made the stripe points as noisy as the rim's, which
      lowered ``ml``'s triangulation error by 10-25 %.  :func:`lightplane.plane.ml.refine_ml`
      now weighs each point type by its own long-run variance (sigma² times the
      integrated autocorrelation time: speckle makes a stripe's centres correlated along
      it, tau ~ 6 for raw centres on the realistic renders), so the averaging is no
      longer needed for accuracy.  Measured on 10 seeds x 2 polarities of 12-image
      realistic renders (benchmarks/bench_uncertainty.py): ``auto`` and ``1`` give the
      same errors (RMS triangulation 0.0043 vs 0.0046 mm, angle 0.0023 vs 0.0025 deg)
      and equally honest predicted sigmas (predicted / actual 0.95 vs 0.91); ``auto``
      stays the default because its solve is ~15 % faster (130 vs 153 ms).  ``1`` gives
      the solver the raw centres.  The chord is straight, so averaging along it loses
      nothing but resolution of the noise's correlation.
    """

    distance_range_mm: tuple[float, float] = (200.0, 1500.0)
    channel: str | None = None
    stripe_width_px: float | None = None
    margin_px: float | None = None
    min_stripe_points: int = 20
    stripe_bin: int | str = "auto"

    def __post_init__(self):
        try:
            lo, hi = float(self.distance_range_mm[0]), float(self.distance_range_mm[1])
        except (TypeError, ValueError, IndexError):
            lo, hi = float("nan"), float("nan")
        if not (0 < lo < hi):
            raise LightplaneError(f"distance_range_mm must be (near, far) with 0 < near < far, "
                                  f"got {self.distance_range_mm}")
        object.__setattr__(self, "distance_range_mm", (lo, hi))
        if self.stripe_bin != "auto":
            try:
                k = int(self.stripe_bin)
            except (TypeError, ValueError):
                raise LightplaneError(f"stripe_bin must be 'auto' or an integer >= 1, got {self.stripe_bin!r}") from None
            if k < 1:
                raise LightplaneError(f"stripe_bin must be 'auto' or an integer >= 1, got {self.stripe_bin!r}")


def observe_image(source, camera: Camera, diameter_mm: float, index: int = 0,
                  options: ObserveOptions | None = None) -> ImageObservation:
    """Find the target's rim points and the stripe points on it in one image (docs/method.md §Ellipse, §Stripe centres).

    Parameters
    ----------
    source : file path, or (H, W) / (H, W, 3) array (8/16-bit or float).
    camera : the camera (its image size is checked; rim points are undistorted for the conic).
    diameter_mm : target diameter (mm), for the plausible ellipse size.
    options : :class:`ObserveOptions`, optional (meanings there; defaults when omitted).

    Returns an :class:`ImageObservation` (``ok=False`` with a reason when the image
    cannot be used, its file unreadable included).  Raises :class:`LightplaneError` only
    for an image whose size differs from the camera's (a wrong camera, not a bad image).
    """
    return observe_image_lasers(source, camera, diameter_mm, index, None, options)[0]


def observe_image_lasers(source, camera: Camera, diameter_mm: float, index: int = 0, lasers=None,
                         options: ObserveOptions | None = None) -> list[ImageObservation]:
    """:func:`observe_image` for several lasers whose stripes cross the target in the same image.

    ``lasers``: :class:`lightplane.stripe.lasers.LaserSelector` s (colour channel and/or image region
    per laser), or None for one laser seen in ``options.channel`` (exactly :func:`observe_image`).
    The target is found once: the ellipses are detected in the image, the target is the
    ellipse most lasers' stripes cross (each laser's stripe looked for in its own channel and
    region), refined once; rim points near any laser's chord are dropped, so every laser's
    observation holds the same rim points (the same placement).  Then each laser's stripe
    centres are extracted on the target in its channel and region.  Returns one
    observation per laser (in order); a laser whose stripe misses the target gets
    ``ok=False`` with the reason while the others are kept.
    """
    opts = ObserveOptions() if options is None else options
    t0 = time.perf_counter()
    single = lasers is None
    sels = [LaserSelector("", opts.channel)] if single else [s for s in lasers]
    img, name, problem = _load(source, index)
    if img is None:
        return [ImageObservation(index=index, source=name, ok=False, reason=problem,
                                 seconds=time.perf_counter() - t0) for _ in sels]
    try:
        camera.check_image(img)
    except LightplaneError as e:
        raise LightplaneError(f"{name}: {e}") from None
    for s in sels:
        s.check_image(img, name)
    shape = tuple(img.shape[:2])
    found = _find_target(img, camera, diameter_mm, sels, single, opts.distance_range_mm)
    if isinstance(found, _NoTarget):
        return [ImageObservation(index=index, source=name, ok=False, reason=why, shape=shape,
                                 seconds=time.perf_counter() - t0, ellipse=found.ellipse,
                                 n_candidates=found.n_candidates) for why in found.reasons]
    per_laser = _laser_stripes(img, camera, sels, single, found, opts)
    # rim points where a stripe meets the rim are disturbed by its light (every laser's stripe)
    rim = found.ref.edge_points_px
    for chord, _, fwhm in per_laser:
        if chord is not None and len(rim):
            far = np.abs(_line_distance(rim, chord[0], chord[1])) > fwhm + 3.0
            if far.sum() >= 0.5 * len(rim):
                rim = rim[far]
    out = []
    for chord, uv, _ in per_laser:
        raw = uv
        uv, k = _binned(camera, uv, found.ref.residual_rms_px, opts.stripe_bin)
        obs = ImageObservation(index=index, source=name, ok=True, reason="", shape=shape,
                               seconds=time.perf_counter() - t0, ellipse=found.ref.image_ellipse,
                               conic_undistorted=found.ref.conic, rim_uv=rim, stripe_uv=uv, stripe_raw_uv=raw,
                               stripe_bin=k, chord_px=chord, rim_fit_rms_px=found.ref.residual_rms_px,
                               n_candidates=found.n_candidates)
        if len(raw) == 0:
            obs = replace(obs, ok=False, reason="no stripe crossing the target")
        elif len(raw) < opts.min_stripe_points:
            obs = replace(obs, ok=False, reason=f"too few stripe points ({len(raw)})")
        out.append(obs)
    return out


@dataclass(frozen=True)
class _NoTarget:
    """Why no target was found, per laser, and what was found on the way."""

    reasons: list
    ellipse: Ellipse | None = None
    n_candidates: int = 0


@dataclass(frozen=True)
class _Target:
    """The target found once for all lasers: its refined ellipse, each laser's stripe crossing (or
    None) and the ellipses detected."""

    ref: RefinedEllipse
    crossings: list
    n_candidates: int


def _find_target(img: np.ndarray, camera: Camera, diameter_mm: float, sels: list, single: bool,
                 distance_range_mm: tuple[float, float]) -> _Target | _NoTarget:
    """Detect the ellipses, choose the one most lasers' stripes cross and refine it (``single``: one
    laser, no selectors)."""
    lo, hi = expected_axis_range_px(camera, diameter_mm, distance_range_mm)
    # the minor semi-axis of a disc tilted by up to ~70 deg is >= a cos 70 deg
    ellipses = detect_ellipses(img, EllipseDetectionOptions(min_axis_px=max(0.35 * lo, 6.0), max_axis_px=hi))
    if not ellipses:
        return _NoTarget(["no target ellipse found" for _ in sels])
    # one laser with no region: its stripe is looked for in the image as given (as always)
    views = [img] if single or (len(sels) == 1 and sels[0].region is None) else [s.view(img) for s in sels]
    picks = [select_target(v, ellipses, axis_range_px=(lo, hi), min_chord_fraction=0.15) for v in views]
    chosen = [p.index for p in picks if p.ellipse is not None]
    if not chosen:
        why = {"stripe misses the target": "no stripe crossing the target",
               "no plausible ellipse": f"no target ellipse found (none of {len(ellipses)} ellipses has a "
                                       f"plausible size for a {diameter_mm:g} mm disc at "
                                       f"{distance_range_mm[0]:g}-{distance_range_mm[1]:g} mm)"}
        return _NoTarget([why.get(p.reason, p.reason or "no target ellipse found") for p in picks],
                         n_candidates=len(ellipses))
    # the target: the ellipse most lasers' stripes cross (ties: the first laser's choice)
    best = max(dict.fromkeys(chosen), key=chosen.count)
    target = ellipses[best]
    crossings: list = []  # per laser: its StripeCrossing, or None
    for p, v in zip(picks, views):
        if p.ellipse is not None and p.index == best:
            crossings.append(p.crossing)
        else:
            cr = stripe_crossing(v, target)
            crossings.append(cr if cr.crosses(0.5, 0.15) else None)
    try:
        ref = refine_ellipse(img, target, camera)
    except LightplaneError as e:
        return _NoTarget([f"target ellipse could not be refined ({e})" for _ in sels], target, len(ellipses))
    return _Target(ref, crossings, len(ellipses))


def _laser_stripes(img: np.ndarray, camera: Camera, sels: list, single: bool, found: _Target,
                   opts: ObserveOptions) -> list:
    """Per laser ``(chord, stripe centres on the target (distorted px), FWHM)``: Steger on a crop around
    the target, inside the ellipse shrunk by a margin."""
    e_img = found.ref.image_ellipse
    h, w = img.shape[:2]
    u0, v0, u1, v1 = e_img.bbox()
    pad = 12
    cu0, cv0 = max(int(math.floor(u0)) - pad, 0), max(int(math.floor(v0)) - pad, 0)
    cu1, cv1 = min(int(math.ceil(u1)) + pad, w - 1), min(int(math.ceil(v1)) + pad, h - 1)
    crop = np.ascontiguousarray(img[cv0:cv1 + 1, cu0:cu1 + 1])
    off = np.array([cu0, cv0], dtype=np.float64)
    local = type(e_img).from_params(e_img.centre - off, e_img.a, e_img.b, e_img.angle)
    inside_all = local.mask(crop.shape[:2], shrink_px=2.0)
    per_laser: list[tuple] = []
    for s, cr in zip(sels, found.crossings):
        chord = None if cr is None else cr.chord_px
        if chord is None and not single:
            per_laser.append((None, np.zeros((0, 2)), 5.0))
            continue
        uv, fwhm = _stripe_on_target(camera, crop, off, inside_all, e_img, s, chord, single, opts)
        per_laser.append((chord, uv, fwhm))
    return per_laser


def _stripe_on_target(camera: Camera, crop: np.ndarray, off: np.ndarray, inside_all: np.ndarray, e_img, s,
                      chord, single: bool, opts: ObserveOptions) -> tuple[np.ndarray, float]:
    """One laser's stripe centres (distorted px) on the target in ``crop`` (at ``off``) and its FWHM (px)."""
    cu0, cv0 = int(off[0]), int(off[1])
    inside = inside_all
    region = s.region_mask(crop.shape[:2], (cu0, cv0))
    if region is not None:
        inside = inside & region
    width, contrast = opts.stripe_width_px, None
    gray = s.outside_removed(to_gray_float(crop, s.channel), (cu0, cv0))
    if chord is not None:
        w_est, height = stripe_width_along(gray, chord[0] - off, chord[1] - off)
        if width is None and np.isfinite(w_est):
            width = float(np.clip(w_est, 2.0, 40.0))
        if np.isfinite(height):
            # a stripe on a dark disc is faint: threshold relative to what this stripe shows
            contrast = float(np.clip(0.35 * height, 2.0 / 255.0 * _full_scale(crop), None))
    # no along-stripe smoothing: the joint fit averages hundreds of centres itself, and its noise
    # model (white or correlated along the curve, measured from the residuals) was validated on
    # unsmoothed centres (benchmarks/bench_uncertainty.py)
    # several lasers: the stripe is read in its own channel alone; extract_stripe's centring of
    # whitish saturated cores (colour image + channel) takes the speckle dips of a colour stripe
    # on a bright white disc for cores and can drop the whole stripe (two-colour renders: one
    # stripe in 8 images lost)
    sp = extract_stripe(crop if single else gray,
                        StripePointsOptions(width_px=width, channel=s.channel if single else None,
                                            min_contrast=contrast, sigma_along_px=0.0), mask=inside)
    uv = sp.uv + off
    fwhm = float(width) if width is not None else float(sp.meta.get("width_px", 5.0))
    # the rim's intensity step inside Steger's kernel (about 3 sigma) shifts the centres
    margin = max(3.0, 3.0 * float(sp.sigma_px) + 1.0) if opts.margin_px is None else float(opts.margin_px)
    if len(uv):
        uv = uv[_distance_inside(e_img, uv) >= margin]
    if len(uv) and s.region is not None:
        uv = uv[s.in_region(uv)]
    if len(uv) and chord is not None:
        # keep the stripe's line through the target (clutter, reflections, rim fragments)
        uv = uv[np.abs(_line_distance(uv, chord[0], chord[1])) <= max(3.0, 0.6 * fwhm + 2.0)]
    if len(uv) >= 3:
        und = camera.undistort_points(uv)
        uv = uv[_robust_line(und, 0.5)]
    return uv, fwhm


def stripe_line_scatter_px(camera: Camera, uv: np.ndarray) -> float:
    """Robust scatter (px) of a target's stripe centres (distorted px) about their straight line: the chord
    of a flat target is straight in undistorted px, so the scatter is the centres' noise."""
    und = camera.undistort_points(uv)
    m, _, nrm = tls_line(und)
    return robust_sigma((und - m) @ nrm)


def _binned(camera: Camera, uv: np.ndarray, rim_rms_px: float, stripe_bin: int | str) -> tuple[np.ndarray, int]:
    """The solver's stripe points: averages of k consecutive centres (:func:`_bin_along_line`), k from
    ``stripe_bin`` (``"auto"``: the stripe's robust line scatter over the rim fit's RMS, squared)."""
    if len(uv) < 3:
        return uv, 1
    if stripe_bin == "auto":
        s_stripe = stripe_line_scatter_px(camera, uv)
        k = int(np.clip(round((s_stripe / max(rim_rms_px, 1e-3)) ** 2), 1, 50))
    else:
        k = int(stripe_bin)
    return _bin_along_line(uv, k, min_bins=12)


def _process_worker_init() -> None:
    import cv2

    enter_serial()
    cv2.setNumThreads(1)


def _observe_task(args):
    source, camera, diameter_mm, index, lasers, options = args
    try:
        if lasers is not None:
            return observe_image_lasers(source, camera, diameter_mm, index, lasers, options)
        return observe_image(source, camera, diameter_mm, index, options)
    except LightplaneError as e:
        return e


def _checked_inputs(images) -> list:
    """The calibration commands' cheap checks, before any work: the images as a list (one
    path or array becomes a list of one; none is an error; a missing file is an error, a
    folder or a bad file is skipped later with its reason)."""
    if isinstance(images, (str, os.PathLike, np.ndarray)):
        images = [images]
    images = list(images)
    if not images:
        raise LightplaneError("no images given")
    for i, src in enumerate(images):
        if isinstance(src, (str, os.PathLike)):
            if not Path(src).exists():  # a mistyped name
                raise LightplaneError(f"{src}: no such file")
        elif not isinstance(src, np.ndarray):
            raise LightplaneError(f"images[{i}] must be a file path or an image array, got {type(src).__name__}")
    return images


# ------------------------------------------------------------------------ public
@dataclass(frozen=True)
class PlaneCalibrationOptions:
    """Options of the light-plane calibration from images (:func:`calibrate_plane`, :func:`calibrate_planes`,
    :func:`observe_images`).  Checked on construction.

    - ``observe``: :class:`ObserveOptions`, the per-image observation's.
    - ``solver``: :class:`~lightplane.plane.solvers.SolverOptions`, the plane solver's.
    - ``min_placements``: fewest used placements accepted (>= 3 for a checked result).
    - ``workers``: processes (or threads) for the per-image work; None (default): all cores;
      1 runs in this process.
    - ``executor``: ``"thread"`` (default: OpenCV and the numba kernels release the GIL; on 2 cores
      12 images take ~1.0 s with threads against ~1.7 s with processes, whose workers each load the
      compiled kernels first; benchmarks/bench_calibrate.py) or ``"process"``.
    - ``keep_suspect``: keep a plane whose stripe points contradict their stripe noise
      (:mod:`lightplane.plane.quality`), marked in ``meta["quality"]``, instead of raising.
    """

    observe: ObserveOptions = field(default_factory=ObserveOptions)
    solver: SolverOptions = field(default_factory=SolverOptions)
    min_placements: int = 3
    workers: int | None = None
    executor: str = "thread"
    keep_suspect: bool = False

    def __post_init__(self):
        if not isinstance(self.observe, ObserveOptions):
            raise LightplaneError(f"observe must be ObserveOptions, got {type(self.observe).__name__}")
        if not isinstance(self.solver, SolverOptions):
            raise LightplaneError(f"solver must be SolverOptions, got {type(self.solver).__name__}")
        if self.executor not in ("process", "thread"):
            raise LightplaneError(f"executor must be 'process' or 'thread', got {self.executor!r}")


@with_blas_limited
def calibrate_plane(images: Sequence, camera: Camera, diameter_mm: float, method: str = "ml",
                    options: PlaneCalibrationOptions | None = None, *,
                    progress: Callable[[int, int], None] | None = None) -> ImagePlaneCalibration:
    """Calibrate the light plane from images of a circular target crossed by the stripe (paper §2.2).

    Parameters
    ----------
    images : sequence of file paths (PNG, JPEG, BMP, TIFF...) or arrays ((H, W) or
        (H, W, 3), 8/16-bit or float), one per target placement.
    camera : calibrated :class:`~lightplane.camera.model.Camera`; every image must have its size.
    diameter_mm : target diameter, mm (> 0).
    method : ``"ml"`` (default), ``"global"`` or ``"paper"`` (docs/method.md §Light plane; see
        :func:`~lightplane.plane.solvers.calibrate_plane_from_points`).
    options : :class:`PlaneCalibrationOptions`, optional: the per-image observation's options
        (``observe``, :class:`ObserveOptions`), the solver's (``solver``,
        :class:`~lightplane.plane.solvers.SolverOptions`), ``min_placements``, ``workers`` and
        ``executor`` (meanings there; defaults when omitted).
    progress : optional callable ``progress(done, total)`` after each image.

    Returns
    -------
    :class:`ImagePlaneCalibration` (a :class:`~lightplane.plane.solvers.PlaneCalibration`):
    the plane (covariance for ``ml``), per-image diagnostics in ``images``.

    Raises
    ------
    LightplaneError
        No images, a missing file among the paths, an image whose size
        differs from the camera's, fewer than ``min_placements`` usable images (the
        message counts them and groups the others' reasons, unreadable files included),
        placements too alike, or an unresolvable ambiguity.  An unreadable, truncated or
        non-image file is skipped with its reason like an image without the target.
    """
    t_start = time.perf_counter()
    opts = PlaneCalibrationOptions() if options is None else options
    diameter = check_calibration_args(method, camera, diameter_mm)
    images = _checked_inputs(images)
    obs = observe_images(images, camera, diameter, opts, progress=progress)
    return solve_observations(obs, camera, diameter, method, min_placements=opts.min_placements,
                              seconds=time.perf_counter() - t_start, solver=opts.solver, keep_suspect=opts.keep_suspect)


def calibrate_planes(images: Sequence, camera: Camera, diameter_mm: float, lasers: Sequence, method: str = "ml",
                     options: PlaneCalibrationOptions | None = None, *,
                     progress: Callable[[int, int], None] | None = None) -> dict:
    """One light plane per laser from the same images of a circular target (several lasers).

    ``lasers``: :class:`lightplane.stripe.lasers.LaserSelector` s; each laser's stripe is told apart
    by its colour channel, its image region and/or its frames (``frames:`` selects, among the
    image files, those that are the laser's).  Where several lasers' stripes cross the target
    in one image, the target is found once and both planes use the same rim points
    (:func:`observe_image_lasers`); each plane is then solved from its own stripes as
    :func:`calibrate_plane` does.  An image in which a laser's stripe is missing is skipped
    for that laser, with the reason.

    ``options``: :class:`PlaneCalibrationOptions` as for :func:`calibrate_plane` (``observe.channel``
    is not used: each laser's channel is its selector's).  Returns ``{name: ImagePlaneCalibration}`` in the order of ``lasers``.  Raises
    LightplaneError (nothing solved) for a laser whose stripe is found in none of its images,
    a laser with no images, or one with too few usable placements (the message names the laser).
    """
    t_start = time.perf_counter()
    opts = PlaneCalibrationOptions() if options is None else options
    diameter = check_calibration_args(method, camera, diameter_mm)
    images = _checked_inputs(images)
    lasers = list(lasers)
    if not lasers:
        raise LightplaneError("no lasers given")
    for s in lasers:
        if s.cycle is not None:
            raise LightplaneError(f"laser {s.name}: cycle:K selects laser frames per board pose (calibrate-plane-board "
                                  "with --cycle or --pattern); here use frames:PATTERN")
    per_image = _observe_by_lasers(images, camera, diameter, lasers, opts, progress)
    seconds = time.perf_counter() - t_start
    out = {}
    for k, s in enumerate(lasers):
        obs = [replace(per_image[i][k], index=j) for j, i in enumerate(i for i in range(len(images)) if k in per_image[i])]
        if not any(o.ok for o in obs):
            raise LightplaneError(no_stripe_message(s.name, s, len(obs), {o.name: o.reason for o in obs}))
        out[k] = obs
    result = {}
    for k, s in enumerate(lasers):
        try:
            result[s.name] = solve_observations(out[k], camera, diameter, method, min_placements=opts.min_placements,
                                                seconds=seconds, solver=opts.solver, keep_suspect=opts.keep_suspect)
        except LightplaneError as e:
            raise LightplaneError(f"laser {s.name}: {e}") from None
    return result


def _observe_by_lasers(images: list, camera: Camera, diameter: float, lasers: list, opts: PlaneCalibrationOptions,
                       progress: Callable[[int, int], None] | None) -> list[dict]:
    """Per image, ``{laser position: ImageObservation}`` of the lasers whose frame it is: each group of
    images seen by the same lasers observed together (:func:`observe_image_lasers`)."""
    takes = [tuple(k for k, s in enumerate(lasers) if s.takes_file(src)) if isinstance(src, (str, os.PathLike))
             else tuple(range(len(lasers))) for src in images]
    for k, s in enumerate(lasers):
        if not any(k in t for t in takes):
            raise LightplaneError(f"laser {s.name} ({s.text}): none of the {len(images)} images is one of its frames")
    per_image: list[dict] = [{} for _ in images]
    groups: dict[tuple, list[int]] = {}
    for i, t in enumerate(takes):
        if t:
            groups.setdefault(t, []).append(i)
    done = 0
    for t, idx in groups.items():
        def step(j, n, base=done):
            if progress is not None:
                progress(base + j, len(images))

        obs = observe_images([images[i] for i in idx], camera, diameter, opts, lasers=[lasers[k] for k in t],
                             progress=step)
        for i, o in zip(idx, obs):
            per_image[i] = dict(zip(t, cast(list, o)))
        done += len(idx)
    return per_image


def observe_images(images: Sequence, camera: Camera, diameter_mm: float, options: PlaneCalibrationOptions | None = None,
                   *, lasers: Sequence | None = None,
                   progress: Callable[[int, int], None] | None = None) -> list:
    """:func:`observe_image` (``lasers``: :func:`observe_image_lasers`) on every image, in parallel
    (``options.workers`` processes or threads, ``options.executor``; ``options.observe`` for each image).

    Unreadable files give skipped observations; raises :class:`LightplaneError` for the
    first image whose size differs from the camera's.
    """
    opts = PlaneCalibrationOptions() if options is None else options
    las = None if lasers is None else list(lasers)
    tasks = [(src, camera, float(diameter_mm), i, las, opts.observe) for i, src in enumerate(images)]
    n = len(tasks)
    n_workers = default_workers() if opts.workers is None else max(1, int(opts.workers))
    n_workers = min(n_workers, n)
    results: list = [None] * n
    if n_workers == 1:
        for k, t in enumerate(tasks):
            results[k] = _observe_task(t)
            if isinstance(results[k], LightplaneError):
                raise results[k]
            if progress is not None:
                progress(k + 1, n)
    else:
        # one level of parallelism: images across the workers, serial kernels in each (lightplane.core.threads)
        if opts.executor == "process":
            import multiprocessing as mp

            # spawn, not fork: forking a process that already ran OpenMP code (numba, OpenCV) aborts it
            pool: Executor = ProcessPoolExecutor(max_workers=n_workers, mp_context=mp.get_context("spawn"),
                                                 initializer=_process_worker_init)
        else:
            pool = ThreadPoolExecutor(max_workers=n_workers, initializer=enter_serial)
        with frames_across_threads(), pool:
            for k, res in enumerate(pool.map(_observe_task, tasks)):
                if isinstance(res, LightplaneError):
                    for f in getattr(pool, "_pending_work_items", {}).values():  # pragma: no cover
                        f.future.cancel()
                    raise res
                results[k] = res
                if progress is not None:
                    progress(k + 1, n)
    return results


def solve_observations(observations: Sequence[ImageObservation], camera: Camera, diameter_mm: float,
                       method: str = "ml", *, min_placements: int = 3, seconds: float = 0.0,
                       solver: SolverOptions | None = None, keep_suspect: bool = False) -> ImagePlaneCalibration:
    """The light plane from per-image observations (:func:`observe_images`) (docs/method.md §Light plane).

    Runs :func:`~lightplane.plane.solvers.calibrate_plane_from_points` on the images that gave
    a target and stripe points, and maps its per-placement results back to the images.
    Lets one set of observations be solved by several methods (``paper``, ``global``, ``ml``).
    Raises LightplaneError when some used image's stripe points contradict their stripe noise
    (:func:`placement_quality`), unless ``keep_suspect`` (the plane's ``meta["quality"]`` says so).
    """
    obs = list(observations)
    n = len(obs)
    diameter = float(diameter_mm)
    t_start = time.perf_counter()
    ok = [o for o in obs if o.ok]
    if len(ok) < min_placements:
        raise LightplaneError(too_few_images_message("images", len(ok), min_placements,
                                                     [(o.name, o.reason) for o in obs if not o.ok]))
    try:
        cal = calibrate_plane_from_points(camera, diameter, [o.rim_uv for o in ok], [o.stripe_uv for o in ok],
                                          method=method, options=solver, min_placements=min_placements)
    except LightplaneError as e:
        msg = str(e)
        # the solver names placements by their position among the usable images: name the files
        for j in sorted(range(len(ok)), reverse=True):
            msg = msg.replace(f"placement {j}:", f"{ok[j].name}:").replace(f"placement {j} ", f"{ok[j].name} ")
        rejected = [f"{o.name}: {o.reason}" for o in obs if not o.ok]
        if rejected:
            msg += " [rejected before the solver: " + "; ".join(rejected) + "]"
        raise LightplaneError(msg) from None
    placements = []
    final = list(obs)
    for j, o in enumerate(ok):
        pr = replace(cal.placements[j], index=o.index)
        placements.append(pr)
        reason = "" if pr.used else pr.reason.replace("rejected: ", "")
        final[o.index] = replace(o, used=bool(pr.used), placement=pr, reason=reason)
    warnings = []
    for w in cal.warnings:
        for j in sorted(range(len(ok)), reverse=True):
            w = w.replace(f"placement {j} ", f"{ok[j].name} ")
        warnings.append(w)
    warnings.extend(f"{o.name} not used: {o.reason}" for o in obs if not o.ok)
    meta = dict(cal.plane.meta)
    meta.update({"diameter_mm": diameter, "n_images": n, "camera": camera_record(camera)})
    dep = None
    if camera.covariance is not None and cal.covariance is not None:
        rims, stripes = [o.rim_uv for o in ok], [o.stripe_uv for o in ok]
        dep = propagate_camera(
            lambda cam: calibrate_plane_from_points(cam, diameter, rims, stripes, method=method, options=solver,
                                                    min_placements=min_placements).plane, camera, cal.plane)
        meta[CameraDependence.KEY] = dep.to_dict()
    cov = cal.covariance
    if dep is not None and meta.get("noise_model"):
        meta["noise_model"], f = _dispersion_beside_camera(meta["noise_model"], dep)
        cov = f * np.asarray(cov)
    q = placement_quality(camera, cal.plane, final, diameter)
    meta["quality"] = check_plane_quality(q, keep=keep_suspect)
    warnings.extend(q.warnings())
    pts = [im.points_mm for im in _stripe_images(camera, final)]
    if pts:
        meta["working_volume"] = working_volume(np.vstack(pts))
        meta["geometry"] = plane_geometry(np.vstack(pts), np.repeat(np.arange(len(pts)), [len(x) for x in pts]),
                                          cal.plane.normal, cal.plane.d, cov)
        if meta["geometry"]["refusal"] and not keep_suspect:
            raise LightplaneError(meta["geometry"]["refusal"] + "; or keep the plane as it is with --keep-suspect")
        warnings.extend(meta["geometry"]["warnings"])
    plane = type(cal.plane)(cal.plane.normal, cal.plane.d, cov, meta=meta)
    return ImagePlaneCalibration(plane=plane, covariance=plane.covariance, sigma_px=cal.sigma_px,
                                 placements=tuple(placements), method=cal.method, ambiguity=cal.ambiguity,
                                 warnings=tuple(warnings), iterations=cal.iterations, images=tuple(final),
                                 camera=camera, diameter_mm=diameter,
                                 seconds=seconds + time.perf_counter() - t_start)


def _stripe_images(camera: Camera, observations: Sequence[ImageObservation]) -> list:
    """The used placements' stripe points (the solver's inliers) on their discs' planes."""
    out = []
    for o in observations:
        p = o.placement
        if not o.used or p is None or p.pose is None or len(o.stripe_uv) < 3:
            continue
        uv = o.stripe_uv if p.stripe_inliers is None or len(p.stripe_inliers) != len(o.stripe_uv) \
            else o.stripe_uv[p.stripe_inliers]
        pts = ray_plane(camera.undistort_points(uv, normalized=True), p.pose.normal, p.pose.center)
        out.append(stripe_image(camera, o.source, pts, p.pose.normal, p.pose.center))
    return out


def placement_quality(camera: Camera, plane: LightPlane, observations: Sequence[ImageObservation],
                      diameter_mm: float) -> PlaneQuality:
    """Each used placement's stripe points (on its refined disc) against ``plane`` and their stripe noise
    (:func:`lightplane.plane.quality.plane_quality`, the disc's diameter as the target's scale)."""
    return plane_quality(camera, plane.normal, plane.d, _stripe_images(camera, observations), diameter_mm)


def _dispersion_beside_camera(nm: dict, dep: CameraDependence) -> tuple[dict, float]:
    """The images' dispersion against the noise model *and* the intrinsics' covariance: ``(noise model, factor)``.

    With a calibrated camera each image's pull on the plane also carries the intrinsics' error
    (it moves each image's pose and chord differently), which the camera's share already
    covers; measured against the noise model alone the dispersion would count it twice.  Its
    statistic ``T`` is quadratic in the intrinsics, so the re-solves of :func:`propagate_camera`
    give its expected part due to Cov(K): ``E_K = Σ_k (T(K + s_k) + T(K − s_k) − 2 T(K)) / 2``.
    The dispersion becomes ``T / (E + E_K)`` (``E``: the noise model's part): 1 when both the noise
    model and the intrinsics' covariance hold; an excess of the image noise shows diluted by
    ``E / (E + E_K)`` rather than counted twice.  ``factor``: the plane covariance's rescaling
    (new over old :func:`lightplane.plane.ml.dispersion_factor`, never below 1, where the
    covariance applies it, else 1).
    """
    T0, E, EK = dep.extra.get("image_dispersion_statistic"), nm.get("image_dispersion_expected"), dep.extra.get(
        "image_dispersion_camera_expected")
    if T0 is None or E is None or EK is None or not (np.isfinite(E) and E > 0 and np.isfinite(EK)):
        return nm, 1.0
    old = float(nm.get("image_dispersion") or 1.0)
    new = float(T0) / (float(E) + max(float(EK), 0.0))
    f_old = dispersion_factor(nm)
    out = dict(nm, image_dispersion=new, image_dispersion_noise_only=old,
               image_dispersion_camera_expected=max(float(EK), 0.0))
    if not nm.get("image_dispersion_applied"):
        return out, 1.0
    out["image_dispersion_factor"] = max(new, 1.0)
    return out, (out["image_dispersion_factor"] / f_old if f_old > 0 else 1.0)


def propagate_camera(solve: Callable[[Camera], LightPlane], camera: Camera, plane: LightPlane) -> CameraDependence:
    """The plane's dependence on the intrinsics, for the plane file (``camera_jacobian``).

    ``solve(camera)`` re-runs the whole plane calibration (circle poses, stripe rays,
    chord choice, ML) on the same image points with other intrinsics.  It is run at ±1
    sigma along each principal axis ``s_k`` of the camera's covariance; the central
    differences ``g_k = (plane(K + s_k) − plane(K − s_k)) / 2`` give
    ``J = G S⁺`` (4 x P, ``S`` the steps as columns): ``∂(a, b, c, d)/∂(fx, fy, cx, cy, dist)``
    within the span of the covariance.  Returns ``{"params", "matrix", "covariance_camera"
    (J Cov(K) Jᵀ, the plane's covariance due to the intrinsics alone), "method"}``.
    """
    def statistic(pl: LightPlane) -> float | None:  # the images' dispersion statistic of an ml solve
        nm = pl.meta.get("noise_model") or {}
        d, e = nm.get("image_dispersion"), nm.get("image_dispersion_expected")
        return None if d is None or e is None else float(d) * float(e)

    steps = camera_steps(camera)
    p0 = camera_params(camera)
    G = []
    T0 = statistic(plane)
    curv: list[float] | None = [] if T0 is not None and np.isfinite(T0) else None
    for s in steps:
        pl = [solve(camera_with_params(camera, p0 + sign * s)) for sign in (1.0, -1.0)]
        th = [q.coefficients for q in pl]
        if np.dot(th[0][:3], plane.normal) < 0 or np.dot(th[1][:3], plane.normal) < 0:
            raise LightplaneError("the plane's dependence on the intrinsics: a re-solve flipped the plane")
        G.append(0.5 * (th[0] - th[1]))
        if curv is not None and T0 is not None:
            tp, tm = statistic(pl[0]), statistic(pl[1])
            curv = None if tp is None or tm is None else curv + [0.5 * (tp + tm - 2 * T0)]
    J = np.array(G).T @ np.linalg.pinv(steps.T) if len(G) else np.zeros((4, len(p0)))
    C = J @ np.asarray(camera.covariance) @ J.T
    extra = {}
    if curv is not None:
        # the images' dispersion statistic's expected part due to the intrinsics' covariance (its second
        # differences along the same steps; see _dispersion_beside_camera)
        extra = {"image_dispersion_statistic": T0, "image_dispersion_camera_expected": float(np.sum(curv))}
    return CameraDependence(camera_param_names(camera), J, C, "central differences of the whole plane solve at "
                            "±1 sigma along the principal axes of the intrinsics' covariance", extra)


def uncertainty_summary(cal: PlaneCalibration, camera: Camera) -> dict:
    """The plane's uncertainty in the user's units (needs ``cal.covariance``, i.e. ``ml``).

    Returns a dict: ``normal_sigma_deg`` (the two principal standard deviations of the
    normal's direction, deg, largest first), ``d_sigma_mm``, ``working_distance_mm``
    (where the plane crosses the optical axis), ``point_sigma_axis_mm`` (sigma of a
    point triangulated there), ``distance_range_mm`` (the used targets' distances),
    ``point_sigma_rms_mm`` (camera frame) and ``shape_sigma_rms_mm`` (after the best
    rigid motion), RMS over the image region whose rays meet the plane in that range,
    with all the sources the files carry, and ``plane_only_sigma_rms_mm`` (the plane's
    image noise alone); ``covers`` says which sources each covers, ``camera_share``
    whether the camera's is included (it needs a camera file with a covariance).  With the
    camera's share also ``normal_sigma_with_camera_deg`` and ``d_sigma_with_camera_mm``
    (``normal_sigma_deg``, ``d_sigma_mm``: the plane's image noise only).  Empty without a
    covariance (:mod:`lightplane.plane.uncertainty`).
    """
    C = cal.covariance
    if C is None:
        return {}
    plane = cal.plane
    n = plane.normal
    ref = np.eye(3)[int(np.argmin(np.abs(n)))]
    e1 = np.cross(n, ref)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    B = np.column_stack([e1, e2])
    def principal_deg(M):
        w = np.linalg.eigvalsh(B.T @ np.asarray(M)[:3, :3] @ B)
        return [float(np.degrees(np.sqrt(max(x, 0.0)))) for x in w[::-1]]

    out: dict = {"normal_sigma_deg": principal_deg(C), "d_sigma_mm": float(np.sqrt(max(C[3, 3], 0.0)))}
    why_not = camera_share_status(camera, plane)
    if why_not is None:
        Ct = np.asarray(C) + plane.camera_dependence.covariance_camera  # type: ignore[union-attr]
        out["normal_sigma_with_camera_deg"] = principal_deg(Ct)
        out["d_sigma_with_camera_mm"] = float(np.sqrt(max(Ct[3, 3], 0.0)))
    out["camera_share"] = "included" if why_not is None else why_not
    p_axis = plane.point_on_axis()
    if np.all(np.isfinite(p_axis)) and p_axis[2] > 0:
        out["working_distance_mm"] = float(p_axis[2])
        uv = camera.project(p_axis[None])
        if np.all(np.isfinite(uv)):
            out["point_sigma_axis_mm"] = float(point_sigma_mm(camera, plane, uv)[0])
            out["point_sigma_axis_plane_only_mm"] = float(point_sigma_mm(camera, plane, uv, covariance=C)[0])
    dists = [float(np.linalg.norm(p.pose.center)) for p in cal.placements if p.used and p.pose is not None]
    if dists:
        rng = (min(dists), max(dists))
        if rng[1] - rng[0] < 1.0:
            rng = (rng[0] - 0.5, rng[1] + 0.5)
        out["distance_range_mm"] = [rng[0], rng[1]]
        try:
            vol = working_volume_grid(camera, plane, distance_mm=rng)
            vs = volume_sigma(camera, plane, vol)
            out["point_sigma_rms_mm"] = vs.camera_frame_mm
            out["shape_sigma_rms_mm"] = vs.shape_mm
            out["plane_only_sigma_rms_mm"] = vs.plane_only_mm
            out["covers"] = {
                "point_sigma_rms_mm": f"camera frame (absolute positions), RMS over the targets' range; {vs.covers}",
                "shape_sigma_rms_mm": f"after the best rigid motion over that volume (distances, heights, "
                                      f"flatness); {vs.covers}",
                "plane_only_sigma_rms_mm": f"camera frame; {plane_noise_covers(plane)} only (the camera "
                                           "taken as exact)",
                "which": WHICH_SIGMA}
        except LightplaneError:
            pass
    return out
