"""`render_scene`: one labelled street scene, thermal and visible, with dense and LiDAR depth."""

from __future__ import annotations

import numpy as np

from irdepth_jax.config import IGNORE_LABEL
from irdepth_jax.data.synthetic.caster import Geometry, cast_scene
from irdepth_jax.data.synthetic.materials import COND, CONDITIONS, KIND_SEG, SEG_ID
from irdepth_jax.data.synthetic.radiometry import render_lwir
from irdepth_jax.data.synthetic.scene import sample_scene
from irdepth_jax.data.synthetic.surface import shade_surfaces
from irdepth_jax.data.synthetic.visible import render_rgb

LIDAR_MAX_RANGE = 80.0
"""Range limit (metres, Euclidean) of the simulated LiDAR."""


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
    scene, lay = sample_scene(rng)
    cam_h = rng.uniform(1.4, 1.6)
    tab = scene.table()
    geo = cast_scene(scene, tab["kind"], height, width, cam_h)
    t_air, sun_dir = _sample_lighting(rng, condition)
    surf = shade_surfaces(geo, scene, lay, tab, sun_dir)
    raw14, ir8 = render_lwir(rng, condition, t_air, geo, surf, tab["toff"])
    rgb = render_rgb(rng, condition, geo, surf, tab["color"], lay["lamps"], sun_dir)
    seg = np.where(surf.ground, np.where(surf.road, SEG_ID["road"], IGNORE_LABEL),
                   KIND_SEG[geo.kind]).astype(np.uint8)
    depth_lidar = _lidar(rng, geo)
    return dict(raw14=raw14, ir8=ir8, rgb=rgb, depth=geo.depth, depth_lidar=depth_lidar,
                valid=depth_lidar > 0, seg=seg, condition=condition)


def _sample_lighting(rng, condition):
    """Air temperature (K) and the (3,) unit vector toward the sun (None at night)."""
    p = COND[condition]
    t_air = rng.uniform(*p["t_air"]) + 273.15
    if p["sun_el"] is None:
        return t_air, None
    el, az = np.deg2rad(rng.uniform(*p["sun_el"])), rng.uniform(-np.pi, np.pi)
    return t_air, np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])


def _lidar(rng, geo: Geometry):
    """(H, W) float32 sparse LiDAR-like depth: scan lines at uniform elevations, ~2 px azimuth
    step, dropouts, range noise, no return beyond LIDAR_MAX_RANGE or on sky."""
    depth = geo.depth
    height, width = depth.shape
    n_beams = max(8, height // 4)
    el = np.linspace(np.arctan(-(height - geo.cy) / geo.f), np.deg2rad(10.0), n_beams)
    rows = np.round(geo.cy - geo.f * np.tan(el) - 0.5)
    rows = np.unique(np.clip(rows, 0, height - 1)).astype(int)
    step = 2 if width >= 160 else 1
    mask = np.zeros((height, width), bool)
    phase = rng.integers(0, step, len(rows))
    for r, ph in zip(rows, phase):  # one slice assignment per scan line
        mask[r, ph::step] = True
    mask &= rng.random((height, width)) > 0.08
    noise = 1 + 0.003 * rng.standard_normal((height, width), dtype=np.float32)  # ~ +-3 mm/m
    mask &= (depth > 0) & (geo.rng_m * noise <= LIDAR_MAX_RANGE)
    return np.where(mask, depth * noise, 0).astype(np.float32)
