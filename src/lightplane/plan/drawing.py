"""A placement plan drawn over the camera's image: the working volume and each placement's ghost outline."""

from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np

from lightplane.camera.model import Camera
from lightplane.plane.uncertainty import WorkingVolume

__all__ = ["draw_plan", "ghost_colour"]


def ghost_colour(k: int, n: int) -> tuple[int, int, int]:
    """BGR colour of the k-th of n outlines: from blue (first) to orange (last)."""
    t = 0.0 if n <= 1 else k / (n - 1)
    return (int(230 * (1 - t) + 40 * t), int(120 + 40 * t), int(40 * (1 - t) + 240 * t))


def draw_plan(camera: Camera, volume: WorkingVolume, outlines: Sequence[np.ndarray], labels: Sequence[str] = (),
              background: np.ndarray | None = None, title: str = "") -> np.ndarray:
    """(H, W, 3) uint8 BGR: ``background`` (or a dark frame of the camera's size), the working volume's samples
    (gray dots), each outline (px) numbered from 1 with its label beside it, and ``title`` at the top."""
    h, w = camera.height, camera.width
    img: np.ndarray
    if background is None:
        img = np.full((h, w, 3), 24, np.uint8)
    else:
        b = np.asarray(background)
        b = b if b.dtype == np.uint8 else np.clip(b * (255.0 / max(float(b.max()), 1e-9)), 0, 255).astype(np.uint8)
        img = cv2.cvtColor(b, cv2.COLOR_GRAY2BGR) if b.ndim == 2 else b.copy()
    for u, v in np.round(volume.uv).astype(int):
        cv2.circle(img, (int(u), int(v)), 2, (110, 110, 110), -1, cv2.LINE_AA)
    n = len(outlines)
    placed: list[tuple[float, float]] = []
    for k, poly in enumerate(outlines):
        c = ghost_colour(k, n)
        pts = np.round(np.asarray(poly) * 16).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(img, [pts], True, c, 2, cv2.LINE_AA, shift=4)
        cu, cv_ = np.mean(poly, axis=0)
        repeats = sum(1 for a, b in placed if abs(a - cu) < 30 and abs(b - cv_) < 30)
        placed.append((cu, cv_))
        cv_ += 24 * repeats  # the same place again: its label below the earlier ones
        text = f"{k + 1}" + (f" {labels[k]}" if k < len(labels) and labels[k] else "")
        cv2.putText(img, text, (int(cu) - 10, int(cv_) + 6), cv2.FONT_HERSHEY_SIMPLEX, 0.6, c, 2, cv2.LINE_AA)
    if title:
        cv2.putText(img, title, (12, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (235, 235, 235), 2, cv2.LINE_AA)
    return img
