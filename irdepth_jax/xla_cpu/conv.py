"""Convolution and dense-layer gradients for XLA:CPU: `lax.conv_general_dilated` and
`lax.dot_general` with the same values, whose kernel gradients are computed as matmuls.

XLA:CPU differentiates a convolution's kernel as one convolution whose window is the whole
image, which its library kernels run several times slower than the forward pass
(docs/benchmarks.md has the figures). Here the kernel gradient of a stride-1 k x k convolution
is an im2col matmul, (k*k*C_in, pixels) @ (pixels, C_out): the k*k shifted input windows
concatenated along the channels. Large layers do it in a loop over blocks of output rows whose
im2col stays in cache, summing the blocks' products; small ones build the whole im2col; deep
ones with few pixels and many channels sum one matmul per tap instead; wide 3x3 layers use
Winograd's F(3x3, 2x2), 2.25x fewer multiply-adds (`kernel_gradient_method` says when). With
``native=True`` the float32 layers take the C++ kernel of `native_conv` instead.

A 1x1 convolution is a matmul over the channel axis, its kernel gradient a matmul with the
pixels minor on the left (`_pointwise_conv`). The input gradient is a convolution with the
flipped kernel (`input_gradient`). Only `irdepth_jax.xla_cpu.training_layers` installs these,
and only on a CPU backend.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax import lax

from irdepth_jax.xla_cpu import native_conv

BLOCK_PIXELS = 2048
"""Output pixels (batch x rows x width) per block of the kernel-gradient loop: its im2col block
(k*k*C_in x BLOCK_PIXELS floats, 2.4 MB for 3x3 x 32 channels) stays in cache; 1000-3000 were
within 10 % of each other (docs/benchmarks.md)."""

MIN_LOOP_PIXELS = 16384
"""Below this many output pixels (batch x height x width) the kernel gradient is not the loop,
which would have few blocks and whose set-up would not pay."""

IM2COL_BYTES = 16 * 2**20
"""Largest float32 im2col (kh*kw*C_in x output pixels) that the kernel gradient builds whole."""

CHANNELS_FIRST_MAX_OUT = 64
"""The loop lays each block's im2col out channels first, (k*k*C_in, pixels), when the layer has
at most this many output channels: XLA:CPU's matmul with the contraction axis minor on the left
ran faster, worth the transpose of the input for narrow layers, not for wide ones."""

WINOGRAD_MIN_CHANNELS = 64 * 128
"""3x3 layers with at least this C_in x C_out take the Winograd kernel gradient: its 2.25x
fewer multiply-adds pay for its transforms (additions, proportional to C_in + C_out) only on
wide layers."""

WINOGRAD_OVER_NATIVE_MIN_CHANNELS = 128 * 128
"""With the native kernel, 3x3 layers take Winograd only from this C_in x C_out up."""

_NHWC = ("NHWC", "HWIO", "NHWC")


def _is_nhwc(dimension_numbers) -> bool:
    if dimension_numbers is None:
        return False
    if isinstance(dimension_numbers, lax.ConvDimensionNumbers):
        return dimension_numbers == lax.conv_dimension_numbers((1, 1, 1, 1), (1, 1, 1, 1), _NHWC)
    return tuple(dimension_numbers) == _NHWC


def conv_general_dilated(lhs, rhs, window_strides, padding, lhs_dilation=None, rhs_dilation=None,
                         dimension_numbers=None, feature_group_count=1, precision=None, *, native: bool = False):
    """`lax.conv_general_dilated` with the same arguments (what `nn.Conv` calls), computed as
    the module docstring says for 2-D NHWC / HWIO convolutions; any other case is
    `lax.conv_general_dilated` itself. `native`: whether kernel gradients may take `native_conv`.

    lhs: (B, H, W, C_in); rhs: (kh, kw, C_in, C_out) -> (B, H', W', C_out).
    """
    kwargs = dict(lhs_dilation=lhs_dilation, rhs_dilation=rhs_dilation,
                  dimension_numbers=dimension_numbers, feature_group_count=feature_group_count,
                  precision=precision)
    plain = (lhs.ndim != 4 or not _is_nhwc(dimension_numbers) or feature_group_count != 1
             or any(d != 1 for d in (lhs_dilation or ()) + (rhs_dilation or ())))
    if plain:
        return lax.conv_general_dilated(lhs, rhs, window_strides, padding, **kwargs)
    kh, kw = rhs.shape[:2]
    if isinstance(padding, str):
        padding = lax.padtype_to_pads(lhs.shape[1:3], (kh, kw), window_strides, padding)
    pads = tuple(tuple(p) for p in padding)
    if (kh, kw) == (1, 1) and tuple(window_strides) == (1, 1) and pads == ((0, 0), (0, 0)):
        return _pointwise_conv(lhs, rhs[0, 0], precision, native)
    if tuple(window_strides) != (1, 1):
        return lax.conv_general_dilated(lhs, rhs, window_strides, padding, **kwargs)
    return _conv_stride1(lhs, rhs, pads, precision, native)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2, 3))
def _pointwise_conv(x, kernel, precision, native):
    """A matmul over the last axis, (..., C_in) @ (C_in, C_out) -> (..., C_out): a 1x1
    convolution, or a dense layer (`dot_general`). Its kernel gradient contracts the pixels
    (tokens) with x laid out channels first, made an array of its own (`materialize`): XLA:CPU's
    own transposed x inside a fusion with x's producers and contracted the leading axes, several
    times slower."""
    return jnp.einsum("...c,cd->...d", x, kernel, precision=precision)


def _pointwise_conv_fwd(x, kernel, precision, native):
    return _pointwise_conv(x, kernel, precision, native), (x, kernel)


def _pointwise_conv_bwd(precision, native, residuals, g):
    x, kernel = residuals
    dx = jnp.einsum("...d,cd->...c", g, kernel, precision=precision)
    # images (not the ViT's tokens, one long row, where it is slower): the native kernel reads x
    # in place, no transposed copy
    if x.ndim == 4 and kernel_gradient_method(x.shape, g.shape, (1, 1), jnp.result_type(x, g), native) == "native":
        dkernel = native_conv.kernel_gradient_native(x, g, (1, 1), ((0, 0), (0, 0)))[0, 0]
        return dx, dkernel.astype(kernel.dtype)
    x_t = materialize(x.reshape(-1, x.shape[-1]).T)
    dkernel = jnp.einsum("cp,pd->cd", x_t, g.reshape(-1, g.shape[-1]), precision=precision,
                         preferred_element_type=_accumulator(x, g))
    return dx, dkernel.astype(kernel.dtype)


_pointwise_conv.defvjp(_pointwise_conv_fwd, _pointwise_conv_bwd)


def dot_general(lhs, rhs, dimension_numbers, precision=None, preferred_element_type=None, *,
                native: bool = False):
    """`lax.dot_general` for `flax.linen.Dense`: its contraction of lhs's last axis with a 2-D
    kernel is `_pointwise_conv` (the kernel gradient above); anything else is `lax.dot_general`
    itself."""
    if (rhs.ndim == 2 and preferred_element_type is None
            and tuple(map(tuple, dimension_numbers[0])) == ((lhs.ndim - 1,), (0,))
            and not any(dimension_numbers[1])):
        return _pointwise_conv(lhs, rhs, precision, native)
    return lax.dot_general(lhs, rhs, dimension_numbers, precision=precision,
                           preferred_element_type=preferred_element_type)


def _plain_conv(x, kernel, pads, precision):
    return lax.conv_general_dilated(x, kernel, (1, 1), pads, dimension_numbers=_NHWC,
                                    precision=precision)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2, 3, 4))
def _conv_stride1(x, kernel, pads, precision, native):
    return _plain_conv(x, kernel, pads, precision)


def _conv_stride1_fwd(x, kernel, pads, precision, native):
    return _plain_conv(x, kernel, pads, precision), (x, kernel)


def _conv_stride1_bwd(pads, precision, native, residuals, g):
    x, kernel = residuals
    dkernel = kernel_gradient(x, g, kernel.shape[:2], pads, native=native).astype(kernel.dtype)
    return input_gradient(g, kernel, pads, precision), dkernel


def input_gradient(g, kernel, pads, precision=None):
    """Gradient of a stride-1 convolution's input: (B, H', W', C_out) output gradient and its
    (kh, kw, C_in, C_out) kernel -> (B, H, W, C_in), the convolution of g with the kernel flipped
    in space and transposed in its channels (XLA's own gradient of the convolution was slower).
    Paddings over kh - 1 (the output smaller than the padding) are XLA's own."""
    kh, kw = kernel.shape[:2]
    (top, bottom), (left, right) = pads
    if max(top, bottom) > kh - 1 or max(left, right) > kw - 1:
        x_shape = (g.shape[0], g.shape[1] - top - bottom + kh - 1, g.shape[2] - left - right + kw - 1,
                   kernel.shape[2])
        return jax.vjp(lambda x: _plain_conv(x, kernel, pads, precision), jnp.zeros(x_shape, g.dtype))[1](g)[0]
    flipped = kernel[::-1, ::-1].transpose(0, 1, 3, 2)
    return _plain_conv(g, flipped, ((kh - 1 - top, kh - 1 - bottom), (kw - 1 - left, kw - 1 - right)),
                       precision)


_conv_stride1.defvjp(_conv_stride1_fwd, _conv_stride1_bwd)


def kernel_gradient(x, g, kernel_size: tuple[int, int], pads, block_pixels: int = BLOCK_PIXELS, *,
                    native: bool = False):
    """Gradient of a stride-1 convolution's kernel, by whichever of the five ways below was the
    fastest for the layer's size on XLA:CPU (`experiments/bench_conv_grad.py`): Winograd's
    F(3x3, 2x2) for wide 3x3 layers (`WINOGRAD_MIN_CHANNELS`, or
    `WINOGRAD_OVER_NATIVE_MIN_CHANNELS` where the native kernel would serve), else the native kernel for
    float32 layers whose output channels fit its tiles (with `native`, `native_conv`), else one
    channels-first im2col matmul when its im2col is at most `IM2COL_BYTES`, else a sum of one
    matmul per kernel tap below `MIN_LOOP_PIXELS` output pixels, else the row-block loop.

    Args:
      x: (B, H, W, C_in) the convolution's input.
      g: (B, H', W', C_out) the gradient of its output, H' = H + pad_h - kh + 1 (W' likewise).
      kernel_size: (kh, kw).
      pads: ((top, bottom), (left, right)) zero padding of x.
      block_pixels: output pixels per block of the loop (rounded to whole rows, at least one).
      native: whether the native kernel may serve (it must be `native_conv.available()`).
    Returns:
      (kh, kw, C_in, C_out) float32 (float64 for float64 operands): sum over b, i, j of
      x_pad[b, i + p, j + q, :] outer g[b, i, j, :].
    """
    method = kernel_gradient_method(x.shape, g.shape, kernel_size, jnp.result_type(x, g), native)
    if method == "winograd":
        return kernel_gradient_winograd(x, g, pads, block_pixels)
    if method == "native":
        return native_conv.kernel_gradient_native(x, g, kernel_size, pads)
    if method == "im2col":
        return kernel_gradient_im2col(x, g, kernel_size, pads)
    if method == "by_tap":
        return kernel_gradient_by_tap(x, g, kernel_size, pads)
    return kernel_gradient_row_blocks(x, g, kernel_size, pads, block_pixels,
                                      channels_first=g.shape[-1] <= CHANNELS_FIRST_MAX_OUT)


def _accumulator(x, g):
    """The kernel gradient's dtype: float32, or float64 where an operand is."""
    return jnp.promote_types(jnp.promote_types(x.dtype, g.dtype), jnp.float32)


def kernel_gradient_method(x_shape, g_shape, kernel_size, dtype=jnp.float32, native: bool = False) -> str:
    """Which way `kernel_gradient` computes a layer's: 'winograd', 'native', 'im2col', 'by_tap'
    or 'row_blocks'. x_shape (B, H, W, C_in), g_shape (B, H', W', C_out), kernel_size (kh, kw),
    dtype the operands' (the native kernel is float32), native whether it may serve."""
    native = (native and jnp.dtype(dtype) == jnp.float32 and native_conv.available()
              and g_shape[-1] % native_conv.tile_channels() == 0)
    wide = WINOGRAD_OVER_NATIVE_MIN_CHANNELS if native else WINOGRAD_MIN_CHANNELS
    if tuple(kernel_size) == (3, 3) and x_shape[-1] * g_shape[-1] >= wide:
        return "winograd"
    if native:
        return "native"
    out_pixels = g_shape[0] * g_shape[1] * g_shape[2]
    if kernel_size[0] * kernel_size[1] * x_shape[-1] * out_pixels * 4 <= IM2COL_BYTES:
        return "im2col"
    return "by_tap" if out_pixels < MIN_LOOP_PIXELS else "row_blocks"


def materialize(x):
    """x, computed by XLA:CPU as an array of its own before any use: the operand of a
    conditional on one of its values (both branches return x; a NaN there makes all of it NaN,
    an unusable value anyway). XLA:CPU fuses elementwise producers into each consumer,
    recomputing them there, and removes `lax.optimization_barrier` before fusion; a
    conditional's operand it must compute whole (XLA:CPU only: a GPU conditional waits for its
    predicate on the host)."""
    first = x[(0,) * x.ndim]
    return lax.cond(first == first, lambda x: x, lambda x: x + first * 0, x)


def _channels_first(x, pads):
    """(B, H, W, C) -> (C, B, H + pads, W + pads), zero padded. The transpose is made an array
    before the padding: fused, the two ran 2-3x slower than apart."""
    return jnp.pad(materialize(x.transpose(3, 0, 1, 2)), ((0, 0), (0, 0)) + tuple(pads))


def _channels_first_taps(x, out_shape, kernel_size, pads):
    """The kh * kw shifted windows of the zero-padded x, channels first: a list of
    (C_in, B, H', W') arrays in (p, q) order, for out_shape = (H', W')."""
    (kh, kw), (out_h, out_w) = kernel_size, out_shape
    x_pad = _channels_first(x, pads)
    return [x_pad[:, :, p:p + out_h, q:q + out_w] for p in range(kh) for q in range(kw)]


def kernel_gradient_im2col(x, g, kernel_size, pads):
    """`kernel_gradient` as one matmul, (kh*kw*C_in, B*H'*W') @ (B*H'*W', C_out). The im2col is
    built channels first: XLA:CPU's matmul contracting the leading axis of both operands (the
    pixel-major layout) ran slower than with the pixels minor on the left."""
    kh, kw = kernel_size
    patches = jnp.concatenate(_channels_first_taps(x, g.shape[1:3], kernel_size, pads), axis=0)
    total = jnp.einsum("kbhw,bhwd->kd", patches, g, preferred_element_type=_accumulator(x, g))
    return total.reshape(kh, kw, x.shape[-1], g.shape[-1])


def kernel_gradient_by_tap(x, g, kernel_size, pads):
    """`kernel_gradient` as one (C_in, B*H'*W') @ (B*H'*W', C_out) matmul per kernel tap: for
    deep layers (few pixels, many channels) no im2col copy kh*kw times the input."""
    kh, kw = kernel_size
    taps = [jnp.einsum("cbhw,bhwd->cd", window, g, preferred_element_type=_accumulator(x, g))
            for window in _channels_first_taps(x, g.shape[1:3], kernel_size, pads)]
    return jnp.stack(taps).reshape(kh, kw, x.shape[-1], g.shape[-1])


def kernel_gradient_row_blocks(x, g, kernel_size, pads, block_pixels: int = BLOCK_PIXELS,
                               channels_first: bool = True):
    """`kernel_gradient` as a loop over blocks of output rows (module docstring), each block's
    im2col laid out (kh*kw*C_in, pixels) when channels_first, else (pixels, kh*kw*C_in)."""
    kh, kw = kernel_size
    b, out_h, out_w, c_out = g.shape
    c_in = x.shape[-1]
    rows = max(1, round(block_pixels / (b * out_w)))
    blocks = -(-out_h // rows)
    extra = blocks * rows - out_h  # zero rows: they add nothing to the sum
    pad_rows = (pads[0][0], pads[0][1] + extra)
    if channels_first:
        x_pad = _channels_first(x, (pad_rows, pads[1]))
        row_axis, tap_axis, spec = 2, 0, "kbhw,bhwd->kd"
    else:
        x_pad = jnp.pad(x, ((0, 0), pad_rows, pads[1], (0, 0)))
        row_axis, tap_axis, spec = 1, -1, "bhwk,bhwd->kd"
    g_pad = jnp.pad(g, ((0, 0), (0, extra), (0, 0), (0, 0)))

    def block(i, total):
        top = i * rows
        window = lax.dynamic_slice_in_dim(x_pad, top, rows + kh - 1, axis=row_axis)
        taps = [lax.slice_in_dim(lax.slice_in_dim(window, p, p + rows, axis=row_axis),
                                 q, q + out_w, axis=row_axis + 1)
                for p in range(kh) for q in range(kw)]
        g_rows = lax.dynamic_slice_in_dim(g_pad, top, rows, axis=1)
        return total + jnp.einsum(spec, jnp.concatenate(taps, axis=tap_axis), g_rows,
                                  preferred_element_type=_accumulator(x, g))

    total = lax.fori_loop(0, blocks, block, jnp.zeros((kh * kw * c_in, c_out), _accumulator(x, g)))
    return total.reshape(kh, kw, c_in, c_out)


# Winograd F(3x3, 2x2): for a 2x2 tile t of the output gradient and the 4x4 input patch d
# under it, the tile's share of the 3x3 kernel gradient is A^T [(G t G^T) * (B^T d B)] A.
# B^T = [[1, 0, -1, 0], [0, 1, 1, 0], [0, -1, 1, 0], [0, 1, 0, -1]],
# G = [[1, 0], [1/2, 1/2], [1/2, -1/2], [0, -1]], A^T = [[1, 1, 1, 0], [0, 1, -1, 0], [0, 1, 1, 1]].
def _winograd_bt(d0, d1, d2, d3):
    """B^T applied across four arrays (the patch's rows or columns)."""
    return [d0 - d2, d1 + d2, d2 - d1, d1 - d3]


def _winograd_g(t0, t1):
    """G applied across two arrays (the tile's rows or columns)."""
    return [t0, 0.5 * (t0 + t1), 0.5 * (t0 - t1), -t1]


def _winograd_at(m):
    """A^T applied along axis 0 of a (4, ...) array -> (3, ...)."""
    return jnp.stack([m[0] + m[1] + m[2], m[1] - m[2], m[1] + m[2] + m[3]])


def kernel_gradient_winograd(x, g, pads, block_pixels: int = BLOCK_PIXELS):
    """`kernel_gradient` of a 3x3 kernel by Winograd's F(3x3, 2x2) (the comment above): per
    2x2 tile of output pixels, 16 transformed products instead of the 36 of the direct sum, so
    16 matmuls (C_in, tiles) @ (tiles, C_out) with 2.25x fewer multiply-adds than the im2col's,
    in a loop over blocks of tile rows (about `block_pixels` output pixels each, balanced so the
    padding to whole blocks stays small). Input columns are split even / odd once beforehand,
    so that the patches' column offsets are contiguous slices. Each 16-way transform is written
    as 4 stacks of 4: XLA:CPU fuses a concatenate of at most 8 operands, and made each of 16 a
    fusion of its own. Transforms in float32 (float64 for
    float64 operands); the result differs from the direct sum by rounding (about 1e-6 of its
    largest value).

    x: (B, H, W, C_in); g: (B, H', W', C_out); pads ((top, bottom), (left, right)) ->
    (3, 3, C_in, C_out)."""
    b, out_h, out_w, c_out = g.shape
    c_in = x.shape[-1]
    acc = _accumulator(x, g)
    even_w = out_w + out_w % 2
    tiles_w = even_w // 2
    blocks = max(1, round(out_h * b * even_w / block_pixels))
    tile_rows = -(-out_h // (2 * blocks))  # per block
    blocks = -(-out_h // (2 * tile_rows))
    rows = 2 * tile_rows
    extra_h, extra_w = blocks * rows - out_h, even_w - out_w  # zeros: they add nothing
    x_pad = jnp.pad(x, ((0, 0), (pads[0][0], pads[0][1] + extra_h), (pads[1][0], pads[1][1] + extra_w),
                        (0, 0)))
    # (C_in, B, rows, 2, tiles_w + 1): [..., s, j] is column 2 j + s
    x_split = materialize(x_pad.reshape(b, x_pad.shape[1], tiles_w + 1, 2, c_in).transpose(4, 0, 1, 3, 2))
    # (B, tile rows, 2, tiles_w, 2, C_out): a reshape, no copy
    g_tiles = jnp.pad(g, ((0, 0), (0, extra_h), (0, extra_w), (0, 0))).reshape(
        b, blocks * tile_rows, 2, tiles_w, 2, c_out)

    def block(i, total):
        window = lax.dynamic_slice_in_dim(x_split, i * rows, rows + 2, axis=2).astype(acc)
        by_rows = _winograd_bt(*(window[:, :, a:a + rows:2] for a in range(4)))
        u = jnp.stack([jnp.stack(_winograd_bt(r[..., 0, :-1], r[..., 1, :-1], r[..., 0, 1:], r[..., 1, 1:]))
                       for r in by_rows]).reshape(16, c_in, -1)
        tile = lax.dynamic_slice_in_dim(g_tiles, i * tile_rows, tile_rows, axis=1).astype(acc)
        v = jnp.stack([jnp.stack(_winograd_g(r[:, :, :, 0], r[:, :, :, 1]))
                       for r in _winograd_g(tile[:, :, 0], tile[:, :, 1])]).reshape(16, -1, c_out)
        return total + jnp.einsum("zct,ztd->zcd", u, v, preferred_element_type=acc)

    m = lax.fori_loop(0, blocks, block, jnp.zeros((16, c_in, c_out), acc)).reshape(4, 4, c_in, c_out)
    return _winograd_at(_winograd_at(m).transpose(1, 0, 2, 3)).transpose(1, 0, 2, 3)
