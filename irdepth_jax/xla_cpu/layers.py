"""The model layers re-implemented for XLA:CPU training, installed by a Flax method interceptor
(`intercept`), so that the models themselves are written with plain Flax layers.

Under the interceptor, on the modules of every model traced inside it:

* `flax.linen.Conv` and `flax.linen.Dense` compute with `conv.conv_general_dilated` and
  `conv.dot_general` (same parameters, initialisation and forward values; the kernel gradients
  as matmuls);
* a `flax.linen.ConvTranspose` whose stride equals its kernel (VALID, no dilation) is one matmul
  and a depth-to-space reshape (`UpsampleByMatmul`), whose kernel gradient is a matmul too
  (XLA:CPU's transposed-convolution gradient was far slower);
* the RGG attention's input (the up block's upsampled features) is made an array of its own
  (`conv.materialize`): XLA:CPU otherwise fused the up block's transpose, BatchNorm and ReLU
  into each of its consumers, and the backward of its gradient map recomputed them per
  neighbour;
* each DINOv2 block's input gradient is computed whole before it is used (`gradient_fence`):
  XLA:CPU otherwise fused the residual stream's gradient into every block's weight-gradient
  fusions, recomputing the later blocks' chain in each.

Each replacement computes the same values as the module it stands for (up to float rounding);
docs/benchmarks.md has the measurements.
"""

from __future__ import annotations

import functools

import flax.linen as nn
import jax

from irdepth_jax.models.dinov2 import Block
from irdepth_jax.models.rgg import RGG
from irdepth_jax.models.unet import upsample_by_matmul
from irdepth_jax.xla_cpu import conv


@jax.custom_vjp
def gradient_fence(x):
    """Identity whose gradient is computed whole (`conv.materialize`) before it is used."""
    return x


gradient_fence.defvjp(lambda x: (x, None), lambda _, g: (conv.materialize(g),))


class UpsampleByMatmul(nn.Module):
    """`flax.linen.ConvTranspose(features, (k, k), strides=(k, k), padding='VALID')` (same
    parameters, initialisation and values) by `upsample_by_matmul`: (B, h, w, C) ->
    (B, k h, k w, features). Flax's kernel is applied spatially flipped (lax.conv_transpose
    without transpose_kernel), so the matmul takes kernel[::-1, ::-1]."""

    like: nn.ConvTranspose

    @nn.compact
    def __call__(self, x):
        m = self.like
        kernel_shape = (*m.kernel_size, x.shape[-1], m.features)
        kernel = self.param("kernel", m.kernel_init, kernel_shape, m.param_dtype)
        bias = self.param("bias", m.bias_init, (m.features,), m.param_dtype) if m.use_bias else None
        x, kernel, bias = m.promote_dtype(x, kernel, bias, dtype=m.dtype)
        y = upsample_by_matmul(x, kernel[::-1, ::-1])
        return y if bias is None else y + bias


def _is_upsampling(m: nn.ConvTranspose, x) -> bool:
    """Whether a ConvTranspose is a 2-D one whose stride equals its kernel (each input pixel a
    block of the output), with nothing `UpsampleByMatmul` does not do."""
    size = tuple(m.kernel_size) if not isinstance(m.kernel_size, int) else (m.kernel_size,)
    return (x.ndim == 4 and len(size) == 2 and size[0] == size[1] and m.strides is not None
            and tuple(m.strides) == size and m.padding == "VALID" and m.kernel_dilation is None
            and m.mask is None and not m.transpose_kernel and m.preferred_element_type is None)


def intercept(next_fun, args, kwargs, context, *, native: bool):
    """A `flax.linen.intercept_methods` interceptor making the replacements of the module
    docstring; `native`: whether kernel gradients may take the C++ kernel (`native_conv`)."""
    m = context.module
    if context.method_name != "__call__":
        return next_fun(*args, **kwargs)
    kind = type(m)
    if kind is nn.Conv and m.conv_general_dilated is None and m.conv_general_dilated_cls is None:
        fast = functools.partial(conv.conv_general_dilated, native=native)
        return m.clone(parent=m.scope, conv_general_dilated=fast)(*args, **kwargs)
    if kind is nn.Dense and m.dot_general is None and m.dot_general_cls is None:
        return m.clone(parent=m.scope, dot_general=functools.partial(conv.dot_general, native=native))(*args, **kwargs)
    if kind is nn.ConvTranspose and len(args) == 1 and not kwargs and _is_upsampling(m, args[0]):
        return UpsampleByMatmul(m, parent=m.scope)(*args)
    if isinstance(m, RGG):
        return next_fun(conv.materialize(args[0]), *args[1:], **kwargs)
    if isinstance(m, Block):
        return next_fun(gradient_fence(args[0]), *args[1:], **kwargs)
    return next_fun(*args, **kwargs)
