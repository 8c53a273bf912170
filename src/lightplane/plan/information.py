"""What a placement's information does to the point sigma over the working volume.

The plane's information from a set of placements is the sum of the placements' own terms
(:func:`lightplane.plane.ml.placement_information`: the Cramér–Rao model of the ML
refinement, each placement's pose marginalised), in the minimal plane parameters
``(α, β, d)`` with ``(a, b, c, d)``-Jacobian ``G``.  A point triangulated from a pixel of
the working volume errs by ``J_k δ`` with ``J_k = ∂X/∂(a, b, c, d) G``
(:func:`lightplane.plane.uncertainty.point_jacobian`), so with ``S = (Σ I)⁻¹`` its
variance is ``tr(S J_kᵀ J_k)`` plus the camera's share (the columns beyond the plane's of
:func:`lightplane.plane.uncertainty.point_error_basis`, which do not shrink with more
placements).  The shape figure projects both out of the rigid motion over the volume
(:func:`lightplane.plane.uncertainty.shape_error_basis`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.plane.model import LightPlane
from lightplane.plane.ml import placement_information
from lightplane.plane.uncertainty import (WorkingVolume, camera_share_status, point_error_basis, point_jacobian,
                                          shape_error_basis)

__all__ = ["VolumeModel", "plane_jacobian_g", "covariance_from_information", "information_from_covariance",
           "FRAMES"]

#: The two figures a point sigma can be stated in.
FRAMES = ("camera", "shape")


def plane_jacobian_g(camera: Camera, plane: LightPlane) -> np.ndarray:
    """(4, 3) ``∂(a, b, c, d)/∂(α, β, d)`` of the minimal parameters :func:`placement_information` uses at ``plane``."""
    return placement_information(camera, 1.0, [], plane, sigma_rim_px=1.0, sigma_stripe_px=1.0)[1]


def covariance_from_information(info: np.ndarray, G: np.ndarray) -> np.ndarray:
    """(4, 4) covariance of ``(a, b, c, d)`` from a (3, 3) information of the minimal parameters."""
    return G @ np.linalg.inv(info) @ G.T


def information_from_covariance(cov: np.ndarray, G: np.ndarray) -> np.ndarray:
    """(3, 3) information of the minimal parameters from a (4, 4) covariance of ``(a, b, c, d)`` (G's columns
    are orthonormal in the normal's part, so ``Gᵀ Σ G`` is the minimal parameters' covariance)."""
    return np.linalg.inv(G.T @ np.asarray(cov, float) @ G)


@dataclass(frozen=True)
class _Parts:
    Q: np.ndarray        # (N, 3, 3) per point J_kᵀ J_k in the minimal parameters
    cam_var: np.ndarray  # (N,) the camera's share of each point's variance (mm²)


class VolumeModel:
    """Per-point sigma over a working volume for any information of the plane (module docstring).

    ``frame``: ``"camera"`` (absolute positions) or ``"shape"`` (after the best rigid motion
    over the volume); ``camera_plane``: the plane whose record of its dependence on the
    intrinsics gives the camera's share (default ``plane``; None where it records none).
    """

    def __init__(self, camera: Camera, plane: LightPlane, volume: WorkingVolume, *, frame: str = "camera",
                 camera_plane: LightPlane | None = None):
        if frame not in FRAMES:
            raise LightplaneError(f"frame must be one of {', '.join(FRAMES)}, got {frame!r}")
        self.camera, self.plane, self.frame = camera, plane, frame
        self.G = plane_jacobian_g(camera, plane)
        xy = camera.undistort_points(volume.uv, normalized=True)
        J = point_jacobian(plane, xy)
        ok = np.all(np.isfinite(J), axis=(1, 2))
        if np.count_nonzero(ok) < 3:
            raise LightplaneError("fewer than 3 working-volume points whose rays meet the light plane")
        self.uv, self.points = volume.uv[ok], volume.points[ok]
        JG = J[ok] @ self.G
        cam_plane = plane if camera_plane is None else camera_plane
        self.camera_share_note = camera_share_status(camera, cam_plane)
        E, inc = point_error_basis(camera, cam_plane, self.uv, covariance=np.zeros((4, 4)))
        Ec = E[:, :, 4:] if inc else np.zeros((len(self.uv), 3, 0))
        if frame == "shape":
            JG = shape_error_basis(JG, self.points)
            if Ec.shape[2]:
                Ec = shape_error_basis(Ec, self.points)
        self._parts = _Parts(np.einsum("nki,nkj->nij", JG, JG), np.sum(Ec**2, axis=(1, 2)))

    @property
    def camera_included(self) -> bool:
        return self.camera_share_note is None

    def sigma(self, info: np.ndarray) -> np.ndarray:
        """(N,) or (k, N) point sigmas (mm) for one (3, 3) information or a stack (k, 3, 3); infinite where an
        information does not determine the plane."""
        info = np.asarray(info, float)
        w = np.linalg.eigvalsh(info)
        ok = w[..., 0] > 1e-15 * np.maximum(w[..., -1], 1e-300)
        S = np.linalg.inv(np.where(ok[..., None, None], info, np.eye(3)))
        var = np.einsum("...ij,nji->...n", S, self._parts.Q)
        var = np.where(ok[..., None], var, np.inf)
        return np.sqrt(np.maximum(var, 0.0) + self._parts.cam_var)

    def camera_floor(self) -> np.ndarray:
        """(N,) the camera's share of each point's sigma (mm): what no placement reduces."""
        return np.sqrt(self._parts.cam_var)

    def figure(self, sigma: np.ndarray, percentile: float) -> np.ndarray:
        """The stated percentile (100: the worst) of point sigmas over the volume (last axis)."""
        s = np.where(np.isfinite(sigma), sigma, 1e300)
        q = np.percentile(s, percentile, axis=-1)
        return np.where(q >= 1e299, np.inf, q)

    def variance_shares(self, infos: np.ndarray) -> np.ndarray:
        """(n,) each placement's share of the volume's mean plane variance reduction: with ``S = (Σ I_i)⁻¹``
        and ``Q̄`` the volume's mean point term, ``tr(S Q̄ S I_i) / tr(S Q̄)``; they sum to 1."""
        infos = np.asarray(infos, float)
        S = np.linalg.inv(infos.sum(axis=0))
        Qm = self._parts.Q.mean(axis=0)
        W = S @ Qm @ S
        return np.einsum("ij,nji->n", W, infos) / np.trace(S @ Qm)
