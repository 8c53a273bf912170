"""Laser stripe centres: Steger's curvilinear-structure detector and fast per-column profiles.

docs/method.md §Stripe centres (paper §2.2.1, Eq. 5–6).  Gaussian derivatives ``r_u, r_v, r_uu, r_uv, r_vv`` of the
image give the Hessian ``H = [[r_uu, r_uv], [r_uv, r_vv]]``; its eigenvector ``n`` of
the most negative eigenvalue ``lambda`` is the stripe normal, ``-lambda`` the ridge
strength.  Scale: ``sigma >= w / sqrt(3)``, ``w`` the stripe's *half*-width (Steger
1998; the paper's inequality is reversed).  ``width_px`` everywhere is the *full*
width at half maximum (FWHM) across the stripe, so the default is
``sigma = max(width_px / (2 sqrt(3)), 1)``.

Two entry points:

- :func:`extract_stripe` — every centre point of every bright line in the image
  (any orientation), linked into ordered curves (:class:`StripePoints`): for
  calibration (points inside the target's ellipse, via ``mask``).
- :func:`extract_profile` — one centre per image column (or row), the measurement
  hot path (:class:`StripeProfile`): a fused numba kernel that finds the peak of
  each column and evaluates the Gaussian derivatives only in a small patch around
  it; a numpy implementation of the same algorithm (``backend="numpy"``) gives the
  same numbers; :func:`extract_profiles` runs a batch of frames.

On real laser stripes (speckle, saturation) a scale larger than Steger's minimum
helps: ``sigma_px`` ~2 px and, for profiles, ``sigma_along_px`` ~5 px of smoothing
along the stripe (straight stripes stay unbiased at any tilt).  Where a specular
hot spot blooms the sensor, ``channel="sum"`` keeps the stripe (the bloom is in
the other channels), ``min_chroma`` flags whitish stretches, and with
``saturated_centre`` :func:`extract_profile` centres them on the midpoint of the
whitish (saturated) run across the stripe instead.

Saturated (clipped) stripes, by default
---------------------------------------
A clipped stripe's profile is flat-topped but still symmetric, so wherever the
Hessian test holds (the scale, from the measured width, is large enough for the
plateau) the derivative's zero crossing stays its centre and nothing changes.
Where it does not -- a hot spot on an otherwise unclipped stripe, whose plateau is
wider than the scale allows (``r''`` ~ 0, no ridge, no crossing, a random normal)
-- :func:`extract_profile` detects the flat top on its own (any single-channel
image, any bit depth: a run of at least 3 samples within 4 % of the contrast
below the line's peak, longer than ``0.24 FWHM + 1.5`` samples, which an
unclipped Gaussian never reaches; the image's own plateau, not the dtype's
maximum, so 12-bit data in 16-bit containers and laser-minus-background frames,
whose clipped level follows the background, are found alike) and centres the line
on the midpoint of the half-level crossings of the flanks, smoothed along the
stripe (``sigma_along_px``): both crossings move alike under a symmetric profile,
and the half level lies below the plateau, so a clipped level that varies with a
subtracted background does not bias it.  Measured (benchmarks/
bench_stripe_saturation.py): bias <= 0.01 px, RMS <= 0.06 px, 1x-8x clipped,
8/12/16-bit, blur and 1 % noise; an off-centre halo does shift it (~0.1 px).
:func:`extract_stripe` has no flat-top fallback yet (it relies on the symmetric
profile and the measured width), but for colour images with a colour channel it
uses the whitish-core cue by default (``saturated_centre``, guarded against white
ambient light); in :func:`extract_profile` that cue (``min_chroma``,
``saturated_centre``) stays opt-in.

Sub-pixel centre: where we depart from Steger's one-step formula
------------------------------------------------------------------
Steger's centre is one Newton step, ``t = -(n . grad r) / (n^T H n)`` from the pixel
centre.  On a sampled Gaussian-smoothed ridge of total scale ``S`` its error is
``t^3 / S^2`` (third-order Taylor term), up to 0.03 px at ``|t| = 0.5`` for a 3 px
stripe: a systematic "pixel-locking" error larger than the 0.015 px this module is
specified for.  So instead of extrapolating, we look at ``g = n . grad r`` (the
derivative across the stripe, ``n`` fixed at the pixel) on the two pixels of the
image column (or row: the grid axis closer to ``n``) that bracket its zero, and
solve the cubic Hermite interpolant of ``g`` and its slope ``n . H e`` there
(error O(h^4)).  The point found is where the centre line crosses that grid line,
so each crossing is reported once; the Hessian still decides where a ridge is, its
normal and its strength, as in Steger's method.

Curvature
---------
Smoothing a ridge that curves with radius ``rho`` moves its maximum inwards by
``sigma^2 / (2 rho)`` (heat equation to first order: ``r = P + (sigma^2/2) P'/rho``);
0.04 px for a 9 px stripe of radius 80 px.  Both functions remove it by default
(``correct_curvature``), with the curvature measured on the linked centres
(sagitta of the chord ``+-4 sigma`` along the curve) and ``sigma^2 + 1/12``
(the pixel's own variance; for profiles the smoothing along the stripe,
``sigma_along_px``); what remains is below 0.005 px in the tests (radius 70 px,
widths 3-9 px; about 0.01 px for a 15 px stripe of radius 70 px).

Bias of asymmetric stripes (Steger 1998, "An unbiased detector of curvilinear
structures", IEEE TPAMI 20(2), §4)
----------------------------------------------------------------------------
For a bar of half-width ``w`` and height ``h`` on a background that is 0 on one side
and ``a h`` (``0 <= a < 1``) on the other, the zero of ``r'`` moves by
``l = -sigma^2 ln(1 - a) / (2 w)`` towards the brighter side — exactly, for the bar
model convolved with a Gaussian.  :func:`extract_stripe` with
``correct_asymmetry=True`` estimates ``a`` from the backgrounds on both sides of
each point (minima along the normal within reach of the stripe) and ``w`` from the
measured FWHM, and removes ``l``.  It is off by default, because (1) a laser
stripe's cross-section is close to Gaussian, not a bar, and the bar formula is
not the shift of a Gaussian line on a step (not derived here), so the correction
can over- or under-correct; (2) in the measurement pipeline the background is subtracted
(laser frame minus laser-off frame), which removes the asymmetry at its source;
(3) the background estimate is noisy where the stripe is short.  Steger's full
correction (inverting the joint width/asymmetry map by table look-up) is not
implemented; the closed form above is the exact bar-model shift for known ``w``.
"""

from __future__ import annotations

import math
import sys
import threading
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.ndimage import map_coordinates, median_filter

from lightplane.stripe import kernels as K
from lightplane.core.errors import LightplaneError
from lightplane.core.threads import ensure_configured, in_serial_context, profile_parallel
from lightplane.core.io import to_gray_float
from lightplane.stripe.options import StripeOptions, StripePointsOptions, _check_width
from lightplane.stripe.reference import profile_numpy
from lightplane.stripe.difference import difference_channels, difference_full_scale, laser_difference, laser_off_level

__all__ = [
    "StripePoints",
    "StripeProfile",
    "extract_stripe",
    "extract_profile",
    "extract_profiles",
    "release_batch_memory",
    "estimate_width",
    "sigma_for_width",
    "PROFILE_STATUS",
    "KERNEL_PIXEL_TYPES",
    "kernel_pixels",
    "channel_image",
    "on_even_reflectance",
]

#: meaning of :attr:`StripeProfile.status`
PROFILE_STATUS = {
    K.OK: "ok",
    K.NO_PEAK: "no peak above min_peak",
    K.NOT_RIDGE: "no bright ridge (Hessian not negative)",
    K.NO_CROSSING: "no zero crossing of the derivative next to the peak",
    K.TOO_WIDE: "wider than max_width_px (glare) or no half-level crossing",
    K.ALONG_LINE: "stripe runs along the scan line (use the other axis)",
    K.EDGE: "centre within the kernel radius of the image (roi) border",
    K.WHITISH: "whitish pixels on the stripe (glare, sensor bloom): min_chroma",
}

_DEFAULT_WIDTH_PX = 5.0
_MIN_SIGMA_PX = 1.0
_SHADOW_REACH_WIDTHS = 12.0
_ALONG_WIDTHS = 2.0   # default along-curve smoothing of extract_stripe, in stripe widths


def _default_sigma_along(width_px: float, sigma: float) -> float:
    """extract_stripe's default smoothing of the centres along their curve, points."""
    return _ALONG_WIDTHS * width_px


@dataclass(frozen=True)
class StripePoints:
    """Centre points of bright lines, ordered along their curves.

    ``uv`` (N, 2) float64 px (OpenCV pixel centres); ``normals`` (N, 2) unit normal
    across the line, oriented with ``n_v > 0`` (or ``n_u > 0`` when ``n_v = 0``);
    ``strength`` (N,) ridge strength ``-lambda`` (grey levels / px^2, of the image as
    given); ``width`` (N,) FWHM across the stripe, px (NaN where not measurable);
    ``curve_id`` (N,) int, points of one curve contiguous and in order along it;
    ``sigma_px`` the Gaussian scale used.
    """

    uv: np.ndarray
    normals: np.ndarray
    strength: np.ndarray
    width: np.ndarray
    curve_id: np.ndarray
    sigma_px: float = float("nan")
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.uv.shape[0])

    @property
    def n_curves(self) -> int:
        return int(np.unique(self.curve_id).size)

    def curve(self, k: int) -> np.ndarray:
        """``uv`` of curve ``k``, (M, 2), in order."""
        return self.uv[self.curve_id == k]


@dataclass(frozen=True)
class StripeProfile:
    """One stripe centre per image column (``axis="columns"``) or row.

    ``uv`` (N, 2) float64 px, NaN where not ``valid``; for ``axis="columns"``
    ``uv[:, 0]`` is exactly the column index (the centre line's crossing of that
    column), for ``"rows"`` ``uv[:, 1]`` the row.  ``valid`` (N,) bool;
    ``intensity`` (N,) Gaussian-smoothed image value at the peak; ``strength`` (N,)
    ridge strength ``-lambda``; ``width`` (N,) FWHM across the stripe, px;
    ``normals`` (N, 2) (n_u, n_v); ``status`` (N,) uint8, see
    :data:`PROFILE_STATUS`; ``lines`` (N,) the column (row) indices; ``width_px`` the
    stripe width the frame was measured at (px), and ``line_width_px`` (N,) the width each
    line was measured at where runs of lines were measured again at their own, wider,
    width (``StripeOptions.local_width``), else None.
    """

    uv: np.ndarray
    valid: np.ndarray
    intensity: np.ndarray
    strength: np.ndarray
    width: np.ndarray
    normals: np.ndarray
    status: np.ndarray
    lines: np.ndarray
    axis: str
    sigma_px: float
    width_px: float
    line_width_px: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.uv.shape[0])

    @property
    def points(self) -> np.ndarray:
        """``uv`` of the valid lines only, (M, 2)."""
        return self.uv[self.valid]


# ----------------------------------------------------------------------------------------
# input handling

#: the pixel types the numba kernels are compiled for: 8-bit images as they are (the fast path: a
#: quarter of float32's memory traffic), every other image as float32 (exact for 16-bit and
#: integer data up to 2**24; float64 frames lose digits below 1e-7 of their value).  numba compiles
#: a kernel once per argument type: one more type would compile every kernel again (~25 s, once)
KERNEL_PIXEL_TYPES = (np.uint8, np.float32)


def kernel_pixels(image: np.ndarray) -> np.ndarray:
    """``image`` in one of :data:`KERNEL_PIXEL_TYPES`: uint8 stays, any other type becomes float32
    (no copy when it is already float32)."""
    return image if image.dtype == np.uint8 else image.astype(np.float32, copy=False)


def channel_image(image: np.ndarray, channel: str | None, name: str = "image") -> tuple[np.ndarray, float]:
    """2-D uint8 or float32 array (:func:`kernel_pixels`) from gray or BGR input, and its full scale.

    ``channel``: None / ``"gray"`` (weighted gray), ``"red"``, ``"green"``,
    ``"blue"``, or ``"sum"`` (unweighted B + G + R: a laser that saturates its own
    channel blooms into the others, which carry the stripe on).  The full scale is
    255 for 8-bit, 65535 for 16-bit, 1 or 255 for float (by the maximum), times 3
    for ``"sum"``.  16-bit data that stays within 10, 12 or 14 bits (a 12-bit sensor
    in a 16-bit container) gets that range as its full scale (1023, 4095, 16383).
    """
    if not isinstance(image, np.ndarray):
        raise LightplaneError(f"{name} must be a numpy array, got {type(image).__name__}")
    out = to_gray_float(image, channel, name=name, native=True)
    # the full scale is the input's (a bool image falls to 255 below)
    if image.dtype == np.uint8:
        fs = 255.0
    elif image.dtype == np.uint16:
        # 10-, 12- or 14-bit data in a 16-bit container: the smallest such range that holds the image
        top = int(image.max()) if image.size else 0
        fs = next(float(2**b - 1) for b in (10, 12, 14, 16) if top <= 2**b - 1)
    elif image.dtype.kind == "f":
        fs = 1.0 if (image.size == 0 or float(np.max(image)) <= 1.0) else 255.0
    else:
        fs = 255.0
    if channel == "sum" and image.ndim == 3:
        fs *= 3.0
    if out.shape[0] < 3 or out.shape[1] < 3:
        raise LightplaneError(f"{name} is too small ({out.shape[1]}x{out.shape[0]} px)")
    # one integer type and one float type: the kernels compile once for each (16-bit data and the
    # 8-bit "sum" (uint16) as float32, exactly)
    return kernel_pixels(out), fs


def _default_min_peak(full_scale: float) -> float:
    """20 grey levels of 255, scaled to the image's full scale."""
    return 20.0 / 255.0 * full_scale


def sigma_for_width(width_px: float) -> float:
    """Steger's scale for a stripe of full width ``width_px``: ``max(w / sqrt(3), 1)``, ``w = width_px / 2``."""
    return max(0.5 * float(width_px) / math.sqrt(3.0), _MIN_SIGMA_PX)


def _fwhm_median(A: np.ndarray, min_peak: float, every: int = 4) -> tuple[float, int]:
    """Median raw FWHM (samples) at each line's highest sample, over every ``every``-th line
    of ``A[s, l]`` (row-major, or the transposed view of a row-major image), and the number
    of lines it is taken over (:func:`_stripe_kernels.fwhm_median`: one serial kernel call)."""
    w, n = K.fwhm_median(A, int(every), 40, float(min_peak))
    return float(w), int(n)


def estimate_width(image: np.ndarray, *, channel: str | None = None, axis: str | None = None,
                   min_peak: float | None = None) -> float:
    """Full width at half maximum (px) of the brightest stripe, median over lines.

    ``axis="columns"`` measures down the columns (stripe roughly horizontal),
    ``"rows"`` along the rows; ``None`` takes the smaller of both (for a stripe at
    an angle ``theta`` the result is then at most ``sqrt(2)`` times too large).
    NaN when no line has a peak above ``min_peak``.
    """
    img, fs = channel_image(image, channel)
    mp = _default_min_peak(fs) if min_peak is None else float(min_peak)
    res = []
    if axis in (None, "columns"):
        res.append(_fwhm_median(img, mp))
    if axis in (None, "rows"):
        res.append(_fwhm_median(img.T, mp))   # the rows as lines, read in place (no transpose)
    if axis not in (None, "columns", "rows"):
        raise LightplaneError(f"axis must be 'columns' or 'rows', got {axis!r}")
    vals = [w for w, n in res if n >= 3]
    return float(min(vals)) if vals else float("nan")


# ----------------------------------------------------------------------------------------
# extract_profile

def check_roi(roi, width: int, height: int, min_size: int = 1) -> tuple[int, int, int, int]:
    """``roi`` ``(x, y, width, height)`` px checked against a ``width`` x ``height`` image
    (None: the whole image); each side at least ``min_size`` px."""
    if roi is None:
        return 0, 0, width, height
    try:
        x, y, w, h = (int(t) for t in roi)
    except (TypeError, ValueError):
        raise LightplaneError(f"roi must be (x, y, width, height) in px, got {roi!r}") from None
    if w < min_size or h < min_size or x < 0 or y < 0 or x + w > width or y + h > height:
        raise LightplaneError(f"roi {roi!r} (x, y, width, height) is empty or outside the {width}x{height} image")
    return x, y, w, h


def _lines_array(img: np.ndarray, axis: str, roi) -> tuple[np.ndarray, int, int]:
    """Sample-major array A[s, l] for the roi, and the (line, sample) offsets."""
    import cv2

    H, W = img.shape
    x, y, w, h = check_roi(roi, W, H)
    sub = img[y:y + h, x:x + w]
    if axis == "columns":
        return np.ascontiguousarray(sub), x, y
    if axis == "rows":
        return cv2.transpose(np.ascontiguousarray(sub)), y, x
    raise LightplaneError(f"axis must be 'columns' or 'rows', got {axis!r}")


def _profile_numba(A, w0, w1, w2, params, parallel=True):
    ensure_configured()  # OpenMP settings before the first parallel kernel
    S, L = A.shape
    centre = np.empty(L)
    normal = np.empty((L, 2))
    strength = np.empty(L)
    intensity = np.empty(L)
    width = np.empty(L)
    status = np.empty(L, np.uint8)
    if not parallel:  # one kernel call on this thread
        K.profile_frame(A, params["sep"], params["min_peak"], params["continuity"], params["tol"], w0, w1, w2,
                        params["xw"], params["qpeak"], params["half"], params["max_width"], params["min_cos"],
                        centre, normal, strength, intensity, width, status)
        return centre, normal, strength, intensity, width, status
    p1 = np.empty(L, np.int64)
    p2 = np.empty(L, np.int64)
    v1 = np.empty(L, np.float64)
    v2 = np.empty(L, np.float64)
    K.profile_candidates(A, params["sep"], p1, v1, p2, v2)
    pos = K.choose_consistent(A, p1, v1, p2, v2, params["min_peak"], 5, params["tol"]) if params["continuity"] else p1
    K.profile_centres(A, pos, w0, w1, w2, params["xw"], params["qpeak"], params["half"], params["min_peak"],
                      params["max_width"], params["min_cos"], centre, normal, strength, intensity, width, status)
    return centre, normal, strength, intensity, width, status


def extract_profile(image: np.ndarray, axis: str = "columns", options: StripeOptions = StripeOptions(), *,
                    roi=None, parallel: bool | None = None) -> StripeProfile:
    """One sub-pixel stripe centre per image column (``axis="columns"``) or row.

    Per line: the highest sample (and the highest one farther than twice the width
    from it: a reflection candidate); with ``continuity`` the second is taken when
    only it agrees with the median of the neighbouring lines' peaks; then the
    stripe's middle sample (midpoint of the half-level crossings: robust to a
    flat saturated top), the Hessian there (normal ``n``, strength ``-lambda``)
    and the zero crossing of ``n . grad r`` along the line (module docstring),
    from the derivatives of a small patch around it only.

    Saturated stripes, by default (no flag): a line whose top is flat (clipped:
    see the module docstring for the test) and where the Hessian finds no ridge
    or no crossing on the plateau is centred on the midpoint of the half-level
    crossings of its flanks, smoothed along the stripe; status ``OK``.  Lines
    where the Hessian works keep its centre (a clipped profile is symmetric).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8, uint16 or float array (BGR for colour).
    axis : ``"columns"`` for a roughly horizontal stripe (one centre per column),
        ``"rows"`` for a roughly vertical one.
    options : :class:`~lightplane.stripe.options.StripeOptions`: width, channel,
        thresholds, scales, corrections, backend.
    roi : ``(x, y, width, height)`` px; only this region is searched; ``uv`` stays
        in full-image pixels.
    parallel : numba backend: ``None`` (default) splits the frame over numba's threads
        only when that pays and nests nothing: a large frame (at least
        ``threads.PARALLEL_MIN_PIXELS`` pixels and ``PARALLEL_MIN_LINES`` lines in the
        roi) called outside a pool of frame workers (:func:`lightplane.core.threads.serial_kernels`);
        otherwise the serial kernels, the width estimate included.  ``True`` / ``False``
        force either; all three give the same numbers.

    Returns
    -------
    :class:`StripeProfile` with one entry per column (row) of the roi.

    Example
    -------
    >>> import numpy as np
    >>> v = np.arange(40.0)[:, None]
    >>> img = (200 * np.exp(-0.5 * ((v - 17.3) / 1.5) ** 2) + 0 * np.arange(30.0)).astype(np.uint8)
    >>> prof = extract_profile(img, options=StripeOptions(width_px=3.5))
    >>> bool(prof.valid.all()), round(float(np.median(prof.uv[:, 1])), 1)
    (True, 17.3)
    """
    A, setup = _profile_setup(image, axis, options, roi, parallel=parallel)
    w0, w1, w2, params = setup["w0"], setup["w1"], setup["w2"], setup["params"]
    if options.backend == "numba":
        raw = _profile_numba(A, w0, w1, w2, params, parallel=setup["parallel"])
    else:
        raw = profile_numpy(A, w0, w1, w2, params)
    scale = _local_widths(A, raw, setup, options) if options.local_width else None
    return _profile_finish(image, axis, raw, setup, options, scale)


#: a line whose stripe is at least this many times the frame's width is measured again at its own width ...
LOCAL_WIDTH_RATIO = 1.6
#: ... in runs of at least this many such lines (a run of fewer is glare or clutter, not a stripe) ...
LOCAL_MIN_LINES = 8
#: ... cut into blocks of at most this many lines, each with its own width (widths change along a stripe)
LOCAL_BLOCK_LINES = 48
#: how far from its peak a wide line's half level is looked for (samples): stripes up to ~2x this wide
LOCAL_HALF = 60


def _scale_params(w: float, options: StripeOptions, min_peak: float, sigma_al: float | None = None) -> dict:
    """The kernels' scales and thresholds for a stripe of width ``w`` (px) (:func:`_profile_setup`)."""
    sigma = sigma_for_width(w) if options.sigma_px is None else float(options.sigma_px)
    sigma_al = (sigma if options.sigma_along_px is None else float(options.sigma_along_px)) \
        if sigma_al is None else sigma_al
    w0, w1, w2 = K.gaussian_derivative_kernels(sigma)
    R = (w0.size - 1) // 2
    maxw = 2.5 * w + 2.0 if options.max_width_px is None else float(options.max_width_px)
    params = dict(
        sep=int(math.ceil(2.0 * w + 2 * R)),
        min_peak=min_peak,
        tol=max(3.0, w),
        continuity=bool(options.continuity),
        qpeak=int(math.ceil(0.5 * w)) + 1,
        half=int(math.ceil(1.5 * w)) + 3,
        max_width=maxw,
        min_cos=float(options.min_cos),
        xw=K.edge_kernels_cached(sigma_al),
    )
    return dict(w0=w0, w1=w1, w2=w2, params=params, sigma=sigma, sigma_al=sigma_al, w=w)


def _local_widths(A: np.ndarray, raw: tuple, setup: dict, options: StripeOptions) -> np.ndarray | None:
    """Measure again, at their own width, the runs of lines where the stripe is much wider than the frame's
    (:data:`LOCAL_WIDTH_RATIO`): lines that were too wide for the frame's scale or found a stripe far wider
    than it.  ``raw`` (the kernel's outputs) is updated in place
    where the second pass finds a centre; returns the width (px) each line was measured at, or None when
    no line needed it (then every line was measured at the frame's width)."""
    centre, normal, strength, intensity, width, status = raw
    w = float(setup["w"])
    flag, n_wide = K.wide_line_flags(status, width, LOCAL_WIDTH_RATIO * w)
    if n_wide < LOCAL_MIN_LINES:
        return None
    blocks, bridged = K.wide_blocks(flag, 3, LOCAL_MIN_LINES, LOCAL_BLOCK_LINES)  # gaps of up to 3 lines bridged
    if not len(blocks):
        return None
    mp = float(setup["params"]["min_peak"])
    L = len(status)
    scale = np.full(L, w)
    S = A.shape[0]
    # the lines a wide block measures again: its wide lines and the lines between them that found nothing
    redo = flag | (bridged & (status != K.OK))
    for a, b, ra, rb in blocks.tolist():
        block = np.ascontiguousarray(A[:, a:b])
        mid, spread, off = K.block_peak_spread(block)  # the peaks' median and the 75th percentile of their offsets
        wl, n = K.fwhm_median(block, 1, LOCAL_HALF, mp)
        # a stripe: wide enough to need it, its peaks line up (texture's do not)
        if not (np.isfinite(wl) and n >= LOCAL_MIN_LINES // 2 and wl >= LOCAL_WIDTH_RATIO * w and spread <= 2.0 * wl):
            continue
        st = _scale_params(float(wl), options, mp)
        # the block with the lines its smoothing along the stripe reaches on either side, within its run (the
        # lines beyond a run are another stripe width, often another surface: a step's edge), and the samples
        # around its peaks that the kernels read
        pad = int(math.ceil(3.0 * st["sigma_al"])) + 1
        a0, b0 = max(ra, a - pad), min(rb, b + pad)
        reach = int(np.max(off[off <= 2.0 * wl + 1.0])) + st["params"]["sep"] + st["params"]["half"] + st["w0"].size
        s0, s1 = max(0, int(mid) - reach), min(S, int(mid) + reach + 1)
        sub = np.ascontiguousarray(A[s0:s1, a0:b0])
        if options.backend == "numba":
            r2 = _profile_numba(sub, st["w0"], st["w1"], st["w2"], st["params"], parallel=False)
        else:
            r2 = profile_numpy(sub, st["w0"], st["w1"], st["w2"], st["params"])
        # the block's wide lines (and those between them that found nothing) take the second pass's result,
        # found or not (the frame's scale was wrong for them); lines that were fine at the frame's scale keep it
        K.merge_local_width(centre, normal, strength, intensity, width, status, *r2, float(s0), redo, a, b, a0,
                            float(wl), scale)
    return scale


def _profile_setup(image, axis, options: StripeOptions, roi, parallel=None, prepared=None):
    """Sample-major array and the scales/thresholds of :func:`extract_profile`.

    ``prepared``: ``(A, full_scale, line0, sample0)`` already made (a stack's frame)."""
    if prepared is None:
        img, fs = channel_image(image, options.channel)
        A, line0, sample0 = _lines_array(img, axis, roi)
    else:
        A, fs, line0, sample0 = prepared
    S, L = A.shape
    parallel = profile_parallel(L, S) if parallel is None else bool(parallel)
    mp = _default_min_peak(fs) if options.min_peak is None else float(options.min_peak)
    w = _check_width(options.width_px)
    if w is None:
        # lines="rows": the image's own rows, read along memory (the same values as A's columns) when
        # they are whole rows; a roi's block (not contiguous: a kernel layout of its own) from A
        E = A
        if prepared is None and axis == "rows":
            block = img[line0:line0 + L, sample0:sample0 + S]
            E = block.T if block.flags.c_contiguous else A
        w, n = _fwhm_median(E, mp, every=max(1, L // 160))
        if not np.isfinite(w):
            w = _DEFAULT_WIDTH_PX
    # given scales are checked by StripeOptions; the derived ones lie within its bounds
    setup = dict(_scale_params(w, options, mp), line0=line0, sample0=sample0, L=L, S=S, parallel=parallel,
                 full_scale=fs)
    return A, setup


def _profile_finish(image, axis, raw, setup, options: StripeOptions, scale: np.ndarray | None = None) -> StripeProfile:
    """Kernel outputs of one frame -> :class:`StripeProfile` (image coordinates, checks, curvature);
    ``scale``: the width each line was measured at, where :func:`_local_widths` changed it."""
    centre, normal, strength, intensity, width, status = raw
    line0, sample0, L = setup["line0"], setup["sample0"], setup["L"]
    sigma, sigma_al, w = setup["sigma"], setup["sigma_al"], setup["w"]
    if options.min_chroma is not None:
        status = _chroma_check(image, axis, centre, status, line0, sample0, float(options.min_chroma),
                               int(math.ceil(w)))
        if options.saturated_centre:
            centre, status = _whitish_centres(image, axis, centre, status, line0, sample0, setup["S"],
                                              float(options.min_chroma), w, setup["params"]["max_width"])
            # a line the kernels left before its derivatives has no normal: a recovered core's is
            # across the line (as a flat top's where the Hessian gives none)
            lost = (status == K.OK) & ~np.isfinite(normal[:, 0])
            if lost.any():
                normal = normal.copy()
                normal[lost] = (0.0, 1.0)
    valid = status == K.OK
    lines = np.arange(L, dtype=np.int64) + line0
    uv = np.full((L, 2), np.nan)
    nrm = np.empty((L, 2))
    if axis == "columns":
        uv[:, 0] = np.where(valid, lines, np.nan)
        uv[:, 1] = centre + sample0
        nrm[:] = normal
    else:
        uv[:, 0] = centre + sample0
        uv[:, 1] = np.where(valid, lines, np.nan)
        nrm[:, 0] = normal[:, 1]
        nrm[:, 1] = normal[:, 0]
    if options.correct_curvature:
        # the inward shift comes from the smoothing along the stripe: sigma_along
        m = max(5, int(math.ceil(4.0 * sigma_al)))
        k = 1 if axis == "columns" else 0
        if options.backend == "numba":
            K.profile_curvature(uv, nrm, valid, sigma_al**2 + CURVATURE_SIGMA2_EXTRA, m, k)
        else:
            uv = _profile_curvature(uv, nrm, valid, sigma_al, m, k)
    return StripeProfile(uv=uv, valid=valid, intensity=intensity, strength=strength, width=width,
                         normals=nrm, status=status, lines=lines, axis=axis, sigma_px=float(sigma),
                         width_px=float(w), line_width_px=scale)


def _stack_lines(frames, axis: str, channel, roi):
    """Stack of frames -> (N, S, L) sample-major array, each frame's full scale, offsets.

    A 2-D-per-frame stack of uint8, uint16 or float32 (no channel) is cut and, for
    ``axis="rows"``, transposed in one go; anything else goes frame by frame through
    :func:`channel_image` (the same conversions as :func:`extract_profile`).
    """
    if isinstance(frames, np.ndarray) and frames.ndim == 3 and channel in (None, "gray") \
            and frames.dtype in (np.uint8, np.uint16, np.float32):
        N, H, W = frames.shape
        if H < 3 or W < 3:
            raise LightplaneError(f"frames are too small ({W}x{H} px)")
        if frames.dtype == np.float32 and not np.all(np.isfinite(frames)):
            raise LightplaneError("frames contain NaN or infinite values")
        x, y, w, h = check_roi(roi, W, H)
        sub = frames[:, y:y + h, x:x + w]
        if axis not in ("columns", "rows"):
            raise LightplaneError(f"axis must be 'columns' or 'rows', got {axis!r}")
        view = sub if axis == "columns" else sub.transpose(0, 2, 1)
        # C-contiguous, in the kernels' pixel type (no copy where the stack already is)
        A3 = np.ascontiguousarray(view, dtype=np.uint8 if frames.dtype == np.uint8 else np.float32)
        line0, sample0 = (x, y) if axis == "columns" else (y, x)
        if frames.dtype == np.uint8:
            fs = np.full(N, 255.0)
        else:
            top = frames.reshape(N, -1).max(axis=1).astype(np.float64) if N else np.zeros(0)
            if frames.dtype == np.uint16:   # as channel_image: the smallest of 10/12/14/16 bits that holds it
                fs = np.select([top <= 1023, top <= 4095, top <= 16383], [1023.0, 4095.0, 16383.0], 65535.0)
            else:
                fs = np.where(top <= 1.0, 1.0, 255.0)
        return A3, fs, line0, sample0
    seq = [frames[i] for i in range(frames.shape[0])] if isinstance(frames, np.ndarray) else list(frames)
    arrays: list[np.ndarray] = []
    fss: list[float] = []
    offs: tuple[int, int] | None = None
    for img in seq:
        g, fs_img = channel_image(img, channel, "frame")
        A, line0, sample0 = _lines_array(g, axis, roi)
        if arrays and (A.shape != arrays[0].shape or A.dtype != arrays[0].dtype):
            raise LightplaneError("frames must all have the same size and type")
        arrays.append(A)
        fss.append(fs_img)
        offs = (line0, sample0)
    if not arrays or offs is None:
        return None, None, 0, 0
    return np.stack(arrays), np.asarray(fss, float), offs[0], offs[1]


class _BatchBlock:
    """One block of memory for a batch's outputs, handed out again once nothing holds it.

    :func:`extract_profiles` writes every frame's outputs (centre, normal, strength,
    intensity, width, image points, status, valid: 66 bytes a line, 84 MB for 1000 x 1280
    lines) into one block.  Fresh memory that large comes from the operating system page
    by page, zeroed, and a long-running process's allocator often returns it after each
    batch, so every batch paid those page faults again: after a `calibrate_plane` in the
    same process a 1000 x 1280x64 batch took 60-140 ms of system time against 0-20 ms
    (5,000-7,800 instead of 10,500-11,700 profiles/s, the same kernels; it came and went
    with the allocator's state).  So the block of the last batch is kept, and the next
    batch of the same size takes it back when no profile, array or view of the last one
    is alive any more (the block's reference count: every returned array is a view that
    holds it); otherwise it gets a new block and the old one stays with whoever holds it.
    The returned profiles never share memory with anything alive.  One block is kept per
    process, at most :attr:`MAX_BYTES`; :func:`release_batch_memory` drops it.
    """

    MAX_BYTES = 512 << 20
    #: (dtype, trailing shape) of the outputs, in the block's order
    LAYOUT = ((np.float64, ()), (np.float64, (2,)), (np.float64, ()), (np.float64, ()), (np.float64, ()),
              (np.float64, (2,)), (np.uint8, ()), (np.bool_, ()))

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._block: np.ndarray | None = None
        self._probe: object | None = None

    @staticmethod
    def _sizes(N: int, L: int) -> list[int]:
        return [N * L * int(np.prod(t, dtype=np.int64)) * np.dtype(d).itemsize for d, t in _BatchBlock.LAYOUT]

    def take(self, N: int, L: int) -> tuple[np.ndarray, list[np.ndarray]]:
        """A block for N frames of L lines, and its arrays: centre, normal, strength,
        intensity, width (N, L[, 2]) float64, uv (N, L, 2), status uint8, valid bool."""
        sizes = self._sizes(N, L)
        starts = np.concatenate([[0], np.cumsum([(n + 63) // 64 * 64 for n in sizes])]).astype(int)
        total = int(starts[-1])
        block = None
        with self._lock:
            b = self._block
            if b is not None and b.nbytes == total:
                # nothing else holds it: as many references as a fresh object held the same way
                # (an attribute and a local), whatever the interpreter counts for the call itself
                self._probe = probe = object()
                if sys.getrefcount(b) == sys.getrefcount(probe):
                    block, self._block = b, None
                self._probe = probe = None
            del b
        if block is None:
            block = np.empty(total, np.uint8)
        arrays: list[np.ndarray] = [block[s0:s0 + n].view(d).reshape((N, L) + t)
                  for (d, t), s0, n in zip(self.LAYOUT, starts[:-1], sizes)]
        return block, arrays

    def keep(self, block: np.ndarray) -> None:
        """Keep ``block`` for the next batch (the one kept before is let go)."""
        with self._lock:
            self._block = block if block.nbytes <= self.MAX_BYTES else None

    def release(self) -> None:
        with self._lock:
            self._block = None


_BATCH = _BatchBlock()


def release_batch_memory() -> None:
    """Let go of the output block :func:`extract_profiles` keeps for its next batch (see
    :class:`_BatchBlock`): memory held by no profile is returned to the allocator."""
    _BATCH.release()


def extract_profiles(frames, axis: str = "columns", options: StripeOptions = StripeOptions(), *, roi=None,
                     parallel: bool | None = None) -> list[StripeProfile]:
    """:func:`extract_profile` of a stack of frames in one call: the ROI sensor's batch.

    ``frames``: (N, H, W) / (N, H, W, 3) array or a sequence of equally sized
    images (e.g. N x 64 x 1280 regions of interest).  The scales (``width_px``,
    estimated from the first frame when None) are shared by all frames; each result
    equals ``extract_profile(frame, axis, replace(options, width_px=that width), roi=roi)``
    of that frame, bit for bit (the numba kernels: ``options.backend`` must be ``"numba"``).
    The per-frame costs of a call (argument checks, kernel launches, Python)
    are paid once per batch: one kernel runs the whole stack, frames across numba's
    threads with each frame serial (``parallel`` None: unless called inside
    :func:`lightplane.core.threads.serial_kernels`, where the batch runs on the calling
    thread; ``True`` / ``False`` force either).  The outputs of a batch share one block of
    memory, which the next batch of the same size reuses once nothing of this one is
    alive (see :class:`_BatchBlock`; :func:`release_batch_memory`).
    """
    ensure_configured()  # OpenMP settings before the first parallel kernel
    if options.backend != "numba":
        raise LightplaneError(f"extract_profiles runs the numba kernels: backend must be 'numba', got {options.backend!r}")
    if isinstance(frames, np.ndarray) and frames.ndim not in (3, 4):
        raise LightplaneError(f"frames must be (N, H, W) or (N, H, W, 3), got shape {frames.shape}")
    if not isinstance(frames, np.ndarray):
        frames = list(frames)
    if len(frames) == 0:
        return []
    A3, fs, line0, sample0 = _stack_lines(frames, axis, options.channel, roi)
    N, S, L = A3.shape
    _, setup = _profile_setup(None, axis, options, roi, parallel=False, prepared=(A3[0], float(fs[0]), line0, sample0))
    w0, w1, w2, params, w_ = setup["w0"], setup["w1"], setup["w2"], setup["params"], setup["w"]
    mp = np.array([_default_min_peak(f) for f in fs]) if options.min_peak is None \
        else np.full(N, float(options.min_peak))
    block, (centre, normal, strength, intensity, width, uv, status, valid) = _BATCH.take(N, L)
    par = (not in_serial_context() and N > 1) if parallel is None else bool(parallel)
    (K.profiles_batch if par else K.profiles_batch_serial)(
        A3, params["sep"], mp, params["continuity"], params["tol"], w0, w1, w2, params["xw"], params["qpeak"],
        params["half"], params["max_width"], params["min_cos"], centre, normal, strength, intensity, width, status)
    scales: dict[int, np.ndarray | None] = {}
    if options.local_width:  # frames with runs of much wider lines: those runs again at their own width
        for f in _frames_to_widen(status, width, float(w_)):
            scales[f] = _local_widths(A3[f], (centre[f], normal[f], strength[f], intensity[f], width[f], status[f]),
                                      setup, options)
    if options.min_chroma is not None:   # colour checks need each frame's image: frame by frame (their own arrays)
        seq = [frames[i] for i in range(N)]
        return [_profile_finish(seq[f], axis, (centre[f], normal[f], strength[f], intensity[f], width[f], status[f]),
                                setup, options, scales.get(f)) for f in range(N)]
    # _profile_finish for the whole stack at once, frames across threads as the profiles were
    lines = np.arange(L, dtype=np.int64) + line0
    lines.setflags(write=False)   # shared by the frames' profiles
    nrm = normal   # (u, v) in place of the kernel's (along, across) normals
    sigma, sigma_al, w = setup["sigma"], setup["sigma_al"], setup["w"]
    m = max(5, int(math.ceil(4.0 * sigma_al)))
    (K.frames_points if par else K.frames_points_serial)(
        centre, normal, status, lines, float(sample0), axis == "columns", bool(options.correct_curvature),
        sigma_al**2 + CURVATURE_SIGMA2_EXTRA, m, uv, nrm, valid)
    _BATCH.keep(block)
    return [StripeProfile(uv=uv[f], valid=valid[f], intensity=intensity[f], strength=strength[f], width=width[f],
                          normals=nrm[f], status=status[f], lines=lines, axis=axis, sigma_px=float(sigma),
                          width_px=float(w), line_width_px=scales.get(f)) for f in range(N)]


def _frames_to_widen(status: np.ndarray, width: np.ndarray, w: float) -> list[int]:
    """Frames of a batch (``status``, ``width``: (N, L)) with at least :data:`LOCAL_MIN_LINES` lines that
    :func:`_local_widths` would look at again (a cheap screen: most frames have none)."""
    counts = K.wide_line_counts(status, width, LOCAL_WIDTH_RATIO * w)
    return np.flatnonzero(counts >= LOCAL_MIN_LINES).tolist()


def _chroma(image: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Least colour saturation ``(max - min) / max`` over each set of pixels (HSV sense).

    ``rows``, ``cols`` (N, K) index K pixels per point; pixels darker than 30 % of
    the brightest of their set are ignored.  NaN where all are black.
    """
    if image.ndim != 3:
        raise LightplaneError("min_chroma needs a colour (H, W, 3) image")
    px = image[rows, cols, :3].astype(np.float64)          # (N, K, 3)
    hi = px.max(axis=2)
    lo = px.min(axis=2)
    bright = hi >= 0.3 * hi.max(axis=1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        chroma = np.where(bright & (hi > 0), (hi - lo) / hi, np.inf)
    out = chroma.min(axis=1)
    return np.where(np.isfinite(out), out, np.nan)


def _chroma_check(image, axis, centre, status, line0, sample0, min_chroma, half):
    """Flag lines whose stripe (centre +- ``half`` samples) holds whitish pixels."""
    status = status.copy()
    ok = np.flatnonzero(status == K.OK)
    if ok.size == 0:
        return status
    n_s = image.shape[0 if axis == "columns" else 1]
    k = np.arange(-half, half + 1)
    s = np.clip(np.round(centre[ok]).astype(np.int64)[:, None] + sample0 + k[None, :], 0, n_s - 1)
    ln = np.broadcast_to((ok + line0)[:, None], s.shape)
    rows, cols = (s, ln) if axis == "columns" else (ln, s)
    chroma = _chroma(image, rows, cols)
    status[ok[~(chroma >= min_chroma)]] = K.WHITISH
    return status


def _whitish_centres(image, axis, centre, status, line0, sample0, S, min_chroma, w, max_width):
    """Centres of saturated (whitish) stretches: midpoint of the whitish run across the stripe.

    Where a laser stripe saturates the sensor, the camera renders its core grey-white
    (R ~ G ~ B) and the laser's own channel no longer peaks there (it may even dip
    below the red glow around it), so the Hessian centre is lost or flagged.  The
    core's extent is still sharp: per invalid line (any status but ``EDGE``: in a
    hot spot the red glow's normal can be anything),
    within ``w + 2`` samples of the centre expected from the valid lines on either
    side (linear interpolation, strays off their running median left out), the run of bright pixels with chroma below
    ``min_chroma`` (bright: as in :func:`_chroma`); its ends are refined to where
    the chroma crosses ``min_chroma`` (linear interpolation with the outer
    neighbour) and the midpoint is the centre (the usual centre of a saturated,
    flat-topped stripe).  Runs longer than ``max_width`` or touching the search
    window's ends (glare, not a stripe core) are left invalid.
    """
    centre = centre.copy()
    status = status.copy()
    good = status == K.OK
    todo = np.flatnonzero(~good & (status != K.EDGE))
    if todo.size == 0 or good.sum() < 2:
        return centre, status
    idx = np.flatnonzero(good)
    # expected centre: the valid lines, less those off the running median of 15 (strays)
    c = centre[idx]
    keep = np.abs(c - median_filter(c, size=15, mode="nearest")) <= max(w, 2.0)
    expect = np.interp(todo, idx[keep], c[keep])
    reach = int(math.ceil(w)) + 2
    n_s = image.shape[0 if axis == "columns" else 1]
    k = np.arange(-reach - 1, reach + 2)
    base = np.round(expect).astype(np.int64) + sample0 - reach - 1   # sample of k[0]
    s = base[:, None] + (k[None, :] + reach + 1)
    inside = (s >= sample0) & (s < sample0 + S)
    s = np.clip(s, 0, n_s - 1)
    ln = np.broadcast_to((todo + line0)[:, None], s.shape)
    rows, cols = (s, ln) if axis == "columns" else (ln, s)
    px = image[rows, cols, :3].astype(np.float64)            # (N, K, 3)
    hi = px.max(axis=2)
    lo = px.min(axis=2)
    bright = (hi >= 0.3 * hi.max(axis=1, keepdims=True)) & (hi > 0) & inside
    with np.errstate(divide="ignore", invalid="ignore"):
        chroma = np.where(hi > 0, (hi - lo) / hi, 1.0)
    white = bright & (chroma < min_chroma)
    white[:, 0] = white[:, -1] = False                       # guard samples
    mid = reach + 1
    for i in range(todo.size):
        runs = np.flatnonzero(np.diff(white[i].astype(np.int8)))  # starts (0->1) and ends (1->0)
        if runs.size < 2:
            continue
        a, b = runs[0::2] + 1, runs[1::2]                     # run i covers a..b
        j = int(np.argmin(np.abs(0.5 * (a + b) - mid)))
        a, b = int(a[j]), int(b[j])
        if a <= 1 or b >= k.size - 2 or b - a + 1 > max_width:
            continue
        c = chroma[i]
        ea = a - 0.5 if c[a - 1] == c[a] else a - (min_chroma - c[a]) / (c[a - 1] - c[a])
        eb = b + 0.5 if c[b + 1] == c[b] else b + (min_chroma - c[b]) / (c[b + 1] - c[b])
        ea = min(max(ea, a - 1.0), float(a))
        eb = min(max(eb, float(b)), b + 1.0)
        centre[todo[i]] = base[i] - sample0 + 0.5 * (ea + eb)
        status[todo[i]] = K.OK
    return centre, status


# ----------------------------------------------------------------------------------------
# extract_stripe

_TILE = 32


def _active_regions(src: np.ndarray, min_contrast: float, R: int):
    """Boxes ``(x0, y0, x1, y1)`` px around the tiles where a stripe may be, or None.

    A 32 x 32 tile is active when its max - min reaches ``min_contrast``; active
    tiles grow by one tile (more than the kernel radius ``R``, so the derivatives
    inside are exact) and their connected groups' bounding boxes are returned.
    None when they cover more than half of the image (filter it whole).
    """
    import cv2

    H, W = src.shape
    T = max(_TILE, R + 3)
    ny, nx = -(-H // T), -(-W // T)
    pad = cv2.copyMakeBorder(src, 0, ny * T - H, 0, nx * T - W, cv2.BORDER_REPLICATE)
    rows = pad.reshape(ny, T, nx * T)    # the tiles' rows reduced first: contiguous, vectorised
    hi = rows.max(axis=1).reshape(ny, nx, T).max(axis=2)
    lo = rows.min(axis=1).reshape(ny, nx, T).min(axis=2)
    contrast = hi.astype(np.float32) - lo.astype(np.float32)
    active = (contrast >= min_contrast).astype(np.uint8)
    if not active.any():
        return []
    active = cv2.dilate(active, np.ones((3, 3), np.uint8))
    if active.mean() > 0.5:
        return None
    n, _, stats, _ = cv2.connectedComponentsWithStats(active, connectivity=8)
    boxes = [(int(x * T), int(y * T), int(min(W, (x + w) * T)), int(min(H, (y + h) * T)))
             for x, y, w, h, _area in stats[1:]]
    # merge overlapping boxes: each pixel must be filtered in one region only
    merged = True
    while merged and len(boxes) > 1:
        merged = False
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                a, b = boxes[i], boxes[j]
                if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                    boxes[i] = (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))
                    del boxes[j]
                    merged = True
                    break
            if merged:
                break
    return boxes


def _ridge_response(width_px: float, sigma: float) -> float:
    """-r'' at the centre of a unit-contrast Gaussian stripe of FWHM ``width_px`` (same kernels)."""
    w0, w1, w2 = K.gaussian_derivative_kernels(sigma)
    R = (w0.size - 1) // 2
    s = width_px / 2.3548
    x = np.arange(-R, R + 1, dtype=float)
    f = np.exp(-0.5 * (x / s) ** 2)
    return float(-np.dot(w2, f))


class _Buffers(threading.local):
    """Preallocated float32 derivative images, reused between calls of the same size.

    One set per thread (``threading.local``), so :func:`extract_stripe` may run in
    several threads at once (``calibrate_plane`` with a thread pool).
    """

    def __init__(self):
        self.shape = None

    def get(self, shape):
        if self.shape != shape:
            self.shape = shape
            self.bufs = [np.empty(shape, np.float32) for _ in range(13)]
            self.index_map = np.full(shape, -1, np.int64)
        return self.bufs


_BUFFERS = _Buffers()


@dataclass(frozen=True)
class _StripeScales:
    """The scales and thresholds of one :func:`extract_stripe` call: width ``w`` (FWHM px),
    ``sigma``, the smoothing along the curves ``sal``, the unit-contrast ridge response
    ``resp``, the hysteresis thresholds ``hi``, ``lo`` and the least contrast ``mc``."""

    w: float
    sigma: float
    sal: float
    resp: float
    hi: float
    lo: float
    mc: float


@dataclass(frozen=True)
class _RidgeMaps:
    """Ridge points of :func:`extract_stripe`, per pixel (float32 (H, W), filled in place): the
    centre ``su``, ``sv``, the normal ``snu``, ``snv`` and the strength ``sstr`` (0: no point)."""

    su: np.ndarray
    sv: np.ndarray
    snu: np.ndarray
    snv: np.ndarray
    sstr: np.ndarray


@dataclass(frozen=True)
class _CurvePoints:
    """Linked centre points of :func:`extract_stripe`, in curve order: ``uv``, ``nrm``, strength
    ``st``, FWHM ``width``, backgrounds and peak ``bg`` (N, 3), curve index ``cid``."""

    uv: np.ndarray
    nrm: np.ndarray
    st: np.ndarray
    width: np.ndarray
    bg: np.ndarray
    cid: np.ndarray

    def take(self, sel: np.ndarray, renumber: bool = True) -> "_CurvePoints":
        """The points ``sel`` (index or mask); with ``renumber`` the curves numbered 0.. again."""
        cid = self.cid[sel]
        if renumber:
            _, cid = np.unique(cid, return_inverse=True)
        return _CurvePoints(self.uv[sel], self.nrm[sel], self.st[sel], self.width[sel], self.bg[sel], cid)


def extract_stripe(image: np.ndarray, options: StripePointsOptions = StripePointsOptions(),
                   mask: np.ndarray | None = None, background: np.ndarray | None = None) -> StripePoints:
    """Centre points of all bright lines (Steger's method), linked into ordered curves.

    Five Gaussian-derivative images (``cv2.sepFilter2D``, pixel-integrated Gaussian
    kernels, float32 buffers reused between calls); per pixel the Hessian's most
    negative eigenvalue ``lambda`` and its eigenvector ``n`` (the normal); a pixel
    holds a point when the zero of ``n . grad r`` along its column (row) lies in
    its cell (module docstring); hysteresis: 8-connected sets of points with
    ``-lambda >= low`` are kept when one of them reaches ``high`` and they hold at
    least ``min_length`` points; then ordered into chains.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8 / uint16 / float.
    options : :class:`~lightplane.stripe.options.StripePointsOptions`: width, channel,
        scales, thresholds, corrections, saturated cores.
    mask : (H, W) bool, points only where True (e.g. inside the target's ellipse).
    background : the laser-off frame of the same view (same shape as ``image``), or None.  Given, the
        stripe is taken from ``image - background`` in the channels that carry it
        (:func:`lightplane.stripe.difference.laser_difference`), and with
        ``options.drop_uneven_reflectance`` (the default) the centres where the laser-off frame's
        reflectance changes across the stripe are dropped (:func:`on_even_reflectance`): a printed or
        textured edge there moves the centre towards the lighter side, and the residual edges of a
        camera that moved between the two frames lie there too.  ``meta["reflectance_dropped"]``
        counts them.

    Returns
    -------
    :class:`StripePoints` (possibly empty).
    """
    ensure_configured()  # OpenMP settings before the first parallel kernel
    lit = None
    if background is not None:
        image, lit, fs = _laser_off_removed(image, background, options.channel, mask)
        if options.reject_fragments is None:
            options = replace(options, reject_fragments=True)
        if fs is None:   # a colour difference: its channel as asked, saturated cores included
            img, fs = channel_image(image, options.channel)
        else:            # channels summed (the laser's own is clipped in the laser-off frame)
            options = replace(options, channel=None, saturated_centre=False)
            img, _ = channel_image(image, None)
    else:
        img, fs = channel_image(image, options.channel)
    H, W = img.shape
    mask = _stripe_mask(mask, (H, W))
    sc = _stripe_scales(img, fs, options)
    maps, regions = _ridge_maps(img, sc)
    if mask is not None:
        maps.sstr[~mask] = 0.0
    # the replicated border biases the derivatives: no points within 2 sigma of it
    b = int(math.ceil(2.0 * sc.sigma)) if options.border_px is None else int(options.border_px)
    if b > 0:
        maps.sstr[:b] = 0.0
        maps.sstr[-b:] = 0.0
        maps.sstr[:, :b] = 0.0
        maps.sstr[:, -b:] = 0.0
    core_map = _saturated_cores(image, img, options, maps, sc)
    meta = {"low": sc.lo, "high": sc.hi, "width_px": sc.w}
    empty = StripePoints(np.empty((0, 2)), np.empty((0, 2)), np.empty(0), np.empty(0),
                         np.empty(0, np.int64), float(sc.sigma), meta)
    strong = _hysteresis(maps.sstr, regions, sc.hi)
    if strong is None:
        return empty
    pts, is_core, core_len = _linked_points(img, strong[0], strong[1], maps, core_map, sc)
    pts = _stripe_curves(image, img, pts, is_core, core_len, sc, options)
    if pts is not None and lit is not None and options.drop_uneven_reflectance:
        # last, so that the stripe's tests (overshadowed curves, fragments) see its curves whole
        even = on_even_reflectance(lit, pts.uv, pts.nrm, sc.w, sc.sigma, fs)
        meta["reflectance_dropped"] = int(np.count_nonzero(~even))
        kept = _split_runs(pts, even, int(options.min_length), False)
        pts = None if kept is None else kept[0]
    if pts is None:
        return empty
    uv = pts.uv
    if options.correct_asymmetry:
        uv = _correct_asymmetry(img.astype(np.float32), uv, pts.nrm, pts.width, pts.bg, sc.sigma)
    if sc.sal > 0:
        uv = _smooth_along(uv, pts.nrm, pts.cid, sc.sal)
    if options.correct_curvature:
        uv = _correct_curvature(uv, pts.nrm, pts.cid, sc.sigma)
    return StripePoints(uv=uv, normals=pts.nrm, strength=pts.st, width=pts.width, curve_id=pts.cid.astype(np.int64),
                        sigma_px=float(sc.sigma), meta=meta)


#: a centre lies on uneven reflectance when the laser-off frame's level across the stripe's reach varies by
#: more than this (max over min) ...
REFLECTANCE_SPREAD_MAX = 1.5
#: ... where levels below this share of the full scale count as this (a dark scene: no reflectance to read)
REFLECTANCE_FLOOR = 4.0 / 255.0


def _laser_off_removed(image: np.ndarray, background: np.ndarray, channel: str | None,
                       mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, float | None]:
    """The laser's light alone, the laser-off frame in the channels it is read in, and the full scale
    of a summed difference.  Where no channel that ``channel`` reads is clipped in the laser-off frame:
    ``image - background`` clipped at 0, in the input's type and channels, and full scale None (read as
    any image); otherwise the sum of the channels that carry the stripe
    (:func:`lightplane.stripe.difference.laser_difference`), float32, and its full scale."""
    import cv2

    if not isinstance(background, np.ndarray) or not isinstance(image, np.ndarray):
        raise LightplaneError("image and background must be numpy arrays")
    if background.dtype != image.dtype:
        raise LightplaneError(f"background image type {background.dtype} differs from the image's {image.dtype}")
    if image.size == 0:
        raise LightplaneError(f"image is empty (shape {image.shape})")
    region = None if mask is None else np.asarray(mask)
    if region is not None and region.shape != image.shape[:2]:
        raise LightplaneError(f"mask shape {region.shape} differs from the image's {image.shape[:2]}")
    _, left_out, _ = difference_channels(image, background, channel, region)
    if not left_out:  # the request as it is: the plain difference, no summed image made to be thrown away
        lit = np.asarray(to_gray_float(background, channel), dtype=np.float32)
        if image.dtype.kind in "ui":
            return cv2.subtract(image, background), lit, None
        return np.clip(image.astype(np.float32) - background.astype(np.float32), 0, None), lit, None
    diff = laser_difference(image, background, channel, region=region)
    return (np.ascontiguousarray(diff.image, dtype=np.float32), laser_off_level(background, diff, channel),
            difference_full_scale(image, diff, channel))


def on_even_reflectance(lit: np.ndarray, uv: np.ndarray, normals: np.ndarray, width_px: float, sigma_px: float,
                        full_scale: float = 255.0, min_level: float = 0.0) -> np.ndarray:
    """(N,) bool: the stripe centres ``uv`` (N, 2, px) whose surface reflects evenly across the stripe.

    The laser's light on a surface is its irradiance times the surface's reflectance, and the laser-off
    frame ``lit`` (ambient light on the same surface) shows that reflectance.  Where it changes within
    the stripe's reach, the product's peak moves towards the lighter side (by a good part of a pixel
    when a printed edge runs along the stripe), and a difference image holds edge residuals there when
    the camera moved between the frames.  Read on ``lit`` smoothed by 1 px: across the stripe
    (``normals``) within half its width plus a pixel, on lines across it up to Steger's scale plus a
    pixel along it (the derivative kernels reach that far).  A centre is kept when on every such line
    the largest level is below :data:`REFLECTANCE_SPREAD_MAX` times the smallest; levels under
    :data:`REFLECTANCE_FLOOR` of the full scale count as that floor (a dark scene says nothing about
    reflectance; its noise must not drop centres).  An edge that crosses the stripe squarely leaves
    each line on one side of it and moves no centre (the profile across is scaled, not skewed): the
    centres next to it are kept.  ``min_level``: also drop the centres where the level anywhere on
    those lines is below it (a board's ink, in units of its white)."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    nrm = np.asarray(normals, np.float64).reshape(-1, 2)
    if uv.shape[0] == 0:
        return np.zeros(0, bool)
    import cv2

    lv = cv2.GaussianBlur(np.ascontiguousarray(lit, dtype=np.float32), (0, 0), 1.0)
    across = 0.5 * float(width_px) + 1.0
    along = float(sigma_px) + 1.0
    t = np.linspace(-across, across, int(math.ceil(2.0 * across)) + 1)
    a = np.linspace(-along, along, int(math.ceil(2.0 * along)) + 1)
    tt, aa = (np.repeat(t, a.size), np.tile(a, t.size))
    pu = uv[:, :1] + tt[None, :] * nrm[:, :1] - aa[None, :] * nrm[:, 1:]
    pv = uv[:, 1:] + tt[None, :] * nrm[:, 1:] + aa[None, :] * nrm[:, :1]
    s = map_coordinates(lv, [pv.ravel(), pu.ravel()], order=1, mode="nearest").reshape(pu.shape)
    floor = REFLECTANCE_FLOOR * float(full_scale)
    # the spread across the stripe at each step along it: an edge that crosses the stripe squarely
    # leaves every such line on one side of it
    s3 = s.reshape(len(uv), t.size, a.size)
    lo = s3.min(axis=1)
    return np.all(s3.max(axis=1) < REFLECTANCE_SPREAD_MAX * np.maximum(lo, floor), axis=1) & \
        (lo.min(axis=1) >= min_level)


def _stripe_mask(mask, shape: tuple[int, int]) -> np.ndarray | None:
    """``mask`` as a bool array of the image's ``shape`` (None stays None)."""
    if mask is None:
        return None
    mask = np.asarray(mask)
    if mask.shape != shape:
        raise LightplaneError(f"mask must have the image's shape {shape}, got {mask.shape}")
    return mask.astype(bool, copy=False)


def _stripe_scales(gray: np.ndarray, fs: float, options: StripePointsOptions) -> _StripeScales:
    """Width (given or estimated), scales and hysteresis thresholds of :func:`extract_stripe`."""
    mc = _default_min_peak(fs) if options.min_contrast is None else float(options.min_contrast)
    w = _check_width(options.width_px)
    if w is None:
        w = estimate_width(gray, min_peak=mc)
        if not np.isfinite(w):
            w = _DEFAULT_WIDTH_PX
    # a given sigma_px is checked by StripePointsOptions; the derived one lies within its bounds
    sigma = sigma_for_width(w) if options.sigma_px is None else float(options.sigma_px)
    sal = _default_sigma_along(w, sigma) if options.sigma_along_px is None else float(options.sigma_along_px)
    if not (np.isfinite(sal) and 0 <= sal <= 100):
        raise LightplaneError(f"sigma_along_px must be between 0 and 100 px, got {options.sigma_along_px!r}")
    resp = _ridge_response(w, sigma)
    hi = 1.0 * mc * resp if options.high is None else float(options.high)
    lo = 0.5 * hi if options.low is None else float(options.low)
    if not (0 < lo <= hi):
        raise LightplaneError(f"need 0 < low <= high, got low={lo}, high={hi}")
    return _StripeScales(w=w, sigma=sigma, sal=sal, resp=resp, hi=hi, lo=lo, mc=mc)


def _ridge_maps(img: np.ndarray, sc: _StripeScales) -> tuple[_RidgeMaps, list]:
    """The ridge points of the image's active regions (:func:`_active_regions`) into this
    thread's buffers, and the regions ``(x0, y0, x1, y1)``."""
    import cv2

    H, W = img.shape
    w0, w1, w2 = (k.astype(np.float32) for k in K.gaussian_derivative_kernels(sc.sigma))
    bufs = _BUFFERS.get((H, W))
    ru, rv, ruu, ruv, rvv, su, sv, snu, snv, sstr, x0, x1, x2 = bufs[:13]
    # separable: three row passes (value, 1st, 2nd derivative along u) on the image
    # as given (8-bit input is filtered fastest), then five column passes
    border = cv2.BORDER_REPLICATE
    src = img
    R = (w0.size - 1) // 2
    regions = _active_regions(src, sc.mc, R)
    if regions is None:                   # stripes everywhere: the whole image at once
        regions = [(0, 0, W, H)]
    else:
        sstr.fill(0.0)
    for (a0, b0, a1, b1) in regions:
        sub = src[b0:b1, a0:a1]
        view = [buf[b0:b1, a0:a1] for buf in (x0, x1, x2, ru, rv, ruu, ruv, rvv, su, sv, snu, snv, sstr)]
        vx0, vx1, vx2, vru, vrv, vruu, vruv, vrvv, vsu, vsv, vsnu, vsnv, vsstr = view
        for k, x in ((w0, vx0), (w1, vx1), (w2, vx2)):
            cv2.filter2D(sub, cv2.CV_32F, k.reshape(1, -1), dst=x, borderType=border)
        for x, k, out in ((vx1, w0, vru), (vx0, w1, vrv), (vx2, w0, vruu), (vx1, w1, vruv), (vx0, w2, vrvv)):
            cv2.filter2D(x, cv2.CV_32F, k.reshape(-1, 1), dst=out, borderType=border)
        K.ridge_points(ru, rv, ruu, ruv, rvv, sc.lo, su, sv, snu, snv, sstr, a0, b0, a1, b1)
        # a region's inner edges (not the image's): the replicated border there is not the image
        m = R + 1
        if a0 > 0:
            vsstr[:, :m] = 0.0
        if b0 > 0:
            vsstr[:m] = 0.0
        if a1 < W:
            vsstr[:, -m:] = 0.0
        if b1 < H:
            vsstr[-m:] = 0.0
    return _RidgeMaps(su, sv, snu, snv, sstr), regions


def _saturated_cores(image, img, options: StripePointsOptions, maps: _RidgeMaps, sc: _StripeScales):
    """:func:`_stripe_cores` when ``saturated_centre`` is on (by default: a colour image and
    channel red, green or blue), else None."""
    channel = options.channel
    sat = (image.ndim == 3 and channel in ("red", "green", "blue")) if options.saturated_centre is None \
        else bool(options.saturated_centre)
    if not sat:
        return None
    if image.ndim != 3 or channel not in ("red", "green", "blue"):
        raise LightplaneError("saturated_centre needs a colour (H, W, 3) image and channel red, green or blue")
    return _stripe_cores(image, img, channel, maps, sc.hi, sc.w, sc.resp,
                         0.5 if options.min_chroma is None else float(options.min_chroma))


def _hysteresis(sstr: np.ndarray, regions: list, hi: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Flat indices and strengths of the ridge points in 8-connected sets (region by region:
    regions are disjoint) one of whose points reaches ``hi``; None when there are none."""
    import cv2

    W = sstr.shape[1]
    pix_l: list[np.ndarray] = []
    lab_l: list[np.ndarray] = []
    n_lab = 0
    for (a0, b0, a1, b1) in regions:
        on = (sstr[b0:b1, a0:a1] > 0).view(np.uint8)
        n_r, labels = cv2.connectedComponents(on, connectivity=8, ltype=cv2.CV_32S)
        loc = np.flatnonzero(on)
        if loc.size:
            r, c = np.divmod(loc, a1 - a0)
            pix_l.append((r + b0) * W + (c + a0))
            lab_l.append(labels.ravel()[loc] + n_lab)
        n_lab += n_r
    if not pix_l:
        return None
    pix = np.concatenate(pix_l)
    lab = np.concatenate(lab_l)
    st = sstr.ravel()[pix]
    maxs = np.zeros(n_lab)
    np.maximum.at(maxs, lab, st)
    keep = maxs[lab] >= hi
    pix, st = pix[keep], st[keep]
    if pix.size == 0:
        return None
    return pix, st


def _linked_points(gray, pix, st, maps: _RidgeMaps, core_map, sc: _StripeScales):
    """The points ``pix`` linked into ordered curves, their normals (saturated cores': from their
    neighbours), widths and backgrounds; also which are cores and the cores' run lengths."""
    H, W = gray.shape
    index_map = _BUFFERS.index_map
    pv, pu = np.divmod(pix, W)
    N = pix.size
    index_map.ravel()[pix] = np.arange(N)
    order = np.empty(N, np.int64)
    curve = np.empty(N, np.int64)
    K.link_points(index_map, pu, pv, maps.su, maps.sv, order, curve, 2.9)
    index_map.ravel()[pix] = -1          # leave the shared buffer all -1 again
    uv = np.column_stack([maps.su.ravel()[pix], maps.sv.ravel()[pix]]).astype(np.float64)[order]
    nrm = np.column_stack([maps.snu.ravel()[pix], maps.snv.ravel()[pix]]).astype(np.float64)[order]
    st = st[order].astype(np.float64)
    cid = curve[order]
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    is_core = np.zeros(uv.shape[0], bool)
    core_len = None
    if core_map is not None:
        core_len = core_map.ravel()[pix][order]
        is_core = np.isfinite(core_len)
        if is_core.any():
            nrm = _core_normals(uv, nrm, cid, is_core)
    width = np.empty(uv.shape[0])
    bg = np.empty((uv.shape[0], 3))
    K.normal_profiles(gray, uv, nrm, 1.5 * sc.w + 3.0 + 2.0 * sc.sigma, 0.5, width, bg)
    return _CurvePoints(uv, nrm, st, width, bg, cid), is_core, core_len


def _stripe_curves(image, gray, pts: _CurvePoints, is_core, core_len, sc: _StripeScales,
                   options: StripePointsOptions) -> _CurvePoints | None:
    """The stripe points of ``pts`` (contrast, width, colour), their curves split where points were
    dropped, curves shorter than ``min_length`` and overshadowed ones left out; None when none is left."""
    H, W = gray.shape
    w = sc.w
    uv, nrm, width, bg = pts.uv, pts.nrm, pts.width, pts.bg
    # a stripe point: contrast above min_contrast, width near the stripe's (thin
    # residual edges of a background subtraction and broad glow are not stripes)
    contrast = bg[:, 2] - 0.5 * (bg[:, 0] + bg[:, 1])
    keep = (contrast >= sc.mc) & (width >= 0.4 * w) & (width <= 2.5 * w + 2.0)
    if is_core.any():
        # a saturated core: its extent across the stripe is its width; the channel's profile dips there
        width[is_core] = core_len[is_core] * np.max(np.abs(nrm[is_core]), axis=1)
        keep |= is_core
    if options.min_chroma is not None:
        steps = np.arange(-int(math.ceil(w)), int(math.ceil(w)) + 1)
        cols = np.clip(np.round(uv[:, :1] + steps[None, :] * nrm[:, :1]).astype(np.int64), 0, W - 1)
        rows = np.clip(np.round(uv[:, 1:] + steps[None, :] * nrm[:, 1:]).astype(np.int64), 0, H - 1)
        if image.ndim != 3:
            raise LightplaneError("min_chroma needs a colour (H, W, 3) image")
        keep &= (_chroma(image, rows, cols) >= float(options.min_chroma)) | is_core
    core = is_core if is_core.any() else None
    kept = _split_runs(pts, keep, int(options.min_length), bool(options.reject_fragments))
    if kept is None:
        return None
    pts, sel = kept
    if options.reject_fragments:
        # first the ends that run onto edges, then whole curves that are not the stripe's kind
        for rule in (_ragged_ends, _stripe_like):
            core = None if core is None else core[sel]
            kept = _split_runs(pts, rule(pts, core, w), int(options.min_length), False)
            if kept is None:
                return None
            pts, sel = kept
    sw = options.suppress_weaker
    if sw is not None and float(sw) > 0 and pts.cid.size:
        good = _drop_overshadowed(pts.uv, pts.nrm, pts.st, pts.cid, (H, W), _SHADOW_REACH_WIDTHS * w, 1.5 * w + 2.0,
                                  1.0 / float(sw))
        if not good.all():
            pts = pts.take(good)
            if pts.cid.size == 0:
                return None
    return pts


def _split_runs(pts: _CurvePoints, keep: np.ndarray, min_length: int, kinks: bool):
    """The points ``keep`` of ``pts``, their curves split where points were dropped (and with
    ``kinks`` where the normal turns by more than 45 degrees at once), runs shorter than
    ``min_length`` left out, numbered 0..; also their indices in ``pts``.  None when none is left."""
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        return None
    brk = np.ones(idx.size, bool)
    brk[1:] = (np.diff(idx) != 1) | (np.diff(pts.cid[idx]) != 0)
    pts = pts.take(idx, renumber=False)
    if kinks:
        # a stripe's normal turns slowly; a texture edge that joins it turns at once, and stays
        # turned (the normals two points before and after differ too: not one speckled point)
        turn = np.abs(np.sum(pts.nrm[1:] * pts.nrm[:-1], axis=1)) < _KINK_COS
        turn[1:-1] &= np.abs(np.sum(pts.nrm[3:] * pts.nrm[:-3], axis=1)) < _KINK_COS
        brk[1:] |= turn
    cid = np.cumsum(brk) - 1
    good = np.bincount(cid)[cid] >= min_length
    if not good.any():
        return None
    pts = _CurvePoints(pts.uv, pts.nrm, pts.st, pts.width, pts.bg, cid).take(good)
    return pts, idx[good]


# fragments (StripePointsOptions.reject_fragments)
_KINK_COS = math.cos(math.radians(45.0))   # a curve splits where its normal turns more than this at once
_WEAK_CONTRAST = 0.5       # of the reference stripe's contrast: a weak point (at a curve's end) ...
_THIN = 0.3                # ... and this much (relative) narrower than the reference: an edge residual
_FAINT_CONTRAST = 0.75     # of the reference contrast: a faint curve, dropped when thin ...
_SHORT_CHAIN = 0.25        # ... or when its chain is shorter than this fraction of the reference chain
_CHAIN_GAP_WIDTHS = 3.0    # curves continue one another across gaps of up to max(3 w, 10) px ...
_CHAIN_COS = math.cos(math.radians(30.0))   # ... when their end tangents agree within 30 degrees
_END_COS = math.cos(math.radians(20.0))     # a curve's end whose normal turns this far runs along an edge


def _curve_ends(uv: np.ndarray, cid: np.ndarray, reach: int):
    """Per curve: its first and last point and the outward unit tangents there (from the point
    ``reach`` points inside, or the curve's other end when shorter)."""
    change = np.flatnonzero(np.diff(cid)) + 1
    starts = np.concatenate([[0], change])
    ends = np.concatenate([change, [cid.size]]) - 1
    k = np.minimum(reach, ends - starts)
    p0, p1 = uv[starts], uv[ends]
    t0 = p0 - uv[starts + k]
    t1 = p1 - uv[ends - k]
    for t in (t0, t1):
        n = np.linalg.norm(t, axis=1, keepdims=True)
        t /= np.where(n > 0, n, 1.0)
    return np.concatenate([p0, p1]), np.concatenate([t0, t1])


def _chains(uv: np.ndarray, cid: np.ndarray, w: float) -> np.ndarray:
    """Chain label per curve: curves that continue one another across a gap (an end within
    ``max(3 w, 10)`` px of another curve's end, both end tangents pointing at each other within
    30 degrees) share a label: one stripe broken by dark or occluded stretches."""
    C = int(cid.max()) + 1
    ends, tang = _curve_ends(uv, cid, max(3, int(math.ceil(2.0 * w))))
    owner = np.concatenate([np.arange(C), np.arange(C)])
    d = ends[None, :, :] - ends[:, None, :]                  # from end i to end j
    dist = np.linalg.norm(d, axis=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        dirn = d / dist[..., None]
    toward = np.sum(tang[:, None, :] * dirn, axis=2)          # end i's tangent towards end j
    facing = (toward >= _CHAIN_COS) & (toward.T >= _CHAIN_COS)
    close = dist <= max(_CHAIN_GAP_WIDTHS * w, 10.0)
    # ends that touch (< 1.5 px): their tangents must be opposed (a continuation, not a branch)
    touch = (dist < 1.5) & (np.sum(tang[:, None, :] * tang[None, :, :], axis=2) <= -_CHAIN_COS)
    link = close & (facing | touch) & (owner[:, None] != owner[None, :])
    label = np.arange(C)
    for i, j in zip(*np.nonzero(np.triu(link))):
        a, b = label[owner[i]], label[owner[j]]
        if a != b:
            label[label == b] = a
    return label


@dataclass(frozen=True)
class _Reference:
    """The main stripe of :func:`_stripe_like`: per point ``contrast``; per curve median ``con``,
    median width ``wid``, ``chain`` label and its chain's points ``chain_n``; ``in_ref`` the
    curves of the reference chain, its contrast ``ref_con``, width ``ref_w`` and points ``ref_n``."""

    contrast: np.ndarray
    con: np.ndarray
    wid: np.ndarray
    chain: np.ndarray
    chain_n: np.ndarray
    in_ref: np.ndarray
    ref_con: float
    ref_w: float
    ref_n: float


def _reference(pts: _CurvePoints, w: float) -> _Reference:
    """The curves' contrast, width and chains (:func:`_chains`), and the chain of the largest
    total contrast (the main stripe)."""
    cid = pts.cid
    contrast = pts.bg[:, 2] - 0.5 * (pts.bg[:, 0] + pts.bg[:, 1])
    C = int(cid.max()) + 1
    order = np.argsort(cid, kind="stable")
    bounds = np.searchsorted(cid[order], np.arange(C + 1))
    con = np.array([np.median(contrast[order[bounds[c]:bounds[c + 1]]]) for c in range(C)])
    wid = np.array([_nanmedian(pts.width[order[bounds[c]:bounds[c + 1]]]) for c in range(C)])
    n = np.bincount(cid, minlength=C)
    chain = _chains(pts.uv, cid, w)
    chain_n = np.bincount(chain, weights=n)
    ref = int(np.argmax(np.bincount(chain, weights=n * np.maximum(con, 0.0))))
    in_ref = chain == ref
    ref_w = _nanmedian(wid[in_ref])
    return _Reference(contrast, con, wid, chain, chain_n[chain], in_ref,
                      float(np.average(con[in_ref], weights=n[in_ref])), ref_w if np.isfinite(ref_w) else w,
                      float(chain_n[ref]))


def _ragged_ends(pts: _CurvePoints, is_core: np.ndarray | None, w: float) -> np.ndarray:
    """Keep mask without the curves' ends that run onto an edge residual: the runs of weak
    (under half the main stripe's contrast) and thin (30 % narrower than it) points at each end,
    and the points at each end whose normal turns (:func:`_turned_ends`)."""
    cid = pts.cid
    if cid.size == 0 or cid.max() == 0:
        return np.ones(cid.size, bool)
    r = _reference(pts, w)
    thin = (r.contrast < _WEAK_CONTRAST * r.ref_con) & ~(pts.width >= (1.0 - _THIN) * r.ref_w)
    drop = _turned_ends(pts.nrm, cid, max(3, int(math.ceil(w))), thin)
    if is_core is not None:
        drop &= ~is_core
    return ~drop


def _stripe_like(pts: _CurvePoints, is_core: np.ndarray | None, w: float) -> np.ndarray:
    """Keep mask of the points whose curve looks like a stripe rather than a texture fragment.

    Reference: the chain (:func:`_chains`) of the largest total contrast (the main stripe).  A
    curve is dropped when its median contrast is below 75 % of the reference's and either its
    median width is 30 % below the reference's (thin residual edges of a background
    subtraction) or its chain holds fewer than a quarter of the reference chain's
    points (short fragments on texture edges).  Curves with a saturated core are kept.
    """
    cid = pts.cid
    if cid.size == 0 or cid.max() == 0:
        return np.ones(cid.size, bool)
    r = _reference(pts, w)
    # a chain's width (a stripe's pieces together): the median over its points
    pch = r.chain[cid]
    cw = np.array([_nanmedian(pts.width[pch == c]) for c in range(int(r.chain.max()) + 1)])
    thin = ~(cw[r.chain] >= (1.0 - _THIN) * r.ref_w)
    frag = (r.con < _FAINT_CONTRAST * r.ref_con) & (thin | (r.chain_n < _SHORT_CHAIN * r.ref_n)) & ~r.in_ref
    if is_core is not None:
        frag[np.unique(cid[is_core])] = False
    return ~frag[cid]


def _turned_ends(nrm: np.ndarray, cid: np.ndarray, m: int, thin: np.ndarray) -> np.ndarray:
    """The runs of ``thin`` points at each curve's ends, and the points at its ends (within ``2 m``
    points) up to the last whose normal differs by more than 20 degrees from the normal ``m``
    points further in: where a stripe's end runs onto an edge that crosses it, its centres bend
    along the edge."""
    N = cid.size
    out = np.zeros(N, bool)
    first = np.ones(N, bool)
    first[1:] = cid[1:] != cid[:-1]
    last = np.ones(N, bool)
    last[:-1] = cid[1:] != cid[:-1]
    # runs of thin points that touch an end: a run's start is an end, or its end is an end
    run_id = np.cumsum(np.concatenate([[True], (thin[1:] != thin[:-1]) | first[1:]]))
    touch = np.zeros(int(run_id.max()) + 1, bool)
    touch[run_id[first | last]] = True
    out |= thin & touch[run_id]
    change = np.flatnonzero(np.diff(cid)) + 1
    starts = np.concatenate([[0], change])
    ends = np.concatenate([change, [N]])
    for s0, e0 in zip(starts, ends):
        n = e0 - s0
        if n < 2 * m + 1:
            continue
        z = min(2 * m, n - m)
        head = np.arange(s0, s0 + z)
        tail = np.arange(e0 - z, e0)
        bad_h = np.abs(np.sum(nrm[head] * nrm[head + m], axis=1)) < _END_COS
        bad_t = np.abs(np.sum(nrm[tail] * nrm[tail - m], axis=1)) < _END_COS
        if bad_h.any():
            out[s0:head[np.flatnonzero(bad_h)[-1]] + 1] = True
        if bad_t.any():
            out[tail[np.flatnonzero(bad_t)[0]]:e0] = True
    return out


def _nanmedian(x: np.ndarray) -> float:
    """Median of the finite values of ``x``; NaN when there are none."""
    x = x[np.isfinite(x)]
    return float(np.median(x)) if x.size else float("nan")


CURVATURE_SIGMA2_EXTRA = 1.0 / 12.0


def _stripe_cores(image, img, channel, maps: _RidgeMaps, hi, w, resp, min_chroma):
    """Put the centres of saturated (whitish) stripe cores into the ridge-point maps.

    Guarded so that only a laser's saturated core qualifies (:func:`K.saturated_core_runs`):
    whitish pixels as bright (B + G + R) as the stripe's typical peak in its own channel
    (the median of the channel at the ridge points reaching ``high``), a run across the
    stripe at most ``2.5 w + 2`` px long (no broad white light), laser-coloured pixels
    within ``w + 2`` px on both sides.  Runs down the columns serve stripes closer to
    horizontal, runs along the rows the others (the shorter run of the two is across
    the stripe).  Ridge points of the channel within ``2 w + 3`` px of a core (the flanks
    of its dip) are replaced by the core's midpoints.  Returns the (H, W) map of core
    run lengths (NaN elsewhere), or None when there is no core.
    """
    import cv2

    sstr, su, sv, snu, snv = maps.sstr, maps.su, maps.sv, maps.snu, maps.snv
    strong = sstr >= hi
    if not strong.any():
        return None
    ref = float(np.median(img[strong]))
    if not ref > 0:
        return None
    ch = {"blue": 0, "green": 1, "red": 2}[channel]
    bgr = kernel_pixels(np.ascontiguousarray(image[:, :, :3]))   # the kernels take uint8 or float32
    H, W = img.shape
    max_len = 2.5 * w + 2.0
    reach = int(math.ceil(w)) + 2
    args = (ch, float(min_chroma), ref, 0.5 * ref, 0.25 * ref, max_len, reach)
    cc = np.full((H, W), np.nan)
    cl = np.full((H, W), np.inf)
    K.saturated_core_runs(bgr, *args, cc, cl)
    rc = np.full((W, H), np.nan)
    rl = np.full((W, H), np.inf)
    K.saturated_core_runs(np.ascontiguousarray(bgr.transpose(1, 0, 2)), *args, rc, rl)
    rc, rl = rc.T, rl.T
    has_c, has_r = np.isfinite(cc), np.isfinite(rc)
    if not (has_c.any() or has_r.any()):
        return None
    k5 = np.ones((5, 5), np.uint8)
    use_c = has_c & (cl <= cv2.erode(rl.astype(np.float32), k5))
    use_r = has_r & (rl < cv2.erode(cl.astype(np.float32), k5)) & ~use_c
    core = use_c | use_r
    if not core.any():
        return None
    d = 2 * (2 * int(math.ceil(w)) + 3) + 1
    near = cv2.dilate(core.view(np.uint8), np.ones((d, d), np.uint8)) > 0
    sstr[near & ~core] = 0.0
    vv, uu = np.nonzero(use_c)
    su[vv, uu] = uu
    sv[vv, uu] = cc[vv, uu]
    vv, uu = np.nonzero(use_r)
    su[vv, uu] = rc[vv, uu]
    sv[vv, uu] = vv
    sstr[core] = resp * ref
    snu[use_c], snv[use_c] = 0.0, 1.0
    snu[use_r], snv[use_r] = 1.0, 0.0
    out = np.full((H, W), np.nan)
    out[use_c] = cl[use_c]
    out[use_r] = rl[use_r]
    return out


def _core_normals(uv, nrm, cid, is_core):
    """Normals of core points: perpendicular to the chord between their neighbours on the curve."""
    nrm = nrm.copy()
    N = uv.shape[0]
    i = np.flatnonzero(is_core)
    a = np.clip(i - 2, 0, N - 1)
    b = np.clip(i + 2, 0, N - 1)
    a = np.where(cid[a] == cid[i], a, i)
    b = np.where(cid[b] == cid[i], b, i)
    t = uv[b] - uv[a]
    L = np.linalg.norm(t, axis=1)
    ok = L > 0
    n = np.column_stack([-t[:, 1], t[:, 0]])
    n[ok] /= L[ok, None]
    n[~ok] = [0.0, 1.0]
    flip = (n[:, 1] < 0) | ((n[:, 1] == 0) & (n[:, 0] < 0))
    n[flip] *= -1
    nrm[i] = n
    return nrm


def _curvature_vectors(uv: np.ndarray, starts: np.ndarray, ends: np.ndarray, m: int) -> np.ndarray:
    """Curvature vector (towards the centre of curvature, length kappa, 1/px) of ordered curves.

    From the sagitta of the chord between the points ``m`` before and after:
    ``kappa_vec = 8 ((a + c) / 2 - b) / |c - a|^2``; points within ``m`` of a curve's
    end take the value of the nearest point that has both neighbours; curves with
    fewer than ``2 m + 1`` points get 0.
    """
    N = uv.shape[0]
    out = np.zeros((N, 2))
    idx = np.arange(N)
    for s0, e0 in zip(starts, ends):
        n = e0 - s0
        if n < 2 * m + 1:
            continue
        j = np.clip(idx[s0:e0], s0 + m, e0 - 1 - m)
        a, b, c = uv[j - m], uv[j], uv[j + m]
        L2 = np.sum((c - a) ** 2, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            kv = 8.0 * (0.5 * (a + c) - b) / L2[:, None]
        out[s0:e0] = np.where(np.isfinite(kv), kv, 0.0)
    return out


def _profile_curvature(uv, nrm, valid, sigma, m, k):
    """:func:`_correct_curvature` for a profile: neighbours ``m`` lines before and after.

    The shift ``delta`` along the normal is applied along the line (coordinate ``k``,
    ``delta / n_k``), so the centre stays on its column (row).
    """
    L = uv.shape[0]
    if L < 2 * m + 1:
        return uv
    i = np.arange(m, L - m)
    ok = valid[i] & valid[i - m] & valid[i + m]
    a, b, c = uv[i - m], uv[i], uv[i + m]
    L2 = np.sum((c - a) ** 2, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        kn = np.sum(8.0 * (0.5 * (a + c) - b) * nrm[i], axis=1) / L2
    kn = np.where(ok & np.isfinite(kn), kn, 0.0)
    out = uv.copy()
    out[i, k] -= 0.5 * (sigma**2 + CURVATURE_SIGMA2_EXTRA) * kn / nrm[i, k]
    return out


def _correct_curvature(uv, nrm, cid, sigma):
    """Undo the inward shift ``(sigma^2 + 1/12) kappa / 2`` of Gaussian smoothing on curved lines.

    Smoothing a curved ridge of radius ``rho`` (heat equation to first order:
    ``r = P + (sigma^2 / 2) P' / rho``) moves its maximum ``sigma^2 / (2 rho)``
    towards the centre of curvature; 1/12 px^2 is the pixel's own variance.
    """
    change = np.flatnonzero(np.diff(cid)) + 1
    starts = np.concatenate([[0], change])
    ends = np.concatenate([change, [cid.size]])
    m = max(5, int(math.ceil(4.0 * sigma)))
    kv = _curvature_vectors(uv, starts, ends, m)
    shift = 0.5 * (sigma**2 + CURVATURE_SIGMA2_EXTRA) * np.sum(kv * nrm, axis=1)
    return uv - shift[:, None] * nrm


def _correct_asymmetry(gray, uv, nrm, width, bg, sigma):
    """Remove the bar-model shift ``l = -sigma^2 ln(1 - a) / (2 w)`` (Steger 1998 §4) along ``n``."""
    import cv2

    # peak height: the image at the centre (bilinear)
    mapx = uv[:, 0].astype(np.float32).reshape(-1, 1)
    mapy = uv[:, 1].astype(np.float32).reshape(-1, 1)
    peak = cv2.remap(gray, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).ravel().astype(float)
    b_minus, b_plus = bg[:, 0], bg[:, 1]
    lo_bg = np.minimum(b_minus, b_plus)
    h = peak - lo_bg
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.abs(b_plus - b_minus) / h
        half_w = 0.5 * width
        shift = -sigma**2 * np.log1p(-np.clip(a, 0.0, 0.9)) / (2.0 * half_w)
    shift = np.where(np.isfinite(shift), shift, 0.0)
    # the detected centre moved towards the brighter side; move it back
    sgn = np.where(b_plus > b_minus, 1.0, -1.0)
    return uv - (sgn * shift)[:, None] * nrm


def _smooth_along(uv: np.ndarray, nrm: np.ndarray, cid: np.ndarray, sigma_along: float):
    """Smooth each point's offset along its normal over its curve's neighbours: a local quadratic.

    For point ``i``, its neighbours ``j`` on the same curve within ``3 sigma_along`` (in
    order; the window truncated symmetrically at the curve's ends) give tangential
    coordinates ``t_j = (p_j - p_i)·tau_i`` and normal offsets ``h_j = (p_j - p_i)·n_i``;
    ``h = a + b t + c t^2`` is fitted with Gaussian weights and the point moves by ``a``
    along its normal.  A quadratic absorbs the curve's own bend (``c = kappa / 2``), so
    straight and curved lines alike stay where they are (no inward shift to correct);
    only the noise of the offsets is averaged.  Returns the moved points.
    """
    N = uv.shape[0]
    R = int(math.ceil(3.0 * sigma_along))
    if N == 0 or R < 1:
        return uv
    change = np.flatnonzero(np.diff(cid)) + 1
    starts = np.concatenate([[0], change])
    ends = np.concatenate([change, [N]])
    n_per = ends - starts
    idx = np.arange(N)
    s = np.repeat(starts, n_per)
    e = np.repeat(ends, n_per)
    # a quadratic is a circle only to second order: fitted with Gaussian weights of scale s to
    # h = kappa^3 t^4 / 8, its intercept is off by -3 s^4 kappa^3 / 8.  The scale shrinks where
    # the line bends so that this stays below ~0.001 px, and what is left of the circle's
    # shape beyond the quadratic is fitted too and taken off (below)
    m_k = max(5, int(math.ceil(2.0 * sigma_along)))
    kv = _curvature_vectors(uv, starts, ends, m_k)
    kap = np.linalg.norm(kv, axis=1)
    side = np.sign(np.sum(kv * nrm, axis=1))  # +1 where the normal points to the centre of curvature
    with np.errstate(divide="ignore"):
        sig = np.minimum(sigma_along, (0.0027 / np.maximum(kap, 1e-12) ** 3) ** 0.25)
    rad = 1.0 / np.maximum(kap, 1e-12)
    a = K.smooth_along_quadratic(np.ascontiguousarray(uv, dtype=np.float64), np.ascontiguousarray(nrm, dtype=np.float64),
                                 s.astype(np.int64), (e - 1).astype(np.int64), sig.astype(np.float64), R,
                                 rad.astype(np.float64), side.astype(np.float64))
    # the shift along the normal, applied along the grid line the point lies on (the axis
    # closer to the normal), so each point stays that line's crossing (module docstring)
    kx = (np.abs(nrm[:, 0]) > np.abs(nrm[:, 1])).astype(np.int64)
    out = uv.copy()
    out[idx, 1 - kx] += a / nrm[idx, 1 - kx]
    return out


def _drop_overshadowed(uv, nrm, st, cid, shape, reach, min_gap, ratio):
    """Keep curves unless most of their points have a stronger, longer line alongside.

    Alongside: on the point's normal, between ``min_gap`` and ``reach`` px away (either
    side), a centre point of another curve (3x3 px neighbourhood) whose median ridge
    strength reaches ``ratio`` times the curve's own and which holds at least twice as
    many points (a whole-curve comparison: a stripe that dims locally, under glare,
    still overshadows the reflection next to it).  Returns the boolean keep mask.
    """
    import cv2

    H, W = shape
    keep = np.ones(uv.shape[0], bool)
    if uv.shape[0] == 0 or cid.max() == 0:
        return keep
    ij = np.clip(np.round(uv).astype(np.int64), 0, [W - 1, H - 1])
    n_pts = np.bincount(cid)
    lmap = np.zeros((H, W), np.float32)
    np.maximum.at(lmap, (ij[:, 1], ij[:, 0]), n_pts[cid].astype(np.float32))
    lmap = cv2.dilate(lmap, np.ones((3, 3), np.uint8))
    med = np.zeros(cid.max() + 1)
    for c in np.unique(cid):
        med[c] = np.median(st[cid == c])
    smap = np.zeros((H, W), np.float32)
    np.maximum.at(smap, (ij[:, 1], ij[:, 0]), med[cid].astype(np.float32))
    smap = cv2.dilate(smap, np.ones((3, 3), np.uint8))
    t = np.arange(math.ceil(min_gap), math.floor(reach) + 1, 1.0)
    t = np.concatenate([-t, t])
    q = uv[:, None, :] + t[None, :, None] * nrm[:, None, :]
    qu = np.clip(np.round(q[..., 0]).astype(np.int64), 0, W - 1)
    qv = np.clip(np.round(q[..., 1]).astype(np.int64), 0, H - 1)
    inside = (q[..., 0] >= -0.5) & (q[..., 0] < W - 0.5) & (q[..., 1] >= -0.5) & (q[..., 1] < H - 0.5)
    strong = (smap[qv, qu] >= ratio * med[cid][:, None]) & (lmap[qv, qu] >= 2.0 * n_pts[cid][:, None])
    shadowed = (inside & strong).any(axis=1)
    frac = np.bincount(cid, weights=shadowed.astype(float)) / np.bincount(cid)
    return frac[cid] < 0.5
