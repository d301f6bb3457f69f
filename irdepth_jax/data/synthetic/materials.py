"""Object kinds, ground materials, their labels, and the per-condition material tables.

Every object of a scene has a kind (SKY .. FAR_TREES); the ground plane is one object whose
pixels get a material ROAD, WALK or GRASS from their position. Material arrays are indexed by
kind, or by ROAD / WALK / GRASS on the ground (N_MATERIALS entries).
"""

from __future__ import annotations

import functools

import numpy as np

from irdepth_jax.config import CLASS_NAMES, IGNORE_LABEL

CONDITIONS: tuple[str, ...] = ("day", "dusk", "night")
"""Lighting conditions `render_scene` accepts."""

# Object kinds (material logic). Index 0 is the sky, 1 the ground plane.
(SKY, GROUND, BUILDING, CAR_BODY, CAR_CABIN, TYRE, BIKE, RIDER, TRUNK, CROWN, POLE, LAMP,
 FAR_BUILDING, FAR_TREES) = range(14)
ROAD, WALK, GRASS = 14, 15, 16  # ground materials (the ground plane is one object)
N_MATERIALS = 17

SEG_ID = {name: i for i, name in enumerate(CLASS_NAMES)}
"""Segmentation label of each class name."""

KIND_SEG = np.full(14, IGNORE_LABEL, np.uint8)
"""(14,) uint8 segmentation label of each object kind (the ground is labelled per material)."""
for _kinds, _name in (((SKY,), "sky"), ((BUILDING, FAR_BUILDING), "building"),
                      ((CAR_BODY, CAR_CABIN, TYRE), "car"), ((BIKE,), "bicycle"),
                      ((TRUNK, CROWN, FAR_TREES), "tree")):
    KIND_SEG[list(_kinds)] = SEG_ID[_name]

COND = {
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
"""Scene parameters of each condition (thermal and visible)."""


@functools.lru_cache(maxsize=len(CONDITIONS))
def material_tables(condition: str) -> dict:
    """Per-material (N_MATERIALS,) float32 arrays of one condition.

    Returns:
      dict with base (K above air), sun (K at full sun), tex (K per unit texture), eps
      (emissivity), tex_rgb (relative albedo texture), each (N_MATERIALS,) float32, indexed by
      kind or by ROAD / WALK / GRASS on the ground. Cached: do not modify.
    """
    p = COND[condition]
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
