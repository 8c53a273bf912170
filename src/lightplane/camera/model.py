"""Camera model: pinhole with one of OpenCV's lens models (docs/conventions.md §Lens model, paper Eq. 1–3).

Conventions (docs/conventions.md §Frames, §Units, §Pixels): camera frame x right, y down, z forward; millimetres;
pixel (0, 0) is the centre of the top-left pixel.  The lens model (:mod:`lightplane.camera.lens`) is
``plumb_bob`` ``(k1, k2, p1, p2, k3)``, ``rational`` (8 coefficients), ``thin_prism`` (12),
``tilted`` (14, a Scheimpflug sensor) or ``fisheye`` (4, ``cv2.fisheye``); for the plumb bob, with
normalised undistorted ``(x, y)``, ``r² = x² + y²``::

    x_d = x (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2 x²)
    y_d = y (1 + k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2 y²) + 2 p2 x y
    [u, v, 1]ᵀ = K [x_d, y_d, 1]ᵀ      (K may have a skew K[0, 1])

Every projection, undistortion and Jacobian of the package goes through this class.

Camera files: our JSON, ROS ``camera_info`` YAML, OpenCV FileStorage YAML/XML.

>>> import numpy as np
>>> cam = Camera(K=[[1000, 0, 640], [0, 1000, 480], [0, 0, 1]], dist=[-0.3, 0.1, 0.001, 0.001, 0], width=1280, height=960)
>>> uv = cam.project(np.array([[10.0, -5.0, 400.0]]))
>>> bool(np.allclose(cam.undistort_points(uv, normalized=True), [[10 / 400, -5 / 400]], atol=1e-12))
True
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lightplane.core.errors import LightplaneError
from lightplane.camera.lens import MODELS, ROS_MODELS, coeff_names, distort_jac, lens_params, model_for
from lightplane.camera.lens_kernels import newton_undistort, newton_undistort_from
from lightplane.core.io import atomic_write, read_json, write_json

__all__ = ["Camera", "as_points", "SAME_CAMERA_RTOL", "ALLOWED_CAMERA_KEY", "camera_record", "camera_difference",
           "check_calibrated_with"]


def as_points(x: Any, dim: int, name: str) -> np.ndarray:
    """Check and convert an array of points to ``(N, dim)`` float64 (a single point is accepted)."""
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 1 and a.shape[0] == dim:
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] != dim:
        raise LightplaneError(f"{name} must have shape (N, {dim}), got {np.shape(x)}")
    return a


def _tight_criteria():
    import cv2

    return (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)


@dataclass(frozen=True, eq=False)
class Camera:
    """A calibrated camera.

    Attributes
    ----------
    K : (3, 3) float64
        Intrinsic matrix ``[[fu, s, u0], [0, fv, v0], [0, 0, 1]]`` in pixels (skew ``s`` usually 0).
    dist : (n,) float64
        The distortion coefficients in OpenCV's order, n = 5 (plumb bob), 8 (rational), 12 (thin
        prism), 14 (tilted) or 4 (fisheye).
    width, height : int
        Image size in pixels.
    rms_px : float or None
        Reprojection RMS of the calibration that produced it, if known.
    meta : dict
        Free-form provenance (where it came from); not used in computations.
    covariance : (P, P) float64 or None
        Covariance of the intrinsic parameters named by ``covariance_params`` (px², from
        :func:`lightplane.camera.intrinsics.intrinsics_covariance`; fixed parameters have zero
        rows), or None when unknown (the camera's share of a point's uncertainty is then
        not included anywhere).
    covariance_params : tuple of str or None
        The parameter order of ``covariance``: ``fx, fy, cx, cy`` then the distortion
        coefficients in ``dist``'s order.
    model : str
        The lens model (:data:`lightplane.camera.lens.MODELS`); None infers it from the length of
        ``dist`` (4 or 5: plumb bob, 8 rational, 12 thin prism, 14 tilted; fisheye must be named).
    """

    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int
    rms_px: float | None = None
    meta: dict = field(default_factory=dict, compare=False, repr=False)
    covariance: np.ndarray | None = field(default=None, compare=False, repr=False)
    covariance_params: tuple[str, ...] | None = field(default=None, compare=False, repr=False)
    model: str | None = None
    # the packed parameters of lightplane.camera.lens (set in __post_init__ from model and dist)
    _lens: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise LightplaneError(f"K must be a finite 3x3 matrix, got {np.shape(self.K)}")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise LightplaneError(f"K: focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
        if abs(K[2, 2] - 1) > 1e-9 or np.any(np.abs(K[2, :2]) > 1e-12) or abs(K[1, 0]) > 1e-12:
            raise LightplaneError("K: last row must be [0, 0, 1] and K[1, 0] zero")
        model, d = model_for(self.dist, self.model)
        try:
            w, h = int(self.width), int(self.height)
        except (TypeError, ValueError):
            raise LightplaneError(f"width/height must be integers, got {self.width!r}, {self.height!r}") from None
        if w <= 0 or h <= 0:
            raise LightplaneError(f"width and height must be positive, got {w}x{h}")
        K.setflags(write=False)
        d.setflags(write=False)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", d)
        object.__setattr__(self, "model", model)
        object.__setattr__(self, "_lens", lens_params(model, d))
        object.__setattr__(self, "width", w)
        object.__setattr__(self, "height", h)
        if self.rms_px is not None:
            object.__setattr__(self, "rms_px", float(self.rms_px))
        if self.covariance is not None:
            C = np.asarray(self.covariance, dtype=np.float64)
            names = tuple(str(n) for n in (self.covariance_params or ()))
            if C.ndim != 2 or C.shape[0] != C.shape[1] or C.shape[0] != len(names) or not np.all(np.isfinite(C)):
                raise LightplaneError(f"covariance must be a finite square matrix with one name per row in "
                                      f"covariance_params, got shape {C.shape} and {len(names)} names")
            C = 0.5 * (C + C.T)
            C.setflags(write=False)
            object.__setattr__(self, "covariance", C)
            object.__setattr__(self, "covariance_params", names)
        elif self.covariance_params is not None:
            object.__setattr__(self, "covariance_params", None)

    # ------------------------------------------------------------------ basics
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def skew(self) -> float:
        return float(self.K[0, 1])

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.width, self.height

    @property
    def has_distortion(self) -> bool:
        """False only where pixels map to rays by K alone (fisheye never: its θ = atan r is not a pinhole)."""
        return self.model == "fisheye" or bool(np.any(self.dist != 0))

    def pinhole(self) -> "Camera":
        """The same camera without distortion."""
        return Camera(self.K, np.zeros(5), self.width, self.height, self.rms_px, dict(self.meta), model="plumb_bob")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        return (
            np.array_equal(self.K, other.K)
            and self.model == other.model
            and np.array_equal(self.dist, other.dist)
            and self.width == other.width
            and self.height == other.height
        )

    def __repr__(self) -> str:
        return (
            f"Camera({self.width}x{self.height}, fx={self.fx:.3f}, fy={self.fy:.3f}, "
            f"cx={self.cx:.3f}, cy={self.cy:.3f}, {self.model} dist={np.array2string(self.dist, precision=5)})"
        )

    # ------------------------------------------------------------- projection
    def distort_normalized(self, xy: np.ndarray) -> np.ndarray:
        """Apply the lens model to normalised undistorted ``(N, 2)`` coordinates (:mod:`lightplane.camera.lens`)."""
        xy = as_points(xy, 2, "xy")
        xd, yd, *_ = distort_jac(xy[:, 0], xy[:, 1], self._lens)
        return np.column_stack([xd, yd])

    def normalized_to_pixels(self, xy: np.ndarray, *, distort: bool = True) -> np.ndarray:
        """Normalised ``(N, 2)`` coordinates (undistorted) to pixels, distorted unless ``distort=False``."""
        xy = as_points(xy, 2, "xy")
        if distort:
            xy = self.distort_normalized(xy)
        K = self.K
        return np.column_stack([K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2], K[1, 1] * xy[:, 1] + K[1, 2]])

    def pixels_to_normalized_linear(self, uv: np.ndarray) -> np.ndarray:
        """Pixels to normalised coordinates by K⁻¹ only (no distortion handling)."""
        uv = as_points(uv, 2, "uv")
        K = self.K
        y = (uv[:, 1] - K[1, 2]) / K[1, 1]
        x = (uv[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        return np.column_stack([x, y])

    def project(self, p_cam: np.ndarray, *, distort: bool = True) -> np.ndarray:
        """Project ``(N, 3)`` camera-frame points (mm) to ``(N, 2)`` pixels.

        Points on or behind the camera plane (z ≤ 0) give NaN.
        """
        p = as_points(p_cam, 3, "p_cam")
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = p[:, :2] / z[:, None]
        xy[~(z > 0)] = np.nan
        return self.normalized_to_pixels(xy, distort=distort)

    def undistort_points(self, uv: np.ndarray, *, normalized: bool = False) -> np.ndarray:
        """Remove lens distortion from ``(N, 2)`` pixel coordinates.

        Returns undistorted pixels (``K`` applied again) or, with ``normalized=True``,
        normalised coordinates ``(x, y)`` such that the ray is ``(x, y, 1)``.
        OpenCV's iterative undistortion (tight criteria) gives the start; a few
        Newton steps on the exact model (docs/conventions.md §Lens model) take it to ~1e-12 px, even with
        strong distortion where the fixed-point iteration is slow.
        """
        uv = as_points(uv, 2, "uv")
        if not self.has_distortion:
            xy = self.pixels_to_normalized_linear(uv)
        else:
            xy = self._undistort_normalized(uv)
        return xy if normalized else self.normalized_to_pixels(xy, distort=False)

    def _undistort_normalized(self, uv: np.ndarray) -> np.ndarray:
        """Newton on the exact model from the linear guess K⁻¹uv (fisheye: its equidistant inverse); any
        point that does not then reproject onto its pixel within 1e-9 px is redone from
        OpenCV's iterative undistortion (tight criteria) followed by Newton."""
        import cv2

        target = self.pixels_to_normalized_linear(uv)
        good = np.all(np.isfinite(uv), axis=1)
        xy, err = np.empty((len(uv), 2)), np.empty(len(uv))
        # per point (lightplane.camera.lens_kernels): Newton to a step of 1e-16, the reprojection error (px)
        newton_undistort(np.ascontiguousarray(target[:, 0]), np.ascontiguousarray(target[:, 1]), self._lens, self.K,
                         np.ascontiguousarray(uv[:, 0]), np.ascontiguousarray(uv[:, 1]), 12, xy, err)
        redo = good & ~(err < 1e-9)
        xy[~good] = np.nan
        if np.any(redo):
            src = np.ascontiguousarray(target[redo]).reshape(-1, 1, 2)  # K⁻¹ applied by us (skew included)
            crit = _tight_criteria()
            if self.model == "fisheye":
                xy0 = cv2.fisheye.undistortPoints(src, np.eye(3), self.dist, np.eye(3), np.eye(3), criteria=crit)
            elif hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
                xy0 = cv2.undistortPointsIter(src, np.eye(3), self.dist, np.eye(3), np.eye(3), crit)
            else:  # OpenCV 5 takes the criteria in undistortPoints itself
                xy0 = cv2.undistortPoints(src, np.eye(3), self.dist, None, np.eye(3), np.eye(3), crit)
            with np.errstate(all="ignore"):
                xy[redo] = self._newton_undistort(xy0.reshape(-1, 2).astype(np.float64), target[redo])
        return xy

    def distortion_jacobian(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Entries ``(j11, j12, j21, j22)`` of ∂(x_d, y_d)/∂(x, y) at normalised undistorted ``xy`` (N, 2).

        The derivative of the camera's lens model (:func:`lightplane.camera.lens.distort_jac`); ``j12 == j21``
        only for the radially symmetric part (thin prism and tilt make it unsymmetric).
        """
        xy = as_points(xy, 2, "xy")
        return distort_jac(xy[:, 0], xy[:, 1], self._lens)[2:]

    def pixel_jacobian(self, xy: np.ndarray) -> np.ndarray:
        """``(N, 2, 2)``: ∂(u, v)/∂(x, y), distortion and K, at normalised undistorted ``xy``."""
        j11, j12, j21, j22 = self.distortion_jacobian(xy)
        K = self.K
        out = np.empty((len(j11), 2, 2))
        out[:, 0, 0] = K[0, 0] * j11 + K[0, 1] * j21
        out[:, 0, 1] = K[0, 0] * j12 + K[0, 1] * j22
        out[:, 1, 0] = K[1, 1] * j21
        out[:, 1, 1] = K[1, 1] * j22
        return out

    def _undistort_near(self, uv: np.ndarray, start: np.ndarray, *, iters: int = 8,
                        tol_px: float = 1e-5) -> tuple[np.ndarray, tuple]:
        """:meth:`undistort_points` (normalised) of pixels ``uv`` (N, 2) by Newton from ``start`` (N, 2), a
        close guess (e.g. a local linearisation of the lens about a nearby point), with
        :meth:`distortion_jacobian` (j11, j12, j21, j22) at the result.

        Each point iterates until its step is below ``tol_px``: Newton's error squares each step, so
        that step ends within ~(tol_px / f)² f of the root (1e-14 px for 1e-5 px, f = 4000 px); the
        Jacobian kept is the one at that step's start (a relative change of ~1e-10 over tol_px).  A
        point not there after ``iters`` steps, or not finite, is solved by :meth:`undistort_points`
        instead.  From a start within ~1 px: two evaluations of the lens model instead of ~6, a point
        at a time (compiled: :func:`lightplane.camera.lens_kernels.newton_undistort_from`)."""
        target = self.pixels_to_normalized_linear(uv)
        n = len(uv)
        xy, jac, done = np.empty((n, 2)), np.empty((4, n)), np.empty(n, bool)
        newton_undistort_from(np.ascontiguousarray(target[:, 0]), np.ascontiguousarray(target[:, 1]),
                              np.ascontiguousarray(start[:, 0], np.float64),
                              np.ascontiguousarray(start[:, 1], np.float64), self._lens,
                              tol_px / max(self.K[0, 0], self.K[1, 1]), int(iters), xy, jac, done)
        redo = ~done
        if np.any(redo):
            xy[redo] = self._undistort_normalized(uv[redo])
            jac[:, redo] = np.array(self.distortion_jacobian(xy[redo]))
        return xy, (jac[0], jac[1], jac[2], jac[3])

    def _newton_undistort(self, xy: np.ndarray, target: np.ndarray, iters: int = 20) -> np.ndarray:
        """Solve distort(xy) = target by Newton's method, starting from ``xy``."""
        for _ in range(iters):
            xd, yd, j11, j12, j21, j22 = distort_jac(xy[:, 0], xy[:, 1], self._lens)
            f0, f1 = xd - target[:, 0], yd - target[:, 1]
            det = j11 * j22 - j12 * j21
            dx = (j22 * f0 - j12 * f1) / det
            dy = (-j21 * f0 + j11 * f1) / det
            xy = xy - np.column_stack([dx, dy])
            if not np.nanmax(np.abs(np.concatenate([dx, dy])), initial=0.0) > 1e-16:
                break
        return xy

    def solve_pnp(self, obj: np.ndarray, uv: np.ndarray, *, name: str = "points") -> tuple[np.ndarray, np.ndarray]:
        """Pose ``(R, t)`` (camera <- object) minimising the pixel reprojection error of ``(N, 3)`` object
        points seen at distorted pixels ``uv`` (N, 2).

        OpenCV's ``solvePnP`` + ``solvePnPRefineLM`` with K and the distortion vector where OpenCV
        projects as this camera does (no skew, not fisheye); otherwise the same on the undistorted
        normalised points, then Levenberg-Marquardt on the pixel residuals of :meth:`project`.
        """
        import cv2

        o = np.ascontiguousarray(as_points(obj, 3, "obj"))
        u = np.ascontiguousarray(as_points(uv, 2, "uv"))
        native = self.model != "fisheye" and self.skew == 0
        K, d, pts = (self.K, self.dist, u) if native else (np.eye(3), None, self.undistort_points(u, normalized=True))
        ok, rvec, tvec = cv2.solvePnP(o, pts, K, d, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok or not np.all(np.isfinite(rvec)) or not np.all(np.isfinite(tvec)):
            raise LightplaneError(f"{name}: solvePnP failed")
        rvec, tvec = cv2.solvePnPRefineLM(o, pts, K, d, rvec, tvec)
        if not native:
            from scipy.optimize import least_squares

            def res(x: np.ndarray) -> np.ndarray:
                R = cv2.Rodrigues(x[:3])[0]
                return (self.project(o @ R.T + x[3:]) - u).ravel()

            x = least_squares(res, np.concatenate([rvec.ravel(), tvec.ravel()]), method="lm", xtol=1e-14,
                              ftol=1e-14).x
            rvec, tvec = x[:3], x[3:]
        return cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3))[0], np.asarray(tvec, np.float64).ravel()

    def rays(self, uv: np.ndarray, *, unit: bool = False) -> np.ndarray:
        """Camera-frame rays ``(N, 3)`` through distorted pixels ``uv``.

        By default ``(x, y, 1)`` (the point at depth z = 1 mm); ``unit=True`` normalises.
        """
        xy = self.undistort_points(uv, normalized=True)
        r = np.column_stack([xy, np.ones(len(xy))])
        if unit:
            r /= np.linalg.norm(r, axis=1, keepdims=True)
        return r

    def undistort_image(self, img: np.ndarray, *, interpolation: int | None = None) -> np.ndarray:
        """Resample an image as seen by the same camera without distortion (same K, every lens model)."""
        import cv2

        if interpolation is None:
            interpolation = cv2.INTER_LINEAR
        h, w = img.shape[:2]
        v, u = np.mgrid[0:h, 0:w]
        xy = self.pixels_to_normalized_linear(np.column_stack([u.ravel(), v.ravel()]).astype(np.float64))
        with np.errstate(all="ignore"):
            src = self.normalized_to_pixels(xy).reshape(h, w, 2).astype(np.float32)
        return cv2.remap(img, src[..., 0], src[..., 1], interpolation)

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Boolean mask of ``(N, 2)`` pixels inside the image (pixel centres 0..W-1)."""
        uv = as_points(uv, 2, "uv")
        return (
            (uv[:, 0] >= -0.5 + margin)
            & (uv[:, 0] <= self.width - 0.5 - margin)
            & (uv[:, 1] >= -0.5 + margin)
            & (uv[:, 1] <= self.height - 0.5 - margin)
        )

    def check_image(self, img: np.ndarray, name: str = "image") -> None:
        """Raise if an image's size differs from the camera's (a wrong camera file)."""
        h, w = img.shape[:2]
        if (w, h) != (self.width, self.height):
            raise LightplaneError(
                f"{name} is {w}x{h} px but the camera is calibrated for {self.width}x{self.height} px (wrong camera file?)"
            )

    # ------------------------------------------------------------------ files
    def to_dict(self) -> dict:
        d = {
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "model": self.model,
            "dist": self.dist.tolist(),
        }
        if self.rms_px is not None:
            d["rms_px"] = self.rms_px
        if self.covariance is not None:
            d["covariance"] = self.covariance.tolist()
            d["covariance_params"] = list(self.covariance_params or ())  # set with the covariance
        return d

    @classmethod
    def from_dict(cls, d: dict, source: str = "camera") -> "Camera":
        """From our JSON layout ``{"width", "height", "K", "model"?, "dist", "rms_px"?, "covariance"?,
        "covariance_params"?}`` (no model: from the length of ``dist``)."""
        for key in ("width", "height", "K", "dist"):
            if key not in d:
                raise LightplaneError(f"{source}: missing field '{key}'")
        try:
            K = np.asarray(d["K"], dtype=np.float64)
        except (TypeError, ValueError):
            raise LightplaneError(f"{source}: field 'K' is not a 3x3 matrix of numbers") from None
        if K.shape != (3, 3):
            raise LightplaneError(f"{source}: field 'K' must be 3x3, got shape {K.shape}")
        try:
            dist = np.asarray(d["dist"], dtype=np.float64).ravel()
        except (TypeError, ValueError):
            raise LightplaneError(f"{source}: field 'dist' is not a list of numbers") from None
        cov, names = d.get("covariance"), d.get("covariance_params")
        if (cov is None) != (names is None):
            raise LightplaneError(f"{source}: 'covariance' and 'covariance_params' go together (one is missing)")
        try:
            if cov is not None:
                cov = np.asarray(cov, dtype=np.float64)
                if not isinstance(names, list):
                    raise TypeError
        except (TypeError, ValueError):
            raise LightplaneError(f"{source}: field 'covariance' must be a matrix of numbers and "
                                  f"'covariance_params' a list of names") from None
        model = d.get("model")
        if model is not None and not isinstance(model, str):
            raise LightplaneError(f"{source}: field 'model' must be a lens model name ({', '.join(MODELS)})")
        try:
            return cls(K, dist, d["width"], d["height"], d.get("rms_px"), meta={"source": source},
                       covariance=cov, covariance_params=None if names is None else tuple(names), model=model)
        except LightplaneError as e:
            raise LightplaneError(f"{source}: {e}") from None

    def save_json(self, path: str | os.PathLike, *, force: bool = False, extra: dict | None = None) -> Path:
        """Write our JSON camera file atomically (``extra`` keys, e.g. provenance, are added)."""
        d = self.to_dict()
        if extra:
            d.update(extra)
        return write_json(path, d, force=force)

    def ros_yaml_text(self, camera_name: str = "camera") -> str:
        """ROS ``camera_info`` YAML text (identity R, P = [K | 0]); ``distortion_model`` plumb_bob,
        rational_polynomial (8, 12 or 14 coefficients, as ROS's image_geometry hands them to OpenCV)
        or equidistant (fisheye)."""
        import yaml

        P = np.hstack([self.K, np.zeros((3, 1))])
        assert self.model is not None  # __post_init__ names the model
        doc = {
            "image_width": self.width,
            "image_height": self.height,
            "camera_name": camera_name,
            "camera_matrix": {"rows": 3, "cols": 3, "data": [float(v) for v in self.K.ravel()]},
            "distortion_model": ROS_MODELS[self.model],
            "distortion_coefficients": {"rows": 1, "cols": int(self.dist.size), "data": [float(v) for v in self.dist]},
            "rectification_matrix": {"rows": 3, "cols": 3, "data": [float(v) for v in np.eye(3).ravel()]},
            "projection_matrix": {"rows": 3, "cols": 4, "data": [float(v) for v in P.ravel()]},
        }
        return yaml.safe_dump(doc, sort_keys=False)

    def save_ros_yaml(self, path: str | os.PathLike, *, force: bool = False) -> Path:
        return atomic_write(path, self.ros_yaml_text(), force=force)

    def save_opencv(self, path: str | os.PathLike, *, force: bool = False) -> Path:
        """Write an OpenCV FileStorage file (``.yaml``/``.yml`` or ``.xml`` by suffix)."""
        import cv2

        def writer(tmp: str) -> None:
            fs = cv2.FileStorage(tmp, cv2.FILE_STORAGE_WRITE)
            fs.write("image_width", self.width)
            fs.write("image_height", self.height)
            fs.write("camera_matrix", self.K)
            fs.write("distortion_model", str(self.model))  # named by __post_init__
            fs.write("distortion_coefficients", self.dist.reshape(1, -1))
            fs.release()

        if Path(path).suffix.lower() not in (".yaml", ".yml", ".xml"):
            raise LightplaneError(f"{path}: OpenCV camera files must end in .yaml, .yml or .xml")
        return atomic_write(path, writer, force=force)

    def save(self, path: str | os.PathLike, *, force: bool = False, fmt: str | None = None) -> Path:
        """Save by format: ``json`` (default for .json), ``ros`` or ``opencv`` (.xml)."""
        suffix = Path(path).suffix.lower()
        fmt = fmt or ("json" if suffix == ".json" else "opencv" if suffix == ".xml" else "ros")
        if fmt == "json":
            return self.save_json(path, force=force)
        if fmt == "ros":
            return self.save_ros_yaml(path, force=force)
        if fmt == "opencv":
            return self.save_opencv(path, force=force)
        raise LightplaneError(f"unknown camera file format {fmt!r} (json, ros, opencv)")

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Camera":
        """Read a camera file: our JSON, ROS ``camera_info`` YAML, or OpenCV FileStorage YAML/XML
        (or a sensor file's camera, :mod:`lightplane.measure.sensor`).

        The format is recognised from the content.  A missing file, a corrupt one, or
        a missing/invalid field raises :class:`LightplaneError` naming the file and field.
        """
        p = Path(path)
        if not p.is_file():
            raise LightplaneError(f"{p}: no such camera file")
        try:
            text = p.read_text()
        except UnicodeDecodeError:
            raise LightplaneError(f"{p}: not a text camera file (JSON, YAML or XML expected)") from None
        head = text.lstrip()[:64]
        if head.startswith("{"):
            d = read_json(p, "camera file")
            if d.get("kind") == "lightplane sensor" and isinstance(d.get("camera"), dict):
                d = d["camera"]  # a sensor file (lightplane.measure.sensor) holds its camera
            return cls.from_dict(d, source=str(p))
        if head.startswith("<") or head.startswith("%YAML"):
            return cls._load_opencv(p)
        return cls._load_ros(p, text)

    @classmethod
    def _load_ros(cls, p: Path, text: str) -> "Camera":
        import yaml

        try:
            doc = yaml.safe_load(text)
        except yaml.YAMLError as e:
            raise LightplaneError(f"{p}: not valid YAML ({str(e).splitlines()[0]})") from None
        if not isinstance(doc, dict):
            raise LightplaneError(f"{p}: not a camera file (expected a YAML mapping or JSON object)")

        def matrix(key: str, n: int | None) -> np.ndarray:
            if key not in doc:
                raise LightplaneError(f"{p}: missing field '{key}'")
            node = doc[key]
            data = node.get("data") if isinstance(node, dict) else node
            try:
                a = np.asarray(data, dtype=np.float64).ravel()
            except (TypeError, ValueError):
                raise LightplaneError(f"{p}: field '{key}' is not a list of numbers") from None
            if n is not None and a.size != n:
                raise LightplaneError(f"{p}: field '{key}' must hold {n} numbers, got {a.size}")
            return a

        K = matrix("camera_matrix", 9).reshape(3, 3)
        dist = matrix("distortion_coefficients", None)
        ros_model = doc.get("distortion_model", "plumb_bob")
        try:
            model = _model_from_ros(ros_model, dist.size)
        except LightplaneError as e:
            raise LightplaneError(f"{p}: {e}") from None
        for key in ("image_width", "image_height"):
            if key not in doc:
                raise LightplaneError(f"{p}: missing field '{key}'")
        try:
            return cls(K, dist, doc["image_width"], doc["image_height"], meta={"source": str(p), "format": "ros"},
                       model=model)
        except LightplaneError as e:
            raise LightplaneError(f"{p}: {e}") from None

    @classmethod
    def _load_opencv(cls, p: Path) -> "Camera":
        import cv2

        try:
            fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
        except cv2.error as e:
            raise LightplaneError(f"{p}: not a valid OpenCV FileStorage file ({str(e).strip().splitlines()[-1]})") from None
        if not fs.isOpened():
            raise LightplaneError(f"{p}: cannot be opened as an OpenCV FileStorage file")
        try:
            def mat(key: str) -> np.ndarray:
                node = fs.getNode(key)
                if node.empty():
                    raise LightplaneError(f"{p}: missing field '{key}'")
                m = node.mat()
                if m is None:
                    raise LightplaneError(f"{p}: field '{key}' is not a matrix")
                return np.asarray(m, dtype=np.float64)

            def integer(key: str) -> int:
                node = fs.getNode(key)
                if node.empty():
                    raise LightplaneError(f"{p}: missing field '{key}'")
                return int(node.real())

            K = mat("camera_matrix")
            if K.shape != (3, 3):
                raise LightplaneError(f"{p}: field 'camera_matrix' must be 3x3, got {K.shape}")
            dist = mat("distortion_coefficients").ravel()
            w, h = integer("image_width"), integer("image_height")
            node = fs.getNode("distortion_model")
            model = None if node.empty() else node.string()
            if model is not None and not model:
                raise LightplaneError(f"{p}: field 'distortion_model' must be a lens model name")
        finally:
            fs.release()
        try:
            if model is not None:
                model = _model_from_ros(model, dist.size) if model in _ROS_NAMES else model
            return cls(K, dist, w, h, meta={"source": str(p), "format": "opencv"}, model=model)
        except LightplaneError as e:
            raise LightplaneError(f"{p}: {e}") from None


#: relative tolerance of :func:`camera_difference`: K's entries within ``SAME_CAMERA_RTOL`` times the
#: focal length (1e-3 px at f = 1000 px), each distortion coefficient within ``SAME_CAMERA_RTOL``
#: times ``max(1, |k|)``.  A recalibration of the same camera moves f by ~1e-4 of itself (its σ)
#: or more, so it is "another camera"; a camera file written again (JSON, ROS or OpenCV YAML/XML,
#: all with >= 7 significant digits) is the same one.
SAME_CAMERA_RTOL = 1e-6

#: the field of a plane or turntable record, inside a sensor file, naming the camera (a
#: :func:`camera_record`) it was joined with by ``lightplane sensor --allow-other-camera``
ALLOWED_CAMERA_KEY = "allowed_camera"


def camera_record(camera: Camera) -> dict:
    """What a result file records of the camera it was calibrated with (``"camera"``): image size,
    lens model, K and the distortion coefficients (:func:`camera_difference` compares them)."""
    return {"width": camera.width, "height": camera.height, "model": camera.model, "K": camera.K.tolist(),
            "dist": camera.dist.tolist()}


def _recorded(rec: Any) -> tuple[tuple[int, int], str, np.ndarray, np.ndarray] | None:
    try:
        size = (int(rec["width"]), int(rec["height"]))
        K = np.asarray(rec["K"], dtype=np.float64).reshape(3, 3)
        model, dist = model_for(rec["dist"], rec.get("model"))
    except (KeyError, TypeError, ValueError, AttributeError, LightplaneError):
        return None
    return (size, model, K, dist) if np.all(np.isfinite(K)) else None


def camera_difference(recorded: Any, camera: Camera, rtol: float = SAME_CAMERA_RTOL) -> str | None:
    """The first difference between a recorded camera (a dict as :func:`camera_record` or
    :meth:`Camera.to_dict` write it) and ``camera``, in words (``fx 1000 px vs 1005 px``: the
    recorded value first), or None when they are the same camera: the same image size and lens
    model, K and the coefficients within :data:`SAME_CAMERA_RTOL` (see there)."""
    rec = _recorded(recorded)
    if rec is None:
        return "its recorded camera is malformed"
    size, model, K, dist = rec
    if size != camera.size:
        return f"image size {size[0]}x{size[1]} px vs {camera.width}x{camera.height} px"
    if model != camera.model:
        return f"lens model {model} vs {camera.model}"
    tol = rtol * max(camera.fx, camera.fy)
    for name, (i, j) in (("fx", (0, 0)), ("fy", (1, 1)), ("cx", (0, 2)), ("cy", (1, 2)), ("skew", (0, 1))):
        if not abs(K[i, j] - camera.K[i, j]) <= tol:
            return f"{name} {K[i, j]:.10g} px vs {camera.K[i, j]:.10g} px"
    for name, a, b in zip(coeff_names(model), dist, camera.dist):
        if not abs(a - b) <= rtol * max(1.0, abs(a), abs(b)):
            return f"distortion {name} {a:.10g} vs {b:.10g}"
    return None


def check_calibrated_with(recorded: Any, camera: Camera, *, source: str, camera_file: str, what: str,
                          allow_other: bool = False, override: Any = None) -> str | None:
    """Raise :class:`LightplaneError` (one line naming ``source``, ``camera_file`` and the first
    difference) when ``recorded`` (the camera a ``what`` -- "plane", "turntable" -- was calibrated
    with, None if the file records none) is not ``camera``.

    Returns None when it is the same camera, else the one-line note to show and to record in the
    output's provenance: the file records no camera (written before files recorded it: not
    checked), or it differs and the use is allowed -- by ``allow_other`` (the
    ``--allow-other-camera`` flag) or by ``override``, a camera record this file was explicitly
    joined with before (a sensor file built with the flag), when that is ``camera``."""
    if recorded is None:
        return f"{source} records no camera (written by an older lightplane): not checked against {camera_file}"
    diff = camera_difference(recorded, camera)
    if diff is None:
        return None
    other = f"{source}: calibrated with another camera than {camera_file} ({diff} in {camera_file})"
    if allow_other:
        return f"{other}; used by --allow-other-camera"
    if override is not None and camera_difference(override, camera) is None:
        return f"{other}; used by the --allow-other-camera recorded with it"
    raise LightplaneError(f"{other}; recalibrate the {what} with this camera (or give --allow-other-camera to use "
                          "it anyway)")


_ROS_NAMES = ("rational_polynomial", "equidistant")


def _model_from_ros(name: object, n: int) -> str:
    """Our model of a ROS ``distortion_model`` with ``n`` coefficients (our own names are accepted too)."""
    if name == "equidistant":
        return "fisheye"
    if name == "rational_polynomial":
        by_n = {8: "rational", 12: "thin_prism", 14: "tilted"}
        if n not in by_n:
            raise LightplaneError(f"distortion_model rational_polynomial needs 8, 12 or 14 coefficients, got {n}")
        return by_n[n]
    if name in MODELS:
        return str(name)
    raise LightplaneError(f"distortion_model {name!r} is not supported "
                          f"(plumb_bob, rational_polynomial, equidistant; or {', '.join(MODELS)})")
