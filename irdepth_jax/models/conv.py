"""Convolutions for XLA:CPU: `nn.Conv` with the same parameters, init and forward, and a
weight gradient computed in row blocks.

XLA:CPU differentiates a convolution's kernel as one convolution whose window is the whole
image (batch as the feature axis), after transposing both operands to that layout; its
library kernels run it 3-5x slower than the forward pass (measured, 2 x 518 x 518 x 32 -> 32
channels, 3x3: forward 62 ms, kernel gradient 330 ms; PyTorch's oneDNN about 4x faster). Here
the kernel gradient of a stride-1 k x k convolution is a loop over blocks of `rows` output rows:
each block's k*k shifted input windows are concatenated along the channels (an im2col of a few
rows, which stays in cache) and contracted with the block's output gradient in one matmul,
(k*k*C_in, pixels) @ (pixels, C_out), summed over the blocks: 110 ms for the same layer.

A 1x1 convolution is a matmul over the channel axis (faster than XLA:CPU's convolution in both
directions, and its kernel gradient is a matmul too). The input gradient of every convolution is
XLA's own. Off CPU (GPU / TPU, whose convolution libraries are fast both ways) and on small
inputs, `conv_general_dilated` is `lax.conv_general_dilated`.
"""

from __future__ import annotations

import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
from jax import lax

BLOCK_PIXELS = 2048
"""Output pixels (batch x rows x width) per block of the kernel-gradient loop: its im2col block
(k*k*C_in x BLOCK_PIXELS floats, 2.4 MB for 3x3 x 32 channels) stays in cache. Measured on a 2-core
x86 CPU for 2-4 images of 256x320 to 518x518 with 32-64 channels: 1000-2600 pixels per block
are within 10 % of each other, single rows of 300 pixels 1.5-2x slower."""

MIN_LOOP_PIXELS = 16384
"""Below this many output pixels (batch x height x width) the kernel gradient is XLA's: the loop
would have few blocks and its set-up would not pay."""

_NHWC = ("NHWC", "HWIO", "NHWC")


def _is_nhwc(dimension_numbers) -> bool:
    if dimension_numbers is None:
        return False
    if isinstance(dimension_numbers, lax.ConvDimensionNumbers):
        return dimension_numbers == lax.conv_dimension_numbers((1, 1, 1, 1), (1, 1, 1, 1), _NHWC)
    return tuple(dimension_numbers) == _NHWC


def conv_general_dilated(lhs, rhs, window_strides, padding, lhs_dilation=None, rhs_dilation=None,
                         dimension_numbers=None, feature_group_count=1, precision=None):
    """`lax.conv_general_dilated` with the same arguments (what `nn.Conv` calls), computed as
    the module docstring says for 2-D NHWC / HWIO convolutions on CPU; any other case is
    `lax.conv_general_dilated` itself.

    lhs: (B, H, W, C_in); rhs: (kh, kw, C_in, C_out) -> (B, H', W', C_out).
    """
    kwargs = dict(lhs_dilation=lhs_dilation, rhs_dilation=rhs_dilation,
                  dimension_numbers=dimension_numbers, feature_group_count=feature_group_count,
                  precision=precision)
    plain = (lhs.ndim != 4 or not _is_nhwc(dimension_numbers) or feature_group_count != 1
             or any(d != 1 for d in (lhs_dilation or ()) + (rhs_dilation or ()))
             or jax.default_backend() != "cpu")
    if plain:
        return lax.conv_general_dilated(lhs, rhs, window_strides, padding, **kwargs)
    kh, kw = rhs.shape[:2]
    if isinstance(padding, str):
        padding = lax.padtype_to_pads(lhs.shape[1:3], (kh, kw), window_strides, padding)
    pads = tuple(tuple(p) for p in padding)
    if (kh, kw) == (1, 1) and tuple(window_strides) == (1, 1) and pads == ((0, 0), (0, 0)):
        return jnp.einsum("bhwc,cd->bhwd", lhs, rhs[0, 0], precision=precision)
    out_pixels = lhs.shape[0] * (lhs.shape[1] + sum(pads[0]) - kh + 1) * (lhs.shape[2] + sum(pads[1]) - kw + 1)
    if tuple(window_strides) != (1, 1) or out_pixels < MIN_LOOP_PIXELS:
        return lax.conv_general_dilated(lhs, rhs, window_strides, padding, **kwargs)
    return _conv_stride1(lhs, rhs, pads, precision)


def _plain_conv(x, kernel, pads, precision):
    return lax.conv_general_dilated(x, kernel, (1, 1), pads, dimension_numbers=_NHWC,
                                    precision=precision)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2, 3))
def _conv_stride1(x, kernel, pads, precision):
    return _plain_conv(x, kernel, pads, precision)


def _conv_stride1_fwd(x, kernel, pads, precision):
    return _plain_conv(x, kernel, pads, precision), (x, kernel)


def _conv_stride1_bwd(pads, precision, residuals, g):
    x, kernel = residuals
    dx = jax.vjp(lambda x: _plain_conv(x, kernel, pads, precision), x)[1](g)[0]
    return dx, kernel_gradient(x, g, kernel.shape[:2], pads).astype(kernel.dtype)


_conv_stride1.defvjp(_conv_stride1_fwd, _conv_stride1_bwd)


def kernel_gradient(x, g, kernel_size: tuple[int, int], pads, block_pixels: int = BLOCK_PIXELS):
    """Gradient of a stride-1 convolution's kernel, in blocks of output rows (module docstring).

    Args:
      x: (B, H, W, C_in) the convolution's input.
      g: (B, H', W', C_out) the gradient of its output, H' = H + pad_h - kh + 1 (W' likewise).
      kernel_size: (kh, kw).
      pads: ((top, bottom), (left, right)) zero padding of x.
      block_pixels: output pixels per block (rounded to whole rows, at least one).
    Returns:
      (kh, kw, C_in, C_out) float32: sum over b, i, j of x_pad[b, i + p, j + q, :] outer g[b, i, j, :].
    """
    kh, kw = kernel_size
    b, out_h, out_w, c_out = g.shape
    c_in = x.shape[-1]
    rows = max(1, round(block_pixels / (b * out_w)))
    blocks = -(-out_h // rows)
    extra = blocks * rows - out_h  # zero rows: they add nothing to the sum
    x_pad = jnp.pad(x, ((0, 0), (pads[0][0], pads[0][1] + extra), pads[1], (0, 0)))
    g_pad = jnp.pad(g, ((0, 0), (0, extra), (0, 0), (0, 0)))

    def block(i, total):
        top = i * rows
        window = lax.dynamic_slice_in_dim(x_pad, top, rows + kh - 1, axis=1)
        patches = jnp.concatenate(
            [window[:, p:p + rows, q:q + out_w] for p in range(kh) for q in range(kw)], axis=-1)
        g_rows = lax.dynamic_slice_in_dim(g_pad, top, rows, axis=1)
        return total + jnp.einsum("bhwk,bhwd->kd", patches, g_rows,
                                  preferred_element_type=jnp.float32)

    total = lax.fori_loop(0, blocks, block, jnp.zeros((kh * kw * c_in, c_out), jnp.float32))
    return total.reshape(kh, kw, c_in, c_out)


class Conv(nn.Conv):
    """`flax.linen.Conv` (same attributes, parameters and initialisation) computed by
    `conv_general_dilated` above."""

    conv_general_dilated: object = staticmethod(conv_general_dilated)


def upsample_by_matmul(x, kernel):
    """A transposed convolution whose stride equals its kernel: each input pixel becomes a k x k
    block, out[b, k i + p, k j + q, o] = sum_c x[b, i, j, c] kernel[p, q, c, o].

    x: (B, h, w, C_in); kernel: (k, k, C_in, C_out) -> (B, k h, k w, C_out). One matmul and a
    depth-to-space reshape: on XLA:CPU faster than the transposed convolution both ways (input
    128x160x64 -> 32 channels: forward 4 vs 7 ms, kernel gradient 5 vs 270 ms).
    """
    k = kernel.shape[0]
    b, h, w, c = x.shape
    features = kernel.shape[-1]
    y = x.reshape(-1, c) @ kernel.transpose(2, 0, 1, 3).reshape(c, k * k * features)
    y = y.reshape(b, h, w, k, k, features).transpose(0, 1, 3, 2, 4, 5)
    return y.reshape(b, k * h, k * w, features)


class ConvTranspose(nn.Module):
    """`flax.linen.ConvTranspose(features, (k, k), strides=(k, k), padding='VALID')` (same
    parameters, initialisation and values) by `upsample_by_matmul`: (B, h, w, C) ->
    (B, k h, k w, features). Flax's kernel is applied spatially flipped (lax.conv_transpose
    without transpose_kernel), so the matmul takes kernel[::-1, ::-1]."""

    features: int
    factor: int
    use_bias: bool = True
    dtype: object = None

    @nn.compact
    def __call__(self, x):
        k = self.factor
        kernel = self.param("kernel", nn.initializers.lecun_normal(), (k, k, x.shape[-1], self.features))
        bias = self.param("bias", nn.initializers.zeros_init(), (self.features,)) if self.use_bias else None
        x, kernel, bias = nn.dtypes.promote_dtype(x, kernel, bias, dtype=self.dtype)
        y = upsample_by_matmul(x, kernel[::-1, ::-1])
        return y if bias is None else y + bias
