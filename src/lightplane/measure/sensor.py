"""One sensor file: what a measurement needs (docs/conventions.md §Sensor file).

A sensor file (JSON) holds the camera, the named light planes (with their
covariances) and the motion calibration — a turntable's axis
(:class:`lightplane.motion.model.Turntable`) or a robot's sensor-to-flange transform — each
with the provenance of the file it came from, and how frames are read (a clockwise
rotation applied to every image file, e.g. FabScan's).  ``lightplane sensor``
assembles one from calibration files, ``lightplane import-fabscan`` from a FabScanPi
``fabscan-config.json``; ``lightplane measure --sensor`` measures with it, one frame
sequence per laser, into one cloud with a ``laser`` attribute (:func:`measure_lasers`).

Layout::

    {"kind": "lightplane sensor", "version": 1,
     "camera": {width, height, K, dist, rms_px?, provenance?},
     "frames": {"rotate_deg": 0},
     "planes": {"laser0": {normal, d, covariance, units, frame, provenance?...}, ...},
     "turntable": {point_mm, direction, covariance, camera, counts_per_rev, ...} | null,
     "flange": {"T_flange_cam": {"R", "t_mm"}, "provenance"?} | null,
     "provenance": {...}}
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from lightplane.camera.model import Camera, camera_record
from lightplane.camera.model import MAX_IMAGE_PX, check_camera_file
from lightplane.core.checks import array, integer, mapping, number
from lightplane.core.errors import LightplaneError
from lightplane.motion.model import Motion, Turntable, rigid_from_dict
from lightplane.plane.model import LightPlane
from lightplane.measure.pointcloud import POINT_DTYPE, POINT_FIELDS
from lightplane.core.io import provenance, read_json, summarize_reasons, too_few_images_message, write_json
from lightplane.measure.options import CloudOutput, MeasureOptions
from lightplane.measure.pointcloud import PointSpool, write_cloud
from lightplane.measure.scan import Dropped, FrameProcessor, _prepare, iter_scan, no_points_message
from lightplane.core.threads import with_blas_limited

__all__ = ["Sensor", "LASER_POINT_DTYPE", "measure_lasers", "import_fabscan", "plane_name", "recorded_rotation"]

SENSOR_KIND = "lightplane sensor"

if TYPE_CHECKING:
    from lightplane.measure.scan import FrameSource

#: a merged cloud's records: :data:`lightplane.measure.pointcloud.POINT_DTYPE` and the laser's index
#: (the names are listed in the file's comments, ``laser 0: NAME``)
LASER_POINT_DTYPE = np.dtype(POINT_DTYPE.descr + [("laser", "<u1")])


def recorded_rotation(path: str | os.PathLike | None) -> int | None:
    """The clockwise frame rotation (0/90/180/270 deg) a camera or sensor file records for the images it
    was calibrated on, or None where it records none.

    A sensor file's ``frames.rotate_deg`` (``lightplane sensor``, ``import-fabscan``); a camera, plane or
    turntable JSON file's ``provenance.options.rotate_deg`` (``calibrate-camera --rotate``).  ROS and
    OpenCV camera files record none.  Every command that reads images with such a file applies it
    by default, so a camera calibrated on rotated frames is used on frames rotated the same way.
    """
    if path is None or Path(path).suffix.lower() != ".json" or not Path(path).is_file():
        return None
    d = read_json(path, "camera file")
    if d.get("kind") == SENSOR_KIND:
        return Sensor.from_dict(d, str(path)).rotate_deg
    prov = d.get("provenance")
    opts = prov.get("options") if isinstance(prov, dict) else None
    rot = opts.get("rotate_deg") if isinstance(opts, dict) else None
    if rot is None:
        return None
    if isinstance(rot, bool) or rot not in (0, 90, 180, 270):
        raise LightplaneError(f"{path}: field 'provenance.options.rotate_deg' must be 0, 90, 180 or 270, "
                              f"got {rot!r:.40}")
    return int(rot)


def plane_name(plane: LightPlane, fallback: str) -> str:
    """A plane's laser name: its file's top-level ``laser`` field, else ``fallback``."""
    name = plane.meta.get("laser")
    return str(name) if isinstance(name, str) and name else fallback


def check_name(name: str) -> str:
    if not name or any(c in name for c in "=,; \t") or not name.isprintable():
        raise LightplaneError(f"laser name {name!r}: use letters, digits, '_' or '-' (no spaces, '=', ',')")
    return name


@dataclass(frozen=True, eq=False)
class Sensor:
    """Camera, named planes, motion calibration; ``rotate_deg``: how image files are read."""

    camera: Camera
    planes: dict
    turntable: Turntable | None = None
    flange: tuple[np.ndarray, np.ndarray] | None = None
    rotate_deg: int = 0
    records: dict = field(default_factory=dict)  # per part: its provenance as read

    def plane(self, name: str, source: str = "sensor file") -> LightPlane:
        if name not in self.planes:
            have = ", ".join(self.planes) or "none"
            raise LightplaneError(f"{source}: no laser named {name!r} (it has: {have})")
        return self.planes[name]

    def to_dict(self, provenance: dict | None = None) -> dict:
        cam = self.camera.to_dict()
        cam.update({k: v for k, v in self.records.get("camera", {}).items() if k not in cam})
        d = {"kind": SENSOR_KIND, "version": 1, "units": "mm", "frame": "camera", "camera": cam,
             "frames": {"rotate_deg": self.rotate_deg, "note": "image files are rotated clockwise by rotate_deg "
                        "before use; the camera refers to the rotated frame"},
             "planes": {n: p.to_dict() for n, p in self.planes.items()},
             "turntable": None if self.turntable is None else self.turntable.to_dict(),
             "flange": None}
        if self.flange is not None:
            R, t = self.flange
            d["flange"] = {"T_flange_cam": {"R": np.asarray(R).tolist(), "t_mm": np.asarray(t).tolist()},
                           **self.records.get("flange", {})}
        if provenance is not None:
            d["provenance"] = provenance
        return d

    def save(self, path: str | os.PathLike, *, force: bool = False, provenance: dict | None = None) -> Path:
        return write_json(path, self.to_dict(provenance), force=force)

    @classmethod
    def from_dict(cls, d: dict, source: str = "sensor file") -> "Sensor":
        if d.get("kind") != SENSOR_KIND:
            raise LightplaneError(f"{source}: not a lightplane sensor file (kind {d.get('kind')!r}; make one with "
                                  "'lightplane sensor' or 'lightplane import-fabscan')")
        for key in ("camera", "planes"):
            if not isinstance(d.get(key), dict):
                raise LightplaneError(f"{source}: missing or malformed field '{key}'")
        cam = Camera.from_dict(d["camera"], source=f"{source}: camera")
        if not d["planes"]:
            raise LightplaneError(f"{source}: holds no light plane")
        planes = {str(n): LightPlane.from_dict(p, source=f"{source}: plane {n!r}") for n, p in d["planes"].items()}
        tt = None
        if d.get("turntable") is not None:
            tt = Turntable.from_dict(d["turntable"], source=f"{source}: turntable")
            tt.check_camera(cam, f"{source}: turntable")
        fl = None
        if d.get("flange") is not None:
            fd = mapping(d["flange"], "flange", source)
            fl = rigid_from_dict(fd.get("T_flange_cam", fd), f"{source}: flange")
        frames = d.get("frames")
        rot = 0 if frames is None else mapping(frames, "frames", source).get("rotate_deg", 0)
        if isinstance(rot, bool) or rot not in (0, 90, 180, 270):
            raise LightplaneError(f"{source}: field 'frames.rotate_deg' must be 0, 90, 180 or 270, got {rot!r:.40}")
        records = {"camera": {k: v for k, v in d["camera"].items() if k in ("provenance", "source")}}
        if d.get("flange") is not None:
            records["flange"] = {k: v for k, v in d["flange"].items() if k != "T_flange_cam"}
        return cls(cam, planes, tt, fl, int(rot), records)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Sensor":
        return cls.from_dict(read_json(path, "sensor file"), source=str(path))


# ----------------------------------------------------------------------------- FabScan
def _fabscan_rotation(cam: dict, source: str) -> int:
    """FabScan's frame flips as one clockwise rotation (rotate = transpose, then the flips)."""

    def flag(k):
        return str(cam.get(k, "False")).strip().lower() in ("true", "1", "yes")

    key = (flag("rotate"), flag("hflip"), flag("vflip"))
    table = {(False, False, False): 0, (True, True, False): 90, (False, True, True): 180, (True, False, True): 270}
    if key not in table:
        raise LightplaneError(f"{source}: camera rotate={key[0]}, hflip={key[1]}, vflip={key[2]} mirrors the frames "
                              "(not a rotation); lightplane reads frames rotated only")
    return table[key]


def import_fabscan(path: str | os.PathLike) -> Sensor:
    """A FabScanPi configuration (``fabscan-config.json``) as a :class:`Sensor`.

    Camera: ``calibration.camera_matrix`` and ``distortion_vector``, its size the
    ``camera.resolution`` in the frame FabScan uses (``rotate``/``hflip``/``vflip``
    recorded as one clockwise rotation of every frame, so frames are read as FabScan
    reads them).  Planes ``laser0``, ``laser1``... from ``calibration.laser_planes``
    (FabScan's ``normal · X = distance`` is ``d = −distance``; no covariance: FabScan
    stores only a ``deviation``, kept as ``fabscan_deviation_mm``).  Turntable: the
    platform's origin ``platform_translation`` and, of ``platform_rotation``'s columns,
    the one most nearly along the camera's y axis as the axis direction;
    ``turntable.steps`` as the counts per revolution.
    """
    src = str(path)
    d = read_json(path, "FabScan configuration")
    cal = d.get("calibration")
    camd = d.get("camera")
    if not isinstance(cal, dict) or not isinstance(camd, dict):
        raise LightplaneError(f"{src}: not a FabScan configuration (no 'calibration' and 'camera' sections)")
    rot = _fabscan_rotation(camd, src)
    cam = _fabscan_camera(cal, camd, rot, src)
    prov = provenance([src], {"importer": "fabscan"})
    planes = _fabscan_planes(cal, cam, prov, src)
    tt = None
    if cal.get("platform_translation") is not None and cal.get("platform_rotation") is not None:
        tt = _fabscan_turntable(cal, d.get("turntable"), cam, prov, src)
    return Sensor(cam, planes, tt, None, rot, {"camera": {"provenance": prov}})


def _fabscan_camera(cal: dict, camd: dict, rot: int, src: str) -> Camera:
    """The camera of a FabScan configuration, in the frame FabScan reads (rotated by ``rot``)."""
    for key in ("camera_matrix", "distortion_vector"):
        if key not in cal:
            raise LightplaneError(f"{src}: no camera calibration (calibration.{key} is missing)")
    K = array(cal["camera_matrix"], "calibration.camera_matrix", src)
    if K.shape != (3, 3) or not K[0, 0] > 0:
        raise LightplaneError(f"{src}: field 'calibration.camera_matrix' is not a calibrated 3x3 matrix (run "
                              "FabScan's calibration first)")
    dist = array(cal["distortion_vector"], "calibration.distortion_vector", src).ravel()
    res = mapping(camd.get("resolution"), "camera.resolution", src)
    w, h = (integer(res.get(k), f"camera.resolution.{k}", src, lo=1, hi=MAX_IMAGE_PX) for k in ("width", "height"))
    if rot in (90, 270):
        w, h = h, w
    try:
        cam = Camera(K, dist, w, h, meta={"source": src})
    except LightplaneError as e:
        raise LightplaneError(f"{src}: calibration: {e}") from None
    return check_camera_file(cam, src, k_field="calibration.camera_matrix", dist_field="calibration.distortion_vector")


def _fabscan_planes(cal: dict, cam: Camera, prov: dict, src: str) -> dict[str, LightPlane]:
    """FabScan's ``calibration.laser_planes`` (``normal · X = distance``) as planes ``laser0``, ``laser1``..."""
    lps = cal.get("laser_planes") or []
    if not isinstance(lps, list):
        raise LightplaneError(f"{src}: field 'calibration.laser_planes' must be a list of planes")
    planes = {}
    for i, lp in enumerate(lps):
        where = f"calibration.laser_planes[{i}]"
        lp = mapping(lp, where, src)
        if "normal" not in lp or "distance" not in lp:
            raise LightplaneError(f"{src}: {where} lacks a normal and a distance")
        n = array(lp["normal"], f"{where}.normal", src, (3,))
        dd = number(lp["distance"], f"{where}.distance", src)
        dev = lp.get("deviation")
        with np.errstate(over="ignore"):
            norm = float(np.linalg.norm(n))
        if not 0 < norm < np.inf:
            raise LightplaneError(f"{src}: field '{where}.normal' must be a non-zero vector of moderate size")
        rec = {"normal": (n / norm).tolist(), "d": -dd / norm, "method": "fabscan", "laser": f"laser{i}",
               "fabscan_deviation_mm": None if dev is None else number(dev, f"{where}.deviation", src, lo=0),
               "camera": camera_record(cam), "provenance": prov}
        planes[f"laser{i}"] = LightPlane.from_dict(rec, source=f"{src}: {where}")
    if not planes:
        raise LightplaneError(f"{src}: calibration.laser_planes is empty (no calibrated laser)")
    return planes


def _fabscan_turntable(cal: dict, table: Any, cam: Camera, prov: dict, src: str) -> Turntable:
    """The platform's origin and, of its rotation's columns, the one most nearly along the camera's y axis."""
    Rp = array(cal["platform_rotation"], "calibration.platform_rotation", src, (3, 3))
    tp = array(cal["platform_translation"], "calibration.platform_translation", src, (3,))
    table = {} if table is None else mapping(table, "turntable", src)
    col = int(np.argmax(np.abs(Rp[1, :])))
    with np.errstate(all="ignore"):
        axis = Rp[:, col] / np.linalg.norm(Rp[:, col])
    if not np.all(np.isfinite(axis)):
        raise LightplaneError(f"{src}: field 'calibration.platform_rotation' must be a rotation (its column {col} "
                              "is zero or huge)")
    steps, radius = table.get("steps"), table.get("radius")
    rec = {"point_mm": tp.tolist(), "direction": axis.tolist(), "camera": cam.to_dict(),
           "counts_per_rev": number(steps, "turntable.steps", src, positive=True) if steps else None,
           "method": "fabscan platform pose", "fabscan_platform_rotation_column": col,
           "fabscan_turntable_radius_mm": None if radius is None else number(radius, "turntable.radius", src),
           "provenance": prov}
    return Turntable.from_dict(rec, source=f"{src}: calibration.platform_rotation/platform_translation")


# ----------------------------------------------------------------------------- measuring
@dataclass(frozen=True)
class LaserScanSummary:
    """What :func:`measure_lasers` did; ``lasers``: per laser ``(name, frames, frames used, points,
    skipped (index, name, reason)..., profile axis, stripe width px or None)``; ``dropped``: per laser
    ``(name, Dropped)``, the points the screen dropped (:class:`lightplane.measure.scan.Dropped`)."""

    path: Path
    format: str
    lasers: tuple  # (name, n_frames, n_used, n_points, skipped)
    n_points: int
    motion: dict
    seconds: float
    dropped: tuple = ()


@with_blas_limited
def measure_lasers(scans: Sequence[tuple[str, FrameSource, LightPlane]], camera: Camera, out_path,
                   options: MeasureOptions = MeasureOptions(), *, motion: Motion | None = None,
                   output: CloudOutput = CloudOutput(), workers: int | None = None,
                   progress: Callable[[int, int | None], None] | None = None) -> LaserScanSummary:
    """Measure one frame sequence per laser (``(name, FrameSource, plane)``) into one cloud.

    Every point gets its laser's index (``laser``, :data:`LASER_POINT_DTYPE`; names in the
    file's comments) and its frame index within its laser's sequence; the same
    ``motion`` places every laser's frames.  ``options``
    (:class:`~lightplane.measure.options.MeasureOptions`) apply to every laser (a stripe
    width of None is estimated on each laser's first frame); ``output``:
    :class:`~lightplane.measure.options.CloudOutput`.  All inputs are checked (first frames,
    sizes, frame counts against the motion) before any frame is measured; the file is written
    atomically at the end, so an error leaves nothing behind.
    """

    t0 = time.perf_counter()
    out, fmt = output.target(out_path)
    if not scans:
        raise LightplaneError("no laser to measure")
    names = [n for n, _, _ in scans]
    if len(set(names)) != len(names):
        raise LightplaneError(f"a laser is named twice: {', '.join(names)}")
    if len(scans) > 255:
        raise LightplaneError("at most 255 lasers in one cloud")
    motion = Motion.none() if motion is None else motion
    try:
        prepared = [_prepare_laser(name, source, camera, plane, motion, options) for name, source, plane in scans]
        total = sum((s.n_frames or 0) for _, s, _, _, _ in prepared) or None
        done = 0

        def step() -> None:
            nonlocal done
            done += 1
            if progress is not None:
                progress(done, total)

        per_laser, dropped = [], []
        with PointSpool(out.parent if str(out.parent) else None, dtype=LASER_POINT_DTYPE) as spool:
            for li, (name, src, proc, ax, w) in enumerate(prepared):
                dr = Dropped()
                n, skipped, npts = _spool_laser(li, name, src, proc, spool, motion, workers, step, dr)
                per_laser.append((name, n, n - len(skipped), npts, tuple(skipped), ax, w))
                dropped.append((name, dr))
            lines = _lasers_comments(prepared, scans, per_laser, names, motion, options) + list(output.comments)
            lines += [f"laser {name}: {line}" for name, dr in dropped for line in dr.comments()]
            write_cloud(out, spool, fmt=fmt, ascii=output.ascii, force=output.force, comments=lines)
            n_points = spool.count
    finally:
        for _, s, _ in scans:
            s.close()
    return LaserScanSummary(out, fmt, tuple(per_laser), n_points, motion.to_dict(), time.perf_counter() - t0,
                            tuple(dropped))


def _prepare_laser(name: str, source, camera: Camera, plane: LightPlane, motion: Motion, options: MeasureOptions):
    """One laser's scan checked and its frame processor: ``(name, source, processor, axis, width)``."""
    try:
        src, mo, opts = _prepare(source, camera, plane, motion, options)
    except LightplaneError as e:
        raise LightplaneError(f"laser {name}: {e}") from None
    return name, src, FrameProcessor(camera, plane, mo, opts), opts.axis, opts.stripe.width_px


def _spool_laser(li: int, name: str, src, proc, spool: PointSpool, motion: Motion, workers: int | None,
                 step: Callable[[], None], dropped: Dropped) -> tuple[int, list, int]:
    """Laser ``li``'s frames measured into ``spool`` (``step()`` after each frame, what the screen
    dropped into ``dropped``); its number of frames, skipped frames and points.  Raises for frame
    counts off the motion's, no readable frame, no stripe."""
    n, skipped, count0 = 0, [], spool.count
    if workers is None and src.n_frames is not None and src.n_frames < 64:
        workers = 1
    for r in iter_scan(src, proc, workers=workers):
        n += 1
        if r.error is not None:
            skipped.append((r.index, r.name, r.error))
            step()
            continue
        dropped.add(r)
        if r.records is not None and r.records.size:  # no error: the frame has its records
            rec = np.empty(r.records.size, LASER_POINT_DTYPE)
            for f in POINT_FIELDS:
                rec[f] = r.records[f]
            rec["laser"] = li
            spool.append(rec)
        step()
    if motion.n_frames is not None and motion.n_frames != n:
        raise LightplaneError(f"laser {name}: the {motion.what} give {motion.n_frames} frames but the "
                              f"input has {n}")
    if n == len(skipped):
        raise LightplaneError(f"laser {name}: " + too_few_images_message(
            "frames", 0, 1, [(nm, why) for _, nm, why in skipped]))
    if spool.count == count0:
        raise LightplaneError(f"laser {name}: {no_points_message(n - len(skipped), dropped)}")
    return n, skipped, spool.count - count0


def _lasers_comments(prepared, scans, per_laser, names, motion: Motion, options: MeasureOptions) -> list[str]:
    """A merged cloud's comment lines: the lasers, provenance, options, skipped frames."""
    record = {"lasers": names, "axis": options.axis, "roi": options.roi, "width_px": options.stripe.width_px,
              "channel": options.stripe.channel, "motion": motion.to_dict()}
    prov = provenance([getattr(s, "description", "") for _, s, _, _, _ in prepared], record)
    return [f"lightplane point cloud: x y z in mm ({motion.frame_description}); laser = index below",
            *(f"laser {i}: {n} ({nf} frames, {npt} points; plane {plane!r})"
              for i, ((n, nf, _, npt, _, _, _), (_, _, plane)) in enumerate(zip(per_laser, scans))),
            f"created: {prov['created_utc']}", f"command: {prov['command']}",
            f"versions: {' '.join(f'{k}={v}' for k, v in prov['versions'].items())}",
            f"options: {record}",
            *(f"laser {n}: skipped frames: {summarize_reasons([(nm, why) for _, nm, why in sk])}"
              for n, _, _, _, sk, _, _ in per_laser if sk)]
