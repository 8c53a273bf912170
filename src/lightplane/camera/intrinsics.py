"""Zhang intrinsic calibration with OpenCV, and its diagnostics (docs/method.md §Camera calibration).

Corners by ``cv2.findChessboardCornersSB`` (sub-pixel by construction), the
solve by ``cv2.calibrateCameraExtended`` (standard deviations of the intrinsics,
per-view RMS errors).  The result keeps every view's residuals so the report
can show where the model fits worst.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from lightplane.camera.corners import MIN_BOARD_BLUR_PX, _detect_board, _fit_corners, _refine_method, corner_noise
from lightplane.camera.diagnostics import (CornerNoiseCheck, board_tilts, check_corner_noise, corner_noise_check,
                                           degenerate_views_message, focal_length_problem, outlier_views,
                                           perspective_px)
from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.camera.lens import COEFF_NAMES, MODELS, coeff_names
from lightplane.camera.targets import Target, as_target, correct_circle_centres, dot_diameter_mm
from lightplane.core.io import to_gray_float, too_few_images_message, try_read_image
from lightplane.core.threads import with_blas_limited

__all__ = ["BoardView", "IntrinsicsCalibration", "CameraCalibrationOptions",
           "LENS_REFIT_BEND_PX", "opencv_std_ratio", "rays_up_to_rotation",
           "calibrate_camera", "INTRINSIC_NAMES", "DIST_NAMES", "intrinsics_covariance", "IntrinsicsCovariance",
           "view_dispersion"]


INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")

#: OpenCV's distortion coefficients, in its order (4, 5, 8, 12 or 14 of them; fisheye: lens.coeff_names).
DIST_NAMES = COEFF_NAMES


@dataclass(frozen=True)
class IntrinsicsCovariance:
    """Covariance of the intrinsic parameters ``params`` (``fx, fy, cx, cy``, then the
    distortion coefficients), marginalised over the board poses (:func:`intrinsics_covariance`).

    ``covariance`` (P, P) in the parameters' units (px, unitless), zero rows and columns
    for the parameters the calibration kept fixed (``free`` False); ``sigma_px`` the
    corner noise estimated from the residuals; ``dof`` the degrees of freedom it has.
    ``undetermined``: the free parameters in a direction the views do not determine at all
    (the normal matrix singular to machine precision, e.g. the rational model's numerator
    and denominator sharing a factor); ``covariance`` leaves those directions out (they do
    not move the corners seen), and :meth:`std` gives them ``inf``.
    ``dispersion``: the corner errors' variance along the directions that move the
    intrinsics over the residuals' σ² (:func:`view_dispersion`); ``noise`` ``"views"``
    (default): ``covariance`` is ``dispersion · σ² S⁻¹``; ``"white"``: ``σ² S⁻¹``, the
    corner errors taken as independent (``dispersion`` reported, not applied).
    """

    covariance: np.ndarray
    params: tuple[str, ...]
    free: np.ndarray
    sigma_px: float
    dof: int
    undetermined: tuple[str, ...] = ()
    dispersion: float = 1.0
    noise: str = "views"

    def std(self) -> dict[str, float]:
        return {n: float("inf") if n in self.undetermined else float(np.sqrt(max(c, 0.0)))
                for n, c in zip(self.params, np.diag(self.covariance))}


def free_parameters(n_dist: int, flags: int) -> np.ndarray:
    """Which of ``fx, fy, cx, cy, dist[0..n_dist)`` ``cv2.calibrateCamera`` estimates under ``flags``."""
    import cv2

    free = np.ones(4 + n_dist, bool)
    fixed = {"k1": cv2.CALIB_FIX_K1, "k2": cv2.CALIB_FIX_K2, "k3": cv2.CALIB_FIX_K3, "k4": cv2.CALIB_FIX_K4,
             "k5": cv2.CALIB_FIX_K5, "k6": cv2.CALIB_FIX_K6}
    for j, name in enumerate(DIST_NAMES[:n_dist]):
        off = (flags & fixed.get(name, 0)
               or (name in ("p1", "p2") and flags & cv2.CALIB_ZERO_TANGENT_DIST)
               or (name in ("k4", "k5", "k6") and not flags & cv2.CALIB_RATIONAL_MODEL)
               or (name.startswith("s") and (not flags & cv2.CALIB_THIN_PRISM_MODEL or flags & cv2.CALIB_FIX_S1_S2_S3_S4))
               or (name.startswith("tau") and (not flags & cv2.CALIB_TILTED_MODEL or flags & cv2.CALIB_FIX_TAUX_TAUY)))
        free[4 + j] = not off
    if flags & cv2.CALIB_FIX_FOCAL_LENGTH:
        free[:2] = False
    if flags & cv2.CALIB_FIX_PRINCIPAL_POINT:
        free[2:4] = False
    return free


def intrinsics_covariance(object_points: Sequence[np.ndarray], image_points: Sequence[np.ndarray],
                          rvecs: Sequence[np.ndarray], tvecs: Sequence[np.ndarray], K: np.ndarray,
                          dist: np.ndarray, flags: int = 0, *, model: str | None = None,
                          noise: str = "views") -> IntrinsicsCovariance:
    """Covariance of a Zhang calibration's intrinsics, the board poses marginalised out.

    At the solution, ``cv2.projectPoints`` gives the Jacobian of every corner's projection
    in the view's pose (rvec, tvec) and in the intrinsics ``(fx, fy, cx, cy, dist...)``.
    The Gauss–Newton normal matrix of all views is reduced to the intrinsics by the Schur
    complement of the (block-diagonal) pose blocks, ``S = A − Σ_i C_i B_i⁻¹ C_iᵀ``, and
    ``Cov = σ² S⁻¹`` with ``σ² = Σ r² / (2 N − P_free − 6 M)`` the corner noise from the
    residuals (N corners, M views, P_free estimated intrinsics).  This is the full matrix
    of which OpenCV's ``stdDeviationsIntrinsics`` are the square roots of the diagonal:
    the parameters are strongly correlated (fx with fy, the principal point with p1, p2),
    and a point's uncertainty needs the correlations.  Parameters held fixed by ``flags``
    (``CALIB_FIX_K3``, ``CALIB_ZERO_TANGENT_DIST``, ...) get zero rows and columns.
    ``CALIB_FIX_ASPECT_RATIO`` and ``CALIB_USE_LU``-style options that tie parameters
    together are not supported (LightplaneError).  ``model="fisheye"``: the Jacobian of
    ``cv2.fisheye.projectPoints`` (fx, fy, cx, cy, k1..k4 free, skew fixed; ``flags`` ignored).

    ``noise="views"`` (default) scales ``σ² S⁻¹`` by :func:`view_dispersion`, the corner
    errors' excess along the directions that move the intrinsics (errors correlated
    within a view: a detector's systematic error that varies from view to view, which σ²
    of the residuals cannot show); ``"white"`` keeps ``σ² S⁻¹`` (the corner errors taken as
    independent).
    """
    import cv2

    if noise not in ("views", "white"):
        raise LightplaneError(f"intrinsics_covariance: noise must be 'views' or 'white', got {noise!r}")
    if model == "fisheye":
        return _fisheye_covariance(object_points, image_points, rvecs, tvecs, K, dist, noise)

    if flags & (cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_SAME_FOCAL_LENGTH):
        raise LightplaneError("intrinsics_covariance: CALIB_FIX_ASPECT_RATIO / SAME_FOCAL_LENGTH are not supported")
    K = np.asarray(K, np.float64)
    dist = np.asarray(dist, np.float64).ravel()
    names = ("fx", "fy", "cx", "cy") + DIST_NAMES[:dist.size]
    if dist.size not in (4, 5, 8, 12, 14):
        raise LightplaneError(f"intrinsics_covariance: {dist.size} distortion coefficients (4, 5, 8, 12 or 14 expected)")
    free = free_parameters(dist.size, flags)

    def view(obj, rv, tv):
        proj, jac = cv2.projectPoints(obj, rv, tv, K, dist)
        return proj.reshape(-1, 2), jac[:, :6], jac[:, 6:6 + 4 + dist.size]

    return _schur_covariance(object_points, image_points, rvecs, tvecs, names, free, view, noise)


def _fisheye_covariance(object_points, image_points, rvecs, tvecs, K, dist, noise: str) -> IntrinsicsCovariance:
    import cv2

    K = np.asarray(K, np.float64)
    dist = np.asarray(dist, np.float64).ravel()

    def view(obj, rv, tv):  # fisheye's Jacobian columns: f (2), c (2), k (4), om (3), T (3), alpha
        proj, jac = cv2.fisheye.projectPoints(obj.reshape(-1, 1, 3), rv, tv, K, dist)
        return proj.reshape(-1, 2), jac[:, 8:14], jac[:, :8]

    return _schur_covariance(object_points, image_points, rvecs, tvecs, ("fx", "fy", "cx", "cy") +
                             coeff_names("fisheye"), np.ones(8, bool), view, noise)


def _schur_covariance(object_points, image_points, rvecs, tvecs, names, free, view,
                      noise: str = "views") -> IntrinsicsCovariance:
    """The covariance of :func:`intrinsics_covariance`: ``view(obj, rvec, tvec)`` gives a view's projection
    ``(N, 2)``, its Jacobian in the pose ``(2N, 6)`` and in the intrinsics ``(2N, len(names))``."""
    idx = np.flatnonzero(free)
    p = idx.size
    S = np.zeros((p, p))
    A, g = [], []  # per view: its share of S and its score (the pull of its residuals on the intrinsics)
    ssr, n_obs = 0.0, 0
    for obj, uv, rv, tv in zip(object_points, image_points, rvecs, tvecs):
        obj = np.asarray(obj, np.float64).reshape(-1, 3)
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        proj, Je, Ji = view(obj, np.asarray(rv, np.float64).reshape(3, 1), np.asarray(tv, np.float64).reshape(3, 1))
        r = (uv - proj).ravel()
        ssr += float(r @ r)
        n_obs += r.size
        Ji = Ji[:, idx]
        Jt = Ji - Je @ np.linalg.solve(Je.T @ Je, Je.T @ Ji)  # the intrinsics' columns, the view's pose projected out
        A.append(Jt.T @ Jt)
        g.append(Jt.T @ r)
        S += A[-1]
    dof = n_obs - p - 6 * len(rvecs)
    if dof <= 0:
        raise LightplaneError(f"intrinsics_covariance: {n_obs // 2} corners in {len(rvecs)} views leave no "
                              f"degrees of freedom for {p} intrinsics")
    sigma2 = ssr / dof
    cov = np.zeros((names.__len__(), len(names)))
    # inverted scaled to unit diagonal (the parameters' units differ by ~1e10): an eigenvalue of the
    # scaled matrix below UNDETERMINED_EIGENVALUE of the largest is zero to machine precision
    dg = np.sqrt(np.diag(S))
    if not (np.all(np.isfinite(S)) and np.all(dg > 0)):
        raise LightplaneError("intrinsics_covariance: the intrinsics are not determined by these views "
                              "(singular normal matrix)")
    w, V = np.linalg.eigh(S / np.outer(dg, dg))
    keep = w > UNDETERMINED_EIGENVALUE * w.max()
    Si = ((V[:, keep] / w[keep]) @ V[:, keep].T) / np.outer(dg, dg)  # S⁻¹ within the determined directions
    disp = view_dispersion(Si, A, g, sigma2)
    cov[np.ix_(idx, idx)] = (disp if noise == "views" else 1.0) * sigma2 * Si
    undetermined = tuple(names[idx[i]] for i in range(p) if np.linalg.norm(V[i, ~keep]) > 1e-3)
    return IntrinsicsCovariance(0.5 * (cov + cov.T), names, free, float(np.sqrt(sigma2)), int(dof), undetermined,
                                dispersion=disp, noise=noise)


def view_dispersion(S_inv: np.ndarray, shares: Sequence[np.ndarray], scores: Sequence[np.ndarray],
                    sigma2: float) -> float:
    """The corner errors' variance along the directions that move the intrinsics, over ``sigma2``
    (the residuals' variance): 1 for independent corner errors, more when they are correlated
    within a view (docs/method.md §Camera calibration).

    Per view ``v``: ``A_v`` (``shares``) its part of the pose-marginalised normal matrix
    ``S = Σ A_v`` (``S_inv`` its inverse), ``g_v = J̃_vᵀ r_v`` (``scores``) the pull of its
    residuals on the intrinsics (``J̃_v``: the view's intrinsics columns with its pose's
    projected out).  The statistic ``T = Σ_v g_vᵀ S⁻¹ g_v`` has expectation
    ``σ² (tr I − Σ_v tr (S⁻¹A_v)²)`` under independent corner noise of variance ``σ²``
    (the fit absorbs the part of each view's errors that all views share); the dispersion
    is ``T`` over that.  A systematic error that differs from view to view (illumination,
    blur, the detector's response to each view's perspective) pulls each view's estimate
    more than its residuals' size says, and shows here while ``σ²`` does not.  Its
    sampling sd is at least ``sqrt(2 / (p (M − 1)))`` (p intrinsics, M views; 0.18 over 60
    synthetic calibrations of 16 views of 63 corners, where that gives 0.12).  1.0 with
    fewer than two views or no determined direction.
    """
    if len(shares) < 2 or not sigma2 > 0:
        return 1.0
    T = sum(float(gv @ S_inv @ gv) for gv in scores)
    B = [S_inv @ a for a in shares]
    expected = sigma2 * (float(np.trace(sum(B))) - sum(float(np.sum(b * b.T)) for b in B))
    if not (expected > 0 and np.isfinite(T)):
        return 1.0
    return float(T / expected)


#: Relative eigenvalue (of the normal matrix scaled to unit diagonal) below which a direction of the
#: intrinsics counts as not determined at all (:class:`IntrinsicsCovariance`, ``undetermined``).
UNDETERMINED_EIGENVALUE = 1e-12


@dataclass(frozen=True)
class BoardView:
    """One image's board detection: ``corners_uv`` (N, 2) px or None when not found; ``ids`` (N,)
    the target's point ids (None: all points, id order)."""

    name: str
    corners_uv: np.ndarray | None
    image_size: tuple[int, int]  # (width, height)
    ids: np.ndarray | None = None


@dataclass(frozen=True)
class IntrinsicsCalibration:
    """Result of :func:`calibrate_camera`.

    ``std`` holds the standard deviations of ``INTRINSIC_NAMES`` (px for fx..cy,
    unitless for the distortion); ``per_view_rms_px`` the RMS reprojection error of
    each used view (same order as ``used``); ``residuals_px`` per used view (N, 2);
    ``ids`` per used view, the target's point ids of ``corners_uv`` (partial ChArUco
    views have fewer); ``skipped`` maps every image not used to its reason.
    """

    camera: Camera
    rms_px: float
    std: dict[str, float]
    used: tuple[str, ...]
    not_found: tuple[str, ...]
    per_view_rms_px: np.ndarray
    residuals_px: tuple[np.ndarray, ...]
    corners_uv: tuple[np.ndarray, ...]
    rvecs: tuple[np.ndarray, ...]
    tvecs: tuple[np.ndarray, ...]
    board: tuple[int, int]
    square_mm: float
    flags: int
    options: dict = field(default_factory=dict)
    target: Target | None = None
    ids: tuple[np.ndarray, ...] = ()
    skipped: dict = field(default_factory=dict)
    warnings: tuple[str, ...] = ()
    std_opencv: dict = field(default_factory=dict)
    dropped: dict = field(default_factory=dict)
    noise_check: CornerNoiseCheck | None = None
    geometry: dict = field(default_factory=dict)

    def diagnostics_lines(self) -> list[str]:
        """What the views determine, in words: the boards' tilts, the check against the corners' noise and
        (one line each; the views dropped are among ``skipped``)."""
        out = []
        g = self.geometry
        if g:
            lo, hi = g["tilt_deg_range"]
            out.append(f"Views: boards tilted {lo:.1f}-{hi:.1f} deg against the line of sight; perspective "
                       f"{min(g['perspective_px'].values()):.2g}-{max(g['perspective_px'].values()):.2g} px "
                       "(what determines the focal length)")
        nc = self.noise_check
        if nc is None:
            out.append("Corner noise check: not available (needs the saddle fit's corners: chessboards whose "
                       "images are not sharpened)")
        else:
            out.append(f"Corner noise check: reprojection RMS {nc.rms_px:.3g} px, {nc.ratio:.1f}x the "
                       f"{nc.predicted_px:.2g} px the corners' own noise predicts: "
                       + ("suspect, kept by request" if nc.suspect else "consistent"))
        return out

    def ranked_views(self) -> list[tuple[str, float]]:
        """(view name, RMS px), worst first."""
        order = np.argsort(-self.per_view_rms_px)
        return [(self.used[i], float(self.per_view_rms_px[i])) for i in order]

    def T_cam_board(self, i: int) -> np.ndarray:
        """4x4 pose of the board in used view ``i`` (board points → camera frame)."""
        import cv2

        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(self.rvecs[i])[0]
        T[:3, 3] = self.tvecs[i].ravel()
        return T

    def to_dict(self) -> dict:
        target = self.target or as_target(self.board, self.square_mm)
        return {
            "std": {n: (v if np.isfinite(v) else None) for n, v in self.std.items()},  # None: not determined
            "std_covers": ("the corner noise (estimated from the residuals"
                           + (", times the views' dispersion" if self.options.get("covariance_noise") == "views"
                              else "") + "), board poses marginalised; "
                           + ("OpenCV's stdDeviationsIntrinsics" if self.camera.model == "plumb_bob"
                              else "from the full covariance (intrinsics_covariance)")),
            "std_opencv": self.std_opencv,
            "per_view_rms_px": dict(zip(self.used, map(float, self.per_view_rms_px))),
            "views_used": list(self.used),
            "views_board_not_found": list(self.not_found),
            "views_skipped": dict(self.skipped),
            "views_dropped": dict(self.dropped),
            "corner_noise_check": None if self.noise_check is None else self.noise_check.to_dict(),
            "view_geometry": self.geometry,
            "points_per_view": dict(zip(self.used, (len(c) for c in self.corners_uv))),
            "board": {"cols": self.board[0], "rows": self.board[1], "square_mm": self.square_mm},
            "target": target.to_dict(),
            "flags": self.flags,
            "model": self.camera.model,
            "warnings": list(self.warnings),
            "covariance": {"sigma_px": self.options.get("covariance_sigma_px"),
                           "dof": self.options.get("covariance_dof"),
                           "view_dispersion": self.options.get("covariance_dispersion"),
                           "noise": self.options.get("covariance_noise"),
                           "board_poses": "marginalised (Schur complement of the normal matrix)"},
            "corners": {"refine": self.options.get("refine"),
                        "median_blur_px": (float(self.options["median_blur_px"])
                                           if np.isfinite(self.options.get("median_blur_px", np.nan)) else None),
                        "lens_frame_refit_corners": self.options.get("lens_frame_refit_corners", 0),
                        "dot_mm": self.options.get("dot_mm"),
                        "circle_centre_correction_px": self.options.get("circle_centre_correction_px")},
        }


@dataclass(frozen=True)
class CameraCalibrationOptions:
    """Options of :func:`calibrate_camera` (checked on construction: the model, the corner
    refinement, the covariance's noise and a held tilt).

    flags : ``cv2.CALIB_*`` flags for ``calibrateCameraExtended`` (0: 5 coefficients, as OpenCV's default)
    model : the lens model (:data:`lightplane.camera.lens.MODELS`): ``plumb_bob``, ``rational``
        (``CALIB_RATIONAL_MODEL``), ``thin_prism`` (``+ CALIB_THIN_PRISM_MODEL``), ``tilted``
        (``CALIB_TILTED_MODEL``: the plumb bob and tauX, tauY, the other coefficients held at 0) or
        ``fisheye`` (``cv2.fisheye.calibrate``, skew fixed; its std from the Jacobian of the
        reprojection, see :func:`reprojection_covariance`); None: from ``flags``
    tilt_deg : ``model="tilted"``: hold the sensor tilt (tauX, tauY, degrees) at this value, e.g. the
        mechanical design's (``CALIB_FIX_TAUX_TAUY`` from OpenCV's initial guess).  Through a narrow
        lens the views do not separate the tilt from the principal point (README, Lens models):
        held, the principal point is determined, relative to that tilt (a tilt off by δ moves it
        by ~f δ and turns the camera frame by δ; shapes measured are not affected), and OpenCV's
        own std are then right
    rotate_deg : clockwise rotation applied to path inputs on reading (0/90/180/270)
    min_views : fewer usable views raise :class:`LightplaneError` (saying why the others were not usable)
    refine : chessboards: polish the corners (see :func:`find_board`): True or ``"saddle"`` fits the
        blurred saddle of :func:`fit_corners`, ``"forstner"`` runs :func:`refine_corners`,
        False keeps cornerSubPix's.  On the rendered calibration capture (realistic
        imaging, 16 mm lens, k3 fixed) corner errors of 0.031 / 0.019 / 0.006 px RMS
        (cornerSubPix / Förstner / saddle) give OpenCV std of (cx, cy) of (0.47, 0.31) /
        (0.28, 0.19) / (0.09, 0.06) px with 30 views, and the principal-point error
        drops to <= 0.06 px; the saddle fit costs ~0.1 s per 1280x960 view of 165 corners.
        The saddle model's edges are straight: after a first calibration the corners whose
        windows its lens bends by more than :data:`LENS_REFIT_BEND_PX` are fitted again in
        its lens frame (:func:`fit_corners` with ``camera``) and the calibration is solved
        again (``options["lens_frame_refit_corners"]``: how many)
    covariance_noise : the corner noise of the intrinsics' covariance (:func:`intrinsics_covariance`):
        ``"views"`` (default) the residuals' σ² times the views' dispersion (:func:`view_dispersion`,
        ``options["covariance_dispersion"]``), ``"white"`` the residuals' σ² alone
    drop_outlier_views : views whose reprojection RMS is far above the others'
        (:func:`lightplane.camera.diagnostics.outlier_views`) are left out and the calibration solved
        again (``dropped``: each with its reason); False: kept, named in a warning
    keep_suspect : keep a calibration whose RMS is far above what its corners' own noise predicts
        (:func:`lightplane.camera.diagnostics.corner_noise_check`; refused by default), marked in its result
    """

    flags: int = 0
    model: str | None = None
    tilt_deg: tuple[float, float] | None = None
    rotate_deg: int = 0
    min_views: int = 3
    refine: bool | str = True
    covariance_noise: str = "views"
    drop_outlier_views: bool = True
    keep_suspect: bool = False

    def __post_init__(self) -> None:
        model = calibration_flags(self.model, self.flags)[0]  # an unknown model raises
        _refine_method(self.refine)
        if self.covariance_noise not in ("views", "white"):
            raise LightplaneError(f"covariance_noise must be 'views' or 'white', got {self.covariance_noise!r}")
        if self.tilt_deg is not None:
            tilt = np.asarray(self.tilt_deg, dtype=np.float64).ravel()
            if model != "tilted":
                raise LightplaneError(f"a held sensor tilt needs the tilted model, not {model}")
            if tilt.size != 2 or not np.all(np.isfinite(tilt)) or np.any(np.abs(tilt) >= 45.0):
                raise LightplaneError(f"the sensor tilt must be two finite angles (tauX, tauY) under 45 degrees, "
                                      f"got {tilt.tolist()}")


@dataclass
class _Capture:
    """What :func:`calibrate_camera` read: per view with a readable image of the right size its
    detection, image (array or path, for the refit in the lens frame), saddle-fit corners and
    parameters (chessboards with the saddle fit, else None); the saddle fits' blurs, the dots'
    diameters (circle grids), the images skipped with their reasons and the image size."""

    views: list[BoardView] = field(default_factory=list)
    sources: list = field(default_factory=list)
    saddles: list = field(default_factory=list)
    fits: list = field(default_factory=list)
    blurs: list = field(default_factory=list)
    dots: list = field(default_factory=list)
    skipped: dict = field(default_factory=dict)
    size: tuple[int, int] | None = None
    noise: list = field(default_factory=list)


@dataclass
class _Used:
    """The views a calibration uses: each one's :class:`BoardView`, corners (N, 2) px, object
    points (N, 3) float32 and image points (N, 1, 2) float32 as solved."""

    views: list[BoardView]
    uv: list[np.ndarray]
    objs: list[np.ndarray]
    imgpoints: list[np.ndarray]


@with_blas_limited
def calibrate_camera(images: Sequence, board: "tuple[int, int] | Target", square_mm: float | None = None, *,
                     names: Sequence[str] | None = None, options: CameraCalibrationOptions | None = None,
                     progress: Callable[[int, int], None] | None = None) -> IntrinsicsCalibration:
    """Zhang calibration from images of a planar target (docs/method.md §Camera calibration).

    Parameters
    ----------
    images : sequence of image arrays or paths
    board : a :class:`lightplane.camera.targets.Target` (chessboard, circle grid or ChArUco), or
        ``(cols, rows)`` chessboard inner corners with ``square_mm``
    square_mm : chessboard square size, mm, with a ``(cols, rows)`` board (sets the scale of the poses only)
    names : the images' names in the result (default: the paths, or ``image i``)
    options : :class:`CameraCalibrationOptions` (None: the defaults): the flags and lens model, a
        held sensor tilt, the rotation on reading, the fewest views, the corner refinement and
        the covariance's noise
    progress : called with ``(images done, images)`` after each image

    Circle grids: the dots' centroids are moved to the projected circle centres
    (:func:`lightplane.camera.targets.correct_circle_centres`) with the poses of a first
    calibration, then the calibration is solved again.  ChArUco: partial views are used
    (at least 6 corners, not on one line).  An image that cannot be read, has another
    size than the first readable one, or shows no usable board is skipped with its
    reason (``skipped``; board not found also in ``not_found``).
    """
    import cv2

    opts = CameraCalibrationOptions() if options is None else options
    target = as_target(board, square_mm)
    guess_dist = _held_tilt_guess(opts.tilt_deg)  # checked on the options' construction, before any image is read
    if len(images) == 0:
        raise LightplaneError("no images given")
    if names is None:
        names = [str(im) if isinstance(im, (str, Path)) else f"image {i}" for i, im in enumerate(images)]
    method = _refine_method(opts.refine) if target.kind == "chessboard" else None
    cap = _read_views(images, names, target, method, opts.rotate_deg, progress)
    views, method, median_blur = _one_corner_method(cap, method)
    found = [v for v in views if v.corners_uv is not None]
    found_src = [src for v, src in zip(views, cap.sources) if v.corners_uv is not None]
    found_fits = [f for v, f in zip(views, cap.fits) if v.corners_uv is not None]
    found_uv: list[np.ndarray] = [v.corners_uv for v in views if v.corners_uv is not None]
    not_found = tuple(v.name for v in views if v.corners_uv is None)
    for n in not_found:
        cap.skipped[n] = f"{target.spec} board not found" + (" (or fewer than 6 corners)" if target.partial_views else "")
    if len(found) < opts.min_views:
        raise LightplaneError(too_few_images_message("images", len(found), opts.min_views, cap.skipped.items()))
    size = cap.size
    assert size is not None  # set by the first readable image, and some were found
    objs = [target.object_points(v.ids).astype(np.float32) for v in found]
    imgpoints = [uv.astype(np.float32).reshape(-1, 1, 2) for uv in found_uv]
    noise = [n for v, n in zip(views, cap.noise) if v.corners_uv is not None] if method == "saddle" \
        else [None] * len(found)
    perspective = _checked_perspective(objs, found_uv, noise)
    model, flags = calibration_flags(opts.model, opts.flags)
    if guess_dist is not None:
        flags |= cv2.CALIB_FIX_TAUX_TAUY | cv2.CALIB_USE_INTRINSIC_GUESS

    def solve(imgpoints):
        return _solved_camera(objs, imgpoints, size, model, flags, guess_dist)

    out = solve(imgpoints)
    n_refit = 0
    if method == "saddle":
        # the saddle model's edges are straight: refit, in the lens frame of this first calibration, the
        # corners whose windows its lens bends (LENS_REFIT_BEND_PX), then solve again
        cam1 = Camera(out[1], _model_dist(out[2], model), size[0], size[1], model=model)
        found_uv, n_refit = _refit_in_lens_frame(cam1, found_uv, found_src, (target.cols, target.rows),
                                                 opts.rotate_deg, found_fits)
        if n_refit:
            found = [BoardView(v.name, u, v.image_size, v.ids) for v, u in zip(found, found_uv)]
            imgpoints = [uv.astype(np.float32).reshape(-1, 1, 2) for uv in found_uv]
            out = solve(imgpoints)
    dot_mm, shift = None, None
    if target.kind in ("circles", "acircles"):
        dot_mm = float(target.dot_mm or np.median(cap.dots))
        fixed, imgpoints, out = _circle_centres_solved(target, found, found_uv, out, dot_mm, size, model, solve)
        shift = float(np.sqrt(np.mean(np.concatenate([np.sum((f - u) ** 2, axis=1) for f, u in zip(fixed, found_uv)]))))
        found = [BoardView(v.name, f, v.image_size, v.ids) for v, f in zip(found, fixed)]
        found_uv = fixed
    record = {"rotate_deg": opts.rotate_deg, "refine": method or False, "median_blur_px": median_blur,
              "lens_frame_refit_corners": n_refit, "dot_mm": dot_mm, "circle_centre_correction_px": shift}
    predicted = [np.sqrt(np.nanmean(np.trace(C, axis1=1, axis2=2))) if C is not None and np.isfinite(C[:, 0, 0]).any()
                 else np.nan for C in noise]
    dropped = outlier_views([v.name for v in found], out[7], predicted) if opts.drop_outlier_views else {}
    if dropped and len(found) - len(dropped) >= opts.min_views:
        keep = [i for i, v in enumerate(found) if v.name not in dropped]
        found, found_uv = [found[i] for i in keep], [found_uv[i] for i in keep]
        objs, imgpoints = [objs[i] for i in keep], [imgpoints[i] for i in keep]
        noise, perspective = [noise[i] for i in keep], [perspective[i] for i in keep]
        out = solve(imgpoints)
        cap.skipped.update({n: f"dropped: {why}" for n, why in dropped.items()})
    else:
        dropped = {}
    result = _calibration_result(target, _Used(found, found_uv, objs, imgpoints), out, (model, flags),
                                 opts.covariance_noise, record, (not_found, cap.skipped))
    return _diagnosed(result, objs, noise, perspective, dropped, opts.keep_suspect)


def _checked_perspective(objs: list, uv: list, noise: list) -> list[float]:
    """Each view's perspective (px, :func:`lightplane.camera.diagnostics.perspective_px`); LightplaneError
    when no view shows enough of it to determine the focal length (the corners' noise: the median of
    their saddle fits' own, where known)."""
    persp = [perspective_px(o, u) for o, u in zip(objs, uv)]
    sig = [np.sqrt(np.trace(C, axis1=1, axis2=2) / 2) for C in noise if C is not None]
    sig_all = np.concatenate(sig) if sig else np.zeros(0)
    sig_all = sig_all[np.isfinite(sig_all)]
    msg = degenerate_views_message(persp, float(np.median(sig_all)) if sig_all.size else None, len(objs))
    if msg:
        raise LightplaneError(msg)
    return persp


def _solved_camera(objs: list, imgpoints: list, size: tuple[int, int], model: str, flags: int,
                   guess_dist: np.ndarray | None) -> tuple:
    """:func:`_solve_views`, refused in words where the solve fails or ends at no camera (a focal
    length that is not positive and finite)."""
    import cv2

    try:
        out = _solve_views(objs, imgpoints, size, model, flags, guess_dist)
    except cv2.error as e:
        raise LightplaneError(f"the calibration's solve failed ({str(e).strip().splitlines()[-1]}); are the "
                              "views varied enough?") from None
    K = np.asarray(out[1], np.float64)
    tilts = board_tilts(objs, out[3], out[4])[0]
    why = focal_length_problem(float(K[0, 0]), float(K[1, 1]), {}, tilts, [perspective_px(o, u) for o, u in
                                                                          zip(objs, imgpoints)])
    if why:
        raise LightplaneError(why)
    return out


def _diagnosed(result: "IntrinsicsCalibration", objs: list, noise: list, perspective: list, dropped: dict,
               keep_suspect: bool) -> "IntrinsicsCalibration":
    """``result`` with its views' geometry, the views dropped and its corner-noise check; LightplaneError
    when the focal length is not determined or the calibration is far above its corners' noise (unless
    ``keep_suspect``)."""
    from dataclasses import replace

    cam = result.camera
    tilts, axes = board_tilts(objs, result.rvecs, result.tvecs)
    # the larger of the reported std and the full covariance's: OpenCV's pseudo-inverse drops the
    # direction in which a focal length trades against the board distances (face-on boards: 0.007 px
    # against the covariance's 353 px on a render whose fx came out 70 px off)
    std = dict(result.std)
    if cam.covariance is not None and cam.covariance_params is not None:
        sd = np.sqrt(np.clip(np.diag(cam.covariance), 0, None))
        for n, v in zip(cam.covariance_params, sd):
            std[n] = max(float(std.get(n, 0.0)), float(v))
    why = focal_length_problem(cam.fx, cam.fy, std, tilts, perspective)
    if why:
        raise LightplaneError(why)
    n_params = 4 + len(cam.dist) + 6 * len(objs)
    check = check_corner_noise(corner_noise_check(result.used, result.residuals_px, noise, n_params), keep_suspect)
    geometry = {"tilt_deg": dict(zip(result.used, map(float, tilts))),
                "tilt_axis_deg": dict(zip(result.used, map(float, axes))),
                "perspective_px": dict(zip(result.used, map(float, perspective))),
                "tilt_deg_range": [float(tilts.min()), float(tilts.max())],
                "note": "tilt: the board's normal against the line of sight to its centre; axis: the image "
                        "direction it is tilted about; perspective: how far the board's image departs from "
                        "an affine copy (what determines the focal length)"}
    warnings = result.warnings
    if check is not None and check.suspect:
        warnings += (f"kept by request although suspect: {check.diagnosis()}",)
    return replace(result, dropped=dict(dropped), noise_check=check, geometry=geometry, warnings=warnings)


def _held_tilt_guess(tilt_deg) -> np.ndarray | None:
    """OpenCV's initial distortion (14,) holding the sensor tilt ``tilt_deg`` (tauX, tauY degrees), or None."""
    if tilt_deg is None:
        return None
    guess_dist = np.zeros(14)
    guess_dist[12:] = np.deg2rad(np.asarray(tilt_deg, dtype=np.float64).ravel())
    return guess_dist


def _one_corner_method(cap: _Capture, method: str | None) -> tuple[list[BoardView], str | None, float]:
    """One corner method for the whole capture: the saddle fit's corners when the boards' median
    fitted blur reaches :data:`MIN_BOARD_BLUR_PX`, else Förstner's.  The views, the method and
    the median blur (px; NaN without the saddle fit)."""
    blur_all = np.concatenate(cap.blurs) if cap.blurs else np.zeros(0)
    median_blur = float(np.median(blur_all)) if blur_all.size else float("nan")
    views = cap.views
    if method == "saddle":
        if median_blur >= MIN_BOARD_BLUR_PX:
            views = [BoardView(v.name, s, v.image_size) if s is not None else v for v, s in zip(views, cap.saddles)]
        else:
            method = "forstner"
    return views, method, median_blur


def _read_views(images: Sequence, names: Sequence[str], target: Target, method: str | None, rotate_deg: int,
                progress: Callable[[int, int], None] | None) -> _Capture:
    """Read every image and detect the target in it (:func:`calibrate_camera`'s first step)."""
    cap = _Capture()
    for i, (im, name) in enumerate(zip(images, names)):
        img = _read_view_image(im, name, rotate_deg, cap.skipped)
        if img is not None:
            h, w = img.shape[:2]
            if cap.size is None:
                cap.size = (w, h)
            if cap.size != (w, h):
                cap.skipped[name] = f"size {w}x{h} px differs from the first image's {cap.size[0]}x{cap.size[1]} px"
            else:
                _detect_view(img, im, name, target, method, cap)
        if progress:
            progress(i + 1, len(images))
    return cap


def _read_view_image(im, name: str, rotate_deg: int, skipped: dict) -> np.ndarray | None:
    """The image of one view (read from its path, or the array given), or None with its reason in ``skipped``."""
    if isinstance(im, (str, Path)):
        img, reason = try_read_image(im, rotate_deg=rotate_deg)
        if img is None:
            skipped[name] = reason
    else:
        img = None if im is None else np.asarray(im)
        if img is None:
            skipped[name] = "not a readable image"
    if img is not None and img.ndim not in (2, 3):
        skipped[name] = f"not an image (shape {img.shape})"
        img = None
    return img


def _detect_view(img: np.ndarray, source, name: str, target: Target, method: str | None, cap: _Capture) -> None:
    """Detect the target in one view's image and add the view to ``cap``."""
    h, w = img.shape[:2]
    if target.kind == "chessboard":
        c, saddle, blur, fit = _detect_board(img, (target.cols, target.rows), True, method)
        cap.views.append(BoardView(name, c, (w, h)))
        cap.sources.append(source)
        cap.saddles.append(saddle)
        cap.fits.append(fit)
        cap.blurs.append(blur)
        cap.noise.append(None if fit is None or c is None else
                         corner_noise(img if img.ndim == 2 else to_gray_float(img), c, (target.cols, target.rows), fit)[0])
        return
    det = target.detect(img)
    cap.views.append(BoardView(name, None if det is None else det.uv, (w, h), None if det is None else det.ids))
    cap.sources.append(source)
    cap.saddles.append(None)
    cap.fits.append(None)
    cap.noise.append(None)
    if det is not None and target.kind in ("circles", "acircles"):
        cap.dots.append(dot_diameter_mm(img, det, target))


def _solve_views(objs: list, imgpoints: list, size: tuple[int, int], model: str, flags: int,
                 guess_dist: np.ndarray | None) -> tuple:
    """One calibration of the views: ``calibrateCameraExtended``'s tuple ``(rms, K, dist, rvecs, tvecs,
    std_intrinsics, std_extrinsics, per-view RMS)`` (polished for :data:`POLISHED_MODELS`; the
    fisheye's from ``cv2.fisheye.calibrate``, without std)."""
    import cv2

    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    if model != "fisheye":
        if guess_dist is not None:  # OpenCV starts from the guess; the tilt stays where it is put
            K0 = cv2.initCameraMatrix2D(objs, imgpoints, size)
            out = cv2.calibrateCameraExtended(objs, imgpoints, size, K0, guess_dist.copy(), flags=flags,
                                              criteria=crit)
        else:
            # None: no initial guess (OpenCV accepts it; the stubs do not)
            out = cv2.calibrateCameraExtended(objs, imgpoints, size, None, None, flags=flags,  # type: ignore[call-overload]
                                              criteria=crit)
        if model in POLISHED_MODELS:
            out = _polish(objs, imgpoints, out, flags)
        return out
    o64 = [o.astype(np.float64).reshape(1, -1, 3) for o in objs]  # (1, N, 3): fisheye refuses (N, 1, 3)
    i64 = [u.astype(np.float64).reshape(1, -1, 2) for u in imgpoints]
    try:
        rms, K, D, rvecs, tvecs = cv2.fisheye.calibrate(o64, i64, size, None, None, flags=flags,  # type: ignore[call-overload]
                                                        criteria=crit)
    except cv2.error as e:
        raise LightplaneError(f"fisheye calibration failed ({str(e).strip().splitlines()[-1]})") from None
    cam = Camera(K, np.ravel(D), size[0], size[1], model="fisheye")
    per_view = [np.sqrt(np.mean(np.sum((cam.project(o.astype(np.float64) @ cv2.Rodrigues(rv)[0].T + np.ravel(tv))
                                        - u.reshape(-1, 2)) ** 2, axis=1))) for o, u, rv, tv in
                zip(objs, imgpoints, rvecs, tvecs)]
    return rms, K, D, rvecs, tvecs, None, None, np.asarray(per_view)


def _circle_centres_solved(target: Target, found: list[BoardView], raw: list[np.ndarray], out: tuple, dot_mm: float,
                           size: tuple[int, int], model: str, solve: Callable) -> tuple[list, list, tuple]:
    """Circle grids: the dots' centroids ``raw`` moved to the projected centres at the poses of the
    calibration ``out``, then solved again (twice: the poses move a little).  Returns the moved
    centres, their image points and the last calibration."""
    import cv2

    for _ in range(2):
        _, K, dist, rvecs, tvecs = out[:5]
        cam = Camera(K, _model_dist(dist, model), size[0], size[1], model=model)
        fixed = [correct_circle_centres(cam, target, u, v.ids, cv2.Rodrigues(rv)[0], tv.ravel(), dot_mm)
                 for u, v, rv, tv in zip(raw, found, rvecs, tvecs)]
        imgpoints = [f.astype(np.float32).reshape(-1, 1, 2) for f in fixed]
        out = solve(imgpoints)
    return fixed, imgpoints, out


def _calibration_result(target: Target, used: _Used, out: tuple, model_flags: tuple[str, int], covariance_noise: str,
                        record: dict, not_used: tuple[tuple[str, ...], dict]) -> IntrinsicsCalibration:
    """The :class:`IntrinsicsCalibration` of the solved calibration ``out`` of the views ``used``: the
    camera with the intrinsics' covariance, the std, the residuals; ``record`` the first entries of
    its ``options``; ``not_used``: the views where the board was not found and every image skipped."""
    import cv2

    model, flags = model_flags
    rms, K, dist, rvecs, tvecs, std_int, _std_ext, per_view = out
    objs, imgpoints = used.objs, used.imgpoints
    size = used.views[0].image_size
    dist = _model_dist(dist, model)
    try:
        icov = intrinsics_covariance(objs, imgpoints, rvecs, tvecs, K, dist, flags, model=model,
                                     noise=covariance_noise)
    except LightplaneError:  # options the covariance does not model: the camera carries none
        icov = None
    camera = Camera(K, dist, size[0], size[1], rms_px=float(rms), model=model,
                    covariance=None if icov is None else icov.covariance,
                    covariance_params=None if icov is None else icov.params)
    centres = [cv2.Rodrigues(rv)[0] @ o.astype(np.float64).mean(axis=0) + np.ravel(tv)
               for o, rv, tv in zip(objs, rvecs, tvecs)]
    std_cv, std = _calibration_std(model, std_int, icov)
    residuals, corners = [], []
    for uv, o, rv, tv in zip(used.uv, objs, rvecs, tvecs):
        proj = camera.project(o.astype(np.float64) @ cv2.Rodrigues(np.ravel(rv))[0].T + np.ravel(tv))
        residuals.append(uv - proj)
        corners.append(uv)
    not_found, skipped = not_used
    return IntrinsicsCalibration(
        camera=camera,
        rms_px=float(rms),
        std=std,
        used=tuple(v.name for v in used.views),
        not_found=not_found,
        per_view_rms_px=np.asarray(per_view, dtype=np.float64).ravel(),
        residuals_px=tuple(residuals),
        corners_uv=tuple(corners),
        rvecs=tuple(np.asarray(r).ravel() for r in rvecs),
        tvecs=tuple(np.asarray(t).ravel() for t in tvecs),
        board=(target.cols, target.rows),
        square_mm=float(target.square_mm),
        flags=int(flags),
        options={**record,
                 "median_board_distance_mm": float(np.median([np.linalg.norm(c) for c in centres])),
                 "covariance_sigma_px": None if icov is None else icov.sigma_px,
                 "covariance_dof": None if icov is None else icov.dof,
                 "covariance_dispersion": None if icov is None else icov.dispersion,
                 "covariance_noise": None if icov is None else icov.noise},
        target=target,
        ids=tuple(np.arange(target.n_points) if v.ids is None else v.ids for v in used.views),
        skipped=skipped,
        warnings=tuple(overparameterisation_warnings(camera, icov, std, len(used.views))
                       + view_outlier_warnings([v.name for v in used.views], per_view)),
        std_opencv=std_cv,
    )


#: a view whose reprojection RMS is this many times the views' median (and above VIEW_OUTLIER_FLOOR_PX) is
#: named in a warning
VIEW_OUTLIER_RATIO = 3.0
VIEW_OUTLIER_FLOOR_PX = 0.3


def view_outlier_warnings(names, per_view_rms_px) -> list[str]:
    """One warning per view whose reprojection RMS is more than :data:`VIEW_OUTLIER_RATIO` times the
    median of the views (and over :data:`VIEW_OUTLIER_FLOOR_PX`): its corners do not follow the noise
    the others show (a misdetected, blurred or strongly foreshortened board).  The view is kept; the
    covariance's dispersion (``covariance_noise="views"``) already widens the σ for it.  FabScan's
    25-view test set: frame 008 at 3.7 px and 127 at 2.1 px against a median of 0.7 px."""
    rms = np.asarray(per_view_rms_px, np.float64).ravel()
    if len(rms) < 3:
        return []
    med = float(np.median(rms))
    return [f"view {n}: reprojection RMS {r:.2f} px, {r / med:.1f}x the views' median {med:.2f} px (a misdetected, "
            "blurred or strongly foreshortened board? leave it out and calibrate again)"
            for n, r in zip(names, rms) if r > VIEW_OUTLIER_RATIO * med and r > VIEW_OUTLIER_FLOOR_PX]


def _calibration_std(model: str, std_int, icov: "IntrinsicsCovariance | None") -> tuple[dict, dict]:
    """OpenCV's std of the intrinsics (``std_int``, None for the fisheye) by name, and the std the
    calibration reports."""
    names = ("fx", "fy", "cx", "cy") + coeff_names(model)
    std_cv = {}
    if std_int is not None:  # OpenCV's: fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4 taux tauy
        std_cv = {n: float(s) for n, s in zip(names, np.asarray(std_int).ravel())}
    # the plumb bob: OpenCV's (equal to the covariance's within 2 %); the other models: the covariance's
    # (fisheye: OpenCV gives none; tilted: OpenCV's are ~100x too small where tau trades against the
    # principal point, benchmarks/bench_lens_models.py)
    # (OpenCV's scaled by the views' dispersion where the covariance applies it)
    if icov is not None and icov.noise == "views":
        std_cv_scaled = {n: v * float(np.sqrt(icov.dispersion)) for n, v in std_cv.items()}
    else:
        std_cv_scaled = std_cv
    std = std_cv_scaled if (model == "plumb_bob" or icov is None) else icov.std()
    return std_cv, std


#: Saddle-fit corners whose window the first calibration's lens bends by more than this (px,
#: :func:`lens_bend`) are fitted again in its lens frame (:func:`calibrate_camera`).  The refit moves a
#: corner by ~0.09 of the bend under radial distortion (rendered 6 mm wide lens, median over 660
#: corners with bends of 0.01-0.3 px) and by ~0.02 under a Scheimpflug tilt (whose projective part
#: bends no line), so the corners left alone are off by less than ~0.0005 px, a tenth of the fit's noise.
LENS_REFIT_BEND_PX = 0.005


def _refit_in_lens_frame(camera: Camera, corners: list[np.ndarray], sources: list, board: tuple[int, int],
                         rotate_deg: int, starts: Sequence[np.ndarray | None] | None = None,
                         ) -> tuple[list[np.ndarray], int]:
    """Every view's saddle corners fitted again in ``camera``'s lens frame where it bends their
    windows by more than :data:`LENS_REFIT_BEND_PX` (:func:`_fit_corners`): the corners, and how many
    were refitted.  ``sources``: each view's image (array or path, read again); ``starts``: each
    view's first fit (:func:`_fit_corners`' parameters, or None), where the refit starts."""
    out, n = [], 0
    for uv, src, start in zip(corners, sources, starts if starts is not None else [None] * len(corners)):
        img = try_read_image(src, rotate_deg=rotate_deg)[0] if isinstance(src, (str, Path)) else np.asarray(src)
        if img is None:  # read once already: only a file changed in between
            out.append(uv)
            continue
        gray = img if img.ndim == 2 else to_gray_float(img)
        q, _, ok, _ = _fit_corners(gray, uv, board, camera=camera, min_bend_px=LENS_REFIT_BEND_PX, start=start)
        out.append(q)
        n += int(ok.sum())
    return out, n


def opencv_std_ratio(cal: "IntrinsicsCalibration") -> tuple[str, float] | None:
    """The parameter whose std OpenCV's ``stdDeviationsIntrinsics`` understates most against the
    calibration's covariance, and by what factor (None without both).  OpenCV inverts the full,
    unscaled normal matrix by a pseudo-inverse (``cv2.invert``, DECOMP_EIG / DECOMP_SVD) that drops
    eigenvalues below ~2 ε Σλ; where parameters trade against each other (a Scheimpflug tilt
    against p1, p2 and the principal point, the rational model's numerator against its
    denominator) the weakest direction falls under the cut and its variance is lost
    (benchmarks/bench_lens_models.py reproduces OpenCV's numbers that way)."""
    cv, sd = cal.std_opencv, cal.std
    if not cv or sd is cv:
        return None
    # the same corner noise on both sides: OpenCV's is the residuals' alone
    f = float(np.sqrt(cal.options.get("covariance_dispersion") or 1.0)) if cal.options.get("covariance_noise") == "views" \
        else 1.0
    ratios = {n: sd[n] / (f * cv[n]) for n in sd
              if 0 < sd[n] < np.inf and cv.get(n, 0) > 0 and np.isfinite(cv[n])}
    if not ratios:
        return None
    worst = max(ratios, key=lambda n: ratios[n])
    return worst, float(ratios[worst])


@dataclass(frozen=True)
class RayComparison:
    """Two cameras' rays compared over an image (:func:`rays_up_to_rotation`), px in the reference camera:
    ``rms_px``, ``max_px`` as they are; ``rotated_rms_px``, ``rotated_max_px`` after the best rotation
    ``rotation`` (3x3, applied to ``other``'s rays) of ``rotation_deg``."""

    rms_px: float
    max_px: float
    rotated_rms_px: float
    rotated_max_px: float
    rotation: np.ndarray
    rotation_deg: float


def rays_up_to_rotation(reference: Camera, other: Camera, step_px: float = 16.0) -> RayComparison:
    """How far ``other``'s rays land from the pixels they come from when projected by ``reference``,
    on a grid of ``step_px`` over the whole image, as they are and after the rotation of ``other``'s
    frame that fits them best (least squares in px).

    A rotation of the camera frame about the centre of projection moves every camera-frame point
    but no distance between points: a laser sensor calibrated with either camera (plane and camera
    from the same images) measures the same shapes.  A Scheimpflug tilt of a narrow lens is, to
    the corners' noise, such a rotation plus a principal-point shift and tangential terms (README,
    Lens models): two calibrations of it can differ by pixels and agree to ~0.01 px here."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    v, u = np.mgrid[0:reference.height:step_px, 0:reference.width:step_px]
    uv = np.column_stack([u.ravel(), v.ravel()]).astype(float)
    r = other.rays(uv, unit=True)

    def resid(w):
        return (reference.project(r @ Rotation.from_rotvec(w).as_matrix().T) - uv).ravel()

    d0 = np.linalg.norm(resid(np.zeros(3)).reshape(-1, 2), axis=1)
    fit = least_squares(resid, np.zeros(3), x_scale=1e-3)
    d1 = np.linalg.norm(fit.fun.reshape(-1, 2), axis=1)
    return RayComparison(float(np.sqrt(np.mean(d0 ** 2))), float(d0.max()), float(np.sqrt(np.mean(d1 ** 2))),
                         float(d1.max()), Rotation.from_rotvec(fit.x).as_matrix(), float(np.rad2deg(np.linalg.norm(fit.x))))


def calibration_flags(model: str | None, flags: int = 0) -> tuple[str, int]:
    """``(model, flags)`` of a calibration: the model named (its OpenCV flags added) or the one
    ``flags`` select (``CALIB_TILTED_MODEL`` -> tilted, ``THIN_PRISM`` -> thin_prism, ``RATIONAL``
    -> rational, else plumb_bob).  Fisheye: ``cv2.fisheye`` flags (recompute extrinsics, fixed skew)."""
    import cv2

    if model is None:
        model = ("tilted" if flags & cv2.CALIB_TILTED_MODEL else "thin_prism" if flags & cv2.CALIB_THIN_PRISM_MODEL
                 else "rational" if flags & cv2.CALIB_RATIONAL_MODEL else "plumb_bob")
    if model not in MODELS:
        raise LightplaneError(f"unknown lens model {model!r} (known: {', '.join(MODELS)})")
    if model == "fisheye":
        # OpenCV 4 names these flags in cv2.fisheye; OpenCV 5 has them (only) beside the others
        fe = cv2.fisheye
        return model, (getattr(fe, "CALIB_RECOMPUTE_EXTRINSIC", cv2.CALIB_RECOMPUTE_EXTRINSIC)
                       | getattr(fe, "CALIB_FIX_SKEW", cv2.CALIB_FIX_SKEW))
    extra = {"plumb_bob": 0, "rational": cv2.CALIB_RATIONAL_MODEL,
             "thin_prism": cv2.CALIB_RATIONAL_MODEL | cv2.CALIB_THIN_PRISM_MODEL,
             "tilted": cv2.CALIB_TILTED_MODEL}[model]
    return model, int(flags) | extra


def _model_dist(dist, model: str) -> np.ndarray:
    """OpenCV's output vector cut to the model's length (what it holds beyond was not estimated: 0)."""
    d = np.asarray(dist, dtype=np.float64).ravel()
    n = MODELS[model]
    if d.size > n and np.any(d[n:] != 0):
        raise LightplaneError(f"calibration returned non-zero coefficients beyond the {model} model's {n}")
    return d[:n]


#: A parameter whose std exceeds this multiple of its |value| is not determined by the views.
OVERPARAM_STD_RATIO = 1.0
#: |correlation| above which two parameters are not separated by the views.
OVERPARAM_CORRELATION = 0.99


def overparameterisation_warnings(camera: Camera, icov: "IntrinsicsCovariance | None", std: dict,
                                  n_views: int) -> list[str]:
    """Plain-language warnings that a calibration's model has more parameters than its views determine.

    The higher coefficients (k3 and what the model adds to the plumb bob: k4..k6, s1..s4, tauX,
    tauY; fisheye's k3, k4): one whose std is over :data:`OVERPARAM_STD_RATIO` x its |value| (the
    views cannot tell it from 0), and pairs of free parameters, one of them such a coefficient,
    correlated beyond :data:`OVERPARAM_CORRELATION` (from the calibration's covariance, board poses
    marginalised; fx with fy and the principal point with p1, p2 are always strongly correlated and
    are not what this is about).  Empty when the model is determined.
    """
    model = str(camera.model)  # set on construction
    names = ("fx", "fy", "cx", "cy") + coeff_names(model)
    values = dict(zip(names, np.concatenate([[camera.fx, camera.fy, camera.cx, camera.cy], camera.dist])))
    extra = set(coeff_names(model)) - {"k1", "k2", "p1", "p2"} if model != "fisheye" else {"k3", "k4"}
    undetermined = set(icov.undetermined) if icov is not None else set()
    weak = [f"{n} = {values[n]:.3g} ± {std[n]:.2g}" for n in names
            if n in extra and n not in undetermined and std.get(n, 0) > 0
            and std[n] > OVERPARAM_STD_RATIO * abs(values[n])]
    pairs: list[tuple[str, str, float]] = []
    if icov is not None:
        C = icov.covariance
        sd = np.sqrt(np.clip(np.diag(C), 0, None))
        free = np.flatnonzero((sd > 0) & ~np.isin(np.asarray(icov.params), list(undetermined)))
        R = C[np.ix_(free, free)] / np.outer(sd[free], sd[free])
        iu = np.triu_indices(len(free), 1)
        strong = (np.abs(R[iu]) > OVERPARAM_CORRELATION) & np.array(
            [icov.params[free[i]] in extra or icov.params[free[j]] in extra for i, j in zip(*iu)], bool)
        pairs = [(icov.params[free[i]], icov.params[free[j]], float(R[i, j])) for i, j in zip(iu[0][strong], iu[1][strong])]
    out = []
    if icov is not None and icov.undetermined:
        out.append(f"the {model} model's {', '.join(icov.undetermined)} are not determined by these {n_views} views at "
                   f"all (the normal matrix is singular to machine precision in them): their std are infinite; "
                   f"the camera's covariance leaves that direction out (it does not move the corners seen)")
    if weak:
        out.append(f"the {model} model looks over-parameterised for these {n_views} views: "
                   f"{'; '.join(weak)} (std larger than the value: not determined)")
    # a tilt that trades against the principal point: every pair of the tilt's is that one degeneracy
    def tilt(a: str, b: str) -> bool:
        return a.startswith("tau") or b.startswith("tau")

    tilt_vs_pp = any(tilt(a, b) and {a, b} & {"cx", "cy"} for a, b, _ in pairs)
    tilt_pairs = [f"corr({a}, {b}) = {r:+.4f}" for a, b, r in pairs if tilt_vs_pp and tilt(a, b)]
    other_pairs = [f"corr({a}, {b}) = {r:+.4f}" for a, b, r in pairs if not (tilt_vs_pp and tilt(a, b))]
    if other_pairs:
        shown = "; ".join(other_pairs[:6]) + (f" and {len(other_pairs) - 6} more" if len(other_pairs) > 6 else "")
        out.append(f"strongly correlated parameters ({model}, {n_views} views): {shown} "
                   f"(|corr| > {OVERPARAM_CORRELATION}: the views do not separate them; a simpler model, "
                   f"more views or more tilted views help)")
    if tilt_pairs:
        out.append(f"the sensor tilt is not separated from the principal point and p1, p2 ({'; '.join(tilt_pairs)}): "
                   f"through a lens of this field the tilt shows as a rotation of the camera frame plus a principal-point "
                   f"shift and tangential distortion, which other views do not change; the projection is "
                   f"determined (shapes measured are not affected), the frame's orientation and the principal "
                   f"point only within their std. To pin them, hold the tilt at the mechanical design's value "
                   f"(calibrate-camera --tilt TAUX,TAUY; CameraCalibrationOptions(tilt_deg=...)): the principal point is "
                   f"then determined relative to it")
    return out


#: Models whose OpenCV calibration is polished by :func:`_polish` (OpenCV's Levenberg-Marquardt stops
#: early in the long valleys their extra coefficients make: with exact corners of a Scheimpflug render
#: it left the principal point 0.06 px off, 130x its std; the polish reaches the truth to 1e-6 px).
POLISHED_MODELS = ("rational", "thin_prism", "tilted")


def _polish(objs, imgpoints, out, flags: int):
    """Continue OpenCV's calibration ``out`` (calibrateCameraExtended's tuple) by scipy's
    Levenberg-Marquardt on all free intrinsics and poses, double precision, with
    ``cv2.projectPoints``' Jacobian; kept only when it lowers the cost.  The same tuple back
    (OpenCV's std untouched; rms and per-view RMS recomputed)."""
    import cv2
    from scipy.optimize import least_squares

    rms, K, dist, rvecs, tvecs, std_int, std_ext, per_view = out
    dist = np.asarray(dist, np.float64).ravel()
    if flags & (cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_SAME_FOCAL_LENGTH):
        return out
    free = free_parameters(dist.size, flags)
    fi = np.flatnonzero(free)
    obj = [np.asarray(o, np.float64).reshape(-1, 3) for o in objs]
    uv = [np.asarray(u, np.float64).reshape(-1, 2) for u in imgpoints]
    base = np.concatenate([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], dist])
    p = fi.size
    x0 = np.concatenate([base[fi]] + [np.concatenate([np.ravel(r), np.ravel(t)]) for r, t in zip(rvecs, tvecs)])
    rows = np.cumsum([0] + [2 * len(o) for o in obj])

    def unpack(x):
        q = base.copy()
        q[fi] = x[:p]
        Kx = np.array([[q[0], K[0, 1], q[2]], [0.0, q[1], q[3]], [0.0, 0.0, 1.0]])
        return Kx, q[4:]

    def project(x, i):
        Kx, d = unpack(x)
        return cv2.projectPoints(obj[i], x[p + 6 * i:p + 6 * i + 3], x[p + 6 * i + 3:p + 6 * i + 6], Kx, d)

    def fun(x):
        return np.concatenate([(project(x, i)[0].reshape(-1, 2) - uv[i]).ravel() for i in range(len(obj))])

    def jac(x):
        J = np.zeros((rows[-1], x.size))
        for i in range(len(obj)):
            j = project(x, i)[1]
            J[rows[i]:rows[i + 1], :p] = j[:, 6:10 + dist.size][:, fi]
            J[rows[i]:rows[i + 1], p + 6 * i:p + 6 * i + 6] = j[:, :6]
        return J

    r0 = fun(x0)
    with np.errstate(all="ignore"):
        res = least_squares(fun, x0, jac=jac, method="lm", x_scale="jac", xtol=1e-15, ftol=1e-15, gtol=1e-15,
                            max_nfev=200)
    if not (np.all(np.isfinite(res.x)) and res.fun @ res.fun < r0 @ r0):
        return out
    Kx, d = unpack(res.x)
    r = res.fun.reshape(-1, 2)
    n = len(obj)
    rv = tuple(res.x[p + 6 * i:p + 6 * i + 3].reshape(3, 1) for i in range(n))
    tv = tuple(res.x[p + 6 * i + 3:p + 6 * i + 6].reshape(3, 1) for i in range(n))
    pv = np.array([np.sqrt(np.mean(np.sum(r[rows[i] // 2:rows[i + 1] // 2] ** 2, axis=1))) for i in range(n)])
    return float(np.sqrt(np.mean(np.sum(r ** 2, axis=1)))), Kx, d.reshape(1, -1), rv, tv, std_int, std_ext, pv
