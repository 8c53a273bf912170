"""Ray-casting core of the image renderer (numba).

A scene is a few analytic primitives in the camera frame (mm):

- *planar patches*, rows of a ``(P, PATCH_COLS)`` float64 array: origin, two unit
  in-plane axes ``e1, e2``, unit normal, a region (infinite, ellipse or rectangle
  in the patch's ``(u, v)`` coordinates), an albedo and an optional texture (a
  chessboard; a binary bitmap of square cells, looked up by nearest cell, e.g. a
  ChArUco board; a grid of dots, symmetric or staggered, e.g. a circle-grid target);
  coplanar patches (a printed disc on its board) are resolved by the
  ``layer`` column, the higher one wins;
- *spheres*, rows of a ``(Q, SPHERE_COLS)`` array: centre, radius, albedo.

Every surface is Lambertian: radiance ``albedo * (E_ambient + E_laser)`` (grey
levels before noise).  The laser sheet has a Gaussian thickness: at a surface
point ``p`` with unit normal ``n`` (facing the camera)

    E_laser = P * exp(-dist(p, sheet)² / (2 s²)) * max(0, n·l) * (R0 / |L - p|) * speckle(p)

with ``L`` the laser's source (a point of the plane beside the camera; the sheet a plane, or a
cone with its apex at ``L``: a tilted fan lens, :func:`make_laser`), ``l`` the
unit direction from ``p`` to ``L`` and a shadow test along ``p -> L`` (the disc
shadows the background).  ``speckle(p)`` is ``max(0, 1 + c·noise(p))`` with a
smooth 3-D value noise of unit variance and lattice spacing ``corr_mm``, so ``c`` is
the standard deviation of the modulation at a point (before pixel averaging):
a multiplicative, spatially correlated modulation of the sheet (docs/conventions.md §Noise; docs/method.md §Renderer).

Pixels are integrated by stratified jittered supersampling: ``S x S`` samples in
every pixel, then every pixel whose samples do not all see the same material
(and its 8 neighbours) is integrated again with ``F x F`` samples, so edges are
anti-aliased to ~1e-3 px without paying ``F²`` everywhere.  Each sample's pixel
position is mapped to its camera ray through the *distorted* camera by Newton's
method on the camera's exact lens model (lightplane.camera.lens, docs/conventions.md §Lens model), started from the pixel centre's
solution (two or three steps reach 1e-15).  Sample positions come from a
deterministic integer hash, so the same scene gives the same bytes.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from lightplane.core.threads import ensure_configured
from lightplane.core.jit import njit_cached
from lightplane.camera.lens_kernels import distort_jac_kernel, newton_step_kernel
from lightplane.camera.lens import lens_params, undistort_guess
from lightplane.core.errors import LightplaneError

PATCH_COLS = 26
SPHERE_COLS = 5
LASER_COLS = 17

# patch columns
_O, _E1, _E2, _N = 0, 3, 6, 9
_SHAPE, _R0, _R1, _R2, _R3 = 12, 13, 14, 15, 16
_ALB, _TEX, _SQ, _NSX, _NSY, _ALB2, _LAYER = 17, 18, 19, 20, 21, 22, 23
_TP0, _TP1 = 24, 25  # texture parameters: bitmap (offset in the texel pool, -), dots (radius, staggered)

SHAPE_INFINITE, SHAPE_ELLIPSE, SHAPE_RECT = 0, 1, 2
TEX_NONE, TEX_CHECKER, TEX_BITMAP, TEX_DOTS = 0, 1, 2, 3


def make_patch(
    origin,
    e1,
    e2,
    *,
    shape: int = SHAPE_INFINITE,
    region=(0.0, 0.0, 0.0, 0.0),
    albedo: float = 0.5,
    layer: int = 0,
    checker: tuple[float, int, int, float] | None = None,
    bitmap: tuple[float, int, int, float, int] | None = None,
    dots: tuple[float, int, int, float, float, bool] | None = None,
) -> np.ndarray:
    """One patch row.

    ``region``: ellipse ``(a, b, -, -)`` semi-axes along ``e1, e2`` (mm), or rectangle
    ``(u_min, u_max, v_min, v_max)`` (mm).  ``checker=(square_mm, n_x, n_y, dark_albedo)``
    paints ``n_x x n_y`` squares starting at ``(-square, -square)``, the first one dark, so
    that the inner corners are at ``(i·square, j·square)`` (OpenCV's board frame).

    ``bitmap=(cell_mm, n_x, n_y, ink_albedo, offset)``: a binary texture of ``n_x x n_y``
    square cells of ``cell_mm``, cell ``(iu, iv)`` covering ``[iu, iu + 1) x [iv, iv + 1)``
    cells from the patch origin; its texels (1 = ink) are ``pool[offset + iv * n_x + iu]``
    of the texel pool given to :func:`render_radiance`.  Exact for any layout whose edges
    lie on the cell grid (a board of squares and square markers).

    ``dots=(pitch_mm, cols, rows, ink_albedo, radius_mm, staggered)``: ink discs of
    ``radius_mm`` centred at ``(i·pitch, j·pitch)`` (``i < cols, j < rows``), or, staggered,
    at ``((2 i + j mod 2)·pitch, j·pitch)`` (OpenCV's asymmetric circle grid); exact discs
    as long as they do not overlap (radius < pitch/2, staggered: < pitch/√2).
    """
    e1 = np.asarray(e1, dtype=np.float64)
    e2 = np.asarray(e2, dtype=np.float64)
    e1 = e1 / np.linalg.norm(e1)
    e2 = e2 - (e2 @ e1) * e1
    e2 = e2 / np.linalg.norm(e2)
    row = np.zeros(PATCH_COLS)
    row[_O:_O + 3] = origin
    row[_E1:_E1 + 3] = e1
    row[_E2:_E2 + 3] = e2
    row[_N:_N + 3] = np.cross(e1, e2)
    row[_SHAPE] = shape
    row[_R0:_R0 + 4] = region
    row[_ALB] = albedo
    row[_LAYER] = layer
    if checker is not None:
        row[_TEX] = TEX_CHECKER
        row[_SQ], row[_NSX], row[_NSY], row[_ALB2] = checker
    if bitmap is not None:
        row[_TEX] = TEX_BITMAP
        row[_SQ], row[_NSX], row[_NSY], row[_ALB2], row[_TP0] = bitmap
    if dots is not None:
        pitch, cols, rows, ink, radius, staggered = dots
        if not 0 < radius < pitch * (np.sqrt(0.5) if staggered else 0.5):
            raise ValueError(f"dots of radius {radius} mm overlap at pitch {pitch} mm")
        row[_TEX] = TEX_DOTS
        row[_SQ], row[_NSX], row[_NSY], row[_ALB2] = pitch, cols, rows, ink
        row[_TP0], row[_TP1] = radius, float(bool(staggered))
    if sum(x is not None for x in (checker, bitmap, dots)) > 1:
        raise ValueError("a patch has one texture")
    return row


def make_sphere(center, radius_mm: float, albedo: float) -> np.ndarray:
    row = np.zeros(SPHERE_COLS)
    row[:3] = center
    row[3] = radius_mm
    row[4] = albedo
    return row


def make_laser(plane_normal, plane_d, source, *, power: float, sigma_mm: float, speckle: float = 0.0,
               corr_mm: float = 0.12, seed: int = 0, cone: tuple | None = None) -> np.ndarray:
    """Laser row: plane normal (3), d (mm), source (3, mm), power (grey levels at albedo 1, normal
    incidence, 450 mm), sheet sigma_mm, speckle contrast, speckle corr_mm, speckle seed, and the
    curved sheet: ``cone=(axis, tau)``, the sheet a circular cone with its apex at ``source``,
    unit ``axis`` and half-angle ``pi/2 - tau`` (tau in radians; None or tau = 0: the plane)."""
    row = np.zeros(LASER_COLS)
    if cone is not None and float(cone[1]) != 0.0:
        axis = np.asarray(cone[0], dtype=np.float64)
        row[12:15] = axis / np.linalg.norm(axis)
        row[15] = np.sin(float(cone[1]))
        row[16] = np.cos(float(cone[1]))
    row[0:3] = plane_normal
    row[3] = plane_d
    row[4:7] = source
    row[7] = power
    row[8] = sigma_mm
    row[9] = speckle
    row[10] = corr_mm
    row[11] = float(int(seed) % (2**31))
    return row


_R0_MM = 450.0
# 1 / std of _value_noise (measured over 20000 random points: 0.3706): unit-variance noise
_NOISE_UNIT = 2.7

_jit = dict(fastmath=False)


@njit_cached(**_jit)
def _mix(x):
    # splitmix64 finaliser on uint64
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


@njit_cached(**_jit)
def _hash01(a, b, c, d):
    """Deterministic uniform [0, 1) from four integers."""
    h = _mix(np.uint64(a & 0xFFFFFFFF) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(0x632BE59BD9B4E019))
    h = _mix(h ^ (np.uint64(b & 0xFFFFFFFF) * np.uint64(0xC2B2AE3D27D4EB4F)))
    h = _mix(h ^ (np.uint64(c & 0xFFFFFFFF) * np.uint64(0x165667B19E3779F9)))
    h = _mix(h ^ (np.uint64(d & 0xFFFFFFFF) * np.uint64(0x27D4EB2F165667C5)))
    return float(h >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@njit_cached(**_jit)
def _pixel_state(u, v, salt):
    return _mix(np.uint64(u & 0xFFFFFFFF) * np.uint64(0x9E3779B97F4A7C15) ^ _mix(np.uint64(v & 0xFFFFFFFF)
                * np.uint64(0xC2B2AE3D27D4EB4F) + np.uint64(salt & 0xFFFFFFFF)))


@njit_cached(**_jit)
def _next01(state):
    """PCG-style step: (new state, uniform [0, 1))."""
    state = state * np.uint64(6364136223846793005) + np.uint64(1442695040888963407)
    x = state ^ (state >> np.uint64(29))
    x = x * np.uint64(0xBF58476D1CE4E5B9)
    return state, float(x >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@njit_cached(**_jit)
def _value_noise(x, y, z, seed):
    """Smooth 3-D value noise (unit lattice), values in about [-1, 1]."""
    ix = int(np.floor(x))
    iy = int(np.floor(y))
    iz = int(np.floor(z))
    fx = x - ix
    fy = y - iy
    fz = z - iz
    # smoothstep weights: C1 continuous
    wx = fx * fx * (3.0 - 2.0 * fx)
    wy = fy * fy * (3.0 - 2.0 * fy)
    wz = fz * fz * (3.0 - 2.0 * fz)
    acc = 0.0
    for dz in range(2):
        for dy in range(2):
            for dx in range(2):
                w = (wx if dx else 1.0 - wx) * (wy if dy else 1.0 - wy) * (wz if dz else 1.0 - wz)
                acc += w * (2.0 * _hash01(ix + dx, iy + dy, iz + dz, seed) - 1.0)
    return acc


_undistort_guess = njit_cached(**_jit)(undistort_guess)


@njit_cached(**_jit)
def _undistort(xd, yd, x, y, lens, max_iter):
    """Newton's method for distort(x, y) = (xd, yd), started at (x, y); ``lens`` the packed model of
    :func:`lightplane.camera.lens.lens_params` (the one implementation of every lens model)."""
    for _ in range(max_iter):
        x, y, dx, dy, _, _, _, _ = newton_step_kernel(x, y, xd, yd, lens)
        if abs(dx) + abs(dy) < 1e-16:
            break
    return x, y


@njit_cached(**_jit)
def _hit_patch(row, ox, oy, oz, dx, dy, dz, tmin, tmax):
    """Ray o + t d against one patch: (t, u, v) or t = -1 when missed."""
    nx, ny, nz = row[9], row[10], row[11]
    den = nx * dx + ny * dy + nz * dz
    if abs(den) < 1e-14:
        return -1.0, 0.0, 0.0
    t = (nx * (row[0] - ox) + ny * (row[1] - oy) + nz * (row[2] - oz)) / den
    if t <= tmin or t >= tmax:
        return -1.0, 0.0, 0.0
    qx = ox + t * dx - row[0]
    qy = oy + t * dy - row[1]
    qz = oz + t * dz - row[2]
    u = qx * row[3] + qy * row[4] + qz * row[5]
    v = qx * row[6] + qy * row[7] + qz * row[8]
    shape = int(row[12])
    if shape == 1:
        a = u / row[13]
        b = v / row[14]
        if a * a + b * b > 1.0:
            return -1.0, 0.0, 0.0
    elif shape == 2:
        if u < row[13] or u > row[14] or v < row[15] or v > row[16]:
            return -1.0, 0.0, 0.0
    return t, u, v


@njit_cached(**_jit)
def _hit_sphere(row, ox, oy, oz, dx, dy, dz, tmin, tmax):
    cx = ox - row[0]
    cy = oy - row[1]
    cz = oz - row[2]
    a = dx * dx + dy * dy + dz * dz
    b = cx * dx + cy * dy + cz * dz
    c = cx * cx + cy * cy + cz * cz - row[3] * row[3]
    disc = b * b - a * c
    if disc < 0.0:
        return -1.0
    sq = np.sqrt(disc)
    t = (-b - sq) / a
    if t > tmin and t < tmax:
        return t
    t = (-b + sq) / a
    if t > tmin and t < tmax:
        return t
    return -1.0


@njit_cached(**_jit)
def _occluded(patches, spheres, px, py, pz, lx, ly, lz):
    dx = lx - px
    dy = ly - py
    dz = lz - pz
    for k in range(patches.shape[0]):
        t, u, v = _hit_patch(patches[k], px, py, pz, dx, dy, dz, 1e-7, 1.0)
        if t > 0.0:
            return True
    for k in range(spheres.shape[0]):
        if _hit_sphere(spheres[k], px, py, pz, dx, dy, dz, 1e-7, 1.0) > 0.0:
            return True
    return False


@njit_cached(**_jit)
def _bitmap_ink(row, tex, u, v):
    """Is the bitmap texel under (u, v) ink?  (Nearest cell; outside the bitmap: no.)"""
    cell = row[19]
    iu = int(np.floor(u / cell))
    iv = int(np.floor(v / cell))
    nx = int(row[20])
    if iu < 0 or iv < 0 or iu >= nx or iv >= int(row[21]):
        return False
    return tex[int(row[24]) + iv * nx + iu] != 0


@njit_cached(**_jit)
def _dot_ink(row, u, v):
    """Is (u, v) inside one of the grid's dots?  The two nearest rows (and, unstaggered, the
    two nearest columns) hold the only dot a point can be in when the dots do not overlap."""
    p = row[19]
    cols = int(row[20])
    rows = int(row[21])
    r2 = row[24] * row[24]
    fu = u / p
    fv = v / p
    j0 = int(np.floor(fv))
    for j in range(j0, j0 + 2):
        if j < 0 or j >= rows:
            continue
        dv = v - j * p
        if row[25] != 0.0:
            sh = j % 2
            i = int(np.floor((fu - sh) * 0.5 + 0.5))
            if i >= 0 and i < cols:
                du = u - (2 * i + sh) * p
                if du * du + dv * dv < r2:
                    return True
        else:
            i0 = int(np.floor(fu))
            for i in range(i0, i0 + 2):
                if i >= 0 and i < cols:
                    du = u - i * p
                    if du * du + dv * dv < r2:
                        return True
    return False


@njit_cached(**_jit)
def _ink(row, tex, u, v):
    """Is the point (u, v) of a bitmap- or dot-textured patch ``row`` in its ink (the second albedo)?
    (Off :func:`_shade`'s hot path, which tests the chessboard itself.)"""
    if row[18] == 2.0:
        return _bitmap_ink(row, tex, u, v)
    if row[18] == 3.0:
        return _dot_ink(row, u, v)
    return False


@njit_cached(**_jit)
def _cone_distance(laser, px, py, pz):
    """Signed distance (mm) of a point to the curved sheet of :func:`make_laser`: ``v`` from the apex,
    ``a`` the axis, ``sin tau``, ``cos tau``: ``(v.a) cos tau - |v x a| sin tau`` (exact near the sheet;
    at tau = 0 the plane's ``n.p + d``)."""
    vx = px - laser[4]
    vy = py - laser[5]
    vz = pz - laser[6]
    va = vx * laser[12] + vy * laser[13] + vz * laser[14]
    perp = np.sqrt(max(vx * vx + vy * vy + vz * vz - va * va, 0.0))
    return va * laser[16] - perp * laser[15]


@njit_cached(inline="always", **_jit)  # inlined where it is called: 0.7-0.75x the corner probe's time, the compile ~6 s longer once
def _shade(patches, spheres, laser, ambient, x, y, tex):
    """Radiance and material id seen along the ray (x, y, 1)."""
    dx, dy, dz = x, y, 1.0
    best_t = 1e300
    best_k = -1
    best_layer = -1.0e9
    best_u = 0.0
    best_v = 0.0
    for k in range(patches.shape[0]):
        t, u, v = _hit_patch(patches[k], 0.0, 0.0, 0.0, dx, dy, dz, 1e-9, 1e300)
        if t > 0.0:
            layer = patches[k, 23]
            # coplanar patches (a printed disc on its board): the higher layer wins
            if t < best_t - 1e-7 or (abs(t - best_t) <= 1e-7 and layer > best_layer):
                best_t = t
                best_k = k
                best_layer = layer
                best_u = u
                best_v = v
    best_s = -1
    for k in range(spheres.shape[0]):
        t = _hit_sphere(spheres[k], 0.0, 0.0, 0.0, dx, dy, dz, 1e-9, 1e300)
        if t > 0.0 and t < best_t - 1e-7:
            best_t = t
            best_s = k
    if best_k < 0 and best_s < 0:
        return 0.0, -1, 1e9
    px = best_t * dx
    py = best_t * dy
    pz = best_t * dz
    if best_s >= 0:
        row = spheres[best_s]
        nx = (px - row[0]) / row[3]
        ny = (py - row[1]) / row[3]
        nz = (pz - row[2]) / row[3]
        albedo = row[4]
        mat = 2 * (patches.shape[0] + best_s)
    else:
        row = patches[best_k]
        nx, ny, nz = row[9], row[10], row[11]
        albedo = row[17]
        mat = 2 * best_k
        kind = row[18]
        if kind == 1.0:  # chessboard, the common texture, inline
            sq = row[19]
            iu = int(np.floor((best_u + sq) / sq))
            iv = int(np.floor((best_v + sq) / sq))
            if iu >= 0 and iv >= 0 and iu < int(row[20]) and iv < int(row[21]) and (iu + iv) % 2 == 0:
                albedo = row[22]
                mat += 1
        elif kind != 0.0 and _ink(row, tex, best_u, best_v):
            albedo = row[22]
            mat += 1
    # face the camera
    if nx * dx + ny * dy + nz * dz > 0.0:
        nx, ny, nz = -nx, -ny, -nz
    e = ambient
    power = laser[7]
    dist = laser[0] * px + laser[1] * py + laser[2] * pz + laser[3]
    if laser[15] != 0.0:
        dist = _cone_distance(laser, px, py, pz)
    if power > 0.0:
        s = laser[8]
        if abs(dist) < 6.0 * s:
            g = np.exp(-0.5 * dist * dist / (s * s))
            lx = laser[4] - px
            ly = laser[5] - py
            lz = laser[6] - pz
            ln = np.sqrt(lx * lx + ly * ly + lz * lz)
            cosi = (nx * lx + ny * ly + nz * lz) / ln
            if cosi > 0.0:
                if _occluded(patches, spheres, px, py, pz, laser[4], laser[5], laser[6]):
                    mat += 1 << 20  # shadow edges are edges too
                else:
                    el = power * g * cosi * (_R0_MM / ln)
                    c = laser[9]
                    if c > 0.0:
                        inv = 1.0 / laser[10]
                        nz_ = _value_noise(px * inv, py * inv, pz * inv, int(laser[11]))
                        m = 1.0 + c * _NOISE_UNIT * nz_
                        el *= m if m > 0.0 else 0.0
                    e += el
    return albedo * e, mat, dist


@njit_cached(parallel=True, **_jit)
def undistort_grid(fx, fy, cx, cy, skew, lens, width, height, offset):
    """Normalised undistorted ``(x, y)`` of the pixel positions ``(j + offset, i + offset)``,
    ``i < height, j < width``: ``(height, width, 2)`` float64 (Newton, docs/conventions.md §Lens model)."""
    out = np.empty((height, width, 2))
    for i in nb.prange(height):
        for j in range(width):
            yd = (i + offset - cy) / fy
            xd = (j + offset - cx - skew * yd) / fx
            x0, y0 = _undistort_guess(xd, yd, lens)
            x, y = _undistort(xd, yd, x0, y0, lens, np.int64(50))   # not a literal: one compiled variant
            out[i, j, 0] = x
            out[i, j, 1] = y
    return out


@njit_cached(parallel=True, **_jit)
def probe_corners(corner_xy, patches, spheres, laser, ambient, tex):
    """Material id and signed distance to the light plane (mm) seen at every pixel corner.

    ``corner_xy``: ``(H+1, W+1, 2)`` rays of the corners (corner (i, j) is at pixel
    position ``(j - 0.5, i - 0.5)``).  Returns ``(mat (H+1, W+1) int64, dist (H+1, W+1))``.
    """
    h1, w1 = corner_xy.shape[0], corner_xy.shape[1]
    mat = np.empty((h1, w1), dtype=np.int64)
    dst = np.empty((h1, w1))
    for i in nb.prange(h1):
        for j in range(w1):
            r, m, d = _shade(patches, spheres, laser, ambient, corner_xy[i, j, 0], corner_xy[i, j, 1], tex)
            mat[i, j] = m
            dst[i, j] = d
    return mat, dst


@njit_cached(**_jit)
def _pixel(u, v, fx, fy, cx, cy, skew, lens, x0, y0, patches, spheres, laser, ambient, S, salt, tex):
    """S x S stratified jittered samples over pixel (u, v): (mean radiance, mixed materials?)."""
    inv_s = 1.0 / S
    acc = 0.0
    mat0 = -2
    mix = False
    st = _pixel_state(u, v, salt + S)
    # Each sample's Newton starts from the centre's first-order prediction (the distortion's
    # inverse Jacobian at the centre's ray): two steps reach the same 1e-16 instead of three.
    xc, yc, j11, j12, j21, j22 = distort_jac_kernel(x0, y0, lens)
    det = j11 * j22 - j12 * j21
    i11, i12, i21, i22 = j22 / det, -j12 / det, -j21 / det, j11 / det
    for j in range(S):
        for i in range(S):
            st, ju = _next01(st)
            st, jv = _next01(st)
            yd = (v - 0.5 + (j + jv) * inv_s - cy) / fy
            xd = (u - 0.5 + (i + ju) * inv_s - cx - skew * yd) / fx
            ex = xd - xc
            ey = yd - yc
            x, y = _undistort(xd, yd, x0 + i11 * ex + i12 * ey, y0 + i21 * ex + i22 * ey, lens, np.int64(4))
            r, mat, d = _shade(patches, spheres, laser, ambient, x, y, tex)
            acc += r
            if mat0 == -2:
                mat0 = mat
            elif mat != mat0:
                mix = True
    return acc * inv_s * inv_s, mix


@njit_cached(parallel=True, **_jit)
def render_modes(fx, fy, cx, cy, skew, lens, centre_xy, patches, spheres, laser, ambient, mode, S, F, salt, tex):
    """Integrate every pixel by its mode: 0 uniform (one sample is the exact mean), 1 S x S
    samples (upgraded to F x F if they see several materials), 2 F x F samples."""
    height, width = mode.shape
    img = np.zeros((height, width))
    for vp in nb.prange(height):
        v = np.int64(vp)   # prange's index is unsigned in the parallel loop: one type for _pixel
        for u in range(width):
            x0 = centre_xy[v, u, 0]
            y0 = centre_xy[v, u, 1]
            md = mode[v, u]
            if md == 0:
                r, mat, d = _shade(patches, spheres, laser, ambient, x0, y0, tex)
                img[v, u] = r
                continue
            if md == 1:
                r, mix = _pixel(u, v, fx, fy, cx, cy, skew, lens, x0, y0, patches, spheres, laser, ambient,
                                S, salt, tex)
                if not mix:
                    img[v, u] = r
                    continue
            r, mix = _pixel(u, v, fx, fy, cx, cy, skew, lens, x0, y0, patches, spheres, laser, ambient,
                            F, salt, tex)
            img[v, u] = r
    return img


_RAY_MAPS: dict = {}


def _ray_maps(camera) -> tuple[np.ndarray, np.ndarray]:
    """Cached rays (normalised undistorted x, y) of the pixel centres ``(H, W, 2)`` and
    corners ``(H+1, W+1, 2)`` of a camera (the last two cameras used are kept, ~40 MB each at 1280x960)."""
    ensure_configured()  # OpenMP settings before the first parallel kernel
    key = (camera.K.tobytes(), camera.model, camera.dist.tobytes(), camera.width, camera.height)
    if key not in _RAY_MAPS:
        if len(_RAY_MAPS) >= 2:
            _RAY_MAPS.pop(next(iter(_RAY_MAPS)))
        args = (camera.fx, camera.fy, camera.cx, camera.cy, camera.skew, lens_params(camera.model, camera.dist))
        centre = undistort_grid(*args, camera.width, camera.height, 0.0)
        corner = undistort_grid(*args, camera.width + 1, camera.height + 1, -0.5)
        _RAY_MAPS[key] = (centre, corner)
    return _RAY_MAPS[key]


def render_radiance(camera, patches: np.ndarray, spheres: np.ndarray, laser: np.ndarray, ambient: float, *,
                    samples: int = 4, edge_samples: int = 16, salt: int = 0, return_modes: bool = False,
                    texels: np.ndarray | None = None):
    """Pixel-integrated radiance ``(H, W)`` float64 of a scene seen by ``camera`` (distorted).

    Every pixel is the mean over ``samples x samples`` stratified jittered sub-pixel
    samples (``S >= 4``), raised to ``edge_samples x edge_samples`` where the samples
    see more than one material (edges, shadow boundaries) or next to a pixel whose
    corners do.  A pixel whose 3x3 neighbourhood of corners all see the same material
    and no laser light has a constant radiance over its area: there one sample is the
    S x S mean exactly and is what is computed.  ``laser`` as made by
    :func:`make_laser` (power 0: laser off).  ``return_modes``: also return the
    per-pixel mode (0 uniform, 1 S x S, 2 F x F).  ``texels``: the pool of bitmap
    texels (uint8, 1 = ink) that ``bitmap`` patches index (see :func:`make_patch`).
    """
    ensure_configured()  # OpenMP settings before the first parallel kernel
    import cv2

    if int(samples) < 4:
        raise LightplaneError(f"samples must be >= 4 (4x4 per pixel), got {samples}")
    patches = np.ascontiguousarray(patches, dtype=np.float64).reshape(-1, PATCH_COLS)
    spheres = np.ascontiguousarray(spheres, dtype=np.float64).reshape(-1, SPHERE_COLS)
    laser = np.ascontiguousarray(laser, dtype=np.float64)
    lens = lens_params(camera.model, camera.dist)
    fx, fy, cx, cy, skew = camera.fx, camera.fy, camera.cx, camera.cy, camera.skew
    centre_xy, corner_xy = _ray_maps(camera)
    tex = np.zeros(1, np.uint8) if texels is None else np.ascontiguousarray(texels, dtype=np.uint8).ravel()
    for row in patches[patches[:, _TEX] == TEX_BITMAP]:
        if row[_TP0] < 0 or row[_TP0] + row[_NSX] * row[_NSY] > tex.size:
            raise LightplaneError(f"a bitmap patch indexes texels {row[_TP0]:.0f}..{row[_TP0] + row[_NSX] * row[_NSY]:.0f}"
                                  f" of a pool of {tex.size}")
    mat, dst = probe_corners(corner_xy, patches, spheres, laser, float(ambient), tex)
    # a pixel is on an edge when its four corners disagree
    edge = ((mat[:-1, :-1] != mat[:-1, 1:]) | (mat[:-1, :-1] != mat[1:, :-1]) | (mat[:-1, :-1] != mat[1:, 1:]))
    # near the sheet: a corner within 8 sigma of it, or corners on both sides of it
    s = max(laser[8], 1e-9)
    near = np.abs(dst) < 8.0 * s
    sgn = dst > 0
    lit = (near[:-1, :-1] | near[:-1, 1:] | near[1:, :-1] | near[1:, 1:]
           | (sgn[:-1, :-1] != sgn[:-1, 1:]) | (sgn[:-1, :-1] != sgn[1:, :-1]) | (sgn[:-1, :-1] != sgn[1:, 1:]))
    if laser[7] <= 0:
        lit[:] = False
    # edge pixels get F x F samples; their neighbours S x S, raised to F x F if their samples
    # see an edge after all (a curved edge clipping a pixel between its corners)
    kernel = np.ones((3, 3), np.uint8)
    edge8 = edge.astype(np.uint8)
    mode = np.maximum(cv2.dilate(np.maximum(lit.astype(np.uint8), edge8), kernel), 2 * edge8)
    mode = np.ascontiguousarray(mode.astype(np.uint8))
    img = render_modes(fx, fy, cx, cy, skew, lens, centre_xy, patches, spheres, laser, float(ambient), mode, int(samples),
                       int(max(edge_samples, samples)), int(salt), tex)
    return (img, mode) if return_modes else img
