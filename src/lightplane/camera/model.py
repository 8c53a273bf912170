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
from lightplane.core.checks import array, covariance, integer, mapping, number
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
            raise LightplaneError(f"{name}: {self.size_mismatch(w, h)}")

    def size_mismatch(self, w: int, h: int) -> str:
        """Why an image of ``w`` x ``h`` px does not fit this camera, in words (with a hint when the
        size is the camera's transposed: the frames are read turned by 90 degrees against the calibration)."""
        msg = f"{w}x{h} px but the camera is calibrated for {self.width}x{self.height} px"
        if (h, w) == (self.width, self.height):
            return msg + (", its frame turned by 90 deg: read the images rotated as the camera was calibrated, "
                          "--rotate 90 or --rotate 270")
        return msg + " (wrong camera file?)"

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
        "covariance_params"?}`` (no model: from the length of ``dist``); every number is checked
        (:func:`check_camera_file`), errors name ``source`` and the field."""
        d = mapping(d, "camera", source)
        for key in ("width", "height", "K", "dist"):
            if key not in d:
                raise LightplaneError(f"{source}: missing field '{key}'")
        K = array(d["K"], "K", source, (3, 3))
        dist = _coefficients(d["dist"], "dist", source)
        cov, names = d.get("covariance"), d.get("covariance_params")
        if (cov is None) != (names is None):
            raise LightplaneError(f"{source}: 'covariance' and 'covariance_params' go together (one is missing)")
        if names is not None and not (isinstance(names, list) and all(isinstance(n, str) for n in names)):
            raise LightplaneError(f"{source}: field 'covariance_params' must be a list of parameter names")
        model = d.get("model")
        if model is not None and not isinstance(model, str):
            raise LightplaneError(f"{source}: field 'model' must be a lens model name ({', '.join(MODELS)})")
        rms = d.get("rms_px")
        return _camera_read(cls, K, dist, (integer(d["width"], "width", source, lo=1, hi=MAX_IMAGE_PX),
                                           integer(d["height"], "height", source, lo=1, hi=MAX_IMAGE_PX)),
                            source, model=model, rms_px=None if rms is None else number(rms, "rms_px", source, lo=0),
                            cov=cov, names=names)

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
        except OSError as e:
            raise LightplaneError(f"{p}: cannot be read ({e.strerror or e})") from None
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
        except (yaml.YAMLError, ValueError, RecursionError) as e:
            raise LightplaneError(f"{p}: not valid YAML ({(str(e).splitlines() or [type(e).__name__])[0]})") from None
        if not isinstance(doc, dict):
            raise LightplaneError(f"{p}: not a camera file (expected a YAML mapping or JSON object)")
        for key in ("camera_matrix", "distortion_coefficients", "image_width", "image_height"):
            if key not in doc:
                raise LightplaneError(f"{p}: missing field '{key}'")

        def data(key: str):
            node = doc[key]
            return node.get("data") if isinstance(node, dict) else node

        K = _coefficients(data("camera_matrix"), "camera_matrix", str(p))
        if K.size != 9:
            raise LightplaneError(f"{p}: field 'camera_matrix' must hold 9 numbers, got {K.size}")
        dist = _coefficients(data("distortion_coefficients"), "distortion_coefficients", str(p))
        ros_model = doc.get("distortion_model", "plumb_bob")
        if not isinstance(ros_model, str):
            raise LightplaneError(f"{p}: field 'distortion_model' must be a name, got {ros_model!r:.40}")
        try:
            model = _model_from_ros(ros_model, dist.size)
        except LightplaneError as e:
            raise LightplaneError(f"{p}: {e}") from None
        w, h = (integer(doc[k], k, str(p), lo=1, hi=MAX_IMAGE_PX) for k in ("image_width", "image_height"))
        return _camera_read(cls, K.reshape(3, 3), dist, (w, h), str(p), model=model,
                            fields=("camera_matrix", "distortion_coefficients"), meta={"format": "ros"})

    @classmethod
    def _load_opencv(cls, p: Path) -> "Camera":
        nodes = _read_filestorage(p, ("camera_matrix", "distortion_coefficients", "image_width", "image_height",
                                      "distortion_model"))
        for key in ("camera_matrix", "distortion_coefficients", "image_width", "image_height"):
            if key not in nodes:
                raise LightplaneError(f"{p}: missing field '{key}'")
        for key in ("camera_matrix", "distortion_coefficients"):
            if not isinstance(nodes[key], np.ndarray):
                raise LightplaneError(f"{p}: field '{key}' is not a matrix of numbers, got {nodes[key]!r:.60}")
        K = array(nodes["camera_matrix"], "camera_matrix", str(p), (3, 3))
        dist = _coefficients(nodes["distortion_coefficients"], "distortion_coefficients", str(p))
        w, h = (integer(nodes[k], k, str(p), lo=1, hi=MAX_IMAGE_PX) for k in ("image_width", "image_height"))
        model = nodes.get("distortion_model")
        if model is not None and not (isinstance(model, str) and model):
            raise LightplaneError(f"{p}: field 'distortion_model' must be a lens model name")
        try:
            if model is not None:
                model = _model_from_ros(model, dist.size) if model in _ROS_NAMES else model
        except LightplaneError as e:
            raise LightplaneError(f"{p}: {e}") from None
        return _camera_read(cls, K, dist, (w, h), str(p), model=model,
                            fields=("camera_matrix", "distortion_coefficients"), meta={"format": "opencv"})


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


# ----------------------------------------------------------------------------- what a camera file may hold
__all__ += ["MAX_IMAGE_PX", "FOV_RANGE_DEG", "PRINCIPAL_POINT_MARGIN", "MAX_SKEW", "MAX_INTRINSIC_SD", "MAX_LENS_SCALE",
            "check_camera_file", "lens_defect"]

#: the largest image side (px) a camera file may give
MAX_IMAGE_PX = 100_000
#: the horizontal and vertical field of view (degrees) the focal lengths must give over the image
FOV_RANGE_DEG = (1.0, 179.0)
#: how far (a fraction of the image's width / height) the principal point may lie beyond the image's edges
PRINCIPAL_POINT_MARGIN = 0.25
#: the largest ``|skew| / fx``: the pixel axes within 5.7° of perpendicular
MAX_SKEW = 0.1
#: the largest standard deviation of a camera file's covariance (px for fx, fy, cx, cy; the coefficients' own units)
MAX_INTRINSIC_SD = 1e6
#: the largest local magnification of the lens model (the largest singular value of
#: ∂(x_d, y_d)/∂(x, y)) over the image: no lens magnifies part of its field tenfold
MAX_LENS_SCALE = 10.0


def check_camera_file(camera: Camera, source: str, *, k_field: str = "K", dist_field: str = "dist") -> Camera:
    """Raise :class:`LightplaneError` (one line naming ``source`` and the field) unless ``camera``, as
    read from a file, is physically sane (docs/conventions.md §Limits on what is read): focal lengths
    giving a horizontal and vertical field of view within :data:`FOV_RANGE_DEG`, the principal point
    within :data:`PRINCIPAL_POINT_MARGIN` of the image, ``|skew| <= MAX_SKEW fx``, and a lens model
    that is one-to-one over the image (:func:`lens_defect`).  Returns ``camera``."""
    K, w, h = camera.K, camera.width, camera.height
    for axis, f, c, n, side in (("horizontal", camera.fx, camera.cx, w, "fx"), ("vertical", camera.fy, camera.cy, h, "fy")):
        m = PRINCIPAL_POINT_MARGIN * n
        if not -0.5 - m <= c <= n - 0.5 + m:
            name = "cx" if side == "fx" else "cy"
            raise LightplaneError(f"{source}: field '{k_field}': principal point {name} = {c:.6g} px lies more than "
                                  f"{PRINCIPAL_POINT_MARGIN:.0%} of the image ({n} px) beyond its edge")
        fov = float(np.degrees(np.arctan((n - 0.5 - c) / f) - np.arctan((-0.5 - c) / f)))
        lo, hi = FOV_RANGE_DEG
        if not lo <= fov <= hi:
            raise LightplaneError(f"{source}: field '{k_field}': {side} = {f:.6g} px gives a {axis} field of view of "
                                  f"{fov:.3g}° over {n} px ({lo:g}°..{hi:g}° expected)")
    if abs(K[0, 1]) > MAX_SKEW * camera.fx:
        raise LightplaneError(f"{source}: field '{k_field}': skew {K[0, 1]:.6g} px is more than {MAX_SKEW:g} fx "
                              f"(pixel axes more than {np.degrees(np.arctan(MAX_SKEW)):.1f}° off perpendicular)")
    defect = lens_defect(camera)
    if defect is not None:
        raise LightplaneError(f"{source}: field '{dist_field}': the {camera.model} lens model {defect}")
    return camera


def lens_defect(camera: Camera, n_dir: int = 72, n_radii: int = 400) -> str | None:
    """Why ``camera``'s lens model is not a one-to-one map over its image, in words, or None.

    Rays from the optical axis outwards in ``n_dir`` directions, at ``n_radii`` normalised radii
    from 1e-5 to 1e3 (geometric: 89.94° off axis), are projected by :meth:`Camera.normalized_to_pixels`;
    along each, until it leaves the ellipse inscribed in the image, the pixel must move away from
    the principal point's image, :meth:`Camera.pixel_jacobian` keep a positive determinant and the
    lens model magnify at most :data:`MAX_LENS_SCALE`-fold.  A ray that folds back before leaving
    the ellipse, or (fisheye excepted: its image circle may lie inside the image) never leaves it,
    leaves pixels that no ray or two rays reach.  The image's corners beyond the ellipse are not
    checked: calibrations often extrapolate poorly there (FabScanPi's camera folds at 0.69 of its
    focal length, its corners are at 0.77)."""
    if not camera.has_distortion:
        return None
    phi = np.linspace(0.0, 2 * np.pi, n_dir, endpoint=False)
    r = np.concatenate([[0.0], np.geomspace(1e-5, 1e3, n_radii)])
    xy = np.stack([np.multiply.outer(np.cos(phi), r), np.multiply.outer(np.sin(phi), r)], axis=-1).reshape(-1, 2)
    with np.errstate(all="ignore"):
        uv = camera.normalized_to_pixels(xy).reshape(n_dir, -1, 2)
        J = camera.pixel_jacobian(xy).reshape(n_dir, -1, 2, 2)
        j11, j12, j21, j22 = camera.distortion_jacobian(xy)
        s2, dj = j11 ** 2 + j12 ** 2 + j21 ** 2 + j22 ** 2, j11 * j22 - j12 * j21
        scale = np.sqrt(0.5 * (s2 + np.sqrt(np.maximum(s2 ** 2 - 4 * dj ** 2, 0.0)))).reshape(n_dir, -1)  # largest σ
    a, b = camera.width / 2.0, camera.height / 2.0
    with np.errstate(all="ignore"):
        inside = ((uv[..., 0] - (a - 0.5)) / a) ** 2 + ((uv[..., 1] - (b - 0.5)) / b) ** 2 <= 1.0
        entered = np.cumsum(inside, axis=1) > 0
        left = entered & ~inside
        reached = np.asarray(left.any(axis=1))
        met = np.asarray(entered.any(axis=1))  # rays that reach the image at all
        last = np.where(reached, np.argmax(left, axis=1), r.size - 1)
        checked = (np.arange(r.size)[None, :] <= last[:, None]) & met[:, None]
        dist = np.linalg.norm(uv - uv[:, :1], axis=-1)
        det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
        ok = np.isfinite(dist) & np.isfinite(det) & np.isfinite(scale)
        fold = np.zeros_like(checked)
        fold[:, 1:] = ~(np.diff(dist, axis=1) > 0) | ~(det[:, 1:] > 0)
        fold |= ~ok
    bad = checked & fold
    if np.any(bad):
        i, j = np.argwhere(bad)[0]
        return (f"is not one-to-one over the image: it folds back {r[j]:.3g} focal lengths off axis in the direction "
                f"{np.degrees(phi[i]):.0f}°, inside the image (at pixel {uv[i, j, 0]:.0f}, {uv[i, j, 1]:.0f})")
    if camera.model != "fisheye" and np.any(met & ~reached):
        i = int(np.flatnonzero(met & ~reached)[0])
        return f"does not reach the image's edge in the direction {np.degrees(phi[i]):.0f}° (a fold or a saturation)"
    big = checked & (scale > MAX_LENS_SCALE)
    if np.any(big):
        i, j = np.argwhere(big)[0]
        return (f"magnifies the image {scale[i, j]:.3g}-fold {r[j]:.3g} focal lengths off axis (at most "
                f"{MAX_LENS_SCALE:g}-fold expected of a lens)")
    return None


def _coefficients(value: Any, field: str, source: str) -> np.ndarray:
    """A distortion vector as read: finite numbers, a list (or a 1xN / Nx1 matrix)."""
    a = array(value, field, source)
    if a.ndim > 2 or (a.ndim == 2 and min(a.shape) != 1):
        raise LightplaneError(f"{source}: field '{field}' must be a list of numbers, got shape {a.shape}")
    return a.ravel()


def _camera_read(cls: type[Camera], K: np.ndarray, dist: np.ndarray, size: tuple[int, int], source: str, *,
                 model: str | None = None, rms_px: float | None = None, cov: Any = None,
                 names: list[str] | None = None, fields: tuple[str, str] = ("K", "dist"),
                 meta: dict | None = None) -> Camera:
    """A camera read from a file (numbers already converted and finite), checked by :func:`check_camera_file`;
    every error names ``source`` (and ``fields``: the file's names of K and the distortion)."""
    try:
        cam = cls(K, dist, size[0], size[1], rms_px, meta={"source": source, **(meta or {})}, model=model)
    except LightplaneError as e:
        raise LightplaneError(f"{source}: {e}") from None
    check_camera_file(cam, source, k_field=fields[0], dist_field=fields[1])
    if cov is None:
        return cam
    assert cam.model is not None and names is not None  # named on construction; read with the covariance
    want = ["fx", "fy", "cx", "cy", *coeff_names(cam.model)]
    if list(names) != want:
        raise LightplaneError(f"{source}: field 'covariance_params' must name the {cam.model} model's parameters "
                              f"{','.join(want)}, got {','.join(names)}")
    C = covariance(cov, "covariance", source, len(want), max_sd=MAX_INTRINSIC_SD)
    return cls(cam.K, cam.dist, cam.width, cam.height, cam.rms_px, cam.meta, C, tuple(names), cam.model)


def _read_filestorage(p: Path, keys: tuple[str, ...]) -> dict[str, Any]:
    """The top-level nodes ``keys`` of an OpenCV FileStorage file as Python values: a matrix as a
    float64 array, a number as int / float, a string as str, anything else as words saying what it
    is (absent keys are left out).  A file OpenCV cannot parse raises :class:`LightplaneError`."""
    import cv2

    out: dict[str, Any] = {}
    try:
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
        try:
            if not fs.isOpened():
                raise LightplaneError(f"{p}: cannot be opened as an OpenCV FileStorage file")
            for key in keys:
                node = fs.getNode(key)
                if node.empty() or node.isNone():
                    continue
                if node.isInt():
                    out[key] = int(node.real())
                elif node.isReal():
                    out[key] = float(node.real())
                elif node.isString():
                    out[key] = node.string()
                else:
                    out[key] = _filestorage_matrix(node) if node.isMap() else "a sequence"
        finally:
            fs.release()
    except (cv2.error, SystemError, UnicodeDecodeError) as e:
        cause = e.__cause__ or e.__context__ or e  # the binding wraps OpenCV's parse error in a SystemError
        text = str(cause).strip()
        reason = text.split("error: ", 1)[-1].splitlines()[0] if text else type(e).__name__
        raise LightplaneError(f"{p}: not a valid OpenCV FileStorage file ({reason})") from None
    return out


def _filestorage_matrix(node: Any) -> np.ndarray | str:
    """An ``opencv-matrix`` node's numbers (rows x cols, one channel), read one at a time, or what the node
    is instead, in words.  Never through ``FileNode.mat()``: OpenCV 5.1 writes past its buffer for a
    negative ``cols``."""
    rows, cols, data = node.getNode("rows"), node.getNode("cols"), node.getNode("data")
    if not (rows.isInt() and cols.isInt() and data.isSeq()):
        return "a mapping (not an opencv-matrix with rows, cols and data)"
    r, c, n = int(rows.real()), int(cols.real()), int(data.size())
    if not (1 <= r <= 1000 and 1 <= c <= 1000 and n == r * c):
        return f"an opencv-matrix of {r}x{c} with {n} numbers"
    values = []
    for i in range(n):
        e = data.at(i)
        if not (e.isInt() or e.isReal()):
            return "an opencv-matrix of non-numbers"
        values.append(e.real())
    return np.array(values, dtype=np.float64).reshape(r, c)
