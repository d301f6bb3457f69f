"""Random street layouts: the primitives (boxes, ellipsoids, wheel rings) of one scene.

`sample_scene(rng)` lays out a street along +z in world metres (x right, y up, z forward; the
camera sits above x = 0, z = 0): a road with lanes and parking strips, sidewalks, buildings on
both sides, a far backdrop closing the view, moving and parked cars, trees, lamp poles and
bicycles with or without riders. It only draws from `rng`; nothing is rendered here.

`SCENES` names the scene distributions: 'street' (the one above, the distribution every
committed dataset and result was rendered from; its draws never change) and 'varied', where the
street may be crossed by another one, may run through open ground with few and set-back
buildings, and may have an obstacle close in front of the camera (a wall, a van, a pole), so
that no fixed depth layout fits most frames.
"""

from __future__ import annotations

import typing

import numpy as np

from irdepth_jax.config_schema import Scenes
from irdepth_jax.data.synthetic.materials import (
    BIKE,
    BUILDING,
    CAR_BODY,
    CAR_CABIN,
    CROWN,
    FAR_BUILDING,
    FAR_TREES,
    GROUND,
    LAMP,
    POLE,
    RIDER,
    SKY,
    TRUNK,
    TYRE,
)


class Scene:
    """Primitives and a per-object property table.

    boxes: (x0, x1, y0, y1, z0, z1, oid) axis-aligned boxes; ellipsoids: (cx, cy, cz, rx, ry, rz,
    oid); rings: (axis, plane, ca, cy, r_out, r_in, oid) wheels (see `_Caster.ring`). Object 0
    is the sky, object 1 the ground plane; `table()` gives the objects' properties as arrays.
    """

    def __init__(self):
        self.boxes, self.ellipsoids, self.rings = [], [], []
        self.kind, self.toff, self.color, self.bounds, self.params = [], [], [], [], []
        self.add_object(SKY, color=(0, 0, 0))
        self.add_object(GROUND, color=(0, 0, 0))

    def add_object(self, kind, toff=0.0, color=(0.5, 0.5, 0.5), bounds=(0,) * 6, params=(0, 0, 0)):
        """Adds an object (kind, K offset, linear RGB albedo, box bounds, kind parameters) and
        returns its id."""
        self.kind.append(kind)
        self.toff.append(toff)
        self.color.append(color)
        self.bounds.append(bounds)
        self.params.append(params)
        return len(self.kind) - 1

    def box(self, kind, x0, x1, y0, y1, z0, z1, **kw):
        """Adds an object made of one box [x0, x1] x [y0, y1] x [z0, z1]; returns its id."""
        oid = self.add_object(kind, bounds=(x0, x1, y0, y1, z0, z1), **kw)
        self.boxes.append((x0, x1, y0, y1, z0, z1, oid))
        return oid

    def table(self) -> dict:
        """Object properties for N objects: kind (N,) int32, toff (N,) float32 (K above the
        material's temperature), color (N, 3) float32, bounds (N, 6) float32, params (N, 3)
        float32 (buildings: window pitch x, y and a hash seed; cars: facing, running, 0)."""
        return dict(kind=np.array(self.kind, np.int32), toff=np.array(self.toff, np.float32),
                    color=np.array(self.color, np.float32),
                    bounds=np.array(self.bounds, np.float32),
                    params=np.array(self.params, np.float32))


SCENES = typing.get_args(Scenes)
"""The scene distributions of `sample_scene` (module docstring)."""


def sample_scene(rng: np.random.Generator, scenes: str = "street") -> tuple[Scene, dict]:
    """Random street -> (Scene, layout).

    The layout dict holds the street's cross-section in x (lane width `lane`, `centre` line,
    lane edges `lanes_l` / `lanes_r`, `n_lanes`, road edges `road_l` / `road_r`, parking strip
    widths `park_l` / `park_r`, sidewalk widths `walk_l` / `walk_r`, outer sidewalk edges
    `side_l` / `side_r`), the backdrop distance `z_far`, the street lamps' bulbs `lamps`
    (list of (x, y, z)), how many building lots are built (`built`) and how far they are set
    back (`setback`), and for a crossing (`varied` only) `cross`: the cross road's (z0, z1) and
    `gap`: the (z0, z1) its road and sidewalks clear of the street's buildings, trees and lamps.
    """
    if scenes not in SCENES:
        raise ValueError(f"scenes must be one of {SCENES}, got {scenes!r}")
    s = Scene()
    lay = _sample_layout(rng)
    if scenes == "varied":
        _vary_layout(rng, lay)
    _buildings(s, rng, lay)
    if "cross" in lay:
        _cross_street(s, rng, lay)
    _backdrop(s, rng, lay["z_far"])
    _cars(s, rng, lay)
    for side in (-1, 1):
        _lamps(s, rng, lay, _trees(s, rng, lay, side), side)
    _bicycles(s, rng, lay)
    if scenes == "varied" and rng.random() < 0.35:
        _close_obstacle(s, rng, lay)
    # plain Python floats: the caster does scalar arithmetic on them (numpy scalars are slow)
    s.boxes, s.ellipsoids, s.rings = ([tuple(map(float, p[:-1])) + (int(p[-1]),) for p in prims]
                                      for prims in (s.boxes, s.ellipsoids, s.rings))
    return s, lay


def _sample_layout(rng):
    """Lanes, parking strips, sidewalks and the backdrop distance (see `sample_scene`)."""
    lane = rng.uniform(3.0, 3.6)
    n_right, n_left = rng.integers(1, 3), rng.integers(1, 3)
    k = rng.integers(0, n_right)
    centre = -(k + 0.5) * lane
    park_l, park_r = (2.3 if rng.random() < 0.75 else 0.0 for _ in range(2))  # parking strips
    lanes_l, lanes_r = centre - n_left * lane, centre + n_right * lane
    road_l, road_r = lanes_l - park_l, lanes_r + park_r
    walk_l, walk_r = rng.uniform(2.0, 4.5, 2)
    return dict(lane=lane, centre=centre, road_l=road_l, road_r=road_r, lanes_l=lanes_l,
                lanes_r=lanes_r, n_lanes=n_left + n_right, park_l=park_l, park_r=park_r,
                walk_l=walk_l, walk_r=walk_r, side_l=road_l - walk_l, side_r=road_r + walk_r,
                z_far=rng.uniform(110.0, 200.0), lamps=[], built=0.85, setback=(0.0, 4.0))


def _vary_layout(rng, lay):
    """The `varied` distribution's layouts: a crossing (35 %), open ground (25 %) or the plain
    street; the backdrop anywhere from 50 to 200 m."""
    lay["z_far"] = rng.uniform(50.0, 200.0)
    kind = rng.random()
    if kind < 0.35:
        width = rng.uniform(7.0, 16.0)
        z0 = rng.uniform(8.0, min(45.0, lay["z_far"] - 30.0))
        walk = rng.uniform(2.0, 4.0)
        lay["cross"] = (z0, z0 + width)
        lay["gap"] = (z0 - walk, z0 + width + walk)
    elif kind < 0.6:  # open ground: few buildings, far from the road
        lay["built"], lay["setback"] = 0.25, (8.0, 40.0)


def _clear(lay, z0, z1):
    """Whether [z0, z1] stays out of the crossing's gap (always, without a crossing)."""
    gap = lay.get("gap")
    return gap is None or z1 < gap[0] or z0 > gap[1]


def _window_params(rng):
    """A facade's (window pitch along the wall, floor height, window hash seed)."""
    return rng.uniform(2.4, 4.0), rng.uniform(2.9, 3.6), rng.integers(0, 1000)


def _buildings(s, rng, lay):
    """Rows of buildings (with gaps and setbacks) along both outer sidewalk edges."""
    for side in (-1, 1):
        edge = lay["side_l"] if side < 0 else lay["side_r"]
        z = rng.uniform(-15.0, 0.0)
        while z < lay["z_far"] - 10:
            length = rng.uniform(8.0, 30.0)
            if rng.random() < lay["built"] and _clear(lay, z, z + length):
                setback = rng.uniform(*lay["setback"]) if rng.random() < 0.5 else 0.0
                depth = rng.uniform(8.0, 20.0)
                x_in = edge + side * setback
                x0, x1 = sorted((x_in, x_in + side * depth))
                shade = rng.uniform(0.25, 0.8)
                tint = rng.uniform(0.85, 1.15, 3) * shade
                s.box(BUILDING, x0, x1, 0.0, rng.uniform(4.0, 28.0), z, z + length,
                      toff=rng.normal(0, 1.0), color=tuple(np.clip(tint, 0, 1)),
                      params=_window_params(rng))
            z += length + (rng.uniform(0.0, 8.0) if rng.random() < 0.5 else 0.0)


def _cross_street(s, rng, lay):
    """Buildings lining the cross street on both sides of the street, out to 40-120 m."""
    g0, g1 = lay["gap"]
    for side in (-1, 1):
        edge = lay["side_l"] if side < 0 else lay["side_r"]
        for near in (True, False):
            x, end = edge, edge + side * rng.uniform(40.0, 120.0)
            while side * (end - x) > 0:
                length, depth = rng.uniform(8.0, 30.0), rng.uniform(8.0, 20.0)
                if rng.random() < lay["built"]:
                    x0, x1 = sorted((x, x + side * length))
                    z0, z1 = (g0 - depth, g0) if near else (g1, g1 + depth)
                    shade = rng.uniform(0.25, 0.8)
                    s.box(BUILDING, x0, x1, 0.0, rng.uniform(4.0, 28.0), z0, z1,
                          toff=rng.normal(0, 1.0),
                          color=tuple(np.clip(rng.uniform(0.85, 1.15, 3) * shade, 0, 1)),
                          params=_window_params(rng))
                x += side * (length + rng.uniform(0.0, 6.0))


def _close_obstacle(s, rng, lay):
    """One thing within 2-9 m in front of the camera: a wall or fence across part of the view,
    a van or car ahead, or a pole."""
    z = rng.uniform(2.0, 9.0)
    kind = rng.random()
    if kind < 0.4:
        x = rng.uniform(-4.0, 4.0)
        half = rng.uniform(1.0, 5.0)
        s.box(BUILDING, x - half, x + half, 0.0, rng.uniform(1.0, 3.5), z, z + rng.uniform(0.2, 1.0),
              toff=rng.normal(0, 1.0), color=tuple(rng.uniform(0.3, 0.8, 3)), params=_window_params(rng))
    elif kind < 0.8:
        _car(s, rng, rng.uniform(-1.5, 1.5), z + 2.5, rng.choice((-1, 1)), rng.random() < 0.5, min_z=0.0)
    else:
        x = rng.uniform(-2.5, 2.5)
        s.box(POLE, x - 0.15, x + 0.15, 0.0, rng.uniform(3.0, 8.0), z, z + 0.3, color=(0.4, 0.4, 0.42))


def _backdrop(s, rng, z_far):
    """The far backdrop closing the street: a contiguous row of buildings or a tree line."""
    far_kind = FAR_TREES if rng.random() < 0.3 else FAR_BUILDING
    x = -320.0
    while x < 320.0:
        w = rng.uniform(8.0, 35.0)
        hgt = rng.uniform(6.0, 14.0) if far_kind == FAR_TREES else rng.uniform(5.0, 45.0)
        col = (0.2, 0.3, 0.15) if far_kind == FAR_TREES else tuple(rng.uniform(0.3, 0.7, 3))
        zz = z_far + rng.uniform(0.0, 15.0)
        s.box(far_kind, x, x + w, 0.0, hgt, zz, zz + 15.0, toff=rng.normal(0, 1.0), color=col,
              params=_window_params(rng))
        x += w


def _cars(s, rng, lay):
    """Traffic in every lane (ours: going away; opposite: facing us), parked at both curbs."""
    lane, centre = lay["lane"], lay["centre"]
    for i in range(lay["n_lanes"]):
        xc = lay["lanes_l"] + (i + 0.5) * lane
        ours = xc > centre
        z = rng.uniform(4.0, 25.0) + (6.0 if abs(xc) < 1.0 else 0.0)
        while z < 110:
            _car(s, rng, xc + rng.normal(0, 0.2), z, -1 if ours else 1, True,
                 min_z=8.0 if abs(xc) < 1.0 else 3.0)
            z += rng.uniform(8.0, 45.0)
    for side, strip in ((-1, lay["park_l"]), (1, lay["park_r"])):
        curb = lay["road_l"] if side < 0 else lay["road_r"]
        z = rng.uniform(-2.0, 8.0)
        while strip > 0 and z < 90 and rng.random() < 0.85:
            facing, running = rng.choice((-1, 1)), rng.random() < 0.15
            if _clear(lay, z - 2.5, z + 2.5):
                _car(s, rng, curb - side * 1.1, z, facing, running, min_z=1.0)
            z += rng.uniform(5.2, 14.0)


def _car(s, rng, xc, zc, facing, running, min_z):
    """One car or van centred at (xc, zc) (skipped if zc < min_z): body, cabin, four tyres.

    facing: +1 toward the camera, -1 away; running: engine on (warm front, tyres, exhaust).
    """
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


def _trees(s, rng, lay, side):
    """Trees (trunk box, ellipsoid crown) along one sidewalk; returns their row's x."""
    # trees at 35 % of the sidewalk's width from the kerb
    if side < 0:
        x = lay["road_l"] - 0.35 * lay["walk_l"]
    else:
        x = lay["road_r"] + 0.35 * lay["walk_r"]
    z = rng.uniform(2.0, 12.0)
    tree_gap = rng.uniform(7.0, 16.0)
    while z < lay["z_far"] - 10 and rng.random() < 0.9:
        r = rng.uniform(0.12, 0.25)
        trunk_h = rng.uniform(1.8, 3.0)
        if not _clear(lay, z - 3.0, z + 3.0):
            z += tree_gap
            continue
        s.box(TRUNK, x - r, x + r, 0.0, trunk_h + 0.5, z - r, z + r, toff=rng.normal(0, 0.5),
              color=(0.25, 0.18, 0.12))
        rx, ry = rng.uniform(1.3, 2.8), rng.uniform(1.6, 3.5)
        oid = s.add_object(CROWN, toff=rng.normal(0, 0.5),
                           color=tuple(np.array((0.18, 0.35, 0.12)) * rng.uniform(0.6, 1.3)))
        s.ellipsoids.append((x, trunk_h + ry * 0.9, z, rx, ry, rx, oid))
        z += tree_gap * rng.uniform(0.7, 1.4)
    return x


def _lamps(s, rng, lay, x, side):
    """Lamp poles 0.5 m outside the tree row at x, arms over the road; bulbs go to lay['lamps']."""
    zp = rng.uniform(5.0, 20.0)
    xp = x + side * 0.5
    while zp < 100:
        top = rng.uniform(6.0, 8.0)
        if not _clear(lay, zp - 1.0, zp + 1.0):
            zp += 10.0
            continue
        s.box(POLE, xp - 0.08, xp + 0.08, 0.0, top, zp - 0.08, zp + 0.08, color=(0.4, 0.4, 0.42))
        arm0, arm1 = sorted((xp, xp - side * 1.6))
        s.box(LAMP, arm0, arm1, top - 0.25, top, zp - 0.2, zp + 0.2, color=(0.8, 0.8, 0.7))
        lay["lamps"].append((xp - side * 1.4, top - 0.3, zp))
        zp += rng.uniform(25.0, 40.0)


def _bicycles(s, rng, lay):
    """1-5 riding bicycles (wheels in x = const planes, seen from behind) or parked racks."""
    for _ in range(rng.integers(1, 6)):
        if rng.random() < 0.6:  # riding: at the kerb side of the right lane, or on a sidewalk
            where = rng.integers(0, 3)
            xc = (lay["lanes_r"] - 0.45, lay["road_l"] - 0.7 * lay["walk_l"],
                  lay["road_r"] + 0.7 * lay["walk_r"])[where]
            _bicycle(s, rng, xc, rng.uniform(4.0, 35.0), along=True, rider=rng.random() < 0.7)
        else:  # a rack of 1-4 parked bikes
            side = rng.choice((-1, 1))
            xc = (lay["side_l"] + 1.2) if side < 0 else (lay["side_r"] - 1.2)
            z0 = rng.uniform(4.0, 30.0)
            for k in range(rng.integers(1, 5)):
                _bicycle(s, rng, xc, z0 + 0.7 * k, along=False, rider=False)


def _bicycle(s, rng, xc, zc, along, rider):
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
