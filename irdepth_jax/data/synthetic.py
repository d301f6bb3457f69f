"""Procedural LWIR street scenes with exact depth and segmentation labels.

`render_scene(seed, condition, height, width)` builds a random street (road with lanes and
markings, sidewalks, buildings on both sides with windows, a far backdrop that closes the view,
moving and parked cars, bicycles with or without riders, trees, lamp poles, sky) and renders it
by ray casting: every primitive is an axis-aligned box, an ellipsoid or a wheel ring, intersected
with all the rays of its projected bounding box at once (ray directions separate into a row
vector and a column vector, so each intersection is a few broadcast numpy operations).

Camera: pinhole at height ~1.5 m looking along +z, no pitch, focal length 0.9 * width, horizon at
row 0.45 * height. Depth is the z-depth (distance along the optical axis, KITTI/MS2 convention).

The LWIR frame is built in radiometric units: each pixel gets a temperature and an emissivity
from its material and the condition (day: sun-heated road and sun-facing walls, thermal shadows;
dusk: low sun, road keeps its heat; night: warm engines, tyres, lit windows and lamps), plus the
reflected sky (cold at the zenith, near air temperature at the horizon), mixed in radiance
(8-14 um band radiance from Planck's law), attenuated by the atmosphere with distance, then
turned into counts with a random global gain/offset, fixed-pattern noise (per-pixel gain and
offset, column and row offsets: one pattern per image size, like a single camera), radial
vignetting and narcissus, temporal noise (NETD ~50 mK) and 14-bit quantisation.

Sky holds depth 0 in both `depth` (dense) and `depth_lidar` (0 = invalid, as in the folder
format); `seg == 0` marks it. Every other pixel has a dense depth < 232 m (the far backdrop
closes the view).
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np

from irdepth_jax.config import CLASS_NAMES, IGNORE_LABEL
from irdepth_jax.imaging.raw import RAW_MAX
from irdepth_jax.imaging.tonemap import camera_like

CONDITIONS: tuple[str, ...] = ("day", "dusk", "night")
"""Lighting conditions `render_scene` accepts."""

LIDAR_MAX_RANGE = 80.0
"""Range limit (metres, Euclidean) of the simulated LiDAR."""

_SEG = {name: i for i, name in enumerate(CLASS_NAMES)}

# Object kinds (material logic). Index 0 is the sky, 1 the ground plane.
(SKY, GROUND, BUILDING, CAR_BODY, CAR_CABIN, TYRE, BIKE, RIDER, TRUNK, CROWN, POLE, LAMP,
 FAR_BUILDING, FAR_TREES) = range(14)
ROAD, WALK, GRASS = 14, 15, 16  # ground materials (the ground plane is one object)
N_MATERIALS = 17

_KIND_SEG = np.full(14, IGNORE_LABEL, np.uint8)
for _kinds, _name in (((SKY,), "sky"), ((BUILDING, FAR_BUILDING), "building"),
                     ((CAR_BODY, CAR_CABIN, TYRE), "car"), ((BIKE,), "bicycle"),
                     ((TRUNK, CROWN, FAR_TREES), "tree")):
    _KIND_SEG[list(_kinds)] = _SEG[_name]

# Normal codes of the face a ray hits: 0 = +-x, 1 = +-y, 2 = z (always -z: rays go to +z).
_NX, _NY, _NZ = 0, 1, 2

_NEAR = 0.05  # near clipping plane (m)


@functools.lru_cache(maxsize=1)
def _band_table() -> tuple[np.ndarray, np.ndarray]:
    """8-14 um band radiance as 'equivalent kelvin around 20 C': affine in radiance.

    Returns (T, X): X(T) = (L(T) - L(293.15)) / dL/dT(293.15), so mixing X values with weights
    that sum to one is mixing radiances.
    """
    h, c, k = 6.62607015e-34, 2.99792458e8, 1.380649e-23
    lam = np.linspace(8e-6, 14e-6, 241)[:, None]
    temps = np.linspace(150.0, 500.0, 701)
    rad = (2 * h * c**2 / lam**5 / np.expm1(h * c / (lam * k * temps[None]))).sum(0)
    ref = np.interp(293.15, temps, rad)
    slope = np.interp(293.15, temps, np.gradient(rad, temps))
    return temps.astype(np.float32), ((rad - ref) / slope).astype(np.float32)


def _band(temp_k):
    temps, x = _band_table()
    return np.interp(temp_k, temps, x).astype(np.float32)


@functools.lru_cache(maxsize=8)
def _fixed_pattern(height: int, width: int):
    """Per-camera fixed-pattern noise: (gain (H,W), offset (H,W)) in relative gain / counts."""
    rng = np.random.default_rng(0x1A2B)
    gain = 1.0 + 0.02 * rng.standard_normal((height, width))
    offset = (8.0 * rng.standard_normal((height, width)) + 6.0 * rng.standard_normal((1, width))
              + 3.0 * rng.standard_normal((height, 1)))
    yy, xx = np.mgrid[0:height, 0:width]
    r2 = ((yy - height / 2) / (height / 2)) ** 2 * 0.5 + ((xx - width / 2) / (width / 2)) ** 2 * 0.5
    return gain.astype(np.float32), offset.astype(np.float32), r2.astype(np.float32)


@functools.lru_cache(maxsize=1)
def _noise_tile() -> np.ndarray:
    """(256, 256) float32 smooth texture in [-1, 1] for asphalt / facades (tiled)."""
    rng = np.random.default_rng(0x5EED)
    fine = rng.standard_normal((256, 256)).astype(np.float32)
    freq = np.fft.fftfreq(256)
    blur = np.exp(-2 * (np.pi * 6) ** 2 * (freq[:, None] ** 2 + freq[None, :] ** 2))
    coarse = np.fft.ifft2(np.fft.fft2(fine) * blur).real.astype(np.float32)  # periodic blur
    tile = 0.6 * fine + 0.4 * coarse / coarse.std()
    return np.clip(tile / 2.5, -1, 1)


class _Scene:
    """Primitives (boxes, ellipsoids, rings) and a per-object property table."""

    def __init__(self):
        self.boxes, self.ellipsoids, self.rings = [], [], []
        self.kind, self.toff, self.color, self.bounds, self.params = [], [], [], [], []
        self.add_object(SKY, color=(0, 0, 0))
        self.add_object(GROUND, color=(0, 0, 0))

    def add_object(self, kind, toff=0.0, color=(0.5, 0.5, 0.5), bounds=(0,) * 6, params=(0, 0, 0)):
        self.kind.append(kind)
        self.toff.append(toff)
        self.color.append(color)
        self.bounds.append(bounds)
        self.params.append(params)
        return len(self.kind) - 1

    def box(self, kind, x0, x1, y0, y1, z0, z1, **kw):
        oid = self.add_object(kind, bounds=(x0, x1, y0, y1, z0, z1), **kw)
        self.boxes.append((x0, x1, y0, y1, z0, z1, oid))
        return oid

    def table(self):
        return dict(kind=np.array(self.kind, np.int32), toff=np.array(self.toff, np.float32),
                    color=np.array(self.color, np.float32),
                    bounds=np.array(self.bounds, np.float32),
                    params=np.array(self.params, np.float32))


def _sample_scene(rng: np.random.Generator):
    """Random street layout -> (_Scene, layout dict)."""
    s = _Scene()
    lane = rng.uniform(3.0, 3.6)
    n_right, n_left = rng.integers(1, 3), rng.integers(1, 3)
    k = rng.integers(0, n_right)
    centre = -(k + 0.5) * lane
    park_l, park_r = (2.3 if rng.random() < 0.75 else 0.0 for _ in range(2))  # parking strips
    lanes_l = centre - n_left * lane
    road_l, road_r = lanes_l - park_l, centre + n_right * lane + park_r
    walk_l, walk_r = rng.uniform(2.0, 4.5, 2)
    z_far = rng.uniform(110.0, 200.0)
    lay = dict(lane=lane, centre=centre, road_l=road_l, road_r=road_r, lanes_l=lanes_l,
               n_lanes=n_left + n_right,
               side_l=road_l - walk_l, side_r=road_r + walk_r, z_far=z_far, lamps=[])

    # buildings, both sides
    for side in (-1, 1):
        edge = lay["side_l"] if side < 0 else lay["side_r"]
        z = rng.uniform(-15.0, 0.0)
        while z < z_far - 10:
            length = rng.uniform(8.0, 30.0)
            if rng.random() < 0.85:
                setback = rng.uniform(0.0, 4.0) if rng.random() < 0.5 else 0.0
                depth = rng.uniform(8.0, 20.0)
                x_in = edge + side * setback
                x0, x1 = sorted((x_in, x_in + side * depth))
                shade = rng.uniform(0.25, 0.8)
                tint = rng.uniform(0.85, 1.15, 3) * shade
                s.box(BUILDING, x0, x1, 0.0, rng.uniform(4.0, 28.0), z, z + length,
                      toff=rng.normal(0, 1.0), color=tuple(np.clip(tint, 0, 1)),
                      params=(rng.uniform(2.4, 4.0), rng.uniform(2.9, 3.6), rng.integers(0, 1000)))
            z += length + (rng.uniform(0.0, 8.0) if rng.random() < 0.5 else 0.0)

    # far backdrop closing the street: a contiguous row of buildings or a tree line
    far_kind = FAR_TREES if rng.random() < 0.3 else FAR_BUILDING
    x = -320.0
    while x < 320.0:
        w = rng.uniform(8.0, 35.0)
        hgt = rng.uniform(6.0, 14.0) if far_kind == FAR_TREES else rng.uniform(5.0, 45.0)
        col = (0.2, 0.3, 0.15) if far_kind == FAR_TREES else tuple(rng.uniform(0.3, 0.7, 3))
        zz = z_far + rng.uniform(0.0, 15.0)
        s.box(far_kind, x, x + w, 0.0, hgt, zz, zz + 15.0, toff=rng.normal(0, 1.0), color=col,
              params=(rng.uniform(2.4, 4.0), rng.uniform(2.9, 3.6), rng.integers(0, 1000)))
        x += w

    # cars: traffic in every lane (ours: going away; opposite: facing us), parked at both curbs
    def car(xc, zc, facing, running, min_z):
        if zc < min_z:
            return
        length, width = rng.uniform(3.8, 4.9), rng.uniform(1.65, 1.9)
        van = rng.random() < 0.15
        h_body = rng.uniform(1.6, 2.1) if van else rng.uniform(0.95, 1.15)
        col = tuple(rng.uniform(0.05, 0.95) * rng.uniform(0.8, 1.2, 3).clip(0, 1 / 0.95))
        # K above air: running engines; parked cars are either still warm or cooled down
        if running:
            engine = rng.uniform(8.0, 14.0)
        else:
            engine = rng.uniform(4.0, 8.0) if rng.random() < 0.6 else -1.0
        z0, z1 = zc - length / 2, zc + length / 2
        x0, x1 = xc - width / 2, xc + width / 2
        params = (facing, float(running), 0)
        s.box(CAR_BODY, x0, x1, 0.32, h_body, z0, z1, toff=engine, color=col, params=params)
        if not van:
            cz0, cz1 = (z0 + 0.9, z1 - 1.3) if facing < 0 else (z0 + 1.3, z1 - 0.9)
            s.box(CAR_CABIN, x0 + 0.1, x1 - 0.1, h_body, h_body + rng.uniform(0.4, 0.55), cz0, cz1,
                  toff=engine * 0.5, color=col, params=params)
        for wz in (z0 + 0.55, z1 - 0.95):
            for wx in (x0 - 0.02, x1 - 0.23):
                s.box(TYRE, wx, wx + 0.25, 0.0, 0.62, wz, wz + 0.62,
                      toff=engine * 1.5 if running else 0.0, color=(0.05, 0.05, 0.05))

    for i in range(n_left + n_right):
        xc = lanes_l + (i + 0.5) * lane
        ours = xc > centre
        z = rng.uniform(4.0, 25.0) + (6.0 if abs(xc) < 1.0 else 0.0)
        while z < 110:
            car(xc + rng.normal(0, 0.2), z, -1 if ours else 1, True,
                min_z=8.0 if abs(xc) < 1.0 else 3.0)
            z += rng.uniform(8.0, 45.0)
    for side, strip in ((-1, park_l), (1, park_r)):
        curb = road_l if side < 0 else road_r
        z = rng.uniform(-2.0, 8.0)
        while strip > 0 and z < 90 and rng.random() < 0.85:
            car(curb - side * 1.1, z, rng.choice((-1, 1)), rng.random() < 0.15, min_z=1.0)
            z += rng.uniform(5.2, 14.0)

    # trees and lamp poles on the sidewalks
    for side in (-1, 1):
        # trees at 35 % of the sidewalk's width from the kerb
        x = (road_l - 0.35 * walk_l) if side < 0 else (road_r + 0.35 * walk_r)
        z = rng.uniform(2.0, 12.0)
        tree_gap = rng.uniform(7.0, 16.0)
        while z < z_far - 10 and rng.random() < 0.9:
            r = rng.uniform(0.12, 0.25)
            trunk_h = rng.uniform(1.8, 3.0)
            s.box(TRUNK, x - r, x + r, 0.0, trunk_h + 0.5, z - r, z + r, toff=rng.normal(0, 0.5),
                  color=(0.25, 0.18, 0.12))
            rx, ry = rng.uniform(1.3, 2.8), rng.uniform(1.6, 3.5)
            oid = s.add_object(CROWN, toff=rng.normal(0, 0.5),
                               color=tuple(np.array((0.18, 0.35, 0.12)) * rng.uniform(0.6, 1.3)))
            s.ellipsoids.append((x, trunk_h + ry * 0.9, z, rx, ry, rx, oid))
            z += tree_gap * rng.uniform(0.7, 1.4)
        zp = rng.uniform(5.0, 20.0)
        xp = x + side * 0.5
        while zp < 100:
            top = rng.uniform(6.0, 8.0)
            s.box(POLE, xp - 0.08, xp + 0.08, 0.0, top, zp - 0.08, zp + 0.08,
                  color=(0.4, 0.4, 0.42))
            arm0, arm1 = sorted((xp, xp - side * 1.6))
            s.box(LAMP, arm0, arm1, top - 0.25, top, zp - 0.2, zp + 0.2, color=(0.8, 0.8, 0.7))
            lay["lamps"].append((xp - side * 1.4, top - 0.3, zp))
            zp += rng.uniform(25.0, 40.0)

    # bicycles: riding (wheels in x = const planes, seen from behind) or parked side-on
    for _ in range(rng.integers(1, 6)):
        if rng.random() < 0.6:  # riding: at the kerb side of the right lane, or on a sidewalk
            where = rng.integers(0, 3)
            xc = (centre + n_right * lane - 0.45, road_l - 0.7 * walk_l,
                  road_r + 0.7 * walk_r)[where]
            _bicycle(s, rng, xc, rng.uniform(4.0, 35.0), along=True, rider=rng.random() < 0.7)
        else:  # a rack of 1-4 parked bikes
            side = rng.choice((-1, 1))
            xc = (lay["side_l"] + 1.2) if side < 0 else (lay["side_r"] - 1.2)
            z0 = rng.uniform(4.0, 30.0)
            for k in range(rng.integers(1, 5)):
                _bicycle(s, rng, xc, z0 + 0.7 * k, along=False, rider=False)
    # plain Python floats: the caster does scalar arithmetic on them (numpy scalars are slow)
    s.boxes, s.ellipsoids, s.rings = ([tuple(map(float, p[:-1])) + (int(p[-1]),) for p in prims]
                                      for prims in (s.boxes, s.ellipsoids, s.rings))
    return s, lay


def _bicycle(s: _Scene, rng, xc, zc, along, rider):
    """Two wheel rings and a frame of thin boxes; `along`: the bike points along z."""
    wr, half = 0.34, 0.55
    col = tuple(rng.uniform(0.1, 0.9, 3))
    oid = s.add_object(BIKE, toff=0.0, color=col)
    for d in (-half, half):
        if along:
            s.rings.append((0, xc, zc + d, wr, wr, wr - 0.1, oid))
        else:
            s.rings.append((2, zc, xc + d, wr, wr, wr - 0.1, oid))
    t = 0.05
    if along:
        s.boxes += [(xc - t, xc + t, wr + 0.2, wr + 0.26, zc - half, zc + half, oid),
                    (xc - t, xc + t, wr - 0.05, wr + 0.5, zc - 0.2 - t, zc - 0.2 + t, oid),
                    (xc - 0.3, xc + 0.3, wr + 0.55, wr + 0.6, zc + half - t, zc + half + t, oid),
                    (xc - t, xc + t, 0.0, wr + 0.6, zc + half - t, zc + half + t, oid)]
    else:
        s.boxes += [(xc - half, xc + half, wr + 0.2, wr + 0.26, zc - t, zc + t, oid),
                    (xc - 0.2 - t, xc - 0.2 + t, wr - 0.05, wr + 0.5, zc - t, zc + t, oid),
                    (xc + half - t, xc + half + t, 0.0, wr + 0.6, zc - 0.3, zc + 0.3, oid)]
    if rider:
        rid = s.add_object(RIDER, color=tuple(rng.uniform(0.1, 0.6, 3)))
        s.boxes += [(xc - 0.2, xc + 0.2, 0.3, 0.95, zc - 0.3, zc - 0.1, rid),
                    (xc - 0.22, xc + 0.22, 0.95, 1.6, zc - 0.3, zc + 0.05, rid)]
        s.ellipsoids.append((xc, 1.75, zc - 0.1, 0.11, 0.13, 0.11, rid))


def _window(lo, hi, size):
    """Clip [lo, hi) to [0, size) -> (lo, hi) ints."""
    return max(0, min(size, math.floor(lo))), max(0, min(size, math.ceil(hi) + 1))


class _Caster:
    """Z-buffer ray caster over an (H, W) image; rays separate into rows (dy) and columns (dx)."""

    def __init__(self, height, width, cam_h):
        self.h, self.w, self.oy = height, width, cam_h
        self.f = 0.9 * width
        self.cx, self.cy = width / 2.0, 0.45 * height
        dx = (np.arange(width, dtype=np.float32) + 0.5 - self.cx) / self.f
        dy = -(np.arange(height, dtype=np.float32) + 0.5 - self.cy) / self.f
        self.dx = np.where(np.abs(dx) < 1e-6, 1e-6, dx)[None, :]
        self.dy = np.where(np.abs(dy) < 1e-6, -1e-6, dy)[:, None]
        ground_t = np.where(self.dy < 0, cam_h / np.maximum(-self.dy, 1e-9), np.inf)
        self.t = np.broadcast_to(ground_t, (height, width)).astype(np.float32)
        self.obj = np.where(np.isfinite(self.t), GROUND, SKY).astype(np.int32)
        self.nrm = np.full((height, width), _NY, np.int8)

    def _bbox(self, x0, x1, y0, y1, z0, z1):
        """Pixel window (v0, v1, u0, u1) covering the projection of a box, or None if empty.

        The projection of x / z is extreme at the box's corners, so 4 values per axis suffice
        (plain Python floats: this runs once per primitive and numpy's overhead would dominate).
        """
        z0, z1 = max(z0, _NEAR), max(z1, _NEAR)
        us = [self.cx + self.f * x / z for x in (x0, x1) for z in (z0, z1)]
        vs = [self.cy - self.f * (y - self.oy) / z for y in (y0, y1) for z in (z0, z1)]
        v0, v1 = _window(min(vs) - 0.5, max(vs) - 0.5, self.h)
        u0, u1 = _window(min(us) - 0.5, max(us) - 0.5, self.w)
        return None if v0 >= v1 or u0 >= u1 else (v0, v1, u0, u1)

    def _commit(self, win, t_hit, oid, nrm):
        v0, v1, u0, u1 = win
        cur = self.t[v0:v1, u0:u1]
        hit = t_hit < cur
        np.copyto(cur, t_hit, where=hit)
        np.copyto(self.obj[v0:v1, u0:u1], oid, where=hit)
        np.copyto(self.nrm[v0:v1, u0:u1], nrm, where=hit)

    def box(self, x0, x1, y0, y1, z0, z1, oid):
        if z1 <= _NEAR:
            return
        win = self._bbox(x0, x1, y0, y1, z0, z1)
        if win is None:
            return
        v0, v1, u0, u1 = win
        if self.t[v0:v1, u0:u1].max() < z0:  # hidden behind what is drawn already
            return
        dx, dy = self.dx[:, u0:u1], self.dy[v0:v1]
        ax, bx = x0 / dx, x1 / dx
        ay, by = (y0 - self.oy) / dy, (y1 - self.oy) / dy
        tx_n, tx_f = np.minimum(ax, bx), np.maximum(ax, bx)
        ty_n, ty_f = np.minimum(ay, by), np.maximum(ay, by)
        t_near = np.maximum(np.maximum(tx_n, ty_n), z0)
        t_far = np.minimum(np.minimum(tx_f, ty_f), z1)
        ok = (t_near <= t_far) & (t_near > _NEAR)
        t_hit = np.where(ok, t_near, np.inf).astype(np.float32)
        nrm = np.where(tx_n >= ty_n, np.where(tx_n >= z0, _NX, _NZ),
                       np.where(ty_n >= z0, _NY, _NZ)).astype(np.int8)
        self._commit(win, t_hit, oid, nrm)

    def ellipsoid(self, cx, cy, cz, rx, ry, rz, oid):
        if cz + rz <= _NEAR:
            return
        win = self._bbox(cx - rx, cx + rx, cy - ry, cy + ry, cz - rz, cz + rz)
        if win is None:
            return
        v0, v1, u0, u1 = win
        dx, dy = self.dx[:, u0:u1] / rx, self.dy[v0:v1] / ry
        dz = 1.0 / rz
        ox, oy, oz = -cx / rx, (self.oy - cy) / ry, -cz / rz
        a = dx * dx + dy * dy + dz * dz
        b = dx * ox + dy * oy + dz * oz
        c = ox * ox + oy * oy + oz * oz - 1.0
        disc = b * b - a * c
        t_hit = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / a, np.inf)
        t_hit = np.where(t_hit > _NEAR, t_hit, np.inf).astype(np.float32)
        self._commit(win, t_hit, oid, np.int8(_NZ))

    def ring(self, axis, plane, ca, cy, r_out, r_in, oid):
        """Wheel: annulus centred at height cy in the plane x = plane (axis 0, centre z = ca)
        or z = plane (axis 2, centre x = ca)."""
        if axis == 0:
            box = (plane, plane, cy - r_out, cy + r_out, ca - r_out, ca + r_out)
        else:
            box = (ca - r_out, ca + r_out, cy - r_out, cy + r_out, plane, plane)
        if box[5] <= _NEAR:
            return
        win = self._bbox(*box)
        if win is None:
            return
        v0, v1, u0, u1 = win
        dx, dy = self.dx[:, u0:u1], self.dy[v0:v1]
        if axis == 0:
            t = plane / dx
            a = t - ca
        else:
            t = np.full_like(dx, plane)
            a = t * dx - ca
        y = self.oy + t * dy - cy
        r2 = a * a + y * y
        ok = (r2 <= r_out**2) & (r2 >= r_in**2) & (t > _NEAR)
        self._commit(win, np.where(ok, t, np.inf).astype(np.float32), oid,
                     np.int8(_NX if axis == 0 else _NZ))


_COND = {
    # t_air (C) and sun_el (deg) ranges; sky_dt: clear-sky zenith depression (K) range;
    # road_sun / wall_sun / car_sun: K above air at full sun; road_base: K the road keeps;
    # crown: foliage K above air; ambient / sun / sun_rgb: visible lighting; exposure: target
    # of the auto exposure (None: fixed night exposure); rgb_noise: visible sensor noise
    "day": dict(t_air=(18.0, 32.0), sun_el=(30.0, 65.0), sky_dt=(30.0, 50.0), road_sun=18.0,
                wall_sun=10.0, road_base=4.0, crown=1.5, car_sun=12.0, ambient=0.35, sun=1.0,
                sun_rgb=(1.0, 0.97, 0.9), exposure=0.85, rgb_noise=0.004),
    "dusk": dict(t_air=(10.0, 22.0), sun_el=(2.0, 10.0), sky_dt=(25.0, 45.0), road_sun=4.0,
                 wall_sun=5.0, road_base=7.0, crown=0.0, car_sun=3.0, ambient=0.12, sun=0.55,
                 sun_rgb=(1.0, 0.6, 0.3), exposure=0.75, rgb_noise=0.004),
    "night": dict(t_air=(0.0, 15.0), sun_el=None, sky_dt=(25.0, 45.0), road_sun=0.0,
                  wall_sun=0.0, road_base=3.0, crown=-1.5, car_sun=0.0, ambient=0.003, sun=0.0,
                  sun_rgb=(0, 0, 0), exposure=None, rgb_noise=0.003),
}


_GROUND_RGB = np.float32([[0.22] * 3, [0.45] * 3, [0.3, 0.33, 0.2], [0.85] * 3, [0.08] * 3])
"""Albedo of road, sidewalk, grass (in ROAD, WALK, GRASS order), lane paint, car glass."""

_GAMMA_LEVELS = 16384


@functools.lru_cache(maxsize=1)
def _gamma_lut() -> np.ndarray:
    """sRGB-like 1/2.2 gamma from linear [0, 1] quantised to _GAMMA_LEVELS, as uint8."""
    return (np.linspace(0, 1, _GAMMA_LEVELS) ** (1 / 2.2) * 255 + 0.5).astype(np.uint8)


@functools.lru_cache(maxsize=len(CONDITIONS))
def _material_tables(condition: str) -> dict:
    """Per-material arrays (indexed by kind, or ROAD / WALK / GRASS on the ground):
    base (K above air), sun (K at full sun), tex (K per unit texture), eps (emissivity),
    tex_rgb (relative albedo texture)."""
    p = _COND[condition]
    base, sun, tex = (np.zeros(N_MATERIALS, np.float32) for _ in range(3))
    eps = np.full(N_MATERIALS, 0.95, np.float32)
    tex_rgb = np.full(N_MATERIALS, 0.12, np.float32)
    base[[ROAD, WALK, GRASS]] = p["road_base"], 0.7 * p["road_base"], -1.0
    base[[BUILDING, FAR_BUILDING]] = 1.5
    base[[CROWN, FAR_TREES]] = p["crown"]
    base[LAMP] = 25.0 if condition == "night" else 0.0  # lit lamp heads
    sun[[ROAD, WALK, GRASS]] = p["road_sun"], 0.6 * p["road_sun"], 0.3 * p["road_sun"]
    sun[[BUILDING, FAR_BUILDING, LAMP]] = p["wall_sun"]
    sun[[POLE, BIKE]] = 0.5 * p["wall_sun"]
    sun[[CAR_BODY, CAR_CABIN, TYRE]] = p["car_sun"]
    tex[ROAD], tex[[BUILDING, FAR_BUILDING]], tex[[CROWN, FAR_TREES]] = 0.8, 0.3, 0.5
    eps[[ROAD, WALK]], eps[[CROWN, FAR_TREES]], eps[[POLE, LAMP, BIKE]] = 0.96, 0.98, 0.5
    tex_rgb[[ROAD, WALK, GRASS]] = 0.23, 0.11, 0.2
    return dict(base=base, sun=sun, tex=tex, eps=eps, tex_rgb=tex_rgb)


def _shadow_map(scene: _Scene, sun_dir, extent):
    """Top-down (z, x) uint8 map at 0.25 m, 1 where the ground is in a cast shadow."""
    (x_lo, x_hi), z_hi = extent, 260.0
    res = 0.25
    grid = np.zeros((int(z_hi / res), int((x_hi - x_lo) / res)), np.uint8)
    sx, sy, sz = sun_dir
    shift = np.array([-sx / sy, -sz / sy])  # ground displacement per metre of height

    def fill(points):  # (N, P, 3) x, y, z points whose convex hulls are the objects
        ground = points[..., [0, 2]] + points[..., 1:2] * shift
        pix = (ground - (x_lo, 0.0)) / res
        pix = np.ascontiguousarray(np.clip(pix, -1e4, 1e4), dtype=np.int32)
        for poly in pix:
            cv2.fillConvexPoly(grid, cv2.convexHull(poly), 1)

    if scene.boxes:
        b = np.array(scene.boxes)[:, :6]
        corners = b[:, [[i, j, k] for i in (0, 1) for j in (2, 3) for k in (4, 5)]]
        fill(corners)
    if scene.ellipsoids:
        e = np.array(scene.ellipsoids)[:, :6]
        fill(_unit_sphere()[None] * e[:, None, 3:6] + e[:, None, 0:3])
    return grid, x_lo, res


@functools.lru_cache(maxsize=1)
def _unit_sphere(n: int = 40) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi, theta = np.arccos(1 - 2 * i / n), np.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(theta) * np.sin(phi), np.cos(phi), np.sin(theta) * np.sin(phi)], 1)


def render_scene(seed: int, condition: str = "day", height: int = 256, width: int = 320) -> dict:
    """Renders one random street scene.

    Args:
      seed: any int; the same (seed, condition, height, width) gives identical arrays.
      condition: 'day', 'dusk' or 'night'.
      height, width: image size in pixels (>= 8 each).

    Returns:
      dict with
        raw14 (H, W) uint16: LWIR counts in 0..16383;
        ir8 (H, W) uint8: `irdepth_jax.imaging.tonemap.camera_like(raw14)`;
        rgb (H, W, 3) uint8: aligned visible image (dark and noisy at night);
        depth (H, W) float32: dense z-depth in metres, 0 on sky;
        depth_lidar (H, W) float32: sparse LiDAR-like z-depth (scan lines, <= 80 m range,
          no sky returns), 0 where there is no return;
        valid (H, W) bool: depth_lidar > 0;
        seg (H, W) uint8: labels in CLASS_NAMES order, 255 unlabelled (sidewalk, grass,
          poles, lamps, riders);
        condition str.
    """
    if condition not in CONDITIONS:
        raise ValueError(f"condition must be one of {CONDITIONS}, got {condition!r}")
    if height < 8 or width < 8:
        raise ValueError(f"height and width must be >= 8, got {height}x{width}")
    rng = np.random.default_rng(seed)
    scene, lay = _sample_scene(rng)
    cam_h = rng.uniform(1.4, 1.6)
    cast = _Caster(height, width, cam_h)
    for b in sorted(scene.boxes, key=lambda b: b[4]):  # near to far: hidden boxes are skipped
        cast.box(*b)
    for e in scene.ellipsoids:
        cast.ellipsoid(*e)
    for r in scene.rings:
        cast.ring(*r)

    tab = scene.table()
    obj, t, nrm = cast.obj, cast.t, cast.nrm
    kind = tab["kind"][obj]
    sky = kind == SKY
    depth = np.where(sky, 0.0, t).astype(np.float32)
    x_w = np.where(sky, 0.0, t * cast.dx)
    y_w = np.where(sky, 0.0, cam_h + t * cast.dy)
    z_w = np.where(sky, 0.0, t)
    rng_m = depth * np.sqrt(cast.dx**2 + cast.dy**2 + 1.0)

    p = _COND[condition]
    t_air = rng.uniform(*p["t_air"]) + 273.15
    if p["sun_el"] is None:
        sun_dir = None
    else:
        el, az = np.deg2rad(rng.uniform(*p["sun_el"])), rng.uniform(-np.pi, np.pi)
        sun_dir = np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])

    # sun: Lambert term of each face (normal codes: x faces look back along -dx, y faces up
    # when the ray goes down, z faces toward the camera; crowns get a fixed up-and-back normal)
    kind_flat = kind.ravel()
    crown = kind == CROWN
    up = ((nrm == _NY) & (cast.dy < 0)) | crown
    if sun_dir is not None:
        sx, sy, sz = (float(v) for v in sun_dir)
        cos = np.where(nrm == _NX, -np.sign(cast.dx) * sx,
                       np.where(nrm == _NY, -np.sign(cast.dy) * sy, -sz))
        cos = np.where(crown, 0.7 * sy - 0.7 * sz, cos)
        grid, x_lo, res = _shadow_map(scene, sun_dir, (lay["side_l"] - 40, lay["side_r"] + 40))
        iz = np.clip((z_w / res).astype(np.int32), 0, grid.shape[0] - 1)
        ix = np.clip(((x_w - x_lo) / res).astype(np.int32), 0, grid.shape[1] - 1)
        shadow = (grid[iz, ix] > 0) & (kind == GROUND)
        lambert = (np.clip(cos, 0, 1) * ~shadow).astype(np.float32)
    else:
        lambert = np.zeros((height, width), np.float32)

    # ground materials and markings
    ground = kind == GROUND
    road = ground & (x_w >= lay["road_l"]) & (x_w <= lay["road_r"])
    walk = ground & ~road & (x_w >= lay["side_l"]) & (x_w <= lay["side_r"])
    lane_x = (x_w - lay["lanes_l"]) / lay["lane"]
    near_line = np.abs(lane_x - np.round(lane_x)) * lay["lane"] < 0.08
    edge_line = (np.round(lane_x) <= 0) | (np.round(lane_x) >= lay["n_lanes"])
    dashed = np.mod(z_w, 9.0) < 3.0
    centre_line = np.abs(x_w - lay["centre"]) < 0.12
    marking = road & ((near_line & (edge_line | dashed)) | centre_line)
    mat = np.where(ground, np.where(road, ROAD, np.where(walk, WALK, GRASS)), kind)
    tile = _noise_tile()
    tex = tile[(z_w * 8).astype(np.int32) & 255, (x_w * 8).astype(np.int32) & 255]

    # facade windows (a hash of floor, column and building decides which are lit at night)
    window, lit = np.zeros(height * width, bool), np.zeros(height * width, bool)
    facade = (kind_flat == BUILDING) | (kind_flat == FAR_BUILDING)
    bi = np.flatnonzero(facade & (nrm.ravel() != _NY))
    prm = tab["params"][obj.ravel()[bi]]
    horiz = np.where(nrm.ravel()[bi] == _NX, z_w.ravel()[bi], x_w.ravel()[bi])
    yb = y_w.ravel()[bi]
    wi, wf = np.divmod(horiz / prm[:, 0], 1.0)
    fi, ff = np.divmod((yb - 1.0) / prm[:, 1], 1.0)
    win = (wf > 0.25) & (wf < 0.75) & (ff > 0.3) & (ff < 0.85) & (yb > 1.0)
    code = (wi.astype(np.int64) * 73856093) ^ (fi.astype(np.int64) * 19349663) ^ (
        prm[:, 2].astype(np.int64) * 83492791)
    window[bi], lit[bi] = win, win & (code % 100 < 35)
    window, lit = window.reshape(height, width), lit.reshape(height, width)

    # car faces: rear lights / headlights, the warm front of cars facing us, exhausts
    tail, head, engine, exhaust = (np.zeros(height * width, bool) for _ in range(4))
    ci = np.flatnonzero((kind_flat == CAR_BODY) & (nrm.ravel() == _NZ))
    cb, cp = tab["bounds"][obj.ravel()[ci]], tab["params"][obj.ravel()[ci]]
    rel_y = (y_w.ravel()[ci] - cb[:, 2]) / (cb[:, 3] - cb[:, 2])
    rel_x = (x_w.ravel()[ci] - cb[:, 0]) / (cb[:, 1] - cb[:, 0])
    lamps = (rel_y > 0.55) & (rel_y < 0.85) & ((rel_x < 0.2) | (rel_x > 0.8))
    facing_us, running = cp[:, 0] > 0, cp[:, 1] > 0
    tail[ci], head[ci] = lamps & ~facing_us, lamps & facing_us
    engine[ci] = facing_us & running
    exhaust[ci] = ~facing_us & running & (rel_y < 0.25) & (rel_x > 0.15) & (rel_x < 0.3)
    tail, head, engine, exhaust = (a.reshape(height, width) for a in (tail, head, engine, exhaust))
    glass = (kind == CAR_CABIN) & (nrm != _NY)

    # ---- thermal: temperature (K) and emissivity per pixel, radiance, sensor
    m = _material_tables(condition)
    sunlit = np.where(glass, 0.0, lambert)
    temp = (t_air + m["base"][mat] + m["sun"][mat] * sunlit + m["tex"][mat] * tex + tab["toff"][obj]
            + 12.0 * engine + 35.0 * exhaust + (7.0 * lit if condition != "day" else 0.0))
    temp[kind == RIDER] = 303.0 - 3.0 * (condition == "night")  # clothed people
    eps = m["eps"][mat]
    eps = np.where(marking, 0.9, np.where(window | glass, 0.84, eps))

    elev = np.arctan2(cast.dy, np.sqrt(1 + cast.dx**2))  # (H, W) elevation of each ray
    sky_dt = rng.uniform(*p["sky_dt"])
    t_sky = t_air - sky_dt * (1 - np.exp(-np.maximum(elev, 0) / 0.15))
    # reflections: horizontal faces see the zenith, vertical ones the horizon and the street
    x_refl = np.where(nrm == _NY, _band(t_air - sky_dt), _band(t_air - 0.2 * sky_dt))
    x_obj = eps * _band(temp) + (1 - eps) * x_refl
    tau = np.exp(-rng_m / rng.uniform(300.0, 1500.0))
    signal = np.where(sky, _band(t_sky), tau * x_obj + (1 - tau) * _band(t_air))

    fp_gain, fp_off, r2 = _fixed_pattern(height, width)
    resp = rng.uniform(34.0, 46.0)  # counts per kelvin near 20 C
    level = rng.uniform(6800.0, 8200.0)
    fpn = rng.uniform(0.7, 1.3)
    counts = (level + resp * signal * (1 + fpn * (fp_gain - 1)) * (1 - 0.08 * r2)
              + fpn * fp_off + rng.uniform(-150.0, 50.0) * r2
              + resp * 0.05 * rng.standard_normal((height, width), dtype=np.float32))
    raw14 = np.clip(np.rint(counts), 0, RAW_MAX).astype(np.uint16)

    # ---- visible image: albedo x (ambient + sun) + lights, auto exposure, noise, gamma
    n_obj = len(tab["color"])
    colours = np.concatenate([tab["color"], _GROUND_RGB])
    alb_idx = np.where(ground, n_obj + mat - ROAD, obj)
    alb_idx = np.where(marking, n_obj + 3, np.where(glass, n_obj + 4, alb_idx))
    fac = 1 + m["tex_rgb"][mat] * tex * ~marking
    fac = np.where(window, 0.35 * fac, fac)
    albedo = colours[alb_idx] * fac[..., None]
    light = ((p["ambient"] * (0.6 + 0.4 * up))[..., None]
             + p["sun"] * lambert[..., None] * np.float32(p["sun_rgb"]))
    img = albedo * light
    img = np.where(sky[..., None], _sky_colour(condition, elev, cast, sun_dir), img)
    if condition != "day":
        night = condition == "night"
        glow = np.zeros_like(img)
        glow[lit] = (1.0, 0.8, 0.45)
        glow[tail] = (1.0, 0.05, 0.02) if night else (0.5, 0.02, 0.01)
        glow[head] = (1.0, 1.0, 0.9)
        glow[kind == LAMP] = (1.0, 0.9, 0.6) if night else (0.3, 0.3, 0.2)
        img += glow * (1.0 if night else 0.3)
        if night:  # light pools of the street lamps on the ground
            gi = np.flatnonzero(ground.ravel())
            gx, gz = x_w.ravel()[gi], z_w.ravel()[gi]
            pool = np.zeros(gi.size, np.float32)
            for lx, ly, lz in lay["lamps"]:
                pool += 4.0 / ((gx - lx) ** 2 + (gz - lz) ** 2 + ly**2)
            flat = img.reshape(-1, 3)
            flat[gi] += albedo.reshape(-1, 3)[gi] * pool[:, None] * np.float32((1.0, 0.85, 0.6))
    exposure = p["exposure"] if p["exposure"] is not None else 1.5
    if condition != "night":
        exposure = exposure / max(np.percentile(img[::4, ::4], 97), 1e-3)
    img *= exposure
    img += p["rgb_noise"] * (1 + 3 * np.sqrt(np.maximum(img, 0))) * rng.standard_normal(
        img.shape, dtype=np.float32)
    rgb = _gamma_lut()[(np.clip(img, 0, 1) * (_GAMMA_LEVELS - 1) + 0.5).astype(np.int32)]

    # ---- labels and LiDAR
    seg = np.where(ground, np.where(road, _SEG["road"], IGNORE_LABEL), _KIND_SEG[kind])
    seg = seg.astype(np.uint8)
    depth_lidar = _lidar(rng, depth, rng_m, cast)

    return dict(raw14=raw14, ir8=camera_like(raw14), rgb=rgb, depth=depth,
                depth_lidar=depth_lidar, valid=depth_lidar > 0, seg=seg, condition=condition)


def _sky_colour(condition, elev, cast, sun_dir):
    """(H, W, 3) float32 linear sky colour: horizon-to-zenith gradient, sun glow at dusk."""
    e = np.clip(elev, 0, None)[..., None]
    horizon, zenith = {"day": ((0.75, 0.85, 0.95), (0.3, 0.5, 0.9)),
                       "dusk": ((1.0, 0.55, 0.3), (0.25, 0.3, 0.55)),
                       "night": ((0.03, 0.03, 0.05), (0.0, 0.0, 0.01))}[condition]
    horizon, zenith = np.float32(horizon), np.float32(zenith)
    sky = zenith + (horizon - zenith) * np.exp(-e / np.float32(0.25))
    if condition == "dusk" and sun_dir is not None:  # glow around the sun's azimuth
        az = np.arctan2(cast.dx, 1.0)[0]
        sun_az = np.arctan2(sun_dir[0], sun_dir[2])
        d = np.angle(np.exp(1j * (az - sun_az))).astype(np.float32)
        sky += (np.exp(-(d / 0.5) ** 2)[None, :, None] * np.exp(-e / np.float32(0.1))
                * np.float32((0.6, 0.3, 0.05)))
    return sky


def _lidar(rng, depth, rng_m, cast):
    """Sparse LiDAR-like depth: scan lines at uniform elevations, ~2 px azimuth step, dropouts."""
    height, width = depth.shape
    n_beams = max(8, height // 4)
    el = np.linspace(np.arctan(-(height - cast.cy) / cast.f), np.deg2rad(10.0), n_beams)
    rows = np.round(cast.cy - cast.f * np.tan(el) - 0.5)
    rows = np.unique(np.clip(rows, 0, height - 1)).astype(int)
    step = 2 if width >= 160 else 1
    mask = np.zeros((height, width), bool)
    phase = rng.integers(0, step, len(rows))
    for r, ph in zip(rows, phase):  # one slice assignment per scan line
        mask[r, ph::step] = True
    mask &= rng.random((height, width)) > 0.08
    noise = 1 + 0.003 * rng.standard_normal((height, width), dtype=np.float32)  # ~ +-3 mm/m
    mask &= (depth > 0) & (rng_m * noise <= LIDAR_MAX_RANGE)
    return np.where(mask, depth * noise, 0).astype(np.float32)

