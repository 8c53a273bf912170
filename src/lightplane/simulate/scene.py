"""Sensor geometry and target placements with exact ground truth (docs/conventions.md §Default sensor, paper §3).

Two sensors are defined here:

- lightplane's default sensor (docs/conventions.md §Default sensor): a 1280x960 camera with 3.75 µm pixels and
  a 16 mm lens (``fx = fy = 16 / 0.00375 = 4266.667 px``), principal point off
  centre, moderate plumb-bob distortion; a light plane that contains the camera's
  y direction, is oblique to the optical axis by 25° and crosses it at
  z = 450 mm, so the laser sits at x ≈ -210 mm beside the camera and the stripe
  runs roughly vertically through the image.
- the paper's simulated sensor (§3): f = 25 mm, light plane
  ``0.9336 y - 0.3584 z + 140.04 = 0`` (the laser 150 mm above the camera, the
  stripe roughly horizontal).

A :class:`TargetPlacement` is a flat circular disc (centre, unit normal towards the
camera, diameter) in the camera frame; :func:`sample_placements` draws random ones
that satisfy docs/conventions.md §Default sensor, :func:`synthetic_observations` turns one into noisy pixel
points on the rim and on the stripe.

>>> import numpy as np
>>> cam, plane = default_camera(), default_plane()
>>> ps = sample_placements(3, np.random.default_rng(0))
>>> rim, stripe = synthetic_observations(cam, plane, ps[0], n_rim=50, n_stripe=40)
>>> rim.shape, stripe.shape
((50, 2), (40, 2))
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.plane.model import LightPlane

__all__ = [
    "default_camera",
    "default_plane",
    "lens_camera",
    "scheimpflug_camera",
    "scheimpflug_focal_plane",
    "paper_camera",
    "paper_plane",
    "PAPER_DISTANCE_MM",
    "TargetPlacement",
    "PlacementOptions",
    "sample_placements",
    "synthetic_observations",
]

#: Distances (mm, camera centre to disc centre) used for the paper's §3 study.  The
#: paper's Figure 6 is not legible in the transcript; with :func:`paper_camera`
#: the paper's plane is in view between ~290 mm and ~640 mm, and 380–520 mm keeps
#: discs of up to 70 mm wholly inside the image with the stripe across them.
PAPER_DISTANCE_MM = (380.0, 520.0)

_DEFAULT_TILT_RAD = np.deg2rad(25.0)
_DEFAULT_AXIS_Z_MM = 450.0


def default_camera(distortion: bool = True) -> Camera:
    """lightplane's default camera (docs/conventions.md §Default sensor).

    1280x960 pixels of 3.75 µm, 16 mm lens: ``fx = fy = 16 / 0.00375 = 4266.667 px``;
    principal point (652.3, 471.8) px (off centre); distortion
    ``(k1, k2, p1, p2, k3) = (-0.08, 0.12, 4e-4, -3e-4, 0)`` (about 2 px at the
    corners), or all zero with ``distortion=False`` (same ``K``).
    """
    f_px = 16.0 / 0.00375
    K = np.array([[f_px, 0.0, 652.3], [0.0, f_px, 471.8], [0.0, 0.0, 1.0]])
    dist = np.array([-0.08, 0.12, 4e-4, -3e-4, 0.0]) if distortion else np.zeros(5)
    return Camera(K, dist, 1280, 960, meta={"source": "lightplane.simulate.scene.default_camera"})


def default_plane() -> LightPlane:
    """lightplane's default light plane (docs/conventions.md §Default sensor).

    The plane contains the camera's y direction and the line through (0, 0, 450) mm
    with direction ``(sin 25°, 0, cos 25°)``: 25° oblique to the optical axis,
    crossing it at z = 450 mm, the laser at x = -450 tan 25° ≈ -209.8 mm on the
    camera's x axis.  Normal ``(-cos 25°, 0, sin 25°)``, ``d = -450 sin 25°``.
    """
    t = _DEFAULT_TILT_RAD
    n = np.array([np.cos(t), 0.0, -np.sin(t)])
    d = -float(n @ np.array([0.0, 0.0, _DEFAULT_AXIS_Z_MM]))
    return LightPlane(n, d, meta={"source": "lightplane.simulate.scene.default_plane"})


#: the lens models :func:`lens_camera` builds
LENS_CAMERAS = ("plumb_bob", "rational", "thin_prism", "tilted", "fisheye")


def scheimpflug_focal_plane(tau_x: float, tau_y: float, f_mm: float, u_mm: float) -> LightPlane:
    """The plane in focus (thin lens of focal length ``f_mm`` focused at ``u_mm`` on the axis) when the sensor
    is tilted by OpenCV's ``tauX``, ``tauY`` (radians): the Scheimpflug condition.

    The sensor plane (normal ``n_s``: the third row of OpenCV's sensor rotation ``Ry(tauY) Rx(tauX)``,
    the sensor's z axis in the camera frame) at the image distance ``v = 1 / (1/f - 1/u)``, the lens
    plane z = 0 and the plane in focus meet in one line; the plane in focus passes through
    ``(0, 0, u)``, so its normal is ``(n_sx, n_sy, -n_sz v / u)``.
    """
    v = 1.0 / (1.0 / f_mm - 1.0 / u_mm)
    ns = np.array([np.sin(tau_y), -np.cos(tau_y) * np.sin(tau_x), np.cos(tau_y) * np.cos(tau_x)])
    n = np.array([ns[0], ns[1], -ns[2] * v / u_mm])
    n /= np.linalg.norm(n)
    return LightPlane(n, -float(n[2] * u_mm), meta={"source": "lightplane.simulate.scene.scheimpflug_focal_plane"})


def scheimpflug_camera(plane: LightPlane | None = None, *, f_mm: float = 16.0, pixel_mm: float = 0.00375,
                       dist=(-0.08, 0.12, 4e-4, -3e-4, 0.0)) -> Camera:
    """A Scheimpflug laser sensor: the default camera's lens (``f_mm``, ``pixel_mm``, principal point,
    plumb-bob ``dist``) with its sensor tilted (OpenCV's tilted model, tauX, tauY) so that the plane in
    focus (:func:`scheimpflug_focal_plane`) is ``plane`` (default :func:`default_plane`: a 4.52° tilt
    about the y axis).  The renderer has no depth-dependent blur, so "in focus" is the geometry only.
    """
    plane = default_plane() if plane is None else plane
    n = np.asarray(plane.normal, float)
    if abs(n[2]) < 1e-9:
        raise LightplaneError("scheimpflug_camera: the plane must cross the optical axis")
    u = -float(plane.d) / n[2]
    if not u > f_mm:
        raise LightplaneError(f"scheimpflug_camera: the plane crosses the axis at {u:.1f} mm, not beyond the lens")
    v = 1.0 / (1.0 / f_mm - 1.0 / u)
    ns = np.array([n[0], n[1], -n[2] * u / v])
    ns *= np.sign(ns[2]) / np.linalg.norm(ns)
    tau_y = float(np.arcsin(ns[0]))
    tau_x = float(np.arctan2(-ns[1], ns[2]))
    f_px = f_mm / pixel_mm
    K = np.array([[f_px, 0.0, 652.3], [0.0, f_px, 471.8], [0.0, 0.0, 1.0]])
    d = np.concatenate([np.asarray(dist, float).ravel()[:5], np.zeros(7), [tau_x, tau_y]])
    return Camera(K, d, 1280, 960, model="tilted",
                  meta={"source": "lightplane.simulate.scene.scheimpflug_camera", "f_mm": f_mm, "focus_mm": u})


def lens_camera(model: str) -> Camera:
    """A 1280x960 camera (3.75 µm pixels) with each lens model (:data:`LENS_CAMERAS`):

    - ``plumb_bob``: :func:`default_camera`;
    - ``rational``: a wide 6 mm lens (``fx = fy = 1600 px``, 44° x 33° field), barrel distortion of
      ~64 px at the corners: ``(k1..k3, k4..k6) = (-0.28, 0.09, -0.01; 0.06, 0.01, 0)``,
      tangential ``(2e-4, -1.5e-4)``;
    - ``thin_prism``: the default lens with thin-prism terms ``s1..s4 = (6e-3, -1e-3, -5e-3, 8e-4)``
      (~1 px at the corners) and the rational terms ``(k4, k5) = (0.02, 0.005)``;
    - ``tilted``: :func:`scheimpflug_camera` (sensor tilted 4.52°, the default light plane in focus);
    - ``fisheye``: a 2.6 mm equidistant lens (``fx = fy = 693.3 px``, ±62° across the width),
      ``(k1..k4) = (0.04, -0.01, 0.002, -3e-4)``.
    """
    src = {"source": f"lightplane.simulate.scene.lens_camera({model!r})"}
    c = default_camera()
    if model == "plumb_bob":
        return c
    if model == "rational":
        f = 6.0 / 0.00375
        K = np.array([[f, 0.0, 645.2], [0.0, f, 476.9], [0.0, 0.0, 1.0]])
        return Camera(K, np.array([-0.28, 0.09, 2e-4, -1.5e-4, -0.01, 0.06, 0.01, 0.0]), 1280, 960, meta=src)
    if model == "thin_prism":
        d = np.concatenate([c.dist, [0.02, 0.005, 0.0], [6e-3, -1e-3, -5e-3, 8e-4]])
        return Camera(c.K, d, 1280, 960, meta=src)
    if model == "tilted":
        return scheimpflug_camera()
    if model == "fisheye":
        f = 2.6 / 0.00375
        K = np.array([[f, 0.0, 641.7], [0.0, f, 478.4], [0.0, 0.0, 1.0]])
        return Camera(K, np.array([0.04, -0.01, 0.002, -3e-4]), 1280, 960, model="fisheye", meta=src)
    raise LightplaneError(f"lens_camera: unknown model {model!r} ({', '.join(LENS_CAMERAS)})")


def paper_camera() -> Camera:
    """The camera of the paper's simulation (§3): f = 25 mm.

    The paper gives only the focal length.  We choose 5 µm pixels
    (``fx = fy = 25 / 0.005 = 5000 px``), a 2048x1536 sensor with the principal point
    at its centre (1023.5, 767.5) px, and no distortion.  With the paper's plane the
    stripe is then a roughly horizontal line, in view for depths ~290–640 mm; see
    :data:`PAPER_DISTANCE_MM` for the placement distances used with it.
    """
    f_px = 25.0 / 0.005
    K = np.array([[f_px, 0.0, 1023.5], [0.0, f_px, 767.5], [0.0, 0.0, 1.0]])
    return Camera(K, np.zeros(5), 2048, 1536, meta={"source": "lightplane.simulate.scene.paper_camera"})


def paper_plane() -> LightPlane:
    """The paper's simulated light plane ``0.9336 y - 0.3584 z + 140.04 = 0`` (§3).

    Stored with ``d < 0`` (docs/conventions.md §Light plane), i.e. ``-0.9336 y + 0.3584 z - 140.04 = 0``
    (the coefficients' norm is 1.0000 to 4 digits; it is normalised exactly).
    It crosses the optical axis at z = 390.7 mm; the laser is 150 mm above the camera.
    """
    return LightPlane(np.array([0.0, 0.9336, -0.3584]), 140.04, meta={"source": "lightplane.simulate.scene.paper_plane"})


def _unit(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def _perpendicular_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors ``e1, e2`` with ``(e1, e2, n)`` right-handed orthonormal."""
    ref = np.zeros(3)
    ref[int(np.argmin(np.abs(n)))] = 1.0
    e1 = _unit(np.cross(ref, n))
    e2 = np.cross(n, e1)
    return e1, e2


@dataclass(frozen=True, eq=False)
class TargetPlacement:
    """A flat circular disc in the camera frame (ground truth of one placement).

    Attributes
    ----------
    center : (3,) float64, mm, camera frame.
    normal : (3,) float64, unit, oriented towards the camera (``normal · center < 0``).
    diameter_mm : float, > 0.
    """

    center: np.ndarray
    normal: np.ndarray
    diameter_mm: float

    def __post_init__(self) -> None:
        c = np.asarray(self.center, dtype=np.float64).ravel()
        n = np.asarray(self.normal, dtype=np.float64).ravel()
        if c.shape != (3,) or n.shape != (3,) or not (np.all(np.isfinite(c)) and np.all(np.isfinite(n))):
            raise LightplaneError("TargetPlacement: center and normal must be 3 finite numbers each")
        if not (np.isfinite(self.diameter_mm) and self.diameter_mm > 0):
            raise LightplaneError(f"TargetPlacement: diameter_mm must be positive, got {self.diameter_mm}")
        nn = np.linalg.norm(n)
        if nn < 1e-12:
            raise LightplaneError("TargetPlacement: normal must not be zero")
        n = n / nn
        if n @ c > 0:
            n = -n  # docs/conventions.md §Target pose: towards the camera
        c.setflags(write=False)
        n.setflags(write=False)
        object.__setattr__(self, "center", c)
        object.__setattr__(self, "normal", n)
        object.__setattr__(self, "diameter_mm", float(self.diameter_mm))

    @property
    def radius_mm(self) -> float:
        return 0.5 * self.diameter_mm

    def basis(self) -> np.ndarray:
        """``(3, 3)`` rotation whose columns are in-plane axes ``e1, e2`` and the normal.

        Right-handed (``e1 × e2 = normal``); it is ``R_cam_target``: target-frame points
        ``(x, y, 0)`` map to ``center + R @ (x, y, 0)``.
        """
        e1, e2 = _perpendicular_basis(self.normal)
        return np.column_stack([e1, e2, self.normal])

    def rim_points(self, n: int) -> np.ndarray:
        """``(n, 3)`` points evenly spaced on the rim (camera frame, mm)."""
        if int(n) < 1:
            raise LightplaneError(f"rim_points: n must be >= 1, got {n}")
        t = 2.0 * np.pi * np.arange(int(n)) / int(n)
        R = self.basis()
        return self.center + self.radius_mm * (np.outer(np.cos(t), R[:, 0]) + np.outer(np.sin(t), R[:, 1]))

    def chord(self, plane: LightPlane) -> np.ndarray | None:
        """``(2, 3)`` endpoints (mm) of the light plane's intersection with the disc, or None.

        None when the planes are (nearly) parallel or the line misses the disc.
        """
        n, d = plane.normal, plane.d
        R = self.basis()
        g = np.array([n @ R[:, 0], n @ R[:, 1]])  # light-plane normal seen in target coordinates
        gn = float(np.hypot(*g))
        if gn < 1e-12:
            return None
        s = float(n @ self.center + d)  # the line is {p : g·p = -s} in target coordinates
        h = abs(s) / gn
        r = self.radius_mm
        if h >= r:
            return None
        foot2 = -s * g / gn**2
        direction2 = np.array([-g[1], g[0]]) / gn
        half = np.sqrt(r * r - h * h)
        ends2 = np.stack([foot2 - half * direction2, foot2 + half * direction2])
        return self.center + ends2 @ R[:, :2].T

    def homography(self, camera: Camera) -> np.ndarray:
        """``(3, 3)`` homography target ``(x, y, 1)`` (mm) -> undistorted pixels: ``K [e1 e2 C]``."""
        R = self.basis()
        return camera.K @ np.column_stack([R[:, 0], R[:, 1], self.center])

    def conic(self, camera: Camera) -> np.ndarray:
        """The rim's image conic ``C`` (3, 3) in UNDISTORTED pixels.

        ``[u, v, 1] C [u, v, 1]ᵀ = 0`` on the rim; symmetric, Frobenius norm 1, sign
        such that the inside of the ellipse is negative.  ``C = H⁻ᵀ diag(1, 1, -r²) H⁻¹``
        with ``H`` the target-to-image homography.
        """
        Hinv = np.linalg.inv(self.homography(camera))
        r = self.radius_mm
        C = Hinv.T @ np.diag([1.0, 1.0, -r * r]) @ Hinv
        C = 0.5 * (C + C.T)
        return C / np.linalg.norm(C)


@dataclass(frozen=True)
class PlacementOptions:
    """The design of random disc placements (:func:`sample_placements`).

    ``diameter_mm``: the disc; ``distance_mm``: the range of the centres' distances;
    ``tilt_deg``: the range of the disc normal's angle to the line of sight; ``min_chord_frac``:
    the stripe's shortest chord across the disc, as a fraction of the diameter; ``margin_px``:
    the rim stays this far inside the image; ``max_tries``: draws before giving up.
    """

    diameter_mm: float = 50.0
    distance_mm: tuple[float, float] = (380.0, 520.0)
    tilt_deg: tuple[float, float] = (15.0, 55.0)
    min_chord_frac: float = 0.4
    margin_px: float = 20.0
    max_tries: int = 100000

    def __post_init__(self) -> None:
        if not (self.diameter_mm > 0):
            raise LightplaneError(f"diameter_mm must be positive, got {self.diameter_mm}")
        if not (0.0 <= self.min_chord_frac < 1.0):
            raise LightplaneError(f"min_chord_frac must be in [0, 1), got {self.min_chord_frac}")


def _draw_placement(rng: np.random.Generator, camera: Camera, plane: LightPlane,
                    options: PlacementOptions) -> TargetPlacement | None:
    """One drawn placement, or None when the draw is rejected (see :func:`sample_placements`)."""
    lo, hi = float(options.distance_mm[0]), float(options.distance_mm[1])
    t_lo, t_hi = np.deg2rad(options.tilt_deg[0]), np.deg2rad(options.tilt_deg[1])
    diameter_mm, margin_px = options.diameter_mm, options.margin_px
    h_max = 0.5 * diameter_mm * np.sqrt(1.0 - options.min_chord_frac**2)
    # a point of the light plane seen somewhere in the image, at an admissible distance
    uv = rng.uniform([margin_px, margin_px], [camera.width - 1 - margin_px, camera.height - 1 - margin_px])
    ray = camera.rays(uv[None, :])[0]
    den = plane.normal @ ray
    if abs(den) < 1e-9:
        return None
    s = -plane.d / den
    if s <= 0:
        return None
    P = s * ray
    if not (lo <= np.linalg.norm(P) <= hi):
        return None
    # disc normal: the line of sight towards the camera, tilted
    view = -_unit(P)
    a1, a2 = _perpendicular_basis(view)
    phi = rng.uniform(0.0, 2.0 * np.pi)
    axis = np.cos(phi) * a1 + np.sin(phi) * a2
    tilt = rng.uniform(t_lo, t_hi)
    # Rodrigues' rotation of `view` about `axis` (axis ⟂ view)
    N = np.cos(tilt) * view + np.sin(tilt) * np.cross(axis, view)
    # shift the centre within the disc plane, perpendicular to the stripe line
    line_dir = np.cross(N, plane.normal)
    if np.linalg.norm(line_dir) < 1e-6:
        return None
    across = _unit(np.cross(N, line_dir))
    C = P + rng.uniform(-h_max, h_max) * across
    if not (lo <= np.linalg.norm(C) <= hi):
        return None
    # re-tilt from the line of sight to the final centre (same axis angle and tilt),
    # so that the tilt is exactly the angle between normal and line of sight
    view = -_unit(C)
    a1, a2 = _perpendicular_basis(view)
    axis = np.cos(phi) * a1 + np.sin(phi) * a2
    N = np.cos(tilt) * view + np.sin(tilt) * np.cross(axis, view)
    try:
        tp = TargetPlacement(C, N, diameter_mm)
    except LightplaneError:
        return None
    chord = tp.chord(plane)
    if chord is None or np.linalg.norm(chord[1] - chord[0]) < options.min_chord_frac * diameter_mm:
        return None
    rim = tp.rim_points(72)
    if np.any(rim[:, 2] <= 0):
        return None
    uv_rim = camera.project(rim)
    if not np.all(np.isfinite(uv_rim)) or not np.all(camera.in_image(uv_rim, margin=margin_px)):
        return None
    return tp


def sample_placements(n: int, rng: np.random.Generator, options: PlacementOptions = PlacementOptions(), *,
                      camera: Camera | None = None, plane: LightPlane | None = None) -> list[TargetPlacement]:
    """Draw ``n`` random disc placements that satisfy docs/conventions.md §Default sensor.

    Each placement (``options``: :class:`PlacementOptions`): a point P on the light plane, seen
    in the image, at a distance in ``distance_mm``; the disc centre C shifted from P within the
    disc plane, perpendicular to the stripe, by up to ``r sqrt(1 - min_chord_frac²)``; the disc
    normal is the line of sight from C towards the camera tilted by an angle
    uniform in ``tilt_deg`` about a uniformly random axis perpendicular to it.  The
    chord is then checked to be at least ``min_chord_frac`` of the diameter.  Rejected and redrawn unless the centre's
    distance is in range and all rim points project inside the image with
    ``margin_px`` to spare.  Defaults: :func:`default_camera`, :func:`default_plane`.

    Returns a list of :class:`TargetPlacement`; raises LightplaneError if the
    constraints cannot be met within ``max_tries`` draws.
    """
    camera = default_camera() if camera is None else camera
    plane = default_plane() if plane is None else plane
    if int(n) < 0:
        raise LightplaneError(f"n must be >= 0, got {n}")
    out: list[TargetPlacement] = []
    tries = 0
    while len(out) < int(n):
        tries += 1
        if tries > options.max_tries:
            raise LightplaneError(
                f"sample_placements: could not place {n} discs within {options.max_tries} draws "
                f"(distance {options.distance_mm} mm, tilt {options.tilt_deg} deg, diameter {options.diameter_mm} mm): "
                "is the light plane in view at those distances?"
            )
        tp = _draw_placement(rng, camera, plane, options)
        if tp is not None:
            out.append(tp)
    return out


def synthetic_observations(
    camera: Camera,
    plane: LightPlane,
    placement: TargetPlacement,
    *,
    n_rim: int = 200,
    n_stripe: int = 300,
    sigma_px: float = 0.0,
    rng: np.random.Generator | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Noisy distorted pixel observations of one placement.

    Returns ``(rim_uv (n_rim, 2), stripe_uv (n_stripe, 2))``: rim points evenly spaced
    on the rim, stripe points evenly spaced along the chord (at ``(k + 0.5) / n_stripe``
    of its length, so none lies exactly on the rim), projected with distortion, plus
    isotropic Gaussian noise of ``sigma_px`` (px) on both.  Raises LightplaneError
    if the light plane misses the disc, or if noise is requested without an ``rng``.
    """
    if sigma_px < 0 or not np.isfinite(sigma_px):
        raise LightplaneError(f"sigma_px must be >= 0, got {sigma_px}")
    if sigma_px > 0 and rng is None:
        raise LightplaneError("synthetic_observations: sigma_px > 0 needs an rng")
    chord = placement.chord(plane)
    if chord is None:
        raise LightplaneError("synthetic_observations: the light plane does not cross the disc")
    rim_uv = camera.project(placement.rim_points(n_rim))
    t = (np.arange(int(n_stripe)) + 0.5) / int(n_stripe)
    stripe_p = chord[0] + t[:, None] * (chord[1] - chord[0])
    stripe_uv = camera.project(stripe_p)
    if sigma_px > 0:
        assert rng is not None  # checked above
        rim_uv = rim_uv + rng.normal(0.0, sigma_px, rim_uv.shape)
        stripe_uv = stripe_uv + rng.normal(0.0, sigma_px, stripe_uv.shape)
    return rim_uv, stripe_uv
