"""The whole model as pure functions: raw counts -> MTSA-UNet -> HSV -> RGB -> depth.

    raw (B, H, W) uint16 counts of cfg.data.raw_bits (14 or 16) bits
      -> unet_input                  the one normalisation of raw counts, (B, H, W) in [0, 1]
      -> MTSAUNet (eval mode)       recon, saturation (B, H, W, 1); seg_logits (B, H, W, C)
      -> unet_to_hsv                 H = class hue of seg, S = saturation, V = recon
      -> hsv_to_rgb                  pseudo-RGB (B, H, W, 3) in [0, 1]
      -> network_input               resize to (cfg.depth.input_height, input_width), ImageNet norm
      -> DepthAnythingV2             depth (B, h, w)
      -> resize_depth                depth (B, H, W) in metres

`run_pipeline` (jitted, `cfg` static) is the one path from raw counts to depth: `irdepth eval`,
`irdepth predict`, the figures and `irdepth export` (`raw_to_depth`) call it, and Stage II's
loss its function unjitted (`pipeline_outputs`, traced inside the training step's own
context), so what is trained is what is evaluated, predicted and exported.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp

from irdepth_jax.config import SKY_CLASS, STAGE1_IMAGES, Config, resolved_raw_bits
from irdepth_jax.imaging.color import class_hue, hsv_compose, hsv_to_rgb
from irdepth_jax.imaging.raw import normalize_raw
from irdepth_jax.models.depth_anything import (
    DepthAnythingConfig,
    DepthAnythingV2,
    depth_anything_config,
    network_input,
    resize_depth,
)
from irdepth_jax.models.dinov2 import attention_implementation
from irdepth_jax.models.unet import MTSAUNet


def depth_model_config(cfg: Config) -> DepthAnythingConfig:
    """The Depth Anything V2 architecture `cfg.depth` asks for (encoder preset + head/numerics)."""
    d = cfg.depth
    return depth_anything_config(d.encoder, metric=d.metric, max_depth=d.max_depth,
                                 dtype=d.dtype, remat=d.remat)


def attention_kernel(cfg: Config) -> str:
    """The attention kernel `cfg`'s depth network runs on the default backend
    (`dinov2.attention_implementation` of its 'auto': 'cudnn' for a bfloat16 model on a GPU,
    a custom call that `jax.export` cannot serialise)."""
    da = depth_model_config(cfg)
    return attention_implementation(da.attention, jax.default_backend(), da.dtype)


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


def depth_from_rgb(da_params: Any, rgb: jax.Array, cfg: Config) -> jax.Array:
    """Depth Anything V2 on an RGB image (B, H, W, 3) in [0, 1] -> depth (B, H, W) (metres)."""
    size = (cfg.depth.input_height, cfg.depth.input_width)
    depth = DepthAnythingV2(depth_model_config(cfg)).apply({"params": da_params},
                                                           network_input(rgb, size))
    return resize_depth(depth, rgb.shape[1:3])


def pipeline_outputs(unet_vars: dict | None, da_params: Any, raw: jax.Array | None, cfg: Config,
                     image: jax.Array | None = None, brightness: jax.Array | None = None
                     ) -> dict[str, jax.Array | None]:
    """The paper's pipeline on a batch of frames (`run_pipeline` is this function jitted).

    Args:
      unet_vars: Stage I ``{'params', 'batch_stats'}`` (frozen: no gradient reaches them), or
        None for a Stage II model without Stage I (tone-mapping / visible baselines).
      da_params: Depth Anything V2 params (differentiable: Stage II's loss calls this), or None
        for a Stage I model (no depth).
      raw: (B, H, W) uint16 raw counts of `cfg.data.raw_bits` bits (None without a UNet).
      cfg: the run's config; `stage2.preprocessing` picks the depth network's input image.
      image: (B, H, W, 3) uint8 input image of a non-HSV model (a tone-mapping baseline made on
        the host, `data.source.host_image`, or a visible frame); unused by HSV models. For
        'blank' every frame's image must be the same (else the depth is NaN).
      brightness: optional (B,) brightness-augmentation factors (training; see `unet_input`).
    Returns:
      dict: ``depth`` (B, H, W) float32 metres (None without `da_params`); ``rgb`` (B, H, W, 3)
      the depth network's input image in [0, 1] (the pseudo-RGB for HSV models, V as grey for
      'value'); with a UNet
      also ``hsv`` (B, H, W, 3) in [0, 1], ``seg`` (B, H, W) int32 classes and ``sky``
      (B, H, W) bool (argmax == sky), else None.
    """
    hsv = seg = sky = None
    if unet_vars is not None:
        outputs = unet_outputs(unet_vars, raw, cfg, brightness)
        hsv = unet_to_hsv(outputs, cfg.stage2.hue_mode)
        seg = jnp.argmax(outputs["seg_logits"], axis=-1).astype(jnp.int32)
        sky = seg == SKY_CLASS
    if cfg.stage2.preprocessing in STAGE1_IMAGES:
        if hsv is None:
            raise ValueError(f"stage2.preprocessing={cfg.stage2.preprocessing} needs the Stage I "
                             "model (unet_vars)")
        rgb = hsv_to_rgb(hsv) if cfg.stage2.preprocessing == "hsv" else jnp.repeat(hsv[..., 2:], 3, -1)
    elif image is not None:
        rgb = image.astype(jnp.float32) / 255.0
    else:
        raise ValueError(f"stage2.preprocessing={cfg.stage2.preprocessing}: the input image is "
                         "made on the host; pass it as `image` (B, H, W, 3) uint8")
    rgb = jax.lax.stop_gradient(rgb)
    if da_params is None:
        depth = None
    elif cfg.stage2.preprocessing == "blank":
        # Every frame's input is the same grey image, so every frame gets the same map: the
        # network runs once (the blank control trains batch-size times faster) and the map is
        # repeated, whose gradient sums the frames' as the full batch's would. An image that is
        # not one constant image gives NaN (the training's finiteness check stops) rather than
        # a wrong map.
        one = jnp.broadcast_to(depth_from_rgb(da_params, rgb[:1], cfg), rgb.shape[:3])
        depth = jnp.where(jnp.all(rgb == rgb[:1]), one, jnp.nan)
    else:
        depth = depth_from_rgb(da_params, rgb, cfg)
    return {"depth": depth, "rgb": rgb, "hsv": hsv, "seg": seg, "sky": sky}


run_pipeline = jax.jit(pipeline_outputs, static_argnames=("cfg",))
"""`pipeline_outputs` jitted (`cfg` static): the one inference path."""


@functools.partial(jax.jit, static_argnames=("cfg",))
def raw_to_depth(unet_vars: dict, da_params: Any, raw: jax.Array, cfg: Config) -> jax.Array:
    """Depth (B, H, W) float32 metres of raw frames (B, H, W) uint16: `run_pipeline`'s depth of
    an HSV model, jitted (`cfg` static). The function `irdepth export` writes out."""
    return run_pipeline(unet_vars, da_params, raw, cfg)["depth"].astype(jnp.float32)
