"""Joint refinement of the camera and the light plane (docs/method.md §Joint refinement).

The two-step calibration solves the intrinsics from the chessboard corners alone, then the
plane from the circle images with those intrinsics held fixed.  The circle images carry
information about the intrinsics too (each rim is a projected circle of known radius, each
stripe a projected line of a plane shared by all images), so the maximum-likelihood
estimate of everything is one problem:

    minimise  Σ_corners |π(K, pose_b, X) − u|² / σ_c²
            + Σ_rim,stripe  w_g r_g(K, plane, target poses)²

over the intrinsics ``K`` (the free ones of the camera calibration), every board pose
(rvec, tvec), every target pose (centre, normal) and the plane.  ``r_g`` are the residuals
of :func:`lightplane.plane.ml.refine_ml` (Sampson distances in distorted pixels), with that
solve's weights held fixed: ``w_g = huber / (tau_g sigma_g²)`` per point type (rim,
stripe; ``tau_g`` the residuals' autocorrelation time, times the images' dispersion where the
plane's covariance applies it: :func:`lightplane.plane.ml.image_dispersion`), ``σ_c`` the corner noise the camera
calibration estimated from its residuals, times the square root of the views' dispersion
when its covariance applies it (:func:`lightplane.camera.intrinsics.view_dispersion`: the corners'
noise along the intrinsics' directions).

Solved by ``scipy.optimize.least_squares`` from the two-step solution; the Jacobian is
block-sparse (a corner row depends on the intrinsics and its board's pose, a rim row on the
intrinsics and its target's pose, a stripe row also on the plane), assembled from
``cv2.projectPoints``' analytic Jacobian, :mod:`lightplane.plane.ml`'s analytic blocks and
central differences in the intrinsics for the rim and stripe rows (the undistortion).
Covariance: the inverse of the weighted normal matrix at the solution (the rows weighted by
their long-run noise, so it is the Cramér–Rao bound of the model to first order).  The
plane's part is split into the part explained by the intrinsics and the rest,

    plane error = J_pK δK + ε,  J_pK = Cov(plane, K) Cov(K)⁻¹,  Cov(ε) = Cov(plane) − J_pK Cov(K) J_pKᵀ

so the plane file keeps its format (``covariance``: Cov(ε), the plane given the
intrinsics; ``camera_jacobian``: J_pK) and every point's uncertainty is computed as after
the two-step calibration (:func:`lightplane.plane.uncertainty.point_error_basis`), with the
joint camera's covariance.

What it does NOT cover, as the two-step: systematic corner, edge or stripe biases, model
errors (lens model, flatness, a curved light sheet), a wrong target diameter or square size.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Sequence

import numpy as np

from lightplane.camera.model import Camera, camera_record
from lightplane.camera.targets import Target
from lightplane.core.errors import LightplaneError
from lightplane.plane.calibrate import ImagePlaneCalibration, PlaneCalibrationOptions, calibrate_plane, calibrate_planes
from lightplane.plane.model import CameraDependence, LightPlane
from lightplane.plane.ml import _huber_weights, _make_pose, _Problem, dispersion_factor, plane_param_jacobian
from lightplane.camera.intrinsics import IntrinsicsCalibration, calibrate_camera, free_parameters, view_dispersion
from lightplane.plane.uncertainty import camera_param_names, camera_params, camera_with_params

__all__ = ["JointResult", "JointBoardViews", "JointTargetPlacements", "JointOptions", "refine_joint_points",
           "refine_joint", "JointCalibration", "joint_dispersion", "JointCameraImages", "LightPlaneImagesResult",
           "calibrate_light_planes"]


@dataclass(frozen=True)
class JointResult:
    """Result of :func:`refine_joint_points`.

    ``camera``: the refined camera with the covariance of its intrinsics (``covariance_params``
    order; zero rows and columns for the parameters held fixed); ``plane``: the refined plane,
    ``covariance`` the plane's given the intrinsics, ``meta["camera_jacobian"]`` its dependence
    on them (module docstring); ``plane_covariance_total`` (4, 4) the plane's marginal
    covariance; ``poses`` the target poses (centre, normal towards the camera); ``rvecs``,
    ``tvecs`` the board poses; ``cost_start``/``cost`` the weighted cost before and after
    (``Σ`` of squared standardised residuals); ``n_residuals``, ``n_params``; ``nfev``;
    ``corner_rms_px``, ``rim_rms_px``, ``stripe_rms_px`` the residual RMS of each type (px);
    ``dispersion`` the joint problem's dispersion (:func:`joint_dispersion`), ``dispersion_applied``
    whether the covariances include it.
    """

    camera: Camera
    plane: LightPlane
    plane_covariance_total: np.ndarray
    poses: list
    rvecs: list
    tvecs: list
    cost_start: float
    cost: float
    n_residuals: int
    n_params: int
    nfev: int
    corner_rms_px: float
    rim_rms_px: float
    stripe_rms_px: float
    converged: bool
    dispersion: float = 1.0
    dispersion_applied: bool = False


def _check(name: str, ok: bool) -> None:
    if not ok:
        raise LightplaneError(f"refine_joint: {name}")


@dataclass(frozen=True)
class JointBoardViews:
    """The camera calibration's side of the joint problem (:func:`refine_joint_points`).

    Per chessboard view: its corners in the board frame ``board_points`` (N, 3) mm, their
    detections ``corners_uv`` (N, 2) distorted px and the start pose (``rvecs``, ``tvecs`` of
    ``cv2``); ``sigma_corner_px`` the corner noise (px).
    """

    board_points: Sequence[np.ndarray]
    corners_uv: Sequence[np.ndarray]
    rvecs: Sequence[np.ndarray]
    tvecs: Sequence[np.ndarray]
    sigma_corner_px: float


@dataclass(frozen=True)
class JointTargetPlacements:
    """The plane calibration's side of the joint problem (:func:`refine_joint_points`).

    ``radius_mm`` the target's radius; per target placement: rim and stripe points
    ``rims_uv``, ``stripes_uv`` (distorted px) and the start pose ``poses0`` (objects with
    ``center``, ``normal``); the plane's start ``plane0``; the rim and stripe noise sigmas (px)
    and autocorrelation times of :func:`lightplane.plane.ml.refine_ml`'s noise model.
    """

    radius_mm: float
    rims_uv: Sequence[np.ndarray]
    stripes_uv: Sequence[np.ndarray]
    plane0: LightPlane
    poses0: Sequence
    sigma_rim_px: float
    sigma_stripe_px: float
    tau_rim: float = 1.0
    tau_stripe: float = 1.0


@dataclass(frozen=True)
class JointOptions:
    """Options of the joint refinement (:func:`refine_joint_points`, :func:`refine_joint`).

    ``huber_c``: points beyond ``huber_c`` sigma at the start are down-weighted (Huber), as in
    :func:`lightplane.plane.ml.refine_ml` (None: no reweighting); ``max_nfev``: the solver's
    evaluations at most; ``dispersion`` (default): the covariance is multiplied by the joint
    problem's dispersion (:func:`joint_dispersion`); False: it is reported only.
    """

    huber_c: float | None = 3.0
    max_nfev: int = 100
    dispersion: bool = True

    def __post_init__(self):
        if self.huber_c is not None and not (np.isfinite(self.huber_c) and self.huber_c > 0):
            raise LightplaneError(f"huber_c must be positive or None, got {self.huber_c}")
        if int(self.max_nfev) < 1:
            raise LightplaneError(f"max_nfev must be >= 1, got {self.max_nfev}")


class _JointModel:
    """The joint problem's residuals and Jacobian in the stacked parameters
    ``[free intrinsics, board poses (rvec, tvec) ..., plane and target poses (refine_ml's)]``."""

    def __init__(self, camera: Camera, free: np.ndarray, views: JointBoardViews, targets: JointTargetPlacements,
                 huber_c: float | None):
        self.camera = camera
        self.names = camera_param_names(camera)
        self.p0 = p0 = camera_params(camera)
        free = np.asarray(free, bool).ravel()
        _check(f"'free' must have {len(p0)} entries, got {free.size}", free.size == len(p0))
        self.fi = fi = np.flatnonzero(free)
        self.nf = fi.size
        self.nb = nb = len(views.board_points)
        _check("board points, corners and poses must have one entry per view",
               nb == len(views.corners_uv) == len(views.rvecs) == len(views.tvecs) and nb >= 1)
        t = targets
        _check("rims, stripes and poses must have one entry per placement",
               len(t.rims_uv) == len(t.stripes_uv) == len(t.poses0))
        _check(f"at least 2 target placements are needed, got {len(t.rims_uv)}", len(t.rims_uv) >= 2)
        for name, v in (("sigma_corner_px", views.sigma_corner_px), ("sigma_rim_px", t.sigma_rim_px),
                        ("sigma_stripe_px", t.sigma_stripe_px), ("tau_rim", t.tau_rim), ("tau_stripe", t.tau_stripe)):
            _check(f"{name} must be positive and finite, got {v}", bool(np.isfinite(v) and v > 0))
        self.obj = [np.asarray(o, np.float64).reshape(-1, 3) for o in views.board_points]
        self.uvc = [np.asarray(u, np.float64).reshape(-1, 2) for u in views.corners_uv]
        _check("each view needs as many corners as board points",
               all(len(o) == len(u) for o, u in zip(self.obj, self.uvc)))
        self.sigma_corner_px = views.sigma_corner_px
        self.radius_mm = t.radius_mm
        self.rims = [np.asarray(r, np.float64).reshape(-1, 2) for r in t.rims_uv]
        self.stripes = [np.asarray(s, np.float64).reshape(-1, 2) for s in t.stripes_uv]
        self.plane0 = t.plane0
        self.poses0 = list(t.poses0)
        self.rows_c = np.cumsum([0] + [2 * len(o) for o in self.obj])
        self.mc = int(self.rows_c[-1])
        self.nbp = 6 * nb
        # the ML weights, fixed at the start (refine_ml's, re-derived from its sigmas and taus)
        self.prob0 = prob0 = self.problem(camera)
        self.m_rim = prob0.m_rim
        is_rim = np.arange(prob0.m) < self.m_rim
        s_rows = np.where(is_rim, t.sigma_rim_px, t.sigma_stripe_px)
        r_start = prob0.residuals(prob0.x0)
        hub = _huber_weights(r_start / s_rows, huber_c) if huber_c is not None else np.ones(prob0.m)
        self.row_w = np.sqrt(hub) / (s_rows * np.sqrt(np.where(is_rim, t.tau_rim, t.tau_stripe)))
        self.n_par = self.nf + self.nbp + prob0.p
        self.m_all = self.mc + prob0.m
        self.x0 = np.concatenate([p0[fi]] + [np.concatenate([np.ravel(r), np.ravel(tv)])
                                             for r, tv in zip(views.rvecs, views.tvecs)] + [prob0.x0])
        # central-difference steps of the intrinsics: 1e-3 px for fx, fy, cx, cy; 1e-6 for the coefficients
        self.scale = np.where(fi < 4, 1e-3, 1e-6)

    def cam_at(self, k: np.ndarray) -> Camera:
        q = self.p0.copy()
        q[self.fi] = k
        return camera_with_params(self.camera, q)

    def problem(self, cam: Camera) -> _Problem:
        return _Problem(cam, self.radius_mm, self.rims, self.stripes, self.plane0, self.poses0)

    def corners(self, x: np.ndarray, jac: bool):
        import cv2

        nf, rows_c, sc = self.nf, self.rows_c, self.sigma_corner_px
        cam = self.cam_at(x[:nf])
        r = np.empty(self.mc)
        J = np.zeros((self.mc, self.n_par)) if jac else None
        for i in range(self.nb):
            rv, tv = x[nf + 6 * i:nf + 6 * i + 3], x[nf + 6 * i + 3:nf + 6 * i + 6]
            proj, jc = cv2.projectPoints(self.obj[i], rv, tv, cam.K, cam.dist)
            r[rows_c[i]:rows_c[i + 1]] = (proj.reshape(-1, 2) - self.uvc[i]).ravel() / sc
            if J is not None:
                J[rows_c[i]:rows_c[i + 1], :nf] = jc[:, 6:6 + len(self.p0)][:, self.fi] / sc
                J[rows_c[i]:rows_c[i + 1], nf + 6 * i:nf + 6 * i + 6] = jc[:, :6] / sc
        return r, J

    def ml(self, k: np.ndarray, xm: np.ndarray) -> np.ndarray:
        pr = self.problem(self.cam_at(k))
        pr.set_row_weights(self.row_w)
        return pr.residuals(xm)

    def fun(self, x: np.ndarray) -> np.ndarray:
        return np.concatenate([self.corners(x, False)[0], self.ml(x[:self.nf], x[self.nf + self.nbp:])])

    def jac(self, x: np.ndarray) -> np.ndarray:
        nf = self.nf
        _, J = self.corners(x, True)
        assert J is not None
        k, xm = x[:nf], x[nf + self.nbp:]
        pr = self.problem(self.cam_at(k))
        pr.set_row_weights(self.row_w)
        Jm = np.zeros((self.prob0.m, self.n_par))
        Jm[:, nf + self.nbp:] = pr.dense_jacobian(xm)
        for j in range(nf):
            e = np.zeros(nf)
            e[j] = self.scale[j]
            Jm[:, j] = (self.ml(k + e, xm) - self.ml(k - e, xm)) / (2 * self.scale[j])
        return np.vstack([J, Jm])

    def covariance(self, x: np.ndarray, fun: np.ndarray, dispersion: bool) -> tuple[np.ndarray, float]:
        """The covariance of all parameters at the solution ``x`` (weighted residuals ``fun``), times the
        joint dispersion when ``dispersion``; and the dispersion."""
        nf, nbp, rows_c, prob0 = self.nf, self.nbp, self.rows_c, self.prob0
        J = self.jac(x)
        H = J.T @ J
        d = np.sqrt(np.maximum(np.diag(H), 1e-300))
        Hs = H / np.outer(d, d)
        w = np.linalg.eigvalsh(Hs)
        _check("the joint problem is singular (the views do not determine the intrinsics, poses and plane)",
               bool(w[0] > 1e-13 * w[-1]))
        cov = np.linalg.inv(Hs) / np.outer(d, d)
        cov = 0.5 * (cov + cov.T)
        # the images' and views' pulls on the shared parameters (intrinsics, plane) against the weights'
        # (fun: the weighted residuals at x; the rows' images are the same in every _Problem of these points)
        glob = np.r_[np.arange(nf), nf + nbp + np.arange(3)]
        clusters = [(np.arange(rows_c[i], rows_c[i + 1]), nf + 6 * i + np.arange(6)) for i in range(self.nb)]
        clusters += [(self.mc + np.r_[np.flatnonzero(prob0.rim_idx == i), self.m_rim + np.flatnonzero(prob0.st_idx == i)],
                      nf + nbp + 3 + 5 * i + np.arange(5)) for i in range(prob0.n)]
        psi = joint_dispersion(J, fun, glob, clusters)
        if dispersion:
            cov = psi * cov
        return cov, psi


def refine_joint_points(camera: Camera, free: np.ndarray, views: JointBoardViews, targets: JointTargetPlacements,
                        options: JointOptions | None = None) -> JointResult:
    """The joint maximum-likelihood refinement on points (module docstring).

    ``camera``: start intrinsics (an OpenCV model, not fisheye); ``free`` (P,) bool: which of
    ``fx, fy, cx, cy, dist...`` are estimated (the others held); ``views``: the chessboard views
    (:class:`JointBoardViews`: corners, start poses, corner noise); ``targets``: the target
    placements (:class:`JointTargetPlacements`: rim and stripe points, start poses and plane,
    their noise model); ``options`` (:class:`JointOptions`): Huber reweighting, the solver's
    evaluations, whether the covariance includes the joint dispersion.
    """
    from scipy.optimize import least_squares

    opts = JointOptions() if options is None else options
    _check("the fisheye model is not supported (OpenCV's pinhole models only)", camera.model != "fisheye")
    jm = _JointModel(camera, free, views, targets, opts.huber_c)
    r0 = jm.fun(jm.x0)
    _check("the start values give non-finite residuals", bool(np.all(np.isfinite(r0))))
    with np.errstate(all="ignore"):
        res = least_squares(jm.fun, jm.x0, jac=jm.jac, method="trf", x_scale="jac", xtol=1e-12, ftol=1e-12,
                            gtol=1e-12, max_nfev=opts.max_nfev)
    x = res.x
    _check("the solver did not reach a finite solution", bool(np.all(np.isfinite(x))))
    cov, psi = jm.covariance(x, res.fun, opts.dispersion)
    return _joint_result(jm, x, res, cov, psi, float(r0 @ r0), opts.dispersion)


def _joint_result(jm: _JointModel, x: np.ndarray, res, cov: np.ndarray, psi: float, cost_start: float,
                  dispersion: bool) -> JointResult:
    """The solution's parts: the camera with its covariance, the plane split into its own covariance and
    its dependence on the intrinsics, the poses and the residuals (module docstring)."""
    nf, nbp, nb, fi, camera = jm.nf, jm.nbp, jm.nb, jm.fi, jm.camera
    cam_opt = jm.cam_at(x[:nf])
    pr = jm.problem(cam_opt)
    nvec, dn, dd, C, N, _ = pr.unpack(x[nf + nbp:])
    G = plane_param_jacobian(dn)  # (4, 3) of (a, b, c, d) in the plane's minimal parameters
    ip = nf + nbp + np.arange(3)
    cov_k = cov[:nf, :nf]
    cov_p = G @ cov[np.ix_(ip, ip)] @ G.T
    cov_pk = G @ cov[np.ix_(ip, np.arange(nf))]
    Jpk_free = cov_pk @ np.linalg.inv(cov_k)
    cov_own = cov_p - Jpk_free @ cov_k @ Jpk_free.T
    cov_own = 0.5 * (cov_own + cov_own.T)
    P = len(jm.p0)
    cov_full = np.zeros((P, P))
    cov_full[np.ix_(fi, fi)] = cov_k
    Jpk = np.zeros((4, P))
    Jpk[:, fi] = Jpk_free
    camera_out = Camera(cam_opt.K, cam_opt.dist, camera.width, camera.height, rms_px=camera.rms_px,
                        model=camera.model, covariance=cov_full, covariance_params=jm.names)
    dep = CameraDependence(jm.names, Jpk, Jpk @ cov_full @ Jpk.T,
                           "joint refinement: Cov(plane, intrinsics) Cov(intrinsics)^-1 of the joint covariance")
    meta = dict(jm.plane0.meta)
    meta.update({CameraDependence.KEY: dep.to_dict(), "camera": camera_record(camera_out), "joint_refinement": True,
                 "joint_dispersion": psi,
                 "joint_dispersion_applied": bool(dispersion)})
    plane = LightPlane(nvec, dd, cov_own, meta=meta)
    poses = [_make_pose(C[i].copy(), N[i] if N[i] @ C[i] < 0 else -N[i], float(jm.radius_mm)) for i in range(len(C))]
    rv = [x[nf + 6 * i:nf + 6 * i + 3].copy() for i in range(nb)]
    tv = [x[nf + 6 * i + 3:nf + 6 * i + 6].copy() for i in range(nb)]
    rc = res.fun[:jm.mc] * jm.sigma_corner_px
    pr.set_row_weights(np.ones(pr.m))
    rm = pr.residuals(x[nf + nbp:])
    m_rim = jm.m_rim
    return JointResult(camera=camera_out, plane=plane, plane_covariance_total=0.5 * (cov_p + cov_p.T), poses=poses,
                       rvecs=rv, tvecs=tv, cost_start=cost_start, cost=float(res.fun @ res.fun),
                       n_residuals=jm.m_all, n_params=jm.n_par, nfev=int(res.nfev),
                       corner_rms_px=float(np.sqrt(np.mean(rc.reshape(-1, 2) ** 2) * 2)),
                       rim_rms_px=float(np.sqrt(np.mean(rm[:m_rim] ** 2))),
                       stripe_rms_px=float(np.sqrt(np.mean(rm[m_rim:] ** 2))), converged=bool(res.status > 0),
                       dispersion=psi, dispersion_applied=bool(dispersion))


def joint_dispersion(J: np.ndarray, r: np.ndarray, shared: np.ndarray, clusters: Sequence) -> float:
    """The joint problem's noise along its shared parameters, cluster by cluster, over what its
    weights say: 1 when each chessboard view's and circle image's errors pull the intrinsics and
    the plane no more than their (weighted) noise model says.

    ``J`` (m, p), ``r`` (m,): the weighted Jacobian and residuals at the solution (rows whose
    noise model has unit variance: the corners over their sigma times the views' dispersion, the
    rims and stripes over theirs times their autocorrelation time and the images' dispersion);
    ``shared``: the columns every cluster depends on; ``clusters``: ``(rows, own columns)`` of each
    view and image (its pose).  Each cluster's shared columns with its own projected out give its
    share of the shared parameters' information and its pull; the statistic and its expectation
    are :func:`lightplane.camera.intrinsics.view_dispersion`'s with unit variance.  The two steps' own
    dispersions look at the intrinsics (views) and at the plane (images) separately; what this
    adds is the circle images' errors along the intrinsics and their correlation with the
    plane's, which the joint solve uses and neither of them measured.  Sampling sd at least
    ``sqrt(2 / (p (M − 1)))`` (p shared parameters, M clusters: 0.08 for 12 and 28).
    """
    shares, scores = [], []
    for rows, own in clusters:
        Jg, Jl = J[np.ix_(rows, shared)], J[np.ix_(rows, own)]
        Jt = Jg - Jl @ np.linalg.lstsq(Jl, Jg, rcond=None)[0]
        shares.append(Jt.T @ Jt)
        scores.append(Jt.T @ r[rows])
    S = sum(shares)
    dg = np.sqrt(np.maximum(np.diag(S), 1e-300))
    S_inv = np.linalg.pinv(S / np.outer(dg, dg), rcond=1e-12) / np.outer(dg, dg)
    return view_dispersion(S_inv, shares, scores, 1.0)


@dataclass(frozen=True)
class JointCalibration:
    """:func:`refine_joint`'s result: ``result`` (the :class:`JointResult`), ``plane_cal`` (the
    plane calibration with the joint plane, poses and camera), ``camera`` (the joint camera)."""

    result: JointResult
    plane_cal: ImagePlaneCalibration
    camera: Camera


def refine_joint(intrinsics, plane_cal: ImagePlaneCalibration, options: JointOptions | None = None) -> JointCalibration:
    """The joint refinement from a camera calibration (:func:`lightplane.camera.intrinsics.calibrate_camera`,
    its corners and board poses) and an ``ml`` plane calibration made with that camera
    (:func:`lightplane.plane.calibrate.calibrate_plane`, its rim and stripe points, poses and noise model);
    ``options``: :class:`JointOptions` (defaults when omitted)."""
    cam = intrinsics.camera
    if plane_cal.method != "ml" or plane_cal.covariance is None:
        raise LightplaneError("the joint refinement needs the plane calibrated with --method ml")
    if cam.model == "fisheye":
        raise LightplaneError("the joint refinement supports OpenCV's pinhole models, not fisheye")
    sigma_c = intrinsics.options.get("covariance_sigma_px")
    if sigma_c is None:
        raise LightplaneError("the joint refinement needs the camera calibration's covariance (corner noise)")
    if intrinsics.options.get("covariance_noise") == "views":
        # the corners weighted by their noise along the intrinsics' directions (the views' dispersion), as
        # in the camera's covariance: the joint's covariance stays the two-step's where the circles add nothing
        sigma_c = float(sigma_c) * float(np.sqrt(intrinsics.options.get("covariance_dispersion") or 1.0))
    used = [o for o in plane_cal.images if o.used and o.placement is not None and o.placement.pose is not None]
    if len(used) < 2:
        raise LightplaneError(f"the joint refinement needs at least 2 used target images, got {len(used)}")
    stripes = []
    for o in used:
        inl = o.placement.stripe_inliers
        stripes.append(o.stripe_uv if inl is None else np.asarray(o.stripe_uv)[np.asarray(inl, bool)])
    nm = plane_cal.plane.meta.get("noise_model") or {}
    s_rim, s_st = nm.get("sigma_rim_px"), nm.get("sigma_stripe_px")
    if s_rim is None or s_st is None:
        raise LightplaneError("the joint refinement needs the plane calibration's noise model (--method ml)")
    objs = [intrinsics.target.object_points(ids).astype(np.float64) for ids in intrinsics.ids]
    free = free_parameters(len(cam.dist), intrinsics.flags)
    # the rim and stripe points weighted by their long-run noise, times the images' dispersion where the
    # plane's covariance applies it (as the corners by the views' dispersion)
    phi = dispersion_factor(nm)
    views = JointBoardViews(objs, list(intrinsics.corners_uv), list(intrinsics.rvecs), list(intrinsics.tvecs),
                            float(sigma_c))
    targets = JointTargetPlacements(plane_cal.diameter_mm / 2, [o.rim_uv for o in used], stripes, plane_cal.plane,
                                    [o.placement.pose for o in used], float(s_rim), float(s_st),
                                    tau_rim=phi * float(nm.get("tau_rim") or 1.0),
                                    tau_stripe=phi * float(nm.get("tau_stripe") or 1.0))
    res = refine_joint_points(cam, free, views, targets, options)
    by_index = {o.index: q for o, q in zip(used, res.poses)}
    images = tuple(replace(o, placement=replace(o.placement, pose=by_index[o.index])) if o.index in by_index else o
                   for o in plane_cal.images)
    placements = tuple(replace(p, pose=by_index.get(p.index, p.pose)) for p in plane_cal.placements)
    plane = res.plane   # its meta: the two-step plane's, plus the camera Jacobian and the joint flag
    new_cal = replace(plane_cal, plane=plane, covariance=plane.covariance, images=images, placements=placements,
                      camera=res.camera)
    return JointCalibration(result=res, plane_cal=new_cal, camera=res.camera)


@dataclass(frozen=True)
class JointCameraImages:
    """Chessboard images to calibrate the camera from, jointly with the plane (:func:`calibrate_light_planes`):
    file paths or arrays, and the chessboard (:class:`lightplane.camera.targets.Target`)."""

    images: Sequence
    target: Target


@dataclass(frozen=True)
class LightPlaneImagesResult:
    """:func:`calibrate_light_planes`' result.

    ``planes``: per laser name (None for one laser) its :class:`~lightplane.plane.calibrate.ImagePlaneCalibration`
    (after the joint refinement, with one); ``camera``: the camera they use (the joint one, with one);
    ``intrinsics``: the chessboard calibration, ``two_step``: the plane calibrated with its camera and
    ``joint``: the :class:`JointCalibration` (all three None without the joint refinement).
    """

    planes: dict
    camera: Camera
    intrinsics: IntrinsicsCalibration | None = None
    two_step: ImagePlaneCalibration | None = None
    joint: JointCalibration | None = None


def calibrate_light_planes(images: Sequence, camera: Camera | None, diameter_mm: float, method: str = "ml",
                           options: PlaneCalibrationOptions | None = None, *, lasers: Sequence | None = None,
                           joint_camera: JointCameraImages | None = None,
                           progress: Callable[[str, int, int], None] | None = None) -> LightPlaneImagesResult:
    """The light plane(s) from images of a circular target, as ``lightplane calibrate-plane`` makes them.

    One laser (``lasers`` None: :func:`~lightplane.plane.calibrate.calibrate_plane`) or several
    (:class:`lightplane.stripe.lasers.LaserSelector` s: :func:`~lightplane.plane.calibrate.calibrate_planes`),
    with ``camera``; or, with ``joint_camera`` (``camera`` None, one laser, ``method`` ``"ml"``), the camera
    calibrated from the chessboards first (:func:`lightplane.camera.intrinsics.calibrate_camera`), the plane
    with it, then both refined jointly (:func:`refine_joint`).  ``progress(stage, done, total)``: after each
    image of a stage (``"chessboard images"``, ``"images"``).
    """
    def step(stage: str):
        return None if progress is None else (lambda i, n: progress(stage, i, n))

    if joint_camera is None:
        if camera is None:
            raise LightplaneError("give a camera (or chessboard images to calibrate it from, jointly with the plane)")
        if lasers is None:
            planes = {None: calibrate_plane(images, camera, diameter_mm, method, options, progress=step("images"))}
        else:
            planes = calibrate_planes(images, camera, diameter_mm, lasers, method, options, progress=step("images"))
        return LightPlaneImagesResult(planes, camera)
    if camera is not None or lasers is not None:
        raise LightplaneError("the joint refinement calibrates the camera itself, with one laser")
    intr = calibrate_camera(list(joint_camera.images), joint_camera.target, progress=step("chessboard images"))
    two_step = calibrate_plane(images, intr.camera, diameter_mm, method, options, progress=step("images"))
    jc = refine_joint(intr, two_step)
    return LightPlaneImagesResult({None: jc.plane_cal}, jc.camera, intr, two_step, jc)
