"""After the fact: how much each placement of a finished calibration added (its information share).

Each used placement's Fisher information on the plane (:func:`lightplane.plane.ml.placement_information`
at the solved plane and poses, with its observed points and the rim and stripe noise the ML
refinement estimated, their correlation along the curves included) and its share of the
plane's variance over the working volume (:meth:`lightplane.plan.information.VolumeModel.variance_shares`:
the shares sum to 1).  A placement whose share is under half of an even share (``1 / (2 n)``)
added little: dropping it would have changed the point sigma by little.
"""

from __future__ import annotations

import numpy as np

from lightplane.camera.model import Camera
from lightplane.core.errors import LightplaneError
from lightplane.plane.ml import placement_information
from lightplane.plane.uncertainty import working_volume_grid
from lightplane.plan.information import VolumeModel

__all__ = ["information_shares", "LITTLE"]

#: A placement added little when its share is below this fraction of an even share.
LITTLE = 0.5


def information_shares(cal, camera: Camera) -> dict[int, float]:
    """``{image index: share}`` over the used placements of an ``ml`` plane calibration
    (:class:`lightplane.plane.calibrate.ImagePlaneCalibration`); the working volume is the image
    region where the plane is seen at the used targets' distances.  Raises when the calibration
    has no noise model (another method) or fewer than two used placements."""
    nm = cal.plane.meta.get("noise_model") or {}
    if nm.get("sigma_rim_px") is None or nm.get("sigma_stripe_px") is None:
        raise LightplaneError("information shares need an 'ml' calibration (its noise model)")
    used = [o for o in cal.images if o.used and o.placement is not None and o.placement.pose is not None]
    if len(used) < 2:
        raise LightplaneError("information shares need at least 2 used placements")
    poses = [o.placement.pose for o in used]
    infos, _ = placement_information(
        camera, 0.5 * cal.diameter_mm, poses, cal.plane,
        sigma_rim_px=float(nm["sigma_rim_px"]) * np.sqrt(float(nm.get("tau_rim", 1.0))),
        sigma_stripe_px=float(nm["sigma_stripe_px"]) * np.sqrt(float(nm.get("tau_stripe", 1.0))),
        observations=[(o.rim_uv, o.stripe_uv) for o in used])
    d = [float(np.linalg.norm(p.center)) for p in poses]
    lo, hi = min(d), max(d)
    if hi - lo < 1.0:
        lo, hi = lo - 0.5, hi + 0.5
    vol = working_volume_grid(camera, cal.plane, distance_mm=(lo, hi), step_px=32.0)
    shares = VolumeModel(camera, cal.plane, vol).variance_shares(infos)
    return {int(o.index): float(s) for o, s in zip(used, shares)}
