"""HSV composition of the MTSA-UNet outputs and the fixed HSV -> RGB transform (paper 3.3.2).

Hue = semantics (a hue per class), Saturation = gradient structure, Value = reconstructed texture.
"""

from __future__ import annotations

import math
import typing

import dm_pix
import jax
import jax.numpy as jnp

from irdepth_jax.config import CLASS_NAMES
from irdepth_jax.config_schema import HueMode

CLASS_HUES: tuple[float, ...] = (4 / 6, 0 / 6, 1 / 6, 5 / 6, 3 / 6, 2 / 6)
"""Hue in [0, 1) per class of `CLASS_NAMES` (sky, building, car, bicycle, road, tree).

Six hues 60 degrees apart, the most separated a 6-class palette can be: sky blue (240 deg),
building red (0), car yellow (60), bicycle magenta (300), road cyan (180), tree green (120).
"""

assert len(CLASS_HUES) == len(CLASS_NAMES)

_HUE_MODES = typing.get_args(HueMode)
_EPS = 1e-12


def class_hue(seg_logits, mode: str = "soft"):
    """Hue map from segmentation logits. Jit-able (`mode` static), differentiable in soft mode.

    Args:
      seg_logits: (B, H, W, C) logits, C = len(CLASS_HUES).
      mode: ``soft``: circular mean of the class hues weighted by the softmax probabilities,
        hue = atan2(sum_c p_c sin 2 pi h_c, sum_c p_c cos 2 pi h_c) / 2 pi mod 1; smooth, and a
        confident pixel gets its class hue. Where the weighted unit vectors cancel (e.g. equal
        probabilities), the hue is undefined: 0 is returned with a zero gradient.
        ``argmax``: the hue of the most probable class (not differentiable).
        ``constant``: hue 0 everywhere, whatever the logits (an image that carries no
        semantics, for a model whose segmentation branch was never trained).

    Returns:
      (B, H, W, 1) float32 hue in [0, 1).
    """
    if mode not in _HUE_MODES:
        raise ValueError(f"class_hue: unknown mode {mode!r}; choose one of {_HUE_MODES}")
    seg_logits = jnp.asarray(seg_logits)
    if seg_logits.shape[-1] != len(CLASS_HUES):
        raise ValueError(
            f"class_hue: seg_logits has {seg_logits.shape[-1]} classes in its last axis, "
            f"expected {len(CLASS_HUES)} ({', '.join(CLASS_NAMES)})"
        )
    hues = jnp.asarray(CLASS_HUES, jnp.float32)
    if mode == "constant":
        return jnp.zeros(seg_logits.shape[:-1] + (1,), jnp.float32)
    if mode == "argmax":
        return hues[jnp.argmax(seg_logits, axis=-1)][..., None]
    probs = jax.nn.softmax(seg_logits.astype(jnp.float32), axis=-1)
    angles = 2 * math.pi * hues
    x = probs @ jnp.cos(angles)
    y = probs @ jnp.sin(angles)
    defined = x * x + y * y > _EPS
    # Double where: atan2's gradient at (0, 0) is 0/0; feed it a safe point there instead.
    angle = jnp.arctan2(jnp.where(defined, y, 0.0), jnp.where(defined, x, 1.0))
    hue = jnp.where(defined, angle / (2 * math.pi), 0.0) % 1.0
    # `% 1.0` of a tiny negative number rounds up to exactly 1.0 in float32.
    return jnp.where(hue >= 1.0, 0.0, hue)[..., None]


def hsv_compose(hue, saturation, value):
    """Stacks the three maps into an HSV image. Jit-able and differentiable.

    Args:
      hue, saturation, value: arrays (..., 1) of one shape (e.g. (B, H, W, 1) as the UNet and
        `class_hue` return). Hue wraps (taken mod 1); saturation and value are clipped to [0, 1].

    Returns:
      (..., 3) HSV image with every channel in [0, 1].
    """
    maps = {"hue": hue, "saturation": saturation, "value": value}
    shapes = {name: jnp.shape(m) for name, m in maps.items()}
    if any(len(s) == 0 or s[-1] != 1 for s in shapes.values()) or len(set(shapes.values())) != 1:
        raise ValueError(f"hsv_compose: expected three (..., 1) maps of one shape, got {shapes}")
    return jnp.concatenate(
        [jnp.asarray(hue) % 1.0, jnp.clip(saturation, 0.0, 1.0), jnp.clip(value, 0.0, 1.0)],
        axis=-1,
    )


def hsv_to_rgb(hsv):
    """HSV (..., 3) in [0, 1] -> RGB (..., 3) in [0, 1]. Jit-able, finite gradients.

    Hue is a fraction of the circle (OpenCV's float HSV2RGB takes it in degrees, H * 360). This
    is dm_pix.hsv_to_rgb: checked to agree with cv2.cvtColor(..., COLOR_HSV2RGB) to < 1e-6 and to
    have finite gradients everywhere (including the sector borders), so we do not re-write it.
    """
    hsv = jnp.asarray(hsv)
    if hsv.ndim == 0 or hsv.shape[-1] != 3:
        raise ValueError(f"hsv_to_rgb: expected (..., 3) HSV input, got shape {hsv.shape}")
    return dm_pix.hsv_to_rgb(hsv)
