"""Motion of a scan: one rigid transform per frame, camera frame → object frame (docs/method.md §Scans).

Every frame ``i`` of a scan is measured in the camera frame; the motion gives the rigid
transform ``T_object_cam(i)`` that maps those points into one object frame:

    p_object = R_i p_camera + t_i

One model, five forms (:class:`Motion`):

- ``none``: the identity (points stay in the camera frame);
- ``step`` / ``positions`` (linear stage, conveyor): pure translations,
  ``p_object = p_camera − (offset_i − offset_0)`` (frame 0's camera frame);
- ``turntable``: the object turns about a calibrated axis (:class:`Turntable`: a point and a
  unit direction in the camera frame) by a known angle per frame (constant step, or a
  CSV of angles or of encoder counts); the object frame is the turntable's own
  (:meth:`Turntable.basis`), turning with the table:
  ``p_object = Rz(−θ_i) Bᵀ (p_camera − o)``;
- ``poses``: any pose per frame from a CSV (``x,y,z,qx,qy,qz,qw``: the camera's pose in
  the object's frame, ``T_object_cam``, mm and a unit quaternion), optionally the
  robot's flange poses composed with a fixed sensor-to-flange transform
  (``T_object_cam = T_object_flange(i) · T_flange_cam``, :func:`load_rigid`).

Angles are right-handed about the turntable's axis direction, which points *up*
(:meth:`Turntable.from_axis` orients it against the camera's y axis, which points down
in the image): a positive step turns the object counter-clockwise seen from above.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lightplane.camera.model import ALLOWED_CAMERA_KEY, check_calibrated_with
from lightplane.camera.model import Camera
from lightplane.core.checks import MAX_DISTANCE_MM, array, covariance, field_error, mapping, number, unit_vector
from lightplane.core.errors import LightplaneError
from lightplane.core.io import read_json, write_json

__all__ = ["Motion", "Turntable", "read_table", "load_rigid", "quaternions_to_matrices", "rotation_about",
           "QUATERNION_TOL"]

#: a quaternion whose norm differs from 1 by more than this is rejected (not renormalised)
QUATERNION_TOL = 1e-3

#: the largest turntable angle (degrees) a file or a step may give: 100 turns either way
MAX_TURNTABLE_DEG = 36000.0
#: the largest standard deviations of a turntable file's covariance: the point (mm), the direction
TURNTABLE_MAX_SD = (MAX_DISTANCE_MM,) * 3 + (1.0,) * 3
__all__ += ["MAX_TURNTABLE_DEG", "TURNTABLE_MAX_SD"]


def unit_direction(direction, name: str = "direction") -> np.ndarray:
    d = np.asarray(direction, dtype=np.float64).ravel()
    if d.shape != (3,) or not np.all(np.isfinite(d)) or np.linalg.norm(d) < 1e-12:
        raise LightplaneError(f"{name} must be 3 finite numbers, not all zero (camera frame); got {direction!r}")
    return d / np.linalg.norm(d)


def rotation_about(axis, angle_rad: float | np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) — or (F, 3, 3) for an array of angles — right-handed about unit ``axis``."""
    from scipy.spatial.transform import Rotation

    a = unit_direction(axis, "axis")
    ang = np.asarray(angle_rad, dtype=np.float64)
    return Rotation.from_rotvec(np.multiply.outer(ang, a)).as_matrix()


def quaternions_to_matrices(q: np.ndarray, source: str = "quaternions", first_row: int = 1) -> np.ndarray:
    """(F, 4) quaternions ``qx, qy, qz, qw`` (scalar last) → (F, 3, 3) rotation matrices.

    A quaternion whose norm is off 1 by more than :data:`QUATERNION_TOL` is an error
    (a wrong column order or a corrupt row, not a rounding), naming the row.
    """
    from scipy.spatial.transform import Rotation

    q = np.asarray(q, dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore"):  # a huge entry: an infinite norm, refused below
        norms = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(~np.isfinite(norms) | (np.abs(norms - 1.0) > QUATERNION_TOL))
    if bad.size:
        k = int(bad[0])
        raise LightplaneError(f"{source}: row {k + first_row}: quaternion (qx,qy,qz,qw) = "
                              f"({','.join(f'{v:g}' for v in q[k])}) has norm {norms[k]:.6g}, not 1 "
                              f"(tolerance {QUATERNION_TOL:g}; {bad.size} such row(s))")
    return Rotation.from_quat(q).as_matrix()


def read_table(path: str | os.PathLike, what: str) -> tuple[list[str] | None, np.ndarray]:
    """A small numeric CSV: ``(column names or None, (rows, cols) float array)``.

    Separators ``,`` or ``;``; blank lines and lines starting with ``#`` are ignored; a
    first row that is not numbers is the header (names lower-cased).  Every row must hold
    as many numbers as the first; errors name the file and the row.
    """
    p = Path(path)
    if not p.is_file():
        raise LightplaneError(f"{p}: no such {what} file")
    try:
        text = p.read_text()
    except UnicodeDecodeError:
        raise LightplaneError(f"{p}: not a text (CSV) {what} file") from None
    except OSError as e:
        raise LightplaneError(f"{p}: cannot read the {what} file ({e.strerror or e})") from None
    rows: list[tuple[int, list[str]]] = []
    for k, line in enumerate(text.splitlines()):
        s = line.strip()
        if s and not s.startswith("#"):
            rows.append((k + 1, [t.strip() for t in s.replace(";", ",").split(",")]))
    if not rows:
        raise LightplaneError(f"{p}: {what} file is empty")

    def numeric(row):
        try:
            [float(t) for t in row]
            return True
        except ValueError:
            return False

    names = None
    if not numeric(rows[0][1]):
        names = [t.lower() for t in rows.pop(0)[1]]
    if not rows:
        raise LightplaneError(f"{p}: {what} file has a header but no rows")
    width = len(rows[0][1])
    for k, (line_no, row) in enumerate(rows):
        if len(row) != width or not numeric(row):
            raise LightplaneError(f"{p}: row {k + 1 + (names is not None)} (line {line_no}) is not {width} numbers: "
                                  f"{','.join(row)!r}")
    a = np.array([r for _, r in rows], dtype=np.float64)
    if names is not None and len(names) != width:
        raise LightplaneError(f"{p}: header names {len(names)} columns but rows hold {width}")
    if not np.all(np.isfinite(a)):
        raise LightplaneError(f"{p}: {what} must be finite numbers")
    return names, a


def rigid_from_dict(d: dict, source: str) -> tuple[np.ndarray, np.ndarray]:
    """``{"R": 3x3, "t_mm": 3}``, ``{"matrix": 4x4}`` or ``{"translation_mm": 3, "quaternion_xyzw": 4}``;
    the translation within :data:`lightplane.core.checks.MAX_DISTANCE_MM`."""
    d = mapping(d, "transform", source)
    if "matrix" in d:
        M = array(d["matrix"], "matrix", source, (4, 4))
        R, t, t_field = M[:3, :3], M[:3, 3], "matrix"
    elif "R" in d:
        R = array(d["R"], "R", source, (3, 3))
        t_field = "t_mm" if "t_mm" in d else "t"
        t = array(d.get(t_field), t_field, source, (3,))
    elif "quaternion_xyzw" in d:
        q = array(d["quaternion_xyzw"], "quaternion_xyzw", source, (4,))
        R = quaternions_to_matrices(q[None], source)[0]
        t_field = "translation_mm"
        t = array(d.get(t_field), t_field, source, (3,))
    else:
        raise LightplaneError(f"{source}: a rigid transform needs 'R' and 't_mm', 'matrix' (4x4) or "
                              "'translation_mm' and 'quaternion_xyzw'")
    if np.abs(t).max() > MAX_DISTANCE_MM:
        raise field_error(source, t_field, f"holds a translation of {np.abs(t).max():g} mm (at most "
                                           f"{MAX_DISTANCE_MM:g} mm)")
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
        raise LightplaneError(f"{source}: the rotation is not a rotation matrix (RᵀR ≠ I or det < 0)")
    return R, t


def _within(a: np.ndarray, limit: float, what: str, source, unit: str, first_row: int) -> np.ndarray:
    """``a`` (one row per frame) if no value exceeds ``limit`` in magnitude, else the error naming
    the first such row (numbered from ``first_row``)."""
    rows = np.abs(a.reshape(len(a), -1)).max(axis=1)
    bad = np.flatnonzero(rows > limit)
    if bad.size:
        k = int(bad[0])
        raise LightplaneError(f"{source}: row {k + first_row}: {what} {rows[k]:g} {unit} is beyond ±{limit:g} {unit} "
                              f"({bad.size} such row(s))")
    return a


def load_rigid(path: str | os.PathLike, key: str = "T_flange_cam") -> tuple[np.ndarray, np.ndarray]:
    """A fixed rigid transform from a JSON file: ``(R, t)`` with ``p_to = R p_from + t`` (mm).

    The file holds ``key`` (default ``T_flange_cam``: the camera's pose in the robot's
    flange frame, a hand-eye calibration) as ``{"R": [[...]], "t_mm": [...]}``,
    ``{"matrix": 4x4}`` or ``{"translation_mm": [...], "quaternion_xyzw": [...]}``; or
    those fields at the top level.
    """
    d = read_json(path, "transform file")
    return rigid_from_dict(d.get(key, d), f"{path}")


# ----------------------------------------------------------------------------- turntable
@dataclass(frozen=True, eq=False)
class Turntable:
    """A turntable's axis in the camera frame: ``point_mm`` on it and the unit ``direction`` (up).

    ``covariance`` (6, 6) of (point, direction) if known; ``camera`` the camera dict it was
    calibrated with (:meth:`lightplane.camera.model.Camera.to_dict`: a turntable file belongs to
    one camera calibration); ``counts_per_rev`` the encoder's counts per turn if known;
    ``meta`` anything else (provenance, residuals).
    """

    point_mm: np.ndarray
    direction: np.ndarray
    covariance: np.ndarray | None = None
    camera: dict | None = None
    counts_per_rev: float | None = None
    meta: dict = field(default_factory=dict)

    @classmethod
    def from_axis(cls, point_mm, direction, **kw) -> "Turntable":
        """The axis with its direction oriented up (negative camera y: the image's y axis points down)."""
        p = np.asarray(point_mm, dtype=np.float64).ravel()
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise LightplaneError(f"the turntable's axis point must be 3 finite numbers (mm), got {point_mm!r}")
        d = unit_direction(direction, "the turntable's axis direction")
        if d[1] > 0:
            d = -d
        return cls(p, d, **kw)

    def basis(self) -> tuple[np.ndarray, np.ndarray]:
        """The turntable frame at angle 0: origin (3,) and ``B`` (3, 3), columns x, y, z in the camera frame.

        Origin: ``point_mm``; z: the axis direction (up); x: from the axis towards the
        camera, perpendicular to the axis (the camera along the axis: camera x instead);
        y = z × x.
        """
        z = self.direction
        x = -self.point_mm - (-self.point_mm @ z) * z
        if np.linalg.norm(x) < 1e-6 * max(1.0, float(np.linalg.norm(self.point_mm))):
            x = np.array([1.0, 0.0, 0.0]) - z[0] * z
        x = x / np.linalg.norm(x)
        return self.point_mm.copy(), np.column_stack([x, np.cross(z, x), z])

    def check_camera(self, camera, source: str = "turntable", *, camera_file: str = "the camera given",
                     allow_other: bool = False) -> str | None:
        """Raise if this axis was calibrated with a different camera (size, lens model, K or distortion:
        :func:`lightplane.camera.model.check_calibrated_with`, whose note, or None, it returns)."""
        return check_calibrated_with(self.camera, camera, source=source, camera_file=camera_file, what="turntable",
                                     allow_other=allow_other, override=self.meta.get(ALLOWED_CAMERA_KEY))

    def to_dict(self) -> dict:
        d = {"kind": "turntable", "units": "mm", "frame": "camera", "point_mm": self.point_mm.tolist(),
             "direction": self.direction.tolist(),
             "covariance": None if self.covariance is None else np.asarray(self.covariance).tolist(),
             "covariance_order": "point x, y, z (mm), direction x, y, z",
             "angle_convention": "right-handed about the direction (up): positive = counter-clockwise seen from above",
             "camera": self.camera, "counts_per_rev": self.counts_per_rev}
        for k, v in self.meta.items():
            d.setdefault(k, v)
        return d

    @classmethod
    def from_dict(cls, d: dict, source: str = "turntable") -> "Turntable":
        """From a turntable file's layout; every number checked (docs/conventions.md §Limits on what is
        read): the point within :data:`lightplane.core.checks.MAX_DISTANCE_MM`, a unit direction, a
        covariance that is one, the camera a camera file's fields; errors name ``source`` and the field."""
        d = mapping(d, "turntable", source)
        for key in ("point_mm", "direction"):
            if key not in d:
                raise LightplaneError(f"{source}: missing field '{key}' (not a turntable file?)")
        if d.get("units", "mm") != "mm" or d.get("frame", "camera") != "camera":
            raise LightplaneError(f"{source}: a turntable axis must be in mm in the camera frame")
        point = array(d["point_mm"], "point_mm", source, (3,), max_abs=MAX_DISTANCE_MM)
        direction = unit_vector(d["direction"], "direction", source)
        cov = d.get("covariance")
        if cov is not None:
            cov = covariance(cov, "covariance", source, 6, max_sd=TURNTABLE_MAX_SD)
        cpr = d.get("counts_per_rev")
        if cpr is not None:
            cpr = number(cpr, "counts_per_rev", source, positive=True, hi=1e12)
        camera = d.get("camera")
        if camera is not None:
            Camera.from_dict(mapping(camera, "camera", source), source=f"{source}: camera")
        known = {"kind", "units", "frame", "point_mm", "direction", "covariance", "covariance_order",
                 "angle_convention", "camera", "counts_per_rev"}
        return cls.from_axis(point, direction, covariance=cov, camera=camera, counts_per_rev=cpr,
                             meta={k: v for k, v in d.items() if k not in known})

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Turntable":
        return cls.from_dict(read_json(path, "turntable file"), source=str(path))

    def save(self, path: str | os.PathLike, *, force: bool = False, extra: dict | None = None) -> Path:
        d = self.to_dict()
        d.update(extra or {})
        return write_json(path, d, force=force)


# ----------------------------------------------------------------------------- motion
@dataclass(frozen=True, eq=False)
class Motion:
    """The rigid transform ``T_object_cam`` of each frame (see the module's doc).

    Build it with :meth:`none`, :meth:`linear`, :meth:`from_positions` /
    :meth:`load_positions`, :meth:`turntable` / :meth:`load_turntable_angles`,
    :meth:`from_poses` / :meth:`load_poses`.  :meth:`transform` gives ``(R, t)`` of frame
    ``i``, :meth:`apply` maps points.
    """

    step_mm: float | None = None
    direction: np.ndarray | None = None
    positions_mm: np.ndarray | None = None
    rotations: np.ndarray | None = None        # (F, 3, 3) poses: R of T_object_cam
    translations: np.ndarray | None = None     # (F, 3) poses: t of T_object_cam (mm)
    table: Turntable | None = None
    step_deg: float | None = None
    start_deg: float = 0.0
    angles_deg: np.ndarray | None = None       # (F,) turntable angles from a file
    source: str | None = None

    def __post_init__(self) -> None:
        # the fields that go together (the constructors above set them so)
        if (self.step_mm is None) != (self.direction is None):
            raise LightplaneError("a step motion needs both step_mm and direction (see Motion.linear)")
        if (self.rotations is None) != (self.translations is None):
            raise LightplaneError("a pose motion needs both rotations and translations (see Motion.from_poses)")
        if self.table is not None and (self.step_deg is None) == (self.angles_deg is None):
            raise LightplaneError("a turntable motion needs step_deg or angles_deg (see Motion.turntable)")

    @classmethod
    def none(cls) -> "Motion":
        return cls()

    @classmethod
    def linear(cls, step_mm: float, direction) -> "Motion":
        """Constant ``step_mm`` between frames along ``direction`` (normalised here)."""
        step = float(step_mm)
        if not (np.isfinite(step) and abs(step) <= MAX_DISTANCE_MM):
            raise LightplaneError(f"step must be a finite number of mm within ±{MAX_DISTANCE_MM:g}, got {step_mm!r}")
        return cls(step_mm=step, direction=unit_direction(direction))

    @classmethod
    def from_positions(cls, positions_mm) -> "Motion":
        p = np.asarray(positions_mm, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 1 or not np.all(np.isfinite(p)):
            raise LightplaneError(f"positions must be a finite (F, 3) array in mm, got shape {p.shape}")
        return cls(positions_mm=p)

    @classmethod
    def load_positions(cls, path: str | os.PathLike, direction=None) -> "Motion":
        """Read an encoder log: one row per frame, in frame order.

        Columns ``dx,dy,dz`` (mm, camera frame; a header row naming them is optional,
        other named columns such as ``frame`` or ``time`` are ignored), or a single
        column: the position along ``direction`` (mm; ``direction`` required).
        Blank lines and lines starting with ``#`` are ignored.
        """
        p = Path(path)
        names, a = read_table(p, "positions")
        width = a.shape[1]
        if names is not None and {"dx", "dy", "dz"} <= set(names):
            a = a[:, [names.index("dx"), names.index("dy"), names.index("dz")]]
        elif names is not None and {"x", "y", "z"} <= set(names):
            a = a[:, [names.index("x"), names.index("y"), names.index("z")]]
        elif width == 3 and names is None:
            pass
        elif width == 1 or (names is not None and width == 2 and "frame" in names):
            if width == 1:
                col = a[:, 0]
            else:
                assert names is not None  # the condition above
                col = a[:, 1 - names.index("frame")]
            if direction is None:
                raise LightplaneError(f"{p}: a single column of positions needs a direction (--direction X,Y,Z)")
            a = col[:, None] * unit_direction(direction)[None, :]
        else:
            raise LightplaneError(f"{p}: expected columns dx,dy,dz (mm) or a single position column, got "
                                  f"{width} columns{'' if names is None else ' ' + ','.join(names)}")
        return cls.from_positions(_within(a, MAX_DISTANCE_MM, "position", p, "mm", 1 + (names is not None)))

    @classmethod
    def turntable(cls, table: Turntable, step_deg: float | None = None, *, angles_deg=None,
                  start_deg: float = 0.0) -> "Motion":
        """Rotation about ``table``'s axis: frame ``i`` at ``start_deg + i · step_deg``, or at ``angles_deg[i]``."""
        if not isinstance(table, Turntable):
            raise LightplaneError(f"a turntable motion needs a Turntable, got {type(table).__name__}")
        if (step_deg is None) == (angles_deg is None):
            raise LightplaneError("a turntable motion needs either a step per frame (deg) or the angle of every frame")
        if not (np.isfinite(start_deg) and abs(start_deg) <= MAX_TURNTABLE_DEG):
            raise LightplaneError(f"the start angle must be a finite number of degrees within ±{MAX_TURNTABLE_DEG:g}, "
                                  f"got {start_deg!r}")
        if step_deg is not None:
            step = float(step_deg)
            if not np.isfinite(step) or step == 0 or abs(step) > MAX_TURNTABLE_DEG:
                raise LightplaneError(f"the turntable step must be a finite, non-zero number of degrees within "
                                      f"±{MAX_TURNTABLE_DEG:g}, got {step_deg!r}")
            return cls(table=table, step_deg=step, start_deg=float(start_deg))
        a = np.asarray(angles_deg, dtype=np.float64).ravel()
        if a.size < 1 or not np.all(np.isfinite(a)) or np.abs(a).max() > MAX_TURNTABLE_DEG:
            raise LightplaneError(f"turntable angles must be finite numbers of degrees within ±{MAX_TURNTABLE_DEG:g}, "
                                  "one per frame")
        return cls(table=table, angles_deg=a, start_deg=float(start_deg))

    @classmethod
    def load_turntable_angles(cls, path: str | os.PathLike, table: Turntable, *,
                              counts_per_rev: float | None = None, start_deg: float = 0.0) -> "Motion":
        """Turntable angles from a CSV, one row per frame: a column ``angle_deg`` (or ``angle``,
        ``deg``; a single unnamed column is degrees), or encoder ``counts`` (``count``,
        ``steps``) with ``counts_per_rev`` (else the turntable file's)."""
        p = Path(path)
        names, a = read_table(p, "turntable angles")
        cpr = table.counts_per_rev if counts_per_rev is None else float(counts_per_rev)
        col = None
        if names is not None:
            for n in ("angle_deg", "angle", "deg", "degrees"):
                if n in names:
                    col = a[:, names.index(n)]
                    break
            if col is None:
                for n in ("counts", "count", "steps", "encoder"):
                    if n in names:
                        if cpr is None or not cpr > 0:
                            raise LightplaneError(f"{p}: encoder counts need the counts per revolution "
                                                  "(--counts-per-rev N, or counts_per_rev in the turntable file)")
                        col = a[:, names.index(n)] * (360.0 / cpr)
                        break
            if col is None:
                raise LightplaneError(f"{p}: expected a column angle_deg (degrees) or counts (encoder), got "
                                      f"{','.join(names)}")
        elif a.shape[1] == 1:
            col = a[:, 0]
        else:
            raise LightplaneError(f"{p}: {a.shape[1]} unnamed columns; give one column of degrees, or a header "
                                  "naming angle_deg or counts")
        col = _within(col, MAX_TURNTABLE_DEG, "turntable angle", p, "°", 1 + (names is not None))
        return cls.turntable(table, angles_deg=col, start_deg=start_deg)._replace(source=str(p))

    @classmethod
    def from_poses(cls, rotations, translations_mm, *, flange: tuple[np.ndarray, np.ndarray] | None = None,
                   source: str | None = None) -> "Motion":
        """Per-frame poses ``T_object_cam`` (or ``T_object_flange`` composed with ``flange`` = ``T_flange_cam``)."""
        R = np.asarray(rotations, dtype=np.float64)
        t = np.asarray(translations_mm, dtype=np.float64)
        if R.ndim != 3 or R.shape[1:] != (3, 3) or t.shape != (R.shape[0], 3) or R.shape[0] < 1:
            raise LightplaneError(f"poses must be (F, 3, 3) rotations and (F, 3) translations, got {R.shape}, {t.shape}")
        if flange is not None:
            Rf, tf = flange
            t = t + R @ np.asarray(tf, dtype=np.float64)
            R = R @ np.asarray(Rf, dtype=np.float64)
        return cls(rotations=R, translations=t, source=source)

    @classmethod
    def load_poses(cls, path: str | os.PathLike, *, flange: tuple[np.ndarray, np.ndarray] | None = None) -> "Motion":
        """Poses from a CSV, one row per frame in frame order: header ``x,y,z,qx,qy,qz,qw``
        (any order; other named columns such as ``frame`` or ``time`` are ignored; without
        a header exactly these 7 columns in this order): the camera's pose in the object's
        frame ``T_object_cam`` (mm, unit quaternion, scalar last) — or, with ``flange``
        (``T_flange_cam``), the flange's pose ``T_object_flange``."""
        p = Path(path)
        names, a = read_table(p, "poses")
        cols = ("x", "y", "z", "qx", "qy", "qz", "qw")
        if names is not None:
            missing = [c for c in cols if c not in names]
            if missing:
                raise LightplaneError(f"{p}: the poses header must name x,y,z,qx,qy,qz,qw; missing {','.join(missing)}")
            a = a[:, [names.index(c) for c in cols]]
        elif a.shape[1] != 7:
            raise LightplaneError(f"{p}: a pose row is 7 numbers x,y,z,qx,qy,qz,qw; got {a.shape[1]}")
        R = quaternions_to_matrices(a[:, 3:], str(p), first_row=1 + (names is not None))
        _within(a[:, :3], MAX_DISTANCE_MM, "translation x,y,z", p, "mm", 1 + (names is not None))
        return cls.from_poses(R, a[:, :3], flange=flange, source=str(p))

    def _replace(self, **kw) -> "Motion":
        import dataclasses

        return dataclasses.replace(self, **kw)

    # ------------------------------------------------------------------ queries
    @property
    def kind(self) -> str:
        if self.rotations is not None:
            return "poses"
        if self.table is not None:
            return "turntable"
        return "positions" if self.positions_mm is not None else "step" if self.step_mm is not None else "none"

    @property
    def n_frames(self) -> int | None:
        """Frames the motion is defined for (None: any number)."""
        for a in (self.positions_mm, self.rotations, self.angles_deg):
            if a is not None:
                return int(a.shape[0])
        return None

    @property
    def what(self) -> str:
        """What gives the frames their motion, for messages: positions, poses, turntable angles."""
        return {"positions": "positions", "poses": "poses", "turntable": "turntable angles"}.get(self.kind, "motion")

    def _check_index(self, index: int) -> None:
        n = self.n_frames
        if n is not None and not 0 <= index < n:
            what = self.what
            raise LightplaneError(f"frame {index} has no {what[:-1] if what.endswith('s') else what}: the {what} "
                                  f"give {n} frames but the input has more")

    def offset(self, index: int) -> np.ndarray:
        """Linear motions: displacement (3,) mm of the object at frame ``index`` relative to frame 0."""
        if self.kind in ("poses", "turntable"):
            raise LightplaneError(f"a {self.kind} motion has no linear offset; use transform()")
        if self.positions_mm is not None:
            self._check_index(index)
            return self.positions_mm[index] - self.positions_mm[0]
        if self.step_mm is not None and self.direction is not None:  # both or neither (__post_init__)
            return index * self.step_mm * self.direction
        return np.zeros(3)

    def angle_deg(self, index: int) -> float:
        """Turntable: the table's angle at frame ``index`` (deg)."""
        if self.table is None:
            raise LightplaneError("not a turntable motion")
        self._check_index(index)
        if self.angles_deg is not None:
            return float(self.start_deg + self.angles_deg[index] - self.angles_deg[0])
        assert self.step_deg is not None  # a turntable has angles or a step (__post_init__)
        return float(self.start_deg + index * self.step_deg)

    def transform(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """``(R, t)`` of frame ``index``: ``p_object = R p_camera + t``."""
        if self.rotations is not None and self.translations is not None:  # both or neither (__post_init__)
            self._check_index(index)
            return self.rotations[index], self.translations[index]
        if self.table is not None:
            o, B = self.table.basis()
            Rz = rotation_about([0.0, 0.0, 1.0], -np.deg2rad(self.angle_deg(index)))
            R = Rz @ B.T
            return R, -R @ o
        return np.eye(3), -self.offset(index)

    def apply(self, index: int, points: np.ndarray) -> np.ndarray:
        """(N, 3) camera-frame points of frame ``index`` → object frame."""
        if self.kind in ("none", "step", "positions"):
            return points - self.offset(index)[None, :]
        R, t = self.transform(index)
        return points @ R.T + t[None, :]

    @property
    def frame_description(self) -> str:
        return {"none": "camera frame", "step": "camera frame, object at frame 0",
                "positions": "camera frame, object at frame 0",
                "turntable": "turntable frame: origin on the axis, z up the axis, x towards the camera at angle 0",
                "poses": "object frame of the poses"}[self.kind]

    def to_dict(self) -> dict:
        k = self.kind
        if k == "positions":
            return {"kind": "positions", "n_frames": self.n_frames}
        if k == "step" and self.direction is not None:  # a step has its direction (__post_init__)
            return {"kind": "step", "step_mm": self.step_mm, "direction": self.direction.tolist()}
        if k == "turntable" and self.table is not None:
            o, B = self.table.basis()
            d = {"kind": "turntable", "axis_point_mm": o.tolist(), "axis_direction": B[:, 2].tolist(),
                 "start_deg": self.start_deg}
            if self.step_deg is not None:
                d["step_deg"] = self.step_deg
            else:
                d.update(n_frames=self.n_frames, angles_file=self.source)
            return d
        if k == "poses":
            return {"kind": "poses", "n_frames": self.n_frames, "poses_file": self.source}
        return {"kind": "none"}
