"""GCM (gradient computation module) of the paper, section 3.2.3, and its rescaling.

    Gx(x, y) = |I(x+1, y) - I(x, y)|,   Gy(x, y) = |I(x, y+1) - I(x, y)|,   G = Gx + Gy

x runs along the width (columns), y along the height (rows). The output has the input's size:
the forward difference does not exist on the last column (for Gx) and the last row (for Gy),
and is taken as 0 there, i.e. the image is edge-replicated by one pixel.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def _spatial_axes(ndim: int, where: str) -> tuple[int, int]:
    if ndim == 2:
        return 0, 1
    if ndim in (3, 4):
        return ndim - 3, ndim - 2
    raise ValueError(f"{where}: expected HW, HWC or NHWC (B, H, W, C) input, got {ndim} dims")


def _forward_abs_diff(img, axis: int):
    """|I[i+1] - I[i]| along `axis`, with 0 for the last index (same shape as `img`)."""
    n = img.shape[axis]
    diff = jnp.abs(
        jax.lax.slice_in_dim(img, 1, n, axis=axis) - jax.lax.slice_in_dim(img, 0, n - 1, axis=axis)
    )
    pad = [(0, 0)] * img.ndim
    pad[axis] = (0, 1)
    return jnp.pad(diff, pad)


def gradient_magnitude(img):
    """GCM map G = Gx + Gy of an image, same shape. Jit-able and differentiable.

    Args:
      img: float array (H, W), (H, W, C) or (B, H, W, C). Each channel is processed on its own.

    Returns:
      Array of `img`'s shape and dtype, >= 0; the last column's Gx and the last row's Gy are 0.

    Gradients: |d| is not differentiable at d = 0 (flat regions); JAX uses the subgradient 1
    there, so gradients stay finite (never NaN); each pixel enters at most 4 differences.
    """
    img = jnp.asarray(img)
    if not jnp.issubdtype(img.dtype, jnp.floating):
        raise ValueError(
            "gradient_magnitude: expected a float image (normalise raw counts first), "
            f"got {img.dtype}"
        )
    row_axis, col_axis = _spatial_axes(img.ndim, "gradient_magnitude")
    return _forward_abs_diff(img, col_axis) + _forward_abs_diff(img, row_axis)


def resize_gradient(g, size: tuple[int, int]):
    """Brings a GCM map (B, H, W, C) to a decoder scale (B, h, w, C).

    When H/h and W/w are integers (the UNet's case: 2, 4, 8, ...), average pooling over the
    factor x factor blocks: it keeps the mean edge strength per area and every edge contributes,
    where sub-sampling would drop thin edges. Otherwise `jax.image.resize` with linear
    interpolation (antialiased when shrinking).

    Args:
      g: array (B, H, W, C).
      size: target (h, w).

    Returns:
      Array (B, h, w, C) of `g`'s dtype.
    """
    if g.ndim != 4:
        raise ValueError(f"resize_gradient: expected (B, H, W, C), got shape {g.shape}")
    b, height, width, c = g.shape
    h, w = size
    if (h, w) == (height, width):
        return g
    if height % h == 0 and width % w == 0:
        fh, fw = height // h, width // w
        return g.reshape(b, h, fh, w, fw, c).mean(axis=(2, 4))
    return jax.image.resize(g, (b, h, w, c), method="linear")
