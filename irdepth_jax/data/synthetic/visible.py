"""The visible (RGB) twin of the thermal frame, aligned pixel for pixel.

Albedo x (ambient + sun) + lights (lit windows, car lights, lamps and their light pools on the
ground at night), a sky gradient (with the sun's glow at dusk), auto exposure (fixed at night),
signal-dependent noise and an sRGB-like gamma.
"""

from __future__ import annotations

import functools

import numpy as np

from irdepth_jax.data.synthetic.caster import Geometry
from irdepth_jax.data.synthetic.materials import COND, LAMP, ROAD, material_tables
from irdepth_jax.data.synthetic.surface import Surface

_GROUND_RGB = np.float32([[0.22] * 3, [0.45] * 3, [0.3, 0.33, 0.2], [0.85] * 3, [0.08] * 3])
"""Albedo of road, sidewalk, grass (in ROAD, WALK, GRASS order), lane paint, car glass."""

_GAMMA_LEVELS = 16384


def render_rgb(rng: np.random.Generator, condition: str, geo: Geometry, surf: Surface,
               colors: np.ndarray, lamps: list, sun_dir) -> np.ndarray:
    """The visible image of a scene.

    Args:
      rng: the scene's generator (draws the sensor noise).
      condition: one of CONDITIONS.
      geo, surf: (H, W) geometry and surface attributes.
      colors: (N, 3) float32 linear albedo of each object (`Scene.table()['color']`).
      lamps: (x, y, z) of the street lamps' bulbs (m).
      sun_dir: (3,) unit vector toward the sun, or None (night).

    Returns:
      (H, W, 3) uint8 RGB image (dark and noisy at night).
    """
    p = COND[condition]
    albedo = _albedo(condition, geo, surf, colors)
    light = ((p["ambient"] * (0.6 + 0.4 * surf.up))[..., None]
             + p["sun"] * surf.lambert[..., None] * np.float32(p["sun_rgb"]))
    img = albedo * light
    img = np.where(geo.sky[..., None], _sky_colour(condition, geo, sun_dir), img)
    if condition != "day":
        _add_lights(img, albedo, condition, geo, surf, lamps)
    exposure = p["exposure"] if p["exposure"] is not None else 1.5
    if condition != "night":
        exposure = exposure / max(np.percentile(img[::4, ::4], 97), 1e-3)
    img *= exposure
    img += p["rgb_noise"] * (1 + 3 * np.sqrt(np.maximum(img, 0))) * rng.standard_normal(
        img.shape, dtype=np.float32)
    return _gamma_lut()[(np.clip(img, 0, 1) * (_GAMMA_LEVELS - 1) + 0.5).astype(np.int32)]


def _albedo(condition, geo, surf, colors):
    """(H, W, 3) float32 linear albedo: objects' colours, ground materials, paint, glass,
    textured, windows darker."""
    n_obj = len(colors)
    colours = np.concatenate([colors, _GROUND_RGB])
    alb_idx = np.where(surf.ground, n_obj + surf.mat - ROAD, geo.obj)
    alb_idx = np.where(surf.marking, n_obj + 3, np.where(surf.glass, n_obj + 4, alb_idx))
    fac = 1 + material_tables(condition)["tex_rgb"][surf.mat] * surf.tex * ~surf.marking
    fac = np.where(surf.window, 0.35 * fac, fac)
    return colours[alb_idx] * fac[..., None]


def _add_lights(img, albedo, condition, geo, surf, lamps):
    """Adds (in place, to the (H, W, 3) float32 img) the glow of lit windows, car lights and
    lamp heads at dusk and night, and at night the street lamps' light pools on the ground."""
    night = condition == "night"
    glow = np.zeros_like(img)
    glow[surf.lit] = (1.0, 0.8, 0.45)
    glow[surf.tail] = (1.0, 0.05, 0.02) if night else (0.5, 0.02, 0.01)
    glow[surf.head] = (1.0, 1.0, 0.9)
    glow[geo.kind == LAMP] = (1.0, 0.9, 0.6) if night else (0.3, 0.3, 0.2)
    img += glow * (1.0 if night else 0.3)
    if night:
        gi = np.flatnonzero(surf.ground.ravel())
        gx, gz = geo.x_w.ravel()[gi], geo.z_w.ravel()[gi]
        pool = np.zeros(gi.size, np.float32)
        for lx, ly, lz in lamps:
            pool += 4.0 / ((gx - lx) ** 2 + (gz - lz) ** 2 + ly**2)
        flat = img.reshape(-1, 3)
        flat[gi] += albedo.reshape(-1, 3)[gi] * pool[:, None] * np.float32((1.0, 0.85, 0.6))


def _sky_colour(condition, geo, sun_dir):
    """(H, W, 3) float32 linear sky colour: horizon-to-zenith gradient, sun glow at dusk."""
    e = np.clip(geo.elev, 0, None)[..., None]
    horizon, zenith = {"day": ((0.75, 0.85, 0.95), (0.3, 0.5, 0.9)),
                       "dusk": ((1.0, 0.55, 0.3), (0.25, 0.3, 0.55)),
                       "night": ((0.03, 0.03, 0.05), (0.0, 0.0, 0.01))}[condition]
    horizon, zenith = np.float32(horizon), np.float32(zenith)
    sky = zenith + (horizon - zenith) * np.exp(-e / np.float32(0.25))
    if condition == "dusk" and sun_dir is not None:  # glow around the sun's azimuth
        az = np.arctan2(geo.dx, 1.0)[0]
        sun_az = np.arctan2(sun_dir[0], sun_dir[2])
        d = np.angle(np.exp(1j * (az - sun_az))).astype(np.float32)
        sky += (np.exp(-(d / 0.5) ** 2)[None, :, None] * np.exp(-e / np.float32(0.1))
                * np.float32((0.6, 0.3, 0.05)))
    return sky


@functools.lru_cache(maxsize=1)
def _gamma_lut() -> np.ndarray:
    """(_GAMMA_LEVELS,) uint8 sRGB-like 1/2.2 gamma of linear [0, 1] quantised to _GAMMA_LEVELS."""
    return (np.linspace(0, 1, _GAMMA_LEVELS) ** (1 / 2.2) * 255 + 0.5).astype(np.uint8)
