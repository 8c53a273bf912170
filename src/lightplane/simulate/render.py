"""Synthetic images with exact ground truth: circle-target, chessboard and scan scenes.

The scenes use lightplane's default sensor (docs/conventions.md §Default sensor,
:mod:`lightplane.simulate.scene`) unless a camera and plane are given.  Images
are made by supersampled ray casting through the *distorted* camera
(:mod:`lightplane.simulate.render_core`: ``4 x 4`` stratified jittered samples per
pixel, ``16 x 16`` on material edges), then a Gaussian PSF, vignetting, shot noise
(Poisson, via a gain in electrons per grey level) and read noise, and 8-bit
quantisation with saturation.

Difficulty levels (:data:`DIFFICULTIES`):

- ``clean``: PSF σ 0.6 px, no speckle, no vignetting, low noise;
- ``realistic``: laser speckle (multiplicative, spatially correlated modulation of
  the sheet: 25 % at a point, correlated over ~1 px; it puts ~0.11 px of noise on each
  stripe centre at Steger's minimum scale, ~0.08 px at the scales recommended for
  speckled stripes: the low end of the physical 0.1–0.3 px of docs/conventions.md §Noise), mild defocus
  (PSF σ 0.9 px), vignetting, realistic noise, and exposure varying by ±15 % between
  images;
- ``hard``: as realistic but with stronger speckle (30 %: ~0.13 px per centre), plus
  2–4 clutter ellipses and rectangles, the stripe partly saturated on every other
  image, and one image whose stripe misses the disc (``usable: false`` in the truth).

Every dataset is a :class:`Dataset` (images, camera, truth dict) that saves PNGs,
``camera.json`` and ``truth.json``; the truth holds everything needed to check a
result exactly (plane; target poses, rim conics in undistorted pixels and chord
endpoints; board poses ``T_cam_board``; scan surfaces and motion).

>>> ds = render_circle_dataset(n=1, seed=0, difficulty="clean")   # doctest: +SKIP
>>> ds.images[0].shape, ds.truth["images"][0]["usable"]             # doctest: +SKIP
((960, 1280), True)
"""

from __future__ import annotations

import os
from functools import lru_cache
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from lightplane.camera.model import Camera
from lightplane.camera.targets import board_object_points
from lightplane.core.errors import LightplaneError
from lightplane.plane.model import LightPlane
from lightplane.simulate import render_core as rc
from lightplane.simulate.scene import (PlacementOptions, TargetPlacement, default_camera, default_plane,
                                       sample_placements)
from lightplane.core.io import atomic_write, provenance, write_json

__all__ = [
    "DIFFICULTIES",
    "Imaging",
    "RenderOptions",
    "CircleOptions",
    "BoardCapture",
    "BoardOptions",
    "Dataset",
    "laser_source",
    "curved_sheet",
    "sheet_tilt_for_sag",
    "render_circle_image",
    "render_circle_dataset",
    "second_laser_plane",
    "render_chessboard_dataset",
    "render_board_pose",
    "render_target_dataset",
    "target_spec",
    "target_object_points",
    "TargetSpec",
    "TARGET_KINDS",
    "TARGET_CAPTURES",
    "dot_image_centres",
    "render_scan_dataset",
    "check_output_dir",
    "settings_tag",
    "sample_board_poses",
    "board_corners",
    "CALIBRATION_CAPTURE",
    "STRIPE_CAPTURE",
]

DIFFICULTIES = ("clean", "realistic", "hard")
POLARITIES = ("light", "dark")
SCAN_KINDS = ("sphere", "step", "plane")


@dataclass(frozen=True)
class Imaging:
    """Image-formation settings of one difficulty level.

    psf_sigma_px: Gaussian PSF (px); vignetting: relative fall-off at the image corner
    (``1 - vignetting · (r / r_corner)²``); speckle: standard deviation of the sheet's
multiplicative modulation at a point (before pixel averaging);
    speckle_corr_mm: its correlation length on the surface; gain_e_per_dn: electrons per
    grey level (shot noise); read_noise_dn: Gaussian read noise (grey levels);
    exposure_jitter: relative random spread of ambient and laser power between images;
    sheet_sigma_mm: the light sheet's Gaussian half-thickness σ (mm): 0.2 mm, a focused
    line of 0.47 mm FWHM (~5.5 px wide on the default sensor at 450 mm), as metrology
    line lasers have.  A thicker sheet biases points on steeply curved surfaces: its
    footprint there is seen unevenly foreshortened, so the stripe's centre is not the
    mid-plane crossing (clean sphere scan, true plane: fitted radius -0.017 mm low
    with σ 0.35 mm, -0.006 mm with 0.2 mm, -0.004 mm with 0.15 mm).
    """

    psf_sigma_px: float
    vignetting: float
    speckle: float
    speckle_corr_mm: float
    gain_e_per_dn: float
    read_noise_dn: float
    exposure_jitter: float
    sheet_sigma_mm: float = 0.2


_IMAGING = {
    "clean": Imaging(0.6, 0.0, 0.0, 0.1, 200.0, 0.3, 0.0),
    "realistic": Imaging(0.9, 0.25, 0.25, 0.1, 40.0, 1.0, 0.15),
    "hard": Imaging(0.9, 0.25, 0.3, 0.1, 40.0, 1.2, 0.15),
}

# Scene brightness (grey levels per unit albedo): ambient light and laser power at 450 mm.
_LIGHT = {"disc": 0.76, "background": 0.12, "ambient": 150.0, "laser": 150.0}
_DARK = {"board": 0.8, "disc": 0.25, "background": 0.1, "ambient": 140.0, "laser": 140.0}


def settings_tag() -> str:
    """Short hash (8 hex digits) of the image-formation settings of every difficulty level
    and of the scene brightness.

    Caches of rendered data sets (the benchmarks') put it in their names, so a change of
    the renderer's settings (speckle, sheet thickness, noise, ...) renders afresh instead
    of measuring stale images.  Changes of the rendering code itself are not covered.
    """
    import hashlib
    import json

    blob = json.dumps({"imaging": {k: v.__dict__ for k, v in _IMAGING.items()}, "light": _LIGHT, "dark": _DARK},
                      sort_keys=True)
    return hashlib.sha1(blob.encode()).hexdigest()[:8]


def _check_choice(value: str, choices: tuple[str, ...], name: str) -> str:
    if value not in choices:
        raise LightplaneError(f"{name} must be one of {', '.join(choices)}; got {value!r}")
    return value


def _check_n(n: int, name: str = "n") -> int:
    try:
        n_int = int(n)
    except (TypeError, ValueError):
        raise LightplaneError(f"{name} must be an integer >= 1, got {n!r}") from None
    if n_int < 1 or n_int != n:
        raise LightplaneError(f"{name} must be an integer >= 1, got {n!r}")
    return n_int


@dataclass(frozen=True)
class RenderOptions:
    """How the images of a rendered data set are formed.

    ``difficulty``: one of :data:`DIFFICULTIES` (its :class:`Imaging`); ``noise=False`` leaves
    out shot and read noise (quantisation stays): for self-consistency checks;
    ``samples`` / ``edge_samples``: S x S stratified samples per pixel (>= 4), F x F on
    material edges; ``sheet_tilt_deg``: the (first) laser's fan lens tilted by this angle, so
    that its sheet is a cone, not a plane (:func:`curved_sheet`; 0: the plane).
    """

    difficulty: str = "realistic"
    noise: bool = True
    samples: int = 4
    edge_samples: int = 16
    sheet_tilt_deg: float = 0.0

    def __post_init__(self) -> None:
        _check_choice(self.difficulty, DIFFICULTIES, "difficulty")
        if int(self.samples) < 4:
            raise LightplaneError(f"samples must be >= 4 (4x4 per pixel), got {self.samples}")
        if not (np.isfinite(self.sheet_tilt_deg) and abs(self.sheet_tilt_deg) <= 10.0):
            raise LightplaneError(f"sheet_tilt_deg must be within +-10 degrees, got {self.sheet_tilt_deg}")

    @property
    def imaging(self) -> Imaging:
        """The image-formation settings of :attr:`difficulty`."""
        return _IMAGING[self.difficulty]


@dataclass(frozen=True)
class CircleOptions(RenderOptions):
    """A circle-target scene (:func:`render_circle_dataset`, :func:`render_circle_image`).

    ``polarity``: ``light`` (a light disc in front of a dark background plane) or ``dark`` (a
    dark printed disc on a light square board); ``diameter_mm``: the disc; ``distance_mm``: the
    range of the discs' distances; ``laser_off``: also a laser-off image of every scene;
    ``more_planes``: the light planes of up to two more lasers; ``colour``: with more lasers,
    BGR images (laser k in channel red, green, blue), else gray images holding every stripe.
    """

    polarity: str = "light"
    diameter_mm: float = 50.0
    distance_mm: tuple[float, float] = (380.0, 520.0)
    laser_off: bool = False
    more_planes: tuple[LightPlane, ...] = ()
    colour: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        _check_choice(self.polarity, POLARITIES, "polarity")
        object.__setattr__(self, "more_planes", tuple(self.more_planes))
        if len(self.more_planes) > 2:
            raise LightplaneError(f"at most 3 lasers (one per colour channel), got {1 + len(self.more_planes)}")


def laser_source(plane: LightPlane) -> np.ndarray:
    """Where the laser sits: the plane's crossing of the camera's x or y axis (mm).

    The axis with the larger normal component is used, so the source is beside the
    camera (default sensor: x ≈ -210 mm; the paper's: y ≈ 150 mm).
    """
    n, d = plane.normal, plane.d
    k = 0 if abs(n[0]) >= abs(n[1]) else 1
    if abs(n[k]) < 1e-9:
        raise LightplaneError("the light plane is parallel to both image axes: no laser position beside the camera")
    p = np.zeros(3)
    p[k] = -d / n[k]
    return p


def _fan_frame(plane: LightPlane) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The laser's source ``L`` and the sheet's in-plane axes: ``e_x`` the fan's centre ray (from ``L``
    to where the optical axis meets the plane), ``e_y = n x e_x`` across the fan."""
    src = laser_source(plane)
    centre = plane.point_on_axis()
    if not np.all(np.isfinite(centre)):
        raise LightplaneError("the light plane is parallel to the optical axis: no centre ray for a curved sheet")
    ex = (centre - src) / np.linalg.norm(centre - src)
    return src, ex, np.cross(plane.normal, ex)


def curved_sheet(plane: LightPlane, tilt_deg: float, camera: Camera | None = None) -> dict | None:
    """The cone a fan lens tilted by ``tilt_deg`` makes of the laser sheet (None for 0), as the truth records it.

    The fan's rays leave the source ``L`` (:func:`laser_source`) and, with the lens tilted by
    ``tau`` about the fan's centre ray's normal, make the constant angle ``pi/2 - tau`` with the
    axis ``a = cos(tau) n + sin(tau) e_x`` (``n`` the plane's normal, ``e_x`` the centre ray): a
    circular cone with its apex at ``L``, tangent to the plane along the centre ray.  A point at
    ``x`` along the centre ray and ``y`` across the fan lies off the plane by
    ``w = tau y² / (2 x)`` (to first order in ``tau``), towards ``n`` for ``tau > 0``.
    ``sag_mm``: ``w`` at the field's edge, ``x`` from ``L`` to where the optical axis meets the
    plane and ``y`` half the stripe's length visible in ``camera``'s image there (default camera).
    """
    if float(tilt_deg) == 0.0:
        return None
    tau = float(np.radians(tilt_deg))
    src, ex, ey = _fan_frame(plane)
    x0, half = _field_of_sheet(plane, camera)
    return {"model": "cone", "tilt_rad": tau, "apex_mm": src, "axis": np.cos(tau) * plane.normal + np.sin(tau) * ex,
            "centre_ray": ex, "across_fan": ey, "field_centre_mm": x0, "field_half_width_mm": half,
            "sag_mm": tau * half**2 / (2.0 * x0),
            "note": "sag_mm = tilt_rad * field_half_width_mm^2 / (2 field_centre_mm): the sheet's largest "
                    "distance from its tangent plane at the field's edge"}


def _field_of_sheet(plane: LightPlane, camera: Camera | None) -> tuple[float, float]:
    """From the source to where the optical axis meets the plane (mm), and half the stripe's visible length there (mm)."""
    camera = default_camera() if camera is None else camera
    src, ex, ey = _fan_frame(plane)
    centre = plane.point_on_axis()
    y = np.linspace(-2000.0, 2000.0, 40001)
    uv = camera.project(centre + y[:, None] * ey)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= camera.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= camera.height - 1)
    if not inside.any():
        raise LightplaneError("the stripe is not in the image: no field for a curved sheet")
    return float(np.linalg.norm(centre - src)), 0.5 * float(y[inside].max() - y[inside].min())


def sheet_tilt_for_sag(sag_mm: float, plane: LightPlane | None = None, camera: Camera | None = None) -> float:
    """The fan lens's tilt (degrees) that bends the sheet by ``sag_mm`` at the field's edge (:func:`curved_sheet`)."""
    plane = default_plane() if plane is None else plane
    x0, half = _field_of_sheet(plane, camera)
    return float(np.degrees(2.0 * x0 * float(sag_mm) / half**2))


def _laser_row(plane: LightPlane, imaging: Imaging, power: float, rng: np.random.Generator,
               tilt_deg: float = 0.0) -> np.ndarray:
    cone = None
    if tilt_deg != 0.0:
        tau = float(np.radians(tilt_deg))
        cone = (np.cos(tau) * plane.normal + np.sin(tau) * _fan_frame(plane)[1], tau)
    return rc.make_laser(
        plane.normal, plane.d, laser_source(plane), power=power, sigma_mm=imaging.sheet_sigma_mm,
        speckle=imaging.speckle, corr_mm=imaging.speckle_corr_mm, seed=int(rng.integers(0, 2**31 - 1)), cone=cone,
    )


@lru_cache(maxsize=4)
def _vignetting(width: int, height: int, cx: float, cy: float, strength: float) -> np.ndarray:
    """The radial falloff ``1 - strength·r²/r²_max`` (r from the principal point, r_max to the
    farthest image corner) of every pixel, ``(height, width)``; kept for the next image of the
    same camera (read-only)."""
    v, u = np.mgrid[0:height, 0:width]
    r2 = (u - cx) ** 2 + (v - cy) ** 2
    corners = np.array([[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]])
    r2max = float(np.max((corners[:, 0] - cx) ** 2 + (corners[:, 1] - cy) ** 2))
    out = 1.0 - strength * r2 / r2max
    out.flags.writeable = False
    return out


def _finish(radiance: np.ndarray, camera: Camera, imaging: Imaging, rng: np.random.Generator | None,
            noise: bool = True) -> np.ndarray:
    """Vignetting, PSF, shot and read noise, 8-bit quantisation with saturation."""
    import cv2

    img = radiance
    if imaging.vignetting > 0:
        img = img * _vignetting(camera.width, camera.height, camera.cx, camera.cy, imaging.vignetting)
    if imaging.psf_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), imaging.psf_sigma_px, borderType=cv2.BORDER_REFLECT)
    if noise:
        if rng is None:
            raise LightplaneError("noise needs an rng")
        g = imaging.gain_e_per_dn
        img = rng.poisson(np.clip(img, 0, None) * g) / g + rng.normal(0.0, imaging.read_noise_dn, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _basis_from_normal(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ref = np.zeros(3)
    ref[int(np.argmin(np.abs(n)))] = 1.0
    e1 = np.cross(ref, n)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


# ----------------------------------------------------------------------------- circle
def _backproject_to_plane(camera: Camera, uv: np.ndarray, n: np.ndarray, p0: np.ndarray) -> np.ndarray:
    ray = camera.rays(np.atleast_2d(uv))[0]
    return ray * (n @ p0) / (n @ ray)


def _sample_clutter(camera: Camera, placement: TargetPlacement, rng: np.random.Generator, surface_n: np.ndarray,
                    surface_p: np.ndarray, polarity: str, max_offset_mm: float = np.inf,
                    basis: np.ndarray | None = None) -> list[dict]:
    """2–4 ellipses and rectangles on the surface behind/around the disc, kept clear of its image."""
    rim_uv = camera.project(placement.rim_points(72))
    c_uv = rim_uv.mean(axis=0)
    r_uv = float(np.max(np.linalg.norm(rim_uv - c_uv, axis=1)))
    out: list[dict] = []
    want = int(rng.integers(2, 5))
    e1, e2 = _basis_from_normal(surface_n)
    for _ in range(500):
        if len(out) == want:
            break
        uv = rng.uniform([0, 0], [camera.width - 1, camera.height - 1])
        kind = "ellipse" if rng.random() < 0.5 else "rectangle"
        a, b = (rng.uniform(6, 25), rng.uniform(6, 25)) if kind == "ellipse" else (rng.uniform(8, 30), rng.uniform(8, 30))
        p = _backproject_to_plane(camera, uv, surface_n, surface_p)
        e1_, e2_ = _basis_from_normal(surface_n) if basis is None else (basis[:, 0], basis[:, 1])
        if max(abs(e1_ @ (p - surface_p)), abs(e2_ @ (p - surface_p))) + np.hypot(a, b) > max_offset_mm:
            continue  # printed marks stay on the board
        size_px = np.hypot(a, b) * camera.fx / p[2]
        if np.linalg.norm(uv - c_uv) < r_uv + size_px + 40:
            continue
        if any(np.linalg.norm(uv - np.asarray(c["center_px"])) < size_px + c["size_px"] for c in out):
            continue
        ang = rng.uniform(0, np.pi)
        ax1 = np.cos(ang) * e1 + np.sin(ang) * e2
        ax2 = np.cross(surface_n, ax1)
        albedo = rng.uniform(0.45, 0.9) if polarity == "light" else rng.uniform(0.08, 0.3)
        out.append({"kind": kind, "center_mm": p, "axis1": ax1, "axis2": ax2, "half_sizes_mm": [a, b],
                    "albedo": albedo, "center_px": uv, "size_px": size_px})
    return out


def _circle_patches(placement: TargetPlacement, polarity: str, background_z_mm: float, clutter: list[dict]) -> np.ndarray:
    R = placement.basis()
    r = placement.radius_mm
    rows = []
    if polarity == "light":
        rows.append(rc.make_patch(placement.center, R[:, 0], R[:, 1], shape=rc.SHAPE_ELLIPSE, region=(r, r, 0, 0),
                                  albedo=_LIGHT["disc"], layer=1))
        rows.append(rc.make_patch([0, 0, background_z_mm], [1, 0, 0], [0, 1, 0], albedo=_LIGHT["background"]))
    else:
        half = 2.6 * r
        rows.append(rc.make_patch(placement.center, R[:, 0], R[:, 1], shape=rc.SHAPE_ELLIPSE, region=(r, r, 0, 0),
                                  albedo=_DARK["disc"], layer=2))
        rows.append(rc.make_patch(placement.center, R[:, 0], R[:, 1], shape=rc.SHAPE_RECT,
                                  region=(-half, half, -half, half), albedo=_DARK["board"], layer=0))
        rows.append(rc.make_patch([0, 0, background_z_mm], [1, 0, 0], [0, 1, 0], albedo=_DARK["background"]))
    for c in clutter:
        a, b = c["half_sizes_mm"]
        if c["kind"] == "ellipse":
            rows.append(rc.make_patch(c["center_mm"], c["axis1"], c["axis2"], shape=rc.SHAPE_ELLIPSE,
                                      region=(a, b, 0, 0), albedo=c["albedo"], layer=1))
        else:
            rows.append(rc.make_patch(c["center_mm"], c["axis1"], c["axis2"], shape=rc.SHAPE_RECT,
                                      region=(-a, a, -b, b), albedo=c["albedo"], layer=1))
    return np.array(rows)


def _circle_clutter(camera: Camera, placement: TargetPlacement, rng: np.random.Generator, polarity: str,
                    bg_z: float) -> list[dict]:
    """The clutter of a circle scene: on the background (light polarity) or printed on the board (dark)."""
    if polarity == "light":
        return _sample_clutter(camera, placement, rng, np.array([0.0, 0.0, -1.0]), np.array([0.0, 0.0, bg_z]), polarity)
    # printed marks on the board, a hair in front of its plane
    return _sample_clutter(camera, placement, rng, placement.normal, placement.center, polarity,
                           max_offset_mm=2.6 * placement.radius_mm, basis=placement.basis())


def _more_lasers_image(camera: Camera, plane: LightPlane, options: CircleOptions, patches: np.ndarray,
                       rad: np.ndarray, power_of, rng: np.random.Generator, nrng: np.random.Generator,
                       salt: int, ambient: float) -> tuple[np.ndarray, list[float]]:
    """The image of a scene lit by more lasers, and every laser's power.

    Light adds up, so each laser's stripe is the radiance with it on minus the radiance with
    every laser off (same scene, same samples); ``rad`` is the radiance with the first laser
    on, ``power_of()`` draws the next laser's power."""
    imaging = options.imaging
    S, F = options.samples, options.edge_samples
    off = rc.render_radiance(camera, patches, np.zeros((0, rc.SPHERE_COLS)),
                             _laser_row(plane, imaging, 0.0, rng, options.sheet_tilt_deg),
                             ambient, samples=S, edge_samples=F, salt=salt)
    stripes = [rad - off]
    powers = []
    for pl in options.more_planes:
        pw = power_of()
        powers.append(pw)
        r = rc.render_radiance(camera, patches, np.zeros((0, rc.SPHERE_COLS)), _laser_row(pl, imaging, pw, rng),
                               ambient, samples=S, edge_samples=F, salt=salt)
        stripes.append(r - off)
    if options.colour:
        # BGR: laser k in channel red, green, blue (k = 0, 1, 2); a channel without a laser
        # shows the scene alone
        chans = [off.copy(), off.copy(), off.copy()]
        for k, st in enumerate(stripes):
            chans[2 - k] = chans[2 - k] + st
        return np.dstack([_finish(c, camera, imaging, nrng, noise=options.noise) for c in chans]), powers
    return _finish(off + sum(stripes), camera, imaging, nrng, noise=options.noise), powers


def _render_circle(camera: Camera, plane: LightPlane, placement: TargetPlacement, rng: np.random.Generator,
                   options: CircleOptions, *, saturate: bool = False, clutter: bool | None = None,
                   laser: bool = True, noise_rng: np.random.Generator | None = None) -> tuple[np.ndarray, dict]:
    imaging = options.imaging
    levels = _LIGHT if options.polarity == "light" else _DARK
    bg_z = float(placement.center[2] + rng.uniform(80.0, 150.0))
    if clutter is None:
        clutter = options.difficulty == "hard"
    items = _circle_clutter(camera, placement, rng, options.polarity, bg_z) if clutter else []
    jit = imaging.exposure_jitter
    ambient = levels["ambient"] * (1.0 + rng.uniform(-jit, jit))

    def power_of() -> float:
        return levels["laser"] * (1.0 + rng.uniform(-jit, jit)) * (3.5 if saturate else 1.0) * float(laser)

    power = power_of()
    patches = _circle_patches(placement, options.polarity, bg_z, items)
    laser_row = _laser_row(plane, imaging, power, rng, options.sheet_tilt_deg)
    salt = int(rng.integers(0, 2**31 - 1))
    rad = rc.render_radiance(camera, patches, np.zeros((0, rc.SPHERE_COLS)), laser_row, ambient,
                             samples=options.samples, edge_samples=options.edge_samples, salt=salt)
    nrng = rng if noise_rng is None else noise_rng
    if options.more_planes:
        img, more = _more_lasers_image(camera, plane, options, patches, rad, power_of, rng, nrng, salt, ambient)
    else:
        img = _finish(rad, camera, imaging, nrng, noise=options.noise)
    info = {
        "background_plane": {"normal": [0.0, 0.0, -1.0], "d": bg_z},
        "ambient_dn": ambient,
        "laser_power_dn": power if not options.more_planes else [power, *more],
        "saturated_stripe": bool(saturate),
        "clutter": [{k: v for k, v in c.items() if k not in ("size_px",)} for c in items],
    }
    return img, info


def render_circle_image(camera: Camera, plane: LightPlane, placement: TargetPlacement, rng: np.random.Generator,
                        options: CircleOptions = CircleOptions(), *, saturate: bool = False,
                        clutter: bool | None = None, laser: bool = True) -> np.ndarray:
    """Render one image ``(H, W) uint8`` of a circular target crossed by the laser stripe.

    ``options``: the scene and the image formation (:class:`CircleOptions`; its
    ``diameter_mm``, ``distance_mm`` and ``laser_off`` are the data set's: the disc is
    ``placement``).  ``polarity="light"``: a light disc in front of a dark background plane
    (80–150 mm behind it); ``"dark"``: a dark printed disc on a light square board (the
    target's plane).  The stripe lights every surface it meets (the disc shadows the
    background).  ``saturate`` raises the laser power 3.5x so the stripe saturates on
    bright surfaces; ``clutter`` (default: only for ``hard``) adds 2–4 ellipses and
    rectangles; ``laser=False`` renders the same scene with the laser off (same random draws).
    """
    img, _ = _render_circle(camera, plane, placement, rng, options, saturate=saturate, clutter=clutter, laser=laser)
    return img


# ----------------------------------------------------------------------------- dataset
@dataclass(frozen=True, eq=False)
class Dataset:
    """Rendered images with their ground truth.

    images: list of ``(H, W)`` uint8 arrays; names: file names (PNG) in the same order;
    camera: the camera that rendered them (distorted); truth: JSON-ready dict.
    """

    images: list
    names: list
    camera: Camera
    truth: dict

    def __post_init__(self) -> None:
        if len(self.images) != len(self.names):
            raise LightplaneError("Dataset: images and names differ in length")

    def save(self, out_dir: str | os.PathLike, force: bool = False) -> list[Path]:
        """Write the PNGs, ``camera.json`` and ``truth.json`` into ``out_dir``.

        The folder is created if its parent exists.  Every target is checked before
        anything is written: an existing file without ``force``, or an unwritable folder,
        raises :class:`LightplaneError` and nothing is written.  Each file is written
        atomically (temporary file, then rename).
        """
        import cv2

        out = check_output_dir(out_dir, list(self.names) + ["camera.json", "truth.json"], force)
        try:
            out.mkdir(exist_ok=True)
        except OSError as e:
            raise LightplaneError(f"{out}: cannot create folder ({e.strerror})") from None
        written: list[Path] = []
        for name, img in zip(self.names, self.images):
            ok, buf = cv2.imencode(".png", img)
            if not ok:
                raise LightplaneError(f"{name}: PNG encoding failed")
            written.append(atomic_write(out / name, buf.tobytes(), force=force))
        written.append(self.camera.save_json(out / "camera.json", force=force))
        truth = dict(self.truth)
        truth["provenance"] = provenance([], truth.get("options", {}))
        written.append(write_json(out / "truth.json", truth, force=force))
        return written


def check_output_dir(out_dir: str | os.PathLike, names: list[str], force: bool = False) -> Path:
    """Check that ``names`` can be written into ``out_dir`` (created later if its parent exists).

    Raises :class:`LightplaneError` for a folder that is a file, has no parent, is not
    writable, or already holds one of the files (unless ``force``).
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise LightplaneError(f"{out}: exists and is not a folder")
    parent = out if out.exists() else out.parent
    if not out.exists() and not parent.is_dir():
        raise LightplaneError(f"{out}: its parent folder {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise LightplaneError(f"{parent}: folder is not writable")
    try:  # the real test (permissions can lie: read-only mounts, /proc, root)
        import tempfile

        with tempfile.NamedTemporaryFile(dir=parent, prefix=".lightplane-probe-"):
            pass
    except OSError as e:
        raise LightplaneError(f"{parent}: folder is not writable ({e.strerror})") from None
    if not force:
        existing = [str(out / n) for n in names if (out / n).exists()]
        if existing:
            raise LightplaneError(f"{existing[0]}: already exists (use --force to overwrite)"
                                  + (f" (and {len(existing) - 1} more)" if len(existing) > 1 else ""))
    return out


def _placement_truth(camera: Camera, plane: LightPlane, tp: TargetPlacement) -> dict:
    chord = tp.chord(plane)
    rim = tp.rim_points(360)
    uv = camera.project(rim)
    return {
        "center_mm": tp.center,
        "normal": tp.normal,
        "diameter_mm": tp.diameter_mm,
        "conic_undistorted_px": tp.conic(camera),
        "chord_mm": chord,
        "chord_length_mm": None if chord is None else float(np.linalg.norm(chord[1] - chord[0])),
        "rim_bbox_px": [float(uv[:, 0].min()), float(uv[:, 1].min()), float(uv[:, 0].max()), float(uv[:, 1].max())],
    }


def _chord_fraction(tp: TargetPlacement, plane: LightPlane) -> float:
    """The plane's chord across the disc as a fraction of its diameter (0 when it misses)."""
    c = tp.chord(plane)
    return 0.0 if c is None else float(np.linalg.norm(c[1] - c[0])) / tp.diameter_mm


def second_laser_plane(plane: LightPlane | None = None) -> LightPlane:
    """A second laser for two-laser renders: ``plane`` (default: the default sensor's) turned
    90 degrees about the optical axis, so its stripe runs across the first one's (a laser
    beside the camera on its y axis, crossing the optical axis at the same distance)."""
    plane = default_plane() if plane is None else plane
    n = plane.normal
    return LightPlane(np.array([-n[1], n[0], n[2]]), plane.d,
                      meta={"source": "lightplane.simulate.render.second_laser_plane"})


def _missing_placement(camera: Camera, plane: LightPlane, tp: TargetPlacement, margin_px: float = 20.0) -> TargetPlacement | None:
    """Shift a placement along the light plane's normal until the stripe misses it (still in view)."""
    for extra in (8.0, 15.0, 25.0):
        for sign in (1.0, -1.0):
            c = tp.center + sign * (tp.radius_mm + extra) * plane.normal
            moved = TargetPlacement(c, tp.normal, tp.diameter_mm)
            if moved.chord(plane) is not None:
                continue
            uv = camera.project(moved.rim_points(72))
            if np.all(np.isfinite(uv)) and np.all(camera.in_image(uv, margin=margin_px)):
                return moved
    return None


def _circle_placements(n: int, rng: np.random.Generator, camera: Camera, plane: LightPlane,
                       options: CircleOptions) -> tuple[list[TargetPlacement], int]:
    """The data set's placements (each crossed by every laser's stripe), and the index of the
    one moved off the sheet (``hard``; -1 otherwise)."""
    design = PlacementOptions(diameter_mm=options.diameter_mm, distance_mm=options.distance_mm)
    placements = sample_placements(n, rng, design, camera=camera, plane=plane)
    for i in range(n):
        for _ in range(100000):
            if all(_chord_fraction(placements[i], pl) >= 0.4 for pl in options.more_planes):
                break
            placements[i] = sample_placements(1, rng, design, camera=camera, plane=plane)[0]
        else:
            raise LightplaneError("render_circle_dataset: no placement found that every laser's stripe crosses")
    miss_index = -1
    if options.difficulty == "hard":
        miss_index = int(rng.integers(0, n))
        moved = None
        for _ in range(50):
            moved = _missing_placement(camera, plane, placements[miss_index])
            if moved is not None:
                break
            placements[miss_index] = sample_placements(1, rng, PlacementOptions(diameter_mm=options.diameter_mm),
                                                       camera=camera, plane=plane)[0]
        if moved is None:
            raise LightplaneError("render_circle_dataset: could not place a target off the light sheet")
        placements[miss_index] = moved
    return placements, miss_index


def _circle_truth(n: int, seed: int, plane: LightPlane, options: CircleOptions, per_image: list[dict]) -> dict:
    o = options
    return {
        "scene": "circle",
        "units": "mm; pixels (OpenCV convention, pixel centre (0, 0)); conics in undistorted pixels",
        "frame": "camera",
        "plane": plane.to_dict(),
        "laser_source_mm": laser_source(plane),
        "sheet": curved_sheet(plane, o.sheet_tilt_deg),
        **({"lasers": [{"name": f"laser{k}", "channel": ("red", "green", "blue")[k] if o.colour else "gray",
                        "plane": pl.to_dict(), "laser_source_mm": laser_source(pl)}
                       for k, pl in enumerate((plane, *o.more_planes))]} if o.more_planes else {}),
        "difficulty": o.difficulty,
        "polarity": o.polarity,
        "imaging": o.imaging.__dict__,
        "seed": seed,
        "options": {"n": n, "seed": seed, "difficulty": o.difficulty, "polarity": o.polarity,
                    "diameter_mm": o.diameter_mm, "laser_off": o.laser_off, "lasers": 1 + len(o.more_planes),
                    "colour": o.colour, "distance_mm": list(o.distance_mm), "sheet_tilt_deg": o.sheet_tilt_deg},
        "images": per_image,
    }


def render_circle_dataset(n: int = 12, seed: int = 0, options: CircleOptions = CircleOptions(), *,
                          camera: Camera | None = None, plane: LightPlane | None = None,
                          progress=None) -> Dataset:
    """``n`` images of a circular target (docs/conventions.md §Default sensor placements) crossed by the stripe.

    ``options``: the scene and the image formation (:class:`CircleOptions`).
    Truth (``Dataset.truth``): ``plane``; per image ``file``, ``target`` (centre and
    normal in mm, camera frame; rim conic in undistorted px; chord endpoints in mm),
    ``usable`` and ``reason``, and scene details (background plane, clutter, exposure).
    ``hard``: one image (chosen by the seed) has the target shifted off the sheet:
    ``usable: false``, ``reason: "stripe misses the target"``; every other image has
    the stripe 3.5x too bright (partly saturated).  ``laser_off``: also, for each image,
    the same scene with the laser off (``circle_XXX_off.png``, listed after its laser-on
    image; ``file_laser_off`` in the truth).  ``progress``: optional callable
    ``progress(i, n)`` after each image.

    ``more_planes``: the light planes of more lasers (up to two) whose stripes cross the
    disc in the same images (every placement is drawn until each stripe's chord is at
    least 0.4 of the diameter).  ``colour`` (default): BGR images, laser 0 (``plane``) in
    the red channel, the next in green, then blue (a channel without a laser shows the
    scene alone; each channel has its own noise, no crosstalk); else gray images holding
    every stripe.  The truth then lists ``lasers`` (name, channel, plane) and each image's
    ``chords_mm`` per laser.
    """
    n = _check_n(n)
    camera = default_camera() if camera is None else camera
    plane = default_plane() if plane is None else plane
    placements, miss_index = _circle_placements(n, np.random.default_rng(seed), camera, plane, options)
    images, names, per_image = [], [], []
    for i, tp in enumerate(placements):
        img_rng = np.random.default_rng([seed, i])
        saturate = options.difficulty == "hard" and i % 2 == 1 and i != miss_index
        img, info = _render_circle(camera, plane, tp, img_rng, options, saturate=saturate)
        name = f"circle_{i:03d}.png"
        entry: dict[str, object] = {"file": name, "target": _placement_truth(camera, plane, tp)}
        off_name = f"circle_{i:03d}_off.png"
        if options.more_planes:
            entry["chords_mm"] = {f"laser{k}": tp.chord(pl) for k, pl in enumerate((plane, *options.more_planes))}
        if options.laser_off:
            # the same scene (same draws), laser off, its own noise
            off, _ = _render_circle(camera, plane, tp, np.random.default_rng([seed, i]), options, saturate=saturate,
                                    laser=False, noise_rng=np.random.default_rng([seed, i, 1]))
            entry["file_laser_off"] = off_name
        if i == miss_index:
            entry.update(usable=False, reason="stripe misses the target")
        else:
            entry.update(usable=True, reason="")
        entry["scene"] = info
        images.append(img)
        names.append(name)
        if options.laser_off:
            images.append(off)
            names.append(off_name)
        per_image.append(entry)
        if progress is not None:
            progress(i + 1, n)
    return Dataset(images, names, camera, _circle_truth(n, seed, plane, options, per_image))


# ----------------------------------------------------------------------------- chessboard
def board_corners(board: tuple[int, int], square_mm: float) -> np.ndarray:
    """``(cols*rows, 3)`` inner corners in the board frame (mm), row by row (OpenCV's order)."""
    cols, rows = board
    j, i = np.mgrid[0:rows, 0:cols]
    return np.column_stack([i.ravel() * square_mm, j.ravel() * square_mm, np.zeros(cols * rows)])


def _rotation(axis: ArrayLike, angle: float) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(axis, dtype=np.float64) * angle)[0]


def _board_outline(board: tuple[int, int], square_mm: float, margin_mm: float) -> np.ndarray:
    cols, rows = board
    u0, u1 = -square_mm - margin_mm, cols * square_mm + margin_mm
    v0, v1 = -square_mm - margin_mm, rows * square_mm + margin_mm
    return np.array([u0, u1, v0, v1])


def _board_stripe(plane: LightPlane, R: np.ndarray, t: np.ndarray, board: tuple[int, int],
                  square_mm: float) -> np.ndarray | None:
    """Endpoints (mm, camera frame) of the plane's line across the board's inner-corner area, or None."""
    cols, rows = board
    n_b = R.T @ plane.normal  # plane in board coordinates: n_b · q + (n·t + d) = 0
    s = float(plane.normal @ t + plane.d)
    g = n_b[:2]
    if np.hypot(*g) < 1e-9:
        return None
    # clip the line g·q = -s to the rectangle [0, (cols-1) sq] x [0, (rows-1) sq]
    umax, vmax = (cols - 1) * square_mm, (rows - 1) * square_mm
    hits = []
    if abs(g[1]) > 1e-12:
        for u in (0.0, umax):
            v = (-s - g[0] * u) / g[1]
            if 0 <= v <= vmax:
                hits.append((u, v))
    if abs(g[0]) > 1e-12:
        for v in (0.0, vmax):
            u = (-s - g[1] * v) / g[0]
            if 0 <= u <= umax:
                hits.append((u, v))
    if len(hits) < 2:
        return None
    pts = np.array(hits)
    dmat = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    a, b = np.unravel_index(np.argmax(dmat), dmat.shape)
    q = np.array([[*pts[a], 0.0], [*pts[b], 0.0]])
    return q @ R.T + t


@dataclass(frozen=True)
class BoardCapture:
    """A capture design: the board's inner corners and square, and the pose ranges of :func:`sample_board_poses`.

    The board (inner corners ``board = (cols, rows)``, ``square_mm``) faces the camera, its
    centre on the ray of a pixel drawn uniformly from the central ``centre_frac`` of the
    image's width and height, at ``distance_mm`` from the camera, tilted by ``tilt_deg``
    about a random in-plane axis and turned by up to ``±spin_deg`` about its normal; poses
    whose board outline leaves the image (less ``margin_px``) are redrawn, and with a light
    plane those whose stripe crosses less than ``min_stripe_frac`` of the board's width (or
    height); at most ``max_tries`` draws.  The defaults are :data:`STRIPE_CAPTURE`.
    """

    board: tuple[int, int] = (9, 6)
    square_mm: float = 8.0
    distance_mm: tuple[float, float] = (330.0, 560.0)
    tilt_deg: tuple[float, float] = (10.0, 45.0)
    centre_frac: float = 0.4
    spin_deg: float = 30.0
    margin_px: float = 15.0
    min_stripe_frac: float = 0.5
    max_tries: int = 20000

    def __post_init__(self) -> None:
        cols, rows = int(self.board[0]), int(self.board[1])
        if cols < 2 or rows < 2:
            raise LightplaneError(f"board needs at least 2x2 inner corners, got {self.board}")
        if not self.square_mm > 0:
            raise LightplaneError(f"square_mm must be positive, got {self.square_mm}")
        object.__setattr__(self, "board", (cols, rows))
        object.__setattr__(self, "distance_mm", (self.distance_mm[0], self.distance_mm[1]))
        object.__setattr__(self, "tilt_deg", (self.tilt_deg[0], self.tilt_deg[1]))
        object.__setattr__(self, "centre_frac", float(self.centre_frac))
        object.__setattr__(self, "spin_deg", float(self.spin_deg))


#: Chessboard capture designed for Zhang calibration of the default 16 mm camera (field
#: of view ~135 x 100 mm at 450 mm): a 15 x 11 inner-corner board of 8 mm squares
#: (144 x 112 mm with its margin) filling much of the image, strongly tilted (25–55°
#: about random in-plane axes) at 350–650 mm (whole in view mostly beyond ~500 mm), its
#: centre in the central 80 % of the image, so the corners spread over the whole image.
#: With this narrow field of view the principal point is tied to the tangential
#: distortion (a shift of the principal point is nearly a rotation of the camera plus
#: p1, p2): OpenCV's std of cx, cy is ~0.35, 0.25 px with 20 views (1.9, 1.3 px for the
#: old 15 views of a 9x6 board); see benchmarks/bench_calibrate.py.
CALIBRATION_CAPTURE = BoardCapture(board=(15, 11), square_mm=8.0, distance_mm=(350.0, 650.0), tilt_deg=(25.0, 55.0),
                                   centre_frac=0.8, spin_deg=30.0)
#: Capture of boards crossed by the stripe (Zhou's method, cross ratios): a small board
#: near the image centre, where the stripe is.
STRIPE_CAPTURE = BoardCapture(board=(9, 6), square_mm=8.0, distance_mm=(330.0, 560.0), tilt_deg=(10.0, 45.0),
                              centre_frac=0.4, spin_deg=30.0)


def _board_pose(rng: np.random.Generator, camera: Camera, capture: BoardCapture,
                centre_b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One drawn pose ``(R, t)`` of the board and its centre ``C`` (camera frame, mm)."""
    lo, hi = 0.5 - capture.centre_frac / 2, 0.5 + capture.centre_frac / 2
    uv = rng.uniform([lo * camera.width, lo * camera.height], [hi * camera.width, hi * camera.height])
    ray = camera.rays(uv[None])[0]
    dist = rng.uniform(*capture.distance_mm)
    C = ray / np.linalg.norm(ray) * dist
    phi = rng.uniform(0, 2 * np.pi)
    tilt = np.deg2rad(rng.uniform(*capture.tilt_deg))
    spin = np.deg2rad(rng.uniform(-capture.spin_deg, capture.spin_deg))
    R = _rotation([np.cos(phi), np.sin(phi), 0.0], tilt) @ _rotation([0, 0, 1.0], spin)
    return R, C - R @ centre_b, C


def _board_pose_ok(camera: Camera, capture: BoardCapture, plane: LightPlane | None, outline_b: np.ndarray,
                   R: np.ndarray, t: np.ndarray, C: np.ndarray) -> bool:
    """Whether a drawn pose faces the camera with the whole board in view (and, with ``plane``, the
    stripe across enough of it)."""
    corners_cam = outline_b @ R.T + t
    if np.any(corners_cam[:, 2] <= 50):
        return False
    # board must face the camera: its z axis points away from the camera
    if R[:, 2] @ C <= 0:
        return False
    uvc = camera.project(corners_cam)
    if not (np.all(np.isfinite(uvc)) and np.all(camera.in_image(uvc, margin=capture.margin_px))):
        return False
    if plane is not None:
        cols, rows = capture.board
        seg = _board_stripe(plane, R, t, capture.board, capture.square_mm)
        if seg is None:
            return False
        if np.linalg.norm(seg[1] - seg[0]) < capture.min_stripe_frac * (min(cols, rows) - 1) * capture.square_mm:
            return False
    return True


def sample_board_poses(n: int, rng: np.random.Generator, capture: BoardCapture = STRIPE_CAPTURE, *,
                       camera: Camera | None = None, plane: LightPlane | None = None,
                       outline: tuple[float, float, float, float] | None = None,
                       centre_mm: tuple[float, float] | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Random chessboard poses ``(R_cam_board (3, 3), t_cam_board (3,) mm)``, whole board in view.

    ``capture``: the board and the pose ranges (:class:`BoardCapture`; the board has a white
    margin of one square around its inner corners).  With ``plane``, only poses where the
    stripe crosses the inner-corner area over at least ``capture.min_stripe_frac`` of the
    board's width (or height) are kept.  :data:`CALIBRATION_CAPTURE` holds the design used
    for camera calibration.  Other targets (circle grids, ChArUco): ``outline = (u0, u1, v0,
    v1)``, the board's rectangle in its frame (mm), and ``centre_mm``, the point put on the
    drawn ray (default: the chessboard's, from ``capture.board`` and ``capture.square_mm``).
    """
    camera = default_camera() if camera is None else camera
    cols, rows = capture.board
    square_mm = capture.square_mm
    u0, u1, v0, v1 = _board_outline(capture.board, square_mm, square_mm) if outline is None else outline
    outline_b = np.array([[u0, v0, 0], [u1, v0, 0], [u1, v1, 0], [u0, v1, 0]])
    if centre_mm is None:
        centre_b = np.array([(cols - 1) * square_mm / 2, (rows - 1) * square_mm / 2, 0.0])
    else:
        centre_b = np.array([float(centre_mm[0]), float(centre_mm[1]), 0.0])
    out: list[tuple[np.ndarray, np.ndarray]] = []
    for _ in range(capture.max_tries):
        if len(out) == n:
            break
        R, t, C = _board_pose(rng, camera, capture, centre_b)
        if _board_pose_ok(camera, capture, plane, outline_b, R, t, C):
            out.append((R, t))
    if len(out) < n:
        raise LightplaneError(f"sample_board_poses: could only place {len(out)} of {n} boards in view "
                              f"(board {cols}x{rows}, square {square_mm} mm, distance {capture.distance_mm} mm)")
    return out


@dataclass(frozen=True)
class BoardOptions(RenderOptions):
    """A board scene (:func:`render_chessboard_dataset`, :func:`render_target_dataset`).

    ``capture``: the pose design (:class:`BoardCapture`; None: :data:`CALIBRATION_CAPTURE`
    without the stripe, :data:`STRIPE_CAPTURE` with it); the chessboard data set also takes
    its board and square from it.  ``with_stripe``: the laser is on and every board is posed
    so that the stripe crosses its points; ``laser_off``: with the stripe, also the same pose
    with the laser off (``*_off.png``); ``dark_laser`` (targets): the laser frames with 3 %
    of the ambient light.
    """

    difficulty: str = "clean"
    capture: BoardCapture | None = None
    with_stripe: bool = False
    laser_off: bool = False
    dark_laser: bool = False

    @property
    def design(self) -> BoardCapture:
        """The capture design used: :attr:`capture`, or the default of the stripe setting."""
        if self.capture is not None:
            return self.capture
        return STRIPE_CAPTURE if self.with_stripe else CALIBRATION_CAPTURE


def _laser_truth(plane: LightPlane, with_stripe: bool, difficulty: str, imaging, seed: int,
                 tilt_deg: float = 0.0) -> dict:
    """The truth entries a board data set shares: the plane and its source (with the stripe), the
    curved sheet (:func:`curved_sheet`, None for the plane), the imaging."""
    return {"plane": plane.to_dict() if with_stripe else None,
            "laser_source_mm": laser_source(plane) if with_stripe else None,
            "sheet": curved_sheet(plane, tilt_deg) if with_stripe else None,
            "with_stripe": bool(with_stripe), "difficulty": difficulty, "imaging": imaging.__dict__, "seed": seed}


def _render_board_view(camera: Camera, plane: LightPlane, patches: np.ndarray, img_rng: np.random.Generator,
                       options: BoardOptions, texels: np.ndarray | None = None
                       ) -> tuple[list[tuple[str, np.ndarray]], float, float]:
    """The images of one board pose: ``[(suffix, image)]`` (``""``, and ``"_off"`` for the laser-off
    companion), the ambient light and the laser power drawn for it."""
    imaging = options.imaging
    jit = imaging.exposure_jitter
    ambient = 150.0 * (1.0 + img_rng.uniform(-jit, jit))
    power = 180.0 * (1.0 + img_rng.uniform(-jit, jit))
    salt = int(img_rng.integers(0, 2**31 - 1))
    stripe = options.with_stripe
    variants = [("", power if stripe else 0.0, 0.03 if (options.dark_laser and stripe) else 1.0)]
    if options.laser_off and stripe:
        variants.append(("_off", 0.0, 1.0))
    out = []
    for suffix, pw, amb in variants:
        laser = _laser_row(plane, imaging, pw, img_rng, options.sheet_tilt_deg)
        rad = rc.render_radiance(camera, patches, np.zeros((0, rc.SPHERE_COLS)), laser, ambient * amb,
                                 samples=options.samples, edge_samples=options.edge_samples, salt=salt, texels=texels)
        out.append((suffix, _finish(rad, camera, imaging, img_rng, noise=options.noise)))
    return out, ambient, power


def _board_patches(spec: TargetSpec, R: np.ndarray, t: np.ndarray, layout: dict | None,
                   margin_mm: float | None = None) -> np.ndarray:
    """The board and the grey background 250 mm behind it."""
    bg = rc.make_patch([0, 0, float(t[2] + 250.0)], [1, 0, 0], [0, 1, 0], albedo=_BACKGROUND_ALBEDO)
    return np.array([_target_patch(spec, R, t, layout, margin_mm), bg])


def render_board_pose(target, R: ArrayLike, t: ArrayLike, *, margin_mm: float | None = None, seed: int = 0,
                      options: BoardOptions = BoardOptions(difficulty="clean", with_stripe=True, laser_off=True),
                      camera: Camera | None = None, plane: LightPlane | None = None) -> dict[str, np.ndarray]:
    """The images of one board pose ``(R, t)`` (board frame to camera, mm) chosen by the caller:
    ``{"": laser frame, "_off": laser-off frame}`` (``options``: as :func:`render_target_dataset`).

    ``margin_mm``: the white margin of the board beyond its squares (or outer dot centres);
    None: one square.  The grey background is 250 mm behind the board.
    """
    spec = target_spec(target)
    if margin_mm is not None and not (np.isfinite(margin_mm) and margin_mm >= 0):
        raise LightplaneError(f"margin_mm must be finite and >= 0, got {margin_mm}")
    camera = default_camera() if camera is None else camera
    plane = default_plane() if plane is None else plane
    layout = _charuco_layout(spec) if spec.kind == "charuco" else None
    R, t = np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)
    shots, _, _ = _render_board_view(camera, plane, _board_patches(spec, R, t, layout, margin_mm),
                                     np.random.default_rng(seed), options,
                                     None if layout is None else layout["texels"])
    return dict(shots)


def render_chessboard_dataset(n: int = 20, seed: int = 0, options: BoardOptions = BoardOptions(), *,
                              camera: Camera | None = None, plane: LightPlane | None = None,
                              progress=None) -> Dataset:
    """``n`` views of a chessboard (``options.design``: its ``board`` inner corners ``(cols, rows)``,
    ``square_mm`` and the pose ranges, see :class:`BoardOptions`).

    The board: ``(cols + 1) x (rows + 1)`` squares, the first one dark, a white margin of
    one square, in the board frame of OpenCV (inner corners at ``(i, j, 0) * square``,
    z away from the camera).  ``with_stripe``: the laser is on and every board is posed
    so the stripe crosses its corners (for Zhou's method and the cross-ratio check,
    docs/method.md §Zhou baseline, §Cross-ratio check); ``laser_off`` adds, for each view, a companion image of the same pose with
    the laser off (``board_XXX_off.png``).
    Truth per view: ``T_cam_board`` (``R``, ``t`` mm), the corners projected (distorted and
    undistorted px), and with the stripe the 3-D segment of the plane across the corner area.
    """
    design = options.design
    n = _check_n(n)
    if options.dark_laser:
        raise LightplaneError("dark_laser: render_target_dataset renders dark laser frames (a chessboard target "
                              "there gives the same images)")
    (cols, rows), square_mm = design.board, design.square_mm
    camera = default_camera() if camera is None else camera
    plane = default_plane() if plane is None else plane
    rng = np.random.default_rng(seed)
    poses = sample_board_poses(n, rng, design, camera=camera, plane=plane if options.with_stripe else None)
    obj = board_corners((cols, rows), square_mm)
    spec = TargetSpec("chessboard", cols, rows, square_mm)
    images, names, views = [], [], []
    for i, (R, t) in enumerate(poses):
        shots, ambient, power = _render_board_view(camera, plane, _board_patches(spec, R, t, None),
                                                   np.random.default_rng([seed, i]), options)
        entry: dict[str, object] = {"T_cam_board": {"R": R, "t": t}, "corners_px": camera.project(obj @ R.T + t),
                                    "corners_undistorted_px": camera.project(obj @ R.T + t, distort=False),
                                    "ambient_dn": ambient}
        for suffix, img in shots:
            images.append(img)
            names.append(f"board_{i:03d}{suffix}.png")
            entry["file" if suffix == "" else "file_laser_off"] = names[-1]
        if options.with_stripe:
            entry["laser_power_dn"] = power
            entry["stripe_on_board_mm"] = _board_stripe(plane, R, t, (cols, rows), square_mm)
        views.append(entry)
        if progress is not None:
            progress(i + 1, n)
    return Dataset(images, names, camera, _chessboard_truth(n, seed, plane, options, obj, views))


def _chessboard_truth(n: int, seed: int, plane: LightPlane, options: BoardOptions, obj: np.ndarray,
                      views: list[dict]) -> dict:
    d = options.design
    (cols, rows), square_mm = d.board, d.square_mm
    return {
        "scene": "chessboard",
        "units": "mm; pixels (OpenCV convention, pixel centre (0, 0))",
        "frame": "camera",
        "board": {"inner_corners": [cols, rows], "square_mm": square_mm, "squares": [cols + 1, rows + 1],
                  "first_square": "dark", "margin_mm": square_mm,
                  "corners_board_mm": obj, "corner_order": "(i * square_mm, j * square_mm, 0), i fastest (OpenCV order)",
                  "outline_board_mm": list(_board_outline((cols, rows), square_mm, square_mm))},
        **_laser_truth(plane, options.with_stripe, options.difficulty, options.imaging, seed, options.sheet_tilt_deg),
        "options": {"n": n, "seed": seed, "board": [cols, rows], "square_mm": square_mm, "sheet_tilt_deg": options.sheet_tilt_deg,
                    "distance_mm": list(d.distance_mm), "tilt_deg": list(d.tilt_deg), "centre_frac": d.centre_frac,
                    "with_stripe": options.with_stripe, "laser_off": options.laser_off,
                    "difficulty": options.difficulty},
        "views": views,
    }


# ----------------------------------------------------------------------------- other targets
TARGET_KINDS = ("chessboard", "circles", "acircles", "charuco")

#: Calibration-capture targets of about the chessboard's size (~130 x 100 mm with margins on
#: the default camera's ~135 x 100 mm field at 450 mm), for :func:`render_target_dataset`
#: with :data:`CALIBRATION_CAPTURE`'s poses: dict form of each target.
TARGET_CAPTURES = {
    "chessboard": {"kind": "chessboard", "cols": 15, "rows": 11, "square_mm": 8.0},
    "circles": {"kind": "circles", "cols": 11, "rows": 8, "square_mm": 11.0},
    "acircles": {"kind": "acircles", "cols": 6, "rows": 11, "square_mm": 9.0},
    "charuco": {"kind": "charuco", "cols": 11, "rows": 8, "square_mm": 12.0, "marker_mm": 9.0,
                "dictionary": "DICT_4X4_50"},
}

_BOARD_ALBEDO, _INK_ALBEDO, _BACKGROUND_ALBEDO = 0.86, 0.06, 0.25


@dataclass(frozen=True)
class TargetSpec:
    """A calibration target as the renderer reads it (the fields of ``lightplane.camera.targets.Target``).

    ``kind``: ``chessboard`` (``cols x rows`` inner corners), ``circles`` (OpenCV's symmetric
    grid of ``cols x rows`` dots), ``acircles`` (OpenCV's asymmetric grid, ``cols`` dots per
    row, ``rows`` rows) or ``charuco`` (``cols x rows`` squares, OpenCV's ``CharucoBoard``);
    ``square_mm``: the square, or the dots' pitch; ``marker_mm`` and ``dictionary`` (e.g.
    ``"DICT_4X4_50"``): ChArUco only; ``dot_mm``: dot diameter (None: half the pitch).
    """

    kind: str
    cols: int
    rows: int
    square_mm: float
    marker_mm: float | None = None
    dictionary: str | None = None
    dot_mm: float | None = None

    @property
    def dot_diameter_mm(self) -> float | None:
        if self.kind not in ("circles", "acircles"):
            return None
        return 0.5 * self.square_mm if self.dot_mm is None else float(self.dot_mm)

    def to_dict(self) -> dict:
        return {"kind": self.kind, "cols": self.cols, "rows": self.rows, "square_mm": self.square_mm,
                "marker_mm": self.marker_mm, "dictionary": self.dictionary, "dot_mm": self.dot_mm}


_SPEC_FIELDS = ("kind", "cols", "rows", "square_mm", "marker_mm", "dictionary", "dot_mm")


def target_spec(target) -> TargetSpec:
    """Read a target given as an object with the attributes of :class:`TargetSpec` (e.g.
    ``lightplane.camera.targets.Target``), a dict of them, a tuple ``(kind, cols, rows, square_mm)``
    (+ ``marker_mm, dictionary`` for ChArUco, + ``dot_mm`` for circle grids) or a
    :data:`TARGET_CAPTURES` name; checked."""
    if isinstance(target, TargetSpec):
        spec = target
    else:
        if isinstance(target, str):
            if target not in TARGET_CAPTURES:
                raise LightplaneError(f"target name must be one of {', '.join(TARGET_CAPTURES)}; got {target!r}")
            target = TARGET_CAPTURES[target]
        if isinstance(target, dict):
            unknown = set(target) - set(_SPEC_FIELDS)
            if unknown:
                raise LightplaneError(f"target: unknown field(s) {', '.join(sorted(unknown))}")
            d = dict(target)
        elif isinstance(target, (tuple, list)):
            t = list(target)
            if len(t) < 4:
                raise LightplaneError(f"target tuple needs (kind, cols, rows, square_mm, ...); got {target!r}")
            d = dict(zip(("kind", "cols", "rows", "square_mm"), t[:4]))
            extra = ("marker_mm", "dictionary") if t[0] == "charuco" else ("dot_mm",)
            if len(t) > 4 + len(extra):
                raise LightplaneError(f"target tuple has too many fields for {t[0]!r}: {target!r}")
            d.update(zip(extra, t[4:]))
        else:
            d = {k: getattr(target, k) for k in _SPEC_FIELDS if hasattr(target, k)}
        for k in ("kind", "cols", "rows", "square_mm"):
            if k not in d:
                raise LightplaneError(f"target has no {k!r}: {target!r}")
        kind = d["kind"]
        kind = getattr(kind, "value", kind)  # an Enum's value
        opt = lambda k: None if d.get(k) is None else d[k]  # noqa: E731
        try:
            spec = TargetSpec(str(kind), int(d["cols"]), int(d["rows"]), float(d["square_mm"]),
                              None if opt("marker_mm") is None else float(d["marker_mm"]),
                              None if opt("dictionary") is None else str(d["dictionary"]),
                              None if opt("dot_mm") is None else float(d["dot_mm"]))
        except (TypeError, ValueError) as e:
            raise LightplaneError(f"target: {e}") from None
    _check_choice(spec.kind, TARGET_KINDS, "target kind")
    if spec.cols < 2 or spec.rows < 2:
        raise LightplaneError(f"target needs cols, rows >= 2; got {spec.cols}x{spec.rows}")
    if not (np.isfinite(spec.square_mm) and spec.square_mm > 0):
        raise LightplaneError(f"square_mm must be positive, got {spec.square_mm}")
    if spec.kind == "charuco":
        if spec.marker_mm is None or spec.dictionary is None:
            raise LightplaneError("a charuco target needs marker_mm and dictionary")
        if not 0 < spec.marker_mm < spec.square_mm:
            raise LightplaneError(f"marker_mm must be in (0, square_mm); got {spec.marker_mm}")
    if spec.kind in ("circles", "acircles"):
        dot = spec.dot_diameter_mm
        assert dot is not None  # a circle grid always has a dot diameter
        r = 0.5 * dot
        limit = spec.square_mm * (np.sqrt(0.5) if spec.kind == "acircles" else 0.5)
        if not 0 < r < limit:
            raise LightplaneError(f"dot_mm {2 * r:g} overlaps its neighbours (must be in (0, {2 * limit:g}) mm)")
    return spec


def target_object_points(target) -> np.ndarray:
    """``(N, 3)`` points of a target in its board frame (mm, z = 0), in id order: chessboard
    inner corners and ChArUco chessboard corners ``j * (cols') + i`` at ``(i, j) * square``
    (ChArUco: ``((i + 1), (j + 1)) * square``, its own frame), circle-grid dot centres
    ``(i, j) * pitch``, or staggered ``((2 i + j mod 2), j) * pitch``; ``i`` fastest: the camera
    layer's :func:`lightplane.camera.targets.board_object_points`."""
    spec = target_spec(target)
    return board_object_points(spec.kind, spec.cols, spec.rows, spec.square_mm)


def _target_outline(spec: TargetSpec, margin_mm: float | None = None) -> np.ndarray:
    """The board's rectangle ``(u0, u1, v0, v1)`` in its frame (mm): a white margin of
    ``margin_mm`` (None: one square or pitch) around the squares (chessboard, ChArUco) or the
    outer dot centres."""
    s = spec.square_mm
    m = s if margin_mm is None else float(margin_mm)
    if spec.kind == "chessboard":
        return _board_outline((spec.cols, spec.rows), s, m)
    if spec.kind == "charuco":
        return np.array([-m, spec.cols * s + m, -m, spec.rows * s + m])
    obj = target_object_points(spec)
    return np.array([obj[:, 0].min() - m, obj[:, 0].max() + m, obj[:, 1].min() - m, obj[:, 1].max() + m])


def _fraction_gcd(values: list[float]) -> float:
    """Largest cell whose multiples hit every value (mm) exactly (values rational to 1e-9)."""
    from fractions import Fraction
    from math import gcd

    fr = []
    for x in values:
        f = Fraction(x).limit_denominator(100000)
        if abs(float(f) - x) > 1e-9 * max(1.0, abs(x)):
            raise LightplaneError(f"charuco: {x} mm is not a simple fraction of a millimetre; no exact texel grid")
        fr.append(f)
    den = 1
    for f in fr:
        den = den * f.denominator // gcd(den, f.denominator)
    g = 0
    for f in fr:
        g = gcd(g, int(f * den))
    return g / den


def _charuco_layout(spec: TargetSpec) -> dict:
    """The ChArUco board of OpenCV (``cv2.aruco.CharucoBoard``, non-legacy pattern): its marker
    ids and corners, its chessboard corners, and its albedo as a binary texture of square cells
    (1 = ink) over ``[0, cols·s] x [0, rows·s]`` (board frame; x along the image columns of
    ``generateImage``, y down its rows).  The geometry is OpenCV's, recomputed exactly in
    float64 (OpenCV keeps float32) and checked against it; the marker bits come from
    ``generateImageMarker`` with one pixel per bit."""
    import cv2

    # target_spec checked both for a charuco target
    assert spec.dictionary is not None and spec.marker_mm is not None
    try:
        dict_id = getattr(cv2.aruco, spec.dictionary)
    except AttributeError:
        raise LightplaneError(f"charuco: unknown dictionary {spec.dictionary!r} (e.g. DICT_4X4_50)") from None
    dictionary = cv2.aruco.getPredefinedDictionary(dict_id)
    board = cv2.aruco.CharucoBoard((spec.cols, spec.rows), spec.square_mm, spec.marker_mm, dictionary)
    s, m, nb = spec.square_mm, spec.marker_mm, int(dictionary.markerSize)
    off = (s - m) / 2
    ids = np.asarray(board.getIds()).ravel().astype(int)
    cv_corners = [np.asarray(c, dtype=np.float64).reshape(4, 3) for c in board.getObjPoints()]
    cell = _fraction_gcd([s, off, m / (nb + 2)])
    k, o, q = (int(round(x / cell)) for x in (s, off, m / (nb + 2)))
    nx, ny = spec.cols * k, spec.rows * k
    if nx * ny > 16_000_000:
        raise LightplaneError(f"charuco: texel grid {nx}x{ny} too fine (cell {cell} mm)")
    ink = np.ones((spec.rows, spec.cols), bool)  # squares without a marker are black
    tex = np.zeros((ny, nx), np.uint8)
    marker_corners = []
    for mid, c in zip(ids, cv_corners):
        ix, iy = (int(np.floor(x / s)) for x in c[:, :2].mean(axis=0))
        x0, y0 = ix * s + off, iy * s + off
        exact = np.array([[x0, y0, 0], [x0 + m, y0, 0], [x0 + m, y0 + m, 0], [x0, y0 + m, 0]])
        if not np.allclose(exact, c, atol=1e-3):
            raise LightplaneError(f"charuco: marker {mid} of OpenCV's board is not where expected ({c.tolist()})")
        marker_corners.append(exact)
        ink[iy, ix] = False
        bits = cv2.aruco.generateImageMarker(dictionary, int(mid), nb + 2, borderBits=1) == 0
        r0, c0 = iy * k + o, ix * k + o
        tex[r0:r0 + (nb + 2) * q, c0:c0 + (nb + 2) * q] = np.kron(bits, np.ones((q, q), np.uint8))
    for iy, ix in zip(*np.nonzero(ink)):
        tex[iy * k:(iy + 1) * k, ix * k:(ix + 1) * k] = 1
    obj = target_object_points(spec)
    cv_obj = np.asarray(board.getChessboardCorners(), dtype=np.float64).reshape(-1, 3)
    if cv_obj.shape != obj.shape or not np.allclose(cv_obj, obj, atol=1e-3):
        raise LightplaneError("charuco: OpenCV's chessboard corners are not at ((i + 1), (j + 1)) * square")
    return {"texels": tex, "cell_mm": cell, "marker_ids": ids, "marker_corners_mm": np.array(marker_corners),
            "board": board}


def _target_patch(spec: TargetSpec, R: np.ndarray, t: np.ndarray, layout: dict | None,
                  margin_mm: float | None = None) -> np.ndarray:
    u0, u1, v0, v1 = _target_outline(spec, margin_mm)
    s = spec.square_mm
    region = (u0, u1, v0, v1)
    if spec.kind == "chessboard":
        return rc.make_patch(t, R[:, 0], R[:, 1], shape=rc.SHAPE_RECT, region=region, albedo=_BOARD_ALBEDO, layer=1,
                             checker=(s, spec.cols + 1, spec.rows + 1, _INK_ALBEDO))
    if spec.kind == "charuco":
        assert layout is not None  # the caller builds the layout of a charuco target
        tex = layout["texels"]
        return rc.make_patch(t, R[:, 0], R[:, 1], shape=rc.SHAPE_RECT, region=region, albedo=_BOARD_ALBEDO, layer=1,
                             bitmap=(layout["cell_mm"], tex.shape[1], tex.shape[0], _INK_ALBEDO, 0))
    dot = spec.dot_diameter_mm
    assert dot is not None  # a circle grid
    return rc.make_patch(t, R[:, 0], R[:, 1], shape=rc.SHAPE_RECT, region=region, albedo=_BOARD_ALBEDO, layer=1,
                         dots=(s, spec.cols, spec.rows, _INK_ALBEDO, 0.5 * dot, spec.kind == "acircles"))


def dot_image_centres(camera: Camera, R: np.ndarray, t: np.ndarray, centres_mm: np.ndarray, radius_mm: float,
                      n_rim: int = 720) -> dict:
    """Where the dots of a circle grid appear (px), exactly.

    A disc's perspective image is an ellipse whose centre is not the image of the disc's
    centre: with ``H = [r1 r2 t]`` (board plane to normalised image), the ellipse's dual
    conic is ``H C* Hᵀ`` with ``C* = [[c1² - r², c1 c2, c1], [c1 c2, c2² - r², c2], [c1, c2, 1]]``
    and its centre is ``H C* Hᵀ (0, 0, 1)ᵀ``.  Returns ``ellipse_centres_undistorted_px``
    (pinhole image), ``ellipse_centres_px`` (that point through the distortion) and
    ``blob_centroids_px``: the area centroid of the *distorted* image of each disc (Green's
    theorem on ``n_rim`` projected rim points), what a blob's moments measure;
    ``projected_centres_px``: the dots' true centres projected (distorted).
    """
    H = np.column_stack([R[:, 0], R[:, 1], t])
    c = np.asarray(centres_mm, dtype=np.float64)[:, :2]
    r2 = float(radius_mm) ** 2
    Cs = np.zeros((len(c), 3, 3))
    Cs[:, 0, 0] = c[:, 0] ** 2 - r2
    Cs[:, 1, 1] = c[:, 1] ** 2 - r2
    Cs[:, 0, 1] = Cs[:, 1, 0] = c[:, 0] * c[:, 1]
    Cs[:, 0, 2] = Cs[:, 2, 0] = c[:, 0]
    Cs[:, 1, 2] = Cs[:, 2, 1] = c[:, 1]
    Cs[:, 2, 2] = 1.0
    e = np.einsum("ij,njk,k->ni", H, np.einsum("njk,lk->njl", Cs, H), np.array([0.0, 0.0, 1.0]))
    xy1 = np.column_stack([e[:, 0] / e[:, 2], e[:, 1] / e[:, 2], np.ones(len(e))])
    ang = np.linspace(0.0, 2 * np.pi, n_rim, endpoint=False)
    rim_b = c[:, None, :] + np.sqrt(r2) * np.stack([np.cos(ang), np.sin(ang)], axis=1)[None]
    rim_cam = rim_b[..., 0:1] * R[:, 0] + rim_b[..., 1:2] * R[:, 1] + t
    uv = camera.project(rim_cam.reshape(-1, 3)).reshape(len(c), n_rim, 2)
    x, y = uv[..., 0], uv[..., 1]
    xn, yn = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cross = x * yn - xn * y
    area = 0.5 * cross.sum(axis=1)
    cen = np.column_stack([((x + xn) * cross).sum(axis=1), ((y + yn) * cross).sum(axis=1)]) / (6.0 * area[:, None])
    centres_cam = np.column_stack([c, np.zeros(len(c))]) @ R.T + t
    return {"ellipse_centres_undistorted_px": camera.project(xy1, distort=False),
            "ellipse_centres_px": camera.project(xy1), "blob_centroids_px": cen,
            "projected_centres_px": camera.project(centres_cam)}


def _target_view_truth(camera: Camera, spec: TargetSpec, obj: np.ndarray, R: np.ndarray, t: np.ndarray,
                       layout: dict | None, ambient: float) -> dict[str, object]:
    """A target view's truth: its pose and its points projected (with the dots' image centres, the markers)."""
    pc = obj @ R.T + t
    points_px = camera.project(pc)
    entry: dict[str, object] = {"T_cam_board": {"R": R, "t": t}, "ids": np.arange(len(obj)),
                                "points_px": points_px, "points_undistorted_px": camera.project(pc, distort=False),
                                "ambient_dn": ambient}
    if spec.kind in ("circles", "acircles"):
        dot = spec.dot_diameter_mm
        assert dot is not None  # a circle grid
        dc = dot_image_centres(camera, R, t, obj, 0.5 * dot)
        entry.update({k: v for k, v in dc.items() if k != "projected_centres_px"})
        entry["centre_bias_px"] = np.linalg.norm(dc["ellipse_centres_px"] - points_px, axis=1)
    if layout is not None:
        mc = layout["marker_corners_mm"]
        entry["marker_ids"] = layout["marker_ids"]
        entry["marker_corners_px"] = camera.project(mc.reshape(-1, 3) @ R.T + t).reshape(-1, 4, 2)
    return entry


def _target_info(spec: TargetSpec, obj: np.ndarray, outline: np.ndarray, layout: dict | None) -> dict[str, object]:
    """The truth's description of the target: its points, their order, its outline and albedos."""
    order = {"chessboard": "inner corners (i, j) * square, id j * cols + i",
             "charuco": "chessboard corners ((i + 1), (j + 1)) * square (OpenCV's CharucoBoard frame), "
                        "id j * (cols - 1) + i",
             "circles": "dot centres (i, j) * pitch, id j * cols + i",
             "acircles": "dot centres ((2 i + j mod 2), j) * pitch, id j * cols + i"}[spec.kind]
    tinfo: dict[str, object] = {**spec.to_dict(), "object_points_mm": obj, "point_order": order,
                                "outline_board_mm": outline, "board_albedo": _BOARD_ALBEDO, "ink_albedo": _INK_ALBEDO}
    if spec.kind in ("circles", "acircles"):
        tinfo["dot_diameter_mm"] = spec.dot_diameter_mm
    if layout is not None:
        tinfo.update(marker_ids=layout["marker_ids"], marker_corners_mm=layout["marker_corners_mm"],
                     texel_mm=layout["cell_mm"])
    return tinfo


def render_target_dataset(target, n: int = 30, seed: int = 0, options: BoardOptions = BoardOptions(), *,
                          camera: Camera | None = None, plane: LightPlane | None = None,
                          progress=None) -> Dataset:
    """``n`` views of a calibration target (chessboard, circle grid, asymmetric circle grid or
    ChArUco board) in the calibration-capture style, with exact truth.

    ``target``: see :func:`target_spec` (a ``lightplane.camera.targets.Target``, a dict, a tuple or a
    :data:`TARGET_CAPTURES` name).  The board (white, albedo 0.86, ink 0.06, with a margin of
    one square or pitch) is posed as by :func:`sample_board_poses` with the distances, tilts,
    centring and spin of ``options.design`` (:class:`BoardOptions`: :data:`CALIBRATION_CAPTURE`
    unless given; its board and square are the target's), whole in view, 250 mm in front of a
    grey background, laser off.  A chessboard target gives the same images as
    :func:`render_chessboard_dataset` with the same seed.
    Circle dots are exact discs, ChArUco boards OpenCV's own layout (bit-exact texture).

    ``with_stripe``: the laser is on and every board is posed so that the stripe crosses
    its points (:data:`STRIPE_CAPTURE`'s distances, tilts and centring unless a capture is
    given; for Zhou's method and the cross-ratio check); ``laser_off`` adds, per view, the same
    pose with the laser off (``*_off.png``: a laser-off frame or a lit pattern frame);
    ``dark_laser`` renders the laser frames with 3 % of the ambient light (dark,
    low-exposure laser frames in which the board cannot be found, as FabScan takes them).
    Truth per view: ``file``, ``T_cam_board`` (``R``, ``t`` mm), ``ids`` (0..N-1) and
    ``points_px`` / ``points_undistorted_px``: :func:`target_object_points` projected, in id
    order; circle grids also ``ellipse_centres_px``, ``ellipse_centres_undistorted_px`` and
    ``blob_centroids_px`` (where the dots' images are centred, see
    :func:`dot_image_centres`) and ``centre_bias_px`` (``|ellipse centre - projected
    centre|`` per dot, distorted px); ChArUco also ``marker_ids`` and ``marker_corners_px``
    ``(M, 4, 2)``.
    """
    spec = target_spec(target)
    n = _check_n(n)
    camera = default_camera() if camera is None else camera
    obj = target_object_points(spec)
    outline = _target_outline(spec)
    centre = 0.5 * (obj[:, :2].min(axis=0) + obj[:, :2].max(axis=0))
    layout = _charuco_layout(spec) if spec.kind == "charuco" else None
    texels = None if layout is None else layout["texels"]
    plane = default_plane() if plane is None else plane  # laser off: its row still takes the chessboard's draws
    # the stripe check clips to [0, (cols-1) s] x [0, (rows-1) s]: the points' rectangle of each kind
    stripe_box = {"acircles": (2 * spec.cols, spec.rows), "charuco": (spec.cols + 1, spec.rows + 1)}.get(
        spec.kind, (spec.cols, spec.rows))
    capture = replace(options.design, board=stripe_box, square_mm=spec.square_mm)
    poses = sample_board_poses(n, np.random.default_rng(seed), capture, camera=camera,
                               plane=plane if options.with_stripe else None, outline=tuple(outline),
                               centre_mm=tuple(centre))
    images, names, views = [], [], []
    for i, (R, t) in enumerate(poses):
        shots, ambient, power = _render_board_view(camera, plane, _board_patches(spec, R, t, layout),
                                                   np.random.default_rng([seed, i]), options, texels)
        files = {}
        for suffix, img in shots:
            images.append(img)
            names.append(f"{spec.kind}_{i:03d}{suffix}.png")
            files["file" if suffix == "" else "file_laser_off"] = names[-1]
        entry: dict[str, object] = {**files, **_target_view_truth(camera, spec, obj, R, t, layout, ambient)}
        if options.with_stripe:
            entry["laser_power_dn"] = power
            entry["stripe_on_board_mm"] = _board_stripe(plane, R, t, stripe_box, spec.square_mm)
        views.append(entry)
        if progress is not None:
            progress(i + 1, n)
    d = options.design
    truth = {
        "scene": "target",
        "units": "mm; pixels (OpenCV convention, pixel centre (0, 0))",
        "frame": "camera",
        "target": _target_info(spec, obj, outline, layout),
        **_laser_truth(plane, options.with_stripe, options.difficulty, options.imaging, seed, options.sheet_tilt_deg),
        "options": {"target": spec.to_dict(), "n": n, "seed": seed, "difficulty": options.difficulty,
                    "distance_mm": list(d.distance_mm), "tilt_deg": list(d.tilt_deg), "centre_frac": d.centre_frac,
                    "spin_deg": d.spin_deg, "samples": options.samples, "edge_samples": options.edge_samples,
                    "noise": options.noise, "with_stripe": options.with_stripe, "laser_off": options.laser_off,
                    "dark_laser": options.dark_laser},
        "views": views,
    }
    return Dataset(images, names, camera, truth)


# ----------------------------------------------------------------------------- scans
_SCAN_DEFAULTS = {"sphere": (41, 1.5), "step": (21, 2.0), "plane": (21, 2.0)}


def _scan_objects(kind: str, offset: np.ndarray, plane: LightPlane) -> tuple[np.ndarray, np.ndarray, dict]:
    """Patches, spheres and truth surfaces of the scanned object displaced by ``offset`` (mm)."""
    spheres = np.zeros((0, rc.SPHERE_COLS))
    patches = []
    surfaces: dict
    if kind == "sphere":
        c = np.array([0.0, 0.0, 470.0]) + offset
        spheres = np.array([rc.make_sphere(c, 25.4, 0.7)])
        surfaces = {"sphere": {"center_mm": c, "radius_mm": 25.4}}
    elif kind == "step":
        # gauge step: base and top faces parallel, 10.000 mm apart, facing the camera tilted 20 deg about x
        Rg = _rotation([1.0, 0, 0], np.deg2rad(20.0))
        e1, e2, n_away = Rg[:, 0], Rg[:, 1], Rg[:, 2]
        p_base = np.array([0.0, 0.0, 480.0]) + offset
        p_top = p_base - 10.0 * n_away  # 10 mm towards the camera
        patches.append(rc.make_patch(p_base, e1, e2, shape=rc.SHAPE_RECT, region=(-40, 0, -45, 45), albedo=0.6))
        patches.append(rc.make_patch(p_top, e1, e2, shape=rc.SHAPE_RECT, region=(0, 40, -45, 45), albedo=0.6))
        patches.append(rc.make_patch(p_base, e2, -n_away, shape=rc.SHAPE_RECT, region=(-45, 45, 0, 10), albedo=0.6))
        n_cam = -n_away
        surfaces = {
            "base": {"normal": n_cam, "d": float(-n_cam @ p_base), "point_mm": p_base},
            "top": {"normal": n_cam, "d": float(-n_cam @ p_top), "point_mm": p_top},
            "separation_mm": 10.0,
            "in_plane_axes": [e1, e2],
            "base_region_uv_mm": [-40, 0, -45, 45],
            "top_region_uv_mm": [0, 40, -45, 45],
        }
    else:
        Rg = _rotation(np.array([0.3, 1.0, 0]) / np.linalg.norm([0.3, 1.0, 0]), np.deg2rad(30.0))
        e1, e2, n_away = Rg[:, 0], Rg[:, 1], Rg[:, 2]
        p0 = np.array([0.0, 0.0, 470.0]) + offset
        patches.append(rc.make_patch(p0, e1, e2, shape=rc.SHAPE_RECT, region=(-70, 70, -70, 70), albedo=0.6))
        n_cam = -n_away
        surfaces = {"plane": {"normal": n_cam, "d": float(-n_cam @ p0), "point_mm": p0}}
    # the table behind everything (static)
    patches.append(rc.make_patch([0, 0, 600.0], [1, 0, 0], [0, 1, 0], albedo=0.3))
    surfaces["background"] = {"normal": [0.0, 0.0, -1.0], "d": 600.0}
    return np.array(patches), spheres, surfaces


def render_scan_dataset(kind: str = "sphere", n_frames: int | None = None, step_mm: float | None = None,
                        direction=None, seed: int = 0, *, difficulty: str = "realistic", camera: Camera | None = None,
                        plane: LightPlane | None = None, noise: bool = True, progress=None) -> Dataset:
    """Frames of a linear scan: an object moved through the light sheet in known steps.

    ``kind``: ``sphere`` (radius 25.4 mm), ``step`` (gauge: two parallel faces 10.000 mm
    apart, and the riser between them) or ``plane`` (tilted 30°).  The object moves by
    ``step_mm`` per frame along ``direction`` (unit; default: the light plane's normal
    projected on the image plane, i.e. across the sheet), centred so that the middle
    frame sits on the sheet.  The scene is dark apart from weak ambient light: the
    stripe is what a scan sees; it also lights the static table (z = 600 mm).
    Truth: ``motion`` (direction, step, per-frame offsets) and per frame the surfaces.
    """
    _check_choice(kind, SCAN_KINDS, "kind")
    _check_choice(difficulty, DIFFICULTIES, "difficulty")
    d_n, d_s = _SCAN_DEFAULTS[kind]
    n_frames = _check_n(d_n if n_frames is None else n_frames, "n_frames")
    step_mm = float(d_s if step_mm is None else step_mm)
    if not (np.isfinite(step_mm) and step_mm > 0):
        raise LightplaneError(f"step_mm must be positive, got {step_mm}")
    camera = default_camera() if camera is None else camera
    plane = default_plane() if plane is None else plane
    if direction is None:
        direction = np.array([plane.normal[0], plane.normal[1], 0.0])
        if np.linalg.norm(direction) < 1e-9:
            direction = np.array([1.0, 0.0, 0.0])
    direction = np.asarray(direction, dtype=np.float64).ravel()
    if direction.shape != (3,) or not np.all(np.isfinite(direction)) or np.linalg.norm(direction) < 1e-12:
        raise LightplaneError(f"direction must be 3 finite numbers, not all zero; got {direction}")
    direction = direction / np.linalg.norm(direction)
    # centre the path so that the object's reference point crosses the sheet mid-scan
    _, _, s0 = _scan_objects(kind, np.zeros(3), plane)
    ref = {"sphere": lambda s: s["sphere"]["center_mm"], "step": lambda s: s["base"]["point_mm"],
           "plane": lambda s: s["plane"]["point_mm"]}[kind](s0)
    rate = float(plane.normal @ direction)
    shift = -float(plane.signed_distance(ref)[0]) / rate if abs(rate) > 1e-6 else 0.0
    offsets = [(shift + (k - (n_frames - 1) / 2) * step_mm) * direction for k in range(n_frames)]
    imaging = _IMAGING[difficulty]
    images, names, frames = [], [], []
    for k, off in enumerate(offsets):
        img_rng = np.random.default_rng([seed, k])
        patches, spheres, surfaces = _scan_objects(kind, off, plane)
        laser = _laser_row(plane, imaging, 220.0, img_rng)
        salt = int(img_rng.integers(0, 2**31 - 1))
        rad = rc.render_radiance(camera, patches, spheres, laser, 4.0, salt=salt)
        images.append(_finish(rad, camera, imaging, img_rng, noise=noise))
        name = f"scan_{k:03d}.png"
        names.append(name)
        frames.append({"file": name, "offset_mm": off, "surfaces": surfaces})
        if progress is not None:
            progress(k + 1, n_frames)
    truth = {
        "scene": "scan",
        "kind": kind,
        "units": "mm; pixels (OpenCV convention)",
        "frame": "camera",
        "plane": plane.to_dict(),
        "laser_source_mm": laser_source(plane),
        "motion": {"direction": direction, "step_mm": step_mm, "n_frames": n_frames,
                   "offsets_mm": [float(shift + (k - (n_frames - 1) / 2) * step_mm) for k in range(n_frames)]},
        "difficulty": difficulty,
        "imaging": imaging.__dict__,
        "seed": seed,
        "options": {"kind": kind, "n_frames": n_frames, "step_mm": step_mm, "seed": seed, "difficulty": difficulty},
        "frames": frames,
    }
    return Dataset(images, names, camera, truth)
