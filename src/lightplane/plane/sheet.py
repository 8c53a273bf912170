"""A light sheet that is not quite a plane: the calibrated plane plus a small curved part.

A line laser whose fan (Powell or cylinder) lens is tilted against the beam spreads its
rays over a circular cone with its apex at the source, tangent to the ideal plane along the
fan's centre ray.  With ``x`` along the centre ray from the apex, ``y`` across the fan and
``w`` along the normal, the cone is ``w (x0 + x') = tau y² / 2`` to first order in the
tilt ``tau`` (``x = x0 + x'``): a quadric, so the sheet is modelled as the height over the
calibrated plane

    w(u, v) = p0 + p1 u + p2 v + Q(u, v) / (1 + r_u u + r_v v),
    Q(u, v) = q_uu u² + q_uv u v + q_vv v²,

``(u, v)`` in-plane coordinates (mm, divided by :attr:`LightSheet.scale_mm`) about the
calibration points' centroid, ``v`` along ``n x z``: the stripe on a target facing the camera, the
direction across the fan when the laser, beside the camera, aims its fan's centre ray at the
field (:attr:`SheetOptions.frame`).  ``Q`` carries the curvature
(the cone's ``tau y² / (2 x0)``); the denominator is the quadric's in-plane x normal cross
term (the cone's ``1 / x``).  On a flat sheet ``Q = 0`` and ``r`` multiplies nothing: it
is unidentifiable and harmless, so it carries a prior: the laser beside the camera (the apex
where the camera centre's perpendicular meets the plane), σ :data:`R_PRIOR_SD` in scaled units,
about 40 % of the distance.  On a curved sheet the data refine it (a prior 4x wider costs 12 %
more triangulation error on the default sensor's simulated calibrations).

Which terms are fitted (:attr:`SheetOptions.terms`): by default ``q_vv`` and ``r_u``, the cone's
own two (its curvature across the fan and how it falls off with the distance from the laser).
``q_uv`` (the fan turned in the plane against ``v``) and ``q_uu`` are estimable only from the
small spread of the lines' directions and from the lines' offsets, which the targets' pose errors
blur: on the default sensor's simulated calibrations (12 placements, 0.01 deg and 0.01 mm pose
errors) fitting ``q_uv`` too doubles the triangulation error (0.015 against 0.008 mm RMS over the
field), while leaving it out costs 0.0014 mm RMS without noise.  A fan turned by an angle ``phi``
in its plane leaves ``2 phi`` times the curvature unmodelled: add ``q_uv`` for such a laser.  ``p`` is fixed by the
calibrated plane: the curved part is taken off its own least-squares plane over the
calibration points, so the sheet keeps the plane calibration's position and tilt and
their covariance, and adds the curvature's.

The curvature is estimated from the stripe points with every image's line free to move as a
whole: each image's stripe points get their own offset and slope along their line (the
pose error of a target moves its whole line), so only the shape *along* each line and its
change *across* lines count (:func:`fit_sheet`).  The flatness test asks whether the sag
across the field — the curvature along the lines times the squared half-length of the
points along them — differs from zero by more than :attr:`SheetOptions.z_curved` of its σ.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from lightplane.camera.model import as_points
from lightplane.core.errors import LightplaneError
from lightplane.core.geometry import ray_plane
from lightplane.plane.model import LightPlane

__all__ = ["LightSheet", "SheetOptions", "FlatnessTest", "SheetFit", "fit_sheet", "triangulate_sheet",
           "sheet_points_sigma_mm", "R_PRIOR_SD", "PARAM_NAMES", "circle_stripe_points", "board_stripe_points",
           "sheet_record"]

#: the prior σ of the cross terms ``r_u, r_v`` (scaled units): a cone's ``r`` is the scale over the
#: apex's distance, 0.1 for 50 mm at 500 mm; the prior's mean puts the laser beside the camera
#: (:attr:`SheetOptions.r_prior_mean`), this σ lets it be about 40 % nearer or farther
R_PRIOR_SD = 0.05
#: the parameters of :attr:`LightSheet.params`, in order
PARAM_NAMES = ("p0", "p1", "p2", "q_uu", "q_uv", "q_vv", "r_u", "r_v")


@dataclass(frozen=True)
class SheetOptions:
    """How the curved sheet is fitted and tested.

    ``z_curved``: the sag's significance (sag / σ) from which the test asks for the curved
    sheet (3: a flat sheet is called curved about 0.3 % of the time); ``r_prior_sd``: the
    cross terms' prior σ (scaled units); ``scale_mm``: the in-plane unit (conditioning only);
    ``correlation_lags``: how many neighbours along a stripe enter the residuals' correlation
    (stripe centres are correlated over a few pixels; the curvature's σ is widened by it);
    ``terms``: the curved terms fitted (always ``q_vv``; see the module's docstring);
    ``estimate``: ``per_image`` (the curvature from each line's shape, every image's offset and
    slope free) or ``joint`` (every term from every point at once: the lines' offsets count too,
    pose errors included); ``frame``: ``v`` along ``n x z`` (``camera``) or the lines' mean
    direction (``lines``); ``r_prior_mean``: the cross terms' prior mean, the laser beside the
    camera (``camera``) or none (``zero``, with a wider ``r_prior_sd``).
    """

    z_curved: float = 3.0
    r_prior_sd: float = R_PRIOR_SD
    scale_mm: float = 50.0
    correlation_lags: int = 8
    terms: tuple[str, ...] = ("q_vv", "r_u")
    estimate: str = "per_image"
    frame: str = "camera"
    r_prior_mean: str = "camera"

    def __post_init__(self) -> None:
        if not set(self.terms) <= set(PARAM_NAMES[3:]) or "q_vv" not in self.terms:
            raise LightplaneError(f"SheetOptions.terms must hold q_vv and name curved terms of {PARAM_NAMES[3:]}, "
                                  f"got {self.terms!r}")
        for name in ("z_curved", "r_prior_sd", "scale_mm"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise LightplaneError(f"SheetOptions.{name} must be a positive number, got {v!r}")
        if self.estimate not in ("per_image", "joint"):
            raise LightplaneError(f"SheetOptions.estimate must be 'per_image' or 'joint', got {self.estimate!r}")
        if self.r_prior_mean not in ("camera", "zero"):
            raise LightplaneError(f"SheetOptions.r_prior_mean must be 'camera' or 'zero', got {self.r_prior_mean!r}")
        if self.frame not in ("camera", "lines"):
            raise LightplaneError(f"SheetOptions.frame must be 'camera' or 'lines', got {self.frame!r}")
        if not 0 <= int(self.correlation_lags) <= 100:
            raise LightplaneError(f"SheetOptions.correlation_lags must be within 0..100, got {self.correlation_lags!r}")


@dataclass(frozen=True, eq=False)
class LightSheet:
    """The sheet: the calibrated ``plane`` plus the curved height ``w(u, v)`` of the module's docstring.

    ``origin`` (3,) mm on the plane, ``axes`` (2, 3) the unit in-plane ``u, v`` directions,
    ``scale_mm`` the in-plane unit, ``params`` (8,) :data:`PARAM_NAMES` (``p`` in mm, ``q`` in mm
    per scaled unit², ``r`` per scaled unit), ``covariance`` (8, 8) or None.
    """

    plane: LightPlane
    origin: np.ndarray
    axes: np.ndarray
    scale_mm: float
    params: np.ndarray
    covariance: np.ndarray | None = None
    meta: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        o = np.asarray(self.origin, np.float64).reshape(3)
        ax = np.asarray(self.axes, np.float64).reshape(2, 3)
        th = np.asarray(self.params, np.float64).reshape(len(PARAM_NAMES))
        if not (np.all(np.isfinite(o)) and np.all(np.isfinite(ax)) and np.all(np.isfinite(th))):
            raise LightplaneError("a light sheet's origin, axes and parameters must be finite")
        if not np.allclose(ax @ ax.T, np.eye(2), atol=1e-6) or np.max(np.abs(ax @ self.plane.normal)) > 1e-6:
            raise LightplaneError("a light sheet's axes must be orthonormal and in its plane")
        if not (np.isfinite(self.scale_mm) and self.scale_mm > 0):
            raise LightplaneError(f"a light sheet's scale must be positive, got {self.scale_mm!r}")
        object.__setattr__(self, "origin", o)
        object.__setattr__(self, "axes", ax)
        object.__setattr__(self, "params", th)
        if self.covariance is not None:
            C = np.asarray(self.covariance, np.float64)
            if C.shape != (8, 8) or not np.all(np.isfinite(C)):
                raise LightplaneError(f"a light sheet's covariance must be a finite 8x8 matrix, got {C.shape}")
            object.__setattr__(self, "covariance", C)

    def local(self, points: np.ndarray) -> np.ndarray:
        """``(u, v, w)`` (N, 3) of camera-frame points: scaled in-plane coordinates and mm off the plane."""
        p = as_points(points, 3, "points")
        q = p - self.origin
        return np.column_stack([q @ self.axes[0] / self.scale_mm, q @ self.axes[1] / self.scale_mm,
                                p @ self.plane.normal + self.plane.d])

    def height(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """``w(u, v)`` (mm) at scaled in-plane coordinates."""
        return _height(self.params, u, v)

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """How far (mm) points lie off the sheet along the plane's normal."""
        uvw = self.local(points)
        return uvw[:, 2] - self.height(uvw[:, 0], uvw[:, 1])

    def to_dict(self) -> dict:
        return {"model": "plane + Q(u, v) / (1 + r_u u + r_v v)", "origin_mm": self.origin.tolist(),
                "axes": self.axes.tolist(), "scale_mm": self.scale_mm, "param_names": list(PARAM_NAMES),
                "params": self.params.tolist(),
                "covariance": None if self.covariance is None else self.covariance.tolist(), **self.meta}

    @classmethod
    def from_dict(cls, plane: LightPlane, rec: dict, source: str = "plane file") -> "LightSheet":
        """The sheet a plane file's ``sheet`` record describes over its ``plane``."""
        if not isinstance(rec, dict):
            raise LightplaneError(f"{source}: field 'sheet' must be a mapping")
        try:
            cov = rec.get("covariance")
            meta = {k: v for k, v in rec.items()
                    if k not in ("model", "origin_mm", "axes", "scale_mm", "param_names", "params", "covariance")}
            return cls(plane, np.asarray(rec["origin_mm"], float), np.asarray(rec["axes"], float),
                       float(rec["scale_mm"]), np.asarray(rec["params"], float),
                       None if cov is None else np.asarray(cov, float), meta)
        except (KeyError, TypeError, ValueError) as e:
            raise LightplaneError(f"{source}: field 'sheet' is not a light sheet ({e})") from None


def _height(th: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    q = th[3] * u * u + th[4] * u * v + th[5] * v * v
    return th[0] + th[1] * u + th[2] * v + q / (1.0 + th[6] * u + th[7] * v)


def _height_jacobian(th: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``∂w / ∂params`` (N, 8)."""
    den = 1.0 + th[6] * u + th[7] * v
    q = th[3] * u * u + th[4] * u * v + th[5] * v * v
    one = np.ones_like(u)
    return np.column_stack([one, u, v, u * u / den, u * v / den, v * v / den, -q * u / den**2, -q * v / den**2])


def _height_gradient(th: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(∂w/∂u, ∂w/∂v)`` at scaled coordinates."""
    den = 1.0 + th[6] * u + th[7] * v
    q = th[3] * u * u + th[4] * u * v + th[5] * v * v
    gu = th[1] + (2 * th[3] * u + th[4] * v) / den - q * th[6] / den**2
    gv = th[2] + (th[4] * u + 2 * th[5] * v) / den - q * th[7] / den**2
    return gu, gv


@dataclass(frozen=True)
class FlatnessTest:
    """Is the plane enough?  ``sag_mm`` ± ``sag_sigma_mm``: the sheet's departure along the stripe lines
    over half their extent (``half_length_mm``) from the straight line, σ from the per-image model;
    ``z`` = sag / σ; ``curved``: ``|z| >= z_curved``; ``sigma_mm``: the points' noise (mm, along the
    normal) and ``correlation_factor`` the widening of the σ for their correlation along a stripe;
    ``chi2`` with ``dof``: every estimable curvature term against zero."""

    sag_mm: float
    sag_sigma_mm: float
    z: float
    curved: bool
    half_length_mm: float
    sigma_mm: float
    correlation_factor: float
    chi2: float
    dof: int
    images: int
    points: int

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


@dataclass(frozen=True)
class SheetFit:
    """The fitted sheet and its flatness test."""

    sheet: LightSheet
    test: FlatnessTest


def _frame(plane: LightPlane, groups: list[np.ndarray], how: str) -> tuple[np.ndarray, np.ndarray]:
    """Origin (the points' centroid on the plane) and axes: ``v`` along ``n x z`` (``camera``: the stripe on a
    target facing the camera) or the lines' mean direction (``lines``)."""
    allp = np.vstack(groups)
    n = plane.normal
    c = allp.mean(axis=0)
    c = c - (c @ n + plane.d) * n
    ev = np.cross(n, [0.0, 0.0, 1.0])
    if how == "camera" and np.linalg.norm(ev) > 1e-6:
        ev /= np.linalg.norm(ev)
        return c, np.array([np.cross(ev, n), ev])
    M = np.zeros((3, 3))
    for g in groups:
        q = g - g.mean(axis=0)
        q = q - np.outer(q @ n, n)
        M += q.T @ q
    w, V = np.linalg.eigh(M)
    ev = V[:, -1] - (V[:, -1] @ n) * n
    ev /= np.linalg.norm(ev)
    return c, np.array([np.cross(ev, n), ev])


def _profile_images(cols: np.ndarray, w: np.ndarray, idx: list[np.ndarray], t: list[np.ndarray]):
    """Columns and data with each image's offset and slope along its line taken out."""
    Xr, wr = np.empty_like(cols), np.empty_like(w)
    for k, t_k in zip(idx, t):
        B = np.column_stack([np.ones(len(k)), t_k])
        P = np.linalg.lstsq(B, np.column_stack([cols[k], w[k]]), rcond=None)[0]
        R = np.column_stack([cols[k], w[k]]) - B @ P
        Xr[k], wr[k] = R[:, :-1], R[:, -1]
    return Xr, wr


def _correlation_factor(res: np.ndarray, idx: list[np.ndarray], t: list[np.ndarray], lags: int) -> float:
    """``1 + 2 Σ ρ_k`` (Bartlett weights) of the residuals along each line: the variance of a sum's widening."""
    if lags == 0:
        return 1.0
    num, den = np.zeros(lags), 0.0
    for k, t_k in zip(idx, t):
        r = res[k][np.argsort(t_k)]
        den += float(r @ r)
        for j in range(1, min(lags, len(r) - 1) + 1):
            num[j - 1] += float(r[:-j] @ r[j:])
    rho = num / max(den, 1e-300)
    f = 1.0 + 2.0 * float(np.sum((1.0 - np.arange(1, lags + 1) / (lags + 1)) * rho))
    return max(f, 1.0)


def fit_sheet(plane: LightPlane, points_mm: Sequence[np.ndarray], options: SheetOptions = SheetOptions(),
              *, iterations: int = 8) -> SheetFit:
    """The curved sheet over the calibrated ``plane`` from each image's stripe points (camera frame, mm).

    The curvature ``q`` and cross terms ``r`` are fitted with every image's offset and slope along
    its line free (Gauss-Newton, ``r`` with its prior); their covariance is the fit's, its noise
    the residuals' (widened for their correlation along a stripe).  ``p`` takes the curved part off
    its least-squares plane over the points, and its covariance is the plane's (mapped to ``p``)
    plus what the curvature's error moves it by.  The flatness test (:class:`FlatnessTest`) comes
    with it.
    """
    groups = [as_points(g, 3, "points_mm") for g in points_mm]
    groups = [g[np.all(np.isfinite(g), axis=1)] for g in groups]
    groups = [g for g in groups if len(g) >= 6]
    if len(groups) < 3:
        raise LightplaneError(f"a curved sheet needs the stripe points of at least 3 images (6+ points each), "
                              f"got {len(groups)}")
    c, axes = _frame(plane, groups, options.frame)
    sheet0 = LightSheet(plane, c, axes, options.scale_mm, np.zeros(8))
    uvw = sheet0.local(np.vstack(groups))
    u, v, w = uvw[:, 0], uvw[:, 1], uvw[:, 2]
    sizes = np.cumsum([0] + [len(g) for g in groups])
    idx = [np.arange(a, b) for a, b in zip(sizes[:-1], sizes[1:])]
    t = [v[k] - v[k].mean() for k in idx]
    n, m = len(w), len(groups)
    th = np.zeros(8)
    prior = np.zeros(5)
    prior[3:] = 1.0 / options.r_prior_sd**2
    mean = np.zeros(5)
    if options.r_prior_mean == "camera":
        # the apex (the laser) beside the camera: where the camera centre's perpendicular meets the plane
        to_c = c + plane.d * plane.normal
        mean[3:] = options.scale_mm * (axes @ to_c) / float(to_c @ to_c)
    th[3:] = mean
    free = np.array([name in options.terms for name in PARAM_NAMES[3:]])
    for _ in range(iterations):
        J = _height_jacobian(th, u, v)[:, 3:] * free
        res = w - _height(th, u, v)
        Xr, wr = _profile_images(J, res, idx, t)
        H = Xr.T @ Xr
        sig2 = float(wr @ wr) / max(n - 2 * m - 5, 1)
        step = np.zeros(5)
        step[free] = np.linalg.solve((H + sig2 * np.diag(prior))[np.ix_(free, free)],
                                     (Xr.T @ wr - sig2 * prior * (th[3:] - mean))[free])
        th[3:] += step
        if np.max(np.abs(step[:3])) < 1e-9 and np.max(np.abs(step[3:])) < 1e-7:
            break
    J = _height_jacobian(th, u, v)[:, 3:] * free
    Xr, wr = _profile_images(J, w - _height(th, u, v), idx, t)
    sig2 = float(wr @ wr) / max(n - 2 * m - int(free.sum()), 1)
    corr = _correlation_factor(wr, idx, t, int(options.correlation_lags))
    C_qr = np.zeros((5, 5))
    C_qr[np.ix_(free, free)] = corr * sig2 * np.linalg.inv((Xr.T @ Xr + sig2 * np.diag(prior))[np.ix_(free, free)])
    th, C = _plane_part(plane, c, axes, options.scale_mm, th, C_qr, u, v)
    test = _flatness(th, C, Xr, wr, sig2 * corr, v, idx, options, (n, m), corr)
    if options.estimate == "joint":
        th, C = _joint_fit(th, u, v, w, free, (prior, mean), corr, iterations)
    meta = {"method": "curved sheet over the calibrated plane", "flatness_test": test.to_dict()}
    return SheetFit(LightSheet(plane, c, axes, options.scale_mm, th, C, meta), test)


def _joint_fit(th: np.ndarray, u: np.ndarray, v: np.ndarray, w: np.ndarray, free: np.ndarray,
               prior_mean: tuple[np.ndarray, np.ndarray], corr: float, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """Every free parameter from every point at once (the lines' offsets and their change across the
    field inform the curvature too), Gauss-Newton from the per-image fit; covariance from the residuals."""
    th = th.copy()
    prior, mean = prior_mean
    mask = np.concatenate([np.ones(3, bool), free])
    P = np.diag(np.concatenate([np.zeros(3), prior]))[np.ix_(mask, mask)]
    m = np.concatenate([np.zeros(3), mean])[mask]
    n = len(w)
    for _ in range(iterations):
        J = _height_jacobian(th, u, v)[:, mask]
        res = w - _height(th, u, v)
        sig2 = float(res @ res) / max(n - int(mask.sum()), 1)
        step = np.linalg.solve(J.T @ J + sig2 * P, J.T @ res - sig2 * P @ (th[mask] - m))
        th[mask] += step
        if np.max(np.abs(step)) < 1e-10:
            break
    J = _height_jacobian(th, u, v)[:, mask]
    res = w - _height(th, u, v)
    sig2 = float(res @ res) / max(n - int(mask.sum()), 1)
    C = np.zeros((8, 8))
    C[np.ix_(mask, mask)] = corr * sig2 * np.linalg.inv(J.T @ J + sig2 * P)
    return th, C


def _plane_part(plane: LightPlane, c: np.ndarray, axes: np.ndarray, scale: float, th: np.ndarray, C_qr: np.ndarray,
                u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``p`` that takes the curved part off its least-squares plane, and the full 8x8 covariance."""
    X = np.column_stack([np.ones_like(u), u, v])
    th = th.copy()
    th[:3] = 0.0
    curved = _height(th, u, v)
    pinv = np.linalg.pinv(X)
    th[:3] = -pinv @ curved
    A = -pinv @ _height_jacobian(th, u, v)[:, 3:]       # ∂p/∂(q, r)
    C = np.zeros((8, 8))
    C[3:, 3:] = C_qr
    C[:3, 3:] = A @ C_qr
    C[3:, :3] = C[:3, 3:].T
    C[:3, :3] = A @ C_qr @ A.T
    if plane.covariance is not None:
        # a plane (n + dn, d + dd) is w = -(dn·c + dd) - (dn·e_u) s u - (dn·e_v) s v over (u, v, w)
        B = np.zeros((3, 4))
        B[0, :3], B[0, 3] = -c, -1.0
        B[1, :3], B[2, :3] = -axes[0] * scale, -axes[1] * scale
        C[:3, :3] += B @ plane.covariance @ B.T
    return th, C


def _flatness(th: np.ndarray, C: np.ndarray, Xr: np.ndarray, wr: np.ndarray, s2: float, v: np.ndarray,
              idx: list[np.ndarray], options: SheetOptions, nm: tuple[int, int], corr: float) -> FlatnessTest:
    """The sag along the lines (``q_vv`` times the lines' squared half-length) against its σ, and the χ² of ``q``."""
    half = float(np.median([0.5 * (v[k].max() - v[k].min()) for k in idx]))
    sag = th[5] * half**2
    sd = float(np.sqrt(C[5, 5])) * half**2
    # χ² of the curvature terms alone (r fixed at its value): estimable directions only
    H = Xr[:, :3].T @ Xr[:, :3] / s2
    lam, V = np.linalg.eigh(H)
    keep = lam > 1e-9 * lam.max()
    b = V[:, keep].T @ (Xr[:, :3].T @ (wr + Xr[:, :3] @ th[3:6])) / s2
    chi2 = float(np.sum(b**2 / lam[keep]))
    z = sag / sd if sd > 0 else float("inf")
    return FlatnessTest(float(sag), sd, float(z), bool(abs(z) >= options.z_curved), half * options.scale_mm,
                        float(np.sqrt(s2 / corr)), corr, chi2, int(keep.sum()), nm[1], nm[0])


def triangulate_sheet(sheet: LightSheet, xy: np.ndarray, *, iterations: int = 6) -> np.ndarray:
    """Points (N, 3) mm where the rays ``(x, y, 1)`` (normalised, undistorted) meet the sheet: Newton on the
    ray's depth from the plane's solution; NaN where the ray grazes the plane or the sheet is behind the camera."""
    xy = as_points(xy, 2, "xy")
    r = np.column_stack([xy, np.ones(len(xy))])
    n, d = sheet.plane.normal, sheet.plane.d
    rn = r @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -d / rn
        ru, rv = (r @ sheet.axes[0]) / sheet.scale_mm, (r @ sheet.axes[1]) / sheet.scale_mm
        cu, cv = sheet.origin @ sheet.axes[0] / sheet.scale_mm, sheet.origin @ sheet.axes[1] / sheet.scale_mm
        for _ in range(iterations):
            u, v = s * ru - cu, s * rv - cv
            f = s * rn + d - _height(sheet.params, u, v)
            gu, gv = _height_gradient(sheet.params, u, v)
            s = s - f / (rn - gu * ru - gv * rv)
    bad = ~(np.abs(rn) >= 1e-3 * np.linalg.norm(r, axis=1)) | ~(s > 0)
    s[bad] = np.nan
    return r * s[:, None]


def sheet_points_sigma_mm(sheet: LightSheet, xy: np.ndarray) -> np.ndarray:
    """σ (mm, ``sqrt(trace Cov X)``) of the points :func:`triangulate_sheet` gives for rays ``xy``, from the
    sheet's covariance (the plane's and the curvature's): ``X = s r``, ``∂s/∂θ = (∂w/∂θ) / f'(s)``."""
    xy = as_points(xy, 2, "xy")
    if sheet.covariance is None:
        return np.full(len(xy), np.nan)
    X = triangulate_sheet(sheet, xy)
    r = np.column_stack([xy, np.ones(len(xy))])
    uvw = sheet.local(np.nan_to_num(X))
    u, v = uvw[:, 0], uvw[:, 1]
    gu, gv = _height_gradient(sheet.params, u, v)
    fprime = r @ sheet.plane.normal - (gu * (r @ sheet.axes[0]) + gv * (r @ sheet.axes[1])) / sheet.scale_mm
    g = _height_jacobian(sheet.params, u, v) / fprime[:, None]
    q = np.einsum("ij,jk,ik->i", g, sheet.covariance, g)
    out = np.sqrt(np.einsum("ij,ij->i", r, r) * np.maximum(q, 0.0))
    out[~np.isfinite(X[:, 0])] = np.nan
    return out


def circle_stripe_points(calibration) -> list[np.ndarray]:
    """Each used placement's stripe points (camera frame, mm) of a circle-target calibration
    (:class:`lightplane.plane.calibrate.ImagePlaneCalibration`): the solver's inlier stripe centres on
    their refined discs' planes."""
    out = []
    for o in calibration.images:
        p = o.placement
        if not o.used or p is None or p.pose is None or len(o.stripe_uv) < 3:
            continue
        uv = o.stripe_uv
        if p.stripe_inliers is not None and len(p.stripe_inliers) == len(uv):
            uv = uv[p.stripe_inliers]
        out.append(ray_plane(calibration.camera.undistort_points(uv, normalized=True), p.pose.normal, p.pose.center))
    return out


def board_stripe_points(calibration) -> list[np.ndarray]:
    """Each board pose's stripe points (camera frame, mm) of Zhou's calibration
    (:class:`lightplane.plane.zhou.ZhouCalibration`)."""
    idx = np.asarray(calibration.view_index)
    return [calibration.points_cam_mm[idx == k] for k in np.unique(idx)]


def sheet_record(plane: LightPlane, points_mm: Sequence[np.ndarray],
                 options: SheetOptions = SheetOptions()) -> tuple[dict, str]:
    """What a plane file records of the sheet's shape, and one line for the user.

    The flatness test always (``sheet_test``); the curved sheet (``sheet``, :meth:`LightSheet.to_dict`)
    only when the test asks for it: on a flat sheet its extra terms only add variance.  Too few
    images for the test: ``sheet_test`` says why, and nothing else is recorded.
    """
    try:
        fit = fit_sheet(plane, points_mm, options)
    except LightplaneError as e:
        return {"sheet_test": {"skipped": str(e)}}, f"flatness of the sheet not tested: {e}"
    except np.linalg.LinAlgError:
        why = "the stripe lines do not determine the curvature (they are too short or all alike)"
        return {"sheet_test": {"skipped": why}}, f"flatness of the sheet not tested: {why}"
    t = fit.test
    verdict = ("the sheet is curved: the curved sheet is written with the plane" if t.curved
               else "the plane is enough")
    line = (f"flatness of the sheet: sag along the stripes {t.sag_mm * 1e3:+.1f} ± {t.sag_sigma_mm * 1e3:.1f} µm "
            f"over ±{t.half_length_mm:.0f} mm (z = {t.z:+.1f}; σ from the stripe noise with every image's line "
            f"free): {verdict}")
    rec: dict = {"sheet_test": t.to_dict()}
    if t.curved:
        rec["sheet"] = fit.sheet.to_dict()
    return rec, line
