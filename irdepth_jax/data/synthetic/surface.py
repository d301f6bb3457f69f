"""Per-pixel surface attributes shared by the thermal and the visible image.

Sunlight (Lambert term of each face, cast shadows on the ground from a top-down shadow map),
ground materials and lane markings, a tiled texture, facade windows (lit or not at night) and
the faces of cars (rear lights, headlights, warm engine fronts, exhausts, glass).
"""

from __future__ import annotations

import dataclasses
import functools

import cv2
import numpy as np

from irdepth_jax.data.synthetic.caster import NX, NY, NZ, Geometry
from irdepth_jax.data.synthetic.materials import (
    BUILDING,
    CAR_BODY,
    CAR_CABIN,
    CROWN,
    FAR_BUILDING,
    GRASS,
    GROUND,
    ROAD,
    WALK,
)
from irdepth_jax.data.synthetic.scene import Scene


@dataclasses.dataclass(frozen=True, eq=False)
class Surface:
    """Surface attributes of an (H, W) image; all (H, W).

    mat int64: material (the object's kind, or ROAD / WALK / GRASS on the ground); tex float32:
    texture in [-1, 1]; lambert float32: direct sunlight in [0, 1] (0 in shadow); up bool: faces
    looking up; the others bool masks: ground, road, marking (lane paint), window, lit (lit
    window), glass (car windows), tail / head (car lights), engine (warm car front), exhaust.
    """

    mat: np.ndarray
    tex: np.ndarray
    lambert: np.ndarray
    up: np.ndarray
    ground: np.ndarray
    road: np.ndarray
    marking: np.ndarray
    window: np.ndarray
    lit: np.ndarray
    glass: np.ndarray
    tail: np.ndarray
    head: np.ndarray
    engine: np.ndarray
    exhaust: np.ndarray


def shade_surfaces(geo: Geometry, scene: Scene, lay: dict, tab: dict, sun_dir) -> Surface:
    """Surface attributes of every pixel.

    Args:
      geo: what the (H, W) rays hit; scene, lay: the scene and its layout (`sample_scene`);
      tab: `scene.table()`; sun_dir: (3,) unit vector toward the sun, or None (night).

    Returns:
      the (H, W) Surface maps.
    """
    crown = geo.kind == CROWN
    ground, road, marking, mat = _ground_materials(geo, lay)
    tile = _noise_tile()
    tex = tile[(geo.z_w * 8).astype(np.int32) & 255, (geo.x_w * 8).astype(np.int32) & 255]
    window, lit = _facade_windows(geo, tab["params"])
    tail, head, engine, exhaust = _car_faces(geo, tab["bounds"], tab["params"])
    return Surface(
        mat=mat, tex=tex, lambert=_sun_lambert(geo, scene, lay, sun_dir, crown),
        up=((geo.nrm == NY) & (geo.dy < 0)) | crown, ground=ground, road=road, marking=marking,
        window=window, lit=lit, glass=(geo.kind == CAR_CABIN) & (geo.nrm != NY), tail=tail,
        head=head, engine=engine, exhaust=exhaust)


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


def _sun_lambert(geo, scene, lay, sun_dir, crown):
    """(H, W) float32 Lambert term of each face, 0 in the ground's cast shadows or at night.

    Normal codes: x faces look back along -dx, y faces up when the ray goes down, z faces toward
    the camera; crowns get a fixed up-and-back normal.
    """
    if sun_dir is None:
        return np.zeros(geo.kind.shape, np.float32)
    sx, sy, sz = (float(v) for v in sun_dir)
    cos = np.where(geo.nrm == NX, -np.sign(geo.dx) * sx,
                   np.where(geo.nrm == NY, -np.sign(geo.dy) * sy, -sz))
    cos = np.where(crown, 0.7 * sy - 0.7 * sz, cos)
    grid, x_lo, res = _shadow_map(scene, sun_dir, (lay["side_l"] - 40, lay["side_r"] + 40))
    iz = np.clip((geo.z_w / res).astype(np.int32), 0, grid.shape[0] - 1)
    ix = np.clip(((geo.x_w - x_lo) / res).astype(np.int32), 0, grid.shape[1] - 1)
    shadow = (grid[iz, ix] > 0) & (geo.kind == GROUND)
    return (np.clip(cos, 0, 1) * ~shadow).astype(np.float32)


def _shadow_map(scene, sun_dir, extent):
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
    """(n, 3) float64 points spread evenly over the unit sphere (Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    phi, theta = np.arccos(1 - 2 * i / n), np.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(theta) * np.sin(phi), np.cos(phi), np.sin(theta) * np.sin(phi)], 1)


def _ground_materials(geo, lay):
    """(H, W) ground, road, marking masks and material ids (kind, or ROAD / WALK / GRASS)."""
    x_w, z_w = geo.x_w, geo.z_w
    ground = geo.kind == GROUND
    road = ground & (x_w >= lay["road_l"]) & (x_w <= lay["road_r"])
    walk = ground & ~road & (x_w >= lay["side_l"]) & (x_w <= lay["side_r"])
    if "cross" in lay:  # the cross road and its sidewalks, across the whole view
        cross = ground & ~road & (z_w >= lay["cross"][0]) & (z_w <= lay["cross"][1])
        walk = (walk & ~cross) | (ground & ~road & ~cross & (z_w >= lay["gap"][0]) & (z_w <= lay["gap"][1]))
        road = road | cross
    lane_x = (x_w - lay["lanes_l"]) / lay["lane"]
    near_line = np.abs(lane_x - np.round(lane_x)) * lay["lane"] < 0.08
    edge_line = (np.round(lane_x) <= 0) | (np.round(lane_x) >= lay["n_lanes"])
    dashed = np.mod(z_w, 9.0) < 3.0
    centre_line = np.abs(x_w - lay["centre"]) < 0.12
    marking = road & ((near_line & (edge_line | dashed)) | centre_line)
    if "cross" in lay:  # no lane paint across the crossing
        marking &= (z_w < lay["cross"][0]) | (z_w > lay["cross"][1])
    mat = np.where(ground, np.where(road, ROAD, np.where(walk, WALK, GRASS)), geo.kind)
    return ground, road, marking, mat


def _facade_windows(geo, params):
    """(H, W) window and lit-window masks on building walls (params: (N, 3) per object).

    A hash of floor, column and building decides which windows are lit at night.
    """
    height, width = geo.kind.shape
    window, lit = np.zeros(height * width, bool), np.zeros(height * width, bool)
    kind_flat = geo.kind.ravel()
    facade = (kind_flat == BUILDING) | (kind_flat == FAR_BUILDING)
    bi = np.flatnonzero(facade & (geo.nrm.ravel() != NY))
    prm = params[geo.obj.ravel()[bi]]
    horiz = np.where(geo.nrm.ravel()[bi] == NX, geo.z_w.ravel()[bi], geo.x_w.ravel()[bi])
    yb = geo.y_w.ravel()[bi]
    wi, wf = np.divmod(horiz / prm[:, 0], 1.0)
    fi, ff = np.divmod((yb - 1.0) / prm[:, 1], 1.0)
    win = (wf > 0.25) & (wf < 0.75) & (ff > 0.3) & (ff < 0.85) & (yb > 1.0)
    code = (wi.astype(np.int64) * 73856093) ^ (fi.astype(np.int64) * 19349663) ^ (
        prm[:, 2].astype(np.int64) * 83492791)
    window[bi], lit[bi] = win, win & (code % 100 < 35)
    return window.reshape(height, width), lit.reshape(height, width)


def _car_faces(geo, bounds, params):
    """(H, W) masks on the car bodies' camera-facing faces: tail lights, headlights, the warm
    front of running cars facing us, exhausts (bounds (N, 6), params (N, 3) per object)."""
    height, width = geo.kind.shape
    tail, head, engine, exhaust = (np.zeros(height * width, bool) for _ in range(4))
    ci = np.flatnonzero((geo.kind.ravel() == CAR_BODY) & (geo.nrm.ravel() == NZ))
    cb, cp = bounds[geo.obj.ravel()[ci]], params[geo.obj.ravel()[ci]]
    rel_y = (geo.y_w.ravel()[ci] - cb[:, 2]) / (cb[:, 3] - cb[:, 2])
    rel_x = (geo.x_w.ravel()[ci] - cb[:, 0]) / (cb[:, 1] - cb[:, 0])
    lamps = (rel_y > 0.55) & (rel_y < 0.85) & ((rel_x < 0.2) | (rel_x > 0.8))
    facing_us, running = cp[:, 0] > 0, cp[:, 1] > 0
    tail[ci], head[ci] = lamps & ~facing_us, lamps & facing_us
    engine[ci] = facing_us & running
    exhaust[ci] = ~facing_us & running & (rel_y < 0.25) & (rel_x > 0.15) & (rel_x < 0.3)
    return tuple(a.reshape(height, width) for a in (tail, head, engine, exhaust))
