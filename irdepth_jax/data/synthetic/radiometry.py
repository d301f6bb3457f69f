"""LWIR radiometry and the thermal camera: temperatures -> radiance -> raw 14-bit counts.

Each pixel gets a temperature and an emissivity from its material and the condition (day:
sun-heated road and sun-facing walls, thermal shadows; dusk: low sun, road keeps its heat;
night: warm engines, tyres, lit windows and lamps), plus the reflected sky (cold at the zenith,
near air temperature at the horizon), mixed in radiance (8-14 um band radiance from Planck's
law), attenuated by the atmosphere with distance, then turned into counts with a random global
gain/offset, fixed-pattern noise (per-pixel gain and offset, column and row offsets: one pattern
per image size, like a single camera), radial vignetting and narcissus, temporal noise (NETD
~50 mK) and 14-bit quantisation; the 8-bit frame is `imaging.tonemap.camera_like` of the counts.
"""

from __future__ import annotations

import functools

import numpy as np

from irdepth_jax.data.synthetic.caster import NY, Geometry
from irdepth_jax.data.synthetic.materials import COND, RIDER, material_tables
from irdepth_jax.data.synthetic.surface import Surface
from irdepth_jax.imaging.raw import RAW_MAX
from irdepth_jax.imaging.tonemap import camera_like


def render_lwir(rng: np.random.Generator, condition: str, t_air: float, geo: Geometry,
                surf: Surface, toff: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The thermal frame of a scene.

    Args:
      rng: the scene's generator (draws the sky, atmosphere, sensor and noise parameters).
      condition: one of CONDITIONS; t_air: air temperature (K).
      geo, surf: (H, W) geometry and surface attributes.
      toff: (N,) float32 temperature offset (K) of each object (`Scene.table()['toff']`).

    Returns:
      (raw14 (H, W) uint16 counts in 0..RAW_MAX, ir8 (H, W) uint8 `camera_like(raw14)`).
    """
    temp, eps = _temperature_emissivity(condition, t_air, geo, surf, toff)
    raw14 = _sensor_counts(rng, _sensor_radiance(rng, condition, t_air, geo, temp, eps))
    return raw14, camera_like(raw14)


def _temperature_emissivity(condition, t_air, geo, surf, toff):
    """(H, W) float32 surface temperature (K) and emissivity of every pixel."""
    m = material_tables(condition)
    mat, obj = surf.mat, geo.obj
    sunlit = np.where(surf.glass, 0.0, surf.lambert)
    temp = (t_air + m["base"][mat] + m["sun"][mat] * sunlit + m["tex"][mat] * surf.tex + toff[obj]
            + 12.0 * surf.engine + 35.0 * surf.exhaust
            + (7.0 * surf.lit if condition != "day" else 0.0))
    temp[geo.kind == RIDER] = 303.0 - 3.0 * (condition == "night")  # clothed people
    eps = m["eps"][mat]
    eps = np.where(surf.marking, 0.9, np.where(surf.window | surf.glass, 0.84, eps))
    return temp, eps


def _sensor_radiance(rng, condition, t_air, geo, temp, eps):
    """(H, W) float32 band radiance reaching the camera, in `_band` units.

    Emission plus reflected sky (horizontal faces see the zenith, vertical ones the horizon and
    the street), attenuated by the atmosphere; the sky's own radiance on sky pixels.
    """
    sky_dt = rng.uniform(*COND[condition]["sky_dt"])
    t_sky = t_air - sky_dt * (1 - np.exp(-np.maximum(geo.elev, 0) / 0.15))
    x_refl = np.where(geo.nrm == NY, _band(t_air - sky_dt), _band(t_air - 0.2 * sky_dt))
    x_obj = eps * _band(temp) + (1 - eps) * x_refl
    tau = np.exp(-geo.rng_m / rng.uniform(300.0, 1500.0))
    return np.where(geo.sky, _band(t_sky), tau * x_obj + (1 - tau) * _band(t_air))


def _sensor_counts(rng, signal):
    """(H, W) uint16 raw counts of an (H, W) signal: gain, offset, FPN, vignetting, noise."""
    height, width = signal.shape
    fp_gain, fp_off, r2 = _fixed_pattern(height, width)
    resp = rng.uniform(34.0, 46.0)  # counts per kelvin near 20 C
    level = rng.uniform(6800.0, 8200.0)
    fpn = rng.uniform(0.7, 1.3)
    counts = (level + resp * signal * (1 + fpn * (fp_gain - 1)) * (1 - 0.08 * r2)
              + fpn * fp_off + rng.uniform(-150.0, 50.0) * r2
              + resp * 0.05 * rng.standard_normal((height, width), dtype=np.float32))
    return np.clip(np.rint(counts), 0, RAW_MAX).astype(np.uint16)


@functools.lru_cache(maxsize=1)
def _band_table() -> tuple[np.ndarray, np.ndarray]:
    """8-14 um band radiance as 'equivalent kelvin around 20 C': affine in radiance.

    Returns (T, X), each (701,) float32: X(T) = (L(T) - L(293.15)) / dL/dT(293.15), so mixing
    X values with weights that sum to one is mixing radiances.
    """
    h, c, k = 6.62607015e-34, 2.99792458e8, 1.380649e-23
    lam = np.linspace(8e-6, 14e-6, 241)[:, None]
    temps = np.linspace(150.0, 500.0, 701)
    rad = (2 * h * c**2 / lam**5 / np.expm1(h * c / (lam * k * temps[None]))).sum(0)
    ref = np.interp(293.15, temps, rad)
    slope = np.interp(293.15, temps, np.gradient(rad, temps))
    return temps.astype(np.float32), ((rad - ref) / slope).astype(np.float32)


def _band(temp_k):
    """Band radiance X (float32, temp_k's shape) of temperatures temp_k (K), see `_band_table`."""
    temps, x = _band_table()
    return np.interp(temp_k, temps, x).astype(np.float32)


@functools.lru_cache(maxsize=8)
def _fixed_pattern(height: int, width: int):
    """Per-camera fixed-pattern noise, each (H, W) float32: (gain (relative), offset (counts),
    r2 (squared normalised radius, for vignetting and narcissus))."""
    rng = np.random.default_rng(0x1A2B)
    gain = 1.0 + 0.02 * rng.standard_normal((height, width))
    offset = (8.0 * rng.standard_normal((height, width)) + 6.0 * rng.standard_normal((1, width))
              + 3.0 * rng.standard_normal((height, 1)))
    yy, xx = np.mgrid[0:height, 0:width]
    r2 = ((yy - height / 2) / (height / 2)) ** 2 * 0.5 + ((xx - width / 2) / (width / 2)) ** 2 * 0.5
    return gain.astype(np.float32), offset.astype(np.float32), r2.astype(np.float32)
