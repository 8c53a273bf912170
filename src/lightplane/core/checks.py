"""The checks every file reader applies to the numbers it reads (docs/conventions.md §Limits on what is read).

Each function takes the value as read (from JSON, YAML, a CSV...), the field's name and
the file (``source``), and returns the value converted or raises :class:`LightplaneError`
with one line naming the file and the field: ``"cam.json: field 'width' must be an integer,
got 'abc'"``.  Strings are never numbers here, booleans are not numbers, and nothing that
is not finite passes.

>>> integer(1280.0, "width", "cam.json", lo=1)
1280
>>> integer(1.5, "width", "cam.json")
Traceback (most recent call last):
...
lightplane.core.errors.LightplaneError: cam.json: field 'width' must be an integer, got 1.5
"""

from __future__ import annotations

import numbers
from typing import Any

import numpy as np

from lightplane.core.errors import LightplaneError

__all__ = ["MAX_DISTANCE_MM", "UNIT_TOL", "COV_RTOL", "field_error", "mapping", "number", "integer", "array",
           "unit_vector", "covariance"]

#: the largest distance (mm) a file may give: a point, a translation, a plane's offset.  A cloud
#: stores float32 coordinates (resolution ~0.06 mm at 1 km), so farther points lose the precision
#: they are measured to; anything beyond is a corrupt or wrongly scaled file.
MAX_DISTANCE_MM = 1e6

#: a vector meant to be unit (a plane's normal, an axis direction) whose norm differs from 1 by
#: more than this is refused (a wrong field, not a rounding); within it, it is renormalised
UNIT_TOL = 1e-6

#: covariance tolerance, relative to the matrix's own scale: ``|C - Cᵀ|`` at most ``COV_RTOL``
#: times ``sqrt(C_ii C_jj)``, and the correlation matrix's least eigenvalue at least ``-COV_RTOL``
COV_RTOL = 1e-6


def _show(value: Any, limit: int = 40) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def field_error(source: str, field: str, what: str) -> LightplaneError:
    """The one-line error ``"{source}: field '{field}' {what}"``."""
    return LightplaneError(f"{source}: field '{field}' {what}")


def mapping(value: Any, field: str, source: str) -> dict:
    """``value`` if it is a JSON object / YAML mapping (a dict), else the error."""
    if not isinstance(value, dict):
        raise field_error(source, field, f"must be an object (a mapping of names to values), got {_show(value)}")
    return value


def number(value: Any, field: str, source: str, *, lo: float | None = None, hi: float | None = None,
           positive: bool = False) -> float:
    """A finite real number within ``[lo, hi]`` (``positive``: above 0)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise field_error(source, field, f"must be a number, got {_show(value)}")
    try:
        x = float(value)
    except OverflowError:
        x = float("inf")
    if not np.isfinite(x):
        raise field_error(source, field, f"must be a finite number, got {_show(value)}")
    if positive and not x > 0:
        raise field_error(source, field, f"must be positive, got {x:g}")
    if (lo is not None and x < lo) or (hi is not None and x > hi):
        raise field_error(source, field, f"must be within [{_bound(lo)}, {_bound(hi)}], got {x:g}")
    return x


def _bound(b: float | None) -> str:
    return "-inf" if b is None else f"{b:g}"


def integer(value: Any, field: str, source: str, *, lo: int | None = None, hi: int | None = None) -> int:
    """An integer within ``[lo, hi]`` (a float with an integral value, e.g. ``1280.0``, is one)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise field_error(source, field, f"must be an integer, got {_show(value)}")
    if isinstance(value, numbers.Integral):
        n = int(value)
    else:
        x = float(value)
        if not (np.isfinite(x) and x == int(x)):
            raise field_error(source, field, f"must be an integer, got {_show(value)}")
        n = int(x)
    if (lo is not None and n < lo) or (hi is not None and n > hi):
        raise field_error(source, field, f"must be an integer within [{_bound(lo)}, {_bound(hi)}], got {n}")
    return n


def array(value: Any, field: str, source: str, shape: tuple[int | None, ...] | None = None, *,
          max_abs: float | None = None) -> np.ndarray:
    """A float64 array of finite numbers, of ``shape`` (None in it: any length) when given, every entry
    at most ``max_abs`` in magnitude when given."""
    what = "numbers" if shape is None else _shape_words(shape)
    try:
        a = np.asarray(value)
    except (TypeError, ValueError, OverflowError):  # ragged nesting
        raise field_error(source, field, f"must be {what}, got {_show(value)}") from None
    if a.dtype.kind not in "iuf" or a.dtype == np.bool_:
        raise field_error(source, field, f"must be {what}, got {_show(value)}")
    a = a.astype(np.float64)
    if shape is not None and (a.ndim != len(shape) or any(n is not None and n != m for n, m in zip(shape, a.shape))):
        raise field_error(source, field, f"must be {what}, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise field_error(source, field, "must hold finite numbers (no NaN, no infinity)")
    if max_abs is not None and a.size and np.max(np.abs(a)) > max_abs:
        raise field_error(source, field, f"must hold numbers of at most {max_abs:g} in magnitude, got "
                                         f"{np.max(np.abs(a)):g}")
    return a


def _shape_words(shape: tuple[int | None, ...]) -> str:
    if len(shape) == 1:
        return "a list of numbers" if shape[0] is None else f"{shape[0]} numbers"
    return "a " + "x".join("N" if n is None else str(n) for n in shape) + " matrix of numbers"


def unit_vector(value: Any, field: str, source: str, n: int = 3, tol: float = UNIT_TOL) -> np.ndarray:
    """A unit ``n``-vector: its norm within ``tol`` of 1 (renormalised), else the error."""
    v = array(value, field, source, (n,))
    with np.errstate(over="ignore"):  # a huge entry: an infinite norm, refused below
        norm = float(np.linalg.norm(v))
    if not abs(norm - 1.0) <= tol:
        raise field_error(source, field, f"must be a unit vector (norm 1 within {tol:g}), got norm {norm:.9g}")
    return v / norm


def covariance(value: Any, field: str, source: str, n: int, *, max_sd: Any = MAX_DISTANCE_MM,
               rtol: float = COV_RTOL) -> np.ndarray:
    """An ``n``x``n`` covariance: finite, symmetric and positive semi-definite within ``rtol`` of its own
    scale (tested on the correlation matrix, so parameters of very different units weigh alike),
    every standard deviation at most ``max_sd`` (a number or one per row).  Returned symmetrised."""
    C = array(value, field, source, (n, n))
    var = np.diag(C).copy()
    top = float(np.max(np.abs(var), initial=0.0))
    if np.any(var < -rtol * top):
        i = int(np.argmin(var))
        raise field_error(source, field, f"is not a covariance: negative variance {var[i]:g} on the diagonal "
                                         f"(row {i + 1})")
    var = np.maximum(var, 0.0)
    sd = np.sqrt(var)
    cap = np.broadcast_to(np.asarray(max_sd, np.float64), (n,))
    if np.any(sd > cap):
        i = int(np.argmax(sd / cap))
        raise field_error(source, field, f"holds a standard deviation of {sd[i]:g} (row {i + 1}), more than "
                                         f"{cap[i]:g}: not a calibration's uncertainty")
    scale = np.sqrt(np.outer(var, var))
    if np.any(np.abs(C - C.T) > rtol * scale + 1e-300) or np.any(np.abs(C) > scale * (1 + rtol) + 1e-300):
        raise field_error(source, field, "is not a covariance: not symmetric, or an off-diagonal entry exceeds "
                                         "the product of its standard deviations")
    C = 0.5 * (C + C.T)
    keep = sd > 0
    if np.any(keep):
        R = C[np.ix_(keep, keep)] / np.outer(sd[keep], sd[keep])
        least = float(np.linalg.eigvalsh(R).min())
        if least < -rtol * max(1.0, float(keep.sum())):
            raise field_error(source, field, f"is not a covariance: not positive semi-definite (correlation "
                                             f"eigenvalue {least:.3g})")
    return C
