"""Joint maximum-likelihood refinement of the light plane and every target pose (docs/method.md §ML refinement).

Goes beyond the paper's progressive fit (§2.2.3): with Gaussian noise on the
detected rim (ellipse edge) points and stripe centres, in *distorted* pixels, the
maximum-likelihood estimate minimises the weighted sum of squared image distances

- of every rim point of placement i to the image of the circle
  ``{X : |X - C_i| = r, N_i·(X - C_i) = 0}`` and
- of every stripe point of placement i to the image of the chord's line
  ``{X : n·X + d = 0, N_i·X - N_i·C_i = 0}``

over the plane ``(n, d)`` (3 degrees of freedom) and every pose ``(C_i, N_i)``
(5 each).  Rim and stripe points have their own noise sigma (a laser stripe's
centres scatter 2–4x more than edge points, and speckle correlates them along the
stripe), each estimated from its residuals with its degrees of freedom, Huber-robust;
weights ``1/(tau sigma²)`` with ``tau`` the residuals' integrated autocorrelation time;
covariance from a sandwich that stays honest under that correlation (see
:func:`refine_ml` for what it covers and what not).

Residuals (the choice, and why it is correct under distortion)
--------------------------------------------------------------
Both curves are algebraic in undistorted normalised coordinates ``x̃ = (x, y, 1)``:

- the circle's cone (the circle's points satisfy ``X = s x̃`` with
  ``s = N·C / N·x̃`` and ``|X − C|² = r²``), multiplied by ``(N·x̃)²``::

      f(x̃) = w² |x̃|² − 2 w (N·x̃)(C·x̃) + (|C|² − r²)(N·x̃)²,   w = N·C

  (the cone matrix ``Q = w² I − w (N Cᵀ + C Nᵀ) + (|C|² − r²) N Nᵀ``, cf. paper Eq. 7);
- the chord's line: the plane through the optical centre that contains it,
  ``m = h n − d N`` with ``h = −N·C``, so ``e(x̃) = m·x̃`` (paper Eq. 2/4).

Each observed point is undistorted exactly once (``Camera.undistort_points``);
its residual is the first-order (Sampson) distance *in distorted pixels*:
``f / |J⁻ᵀ ∇f|`` where ``J = ∂uv_distorted/∂(x, y)`` is the Jacobian of the
distortion and of ``K`` at the point.  To first order a small offset ``δ`` in
distorted pixels is ``J⁻¹ δ`` in normalised coordinates, so this equals the
orthogonal image distance of the point to the *distorted* projected curve up to
terms of order ``residual / curvature radius`` (~1e-3 relative for sub-pixel
noise and ellipses of > 50 px), with no per-point nuisance parameter.  It is
exactly zero on noise-free data, so the noise-free optimum is the truth.
The Jacobian is analytic (dense, ``(m, 3 + 5 n)``), checked against finite
differences in the tests; a small Levenberg–Marquardt loop on the normal equations
solves it (see :func:`_levenberg_marquardt` for why not ``least_squares``).

Parameterisation: the plane normal and each target normal are updated in their
tangent plane at the start value (``n = normalise(n0 + α t1 + β t2)``), so the
parameter count is minimal (3 + 5 n) and ``JᵀJ`` is invertible when the data
determine the geometry.

>>> import numpy as np
>>> from lightplane import Camera, LightPlane
>>> from lightplane.plane.ml import refine_ml, simulate_points
>>> cam = Camera([[4000., 0, 640], [0, 4000, 480], [0, 0, 1]], np.zeros(5), 1280, 960)
>>> plane = LightPlane([0.0, 0.9336, -0.3584], 140.04)
>>> centres = [np.array([x, 40.0 + 0.3 * x, 0.0]) for x in (-40.0, 0.0, 45.0)]
>>> centres = [c + np.array([0, 0, (c[1] * 0.9336 + 140.04) / 0.3584]) for c in centres]
>>> normals = [np.array(v) / np.linalg.norm(v) for v in ([0.3, 0.1, -1], [-0.2, 0.4, -1], [0.1, -0.3, -1])]
>>> rims, stripes = zip(*[simulate_points(cam, plane, c, n, 25.0, 100, 100) for c, n in zip(centres, normals)])
>>> res = refine_ml(cam, 25.0, list(rims), list(stripes), plane, [_Pose(c, n) for c, n in zip(centres, normals)])
>>> bool(np.linalg.norm(np.cross(res.plane.normal, plane.normal)) < 1e-9 and abs(res.plane.d - plane.d) < 1e-9)
True
>>> res.covariance.shape, len(res.poses)
((4, 4), 3)
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from lightplane.camera.model import Camera, as_points
from lightplane.core.errors import LightplaneError
from lightplane.core.geometry import robust_sigma, tls_line
from lightplane.plane.model import LightPlane
from lightplane.plane.circle_pose import CirclePose

__all__ = ["MLResult", "refine_ml", "crlb", "placement_information", "simulate_points", "plane_param_jacobian",
           "integrated_autocorr_time", "dispersion_factor"]


@dataclass(frozen=True)
class _Pose:
    """Minimal stand-in with ``center``/``normal`` (any object with these works as a pose)."""

    center: np.ndarray
    normal: np.ndarray


@dataclass(frozen=True)
class MLOptions:
    """Options of the joint maximum-likelihood refinement (:func:`refine_ml`).

    The defaults are what every command uses.  Checked on construction.

    - ``noise``: ``"per_type"`` (default), ``"per_placement"`` or ``"shared"``.
      ``per_type``: rim points and stripe points have their own noise sigma, each
      estimated from its residuals (weights ``1/sigma_rim²``, ``1/sigma_stripe²``),
      in ``rounds`` rounds of solve / re-estimate (the first from a robust MAD start,
      then ``Σ w r² / (kappa (Σ w − p_g))`` over the group's points, ``w`` 1 within ``huber_c``
      of its previous sigma, 0 beyond ``huber_c + 1``, linear between, ``kappa`` the same
      weighted mean of ``u²`` for a standard normal (a trimmed scale: consistent for Gaussian
      noise, blind to gross outliers, and continuous in the residuals, so that the plane moves
      smoothly with the intrinsics, as the camera's share assumes), with ``p_g`` the group's
      share of the parameters, the trace of its part of the hat matrix).  A laser stripe's
      centres scatter 2–4x more than the rim's edge points (speckle), so one shared sigma
      under-weights the rim and over-weights the stripe.  ``shared``: one sigma for
      all points (the original model; no reweighting).  ``per_placement``: a sigma per type
      *and* placement (stripes differ in brightness, width and speckle from image to image).
    - ``rounds``: rounds of solve / re-estimate of the sigmas (default 3).
    - ``max_iter``: iterations of each round's Levenberg–Marquardt solve (default 100).
    - ``huber_c``: Huber reweighting of standardised residuals beyond ``huber_c`` sigma (default
      3: an efficiency loss under 0.2 % for Gaussian noise, while a gross outlier's
      influence grows only linearly).  None: plain least squares.
    - ``correlated``: True (default): each group's weight and covariance contribution account for the
      integrated autocorrelation time of its residuals (:func:`integrated_autocorr_time`;
      stripe points ordered along the chord, rim points by angle).  False: white noise.
    - ``dispersion``: True (default): the covariance is multiplied by the images' dispersion
      (:func:`image_dispersion`: how much more each image's points pull the plane than their
      sigmas and autocorrelation times say), never by less than 1 (:func:`dispersion_factor`: an
      error shared within an image adds variance, it cannot remove any; an estimate below 1 is
      the statistic's sampling); False: it is reported (``image_dispersion``), not applied.
    """

    max_iter: int = 100
    noise: str = "per_type"
    rounds: int = 3
    huber_c: float | None = 3.0
    correlated: bool = True
    dispersion: bool = True

    def __post_init__(self):
        if self.noise not in ("per_type", "per_placement", "shared"):
            raise LightplaneError(f"noise must be 'per_type', 'per_placement' or 'shared', got {self.noise!r}")
        if int(self.max_iter) < 1 or int(self.rounds) < 1:
            raise LightplaneError(f"max_iter and rounds must be >= 1, got {self.max_iter} and {self.rounds}")
        if self.huber_c is not None and not (np.isfinite(self.huber_c) and self.huber_c > 0):
            raise LightplaneError(f"huber_c must be positive or None, got {self.huber_c}")


@dataclass(frozen=True)
class MLResult:
    """Result of :func:`refine_ml`.

    Attributes
    ----------
    plane : LightPlane
        Refined plane, ``covariance`` set (4x4 of ``(a, b, c, d)``, mm² for d).
    covariance : (4, 4) float64
        The same covariance.
    poses : list of CirclePose
        Refined target poses (centre mm, unit normal towards the camera).
    sigma_px : float
        Noise sigma estimated from the residuals, ``sqrt(Σ r² / (m − p))``, px.
    rim_rms_px, stripe_rms_px : (n,) float64
        Per-placement residual RMS (distorted px).
    iterations : int
        Function evaluations of the solver.
    pose_covariances : list of (6, 6) float64
        Per placement, covariance of ``(Cx, Cy, Cz, Nx, Ny, Nz)`` (mm², rank 5).
    n_residuals, n_params : int
        ``m`` and ``p`` (``p = 3 + 5 n``).
    converged : bool
        Whether the solver met its tolerances.
    sigma_rim_px, sigma_stripe_px : float
        Noise sigma of the rim points and of the stripe points (px), each from its own
        residuals with its degrees of freedom (``noise="shared"``: both the common one).
    tau_rim, tau_stripe : float
        Integrated autocorrelation times of the residuals along each rim / stripe (1:
        white); the covariance inflation of each group (:func:`integrated_autocorr_time`).
    covariance_white : (4, 4) float64 or None
        The plane covariance without that inflation (as if the noise were white) and without
        the images' dispersion.
    n_outliers : int
        Points down-weighted by the Huber reweighting.
    image_dispersion : float
        The rim and stripe errors' variance along the plane's directions, image by image, over
        what their sigmas and autocorrelation times say (:func:`image_dispersion`; 1: no excess).
    image_dispersion_expected : float
        Its statistic's expectation under the noise model (the statistic is the product).
    dispersion_applied : bool
        Whether ``covariance`` (and ``pose_covariances``) include it (``dispersion=True``), as
        ``max(image_dispersion, 1)`` (:func:`dispersion_factor`).
    """

    plane: LightPlane
    covariance: np.ndarray
    poses: list
    sigma_px: float
    rim_rms_px: np.ndarray
    stripe_rms_px: np.ndarray
    iterations: int
    pose_covariances: list = field(default_factory=list)
    n_residuals: int = 0
    n_params: int = 0
    converged: bool = True
    sigma_rim_px: float = float("nan")
    sigma_stripe_px: float = float("nan")
    tau_rim: float = 1.0
    tau_stripe: float = 1.0
    covariance_white: np.ndarray | None = None
    n_outliers: int = 0
    image_dispersion: float = 1.0
    dispersion_applied: bool = False
    image_dispersion_expected: float = float("nan")


# ----------------------------------------------------------------- helpers
def _tangent_basis(n: np.ndarray) -> np.ndarray:
    """(2, 3): two unit vectors orthogonal to unit ``n`` and to each other."""
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t1 = np.cross(n, a)
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(n, t1)
    return np.stack([t1, t2])


def _pixel_jacobian_inv_t(camera: Camera, xy: np.ndarray) -> np.ndarray:
    """(N, 2, 2): ``J⁻ᵀ`` with ``J = ∂(u, v)/∂(x, y)`` (distortion and K) at normalised ``xy``."""
    J = camera.pixel_jacobian(xy)
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    # inv(J)ᵀ = [[a22, -a21], [-a12, a11]] / det
    out = np.empty((len(xy), 2, 2))
    out[:, 0, 0] = J[:, 1, 1] / det
    out[:, 0, 1] = -J[:, 1, 0] / det
    out[:, 1, 0] = -J[:, 0, 1] / det
    out[:, 1, 1] = J[:, 0, 0] / det
    return out


def _normalise_with_jac(base: np.ndarray, tang: np.ndarray, ab: np.ndarray):
    """``n = normalise(base + ab @ tang)`` row-wise and ``∂n/∂ab`` (…, 3, 2)."""
    m = base + np.einsum("...k,...kj->...j", ab, tang)
    norm = np.linalg.norm(m, axis=-1, keepdims=True)
    n = m / norm
    proj = (np.eye(3) - n[..., :, None] * n[..., None, :]) / norm[..., None]
    jac = proj @ np.swapaxes(tang, -1, -2)
    return n, jac


class _Problem:
    """Residuals and analytic Jacobian of the joint model (see the module docstring)."""

    def __init__(self, camera: Camera, radius_mm: float, rims: Sequence[np.ndarray], stripes: Sequence[np.ndarray],
                 plane0: LightPlane, poses0: Sequence[Any]):
        self.n = n = len(rims)
        self.r = float(radius_mm)
        self.rim_idx = np.concatenate([np.full(len(a), i) for i, a in enumerate(rims)])
        self.st_idx = np.concatenate([np.full(len(a), i) for i, a in enumerate(stripes)])
        xy = camera.undistort_points(np.concatenate(list(rims) + list(stripes)), normalized=True)  # one call: fast
        rxy, sxy = xy[: len(self.rim_idx)], xy[len(self.rim_idx):]
        if not (np.all(np.isfinite(rxy)) and np.all(np.isfinite(sxy))):
            raise LightplaneError("refine_ml: some rim or stripe points could not be undistorted (outside the lens model)")
        self.rim_x = np.column_stack([rxy, np.ones(len(rxy))])
        self.st_x = np.column_stack([sxy, np.ones(len(sxy))])
        self.rim_A = _pixel_jacobian_inv_t(camera, rxy)
        self.st_A = _pixel_jacobian_inv_t(camera, sxy)
        self.m_rim = len(rxy)
        rb = np.cumsum([0] + [len(a) for a in rims])
        sb = np.cumsum([0] + [len(a) for a in stripes])
        self.rim_starts, self.st_starts = rb[:-1], sb[:-1]  # first row of each placement
        self.m = len(rxy) + len(sxy)
        self.p = 3 + 5 * n
        # tangent bases at the start values
        self.n0 = plane0.normal.copy()
        self.nt = _tangent_basis(self.n0)
        self.N0 = np.array([np.asarray(q.normal, float) / np.linalg.norm(q.normal) for q in poses0])
        self.Nt = np.array([_tangent_basis(v) for v in self.N0])
        self.x0 = np.zeros(self.p)
        self.x0[2] = plane0.d
        for i, q in enumerate(poses0):
            self.x0[3 + 5 * i: 6 + 5 * i] = np.asarray(q.center, float)
        self.row_w = np.ones(self.m)  # sqrt of the per-row weights (1/sigma_group, robust factor)
        # order of the points along each stripe (principal direction) and each rim (angle):
        # the residual autocorrelation is estimated along these sequences
        self.rim_order = [np.argsort(np.arctan2(*(rxy[a:b] - rxy[a:b].mean(axis=0)).T[::-1]))
                          for a, b in zip(rb[:-1], rb[1:])]
        self.st_order = []
        for a, b in zip(sb[:-1], sb[1:]):
            m, direction, _ = tls_line(sxy[a:b]) if b - a >= 2 else (sxy[a:b].mean(axis=0), np.array([1.0, 0.0]), None)
            self.st_order.append(np.argsort((sxy[a:b] - m) @ direction))
        # the last evaluation (x, residuals, Jacobian blocks or None)
        self._cache_x: np.ndarray | None = None
        self._cache_r: np.ndarray | None = None
        self._cache_J: tuple | None = None

    def set_row_weights(self, row_w: np.ndarray) -> None:
        """Multiply residual row k (and its Jacobian row) by ``row_w[k]`` (sqrt of its weight)."""
        self.row_w = np.asarray(row_w, float).copy()
        self._cache_x = None

    def unpack(self, x: np.ndarray):
        nvec, dn = _normalise_with_jac(self.n0, self.nt, x[:2])
        d = x[2]
        blk = x[3:].reshape(self.n, 5)
        C = blk[:, :3]
        N, dN = _normalise_with_jac(self.N0, self.Nt, blk[:, 3:])
        return nvec, dn, d, C, N, dN

    def evaluate(self, x: np.ndarray, want_jac: bool = True):
        if self._cache_x is not None and np.array_equal(x, self._cache_x) and (self._cache_J is not None or not want_jac):
            return self._cache_r, self._cache_J
        nvec, dn, d, C, N, dN = self.unpack(x)
        # ---- rim points: Sampson distance to the circle's cone (module docstring)
        xr = self.rim_x
        Ci = C[self.rim_idx]
        Ni = N[self.rim_idx]
        w = np.einsum("ij,ij->i", Ni, Ci)
        a = np.einsum("ij,ij->i", Ni, xr)
        c = np.einsum("ij,ij->i", Ci, xr)
        s = np.einsum("ij,ij->i", xr, xr)
        kap = np.einsum("ij,ij->i", Ci, Ci) - self.r ** 2
        f = w * w * s - 2 * w * a * c + kap * a * a
        q = (w * w)[:, None] * xr - (w * c)[:, None] * Ni - (w * a)[:, None] * Ci + (kap * a)[:, None] * Ni
        g2 = np.einsum("ijk,ik->ij", self.rim_A, q[:, :2])
        gn = np.linalg.norm(g2, axis=1)
        G = 2 * gn
        r_rim = f / G
        # ---- stripe points: distance to the chord's image line m·x̃ = 0
        xs = self.st_x
        Cs = C[self.st_idx]
        Ns = N[self.st_idx]
        h = -np.einsum("ij,ij->i", Ns, Cs)
        mv = h[:, None] * nvec[None, :] - d * Ns
        e = np.einsum("ij,ij->i", mv, xs)
        gm = np.einsum("ijk,ik->ij", self.st_A, mv[:, :2])
        Gs = np.linalg.norm(gm, axis=1)
        r_st = e / Gs
        r = np.concatenate([r_rim, r_st])
        J = None
        if want_jac:
            # block-local Jacobian: rim rows depend on their pose only (5 columns),
            # stripe rows on the plane (3) and their pose (5)
            # rim: dr = (df − r dG) / G, dG = 2 ũᵀ dq, ũ = Aᵀ g2 / |g2|
            u2 = np.einsum("ikj,ik->ij", self.rim_A, g2) / gn[:, None]
            ut = np.column_stack([u2, np.zeros(len(u2))])
            ux = np.einsum("ij,ij->i", ut, xr)
            uN = np.einsum("ij,ij->i", ut, Ni)
            uC = np.einsum("ij,ij->i", ut, Ci)
            df_dC = (2 * w * s - 2 * a * c)[:, None] * Ni - (2 * w * a)[:, None] * xr + (2 * a * a)[:, None] * Ci
            df_dN = (2 * w * s - 2 * a * c)[:, None] * Ci - (2 * w * c)[:, None] * xr + (2 * kap * a)[:, None] * xr
            uq_dC = ((2 * w * ux - c * uN - a * uC)[:, None] * Ni - (w * uN)[:, None] * xr
                     - (a * w)[:, None] * ut + (2 * a * uN)[:, None] * Ci)
            uq_dN = ((2 * w * ux - c * uN)[:, None] * Ci - (c * w)[:, None] * ut
                     - (uC * a)[:, None] * Ci - (uC * w)[:, None] * xr
                     + (kap * uN)[:, None] * xr + (kap * a)[:, None] * ut)
            dr_dC = (df_dC - (r_rim * 2)[:, None] * uq_dC) / G[:, None]
            dr_dN = (df_dN - (r_rim * 2)[:, None] * uq_dN) / G[:, None]
            dr_db = np.einsum("ij,ijk->ik", dr_dN, dN[self.rim_idx])
            J_rim = np.column_stack([dr_dC, dr_db])
            # stripe: dr = zᵀ dm, z = (x̃ − r ṽ) / Gs, ṽ = Aᵀ gm / Gs
            v2 = np.einsum("ikj,ik->ij", self.st_A, gm) / Gs[:, None]
            vt = np.column_stack([v2, np.zeros(len(v2))])
            z = (xs - r_st[:, None] * vt) / Gs[:, None]
            zn = z @ nvec
            J_n = h[:, None] * z  # dm/dn = h I
            J_st_plane = np.column_stack([J_n @ dn, -np.einsum("ij,ij->i", z, Ns)])  # dm/dd = −N
            dr_dN_s = -zn[:, None] * Cs - d * z  # dm/dN = −n Cᵀ − d I
            dr_dC_s = -zn[:, None] * Ns  # dm/dC = −n Nᵀ
            dr_db_s = np.einsum("ij,ijk->ik", dr_dN_s, dN[self.st_idx])
            J = (J_rim, J_st_plane, np.column_stack([dr_dC_s, dr_db_s]))
            wr, ws = self.row_w[: self.m_rim, None], self.row_w[self.m_rim:, None]
            J = (J[0] * wr, J[1] * ws, J[2] * ws)
        r = r * self.row_w
        self._cache_x = x.copy()
        self._cache_r = r
        self._cache_J = J
        return r, J

    def residuals(self, x):
        return self.evaluate(x, want_jac=False)[0]

    def dense_jacobian(self, x) -> np.ndarray:
        """(m, p) Jacobian as a dense matrix (for checks; the solver uses the blocks)."""
        J_rim, J_sp, J_spose = self.evaluate(x, want_jac=True)[1]
        J = np.zeros((self.m, self.p))
        J[np.arange(self.m_rim)[:, None], 3 + 5 * self.rim_idx[:, None] + np.arange(5)] = J_rim
        rs = np.arange(self.m_rim, self.m)
        J[rs, :3] = J_sp
        J[rs[:, None], 3 + 5 * self.st_idx[:, None] + np.arange(5)] = J_spose
        return J

    def normal_equations(self, r: np.ndarray, Jb) -> "_Normal":
        """Blocks of ``JᵀJ`` and ``Jᵀr`` from the block-local Jacobian.

        ``JᵀJ = [[A, B], [Bᵀ, blockdiag(D_i)]]``: A (3, 3) plane, D_i (5, 5) pose i,
        B (n, 3, 5) plane–pose.  Sums of per-row outer products (``einsum`` and
        ``add.reduceat``, no multi-threaded BLAS: on a busy machine OpenBLAS's threads
        made 63x63 LAPACK calls take ~100 ms).
        """
        J_rim, J_sp, J_spose = Jb
        r_rim, r_st = r[: self.m_rim], r[self.m_rim:]
        rs, ss = self.rim_starts, self.st_starts
        D = np.add.reduceat(np.einsum("ij,ik->ijk", J_rim, J_rim), rs) \
            + np.add.reduceat(np.einsum("ij,ik->ijk", J_spose, J_spose), ss)
        B = np.add.reduceat(np.einsum("ij,ik->ijk", J_sp, J_spose), ss)
        A = np.einsum("ij,ik->jk", J_sp, J_sp)
        gp = np.einsum("ij,i->j", J_sp, r_st)
        gi = np.add.reduceat(J_rim * r_rim[:, None], rs) + np.add.reduceat(J_spose * r_st[:, None], ss)
        return _Normal(A, B, D, gp, gi)

    def group_normals(self, r: np.ndarray, Jb) -> tuple["_Normal", "_Normal"]:
        """The normal equations of the rim rows alone and of the stripe rows alone (they add up)."""
        J_rim, J_sp, J_spose = Jb
        zr = np.zeros(self.m_rim)
        zs = np.zeros(self.m - self.m_rim)
        rim = self.normal_equations(np.concatenate([r[: self.m_rim], zs]), (J_rim, 0 * J_sp, 0 * J_spose))
        st = self.normal_equations(np.concatenate([zr, r[self.m_rim:]]), (0 * J_rim, J_sp, J_spose))
        return rim, st


@dataclass
class _Normal:
    """Block normal equations of the joint problem (see :meth:`_Problem.normal_equations`)."""

    A: np.ndarray
    B: np.ndarray
    D: np.ndarray
    gp: np.ndarray
    gi: np.ndarray

    def diag(self) -> np.ndarray:
        return np.concatenate([np.diag(self.A), np.einsum("nii->ni", self.D).ravel()])

    def dense(self) -> np.ndarray:
        n = len(self.D)
        H = np.zeros((3 + 5 * n, 3 + 5 * n))
        H[:3, :3] = self.A
        for i in range(n):
            sl = slice(3 + 5 * i, 8 + 5 * i)
            H[sl, sl] = self.D[i]
            H[:3, sl] = self.B[i]
            H[sl, :3] = self.B[i].T
        return H

    @property
    def g(self) -> np.ndarray:
        return np.concatenate([self.gp, self.gi.ravel()])

    def _scaled(self, lam: float):
        """Jacobi-scaled blocks with Marquardt damping ``lam`` on the (unit) diagonal."""
        dg = self.diag()
        dg[dg == 0] = 1.0
        s = np.sqrt(dg)
        sp, si = s[:3], s[3:].reshape(-1, 5)
        A = self.A / np.outer(sp, sp) + lam * np.eye(3)
        D = self.D / (si[:, :, None] * si[:, None, :]) + lam * np.eye(5)
        B = self.B / (sp[None, :, None] * si[:, None, :])
        return A, B, D, sp, si

    def solve(self, lam: float) -> np.ndarray:
        """Solve ``(H + lam diag H) δ = −g`` by the Schur complement on the plane block."""
        A, B, D, sp, si = self._scaled(lam)
        gp, gi = -self.gp / sp, -self.gi / si
        Dinv = np.linalg.inv(D)  # batched 5x5
        BDinv = np.einsum("nij,njk->nik", B, Dinv)
        S = A - np.einsum("nij,nkj->ik", BDinv, B)
        dp = np.linalg.solve(S, gp - np.einsum("nij,nj->i", BDinv, gi))
        di = np.einsum("nij,nj->ni", Dinv, gi - np.einsum("nji,j->ni", B, dp))
        return np.concatenate([dp / sp, (di / si).ravel()])

    def _check_rank(self, sp: np.ndarray, si: np.ndarray) -> None:
        """Raise when the scaled normal matrix is (numerically) singular: eigenvalues only, cheap."""
        Hs = self.dense() / np.outer(np.concatenate([sp, si.ravel()]), np.concatenate([sp, si.ravel()]))
        w = np.linalg.eigvalsh(Hs)
        if not w[0] > 1e-13 * w[-1]:
            raise LightplaneError(
                "refine_ml: the placements do not determine the light plane (the joint problem is singular; "
                "are all stripes parallel or the targets all alike?)"
            )

    def inverse(self) -> np.ndarray:
        """Dense ``H⁻¹`` (p, p) from the Schur complement on the plane block (no LAPACK on p x p).

        Raises :class:`LightplaneError` when ``H`` is (numerically) singular.
        """
        A, B, D, sp, si = self._scaled(0.0)
        self._check_rank(sp, si)
        n = len(D)
        Dinv = np.linalg.inv(D)
        F = np.einsum("nij,njk->nik", B, Dinv)  # B_i D_i⁻¹ (n, 3, 5)
        Sinv = np.linalg.inv(A - np.einsum("nij,nkj->ik", F, B))
        Sinv = 0.5 * (Sinv + Sinv.T)
        Hi = np.zeros((3 + 5 * n, 3 + 5 * n))
        Hi[:3, :3] = Sinv
        E = -np.einsum("ij,njk->nik", Sinv, F)  # plane–pose blocks (n, 3, 5)
        Hi[:3, 3:] = np.concatenate(list(E), axis=1)
        Hi[3:, :3] = Hi[:3, 3:].T
        Fm = np.concatenate(list(F), axis=1)  # (3, 5 n)
        Hi[3:, 3:] = Fm.T @ Sinv @ Fm
        for i in range(n):
            sl = slice(3 + 5 * i, 8 + 5 * i)
            Hi[sl, sl] += Dinv[i]
        s = np.concatenate([sp, si.ravel()])
        Hi = Hi / np.outer(s, s)
        return 0.5 * (Hi + Hi.T)

    def covariance(self, sigma: float) -> tuple[np.ndarray, np.ndarray]:
        """``sigma² (JᵀJ)⁻¹``: the plane block (3, 3) and the pose blocks (n, 5, 5)."""
        A, B, D, sp, si = self._scaled(0.0)
        self._check_rank(sp, si)
        Dinv = np.linalg.inv(D)
        BDinv = np.einsum("nij,njk->nik", B, Dinv)
        Sinv = np.linalg.inv(A - np.einsum("nij,nkj->ik", BDinv, B))
        Sinv = 0.5 * (Sinv + Sinv.T)
        Ci = Dinv + np.einsum("nji,jk,nkl->nil", BDinv, Sinv, BDinv)
        cov_p = sigma**2 * Sinv / np.outer(sp, sp)
        cov_i = sigma**2 * Ci / (si[:, :, None] * si[:, None, :])
        return cov_p, 0.5 * (cov_i + np.swapaxes(cov_i, 1, 2))


def _levenberg_marquardt(prob: "_Problem", x0: np.ndarray, max_iter: int = 100) -> tuple[np.ndarray, int, bool]:
    """Levenberg–Marquardt (Marquardt's diagonal scaling) on the normal equations.

    ``scipy.optimize.least_squares`` was measured first: ``lm`` (MINPACK's unblocked
    QR of the dense 6000x63 Jacobian) took ~200 ms and ``trf`` with a sparse
    Jacobian and LSMR ~2 s for 12 placements; with only 3 + 5 n parameters and the
    block structure (plane + one pose per placement) the normal equations are tiny,
    solved by the Schur complement on the plane block, so this loop costs little
    more than the residual and Jacobian evaluations.  Returns ``(x, evaluations, converged)``.
    """
    x = x0.copy()
    r, J = prob.evaluate(x)
    cost = float(r @ r)
    lam = 1e-4
    nfev = 1
    for _ in range(max_iter):
        ne = prob.normal_equations(r, J)
        H = ne.dense()
        g = ne.g
        for _attempt in range(12):
            try:
                step = ne.solve(lam)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            # predicted decrease of the cost (Gauss–Newton model): stop when it is at
            # round-off level rather than spending evaluations on rejected steps
            predicted = -2 * (step @ g) - step @ (H @ step)
            if predicted <= 1e-13 * cost + 1e-24 * len(r):
                return x, nfev, True
            x_new = x + step
            r_new, J_new = prob.evaluate(x_new)
            nfev += 1
            cost_new = float(r_new @ r_new) if np.all(np.isfinite(r_new)) else np.inf
            if cost_new <= cost:
                break
            lam *= 10
        else:
            return x, nfev, True  # no decrease possible: at the minimum to machine precision
        x, r, J, cost = x_new, r_new, J_new, cost_new
        lam = max(lam / 10, 1e-12)
    return x, nfev, False


def plane_param_jacobian(normal_jac: np.ndarray) -> np.ndarray:
    """(4, 3) ``∂(a, b, c, d)/∂(α, β, d)`` from the (3, 2) normal tangent Jacobian."""
    G = np.zeros((4, 3))
    G[:3, :2] = normal_jac
    G[3, 2] = 1.0
    return G


def _make_pose(center: np.ndarray, normal: np.ndarray, radius_mm: float):
    return CirclePose(center=center, normal=normal, radius_mm=radius_mm)


def _check_inputs(radius_mm, rims, stripes, poses0):
    if not np.isfinite(radius_mm) or radius_mm <= 0:
        raise LightplaneError(f"radius_mm must be positive, got {radius_mm}")
    if len(rims) != len(stripes) or len(rims) != len(poses0):
        raise LightplaneError(
            f"rims_uv, stripes_uv and poses0 must have one entry per placement, got {len(rims)}, {len(stripes)}, {len(poses0)}"
        )
    if len(rims) < 2:
        raise LightplaneError(f"refine_ml needs at least 2 placements, got {len(rims)}")
    out_r, out_s = [], []
    for i, (r, s) in enumerate(zip(rims, stripes)):
        r = as_points(r, 2, f"rims_uv[{i}]")
        s = as_points(s, 2, f"stripes_uv[{i}]")
        if len(r) < 5:
            raise LightplaneError(f"placement {i}: needs at least 5 rim points, got {len(r)}")
        if len(s) < 2:
            raise LightplaneError(f"placement {i}: needs at least 2 stripe points, got {len(s)}")
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(s))):
            raise LightplaneError(f"placement {i}: rim or stripe points contain NaN/inf")
        out_r.append(r)
        out_s.append(s)
    return out_r, out_s


def integrated_autocorr_time(sequences: Sequence[np.ndarray], bases: Sequence[np.ndarray], *,
                             window_c: float = 5.0, max_lag: int = 200) -> tuple[float, int]:
    """Integrated autocorrelation time ``tau = 1 + 2 Σ_k rho_k`` of noise seen through fit residuals.

    ``sequences[s]`` (n_s,) are residuals of one group (e.g. one stripe) in their order
    along the curve; ``bases[s]`` (n_s, b) the smooth components to remove first (a
    stripe: offset and slope along the chord; a rim: the harmonics 0–2 of the angle,
    what a pose fit absorbs).  The autocovariance is pooled over the sequences, the sum
    truncated by Sokal's window (the smallest ``W`` with ``W >= window_c tau(W)``), and
    corrected to first order for the removed components: removing ``b`` smooth components
    from ``n`` samples of noise with integrated time ``tau`` lowers every lagged
    autocovariance by about ``sigma² tau b / n``, so with ``q = Σ b / Σ n`` and
    ``S = Σ_{k<=W} rho_hat_k``

        tau = (1 + 2 S) / (1 - 2 q (W - S)).

    For white noise ``tau`` is 1 (returned clipped to >= 1: never below the white-noise
    covariance); for noise correlated over a length ``L`` (in samples) it is the
    variance inflation of a mean over ``n >> L`` samples: the effective number of
    independent samples is ``n / tau``.  Returns ``(tau, W)``.
    """
    segs = []
    q_num = 0
    n_tot = 0
    for e, Bm in zip(sequences, bases):
        e = np.asarray(e, float)
        if len(e) <= Bm.shape[1] + 2:
            continue
        coef, *_ = np.linalg.lstsq(Bm, e, rcond=None)
        segs.append(e - Bm @ coef)
        q_num += Bm.shape[1]
        n_tot += len(e)
    if not segs or n_tot == 0:
        return 1.0, 0
    kmax = int(min(max_lag, max(len(x) for x in segs) // 2))
    c = np.zeros(kmax + 1)
    cnt = np.zeros(kmax + 1)
    for x in segs:
        nx = len(x)
        K = min(kmax, nx - 1)
        # all lags at once via FFT (zero-padded: linear, not circular, correlation)
        f = np.fft.rfft(x, 2 * nx)
        ac = np.fft.irfft(f * np.conj(f), 2 * nx)[: K + 1]
        c[: K + 1] += ac
        cnt[: K + 1] += nx - np.arange(K + 1)
    ok = cnt > 0
    c = np.where(ok, c / np.maximum(cnt, 1), 0.0)
    if not c[0] > 0:
        return 1.0, 0
    rho = c / c[0]
    tau_hat = 1 + 2 * np.cumsum(rho[1:])
    W = kmax
    for M in range(1, kmax + 1):
        if M >= window_c * tau_hat[M - 1]:
            W = M
            break
    S = float(np.sum(rho[1: W + 1]))
    q = q_num / n_tot
    den = max(1.0 - 2.0 * q * (W - S), 0.2)
    return float(max(1.0, (1 + 2 * S) / den)), int(W)


def _huber_weights(u: np.ndarray, c: float) -> np.ndarray:
    """Huber weights ``min(1, c / |u|)`` of standardised residuals ``u``."""
    a = np.abs(u)
    return np.where(a <= c, 1.0, c / np.maximum(a, 1e-300))


def refine_ml(camera: Camera, radius_mm: float, rims_uv: Sequence[np.ndarray], stripes_uv: Sequence[np.ndarray],
              plane0: LightPlane, poses0: Sequence[Any], options: MLOptions | None = None) -> MLResult:
    """Joint maximum-likelihood refinement of the light plane and all target poses.

    Parameters
    ----------
    camera : Camera
    radius_mm : float
        Target radius (mm).
    rims_uv : list of (M_i, 2)
        Per placement, rim (ellipse edge) points, distorted px.
    stripes_uv : list of (K_i, 2)
        Per placement, stripe centres on the target, distorted px.
    plane0 : LightPlane
        Start value (e.g. the ``global`` solution).
    poses0 : list of poses
        Start values, objects with ``center`` (mm) and unit ``normal`` (the chosen
        candidate of :func:`lightplane.plane.circle_pose.circle_poses`).
    options : MLOptions, optional
        The refinement's options (:class:`MLOptions`, meanings there; defaults when omitted).

    Weights and covariance (what it covers, and what not)
    ------------------------------------------------------
    Each point type g (rim, stripe) gets the weight ``1 / (tau_g sigma_g²)``: its
    long-run variance, with ``tau_g`` the integrated autocorrelation time of its
    residuals along the curves (``correlated=True``; 1 otherwise), estimated from the
    residuals of the previous round.  Why: speckle makes a stripe's centre errors
    correlated over many points (tau ~ 11 for raw centres on the realistic renders,
    against ~1.4 for rim edge points), so n stripe points carry the information of only
    n / tau independent ones; the Jacobian rows vary smoothly along a curve (a line's
    offset and slope; harmonics 0–2 of the rim angle), and for such regressors least
    squares within a group is asymptotically as efficient as generalised least squares
    (Grenander 1954), while the weights *between* the groups must use the long-run
    variance.  Covariance: the sandwich ``H⁻¹ M H⁻¹`` with ``H = Σ_g J_gᵀJ_g w_g`` and
    ``M = Σ_g w_g² tau_g sigma_g² J_gᵀJ_g`` (the banded sandwich ``H⁻¹ JᵀW Σ W J H⁻¹``
    with ``Σ_g`` Toeplitz along each curve, reduced to one factor per group because
    ``J_{i+k} ≈ J_i`` within the correlation length, so ``Σ_k rho_k J_iᵀ J_{i+k} ≈
    tau J_iᵀ J_i``); it equals ``H⁻¹`` when the weights' tau is the final one, and
    ``(JᵀJ)⁻¹ sigma²`` (the Cramér–Rao bound at the estimate) for white noise of one sigma.

    It covers the image noise of the rim and stripe points, white or correlated along
    the curve (laser speckle), to first order; with ``dispersion`` also errors shared by the
    points of one image in the directions that move the plane (the images' dispersion, a
    scalar factor estimated from the residuals; an error that is the same in every image, or
    that the image's own pose absorbs entirely, it cannot see).  It does NOT cover: errors of the camera
    intrinsics and distortion, systematic edge or stripe-centre biases (e.g. a blur- or
    curvature-dependent edge shift, a stripe centre pulled by an asymmetric profile or
    by the rim's intensity step), a wrong target diameter, model errors (a non-flat
    target or a curved light sheet), correlation *between* placements, or noise
    correlated over a length comparable to a whole stripe (tau is then underestimated).
    ``covariance_white`` is what a white-noise model with the same sigmas would claim,
    ``(Σ_g J_gᵀJ_g / sigma_g²)⁻¹``: on the renders 2–3x too small in sigma.
    Measured (benchmarks/bench_uncertainty.py, 10 seeds x 2 polarities of 12-image
    realistic renders, true camera): predicted / actual RMS triangulation error 0.91–0.99
    (one shared white sigma: 0.39–0.60).

    Returns
    -------
    MLResult
        Plane with covariance, refined poses, sigmas, per-placement residual RMS.
    """
    if not isinstance(camera, Camera):
        raise LightplaneError(f"camera must be a Camera, got {type(camera).__name__}")
    if not isinstance(plane0, LightPlane):
        raise LightplaneError(f"plane0 must be a LightPlane, got {type(plane0).__name__}")
    opts = MLOptions() if options is None else options
    if not isinstance(opts, MLOptions):
        raise LightplaneError(f"options must be MLOptions, got {type(opts).__name__}")
    rims, stripes = _check_inputs(float(radius_mm), list(rims_uv), list(stripes_uv), list(poses0))
    prob = _Problem(camera, radius_mm, rims, stripes, plane0, list(poses0))
    if prob.m <= prob.p:
        raise LightplaneError(f"refine_ml: {prob.m} points cannot determine {prob.p} parameters")
    fit = _solve_rounds(prob, opts)
    return _ml_result(prob, fit, opts, plane0, float(radius_mm))


@dataclass(frozen=True)
class _RoundsFit:
    """Where :func:`_solve_rounds` ends: the solution ``x`` and the weights' ingredients."""

    x: np.ndarray
    nfev: int
    converged: bool
    r_raw: np.ndarray   # unweighted residuals at x (px)
    hub: np.ndarray     # Huber factors of the rows
    sig: np.ndarray     # sigma of each noise group (>= 1e-9)
    grp: np.ndarray     # noise group of each row
    is_rim: np.ndarray  # rim rows
    tau_w: np.ndarray   # long-run variance factors used in the weights (rim, stripe)
    n_rounds: int
    kappa: float        # E[w u²] / E[w] of a standard normal, w of _scale_weight (1 without Huber)


def _noise_groups(prob: "_Problem", noise: str) -> tuple[np.ndarray, np.ndarray]:
    """``(is_rim (m,), group (m,))``: the rim rows and each row's noise group (one sigma each)."""
    is_rim = np.arange(prob.m) < prob.m_rim
    if noise == "shared":
        grp = np.zeros(prob.m, int)
    elif noise == "per_type":
        grp = (~is_rim).astype(int)
    else:
        grp = np.concatenate([prob.rim_idx, prob.n + prob.st_idx]).astype(int)
    return is_rim, grp


#: the points within ``huber_c`` sigma count fully in a group's sigma, those beyond ``huber_c + SCALE_TAPER`` not
#: at all, with a linear taper between
SCALE_TAPER = 1.0


def _scale_weight(u: np.ndarray, huber_c: float | None) -> np.ndarray:
    """How much each standardised residual ``u`` counts in its group's sigma: 1 within ``huber_c``, 0
    beyond ``huber_c + SCALE_TAPER``, linear between (all 1 without Huber).  A trimmed scale, blind to
    gross outliers, and, unlike a hard cut, continuous in the residuals: a point crossing the cut does
    not jump the sigma, the weights and the solution with it (the camera's share differentiates it)."""
    if huber_c is None:
        return np.ones(np.shape(u))
    c = float(huber_c)
    return np.clip((c + SCALE_TAPER - np.abs(u)) / SCALE_TAPER, 0.0, 1.0)


@functools.lru_cache(maxsize=8)
def _scale_kappa(huber_c: float | None) -> float:
    """``E[w(u) u²] / E[w(u)]`` of a standard normal with the weights of :func:`_scale_weight` (1 without
    Huber): the scale of the weighted squares, so that the sigma is consistent for Gaussian noise."""
    if huber_c is None:
        return 1.0
    u = np.linspace(-(float(huber_c) + SCALE_TAPER), float(huber_c) + SCALE_TAPER, 200001)
    pdf = np.exp(-0.5 * u * u)
    w = _scale_weight(u, huber_c) * pdf
    return float(np.sum(w * u * u) / np.sum(w))


def _solve_rounds(prob: "_Problem", opts: MLOptions) -> _RoundsFit:
    """The solve, then ``rounds`` rounds of re-estimated sigmas, Huber factors and autocorrelation
    times in the weights, each followed by a solve (see :func:`refine_ml`)."""
    huber_c = opts.huber_c
    is_rim, grp = _noise_groups(prob, opts.noise)
    n_grp = int(grp.max()) + 1
    x, nfev, converged = _levenberg_marquardt(prob, prob.x0, max_iter=opts.max_iter)
    n_rounds = int(opts.rounds) if opts.noise != "shared" or huber_c is not None else 0
    r_raw = prob.residuals(x) / prob.row_w
    hub = np.ones(prob.m)
    # robust start: MAD of each group's residuals (residuals have zero mean)
    sig = np.array([robust_sigma(r_raw[grp == g], center=False) for g in range(n_grp)])
    kappa = _scale_kappa(huber_c)
    tau_w = np.ones(2)  # long-run variance factors used in the weights (rim, stripe)
    for _round in range(n_rounds):
        sig = np.maximum(sig, 1e-9)
        s_rows = sig[grp]
        hub = _huber_weights(r_raw / s_rows, huber_c) if huber_c is not None else np.ones(prob.m)
        if opts.correlated and _round > 0:
            tau_w = _residual_tau(prob, r_raw / s_rows, huber_c)
        prob.set_row_weights(np.sqrt(hub) / (s_rows * np.sqrt(np.where(is_rim, tau_w[0], tau_w[1]))))
        x, nf, converged = _levenberg_marquardt(prob, x, max_iter=opts.max_iter)
        nfev += nf
        r_raw = prob.residuals(x) / prob.row_w
        # re-estimate each group's sigma with its degrees of freedom (its rows' leverages)
        r_w, Jb = prob.evaluate(x, want_jac=True)
        Hinv = prob.normal_equations(r_w, Jb).inverse()
        p_g = np.bincount(grp, _row_leverages(prob, Jb, Hinv), minlength=n_grp)
        ws = _scale_weight(r_raw / s_rows, huber_c)
        ss = np.bincount(grp, ws * r_raw**2, minlength=n_grp)
        nn = np.bincount(grp, ws, minlength=n_grp)
        sig = np.sqrt(ss / (kappa * np.maximum(nn - p_g, 1.0)))
    if n_rounds == 0:
        sig = np.full(n_grp, np.sqrt(np.sum(r_raw ** 2) / (prob.m - prob.p)))
    sig = np.maximum(sig, 1e-9)  # noise-free data: keep the weights finite
    return _RoundsFit(x, nfev, converged, r_raw, hub, sig, grp, is_rim, tau_w, n_rounds, kappa)


@dataclass(frozen=True)
class _Covariances:
    """The final covariance of the minimal parameters and what goes with it (:func:`_covariances`)."""

    cov: np.ndarray        # sandwich, times the images' dispersion when applied
    cov_white: np.ndarray  # what a white-noise model with these sigmas would claim
    sigma: float           # pooled sigma (px)
    sig_type: np.ndarray   # rim, stripe sigma (px)
    tau: np.ndarray        # rim, stripe autocorrelation times of the final residuals
    disp: float
    disp_expected: float


def _covariances(prob: "_Problem", fit: _RoundsFit, opts: MLOptions) -> _Covariances:
    """The covariance from the weighted normal equations at the solution (see :func:`refine_ml`)."""
    x, r_raw, hub, is_rim, tau_w = fit.x, fit.r_raw, fit.hub, fit.is_rim, fit.tau_w
    s_rows = fit.sig[fit.grp]
    prob.set_row_weights(np.sqrt(hub) / (s_rows * np.sqrt(np.where(is_rim, tau_w[0], tau_w[1]))))
    r_w, Jb = prob.evaluate(x, want_jac=True)
    ne_rim, ne_st = prob.group_normals(r_w, Jb)
    H = _add_normals(ne_rim, ne_st)
    Hinv = H.inverse()
    dof = prob.m - prob.p
    sigma = float(np.sqrt(np.sum(r_raw ** 2) / dof))
    # per type: pooled over its groups (with their degrees of freedom)
    lev = _row_leverages(prob, Jb, Hinv)
    ws = _scale_weight(r_raw / s_rows, opts.huber_c)
    sig_type = np.array([np.sqrt(np.sum((ws * r_raw**2)[t]) / (fit.kappa * max(np.sum(ws[t]) - np.sum(lev[t]), 1.0)))
                         for t in (is_rim, ~is_rim)])
    if fit.n_rounds == 0:
        sig_type[:] = fit.sig[0]
    tau = _residual_tau(prob, r_raw / s_rows, opts.huber_c) if opts.correlated else np.ones(2)
    # sandwich H⁻¹ M H⁻¹: rows were weighted with tau_w, the noise has tau (see the docstring)
    ne_rim_w, ne_st_w = _scale_normals(ne_rim, tau_w[0]), _scale_normals(ne_st, tau_w[1])
    M = (tau[0] / tau_w[0]) * ne_rim.dense() + (tau[1] / tau_w[1]) * ne_st.dense()
    cov = Hinv @ M @ Hinv
    cov = 0.5 * (cov + cov.T)
    disp, disp_expected = image_dispersion(prob, Jb, r_w, tau / tau_w, H)
    if opts.dispersion:
        cov = max(disp, 1.0) * cov
    # what a white-noise model with these sigmas would claim: (Σ_g J_gᵀJ_g / sigma_g²)⁻¹
    cov_white = _add_normals(ne_rim_w, ne_st_w).inverse()
    return _Covariances(cov, cov_white, sigma, sig_type, tau, disp, disp_expected)


def _ml_result(prob: "_Problem", fit: _RoundsFit, opts: MLOptions, plane0: LightPlane, radius_mm: float) -> MLResult:
    """The :class:`MLResult` at the solution: plane and pose covariances, residual RMS, oriented poses."""
    cv = _covariances(prob, fit, opts)
    cov, tau, sig_type = cv.cov, cv.tau, cv.sig_type
    nvec, dn, d, C, N, dN = prob.unpack(fit.x)
    G = plane_param_jacobian(dn)
    cov4 = G @ cov[:3, :3] @ G.T
    cov4 = 0.5 * (cov4 + cov4.T)
    cov4_white = G @ cv.cov_white[:3, :3] @ G.T
    cov4_white = 0.5 * (cov4_white + cov4_white.T)
    pose_covs = []
    for i in range(prob.n):
        Gi = np.zeros((6, 5))
        Gi[:3, :3] = np.eye(3)
        Gi[3:, 3:] = dN[i]
        sl = slice(3 + 5 * i, 8 + 5 * i)
        pose_covs.append(Gi @ cov[sl, sl] @ Gi.T)
    m_rim = prob.m_rim
    r_rim, r_st = fit.r_raw[:m_rim], fit.r_raw[m_rim:]
    rim_rms = np.array([np.sqrt(np.mean(r_rim[prob.rim_idx == i] ** 2)) for i in range(prob.n)])
    st_rms = np.array([np.sqrt(np.mean(r_st[prob.st_idx == i] ** 2)) for i in range(prob.n)])
    meta = dict(plane0.meta)
    meta.update({"method": "ml", "sigma_px": cv.sigma, "sigma_rim_px": float(sig_type[0]),
                 "sigma_stripe_px": float(sig_type[1]),
                 "tau_rim": float(tau[0]), "tau_stripe": float(tau[1]), "noise": opts.noise,
                 "image_dispersion": cv.disp, "image_dispersion_applied": bool(opts.dispersion),
                 "image_dispersion_factor": max(cv.disp, 1.0) if opts.dispersion else 1.0,
                 "image_dispersion_expected": cv.disp_expected})
    plane = LightPlane(nvec, d, cov4, meta=meta)
    assert plane.covariance is not None  # cov4, as the plane keeps it
    # orient each normal towards the camera (docs/conventions.md §Target pose)
    poses = []
    for i in range(prob.n):
        Ni = N[i] if N[i] @ C[i] < 0 else -N[i]
        poses.append(_make_pose(C[i].copy(), Ni, radius_mm))
    return MLResult(plane=plane, covariance=plane.covariance, poses=poses, sigma_px=cv.sigma, rim_rms_px=rim_rms,
                    stripe_rms_px=st_rms, iterations=fit.nfev, pose_covariances=pose_covs,
                    n_residuals=prob.m, n_params=prob.p, converged=fit.converged,
                    sigma_rim_px=float(sig_type[0]), sigma_stripe_px=float(sig_type[1]), tau_rim=float(tau[0]),
                    tau_stripe=float(tau[1]), covariance_white=cov4_white,
                    n_outliers=int(np.sum(fit.hub < 1.0)), image_dispersion=cv.disp,
                    image_dispersion_expected=cv.disp_expected,
                    dispersion_applied=bool(opts.dispersion))


def _residual_tau(prob: "_Problem", u: np.ndarray, huber_c: float | None) -> np.ndarray:
    """(2,) integrated autocorrelation times of the standardised residuals ``u`` (m,): rim, stripe.

    Rim points in the order of their angle about the rim's centroid (harmonics 0–2 removed),
    stripe points along the chord (offset and slope removed): :func:`integrated_autocorr_time`.
    """
    if huber_c is not None:
        u = np.clip(u, -huber_c, huber_c)  # winsorised: an outlier must not fake a correlation
    m_rim, m_st = prob.m_rim, prob.m - prob.m_rim
    u_rim, u_st = u[:m_rim], u[m_rim:]
    seq_r, bas_r, seq_s, bas_s = [], [], [], []
    for i in range(prob.n):
        a, b = prob.rim_starts[i], (prob.rim_starts[i + 1] if i + 1 < prob.n else m_rim)
        o = prob.rim_order[i]
        xy = prob.rim_x[a:b, :2][o]
        th = np.arctan2(*(xy - xy.mean(axis=0)).T[::-1])
        seq_r.append(u_rim[a:b][o])
        bas_r.append(np.column_stack([np.ones(len(th)), np.cos(th), np.sin(th), np.cos(2 * th), np.sin(2 * th)]))
        a, b = prob.st_starts[i], (prob.st_starts[i + 1] if i + 1 < prob.n else m_st)
        o = prob.st_order[i]
        seq_s.append(u_st[a:b][o])
        bas_s.append(np.column_stack([np.ones(len(o)), np.linspace(-1.0, 1.0, len(o))]))
    return np.array([integrated_autocorr_time(seq_r, bas_r)[0], integrated_autocorr_time(seq_s, bas_s)[0]])


def image_dispersion(prob: "_Problem", Jb, r_w: np.ndarray, meat_factor: np.ndarray,
                     ne: "_Normal") -> tuple[float, float]:
    """The plane's noise along its own directions, image by image, over what the noise model says:
    ``(dispersion, expected)``; 1 when the rim and stripe errors of one image are no more
    coherent than their sigmas and autocorrelation times say (docs/method.md §ML refinement).

    Per image ``i`` (a cluster: its pose is its own, the plane shared by all): ``J̃_i`` the plane's
    Jacobian columns of its rows (weighted) with its pose's columns projected out, ``S_i = J̃_iᵀJ̃_i``
    (``S = Σ S_i`` is the Schur complement, the plane's information), ``g_i = J̃_iᵀ r_i`` the pull of
    its residuals on the plane and ``M_i = Σ_g c_g J̃_{i,g}ᵀJ̃_{i,g}`` the model's variance of that
    pull (``c_g``, ``meat_factor``: the group's long-run variance over its weight, ``tau_g / tau_w``).
    ``T = Σ_i g_iᵀ S⁻¹ g_i`` has, under the model, expectation
    ``E = Σ_i tr(S⁻¹M_i) − 2 tr(S⁻¹S_iS⁻¹M_i) + tr(S⁻¹S_iS⁻¹S_iS⁻¹M)`` (``M = Σ M_i``; the fit
    absorbs the part of each image's pull that all images share); the dispersion is ``T / E``.
    An error shared by the points of one image (blur, the edge's response to the disc's tilt, a
    stripe's speckle over its whole length) moves the plane more than the points' scatter says
    and shows here.  Its sampling sd is at least ``sqrt(2 / (3 (n − 1)))`` (3 plane parameters,
    n images: 0.25 for 12; 0.34 measured over 60 synthetic 12-placement calibrations with white
    noise, mean 0.94; 0.49 over 12 rendered sets, benchmarks/bench_image_errors.py).  An error that is the same in every image is not seen.
    """
    J_rim, J_sp, J_spose = Jb
    n = prob.n
    m_rim = prob.m_rim
    # ne: the solve's weighted normal equations (their pose blocks D_i and plane-pose blocks B_i)
    # per image: the pose's projection of the plane columns, F_i = D_i⁻¹ B_iᵀ (5, 3)
    F = np.linalg.solve(ne.D, np.swapaxes(ne.B, 1, 2))
    # marginalised plane rows: rim rows −J_pose F, stripe rows J_sp − J_spose F
    Jr = -np.einsum("ij,ijk->ik", J_rim, F[prob.rim_idx])
    Js = J_sp - np.einsum("ij,ijk->ik", J_spose, F[prob.st_idx])
    r_rim, r_st = r_w[:m_rim], r_w[m_rim:]
    # sums over each image's rows (contiguous, every image has rim and stripe rows)
    Sr = np.add.reduceat(np.einsum("ij,ik->ijk", Jr, Jr), prob.rim_starts)
    Ss = np.add.reduceat(np.einsum("ij,ik->ijk", Js, Js), prob.st_starts)
    g = np.add.reduceat(Jr * r_rim[:, None], prob.rim_starts) + np.add.reduceat(Js * r_st[:, None], prob.st_starts)
    S_i = Sr + Ss
    M_i = meat_factor[0] * Sr + meat_factor[1] * Ss
    S = S_i.sum(axis=0)
    M = M_i.sum(axis=0)
    d = np.sqrt(np.diag(S))
    if not (np.all(np.isfinite(S)) and np.all(d > 0)) or n < 2:
        return 1.0, float("nan")
    Si = np.linalg.inv(S / np.outer(d, d)) / np.outer(d, d)
    T = float(np.einsum("ij,jk,ik->", g, Si, g))
    B = np.einsum("jk,ikl->ijl", Si, S_i)  # S⁻¹S_i
    C = np.einsum("jk,ikl->ijl", Si, M_i)  # S⁻¹M_i
    E = float(np.sum(np.einsum("ijj->i", C)) - 2 * np.einsum("ijk,ikj->", B, C)
              + sum(np.trace(b @ b @ Si @ M) for b in B))
    if not (E > 0 and np.isfinite(T)):
        return 1.0, float("nan")
    return T / E, E


def dispersion_factor(noise_model: dict) -> float:
    """The factor the images' dispersion puts on a plane's own covariance, from the plane file's
    ``noise_model``: ``max(image_dispersion, 1)`` where the covariance applies it, else 1.

    The dispersion is the ratio of two variances of the images' pulls on the plane, the observed over
    the noise model's (:func:`image_dispersion`).  Errors shared within an image add to that variance;
    nothing physical takes from it, so a ratio below 1 is the statistic's sampling (sd ~0.3-0.5 with
    12 images) and the noise model's variance is kept: the positive part of a variance component's
    moment estimate.  Under white noise this raises the variance by ~10 % on average (the statistic
    averages 1), where the raw ratio would leave a third of the calibrations optimistic by its
    sampling.  ``noise_model`` keeps ``image_dispersion`` as estimated (the statistic), and
    ``image_dispersion_factor`` what was applied (files without it: the ratio, as written then).
    """
    if not noise_model.get("image_dispersion_applied"):
        return 1.0
    f = noise_model.get("image_dispersion_factor")
    if f is not None:
        return float(f)
    return float(noise_model.get("image_dispersion") or 1.0)


def _scale_normals(a: "_Normal", f: float) -> "_Normal":
    return _Normal(a.A * f, a.B * f, a.D * f, a.gp * f, a.gi * f)


def _row_leverages(prob: "_Problem", Jb, Hinv: np.ndarray) -> np.ndarray:
    """(m,) diagonal of the hat matrix ``J H⁻¹ Jᵀ`` of the (weighted) rows, from the block Jacobian."""
    J_rim, J_sp, J_spose = Jb
    n = prob.n
    idx = 3 + 5 * np.arange(n)[:, None] + np.arange(5)  # (n, 5) pose columns
    Hpp = Hinv[idx[:, :, None], idx[:, None, :]]  # (n, 5, 5)
    lev_r = np.einsum("ij,ijk,ik->i", J_rim, Hpp[prob.rim_idx], J_rim)
    cols = np.concatenate([np.tile(np.arange(3), (n, 1)), idx], axis=1)  # (n, 8) plane + pose i
    Hb = Hinv[cols[:, :, None], cols[:, None, :]]  # (n, 8, 8)
    Js = np.concatenate([J_sp, J_spose], axis=1)
    lev_s = np.einsum("ij,ijk,ik->i", Js, Hb[prob.st_idx], Js)
    return np.concatenate([lev_r, lev_s])


def _add_normals(a: "_Normal", b: "_Normal") -> "_Normal":
    return _Normal(a.A + b.A, a.B + b.B, a.D + b.D, a.gp + b.gp, a.gi + b.gi)


# -------------------------------------------------------- simulation & CRLB
def chord_endpoints(plane: LightPlane, center: np.ndarray, normal: np.ndarray, radius_mm: float) -> np.ndarray | None:
    """(2, 3) ends of the chord where the light plane cuts the disc, or None if it misses (mm)."""
    n, N = plane.normal, np.asarray(normal, float)
    u = np.cross(n, N)
    nu = np.linalg.norm(u)
    if nu < 1e-12:
        return None
    u /= nu
    # point on both planes closest to the centre: C + α n' within the target plane
    A = np.stack([n, N, u])
    b = np.array([-plane.d, N @ center, u @ center])
    p0 = np.linalg.solve(A, b)
    off = p0 - center
    disc = radius_mm**2 - off @ off
    if disc <= 0:
        return None
    t = np.sqrt(disc)
    return np.stack([p0 - t * u, p0 + t * u])


def simulate_points(camera: Camera, plane: LightPlane, center: np.ndarray, normal: np.ndarray, radius_mm: float,
                    n_rim: int, n_stripe: int, sigma_px: float = 0.0, rng: np.random.Generator | None = None):
    """Noise-free (or noisy) rim and stripe points of one placement, distorted px.

    Rim points at ``n_rim`` equally spaced angles, stripe points equally spaced
    along the chord (ends excluded).  Returns ``(rim_uv (n_rim, 2), stripe_uv (n_stripe, 2))``.
    """
    center = np.asarray(center, float)
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    t = _tangent_basis(normal)
    th = 2 * np.pi * np.arange(n_rim) / n_rim
    rim = center + radius_mm * (np.cos(th)[:, None] * t[0] + np.sin(th)[:, None] * t[1])
    ends = chord_endpoints(plane, center, normal, radius_mm)
    if ends is None:
        raise LightplaneError("the light plane does not cross the target")
    s = (np.arange(n_stripe) + 0.5) / n_stripe
    st = ends[0] + s[:, None] * (ends[1] - ends[0])
    rim_uv = camera.project(rim)
    st_uv = camera.project(st)
    if sigma_px > 0:
        if rng is None:
            raise LightplaneError("simulate_points: pass an rng when sigma_px > 0")
        rim_uv = rim_uv + rng.normal(0, sigma_px, rim_uv.shape)
        st_uv = st_uv + rng.normal(0, sigma_px, st_uv.shape)
    return rim_uv, st_uv


def crlb(camera: Camera, radius_mm: float, placements_true: Sequence[Any], plane_true: LightPlane, n_rim: int,
         n_stripe: int, sigma_px: float | None = None, *, sigma_rim_px: float | None = None,
         sigma_stripe_px: float | None = None,
         observations: Sequence[tuple[np.ndarray, np.ndarray]] | None = None) -> np.ndarray:
    """Cramér–Rao lower bound (4, 4) on the covariance of ``(a, b, c, d)``.

    Fisher information of the joint model of :func:`refine_ml` at the truth,
    ``J_rimᵀJ_rim / sigma_rim² + J_stripeᵀJ_stripe / sigma_stripe²`` (white Gaussian
    noise; ``sigma_px`` sets both, or give ``sigma_rim_px`` and ``sigma_stripe_px``),
    with noise-free points (``n_rim`` equally spaced on each rim, ``n_stripe`` along
    each chord, as :func:`simulate_points`, or the given noise-free ``observations``
    [(rim_uv, stripe_uv), ...]); the 3x3 bound on the minimal plane parameters is
    mapped to ``(a, b, c, d)`` (rank 3).  ``placements_true``: objects with ``center``
    (mm) and ``normal``.
    """
    s_r = sigma_px if sigma_rim_px is None else sigma_rim_px
    s_s = sigma_px if sigma_stripe_px is None else sigma_stripe_px
    if s_r is None or s_s is None:
        raise LightplaneError("crlb: give sigma_px, or both sigma_rim_px and sigma_stripe_px")
    s_r, s_s = float(s_r), float(s_s)
    if not (s_r >= 0 and s_s >= 0):
        raise LightplaneError(f"sigmas must be >= 0, got rim {s_r}, stripe {s_s}")
    if s_s > 0 and s_r == 0:
        raise LightplaneError("crlb: sigma_rim_px = 0 with sigma_stripe_px > 0 is degenerate")
    if observations is None:
        observations = [simulate_points(camera, plane_true, p.center, p.normal, radius_mm, n_rim, n_stripe)
                        for p in placements_true]
    rims = [o[0] for o in observations]
    stripes = [o[1] for o in observations]
    prob = _Problem(camera, radius_mm, rims, stripes, plane_true, list(placements_true))
    # information in units of 1/sigma_stripe²: rim rows weighted by sigma_stripe / sigma_rim
    ratio = s_s / s_r if s_r > 0 else 1.0
    prob.set_row_weights(np.concatenate([np.full(prob.m_rim, ratio), np.ones(prob.m - prob.m_rim)]))
    r, Jb = prob.evaluate(prob.x0, want_jac=True)
    cov_p, _ = prob.normal_equations(r, Jb).covariance(s_s if s_r > 0 else 0.0)
    _, dn, *_ = prob.unpack(prob.x0)
    G = plane_param_jacobian(dn)
    return G @ cov_p @ G.T


def placement_information(camera: Camera, radius_mm: float, placements: Sequence[Any], plane: LightPlane, *,
                          sigma_rim_px: float, sigma_stripe_px: float, n_rim: int = 64, n_stripe: int = 32,
                          rim_points: np.ndarray | None = None, stripe_points: np.ndarray | None = None,
                          observations: Sequence[tuple[np.ndarray, np.ndarray]] | None = None
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Each placement's Fisher information on the plane, its own pose marginalised: ``(I (n, 3, 3), G (4, 3))``.

    The joint model of :func:`refine_ml` (and of :func:`crlb`) at ``plane``: its Fisher
    information is block-arrowhead (plane, then one pose block per placement), so the plane's
    marginal information is the sum over placements of ``A_i − B_i D_i⁻¹ B_iᵀ``; this returns
    those terms, in the minimal plane parameters ``(α, β, d)`` (the normal moved in its tangent
    plane at ``plane.normal``: the same basis for every call with the same plane).  A set of
    placements has the covariance ``G (Σ I_i)⁻¹ Gᵀ`` of ``(a, b, c, d)`` (:func:`crlb` for the
    same points).  Each placement is sampled by ``n_rim`` rim and ``n_stripe`` stripe points (as
    :func:`simulate_points`, or the given noise-free ``observations``), each standing for
    ``rim_points[i] / n_rim`` (``stripe_points[i] / n_stripe``) observed points of white noise
    ``sigma_rim_px`` (``sigma_stripe_px``): a long curve's information is its sampled integral.
    Raises :class:`LightplaneError` where the light plane misses a placement's disc.
    """
    s_r, s_s = float(sigma_rim_px), float(sigma_stripe_px)
    if not (s_r > 0 and s_s > 0 and np.isfinite(s_r) and np.isfinite(s_s)):
        raise LightplaneError(f"sigmas must be positive, got rim {s_r}, stripe {s_s}")
    placements = list(placements)
    if not placements:
        return np.zeros((0, 3, 3)), plane_param_jacobian(_tangent_basis(plane.normal).T)
    if observations is None:
        observations = [simulate_points(camera, plane, p.center, p.normal, radius_mm, n_rim, n_stripe)
                        for p in placements]
    rims, stripes = [o[0] for o in observations], [o[1] for o in observations]
    prob = _Problem(camera, radius_mm, rims, stripes, plane, placements)
    nr = np.array([len(a) for a in rims], float)
    ns = np.array([len(a) for a in stripes], float)
    fr = nr if rim_points is None else np.asarray(rim_points, float)
    fs = ns if stripe_points is None else np.asarray(stripe_points, float)
    w_rim = np.sqrt(fr / nr) / s_r
    w_st = np.sqrt(fs / ns) / s_s
    prob.set_row_weights(np.concatenate([w_rim[prob.rim_idx], w_st[prob.st_idx]]))
    r, Jb = prob.evaluate(prob.x0, want_jac=True)
    ne = prob.normal_equations(r, Jb)
    J_sp = Jb[1]
    A = np.add.reduceat(np.einsum("ij,ik->ijk", J_sp, J_sp), prob.st_starts)
    BDinv = np.einsum("nij,njk->nik", ne.B, np.linalg.pinv(ne.D, hermitian=True))
    info = A - np.einsum("nij,nkj->nik", BDinv, ne.B)
    _, dn, *_ = prob.unpack(prob.x0)
    return 0.5 * (info + np.swapaxes(info, 1, 2)), plane_param_jacobian(dn)
