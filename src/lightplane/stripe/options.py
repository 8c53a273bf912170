"""Options of the stripe-centre extractors, checked on construction.

:class:`StripeOptions` -- :func:`lightplane.stripe.extract.extract_profile` and
:func:`~lightplane.stripe.extract.extract_profiles` (one centre per column or row, the
measurement path); :class:`StripePointsOptions` --
:func:`~lightplane.stripe.extract.extract_stripe` (every centre point of every line, linked
into curves: calibration).  Defaults derived from the image (width, thresholds) are
``None`` here and found per call.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lightplane.core.errors import LightplaneError

__all__ = ["StripeOptions", "StripePointsOptions"]

BACKENDS = ("numba", "numpy")


def _check_width(width_px, name="width_px") -> float | None:
    """A full stripe width (FWHM) in px between 0.5 and 200, as float; None stays None."""
    if width_px is None:
        return None
    w = float(width_px)
    if not (np.isfinite(w) and 0.5 <= w <= 200.0):
        raise LightplaneError(f"{name} must be a full stripe width in px between 0.5 and 200, got {width_px!r}")
    return w


def _check_scale(value, name: str, lo: float) -> None:
    """A given Gaussian scale in px between ``lo`` and 100 (None: derived per call)."""
    if value is None:
        return
    s = float(value)
    if not (np.isfinite(s) and lo <= s <= 100):
        raise LightplaneError(f"{name} must be between {lo:g} and 100 px, got {value!r}")


@dataclass(frozen=True)
class StripeOptions:
    """How :func:`~lightplane.stripe.extract.extract_profile` finds one centre per column (row).

    width_px : full stripe width (FWHM) in px; estimated from the frame when None.
    channel : ``"red"``, ``"green"``, ``"blue"``, ``"sum"`` (B + G + R) or None /
        ``"gray"`` (weighted gray).
    min_peak : minimum contrast (peak minus the local minimum within ~1.5 widths),
        in the image's grey levels; default 20/255 of full scale (20 for 8-bit).
    max_width_px : lines whose stripe is wider (glare, blooming) are invalid;
        default ``2.5 * width_px + 2``.
    sigma_px : Gaussian scale; default :func:`~lightplane.stripe.extract.sigma_for_width`.
    sigma_along_px : Gaussian scale across the lines, i.e. along a stripe that
        crosses them (default ``sigma_px``).  Larger values average laser speckle
        along the stripe without widening its profile; a straight stripe's centre
        stays unbiased at any tilt (the smoothing is point-symmetric).
    continuity : per line, take the second-highest peak (farther than twice the width
        from the highest: a reflection candidate) when only it agrees with the median
        of the neighbouring lines' peaks.
    min_cos : lines where the stripe normal makes ``|n . line direction| < min_cos``
        are invalid (the stripe runs along them).
    correct_curvature : remove the inward shift of curved stripes (see
        :func:`~lightplane.stripe.extract.extract_stripe`), curvature from the centres
        ``4 sigma`` lines away (only where both are valid).
    min_chroma : colour images only: a line is invalid (status ``WHITISH``)
        where a pixel of its stripe (within ``width_px`` of the centre, brighter
        than 30 % of the brightest there) has a colour saturation
        ``(max - min) / max`` of its B, G, R below this.  A laser's light is
        strongly coloured (a red laser's core may bloom into magenta, still
        saturated); grey-white pixels on the stripe are glare or sensor blooming
        (a specular hot spot), where the centre found is not the stripe's.  Off by
        default (ambient white light on a raw frame lowers it too); 0.5 suits
        background-subtracted frames.
    saturated_centre : with ``min_chroma``: instead of dropping whitish lines,
        centre them on the midpoint of the whitish run across the stripe (a
        saturated core turns grey-white; its midpoint is the standard centre of a
        saturated stripe), searched within ``w + 2`` px of the centre expected
        from the valid lines around; status ``OK`` then.  Recovers a specular
        hot spot in the laser's own channel (tests/test_stripe_real.py).
    backend : ``"numba"`` (fast) or ``"numpy"`` (same algorithm, same numbers).
    local_width : runs of lines where the stripe is much wider than ``width_px`` (a
        scattering material, defocus, a grazing angle) are measured again at their own
        width (:func:`~lightplane.stripe.extract.extract_profile`); False: one width for
        the whole frame.
    """

    width_px: float | None = None
    channel: str | None = None
    min_peak: float | None = None
    max_width_px: float | None = None
    sigma_px: float | None = None
    sigma_along_px: float | None = None
    continuity: bool = True
    min_cos: float = 0.3
    correct_curvature: bool = True
    min_chroma: float | None = None
    saturated_centre: bool = False
    backend: str = "numba"
    local_width: bool = True

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise LightplaneError(f"backend must be 'numba' or 'numpy', got {self.backend!r}")
        _check_width(self.width_px)
        _check_scale(self.sigma_px, "sigma_px", 0.3)
        _check_scale(self.sigma_along_px, "sigma_along_px", 0.3)


@dataclass(frozen=True)
class StripePointsOptions:
    """How :func:`~lightplane.stripe.extract.extract_stripe` finds the centre points of all bright lines.

    width_px : full stripe width (FWHM) px; estimated
        (:func:`~lightplane.stripe.extract.estimate_width`) when None.
    channel : ``"red"`` etc. or None for weighted gray.
    sigma_px : default :func:`~lightplane.stripe.extract.sigma_for_width`.
    low, high : hysteresis thresholds on the ridge strength ``-lambda``
        (grey levels / px^2); defaults: the response of a Gaussian stripe of width
        ``width_px`` and contrast ``min_contrast`` (``high``) and half of it (``low``).
    min_contrast : least stripe contrast (grey levels of the image as given);
        default 20/255 of the full scale.
    min_length : shortest curve kept, points.
    min_chroma : colour images only: drop points with whitish pixels on their
        stripe (glare, sensor bloom); see :class:`StripeOptions`.
    border_px : no points within this distance of the image border, where the
        replicated border biases the derivatives; default ``ceil(2 sigma)``.
    correct_asymmetry : remove the bar-model bias of stripes on asymmetric
        backgrounds (:mod:`lightplane.stripe.extract`'s docstring).
    correct_curvature : remove the inward shift ``sigma^2 kappa / 2`` of curved
        stripes, ``kappa`` from the linked curve.
    sigma_along_px : smoothing of the centres along their curve (points, ~px): each
        point's offset along its normal is replaced by the intercept of a local quadratic
        fitted, with Gaussian weights of this scale, to its neighbours' offsets (window
        truncated symmetrically at curve ends; the scale shrinks where the line bends, and
        the part of a circle beyond the quadratic is taken off, so straight and curved
        lines stay unbiased).  Default ``2 * width_px``: laser speckle on real photographs
        is correlated over a few px along the stripe, and Steger's minimum scale
        (``sigma_for_width``) does not average it (Ciclop board photos, inlier RMS about a
        straight line: 0.35-0.38 px without, 0.29-0.33 px with it); unlike a larger
        ``sigma_px`` it does not widen the profile across the stripe (no mixing of albedo
        edges, no extra border).  0 turns it off.
    suppress_weaker : drop a curve when, along its normal (``1.5 w + 2`` to ``12 w``
        px away) for most of its points, a curve at least ``1 / suppress_weaker``
        times stronger (median ridge strength) and twice as long runs alongside:
        reflections and glow lines next to a laser stripe.  Default 0.5; None keeps all.
    saturated_centre : centre saturated stripe cores on their whitish run (colour
        cameras render a saturated laser core grey-white; its own channel dips
        there).  Default (None): on for colour images with ``channel`` red, green
        or blue.  Guarded: the whitish run is at most ``2.5 w + 2`` px across, as
        bright (B + G + R) as the stripe's typical peak in its channel, and flanked on
        both sides by laser-coloured pixels within ``w + 2`` px, so white ambient light
        on a raw frame does not qualify.  Chroma threshold: ``min_chroma`` or 0.5.
    reject_fragments : None (the default): on when ``extract_stripe`` is given the laser-off frame
        (``background=``), off otherwise.  Without a laser-off frame it drops real stripe rows where
        a stripe is broken by dark print and bloomed where it is whole (FabScan's scans, boards);
        with one, the print's edges are read from that frame and dropped first
        (``drop_uneven_reflectance``), and what remains beside the stripe is laser light off its
        line (glare, reflections), which this rule removes.  A stripe is a long, continuous,
        consistently bright ridge; short
        responses on texture edges are not.  Curves split where their normal turns by more
        than 45 degrees at once (a texture edge that joins a stripe); curves that continue
        one another across gaps of up to ``max(3 w, 10)`` px (end tangents within 30 degrees)
        form a chain; the chain of the largest total contrast is the reference.  A curve's ends
        are trimmed where they run onto an edge (weak and thin points, or a normal that turns
        by more than 20 degrees); then curves under 75 % of the reference's contrast are
        dropped when their chain is 30 % narrower than the reference (the thin edge residuals
        of a laser-minus-background frame) or holds fewer than a quarter of its points (short
        fragments along a board's squares).  Saturated cores are kept.
    drop_uneven_reflectance : with a laser-off frame (``extract_stripe(..., background=)``), drop
        the centres where the surface's reflectance changes across the stripe
        (:func:`lightplane.stripe.extract.on_even_reflectance`): a printed or textured edge moves
        them towards its lighter side, and the edge residuals of a camera that moved between the
        frames lie there.  Default True; without a laser-off frame it has no effect.
    """

    width_px: float | None = None
    channel: str | None = None
    sigma_px: float | None = None
    low: float | None = None
    high: float | None = None
    min_contrast: float | None = None
    min_length: int = 10
    min_chroma: float | None = None
    border_px: int | None = None
    correct_asymmetry: bool = False
    correct_curvature: bool = True
    sigma_along_px: float | None = None
    suppress_weaker: float | None = 0.5
    saturated_centre: bool | None = None
    reject_fragments: bool | None = None
    drop_uneven_reflectance: bool = True

    def __post_init__(self) -> None:
        _check_width(self.width_px)
        _check_scale(self.sigma_px, "sigma_px", 0.3)
        _check_scale(self.sigma_along_px, "sigma_along_px", 0)
