"""Uncertainty of triangulated points from the light plane's covariance (docs/method.md §Point uncertainty).

A stripe pixel with undistorted normalised ray ``x̃ = (x, y, 1)`` triangulates to
``X = −d x̃ / (n·x̃)`` (paper Eq. 2/4).  To first order an error ``δ(a, b, c, d)`` of
the plane moves it by ``J δ`` with

    ∂X/∂n = d x̃ x̃ᵀ / (n·x̃)²,   ∂X/∂d = −x̃ / (n·x̃),

so ``Cov(X) = J Σ Jᵀ`` (Σ: the plane's 4x4 covariance).  ``point_sigma_mm`` is
``sqrt(trace Cov(X))``: the RMS length of the 3D error vector (mm).

The camera's share: a camera file from ``calibrate-camera`` carries the
covariance of its intrinsics (``fx, fy, cx, cy``, distortion); the plane calibration then
records ``∂(a, b, c, d)/∂(intrinsics)`` (the circle poses and the stripe rays both depend
on them).  A point moved by a change δK of the intrinsics moves by
``dX = ∂X/∂K δK + ∂X/∂plane · ∂plane/∂K δK`` — the ray and the plane are correlated,
and the two terms partly cancel — evaluated by central differences along the principal
axes of Cov(K) (:func:`point_error_basis`).  Two figures over a working volume
(:func:`volume_sigma`): the camera-frame sigma, and the shape sigma after the best rigid
motion (an error of the principal point mostly rotates the whole frame).

What it does NOT cover: the stripe centre's own image noise (a per-point effect that
averages out along a profile) and model errors (a curved or thick light sheet, a lens
the distortion model does not fit); it is the systematic error shared by all points of a scan.

>>> import numpy as np
>>> from lightplane import Camera, LightPlane
>>> cam = Camera([[1000., 0, 640], [0, 1000, 480], [0, 0, 1]], np.zeros(5), 1280, 960)
>>> pl = LightPlane([0, 0, 1], -500, covariance=np.diag([0, 0, 0, 0.01]))
>>> point_sigma_mm(cam, pl, np.array([[640., 480.]]))   # only d uncertain: 0.1 mm along z
array([0.1])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lightplane.camera.model import Camera, as_points
from lightplane.core.errors import LightplaneError
from lightplane.plane.triangulate import GRAZING_COS, points_sigma_mm, triangulate_normalized
from lightplane.plane.model import LightPlane
from lightplane.plane.ml import dispersion_factor
from lightplane.camera.lens import coeff_names

__all__ = ["point_covariance", "point_sigma_mm", "WorkingVolume", "working_volume_grid", "check_distance_range",
           "rms_point_sigma_mm",
           "rms_triangulation_error_mm", "camera_param_names", "camera_params", "camera_with_params", "camera_steps",
           "ray_sigma_rad", "camera_uncertainty_summary", "point_error_basis", "shape_error_basis",
           "rigid_motion_basis", "volume_sigma", "VolumeSigma", "camera_share_status", "plane_camera_jacobian",
           "plane_noise_covers", "zhou_covers", "joint_dispersion_covers", "joint_dispersion_phrase"]


def _plane_cov(plane: LightPlane, covariance: np.ndarray | None) -> np.ndarray:
    cov = plane.covariance if covariance is None else np.asarray(covariance, float)
    if cov is None:
        raise LightplaneError("the light plane has no covariance (calibrate it with method 'ml')")
    if cov.shape != (4, 4) or not np.all(np.isfinite(cov)):
        raise LightplaneError(f"plane covariance must be a finite 4x4 matrix, got shape {cov.shape}")
    return cov


def point_jacobian(plane: LightPlane, xy: np.ndarray) -> np.ndarray:
    """(N, 3, 4) ``∂X/∂(a, b, c, d)`` at normalised rays ``xy`` (N, 2); NaN for grazing rays."""
    xt = np.column_stack([xy, np.ones(len(xy))])
    den = xt @ plane.normal
    bad = ~(np.abs(den) >= GRAZING_COS * np.linalg.norm(xt, axis=1))
    den = np.where(bad, np.nan, den)
    J = np.empty((len(xy), 3, 4))
    J[:, :, :3] = plane.d * xt[:, :, None] * xt[:, None, :] / (den**2)[:, None, None]
    J[:, :, 3] = -xt / den[:, None]
    return J


def point_covariance(camera: Camera, plane: LightPlane, uv: np.ndarray, *,
                     covariance: np.ndarray | None = None) -> np.ndarray:
    """(N, 3, 3) covariance (mm²) of points triangulated from distorted pixels ``uv`` (N, 2).

    From the plane's covariance and, when the camera file has a covariance and the plane
    file records its dependence on the intrinsics, the camera's share with the ray–plane
    correlation (:func:`point_error_basis`); with ``covariance`` (a 4x4 of ``(a, b, c, d)``,
    e.g. a Cramér–Rao bound) that matrix alone.  NaN for rays nearly parallel to the plane.
    """
    uv = as_points(uv, 2, "uv")
    E, _ = point_error_basis(camera, plane, uv, covariance=covariance, camera_share=covariance is None)
    return E @ np.swapaxes(E, 1, 2)


def point_sigma_mm(camera: Camera, plane: LightPlane, uv: np.ndarray, *,
                   covariance: np.ndarray | None = None) -> np.ndarray:
    """(N,) sigma (mm) of points triangulated from distorted pixels ``uv`` (N, 2).

    ``sqrt(trace Cov(X))``: the RMS length of the 3D error (camera frame) due to the plane's
    uncertainty and, where the files carry it, the camera's (:func:`point_covariance`;
    :func:`camera_share_status` says whether).  NaN for grazing rays.  Raises when the
    plane has no covariance.  Plane only: :func:`lightplane.plane.triangulate.points_sigma_mm`.
    """
    uv = as_points(uv, 2, "uv")
    cov = _plane_cov(plane, covariance)
    if covariance is None and camera_share_status(camera, plane) is None:
        E, _ = point_error_basis(camera, plane, uv)
        return np.sqrt(np.sum(E**2, axis=(1, 2)))
    return points_sigma_mm(plane, camera.undistort_points(uv, normalized=True), covariance=cov)


@dataclass(frozen=True)
class WorkingVolume:
    """Image samples of the stripe region: pixels whose ray meets the plane in range.

    ``uv`` (N, 2) distorted px on a regular grid, ``points`` (N, 3) mm on the plane,
    ``distance_mm`` the range of distances from the camera centre used, ``step_px``.
    """

    uv: np.ndarray
    points: np.ndarray
    distance_mm: tuple[float, float]
    step_px: float


def check_distance_range(distance_mm) -> tuple[float, float]:
    """``(near, far)`` distances (mm) as floats, checked: finite, ``0 < near < far``."""
    lo, hi = float(distance_mm[0]), float(distance_mm[1])
    if not (0 < lo < hi < np.inf):
        raise LightplaneError(f"distance_mm must be finite (near, far) with 0 < near < far, got {tuple(distance_mm)}")
    return lo, hi


def working_volume_grid(camera: Camera, plane: LightPlane, *, distance_mm: tuple[float, float] = (380.0, 520.0),
                        step_px: float = 16.0, margin_px: float = 0.0) -> WorkingVolume:
    """Sample the image on a grid and keep pixels whose ray meets the plane at a distance in ``distance_mm``.

    That is the region where the stripe can be seen on objects in the working volume
    (docs/conventions.md §Default sensor: 380–520 mm).  Raises if no pixel qualifies.
    """
    if step_px <= 0:
        raise LightplaneError(f"step_px must be positive, got {step_px}")
    lo, hi = check_distance_range(distance_mm)
    us = np.arange(margin_px, camera.width - margin_px, step_px)
    vs = np.arange(margin_px, camera.height - margin_px, step_px)
    U, V = np.meshgrid(us, vs)
    uv = np.column_stack([U.ravel(), V.ravel()])
    pts = triangulate_normalized(plane, camera.undistort_points(uv, normalized=True)).points
    dist = np.linalg.norm(pts, axis=1)
    keep = np.isfinite(dist) & (dist >= lo) & (dist <= hi)
    if not np.any(keep):
        raise LightplaneError(f"the light plane is not in view at distances {lo:g}–{hi:g} mm")
    return WorkingVolume(uv[keep], pts[keep], (lo, hi), float(step_px))


def rms_point_sigma_mm(camera: Camera, plane: LightPlane, volume: WorkingVolume, *,
                       covariance: np.ndarray | None = None) -> float:
    """RMS over the working volume of :func:`point_sigma_mm` (mm; camera frame)."""
    s = point_sigma_mm(camera, plane, volume.uv, covariance=covariance)
    return float(np.sqrt(np.nanmean(s**2)))


def rms_triangulation_error_mm(camera: Camera, plane_est: LightPlane, plane_true: LightPlane,
                               volume: WorkingVolume) -> float:
    """RMS over the working volume of the distance (mm) between points triangulated with
    ``plane_est`` and with ``plane_true`` (the same pixels)."""
    xy = camera.undistort_points(volume.uv, normalized=True)
    a = triangulate_normalized(plane_est, xy).points
    b = triangulate_normalized(plane_true, xy).points
    e = np.linalg.norm(a - b, axis=1)
    return float(np.sqrt(np.nanmean(e**2)))


# ------------------------------------------------------------------ the camera's share
def camera_param_names(camera: Camera) -> tuple[str, ...]:
    """The intrinsic parameters in the order of a camera covariance: ``fx, fy, cx, cy`` then ``dist``'s."""
    assert camera.model is not None  # a Camera names its model on construction
    return ("fx", "fy", "cx", "cy") + coeff_names(camera.model)


def camera_params(camera: Camera) -> np.ndarray:
    """The vector of :func:`camera_param_names`."""
    return np.concatenate([[camera.fx, camera.fy, camera.cx, camera.cy], camera.dist])


def camera_with_params(camera: Camera, p: np.ndarray) -> Camera:
    """``camera`` with the intrinsic vector ``p`` (order of :func:`camera_param_names`; no covariance)."""
    p = np.asarray(p, np.float64)
    K = camera.K.copy()
    K[0, 0], K[1, 1], K[0, 2], K[1, 2] = p[:4]
    return Camera(K, p[4:], camera.width, camera.height, model=camera.model)


def camera_steps(camera: Camera) -> np.ndarray:
    """(r, P) one-sigma steps of the intrinsics along the principal axes of the camera's
    covariance (their outer products sum to it; axes of zero variance dropped); (0, P)
    when the camera has no covariance.  Raises when the covariance names other
    parameters than the camera's model has."""
    names = camera_param_names(camera)
    if camera.covariance is None:
        return np.zeros((0, len(names)))
    params = camera.covariance_params or ()  # set with the covariance
    if tuple(params) != names:
        raise LightplaneError(f"the camera's covariance is of ({', '.join(params)}) but its model "
                              f"has ({', '.join(names)}): a camera file from another model?")
    w, V = np.linalg.eigh(camera.covariance)
    keep = w > 1e-12 * max(w.max(initial=0.0), 1e-300)
    return (V[:, keep] * np.sqrt(w[keep])).T


def ray_sigma_rad(camera: Camera, uv: np.ndarray) -> np.ndarray:
    """(N,) sigma (rad) of the direction of the rays through distorted pixels ``uv`` due to
    the camera's covariance (first order, central differences along :func:`camera_steps`);
    NaN without a covariance."""
    uv = as_points(uv, 2, "uv")
    steps = camera_steps(camera)
    if len(steps) == 0:
        return np.full(len(uv), np.nan)
    p0 = camera_params(camera)
    var = np.zeros(len(uv))
    for s in steps:
        a = camera_with_params(camera, p0 + s).rays(uv, unit=True)
        b = camera_with_params(camera, p0 - s).rays(uv, unit=True)
        var += np.sum((0.5 * (a - b)) ** 2, axis=1)
    return np.sqrt(var)


def image_grid(camera: Camera, step_px: float = 32.0) -> np.ndarray:
    """(N, 2) pixel centres of a regular grid over the whole image."""
    us = np.arange(step_px / 2, camera.width, step_px)
    vs = np.arange(step_px / 2, camera.height, step_px)
    U, V = np.meshgrid(us, vs)
    return np.column_stack([U.ravel(), V.ravel()])


#: What the camera's share covers (one sentence, printed and stored with every figure that includes it).
CAMERA_SHARE_COVERS = ("the intrinsics' and distortion's covariance from the camera calibration (corner noise "
                       "estimated from its residuals and, in its default, their correlation within a view; board "
                       "poses marginalised)")


def plane_noise_covers(plane: LightPlane) -> str:
    """What the plane's own covariance covers (one phrase, from its noise model in ``plane.meta``)."""
    if plane.meta.get("method") == "zhou":
        return zhou_covers(plane)
    nm = plane.meta.get("noise_model") or {}
    if nm.get("image_dispersion_applied"):
        f, d = dispersion_factor(nm), float(nm.get("image_dispersion") or 1.0)
        est = "" if abs(f - d) < 5e-3 else f", estimated x{d:.2f}, never taken below 1"
        return ("the plane calibration's image noise (rim and stripe points: their sigmas, their correlation "
                f"along the curves, and errors shared within an image: the images' dispersion "
                f"x{f:.2f} in variance{est})")
    return ("the plane calibration's image noise (rim and stripe points: their sigmas and their correlation "
            "along the curves; errors shared within an image not included)")


def zhou_covers(plane: LightPlane) -> str:
    """What a Zhou plane's own covariance covers (one phrase, from ``plane.meta["covariance_method"]``)."""
    how = str(plane.meta.get("covariance_method") or "")
    if how.startswith("jackknife"):
        return ("the plane calibration's image noise (each board pose's error, shared by all its stripe points, "
                f"and the stripe points' scatter: the {how})")
    return ("the plane calibration's stripe points' scatter only (too few board poses for the jackknife: "
            "each pose's error shared by its points not included)")


def joint_dispersion_phrase(dispersion: float) -> str:
    """What a covariance scaled by the joint problem's dispersion includes (one phrase)."""
    return (f"times the joint problem's dispersion x{float(dispersion):.2f} in variance (each view's and image's "
            "pull on the intrinsics and the plane)")


def joint_dispersion_covers(plane: LightPlane) -> str:
    """After a joint refinement of camera and plane: the phrase that says both shares include its
    dispersion (:func:`lightplane.plane.joint.joint_dispersion`); empty otherwise."""
    if not plane.meta.get("joint_dispersion_applied"):
        return ""
    return "; both refined jointly, " + joint_dispersion_phrase(plane.meta["joint_dispersion"])


#: Said wherever a figure lacks the camera's share.
CAMERA_SHARE_MISSING = "the camera's share is not included (the camera file has no covariance)"


def camera_uncertainty_summary(camera: Camera, distance_mm: float, step_px: float = 32.0) -> dict:
    """What the camera's covariance means at ``distance_mm``: the sigma of a ray's direction
    (deg; RMS over the image and its maximum) and the same as a displacement across the
    ray at that distance (mm).  ``{"included": False, "note": ...}`` without a covariance."""
    if camera.covariance is None:
        return {"included": False, "note": CAMERA_SHARE_MISSING}
    if not distance_mm > 0:
        raise LightplaneError(f"the working distance must be positive, got {distance_mm} mm")
    s = ray_sigma_rad(camera, image_grid(camera, step_px))
    rms, mx = float(np.sqrt(np.mean(s**2))), float(np.max(s))
    return {"included": True, "distance_mm": float(distance_mm),
            "ray_sigma_deg_rms": float(np.degrees(rms)), "ray_sigma_deg_max": float(np.degrees(mx)),
            "ray_sigma_mm_rms": rms * float(distance_mm), "ray_sigma_mm_max": mx * float(distance_mm),
            "covers": CAMERA_SHARE_COVERS}


# ------------------------------------------------------- points: the plane's and the camera's shares
def plane_camera_jacobian(plane: LightPlane) -> tuple[np.ndarray, tuple[str, ...]] | None:
    """``(J (4, P), params)``: ∂(a, b, c, d)/∂(intrinsics) recorded by the plane calibration
    (:func:`lightplane.plane.calibrate.propagate_camera`), or None."""
    dep = plane.camera_dependence
    return None if dep is None else (dep.matrix, dep.params)


def camera_share_status(camera: Camera, plane: LightPlane) -> str | None:
    """None when the camera's share can be included in a point's uncertainty, else why not (one sentence)."""
    if camera.covariance is None:
        return CAMERA_SHARE_MISSING
    rec = plane_camera_jacobian(plane)
    if rec is None:
        return ("the camera's share is not included (the plane file records no dependence on the intrinsics: "
                "calibrate the plane with a camera file that has a covariance)")
    if rec[1] != camera_param_names(camera):
        raise LightplaneError(f"the plane was calibrated with a camera of parameters ({', '.join(rec[1])}) but this "
                              f"camera has ({', '.join(camera_param_names(camera))}): wrong camera file?")
    return None


def _shifted_plane(plane: LightPlane, delta: np.ndarray) -> LightPlane:
    return LightPlane(plane.normal + delta[:3], plane.d + delta[3])


def point_error_basis(camera: Camera, plane: LightPlane, uv: np.ndarray, *, covariance: np.ndarray | None = None,
                      camera_share: bool = True) -> tuple[np.ndarray, bool]:
    """``(E (N, 3, m), camera_included)``: the points triangulated from distorted pixels
    ``uv`` (N, 2) err by ``E ξ`` with ``ξ ~ N(0, I_m)`` common to all points (first order).

    The columns: the plane's own covariance (image noise of the plane calibration; or
    ``covariance``, a 4x4 to use instead), then — when ``camera_share`` and the camera
    has a covariance and the plane records its dependence on the intrinsics — one column
    per principal axis of the intrinsics' covariance: each point moved by a one-sigma
    change of the intrinsics *with* the plane's change it causes (the ray and the plane
    are correlated through the same intrinsics), by central differences.  A point's
    covariance is ``E_i E_iᵀ``; two points' cross-covariance ``E_i E_jᵀ``.
    """
    uv = as_points(uv, 2, "uv")
    cov = _plane_cov(plane, covariance)
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    U = V * np.sqrt(np.maximum(w, 0.0))
    xy = camera.undistort_points(uv, normalized=True)
    cols = [point_jacobian(plane, xy) @ U]
    included = bool(camera_share) and camera_share_status(camera, plane) is None
    if included:
        J, _ = plane_camera_jacobian(plane)  # type: ignore[misc]
        p0 = camera_params(camera)
        D = []
        for s in camera_steps(camera):
            a = triangulate_normalized(_shifted_plane(plane, J @ s),
                                       camera_with_params(camera, p0 + s).undistort_points(uv, normalized=True)).points
            b = triangulate_normalized(_shifted_plane(plane, -J @ s),
                                       camera_with_params(camera, p0 - s).undistort_points(uv, normalized=True)).points
            D.append(0.5 * (a - b))
        if D:
            cols.append(np.stack(D, axis=2))
    return np.concatenate(cols, axis=2), included


def rigid_motion_basis(points: np.ndarray) -> np.ndarray:
    """(3N, 6) orthonormal basis of the point displacements a small rigid motion of the
    ``points`` (N, 3) makes (3 translations, 3 rotations about their centroid)."""
    p = points - points.mean(axis=0)
    n = len(p)
    B = np.zeros((n, 3, 6))
    B[:, :, :3] = np.eye(3)
    for k in range(3):
        B[:, :, 3 + k] = np.cross(np.eye(3)[k], p)
    Q, _ = np.linalg.qr(B.reshape(3 * n, 6))
    return Q


def shape_error_basis(E: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``E`` (N, 3, m) with the part a rigid motion of ``points`` explains projected out:
    the errors left after the best rigid alignment of the point set (first order)."""
    n, _, m = E.shape
    Q = rigid_motion_basis(points)
    flat = E.reshape(3 * n, m)
    return (flat - Q @ (Q.T @ flat)).reshape(n, 3, m)


@dataclass(frozen=True)
class VolumeSigma:
    """RMS sigmas (mm) over a working volume's points: ``camera_frame_mm`` (absolute
    positions), ``shape_mm`` (after the best rigid motion over the volume), both with all
    the sources the files carry; ``plane_only_mm`` the plane calibration's image noise
    alone (the figure of earlier versions); ``camera_included`` and ``covers`` say which."""

    camera_frame_mm: float
    shape_mm: float
    plane_only_mm: float
    camera_included: bool
    covers: str


def volume_sigma(camera: Camera, plane: LightPlane, volume: WorkingVolume, *,
                 covariance: np.ndarray | None = None) -> VolumeSigma:
    """Camera-frame and shape sigma over ``volume`` (see :class:`VolumeSigma`)."""
    E, inc = point_error_basis(camera, plane, volume.uv, covariance=covariance)
    ok = np.all(np.isfinite(E), axis=(1, 2))
    E = E[ok]
    if len(E) < 3:
        raise LightplaneError("fewer than 3 working-volume points to state an uncertainty over")
    frame = float(np.sqrt(np.sum(E**2) / len(E)))
    shape = float(np.sqrt(np.sum(shape_error_basis(E, volume.points[ok]) ** 2) / len(E)))
    plane_only = float(np.sqrt(np.sum(E[:, :, :4] ** 2) / len(E)))
    own = plane_noise_covers(plane)
    covers = (own + " and " + CAMERA_SHARE_COVERS + joint_dispersion_covers(plane) if inc else
              own + " only; " + (camera_share_status(camera, plane) or ""))
    return VolumeSigma(frame, shape, plane_only, inc, covers)


#: One sentence saying which sigma applies when (printed next to the two figures).
WHICH_SIGMA = ("camera-frame σ: absolute positions (robot guidance, registration to a machine); "
               "shape σ: what remains after the best rigid motion over the working volume (distances, heights, "
               "flatness)")
