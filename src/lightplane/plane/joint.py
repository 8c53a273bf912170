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
from typing import TYPE_CHECKING, Sequence

import numpy as np

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.plane.model import CameraDependence, LightPlane
from lightplane.plane.ml import _huber_weights, _make_pose, _Problem, plane_param_jacobian
from lightplane.camera.intrinsics import free_parameters, view_dispersion
from lightplane.plane.uncertainty import camera_param_names, camera_params, camera_with_params

if TYPE_CHECKING:
    from lightplane.plane.calibrate import ImagePlaneCalibration

__all__ = ["JointResult", "refine_joint_points", "refine_joint", "JointCalibration", "joint_dispersion"]


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


def refine_joint_points(camera: Camera, free: np.ndarray, board_points: Sequence[np.ndarray],
                        corners_uv: Sequence[np.ndarray], rvecs: Sequence[np.ndarray], tvecs: Sequence[np.ndarray],
                        sigma_corner_px: float, radius_mm: float, rims_uv: Sequence[np.ndarray],
                        stripes_uv: Sequence[np.ndarray], plane0: LightPlane, poses0: Sequence,
                        sigma_rim_px: float, sigma_stripe_px: float, *, tau_rim: float = 1.0, tau_stripe: float = 1.0,
                        huber_c: float | None = 3.0, max_nfev: int = 100, dispersion: bool = True) -> JointResult:
    """The joint maximum-likelihood refinement on points (module docstring).

    ``camera``: start intrinsics (an OpenCV model, not fisheye); ``free`` (P,) bool: which of
    ``fx, fy, cx, cy, dist...`` are estimated (the others held); per board view: its corners
    in the board frame (N, 3) mm, their detections (N, 2) distorted px and the start pose
    (rvec, tvec of ``cv2``); ``sigma_corner_px`` the corner noise; per target placement: rim
    and stripe points (distorted px) and the start pose (objects with ``center``, ``normal``);
    the plane's start ``plane0``; the rim and stripe noise sigmas (px) and autocorrelation
    times.  Points beyond ``huber_c`` sigma at the start are down-weighted (Huber), as in
    :func:`lightplane.plane.ml.refine_ml`.  ``dispersion`` (default): the covariance is multiplied
    by the joint problem's dispersion (:func:`joint_dispersion`); False: it is reported only.
    """
    import cv2
    from scipy.optimize import least_squares


    _check("the fisheye model is not supported (OpenCV's pinhole models only)", camera.model != "fisheye")
    names = camera_param_names(camera)
    p0 = camera_params(camera)
    free = np.asarray(free, bool).ravel()
    _check(f"'free' must have {len(p0)} entries, got {free.size}", free.size == len(p0))
    fi = np.flatnonzero(free)
    nf = fi.size
    nb = len(board_points)
    _check("board points, corners and poses must have one entry per view",
           nb == len(corners_uv) == len(rvecs) == len(tvecs) and nb >= 1)
    _check("rims, stripes and poses must have one entry per placement", len(rims_uv) == len(stripes_uv) == len(poses0))
    _check(f"at least 2 target placements are needed, got {len(rims_uv)}", len(rims_uv) >= 2)
    for s, v in (("sigma_corner_px", sigma_corner_px), ("sigma_rim_px", sigma_rim_px),
                 ("sigma_stripe_px", sigma_stripe_px), ("tau_rim", tau_rim), ("tau_stripe", tau_stripe)):
        _check(f"{s} must be positive and finite, got {v}", bool(np.isfinite(v) and v > 0))
    obj = [np.asarray(o, np.float64).reshape(-1, 3) for o in board_points]
    uvc = [np.asarray(u, np.float64).reshape(-1, 2) for u in corners_uv]
    _check("each view needs as many corners as board points", all(len(o) == len(u) for o, u in zip(obj, uvc)))
    rims = [np.asarray(r, np.float64).reshape(-1, 2) for r in rims_uv]
    stripes = [np.asarray(s, np.float64).reshape(-1, 2) for s in stripes_uv]
    poses0 = list(poses0)
    rows_c = np.cumsum([0] + [2 * len(o) for o in obj])
    mc = int(rows_c[-1])
    nbp = 6 * nb

    def cam_at(k: np.ndarray) -> Camera:
        q = p0.copy()
        q[fi] = k
        return camera_with_params(camera, q)

    def problem(cam: Camera) -> _Problem:
        return _Problem(cam, radius_mm, rims, stripes, plane0, poses0)

    # the ML weights, fixed at the start (refine_ml's, re-derived from its sigmas and taus)
    prob0 = problem(camera)
    m_rim = prob0.m_rim
    is_rim = np.arange(prob0.m) < m_rim
    s_rows = np.where(is_rim, sigma_rim_px, sigma_stripe_px)
    r_start = prob0.residuals(prob0.x0)
    hub = _huber_weights(r_start / s_rows, huber_c) if huber_c is not None else np.ones(prob0.m)
    row_w = np.sqrt(hub) / (s_rows * np.sqrt(np.where(is_rim, tau_rim, tau_stripe)))
    nml = prob0.p
    n_par = nf + nbp + nml
    m_all = mc + prob0.m
    x0 = np.concatenate([p0[fi]] + [np.concatenate([np.ravel(r), np.ravel(t)]) for r, t in zip(rvecs, tvecs)]
                        + [prob0.x0])
    # central-difference steps of the intrinsics: 1e-3 px for fx, fy, cx, cy; 1e-6 for the coefficients
    scale = np.where(fi < 4, 1e-3, 1e-6)

    def corners(x: np.ndarray, jac: bool):
        cam = cam_at(x[:nf])
        r = np.empty(mc)
        J = np.zeros((mc, n_par)) if jac else None
        for i in range(nb):
            rv, tv = x[nf + 6 * i:nf + 6 * i + 3], x[nf + 6 * i + 3:nf + 6 * i + 6]
            proj, jc = cv2.projectPoints(obj[i], rv, tv, cam.K, cam.dist)
            r[rows_c[i]:rows_c[i + 1]] = (proj.reshape(-1, 2) - uvc[i]).ravel() / sigma_corner_px
            if J is not None:
                J[rows_c[i]:rows_c[i + 1], :nf] = jc[:, 6:6 + len(p0)][:, fi] / sigma_corner_px
                J[rows_c[i]:rows_c[i + 1], nf + 6 * i:nf + 6 * i + 6] = jc[:, :6] / sigma_corner_px
        return r, J

    def ml(k: np.ndarray, xm: np.ndarray) -> np.ndarray:
        pr = problem(cam_at(k))
        pr.set_row_weights(row_w)
        return pr.residuals(xm)

    def fun(x: np.ndarray) -> np.ndarray:
        return np.concatenate([corners(x, False)[0], ml(x[:nf], x[nf + nbp:])])

    def jac(x: np.ndarray) -> np.ndarray:
        _, J = corners(x, True)
        assert J is not None
        k, xm = x[:nf], x[nf + nbp:]
        pr = problem(cam_at(k))
        pr.set_row_weights(row_w)
        Jm = np.zeros((prob0.m, n_par))
        Jm[:, nf + nbp:] = pr.dense_jacobian(xm)
        for j in range(nf):
            e = np.zeros(nf)
            e[j] = scale[j]
            Jm[:, j] = (ml(k + e, xm) - ml(k - e, xm)) / (2 * scale[j])
        return np.vstack([J, Jm])

    r0 = fun(x0)
    _check("the start values give non-finite residuals", bool(np.all(np.isfinite(r0))))
    with np.errstate(all="ignore"):
        res = least_squares(fun, x0, jac=jac, method="trf", x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12,
                            max_nfev=max_nfev)
    x = res.x
    _check("the solver did not reach a finite solution", bool(np.all(np.isfinite(x))))
    J = jac(x)
    H = J.T @ J
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    Hs = H / np.outer(d, d)
    w = np.linalg.eigvalsh(Hs)
    _check("the joint problem is singular (the views do not determine the intrinsics, poses and plane)",
           bool(w[0] > 1e-13 * w[-1]))
    cov = np.linalg.inv(Hs) / np.outer(d, d)
    cov = 0.5 * (cov + cov.T)
    # the images' and views' pulls on the shared parameters (intrinsics, plane) against the weights'
    # (res.fun: the weighted residuals at x; the rows' images are the same in every _Problem of these points)
    glob = np.r_[np.arange(nf), nf + nbp + np.arange(3)]
    clusters = [(np.arange(rows_c[i], rows_c[i + 1]), nf + 6 * i + np.arange(6)) for i in range(nb)]
    clusters += [(mc + np.r_[np.flatnonzero(prob0.rim_idx == i), m_rim + np.flatnonzero(prob0.st_idx == i)],
                  nf + nbp + 3 + 5 * i + np.arange(5)) for i in range(prob0.n)]
    psi = joint_dispersion(J, res.fun, glob, clusters)
    if dispersion:
        cov = psi * cov
    # the solution's parts
    cam_opt = cam_at(x[:nf])
    pr = problem(cam_opt)
    nvec, dn, dd, C, N, _ = pr.unpack(x[nf + nbp:])
    G = plane_param_jacobian(dn)  # (4, 3) of (a, b, c, d) in the plane's minimal parameters
    ip = nf + nbp + np.arange(3)
    cov_k = cov[:nf, :nf]
    cov_p = G @ cov[np.ix_(ip, ip)] @ G.T
    cov_pk = G @ cov[np.ix_(ip, np.arange(nf))]
    Jpk_free = cov_pk @ np.linalg.inv(cov_k)
    cov_own = cov_p - Jpk_free @ cov_k @ Jpk_free.T
    cov_own = 0.5 * (cov_own + cov_own.T)
    P = len(p0)
    cov_full = np.zeros((P, P))
    cov_full[np.ix_(fi, fi)] = cov_k
    Jpk = np.zeros((4, P))
    Jpk[:, fi] = Jpk_free
    camera_out = Camera(cam_opt.K, cam_opt.dist, camera.width, camera.height, rms_px=camera.rms_px,
                        model=camera.model, covariance=cov_full, covariance_params=names)
    dep = CameraDependence(names, Jpk, Jpk @ cov_full @ Jpk.T,
                           "joint refinement: Cov(plane, intrinsics) Cov(intrinsics)^-1 of the joint covariance")
    meta = dict(plane0.meta)
    meta.update({CameraDependence.KEY: dep.to_dict(), "joint_refinement": True, "joint_dispersion": psi,
                 "joint_dispersion_applied": bool(dispersion)})
    plane = LightPlane(nvec, dd, cov_own, meta=meta)
    poses = [_make_pose(C[i].copy(), N[i] if N[i] @ C[i] < 0 else -N[i], float(radius_mm)) for i in range(len(C))]
    rv = [x[nf + 6 * i:nf + 6 * i + 3].copy() for i in range(nb)]
    tv = [x[nf + 6 * i + 3:nf + 6 * i + 6].copy() for i in range(nb)]
    rc = res.fun[:mc] * sigma_corner_px
    pr.set_row_weights(np.ones(pr.m))
    rm = pr.residuals(x[nf + nbp:])
    return JointResult(camera=camera_out, plane=plane, plane_covariance_total=0.5 * (cov_p + cov_p.T), poses=poses,
                       rvecs=rv, tvecs=tv, cost_start=float(r0 @ r0), cost=float(res.fun @ res.fun),
                       n_residuals=m_all, n_params=n_par, nfev=int(res.nfev),
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
    plane_cal: "ImagePlaneCalibration"
    camera: Camera


def refine_joint(intrinsics, plane_cal: "ImagePlaneCalibration", *, huber_c: float | None = 3.0) -> JointCalibration:
    """The joint refinement from a camera calibration (:func:`lightplane.camera.intrinsics.calibrate_camera`,
    its corners and board poses) and an ``ml`` plane calibration made with that camera
    (:func:`lightplane.plane.calibrate.calibrate_plane`, its rim and stripe points, poses and noise model)."""
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
    phi = float(nm.get("image_dispersion") or 1.0) if nm.get("image_dispersion_applied") else 1.0
    res = refine_joint_points(cam, free, objs, list(intrinsics.corners_uv), list(intrinsics.rvecs),
                              list(intrinsics.tvecs), float(sigma_c), plane_cal.diameter_mm / 2,
                              [o.rim_uv for o in used], stripes, plane_cal.plane, [o.placement.pose for o in used],
                              float(s_rim), float(s_st), tau_rim=phi * float(nm.get("tau_rim") or 1.0),
                              tau_stripe=phi * float(nm.get("tau_stripe") or 1.0), huber_c=huber_c)
    by_index = {o.index: q for o, q in zip(used, res.poses)}
    images = tuple(replace(o, placement=replace(o.placement, pose=by_index[o.index])) if o.index in by_index else o
                   for o in plane_cal.images)
    placements = tuple(replace(p, pose=by_index.get(p.index, p.pose)) for p in plane_cal.placements)
    plane = res.plane   # its meta: the two-step plane's, plus the camera Jacobian and the joint flag
    new_cal = replace(plane_cal, plane=plane, covariance=plane.covariance, images=images, placements=placements,
                      camera=res.camera)
    return JointCalibration(result=res, plane_cal=new_cal, camera=res.camera)
