"""Measurement: pixels to 3D points on the light plane (docs/method.md §Triangulation, paper Eq. 2 and 4).

pixel → undistorted normalised ``(x, y)`` → ray ``X = s (x, y, 1)`` → on the
plane ``s = -d / (a x + b y + c)``.  Rays nearly parallel to the plane give NaN
(flagged), never huge numbers.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass, field, replace

import numpy as np

from lightplane.camera.model import Camera, as_points
from lightplane.core.errors import LightplaneError
from lightplane.plane.model import LightPlane
from lightplane.plane.triangulate import points_sigma_mm, profile_axis, triangulate_normalized
from lightplane.measure._kernels import DONE, NOT_BUILT, OFF_GRID, hermite_lookup, median_where
from lightplane.plane.uncertainty import camera_share_status, point_error_basis
from lightplane.measure.options import MAX_WIDTH_RATIO, MIN_WIDTH_RATIO, MeasureOptions
from lightplane.stripe.extract import (channel_image, check_roi, extract_profile, extract_profiles, on_even_reflectance,
                                       sigma_for_width)

#: fewer valid lines than this in a frame: no width filter (the median would mean little)
WIDTH_FILTER_MIN_LINES = 20
#: a frame shows a stripe when some run of consecutive lines with a centre is this long (or half the roi's
#: lines, when fewer) ...
STRIPE_MIN_RUN = 20
#: ... and at least this many times the stripe's width (the median FWHM of the frame's centres)
STRIPE_MIN_ELONGATION = 5.0
#: a point whose pixel the camera model does not give back (px) is outside the model's field (past the
#: fold of its distortion)
ROUND_TRIP_PX = 0.05
#: the grid (px) on which a measurer checks once that the camera model is one-to-one over its roi
ROUND_TRIP_GRID_PX = 8
#: why points are dropped (:attr:`Profile.dropped`), in this order
DROP_REASONS = ("no stripe", "outside the camera model", "outside the working volume", "sigma beyond the bound",
                "on uneven reflectance")


# ======================================================================================
# Profiles: one stripe centre per image column (row) -> 3D points with uncertainty

__all__ = ["Profile", "ProfileMeasurer", "measure_profile", "profile_cache_info", "clear_profile_cache",
           "has_stripe", "working_depth", "DROP_REASONS"]

@dataclass(frozen=True)
class Profile:
    """One measured stripe profile: 3D points of one frame.

    One entry per image column (``axis="columns"``) or row of the roi:

    - ``points`` (N, 3) float64 mm, camera frame; NaN where not ``valid``;
    - ``sigma_mm`` (N,) σ of each point (camera frame) from the plane's covariance and,
      when the camera file has a covariance and the plane file its dependence on the
      intrinsics, the camera's share (:func:`lightplane.plane.uncertainty.point_error_basis`;
      ``ProfileMeasurer.camera_share_missing`` says why not otherwise); NaN when the
      plane has no covariance;
    - ``uv`` (N, 2) float64 distorted source pixels of the stripe centres;
    - ``valid`` (N,) bool: a stripe centre was found and its ray meets the plane;
    - ``intensity`` (N,) smoothed image value at the stripe's peak (grey levels);
    - ``width_px`` (N,) stripe width (FWHM, px) across the stripe;
    - ``axis`` ``"columns"`` or ``"rows"``;
    - ``width_rejected`` (N,) bool: a stripe centre was found and triangulated but
      dropped by the width filter (``min_width_ratio`` / ``max_width_ratio`` of
      :class:`~lightplane.measure.options.MeasureOptions`); None when the profile did not go through it;
    - ``line_width_px`` (N,) the stripe width each line was measured at where some lines were measured
      at their own (wider) width (``StripeOptions.local_width``), else None: the width filter compares a
      width with the widths measured at the same scale;
    - ``dropped``: reason (:data:`DROP_REASONS`) → how many triangulated points the screen dropped
      (a frame without a stripe, points outside the working volume or with a σ beyond the bound:
      :class:`ProfileMeasurer`).
    """

    points: np.ndarray
    sigma_mm: np.ndarray
    uv: np.ndarray
    valid: np.ndarray
    intensity: np.ndarray
    width_px: np.ndarray
    axis: str
    width_rejected: np.ndarray | None = None
    dropped: dict = field(default_factory=dict)
    line_width_px: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_valid(self) -> int:
        return int(np.count_nonzero(self.valid))


class ProfileMeasurer:
    """Stripe images → :class:`Profile`, with the per-camera work done once.

    Each frame: :func:`lightplane.stripe.extract.extract_profile` (one sub-pixel centre per
    column or row), then pixel → undistorted normalised ray → light plane (docs/method.md §Triangulation,
    paper Eq. 2 and 4), and σ from the plane's covariance.

    With ``lookup=True`` (default) the exact undistortion (``Camera.undistort_points``)
    of every pixel of the roi is computed once, with its derivative along the profile
    direction (inverse of the distortion's Jacobian, docs/conventions.md §Lens model).  A centre at sub-pixel
    position ``t`` along its column (row) then costs a cubic Hermite interpolation
    between the two bracketing pixels (error O(h⁴): below 1e-9 px for the default
    sensor's distortion), instead of an iterative undistortion per point.
    Tables: 24 bytes per roi pixel (30 MB for 1280x960 when complete), filled in blocks of
    32 lines x 64 samples as the frames' centres first need them (a stripe across a
    1280x960 frame: ~35 of the 600 blocks, ~20 ms), or all at once by :meth:`build_lookup`;
    a block's values do not depend on when it is built, so the numbers are the same
    either way, bit for bit.  Not pickled (each worker process builds its own).
    ``lookup=False`` undistorts the centres exactly per frame.

    Parameters
    ----------
    camera, plane : the calibration.
    options : :class:`~lightplane.measure.options.MeasureOptions`: the stripe's options, the
        profile axis and region, the smoothing of the centres, the grazing-ray limit, the
        width filter (below).
    lookup : the undistortion lookup tables (above) or the exact undistortion per frame.

    The width filter (``options.min_width_ratio``, ``options.max_width_ratio``), a per-point
    quality filter on the stripe's width (FWHM across the stripe, px).  A point whose width is below ``min_width_ratio``
    or above ``max_width_ratio`` times the frame's typical width (median over its
    valid lines, at least :data:`WIDTH_FILTER_MIN_LINES` of them) is dropped
    (``valid`` False, ``width_rejected`` True).  Why: the light sheet has a
    Gaussian thickness (σ = 0.2 mm in the renders), and its footprint is seen
    foreshortened by cos(view angle).  A stripe much narrower than the frame's
    typical one is a surface seen nearly edge-on (near a curved object's
    silhouette); there the footprint's projection is compressed unevenly across
    the stripe, so the intensity centre is not the sheet's mid-plane crossing and
    the point lands inside the surface (clean rendered sphere, R 25.4 mm, true
    plane, a σ 0.35 mm sheet — the bias grows as σ², ~3x smaller at 0.2 mm:
    mean residual +0.004 mm for view angles < 60°, -0.015 mm at 60–70°,
    -0.023 at 70–80°, -0.042 beyond 80°, where widths are 0.9, 0.8 and 0.7 × the
    frame median).  A stripe much wider than typical is a surface nearly parallel
    to the sheet, where the thickness is smeared across the surface.  Defaults
    (0.8, 2.0) chosen on the rendered sphere / step / plane scans
    (``benchmarks/bench_measure.py accuracy``); ``0`` and ``inf`` switch the
    filter off.  No correction of the bias from the width is applied: the bias
    depends on the local curvature and view angle together, which one width does
    not determine.  Not caught: frames where the sheet meets a curved surface
    at a low angle everywhere (the sphere's ends along the scan: stripe ~12 px
    against ~7 px, points ~0.03 mm outside), since the reference is the frame's
    own median; with them the clean sphere's fitted radius was still ~0.018 mm low
    with the 0.35 mm sheet (~0.006 mm with 0.2 mm).
    """

    def __init__(self, camera: Camera, plane: LightPlane, options: MeasureOptions = MeasureOptions(), *,
                 lookup: bool = True) -> None:
        if not isinstance(camera, Camera):
            raise LightplaneError(f"camera must be a Camera, got {type(camera).__name__}")
        if not isinstance(plane, LightPlane):
            raise LightplaneError(f"plane must be a LightPlane, got {type(plane).__name__}")
        if not isinstance(options, MeasureOptions):
            raise LightplaneError(f"options must be a MeasureOptions, got {type(options).__name__}")
        self.camera = camera
        self.plane = plane
        self.options = options
        self.axis = profile_axis(plane) if options.axis == "auto" else options.axis
        self.roi = check_roi(options.roi, camera.width, camera.height, min_size=3)
        self.min_ray_cos = float(options.min_ray_cos)
        self.smooth_lines = int(options.smooth_lines)
        self.min_width_ratio, self.max_width_ratio = float(options.min_width_ratio), float(options.max_width_ratio)
        self.stripe = options.stripe

        #: None when the points' sigma includes the camera's share, else why not (one sentence)
        self.camera_share_missing = camera_share_status(camera, plane)
        #: the working volume's depth range (mm; None: no limit) and the σ bound (mm; None: none)
        self.depth_range: tuple[float, float] | None = None
        self.sigma_bound: float | None = None
        self._lookup = bool(lookup)
        # lookup tables (xy, d xy / d sample per roi pixel) and which blocks of them are built
        self._xy: np.ndarray | None = None
        self._dxy: np.ndarray | None = None
        self._built: np.ndarray | None = None
        #: how many table blocks this measurer has built (a diagnostic: repeated frames build none)
        self.blocks_built = 0
        self._lock = threading.Lock()
        self._screen_limits()

    # ---------------------------------------------------------------- the screen
    def _screen_limits(self) -> None:
        """The depth range and σ bound of :meth:`screen` from the plane's working volume, and whether
        the camera's model is one-to-one over the whole roi (:meth:`_round_trip_everywhere`)."""
        self.round_trip_everywhere = self._round_trip_everywhere()
        depth, centre = working_depth(self.plane)
        k = float(self.options.depth_factor)
        if depth is not None and np.isfinite(k):
            self.depth_range = (depth[0] / k, depth[1] * k)
        if centre is not None and np.isfinite(self.options.max_sigma_ratio) and self.plane.covariance is not None:
            uv = self.camera.project(centre[None, :])
            s = float(self.from_stripe(uv, np.ones(1, bool)).sigma_mm[0]) if np.all(np.isfinite(uv)) else np.nan
            if np.isfinite(s) and s > 0:
                self.sigma_bound = float(self.options.max_sigma_ratio) * s

    def _round_trip_everywhere(self) -> bool:
        """Whether every pixel of the roi comes back onto itself through the undistortion and the
        projection, with room to spare: checked once on a grid of every :data:`ROUND_TRIP_GRID_PX`-th
        pixel and every pixel of the roi's border (the largest radii, where a lens model folds), each
        within a fifth of :data:`ROUND_TRIP_PX`.  Then :meth:`screen` need not project every frame's
        points back (the error is a smooth function of the pixel); else it does."""
        x, y, w, h = self.roi
        us, vs = np.arange(x, x + w, dtype=float), np.arange(y, y + h, dtype=float)
        gu, gv = np.meshgrid(us[::ROUND_TRIP_GRID_PX], vs[::ROUND_TRIP_GRID_PX])
        uv = np.concatenate([np.column_stack([gu.ravel(), gv.ravel()]),
                             np.column_stack([us, np.full_like(us, vs[0])]),
                             np.column_stack([us, np.full_like(us, vs[-1])]),
                             np.column_stack([np.full_like(vs, us[0]), vs]),
                             np.column_stack([np.full_like(vs, us[-1]), vs])])
        with np.errstate(invalid="ignore", over="ignore"):
            xy = self.camera.undistort_points(uv, normalized=True)
            back = self.camera.project(np.column_stack([xy, np.ones(len(xy))]))
            err = np.linalg.norm(back - uv, axis=1)
        return bool(np.all(err < 0.2 * ROUND_TRIP_PX))

    def screen(self, prof: Profile) -> Profile:
        """Drop what is not a measured point, counting why (:attr:`Profile.dropped`).

        - **no stripe**: the frame's centres form no line (:func:`has_stripe`): every point goes
          (``options.stripe_evidence``);
        - **outside the camera model**: the camera does not project the point back onto its pixel
          within :data:`ROUND_TRIP_PX` (the pixel lies past the fold of the lens model's distortion,
          where the undistortion has no answer);
        - **outside the working volume**: depth outside the plane's calibrated depth range divided and
          multiplied by ``options.depth_factor`` (:func:`working_depth`);
        - **sigma beyond the bound**: σ over ``options.max_sigma_ratio`` times the σ of a point at the
          centre of the plane's calibration.

        The last three only without ``options.keep_outliers``.
        """
        valid = np.asarray(prof.valid, bool)
        if not valid.any():
            return prof
        bad = np.zeros(len(valid), np.int8)  # 0 kept, else 1 + the index of the reason
        if self.options.stripe_evidence and not has_stripe(valid, prof.width_px):
            bad[valid] = 1
        elif not self.options.keep_outliers:
            idx = np.flatnonzero(valid)
            p = prof.points[idx]
            with np.errstate(invalid="ignore"):
                off = np.zeros(len(idx), bool) if self.round_trip_everywhere else \
                    np.linalg.norm(self.camera.project(p) - prof.uv[idx], axis=1) > ROUND_TRIP_PX
                far = np.zeros(len(idx), bool) if self.depth_range is None else \
                    (p[:, 2] < self.depth_range[0]) | (p[:, 2] > self.depth_range[1])
                wide = np.zeros(len(idx), bool) if self.sigma_bound is None else prof.sigma_mm[idx] > self.sigma_bound
            bad[idx] = np.select([off, far, wide], [2, 3, 4], 0)
        if not bad.any():
            return prof
        drop = bad > 0
        pts, sig = prof.points.copy(), prof.sigma_mm.copy()
        pts[drop], sig[drop] = np.nan, np.nan
        counts = {DROP_REASONS[k - 1]: int(np.count_nonzero(bad == k)) for k in range(1, 5) if np.any(bad == k)}
        return replace(prof, points=pts, sigma_mm=sig, valid=valid & ~drop, dropped=counts)

    # ---------------------------------------------------------------- lookup tables
    #: the tables are built in blocks of this many lines x samples, when a centre first needs one
    BLOCK_LINES, BLOCK_SAMPLES = 32, 64

    @property
    def has_lookup(self) -> bool:
        """Whether the lookup tables are in use (some block built; never with ``lookup=False``)."""
        return self._built is not None and bool(self._built.any())

    @property
    def lookup_complete(self) -> bool:
        """Whether every block of the lookup tables is built (:meth:`build_lookup`)."""
        return self._built is not None and bool(self._built.all())

    def build_lookup(self) -> None:
        """Build all the lookup tables now (otherwise block by block as centres need them).  Thread-safe."""
        if not self._lookup:
            return
        _, _, built = self._alloc_tables()
        nlb, nsb = built.shape
        for lb in range(nlb):  # one row of blocks at a time: the undistortion's temporaries stay small
            self._ensure_blocks(np.full(nsb, lb), np.arange(nsb))

    def __getstate__(self) -> dict:
        # sent to worker processes without the tables (30 MB) or the lock: each builds its own
        state = self.__dict__.copy()
        state["_xy"] = state["_dxy"] = state["_built"] = None
        del state["_lock"]
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()

    def _line_grid(self) -> tuple[np.ndarray, np.ndarray]:
        """Line indices (image column or row numbers) and sample coordinates of the roi."""
        x, y, w, h = self.roi
        if self.axis == "columns":
            return np.arange(x, x + w), np.arange(y, y + h)
        return np.arange(y, y + h), np.arange(x, x + w)

    def _alloc_tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The (uninitialised) table arrays and the map of built blocks; pages are touched only when filled."""
        if self._built is None:
            with self._lock:
                if self._built is None:
                    lines, samples = self._line_grid()
                    L, S = lines.size, samples.size
                    self._xy = np.empty((L, S, 2))
                    self._dxy = np.empty((L, S, 2), np.float32)
                    self._built = np.zeros((-(-L // self.BLOCK_LINES), -(-S // self.BLOCK_SAMPLES)), bool)
        # the map of built blocks is set last: once it exists, so do the tables
        assert self._xy is not None and self._dxy is not None and self._built is not None
        return self._xy, self._dxy, self._built

    def _ensure_blocks(self, lb: np.ndarray, sb: np.ndarray) -> None:
        """Build the blocks ``(lb[i], sb[i])`` not built yet (one undistortion call for all of them)."""
        _, _, built = self._alloc_tables()
        need = ~built[lb, sb]
        if not need.any():
            return
        with self._lock:
            todo = np.unique(np.ravel_multi_index((lb[need], sb[need]), built.shape))
            todo = todo[~built.ravel()[todo]]  # another thread may have built some meanwhile
            if todo.size:
                self._build_blocks(*np.unravel_index(todo, built.shape))

    def _build_blocks(self, lbs: np.ndarray, sbs: np.ndarray) -> None:
        """Fill the table blocks ``(lbs[i], sbs[i])``; the values do not depend on which blocks go together
        (the undistortion and the Jacobian are per point), so a lazily filled table equals a full build."""
        lines, samples = self._line_grid()
        BL, BS = self.BLOCK_LINES, self.BLOCK_SAMPLES
        # d(xy)/d(sample): xy_d = K^-1 uv is linear in the pixel, xy = distort^-1(xy_d)
        K = self.camera.K
        dxd = np.array([1.0 / K[0, 0], 0.0]) if self.axis == "rows" \
            else np.array([-K[0, 1] / (K[0, 0] * K[1, 1]), 1.0 / K[1, 1]])
        li_parts, si_parts = [], []
        for lb, sb in zip(lbs, sbs):
            l_idx = np.arange(lb * BL, min((lb + 1) * BL, lines.size))
            s_idx = np.arange(sb * BS, min((sb + 1) * BS, samples.size))
            ll, ss = np.meshgrid(l_idx, s_idx, indexing="ij")
            li_parts.append(ll.ravel())
            si_parts.append(ss.ravel())
        li, si = np.concatenate(li_parts), np.concatenate(si_parts)
        lv, sv = lines[li].astype(float), samples[si].astype(float)
        uv = np.column_stack([lv, sv]) if self.axis == "columns" else np.column_stack([sv, lv])
        xy = self.camera.undistort_points(uv, normalized=True)
        j11, j12, j21, j22 = self.camera.distortion_jacobian(xy)
        det = j11 * j22 - j12 * j21
        d = np.column_stack([(j22 * dxd[0] - j12 * dxd[1]) / det, (-j21 * dxd[0] + j11 * dxd[1]) / det])
        tab_xy, tab_dxy, built = self._alloc_tables()
        tab_xy[li, si] = xy
        tab_dxy[li, si] = d
        built[lbs, sbs] = True  # after the values: a reader that sees the flag sees them
        self.blocks_built += len(lbs)

    def normalized(self, uv: np.ndarray) -> np.ndarray:
        """Undistorted normalised ``(x, y)`` (N, 2) of stripe centres ``uv`` (N, 2) px.

        Centres must lie on the grid lines of the measurer's axis (``u`` an integer
        column for ``"columns"``, ``v`` an integer row for ``"rows"``) inside the roi,
        as :func:`extract_profile` returns them; NaN rows stay NaN.  Without lookup
        tables (or for points off the grid lines) the exact undistortion is used.
        """
        uv = as_points(uv, 2, "uv")
        if not self._lookup:
            return self.camera.undistort_points(uv, normalized=True)

        tab_xy, tab_dxy, built = self._alloc_tables()
        x, y = self.roi[:2]
        line0, sample0 = (x, y) if self.axis == "columns" else (y, x)
        li, si = (0, 1) if self.axis == "columns" else (1, 0)
        line = uv[:, li] - line0
        t = uv[:, si] - sample0
        out = np.empty(uv.shape)
        status = np.empty(len(uv), np.int8)
        hermite_lookup(tab_xy, tab_dxy, built, self.BLOCK_LINES, self.BLOCK_SAMPLES, line, t, out, status)
        todo = np.flatnonzero(status == NOT_BUILT)
        if todo.size:  # blocks first needed now: build them, then look these points up
            S = tab_xy.shape[1]
            lb = np.rint(line[todo]).astype(np.intp) // self.BLOCK_LINES
            i0 = np.clip(np.floor(t[todo]), 0, S - 2).astype(np.intp)
            self._ensure_blocks(np.concatenate([lb, lb]), np.concatenate([i0, i0 + 1]) // self.BLOCK_SAMPLES)
            sub_out, sub_status = np.empty((todo.size, 2)), np.empty(todo.size, np.int8)
            hermite_lookup(tab_xy, tab_dxy, built, self.BLOCK_LINES, self.BLOCK_SAMPLES, line[todo], t[todo],
                           sub_out, sub_status)
            assert np.all(sub_status == DONE)
            out[todo] = sub_out
            status[todo] = sub_status
        off = status == OFF_GRID
        if off.any():
            out[off] = self.camera.undistort_points(uv[off], normalized=True)
        return out

    # --------------------------------------------------------------------- measure
    def __call__(self, image: np.ndarray) -> Profile:
        """Measure one frame: ``image`` (H, W) or (H, W, 3), the camera's size.  A frame that carries
        its laser-off frame (``image.lit``: :class:`lightplane.measure.scan.LaserOnly`) has its
        centres on uneven reflectance dropped too (:meth:`reflectance_screen`)."""
        if not isinstance(image, np.ndarray):
            raise LightplaneError(f"image must be a numpy array, got {type(image).__name__}")
        lit, image = getattr(image, "lit", None), np.asarray(image)
        self.camera.check_image(image)
        x, y, w, h = self.roi
        roi = None if (w, h) == (self.camera.width, self.camera.height) else (x, y, w, h)
        sp = extract_profile(image, self.axis, self.stripe, roi=roi, parallel=self.options.parallel)
        uv = smooth_centres(sp.uv, sp.valid, self.axis, self.smooth_lines) if self.smooth_lines else sp.uv
        prof = self.from_stripe(uv, sp.valid, sp.intensity, sp.width, sp.line_width_px)
        prof = self.screen(width_filter(prof, self.min_width_ratio, self.max_width_ratio))
        return prof if lit is None else self.reflectance_screen(prof, lit, image, sp)

    def reflectance_screen(self, prof: Profile, lit: np.ndarray, image: np.ndarray, sp) -> Profile:
        """``prof`` without its points whose centre lies on uneven reflectance in the laser-off frame
        ``lit`` (:func:`lightplane.stripe.extract.on_even_reflectance`, the stripe's normals and width
        of ``sp``, the stripe options' channel), counted as "on uneven reflectance".  A printed or
        textured edge along the stripe moves its centre towards the lighter side."""
        lit = np.asarray(lit)
        if lit.shape != image.shape:
            raise LightplaneError(f"laser-off frame shape {lit.shape} differs from the frame's {image.shape}")
        idx = np.flatnonzero(prof.valid)
        if idx.size == 0:
            return prof
        level, fs = channel_image(lit, self.stripe.channel)
        w = float(sp.width_px) if np.isfinite(sp.width_px) else float(np.nanmedian(prof.width_px[idx]))
        even = on_even_reflectance(level, prof.uv[idx], np.asarray(sp.normals)[idx], w, sigma_for_width(w), fs)
        if even.all():
            return prof
        drop = idx[~even]
        pts, sig = prof.points.copy(), prof.sigma_mm.copy()
        pts[drop], sig[drop] = np.nan, np.nan
        valid = prof.valid.copy()
        valid[drop] = False
        return replace(prof, points=pts, sigma_mm=sig, valid=valid,
                       dropped={**prof.dropped, DROP_REASONS[4]: int(drop.size)})

    #: regions of interest with at most this many samples per line (rows for ``axis="columns"``) are
    #: profiled a batch of frames per call (:meth:`measure_many`): there the per-call costs dominate
    BATCH_MAX_SAMPLES = 128

    @property
    def batches(self) -> bool:
        """Whether :meth:`measure_many` profiles its frames in one call (a short roi of a given stripe
        width, the numba backend); the numbers are those of frame by frame either way."""
        x, y, w, h = self.roi
        samples = h if self.axis == "columns" else w
        return (samples <= self.BATCH_MAX_SAMPLES and self.stripe.width_px is not None
                and self.stripe.backend == "numba" and self.options.parallel is None)

    def measure_many(self, images) -> list[Profile]:
        """:meth:`__call__` of each image; for a short roi (:attr:`batches`) the stripe profiles of
        all of them come from one :func:`lightplane.stripe.extract.extract_profiles` call (identical numbers)."""
        images = list(images)
        if len(images) < 2 or not self.batches:
            return [self(im) for im in images]

        for im in images:
            if not isinstance(im, np.ndarray):
                raise LightplaneError(f"image must be a numpy array, got {type(im).__name__}")
            self.camera.check_image(im)
        x, y, w, h = self.roi
        roi = None if (w, h) == (self.camera.width, self.camera.height) else (x, y, w, h)
        out = []
        lits = [getattr(im, "lit", None) for im in images]
        images = [np.asarray(im) for im in images]
        for sp, lit, im in zip(extract_profiles(images, self.axis, self.stripe, roi=roi), lits, images):
            uv = smooth_centres(sp.uv, sp.valid, self.axis, self.smooth_lines) if self.smooth_lines else sp.uv
            prof = self.screen(width_filter(self.from_stripe(uv, sp.valid, sp.intensity, sp.width, sp.line_width_px),
                                            self.min_width_ratio, self.max_width_ratio))
            out.append(prof if lit is None else self.reflectance_screen(prof, lit, im, sp))
        return out

    def from_stripe(self, uv: np.ndarray, valid: np.ndarray, intensity: np.ndarray | None = None,
                    width_px: np.ndarray | None = None, line_width_px: np.ndarray | None = None) -> Profile:
        """Triangulate given stripe centres ``uv`` (N, 2) (NaN / ``valid`` False where none)."""
        uv = as_points(uv, 2, "uv")
        valid = np.asarray(valid, bool) & np.isfinite(uv[:, 0]) & np.isfinite(uv[:, 1])
        xy = self.normalized(np.where(valid[:, None], uv, np.nan))
        tri = triangulate_normalized(self.plane, xy, min_cos=self.min_ray_cos)
        ok = valid & tri.valid
        pts = tri.points
        pts[~ok] = np.nan
        if self.camera_share_missing is None and self.plane.covariance is not None and np.any(ok):
            sigma = np.full(len(uv), np.nan)
            E, _ = point_error_basis(self.camera, self.plane, uv[ok])
            sigma[ok] = np.sqrt(np.sum(E**2, axis=(1, 2)))
        else:
            sigma = points_sigma_mm(self.plane, xy)
        sigma[~ok] = np.nan
        n = len(uv)
        inten = np.full(n, np.nan) if intensity is None else np.asarray(intensity, float)
        width = np.full(n, np.nan) if width_px is None else np.asarray(width_px, float)
        return Profile(points=pts, sigma_mm=sigma, uv=uv, valid=ok, intensity=inten, width_px=width, axis=self.axis,
                       line_width_px=line_width_px)


def has_stripe(valid: np.ndarray, width_px: np.ndarray) -> bool:
    """Whether a frame's centres (``valid`` per line, their FWHM ``width_px``) form a stripe: some run of
    consecutive lines with a centre at least :data:`STRIPE_MIN_RUN` long (half the lines when there are
    fewer than twice that) and :data:`STRIPE_MIN_ELONGATION` times the median width.

    A laser line across a surface is continuous over many lines and much longer than it is wide;
    what a frame without a laser gives (the ridge of a chessboard's white square between two black
    ones, texture) is fragments about as long as they are wide.  Measured (longest run, median
    width): FabScan scans 205-460 lines / 10-14 px and the Ciclop laser frame 288 / 4.3 against
    chessboard frames without a laser (Ciclop captures and pattern, FabScan lit boards) 1-56 lines
    at 1.6-39 px (elongation <= 3.7 but for one 30-line straight edge), rendered chessboards <= 11
    lines at 55-80 px.
    """
    v = np.asarray(valid, bool)
    if not v.any():
        return False
    edges = np.flatnonzero(np.diff(np.concatenate([[0], v.view(np.int8), [0]])))
    longest = int(np.max(edges[1::2] - edges[::2]))
    w = np.asarray(width_px, float)[v]
    w = w[np.isfinite(w)]
    need = min(STRIPE_MIN_RUN, max(3, len(v) // 2))
    return longest >= need and (not len(w) or longest >= STRIPE_MIN_ELONGATION * float(np.median(w)))


def working_depth(plane: LightPlane) -> tuple[tuple[float, float] | None, np.ndarray | None]:
    """Where ``plane`` was calibrated: ``((near, far) depth mm, centre (3,) mm)``, camera frame.

    From the plane file's ``working_volume`` (written by the calibrations: their stripe points'
    depth range and centre), else the depth range of its placements (``images``: the boards' origins
    or the discs' centres) without a centre (they need not lie on the plane: no σ bound), else
    ``(None, None)`` (a plane from elsewhere: no depth limit, no σ bound).
    """
    wv = plane.meta.get("working_volume")
    if wv is not None:
        try:
            lo, hi = (float(x) for x in wv["depth_mm"])
            centre = np.asarray(wv["centre_mm"], np.float64).reshape(3)
        except (KeyError, TypeError, ValueError):
            raise LightplaneError("plane: field 'working_volume' must hold 'depth_mm' [near, far] and "
                                  "'centre_mm' [x, y, z]") from None
        if not (0 < lo <= hi and np.all(np.isfinite(centre))):
            raise LightplaneError(f"plane: field 'working_volume' needs 0 < near <= far, got {lo:g}, {hi:g}")
        return (lo, hi), centre
    pts = []
    for im in plane.meta.get("images") or []:
        if isinstance(im, dict) and im.get("used", im.get("status") == "used"):
            p = im.get("t_cam_board_mm") or (im.get("pose") or {}).get("center_mm")
            if p is not None and len(p) == 3 and float(p[2]) > 0:
                pts.append([float(x) for x in p])
    if not pts:
        return None, None
    z = np.asarray(pts)[:, 2]
    return (float(z.min()), float(z.max())), None


def width_filter(prof: Profile, min_ratio: float = MIN_WIDTH_RATIO, max_ratio: float = MAX_WIDTH_RATIO) -> Profile:
    """Drop points whose stripe width is outside ``[min_ratio, max_ratio]`` × the frame's median width.

    The median is over the valid points with a finite width; with fewer than
    :data:`WIDTH_FILTER_MIN_LINES` of them nothing is dropped.  Lines measured at their own width
    (``prof.line_width_px``) are compared with the median of the lines measured at the same width
    (or, with fewer than :data:`WIDTH_FILTER_MIN_LINES` of those, with that width).  Returns a new
    :class:`Profile` (``valid`` False, ``points``/``sigma_mm`` NaN and
    ``width_rejected`` True for the dropped points).  See :class:`ProfileMeasurer`.
    """
    w = np.asarray(prof.width_px, float)
    valid = np.asarray(prof.valid, bool)
    rej = np.zeros(len(prof), bool)
    if (min_ratio > 0 or np.isfinite(max_ratio)) and prof.line_width_px is None:
        med, n = median_where(w, valid)   # np.median over the valid finite widths, one pass
        if n >= WIDTH_FILTER_MIN_LINES:   # (NaN widths compare False: never rejected)
            rej = valid & ((w < min_ratio * med) | (w > max_ratio * med))
    elif min_ratio > 0 or np.isfinite(max_ratio):
        scale = np.asarray(prof.line_width_px, float)
        for s in np.unique(scale[valid]):
            group = valid & (scale == s)
            med, n = median_where(w, group)
            ref = med if n >= WIDTH_FILTER_MIN_LINES else s
            rej |= group & ((w < min_ratio * ref) | (w > max_ratio * ref))
    if not rej.any():
        return replace(prof, width_rejected=rej)
    pts, sig = prof.points.copy(), prof.sigma_mm.copy()
    pts[rej], sig[rej] = np.nan, np.nan
    return replace(prof, points=pts, sigma_mm=sig, valid=prof.valid & ~rej, width_rejected=rej)


def smooth_centres(uv: np.ndarray, valid: np.ndarray, axis: str, window: int) -> np.ndarray:
    """Quadratic Savitzky–Golay smoothing of profile centres along runs of consecutive valid lines.

    ``uv`` (N, 2) one centre per line (as :func:`lightplane.stripe.extract.extract_profile`
    returns them); only the sub-pixel coordinate along the lines changes.  Runs shorter
    than ``window`` are returned unchanged.
    """
    from scipy.signal import savgol_filter

    out = uv.copy()
    k = 1 if axis == "columns" else 0
    v = np.asarray(valid, bool)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], v.view(np.int8), [0]])))
    for a, b in zip(edges[::2], edges[1::2]):
        if b - a >= window:
            out[a:b, k] = savgol_filter(uv[a:b, k], window, 2, mode="interp")
    return out


#: how many measurers :func:`measure_profile` keeps (each holds up to 24 bytes per roi pixel of tables)
PROFILE_CACHE_SIZE = 4
_profile_cache: OrderedDict = OrderedDict()
_profile_cache_lock = threading.Lock()
_profile_cache_stats = {"hits": 0, "misses": 0}


def _array_key(a) -> tuple | None:
    if a is None:
        return None
    a = np.asarray(a)
    return (a.dtype.str, a.shape, a.tobytes())


def _profile_cache_key(image: np.ndarray, camera: Camera, plane: LightPlane, options: MeasureOptions):
    """A hashable fingerprint of everything a :class:`ProfileMeasurer` depends on (by value, not identity:
    an equal camera or plane built anew hits, a changed one never does); None when an option is unhashable."""
    try:
        roi_key = None if options.roi is None else tuple(float(v) for v in options.roi)
        key = (_array_key(camera.K), camera.model, _array_key(camera.dist), camera.width, camera.height,
               _array_key(plane.normal), float(plane.d), _array_key(plane.covariance),
               tuple(image.shape), roi_key, replace(options, roi=None))
        hash(key)
    except (TypeError, ValueError):
        return None
    return key


def profile_cache_info() -> dict:
    """:func:`measure_profile`'s cache: ``hits``, ``misses``, ``size`` (measurers held), ``maxsize``."""
    with _profile_cache_lock:
        return {**_profile_cache_stats, "size": len(_profile_cache), "maxsize": PROFILE_CACHE_SIZE}


def clear_profile_cache() -> None:
    """Drop :func:`measure_profile`'s cached measurers (and their tables)."""
    with _profile_cache_lock:
        _profile_cache.clear()
        _profile_cache_stats.update(hits=0, misses=0)


def _cached_measurer(image, camera, plane, options: MeasureOptions) -> ProfileMeasurer:
    key = _profile_cache_key(image, camera, plane, options)
    if key is None:
        return ProfileMeasurer(camera, plane, options)
    with _profile_cache_lock:
        m = _profile_cache.get(key)
        if m is not None:
            _profile_cache.move_to_end(key)
            _profile_cache_stats["hits"] += 1
            return m
    m = ProfileMeasurer(camera, plane, options)  # raises on bad input: nothing cached
    with _profile_cache_lock:
        m = _profile_cache.setdefault(key, m)
        _profile_cache.move_to_end(key)
        _profile_cache_stats["misses"] += 1
        while len(_profile_cache) > PROFILE_CACHE_SIZE:
            _profile_cache.popitem(last=False)
    return m


def measure_profile(image: np.ndarray, camera: Camera, plane: LightPlane, options: MeasureOptions = MeasureOptions(),
                    *, cache: bool = True) -> Profile:
    """3D profile of one stripe image (docs/method.md §Triangulation, §Stripe centres): points (mm, camera frame), σ, pixels.

    One stripe centre per column (``options.axis="columns"``) or row (``"rows"``; ``"auto"``
    picks from the plane, :func:`profile_axis`) within ``options.roi`` ``(x, y, width, height)``,
    triangulated on ``plane``; ``options``: :class:`~lightplane.measure.options.MeasureOptions`
    (its ``stripe`` options go to :func:`lightplane.stripe.extract.extract_profile`).

    Same numbers, bit for bit, as ``ProfileMeasurer(camera, plane, options)(image)``: with
    ``cache=True`` (default) the measurer, and with it
    its undistortion lookup tables, is kept per (camera, plane, image shape, options),
    compared by value (:data:`PROFILE_CACHE_SIZE` of them, least recently used dropped;
    :func:`profile_cache_info`, :func:`clear_profile_cache`), so repeated calls on the
    frames of one setup do not rebuild anything.  ``cache=False`` keeps nothing and
    undistorts the centres exactly instead (``lookup=False``; the same points to ~1e-9 px).

    Example
    -------
    >>> import numpy as np
    >>> cam = Camera(np.array([[1000., 0, 64], [0, 1000, 48], [0, 0, 1]]), np.zeros(5), 128, 96)
    >>> pl = LightPlane([0, 1, -0.5], 100)         # stripe along the columns
    >>> v = np.arange(96.0)[:, None]
    >>> img = (200 * np.exp(-0.5 * ((v - 40.25) / 1.5) ** 2) + 0 * np.arange(128.0)).astype(np.uint8)
    >>> from lightplane.stripe.options import StripeOptions
    >>> prof = measure_profile(img, cam, pl, MeasureOptions(StripeOptions(width_px=3.5)))
    >>> prof.axis, prof.n_valid > 100, bool(np.allclose(pl.signed_distance(prof.points[prof.valid]), 0, atol=1e-9))
    ('columns', True, True)
    """
    if not isinstance(camera, Camera):
        raise LightplaneError(f"camera must be a Camera, got {type(camera).__name__}")
    if not isinstance(plane, LightPlane):
        raise LightplaneError(f"plane must be a LightPlane, got {type(plane).__name__}")
    if not isinstance(image, np.ndarray):
        raise LightplaneError(f"image must be a numpy array, got {type(image).__name__}")
    camera.check_image(image)  # before the cache: a wrong-sized frame leaves no entry
    if not isinstance(options, MeasureOptions):
        raise LightplaneError(f"options must be a MeasureOptions, got {type(options).__name__}")
    if not cache:
        return ProfileMeasurer(camera, plane, options, lookup=False)(image)
    return _cached_measurer(image, camera, plane, options)(image)
