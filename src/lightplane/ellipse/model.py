"""The project's one ellipse type, conic conversions and ellipse fitting (docs/method.md §Ellipse).

Conventions (docs/conventions.md §Pixels): pixel ``(u, v)``, x right, y down, ``(0, 0)`` the centre of
the top-left pixel.  ``angle`` is the direction of the major semi-axis ``a``,
measured from +x towards +y (the same sense as ``cv2.ellipse``), in ``[0, pi)``.

The conic ``C`` (3x3, symmetric) satisfies ``[u v 1] C [u v 1]^T = 0`` on the
ellipse; it is normalised to unit Frobenius norm with the sign chosen so that the
interior is negative (upper-left 2x2 block positive definite).

>>> e = Ellipse.from_params((100.0, 50.0), 20.0, 10.0, 0.3)
>>> bool(np.allclose(Ellipse.from_conic(e.conic).centre, (100, 50)))
True
>>> e2 = Ellipse.from_cv_rotated_rect(e.to_cv_rotated_rect())
>>> bool(abs(e2.a - 20) < 1e-9 and abs(e2.angle - 0.3) < 1e-9)
True
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from lightplane.core.errors import LightplaneError
from lightplane.core.geometry import Failure, fit_conic
from lightplane.core.geometry import sampson_distance  # noqa: F401  (re-exported: lightplane.ellipse.sampson_distance)

__all__ = [
    "Ellipse",
    "conic_from_params",
    "params_from_conic",
    "normalize_conic",
    "fit_ellipse_direct",
    "fit_ellipse_geometric",
    "sampson_distance",
]


def normalize_conic(C: np.ndarray) -> np.ndarray:
    """Unit Frobenius norm, sign such that the upper-left 2x2 block has positive trace."""
    C = np.asarray(C, dtype=np.float64)
    C = 0.5 * (C + C.T)
    n = np.linalg.norm(C)
    if not np.isfinite(n) or n == 0:
        raise LightplaneError("conic must be a finite non-zero 3x3 matrix")
    C = C / n
    if C[0, 0] + C[1, 1] < 0:
        C = -C
    return C


def conic_from_params(centre, a: float, b: float, angle: float) -> np.ndarray:
    """Normalised conic (3x3) of the ellipse ``centre`` (u, v) px, semi-axes a, b px, ``angle`` rad."""
    cx, cy = float(centre[0]), float(centre[1])
    c, s = math.cos(angle), math.sin(angle)
    # Quadratic form M = R diag(1/a^2, 1/b^2) R^T, R = [[c, -s], [s, c]].
    ia, ib = 1.0 / (a * a), 1.0 / (b * b)
    A = c * c * ia + s * s * ib
    B = c * s * (ia - ib)
    Cc = s * s * ia + c * c * ib
    M = np.array([[A, B], [B, Cc]])
    x0 = np.array([cx, cy])
    t = -M @ x0
    f = x0 @ M @ x0 - 1.0
    C = np.array([[A, B, t[0]], [B, Cc, t[1]], [t[0], t[1], f]])
    return normalize_conic(C)


def params_from_conic(C: np.ndarray) -> tuple[np.ndarray, float, float, float]:
    """``(centre (2,), a, b, angle)`` of a real ellipse conic; raises LightplaneError otherwise."""
    C = np.asarray(C, dtype=np.float64)
    if C.shape != (3, 3) or not np.all(np.isfinite(C)):
        raise LightplaneError(f"conic must be a finite (3, 3) array, got shape {C.shape}")
    C = normalize_conic(C)
    M = C[:2, :2]
    if np.linalg.det(M) <= 0:
        raise LightplaneError("conic is not an ellipse (upper-left block not definite)")
    x0 = -np.linalg.solve(M, C[:2, 2])
    f = C[2, 2] + C[:2, 2] @ x0  # value at the centre
    if not f < 0:
        raise LightplaneError("conic is an imaginary or degenerate ellipse")
    w, V = np.linalg.eigh(M)  # ascending: w[0] belongs to the major axis
    a = math.sqrt(-f / w[0])
    b = math.sqrt(-f / w[1])
    angle = math.atan2(V[1, 0], V[0, 0]) % math.pi
    return x0, a, b, angle


@dataclass(frozen=True, eq=False)
class Ellipse:
    """An ellipse in pixel coordinates.

    Attributes
    ----------
    centre : (2,) float64, px.  ``a >= b > 0`` semi-axes px.  ``angle`` rad in [0, pi).
    conic : (3, 3) float64, normalised (see module doc).
    score : detection score in [0, 1] (inlier ratio x coverage), 0 if not detected.
    inlier_ratio : fraction of ellipse samples supported by an edge of the right direction.
    coverage : angular coverage in [0, 1] of the supported samples.
    polarity : +1 interior brighter than outside, -1 darker, 0 unknown.
    """

    centre: np.ndarray
    a: float
    b: float
    angle: float
    conic: np.ndarray = field(repr=False)
    score: float = 0.0
    inlier_ratio: float = 0.0
    coverage: float = 0.0
    polarity: int = 0

    # -- constructors -----------------------------------------------------
    @classmethod
    def from_params(cls, centre, a: float, b: float, angle: float, **kw) -> "Ellipse":
        """Build from centre (px), semi-axes (px, any order) and angle of ``a`` (rad)."""
        centre = np.asarray(centre, dtype=np.float64).reshape(-1)
        if centre.shape != (2,) or not np.all(np.isfinite(centre)):
            raise LightplaneError(f"centre must be 2 finite numbers, got {centre}")
        a, b, angle = float(a), float(b), float(angle)
        if not (a > 0 and b > 0 and math.isfinite(a) and math.isfinite(b) and math.isfinite(angle)):
            raise LightplaneError(f"semi-axes must be finite and > 0, got a={a}, b={b}")
        if b > a:
            a, b, angle = b, a, angle + math.pi / 2
        angle = angle % math.pi
        if angle >= math.pi:  # guard rounding of x % pi
            angle = 0.0
        C = conic_from_params(centre, a, b, angle)
        centre = centre.copy()
        centre.flags.writeable = False
        C.flags.writeable = False
        return cls(centre=centre, a=a, b=b, angle=angle, conic=C, **kw)

    @classmethod
    def from_conic(cls, C, **kw) -> "Ellipse":
        """Build from a 3x3 conic matrix (any scale/sign); raises LightplaneError if not an ellipse."""
        x0, a, b, angle = params_from_conic(C)
        return cls.from_params(x0, a, b, angle, **kw)

    @classmethod
    def from_cv_rotated_rect(cls, rect, **kw) -> "Ellipse":
        """From OpenCV's ``((cx, cy), (width, height), angle_deg)`` (full axes, degrees)."""
        try:
            (cx, cy), (w, h), ang = rect
        except (TypeError, ValueError) as exc:
            raise LightplaneError(f"rect must be ((cx, cy), (w, h), angle_deg), got {rect!r}") from exc
        return cls.from_params((cx, cy), 0.5 * w, 0.5 * h, math.radians(ang), **kw)

    # -- converters -------------------------------------------------------
    def to_cv_rotated_rect(self) -> tuple[tuple[float, float], tuple[float, float], float]:
        """OpenCV ``((cx, cy), (2a, 2b), angle_deg)``, usable by ``cv2.ellipse``."""
        return ((float(self.centre[0]), float(self.centre[1])), (2 * self.a, 2 * self.b), math.degrees(self.angle))

    def with_scores(self, **kw) -> "Ellipse":
        """Copy with some of score / inlier_ratio / coverage / polarity replaced."""
        return replace(self, **kw)

    def points(self, n: int = 64) -> np.ndarray:
        """``(n, 2)`` points on the ellipse at equally spaced parametric angles (px)."""
        t = np.linspace(0.0, 2 * math.pi, int(n), endpoint=False)
        return self.points_at(t)

    def points_at(self, t: np.ndarray) -> np.ndarray:
        """Points ``(N, 2)`` at parametric angles ``t`` (rad)."""
        t = np.asarray(t, dtype=np.float64)
        c, s = math.cos(self.angle), math.sin(self.angle)
        x, y = self.a * np.cos(t), self.b * np.sin(t)
        return np.column_stack([self.centre[0] + c * x - s * y, self.centre[1] + s * x + c * y])

    def normals_at(self, t: np.ndarray) -> np.ndarray:
        """Outward unit normals ``(N, 2)`` at parametric angles ``t``."""
        t = np.asarray(t, dtype=np.float64)
        c, s = math.cos(self.angle), math.sin(self.angle)
        nx, ny = self.b * np.cos(t), self.a * np.sin(t)
        n = np.column_stack([c * nx - s * ny, s * nx + c * ny])
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def algebraic(self, uv: np.ndarray) -> np.ndarray:
        """Normalised radial coordinate minus one: ``rho(uv) - 1`` (<0 inside), shape (N,)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        d = uv - self.centre
        c, s = math.cos(self.angle), math.sin(self.angle)
        x = (c * d[:, 0] + s * d[:, 1]) / self.a
        y = (-s * d[:, 0] + c * d[:, 1]) / self.b
        return np.sqrt(x * x + y * y) - 1.0

    def contains(self, uv: np.ndarray) -> np.ndarray:
        """Boolean ``(N,)``: which points ``uv`` (N, 2) px lie inside (or on) the ellipse."""
        return self.algebraic(uv) <= 0

    def scaled(self, factor: float) -> "Ellipse":
        """Same centre and angle, semi-axes multiplied by ``factor`` (> 0)."""
        if not factor > 0:
            raise LightplaneError(f"factor must be > 0, got {factor}")
        return Ellipse.from_params(self.centre, self.a * factor, self.b * factor, self.angle,
                                   score=self.score, inlier_ratio=self.inlier_ratio,
                                   coverage=self.coverage, polarity=self.polarity)

    def shrunk(self, shrink_px: float) -> "Ellipse | None":
        """Semi-axes reduced by ``shrink_px`` (None if nothing is left)."""
        a, b = self.a - shrink_px, self.b - shrink_px
        if b <= 0:
            return None
        return Ellipse.from_params(self.centre, a, b, self.angle)

    def mask(self, shape: tuple[int, int], shrink_px: float = 0.0) -> np.ndarray:
        """Boolean ``shape`` (H, W) mask of pixel centres inside the ellipse shrunk by ``shrink_px``."""
        if len(shape) < 2:
            raise LightplaneError(f"shape must be (H, W), got {shape}")
        h, w = int(shape[0]), int(shape[1])
        out = np.zeros((h, w), dtype=bool)
        e = self.shrunk(shrink_px) if shrink_px else self
        if e is None:
            return out
        u0, v0, u1, v1 = e.bbox()
        u0, v0 = max(int(math.floor(u0)), 0), max(int(math.floor(v0)), 0)
        u1, v1 = min(int(math.ceil(u1)), w - 1), min(int(math.ceil(v1)), h - 1)
        if u1 < u0 or v1 < v0:
            return out
        vv, uu = np.mgrid[v0:v1 + 1, u0:u1 + 1]
        inside = e.contains(np.column_stack([uu.ravel(), vv.ravel()])).reshape(uu.shape)
        out[v0:v1 + 1, u0:u1 + 1] = inside
        return out

    def bbox(self) -> tuple[float, float, float, float]:
        """Axis-aligned bounding box ``(u_min, v_min, u_max, v_max)`` px."""
        c, s = math.cos(self.angle), math.sin(self.angle)
        hw = math.hypot(self.a * c, self.b * s)
        hh = math.hypot(self.a * s, self.b * c)
        return (self.centre[0] - hw, self.centre[1] - hh, self.centre[0] + hw, self.centre[1] + hh)

    @property
    def area(self) -> float:
        """Area in px^2."""
        return math.pi * self.a * self.b

    @property
    def perimeter(self) -> float:
        """Perimeter in px (Ramanujan's second approximation)."""
        h = ((self.a - self.b) / (self.a + self.b)) ** 2
        return math.pi * (self.a + self.b) * (1 + 3 * h / (10 + math.sqrt(4 - 3 * h)))

    def __repr__(self) -> str:
        return (f"Ellipse(centre=({self.centre[0]:.3f}, {self.centre[1]:.3f}), a={self.a:.3f}, "
                f"b={self.b:.3f}, angle={math.degrees(self.angle):.2f} deg, score={self.score:.3f})")


# --------------------------------------------------------------------------
# Fitting
# --------------------------------------------------------------------------

def fit_ellipse_direct(uv: np.ndarray, weights: np.ndarray | None = None) -> "np.ndarray | Failure":
    """Halir–Flusser numerically stable direct least-squares ellipse fit.

    ``uv`` (N, 2) px, N >= 5; ``weights`` (N,) >= 0 optional.  Returns the normalised
    conic (3x3) or a :class:`~lightplane.core.geometry.Failure` with the reason when no real
    ellipse fits (degenerate data, bad shapes).  The fit is
    :func:`lightplane.core.geometry.fit_conic` (the package's one Halir–Flusser fit).
    """
    uv = np.asarray(uv, dtype=np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2:
        return Failure(f"uv must be an (N, 2) array, got shape {uv.shape}")
    if weights is not None:
        weights = np.asarray(weights, dtype=np.float64)
        if weights.shape != (len(uv),) or not np.all(weights >= 0):
            return Failure(f"weights must be ({len(uv)},) and >= 0")
    return fit_conic(uv, weights)


def _ortho_parts(params: np.ndarray, uv: np.ndarray):
    cx, cy, la, lb, ang = params
    A, B = math.exp(-2 * la), math.exp(-2 * lb)  # 1/a^2, 1/b^2
    c, s = math.cos(ang), math.sin(ang)
    d0 = uv[:, 0] - cx
    d1 = uv[:, 1] - cy
    x = c * d0 + s * d1
    y = -s * d0 + c * d1
    f = A * x * x + B * y * y - 1.0
    q = np.sqrt(A * A * x * x + B * B * y * y)
    g = 2.0 * np.maximum(q, 1e-12)
    return A, B, c, s, x, y, f, g


def _ortho_residuals(params: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Sampson distance (px) of ``uv`` (N, 2) to the ellipse params (cx, cy, log a, log b, angle):
    ``f / |grad f|`` with ``f = x^2/a^2 + y^2/b^2 - 1`` in the ellipse's frame."""
    *_, f, g = _ortho_parts(params, uv)
    return f / g


def _ortho_jacobian(params: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Analytic Jacobian (N, 5) of :func:`_ortho_residuals`."""
    A, B, c, s, x, y, f, g = _ortho_parts(params, uv)
    # derivatives of (x, y) w.r.t. cx, cy, angle; of (A, B) w.r.t. log a, log b
    dx = (-c, -s, 0.0, 0.0, y)
    dy = (s, -c, 0.0, 0.0, -x)
    dA = (0.0, 0.0, -2 * A, 0.0, 0.0)
    dB = (0.0, 0.0, 0.0, -2 * B, 0.0)
    J = np.empty((len(uv), 5))
    for k in range(5):
        df = 2 * A * x * dx[k] + 2 * B * y * dy[k] + x * x * dA[k] + y * y * dB[k]
        dQ = 2 * A * A * x * dx[k] + 2 * B * B * y * dy[k] + 2 * A * x * x * dA[k] + 2 * B * y * y * dB[k]
        dg = 2 * dQ / g
        J[:, k] = (df * g - f * dg) / (g * g)
    return J


def fit_ellipse_geometric(uv: np.ndarray, init: "Ellipse | np.ndarray", *, loss: str = "linear",
                          f_scale: float = 1.0) -> "tuple[np.ndarray, np.ndarray] | Failure":
    """Geometric refinement of an ellipse fit (Sampson distance in px, Levenberg–Marquardt).

    ``uv`` (N, 2) px, ``init`` an :class:`Ellipse` or conic. Returns ``(conic, residuals_px)``
    or a :class:`~lightplane.core.geometry.Failure` with the reason.  The Sampson distance equals
    the orthogonal distance to first order, which for edge points within a pixel of the curve is
    exact far below their noise.
    """
    from scipy.optimize import least_squares

    uv = np.asarray(uv, dtype=np.float64)
    if len(uv) < 6:
        return Failure(f"need at least 6 points for the geometric fit, got {len(uv)}")
    if not isinstance(init, Ellipse):
        try:
            init = Ellipse.from_conic(init)
        except LightplaneError as exc:
            return Failure(f"the starting conic is not an ellipse ({exc})")
    x0 = np.array([init.centre[0], init.centre[1], math.log(init.a), math.log(init.b), init.angle])
    try:
        res = least_squares(_ortho_residuals, x0, jac=_ortho_jacobian, args=(uv,),
                            method="lm" if loss == "linear" else "trf", loss=loss, f_scale=f_scale,
                            x_scale="jac", max_nfev=100)
    except (ValueError, np.linalg.LinAlgError) as exc:
        return Failure(f"the geometric fit failed ({exc})")
    if not np.all(np.isfinite(res.x)):
        return Failure("the geometric fit diverged (non-finite parameters)")
    cx, cy, la, lb, ang = res.x
    try:
        e = Ellipse.from_params((cx, cy), math.exp(la), math.exp(lb), ang)
    except LightplaneError as exc:
        return Failure(f"the geometric fit is not an ellipse ({exc})")
    return e.conic, _ortho_residuals(res.x, uv)
