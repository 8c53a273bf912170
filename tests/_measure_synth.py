"""Exact synthetic stripe frames for the measurement tests (not a test module).

A light plane cuts a flat surface along a 3D line; the line is projected through the
distorted camera and drawn as a Gaussian stripe (float32, no noise), so the true
stripe centre of every row and the true 3D points are known exactly.
"""

from __future__ import annotations

import numpy as np

from lightplane import Camera, LightPlane

CAM = Camera(K=[[2000.0, 0, 331.5], [0, 2000.0, 236.8], [0, 0, 1]], dist=[-0.12, 0.2, 5e-4, -3e-4, 0.0],
             width=640, height=480)
_T = np.deg2rad(25.0)
PLANE = LightPlane([np.cos(_T), 0.0, -np.sin(_T)], 450.0 * np.sin(_T))  # stripe runs along the columns of the image
SIGMA_PX = 1.5


def surface(tilt_deg: float = 20.0, z_mm: float = 455.0) -> tuple[np.ndarray, float]:
    """A flat surface (unit normal n, d) tilted about y, through (0, 0, z_mm)."""
    t = np.deg2rad(tilt_deg)
    n = np.array([np.sin(t), 0.2, -np.cos(t)])
    n /= np.linalg.norm(n)
    return n, float(-n @ np.array([0.0, 0.0, z_mm]))


def stripe_line(n_s: np.ndarray, d_s: float, plane: LightPlane = PLANE, camera: Camera = CAM, m: int = 20001):
    """Dense points of the light-plane/surface line and their distorted pixels, sorted by v."""
    direction = np.cross(plane.normal, n_s)
    A = np.vstack([plane.normal, n_s, direction])
    p0 = np.linalg.solve(A, [-plane.d, -d_s, 0.0])
    t = np.linspace(-150, 150, m)
    pts = p0 + t[:, None] * direction / np.linalg.norm(direction)
    uv = camera.project(pts)
    ok = np.isfinite(uv).all(axis=1)
    order = np.argsort(uv[ok, 1])
    return pts[ok][order], uv[ok][order]


def stripe_image(n_s, d_s, *, amplitude: float = 200.0, background: float = 10.0, shift_px: float = 0.0,
                 plane: LightPlane = PLANE, camera: Camera = CAM) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) float32 image of the stripe (Gaussian across the rows) and the true centre u per row (NaN off it)."""
    _, uv = stripe_line(n_s, d_s, plane, camera)
    rows = np.arange(camera.height, dtype=float)
    inside = (rows >= uv[0, 1]) & (rows <= uv[-1, 1])
    u_c = np.where(inside, np.interp(rows, uv[:, 1], uv[:, 0]), np.nan) + shift_px
    u = np.arange(camera.width, dtype=float)[None, :]
    img = background + amplitude * np.exp(-0.5 * ((u - u_c[:, None]) / SIGMA_PX) ** 2)
    img[~inside] = background
    return img.astype(np.float32), u_c


def write_scan(folder, n_frames: int, frames_folder: str | None = None) -> list:
    """camera.json, plane.json (CAM, PLANE) and ``n_frames`` 8-bit stripe frames of the tilted
    surface, each shifted by a quarter pixel, in ``folder`` (frames in ``frames_folder`` below it
    when given); returns the frame paths."""
    import cv2

    from pathlib import Path

    d = Path(folder)
    CAM.save_json(d / "camera.json")
    PLANE.save(d / "plane.json")
    fd = d / frames_folder if frames_folder else d
    fd.mkdir(exist_ok=True)
    n_s, d_s = surface()
    paths = []
    for k in range(n_frames):
        img, _ = stripe_image(n_s, d_s, shift_px=0.25 * k)
        paths.append(fd / f"f{k:02d}.png")
        cv2.imwrite(str(paths[-1]), np.clip(np.rint(img), 0, 255).astype(np.uint8))
    return paths
