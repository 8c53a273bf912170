"""Scoring against the renderer's exact truth (``truth.json`` of :mod:`lightplane.simulate.render`).

Shared by the tests and the benchmarks, so that both measure the same thing.
"""

from __future__ import annotations

import numpy as np

from lightplane.camera.model import Camera

__all__ = ["stripe_chord_errors", "profile_axis_and_roi"]


def stripe_chord_errors(camera: Camera, target: dict, uv: np.ndarray, width_px: float, *,
                        rim_margin: float = 1.5, gross_px: float = 3.0) -> tuple[np.ndarray, int]:
    """Signed distances (px) of stripe centres to the projected true chord, and the count of gross errors.

    ``target`` is one image's ``truth["images"][i]["target"]`` (``chord_mm``, ``center_mm``,
    ``normal``, ``diameter_mm``); ``uv`` (N, 2) distorted px.  The chord is projected
    through the distorted camera (densely sampled), each centre's signed distance taken
    along the chord's local normal.  Only centres whose stripe lies wholly on the disc
    are scored: farther from the projected rim than ``rim_margin`` stripe widths
    (``width_px``, FWHM) — a stripe cut by the rim is biased by the truncation, not by
    the extractor.  Scored centres farther than ``gross_px`` from the chord are counted
    as gross errors and left out of the returned distances.
    """
    uv = np.asarray(uv, float).reshape(-1, 2)
    if len(uv) == 0:
        return np.empty(0), 0
    chord = np.asarray(target["chord_mm"], float)
    s = np.linspace(0.0, 1.0, 4001)[:, None]
    poly = camera.project(chord[0] + s * (chord[1] - chord[0]))
    centre, normal = np.asarray(target["center_mm"], float), np.asarray(target["normal"], float)
    e1 = np.cross(normal, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    phi = np.linspace(0.0, 2 * np.pi, 1000, endpoint=False)[:, None]
    rim = camera.project(centre + 0.5 * float(target["diameter_mm"]) * (np.cos(phi) * e1 + np.sin(phi) * e2))
    d = np.linalg.norm(uv[:, None, :] - poly[None, ::4, :], axis=2)
    j = np.clip(np.argmin(d, axis=1) * 4, 1, len(poly) - 2)
    t = poly[j + 1] - poly[j - 1]
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    e = np.sum((uv - poly[j]) * np.column_stack([-t[:, 1], t[:, 0]]), axis=1)
    d_rim = np.min(np.linalg.norm(uv[:, None, :] - rim[None], axis=2), axis=1)
    on_disc = d_rim > rim_margin * float(width_px)
    gross = on_disc & (np.abs(e) >= gross_px)
    return e[on_disc & ~gross], int(gross.sum())


def profile_axis_and_roi(camera: Camera, target: dict) -> tuple[str, tuple[int, int, int, int]]:
    """Profile axis for the target's chord (``columns`` if it runs more along u) and the rim's bounding box
    ``(x, y, width, height)`` px as a region of interest."""
    duv = np.diff(camera.project(np.asarray(target["chord_mm"], float)), axis=0)[0]
    x0, y0, x1, y1 = target["rim_bbox_px"]
    return ("columns" if abs(duv[0]) > abs(duv[1]) else "rows"), (int(x0), int(y0), int(x1 - x0), int(y1 - y0))
