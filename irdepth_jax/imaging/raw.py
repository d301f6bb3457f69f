"""Raw LWIR frames: validation (host side) and normalisation to [0, 1] (jit-able).

A raw frame holds sensor counts of 14 bits (0..2^14-1, most LWIR cores) or 16 bits (0..2^16-1,
radiometric cameras that use the full range), stored as uint16 or as a wider integer type; the
run's bit depth is `DataConfig.raw_bits`. Two normalisations are offered (`UNetConfig.raw_scale`):

* ``fixed``: counts / (2^bits - 1). Keeps absolute radiometry (a hot object is bright in every
  frame), but a typical scene uses only a few hundred counts of the range, so the input is dim.
* ``percentile``: per image, clip to the ``low``/``high`` percentiles and rescale to [0, 1]
  (the "linear with tail rejection" camera pipeline). Full contrast, relative radiometry.
"""

from __future__ import annotations

import typing

import jax.numpy as jnp
import numpy as np

from irdepth_jax.config_schema import RawBits, RawScale

RAW_MAX = 2**14 - 1
"""Largest count a 14-bit sensor produces."""

BIT_DEPTHS: tuple[int, ...] = tuple(b for b in typing.get_args(RawBits) if isinstance(b, int))
"""Bit depths of raw counts the model takes (`DataConfig.raw_bits`, once resolved)."""

_MODES = typing.get_args(RawScale)


def _dtype_error(dtype, bits: int = 14) -> str | None:
    """Why an array of `dtype` cannot be a raw frame of `bits` bits (None if it can)."""
    dtype = np.dtype(dtype)
    expected = f"expected a raw {bits}-bit frame (uint16, values 0..{2**bits - 1})"
    if dtype == np.uint8 or dtype == np.int8:
        return f"{expected}, got {dtype}: is this an 8-bit image?"
    if dtype == np.bool_:
        return f"{expected}, got bool (a mask?)"
    if not np.issubdtype(dtype, np.integer):
        return (f"{expected}, got {dtype}: a float array is already normalised or converted; "
                "pass the integer counts")
    return None


def check_raw(raw, bits: int = 14) -> None:
    """Validates a raw frame or batch of `bits`-bit counts on the host (numpy); returns None.

    Args:
      raw: integer array of any shape (H, W), (B, H, W) or (B, H, W, 1) with counts in
        0..2^bits-1. Must be concrete (not a tracer): call it on data before it enters jit.
      bits: 14 or 16.

    Raises:
      ValueError: for 8-bit, bool or float input (NaN included), negative counts, counts over
        `bits` bits, or an empty array; the message says what was found (and, for 14-bit
        counts exceeded, how to declare 16-bit counts).
    """
    if bits not in BIT_DEPTHS:
        raise ValueError(f"raw bit depth {bits!r}: expected one of {BIT_DEPTHS}")
    arr = np.asarray(raw)
    top = 2**bits - 1
    if arr.dtype.kind == "f" and np.isnan(arr).any():
        raise ValueError(f"expected a raw {bits}-bit frame (uint16, values 0..{top}), got "
                         f"{arr.dtype} containing NaN")
    reason = _dtype_error(arr.dtype, bits)
    if reason:
        raise ValueError(reason)
    if arr.size == 0:
        raise ValueError(f"expected a raw {bits}-bit frame, got an empty array of shape "
                         f"{arr.shape}")
    low, high = int(arr.min()), int(arr.max())
    if low < 0:
        raise ValueError(f"raw counts must be >= 0, got a minimum of {low}")
    if high > top:
        fix = (" (a 16-bit camera? declare it: data.raw_bits=16 for training, --raw-bits 16 for "
               "predict)" if bits == 14 else "")
        raise ValueError(f"raw counts exceed {bits} bits: maximum {high} > {top}{fix}")


def normalize_raw(raw, mode: str = "fixed", low: float = 1.0, high: float = 99.0,
                  bits: int = 14):
    """Raw counts -> float32 in [0, 1], same shape. Jit-able (`mode`, `bits` static).

    Args:
      raw: integer array (H, W), (B, H, W) or (B, H, W, C) (NHWC). Integer dtypes only; the
        dtype is checked statically, so uint8 / float input raises even under jit.
      mode: ``fixed`` = counts / (2^bits - 1), clipped to [0, 1]; ``percentile`` = per image
        clip to the `low` / `high` percentiles (over H, W; per channel for NHWC), then rescale.
        A constant image maps to zeros.
      low, high: percentiles in [0, 100] for ``percentile`` mode.
      bits: bit depth of the counts (14 or 16), the full scale of ``fixed`` mode.

    Returns:
      float32 array with the shape of `raw`, values in [0, 1].
    """
    raw = jnp.asarray(raw)
    reason = _dtype_error(raw.dtype, bits)
    if reason:
        raise ValueError(f"normalize_raw: {reason}")
    if mode not in _MODES:
        raise ValueError(f"normalize_raw: unknown mode {mode!r}; choose one of {_MODES}")
    x = raw.astype(jnp.float32)
    if mode == "fixed":
        return jnp.clip(x / (2**int(bits) - 1), 0.0, 1.0)
    if not 0.0 <= low < high <= 100.0:
        raise ValueError(f"normalize_raw: need 0 <= low < high <= 100, got low={low}, high={high}")
    if x.ndim < 2:
        raise ValueError(f"normalize_raw: expected (H, W), (B, H, W) or NHWC, got shape {x.shape}")
    axes = (1, 2) if x.ndim == 4 else (-2, -1)
    lo = jnp.percentile(x, low, axis=axes, keepdims=True)
    hi = jnp.percentile(x, high, axis=axes, keepdims=True)
    span = hi - lo
    # Double where: the constant-frame branch must not divide by zero, even in the gradient.
    safe_span = jnp.where(span > 0, span, 1.0)
    return jnp.where(span > 0, jnp.clip((x - lo) / safe_span, 0.0, 1.0), 0.0)
