"""The whole model as pure functions: raw 14-bit -> MTSA-UNet -> HSV -> RGB -> depth.

    raw (B, H, W) uint16
      -> MTSAUNet (eval mode)       recon, saturation (B, H, W, 1); seg_logits (B, H, W, C)
      -> unet_to_hsv                 H = class hue of seg, S = saturation, V = recon
      -> hsv_to_rgb                  pseudo-RGB (B, H, W, 3) in [0, 1]
      -> depth_input                 resize to (cfg.depth.input_height, input_width), ImageNet norm
      -> DepthAnythingV2             depth (B, h, w)
      -> resize_depth                depth (B, H, W) in metres

Every function is jit-able; the module objects are rebuilt from the (hashable) config, so
``jax.jit(predict_depth, static_argnums=3)`` works.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp

from irdepth_jax.config import SKY_CLASS, Config
from irdepth_jax.imaging.color import class_hue, hsv_compose, hsv_to_rgb
from irdepth_jax.imaging.raw import normalize_raw
from irdepth_jax.models.depth_anything import (IMAGENET_MEAN, IMAGENET_STD, DepthAnythingConfig,
                                               DepthAnythingV2, depth_anything_config,
                                               resize_depth)
from irdepth_jax.models.unet import MTSAUNet


def depth_model_config(cfg: Config) -> DepthAnythingConfig:
    """The Depth Anything V2 architecture `cfg.depth` asks for (encoder preset + head/numerics)."""
    d = cfg.depth
    return depth_anything_config(d.encoder, metric=d.metric, max_depth=d.max_depth,
                                 dtype=d.dtype, remat=d.remat)


def unet_input(raw: jax.Array, cfg: Config, brightness: jax.Array | None = None) -> jax.Array:
    """The MTSA-UNet's input image (B, H, W) float32 in [0, 1] from raw counts.

    Args:
      raw: (B, H, W) integer raw counts of `cfg.data.raw_bits` bits (or a float image in [0, 1],
        returned as is apart from `brightness`).
      cfg: the run's config: `unet.raw_scale` and `data.raw_bits` fix the normalisation.
      brightness: optional (B,) factors of the brightness augmentation (`data.augment`),
        applied after the normalisation, clip(factor * x, 0, 1): the same change the camera's
        8-bit image and the visible image get, which a change of the counts could not make
        (percentile normalisation undoes any gain on the counts).
    """
    if jnp.issubdtype(raw.dtype, jnp.integer):
        x = normalize_raw(raw, cfg.unet.raw_scale, bits=resolved_raw_bits(cfg))
    else:
        x = raw.astype(jnp.float32)
    if brightness is not None:
        x = jnp.clip(x * brightness.astype(jnp.float32).reshape((-1,) + (1,) * (x.ndim - 1)),
                     0.0, 1.0)
    return x


def resolved_raw_bits(cfg: Config) -> int:
    """`cfg.data.raw_bits` as 14 or 16; 'auto' must have been resolved from the data first."""
    bits = cfg.data.raw_bits
    if bits not in (14, 16):
        raise ValueError(f"data.raw_bits {bits!r}: expected 14 or 16 ('auto' is resolved from "
                         "the training frames when a run starts)")
    return int(bits)


def unet_outputs(unet_vars: dict, raw: jax.Array, cfg: Config,
                 brightness: jax.Array | None = None) -> dict[str, jax.Array]:
    """MTSA-UNet in eval mode (BatchNorm running averages), no gradient to its variables.

    Args:
      unet_vars: ``{'params', 'batch_stats'}``.
      raw: (B, H, W) uint16 raw counts (or a float image in [0, 1]); see `unet_input`.
      brightness: optional (B,) brightness-augmentation factors (see `unet_input`).
    Returns:
      the UNet's output dict (recon, seg_logits, saturation, input_gradient), each (B, H, W, *).
    """
    unet_vars = jax.lax.stop_gradient(unet_vars)
    return MTSAUNet(cfg.unet).apply(unet_vars, unet_input(raw, cfg, brightness), train=False)


def unet_to_hsv(outputs: dict[str, jax.Array], hue_mode: str = "soft") -> jax.Array:
    """HSV image (B, H, W, 3) in [0, 1]: Hue from seg_logits, S = saturation, V = recon."""
    return hsv_compose(class_hue(outputs["seg_logits"], hue_mode), outputs["saturation"],
                       outputs["recon"])


def hsv_pseudo_rgb(outputs: dict[str, jax.Array], hue_mode: str = "soft") -> jax.Array:
    """Pseudo-RGB (B, H, W, 3) in [0, 1] of the UNet outputs (fixed HSV -> RGB)."""
    return hsv_to_rgb(unet_to_hsv(outputs, hue_mode))


def sky_mask(seg_logits: jax.Array) -> jax.Array:
    """(B, H, W) bool: pixels whose most probable class is sky."""
    return jnp.argmax(seg_logits, axis=-1) == SKY_CLASS


def depth_input(rgb: jax.Array, size: tuple[int, int]) -> jax.Array:
    """RGB (B, H, W, 3) in [0, 1] -> (B, h, w, 3) ImageNet-normalised network input.

    Cubic resampling (jax.image, a = -0.5; the official pre-processing uses a = -0.75 and a
    size derived from 518: training and inference here share this one, so it is consistent).
    """
    b, h, w, c = rgb.shape
    if (h, w) != tuple(size):
        rgb = jax.image.resize(rgb, (b, size[0], size[1], c), "cubic", antialias=False)
    return (rgb - jnp.asarray(IMAGENET_MEAN)) / jnp.asarray(IMAGENET_STD)


def depth_from_rgb(da_params: Any, rgb: jax.Array, cfg: Config) -> jax.Array:
    """Depth Anything V2 on an RGB image (B, H, W, 3) in [0, 1] -> depth (B, H, W) (metres)."""
    size = (cfg.depth.input_height, cfg.depth.input_width)
    depth = DepthAnythingV2(depth_model_config(cfg)).apply({"params": da_params},
                                                           depth_input(rgb, size))
    return resize_depth(depth, rgb.shape[1:3])


def predict_depth(unet_vars: dict, da_params: Any, raw: jax.Array, cfg: Config
                  ) -> dict[str, jax.Array]:
    """The full pipeline of the paper on raw frames.

    Args:
      unet_vars: Stage I ``{'params', 'batch_stats'}``.
      da_params: Stage II Depth Anything V2 params.
      raw: (B, H, W) uint16 raw 14-bit counts.
      cfg: the run's config (static under jit).
    Returns:
      dict: depth (B, H, W) float32 metres, hsv and rgb (B, H, W, 3) in [0, 1],
      seg (B, H, W) int32 classes, sky (B, H, W) bool.
    """
    outputs = unet_outputs(unet_vars, raw, cfg)
    hsv = unet_to_hsv(outputs, cfg.stage2.hue_mode)
    rgb = hsv_to_rgb(hsv)
    return {"depth": depth_from_rgb(da_params, rgb, cfg), "hsv": hsv, "rgb": rgb,
            "seg": jnp.argmax(outputs["seg_logits"], axis=-1).astype(jnp.int32),
            "sky": sky_mask(outputs["seg_logits"])}


@functools.partial(jax.jit, static_argnums=3)
def raw_to_depth(unet_vars: dict, da_params: Any, raw: jax.Array, cfg: Config) -> jax.Array:
    """Depth (B, H, W) float32 metres of raw frames (B, H, W) uint16: `predict_depth`'s depth
    (raw -> MTSA-UNet -> HSV -> RGB -> Depth Anything V2), jitted (`cfg` static). The function
    `irdepth export` writes out; only the HSV pre-processing is a JAX function (the tone-mapping
    baselines run on the host)."""
    return predict_depth(unet_vars, da_params, raw, cfg)["depth"].astype(jnp.float32)
