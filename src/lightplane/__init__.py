"""lightplane: line-structured-light calibration with a single circular target, and 3D measurement.

Implements Wang & Li, "Calibration Method for Line-Structured Light
Three-Dimensional Measurements Based on a Single Circular Target",
Appl. Sci. 2022, 12, 588, and goes beyond it (global disambiguation, joint
maximum-likelihood refinement, uncertainty).  Conventions: SPEC.md §2
(camera frame x right, y down, z forward; mm; plane normal with d < 0).
"""

from __future__ import annotations

__version__ = "0.1.0"

from .camera import Camera
from .errors import LightplaneError
from .measure import triangulate
from .plane import LightPlane

__all__ = ["Camera", "LightPlane", "LightplaneError", "triangulate", "__version__"]
