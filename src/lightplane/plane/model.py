"""The light plane (docs/conventions.md §Light plane; docs/method.md §Light plane).

``a x + b y + c z + d = 0`` in the camera frame (mm), ``(a, b, c)`` a unit
normal, sign fixed so that ``d < 0``: the normal points from the camera towards
the plane.  The camera centre never lies on a triangulation sensor's plane, so
``d = 0`` is rejected.

>>> p = LightPlane([0, 0.9336, -0.3584], 140.04)   # the paper's simulated plane
>>> bool(p.d < 0), round(float(np.linalg.norm(p.normal)), 12)
(True, 1.0)
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from lightplane.camera.model import ALLOWED_CAMERA_KEY, Camera, as_points, check_calibrated_with
from lightplane.core.checks import MAX_DISTANCE_MM, array, covariance, mapping, number, unit_vector
from lightplane.core.errors import LightplaneError
from lightplane.core.io import read_json, write_json

__all__ = ["LightPlane", "CameraDependence", "recorded_camera", "check_camera"]

#: a plane file's camera centre must lie at least this far (mm) from its plane (docs/conventions.md
#: §Limits on what is read): closer, the rays of the stripe graze the plane and nothing is triangulated
MIN_PLANE_DISTANCE_MM = 1.0
#: the largest standard deviations a plane file's covariance may give: a, b, c (a unit normal's
#: components, at most 1) and d (mm)
PLANE_MAX_SD = (1.0, 1.0, 1.0, MAX_DISTANCE_MM)
#: the largest entry of a plane file's ∂(a, b, c, d)/∂(intrinsics)
MAX_PLANE_JACOBIAN = 1e9
__all__ += ["MIN_PLANE_DISTANCE_MM", "PLANE_MAX_SD", "MAX_PLANE_JACOBIAN"]


@dataclass(frozen=True, eq=False)
class CameraDependence:
    """How a plane depends on the intrinsics of the camera it was calibrated with.

    ``matrix`` (4, P): ``∂(a, b, c, d)/∂(params)``, ``params`` the camera's parameter names in
    the order of :func:`lightplane.plane.uncertainty.camera_param_names` (``fx, fy, cx, cy``
    and the distortion coefficients); ``covariance_camera`` (4, 4): the plane's covariance
    due to the intrinsics alone, ``J Cov(K) Jᵀ``; ``method``: how ``matrix`` was obtained;
    ``extra``: further numbers the calibration recorded with it (the images' dispersion
    statistic and its expected part due to the intrinsics).  Stored in the plane file under
    :attr:`KEY`; a camera whose parameters differ from ``params`` is not the plane's camera.
    """

    params: tuple[str, ...]
    matrix: np.ndarray
    covariance_camera: np.ndarray
    method: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    #: the plane file's field
    KEY: ClassVar[str] = "camera_jacobian"

    def __post_init__(self) -> None:
        names = tuple(str(n) for n in self.params)
        J = np.asarray(self.matrix, np.float64)
        C = np.asarray(self.covariance_camera, np.float64)
        if J.shape != (4, len(names)) or not np.all(np.isfinite(J)):
            raise LightplaneError(f"'{self.KEY}' matrix must be finite 4x{len(names)}, got {J.shape}")
        if C.shape != (4, 4) or not np.all(np.isfinite(C)):
            raise LightplaneError(f"'{self.KEY}' covariance_camera must be a finite 4x4 matrix, got {C.shape}")
        object.__setattr__(self, "params", names)
        object.__setattr__(self, "matrix", J)
        object.__setattr__(self, "covariance_camera", C)

    def to_dict(self) -> dict:
        return {"params": list(self.params), "matrix": self.matrix.tolist(),
                "covariance_camera": self.covariance_camera.tolist(), "method": self.method, **self.extra}

    @classmethod
    def from_dict(cls, rec: Any, source: str = "plane file") -> "CameraDependence":
        """From a plane file's :attr:`KEY` record; every number checked, errors name ``source`` and the field."""
        rec = mapping(rec, cls.KEY, source)
        for key in ("params", "matrix", "covariance_camera"):
            if key not in rec:
                raise LightplaneError(f"{source}: field '{cls.KEY}' must hold 'params', 'matrix' (4xP) and "
                                      f"'covariance_camera' (4x4); '{key}' is missing")
        names = rec["params"]
        if not (isinstance(names, list) and all(isinstance(n, str) for n in names)):
            raise LightplaneError(f"{source}: field '{cls.KEY}.params' must be a list of parameter names")
        J = array(rec["matrix"], f"{cls.KEY}.matrix", source, (4, len(names)), max_abs=MAX_PLANE_JACOBIAN)
        C = covariance(rec["covariance_camera"], f"{cls.KEY}.covariance_camera", source, 4, max_sd=PLANE_MAX_SD)
        known = {"params", "matrix", "covariance_camera", "method"}
        try:
            return cls(tuple(names), J, C, str(rec.get("method", "")), {k: v for k, v in rec.items() if k not in known})
        except LightplaneError as e:
            raise LightplaneError(f"{source}: {e}") from None


@dataclass(frozen=True, eq=False)
class LightPlane:
    """A light plane with optional 4x4 covariance of ``(a, b, c, d)``.

    Attributes
    ----------
    normal : (3,) float64, unit, oriented so that ``d < 0``.
    d : float, mm.
    covariance : (4, 4) float64 or None
        Covariance of ``(a, b, c, d)`` (mm² for d), rank 3 (the normal is unit).
    meta : dict
        What produced it (method, inputs, diagnostics); stored in the JSON file.
    """

    normal: np.ndarray
    d: float
    covariance: np.ndarray | None = None
    meta: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        n = np.asarray(self.normal, dtype=np.float64).ravel()
        if n.shape != (3,) or not np.all(np.isfinite(n)):
            raise LightplaneError(f"plane normal must be 3 finite numbers, got {self.normal!r}")
        try:
            d = float(self.d)
        except (TypeError, ValueError):
            raise LightplaneError(f"plane d must be a number, got {self.d!r}") from None
        if not np.isfinite(d):
            raise LightplaneError("plane d must be finite")
        norm = float(np.linalg.norm(n))
        if norm < 1e-12:
            raise LightplaneError("plane normal must not be zero")
        n, d = n / norm, d / norm
        if abs(d) < 1e-9:
            raise LightplaneError("the light plane passes through the camera centre (d = 0): nothing can be triangulated")
        cov = self.covariance
        if d > 0:
            n, d = -n, -d  # docs/conventions.md §Light plane: d < 0; (a, b, c, d) -> -(a, b, c, d) keeps the covariance
        if cov is not None:
            cov = np.asarray(cov, dtype=np.float64)
            if cov.shape != (4, 4) or not np.all(np.isfinite(cov)):
                raise LightplaneError(f"plane covariance must be a finite 4x4 matrix, got shape {cov.shape}")
            cov = cov / norm**2
            cov.setflags(write=False)
        n.setflags(write=False)
        object.__setattr__(self, "normal", n)
        object.__setattr__(self, "d", d)
        object.__setattr__(self, "covariance", cov)

    @property
    def coefficients(self) -> np.ndarray:
        """``(a, b, c, d)``."""
        return np.append(self.normal, self.d)

    def signed_distance(self, p: np.ndarray) -> np.ndarray:
        """Signed distance (mm) of ``(N, 3)`` points; positive on the side the normal points to."""
        p = as_points(p, 3, "p")
        return p @ self.normal + self.d

    def angle_to(self, other: "LightPlane") -> float:
        """Angle between the two normals, radians."""
        c = float(np.clip(abs(self.normal @ other.normal), -1.0, 1.0))
        return float(np.arccos(c))

    def point_on_axis(self) -> np.ndarray:
        """Where the optical axis (z) meets the plane (mm), or NaNs if parallel."""
        c = self.normal[2]
        if abs(c) < 1e-12:
            return np.full(3, np.nan)
        return np.array([0.0, 0.0, -self.d / c])

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, LightPlane):
            return NotImplemented
        return np.array_equal(self.normal, other.normal) and self.d == other.d

    def __repr__(self) -> str:
        a, b, c = self.normal
        return f"LightPlane({a:+.6f} x {b:+.6f} y {c:+.6f} z {self.d:+.4f} = 0)"

    @property
    def camera_dependence(self) -> CameraDependence | None:
        """The plane's dependence on its camera's intrinsics (:class:`CameraDependence`), when the
        calibration recorded it (a camera file with a covariance), else None."""
        rec = self.meta.get(CameraDependence.KEY)
        return None if not rec else CameraDependence.from_dict(rec)

    # ---------------------------------------------------------------- files
    def to_dict(self) -> dict:
        d = {
            "normal": self.normal.tolist(),
            "d": self.d,
            "units": "mm",
            "frame": "camera",
            "method": self.meta.get("method"),
            "covariance": None if self.covariance is None else self.covariance.tolist(),
        }
        for k, v in self.meta.items():
            if k not in d or d[k] is None:
                d[k] = v
        return d

    @classmethod
    def from_dict(cls, d: dict, source: str = "plane") -> "LightPlane":
        """From a plane file's layout (docs/conventions.md §Plane file); every number is checked
        (§Limits on what is read): a unit normal (renormalised within
        :data:`lightplane.core.checks.UNIT_TOL`), the camera centre at least :data:`MIN_PLANE_DISTANCE_MM`
        from the plane, a covariance that is one; errors name ``source`` and the field."""
        d = mapping(d, "plane", source)
        for key in ("normal", "d"):
            if key not in d:
                raise LightplaneError(f"{source}: missing field '{key}'")
        if d.get("units", "mm") != "mm":
            raise LightplaneError(f"{source}: field 'units' must be 'mm', got {d.get('units')!r:.40}")
        if d.get("frame", "camera") != "camera":
            raise LightplaneError(f"{source}: field 'frame' must be 'camera', got {d.get('frame')!r:.40}")
        normal = unit_vector(d["normal"], "normal", source)
        offset = number(d["d"], "d", source, lo=-MAX_DISTANCE_MM, hi=MAX_DISTANCE_MM)
        if abs(offset) < MIN_PLANE_DISTANCE_MM:
            raise LightplaneError(f"{source}: field 'd': the camera centre lies {abs(offset):.3g} mm from the plane "
                                  f"(at least {MIN_PLANE_DISTANCE_MM:g} mm expected): nothing can be triangulated")
        cov = d.get("covariance")
        if cov is not None:
            cov = covariance(cov, "covariance", source, 4, max_sd=PLANE_MAX_SD)
        if d.get(CameraDependence.KEY) is not None:
            CameraDependence.from_dict(d[CameraDependence.KEY], source)  # checked here, read where it is used
        meta = {k: v for k, v in d.items() if k not in ("normal", "d", "covariance", "units", "frame")}
        try:
            return cls(normal, offset, cov, meta=meta)
        except LightplaneError as e:
            raise LightplaneError(f"{source}: {e}") from None

    @classmethod
    def load(cls, path: str | os.PathLike) -> "LightPlane":
        """Read a light-plane JSON file (docs/conventions.md §Plane file)."""
        return cls.from_dict(read_json(path, "plane file"), source=str(path))

    def save(self, path: str | os.PathLike, *, force: bool = False, extra: dict | None = None) -> Path:
        """Write the light-plane JSON file atomically."""
        d = self.to_dict()
        if extra:
            d.update(extra)
        return write_json(path, d, force=force)


def recorded_camera(plane: LightPlane) -> dict | None:
    """The camera ``plane`` was calibrated with, as its file records it: the field ``camera``
    (:func:`lightplane.camera.model.camera_record`, written by every calibration), else the camera
    of ``report_inputs`` (``calibrate-plane``'s files before the field existed), else None."""
    rec = plane.meta.get("camera")
    if isinstance(rec, dict):
        return rec
    inputs = plane.meta.get("report_inputs")
    rec = inputs.get("camera") if isinstance(inputs, dict) else None
    return rec if isinstance(rec, dict) else None


def check_camera(plane: LightPlane, camera: Camera, *, plane_file: str = "plane", camera_file: str = "camera",
                 allow_other: bool = False) -> str | None:
    """Raise :class:`LightplaneError` when ``plane`` was calibrated with another camera than ``camera``
    (image size, lens model, K or distortion: :func:`lightplane.camera.model.camera_difference`); the
    one line names both files and the first difference.

    Returns None for the same camera, else a one-line note for the user and the output's provenance:
    the plane records no camera (an older plane file; not checked, not refused), or ``allow_other``
    (``--allow-other-camera``) let another camera through."""
    return check_calibrated_with(recorded_camera(plane), camera, source=plane_file, camera_file=camera_file,
                                 what="plane", allow_other=allow_other, override=plane.meta.get(ALLOWED_CAMERA_KEY))
