"""DINOv2 vision transformer (the Depth Anything V2 backbone), an exact port of the official model.

Pre-norm blocks with LayerScale, LayerNorm eps 1e-6, exact (erf) GELU or SwiGLU (vitg), no
register tokens. Parameter names mirror the official PyTorch checkpoint (`pretrained.*`):
`patch_embed/proj`, `cls_token`, `pos_embed`, `blocks_{i}/{norm1,attn/qkv,attn/proj,ls1,norm2,
mlp/fc1,mlp/fc2 | mlp/w12,mlp/w3,ls2}`, `norm`. The checkpoint's `mask_token` is used only in
DINOv2 pre-training and has no parameter here.

Position embeddings are resampled from the 37x37 training grid with PyTorch's bicubic kernel
(a = -0.75, clamped borders, align_corners False) through precomputed interpolation matrices:
  * 'official': `scale_factor=((h + 0.1) / 37, (w + 0.1) / 37)`, i.e. source step 37 / (h + 0.1)
    (the Depth Anything V2 / DINOv2 code; ground truth for the released checkpoints);
  * 'transformers': `size=(h, w)`, i.e. source step 37 / h (HF transformers' Dinov2).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

POS_EMBED_MODES = ("official", "transformers")
_INTERPOLATE_OFFSET = 0.1  # the official code's work-around offset (DINOv2 without registers)
_CUBIC_A = -0.75  # PyTorch's and OpenCV's bicubic coefficient (jax.image uses -0.5)


def _cubic_weights(t: np.ndarray) -> np.ndarray:
    """Keys cubic-convolution weights (a = -0.75) of the 4 taps at offsets -1, 0, 1, 2.

    t: (N,) fractional positions in [0, 1) -> (N, 4) weights (each row sums to 1).
    """
    a = _CUBIC_A

    def near(x):  # |x| <= 1
        return ((a + 2) * x - (a + 3)) * x * x + 1

    def far(x):  # 1 < |x| < 2
        return ((a * x - 5 * a) * x + 8 * a) * x - 4 * a

    return np.stack([far(t + 1), near(t), near(1 - t), far(2 - t)], axis=-1)


def cubic_resize_matrix(in_size: int, out_size: int, scale: float) -> np.ndarray:
    """Matrix of PyTorch's bicubic resampling (align_corners False, borders clamped) along one axis.

    Output sample o reads the input at x = (o + 0.5) * scale - 0.5 with the a = -0.75 kernel; taps
    outside [0, in_size) are clamped to the border, as torch's `upsample_bicubic2d` and OpenCV's
    INTER_CUBIC do. `scale` is input pixels per output pixel (torch: in/out for `size=`,
    1/scale_factor for `scale_factor=`). Returns (out_size, in_size) float64; apply as M @ x.
    """
    src = (np.arange(out_size, dtype=np.float64) + 0.5) * scale - 0.5
    base = np.floor(src)
    weights = _cubic_weights(src - base)
    taps = np.clip(base[:, None].astype(np.int64) + np.arange(-1, 3), 0, in_size - 1)
    matrix = np.zeros((out_size, in_size))
    np.add.at(matrix, (np.repeat(np.arange(out_size), 4), taps.ravel()), weights.ravel())
    return matrix


def interpolate_pos_embed(pos_embed: jax.Array, grid_hw: tuple[int, int], mode: str = "official") -> jax.Array:
    """Resample ViT position embeddings to a patch grid, in float32.

    pos_embed: (1, 1 + G*G, D) with the class-token row first; grid_hw: (h, w) patches;
    mode: 'official' | 'transformers' (see the module docstring). Returns (1, 1 + h*w, D);
    unchanged when (h, w) == (G, G).
    """
    if mode not in POS_EMBED_MODES:
        raise ValueError(f"pos_embed_mode must be one of {POS_EMBED_MODES}, got {mode!r}")
    n, d = pos_embed.shape[1] - 1, pos_embed.shape[2]
    g = int(round(n**0.5))
    if g * g != n:
        raise ValueError(f"pos_embed has {n} patch rows, not a square grid")
    h, w = grid_hw
    if (h, w) == (g, g):
        return pos_embed
    if mode == "official":
        steps = (g / (h + _INTERPOLATE_OFFSET), g / (w + _INTERPOLATE_OFFSET))
    else:
        steps = (g / h, g / w)
    rows = jnp.asarray(cubic_resize_matrix(g, h, steps[0]), jnp.float32)
    cols = jnp.asarray(cubic_resize_matrix(g, w, steps[1]), jnp.float32)
    grid = pos_embed[0, 1:].astype(jnp.float32).reshape(g, g, d)
    hi = jax.lax.Precision.HIGHEST
    grid = jnp.einsum("hi,ijd->hjd", rows, grid, precision=hi)
    grid = jnp.einsum("wj,hjd->hwd", cols, grid, precision=hi)
    out = jnp.concatenate([pos_embed[0, :1].astype(jnp.float32), grid.reshape(h * w, d)], axis=0)
    return out[None].astype(pos_embed.dtype)


def _dense_init():
    return nn.initializers.truncated_normal(0.02)


def after(x, g):
    """x, as a value XLA can compute only once `g` exists: x + 0 * (one value of g).

    For the recomputations in backward passes: XLA:CPU schedules an operation as soon as its
    inputs exist, so a recomputation that needs only forward values (the residuals) runs during
    the forward pass, for every layer, and its results wait there for the backward pass: the
    memory recomputation was meant to save, and more. Its first use of g moves it to where the
    backward pass reaches its layer. XLA cannot fold x + 0 * v away (v may be inf or NaN, which
    it then spreads: such a gradient is unusable anyway).
    """
    return x + (g.reshape(-1)[0] * 0).astype(x.dtype)


@jax.custom_vjp
def exact_gelu(x):
    """`jax.nn.gelu(x, approximate=False)` (the same forward), whose backward keeps only x.

    Autodiff keeps erfc's output and an intermediate of its derivative, two more arrays of the
    MLP's hidden size per block (ViT-S, 2 images of 518x518: 400 MB in all, fresh pages every
    step); the derivative cdf(x) + x pdf(x) is recomputed from x instead.
    """
    return jax.nn.gelu(x, approximate=False)


def _gelu_fwd(x):
    return exact_gelu(x), x


def _gelu_bwd(x, g):
    x = after(x, g)
    cdf = 0.5 * lax.erfc(-x * np.sqrt(0.5).astype(x.dtype))
    pdf = jnp.exp(-0.5 * x * x) * np.asarray(1.0 / np.sqrt(2.0 * np.pi), x.dtype)
    return (g * (cdf + x * pdf),)


exact_gelu.defvjp(_gelu_fwd, _gelu_bwd)


class LayerScale(nn.Module):
    """x * gamma (per channel), gamma initialised to 1.0 as in Depth Anything V2's DINOv2."""

    dim: int
    init_value: float = 1.0

    @nn.compact
    def __call__(self, x):
        gamma = self.param("gamma", nn.initializers.constant(self.init_value), (self.dim,))
        return x * gamma.astype(x.dtype)


ATTENTION = ("auto", "einsum", "xla", "cudnn")
"""Attention kernels: the heads-major einsums, XLA's `jax.nn.dot_product_attention`, or cuDNN's
fused (flash) attention through it; 'auto' picks one per backend (`attention_implementation`)."""


def attention_implementation(choice: str, backend: str, dtype) -> str:
    """The kernel `choice` stands for on `backend` ('cpu' | 'gpu' | 'tpu') at compute `dtype`.

    'auto': on GPU, cuDNN's fused attention for bfloat16 / float16 compute (it takes no float32)
    and XLA's dot_product_attention in float32; elsewhere the einsums (measured 1.8x faster per
    layer than dot_product_attention on XLA:CPU, ViT-S with 1370 tokens: 35 vs 62 ms).
    """
    if choice not in ATTENTION:
        raise ValueError(f"attention {choice!r}: choose one of {ATTENTION}")
    if choice != "auto":
        return choice
    if backend == "gpu":
        return "cudnn" if jnp.dtype(dtype) in (jnp.bfloat16, jnp.float16) else "xla"
    return "einsum"


def attend(qkv, num_heads: int, implementation: str):
    """Softmax attention, scale 1/sqrt(head_dim), softmax in float32.

    Args:
      qkv: (B, N, 3 * D) fused projections (official layout: q, k, v blocks of D = heads x
        head_dim).
      num_heads: heads.
      implementation: one of ATTENTION without 'auto'.
    Returns:
      (B, N, D).
    """
    b, n, _ = qkv.shape
    head_dim = qkv.shape[-1] // (3 * num_heads)
    qkv = qkv.reshape(b, n, 3, num_heads, head_dim)
    if implementation in ("xla", "cudnn"):
        q, k, v = jnp.moveaxis(qkv, 2, 0)
        out = jax.nn.dot_product_attention(q, k, v, implementation=implementation)
        return out.reshape(b, n, num_heads * head_dim)
    q, k, v = jnp.transpose(qkv, (2, 0, 3, 1, 4))  # (B, heads, N, head_dim) each
    out = jnp.transpose(softmax_attention(q, k, v, head_dim**-0.5), (0, 2, 1, 3))
    return out.reshape(b, n, num_heads * head_dim)


@functools.partial(jax.custom_vjp, nondiff_argnums=(3,))
def softmax_attention(q, k, v, scale: float):
    """softmax(scale * q k^T) v per head, the softmax in float32: q, k, v (B, heads, N, head_dim)
    -> (B, heads, N, head_dim).

    The forward is `jax.nn.softmax`'s arithmetic op for op. The backward recomputes the
    attention weights from q, k and the softmax statistics instead of keeping them: autodiff
    keeps 2-3 (B, heads, N, N) float32 arrays per layer for the backward pass (ViT-S, 2 images of
    518x518: 4.8 GB in all), which on XLA:CPU are fresh pages every step (page faults took more
    than a third of the train step's time). Recomputing them costs one more N x N matmul per
    layer; measured train step of the ViT-S backbone 6.2 -> 4.1 s (2 cores).
    """
    return _attention_fwd(q, k, v, scale)[0]


def _attention_fwd(q, k, v, scale):
    logits = jnp.einsum("bhqd,bhkd->bhqk", q * jnp.asarray(scale, q.dtype), k).astype(jnp.float32)
    row_max = jnp.max(logits, axis=-1, keepdims=True)
    unnormalized = jnp.exp(logits - row_max)
    row_sum = jnp.sum(unnormalized, axis=-1, keepdims=True)
    out = jnp.einsum("bhqk,bhkd->bhqd", (unnormalized / row_sum).astype(v.dtype), v)
    return out, (q, k, v, out, row_max, row_sum)


def _attention_bwd(scale, residuals, g):
    q, k, v, out, row_max, row_sum = residuals
    k = after(k, g)
    q_scaled = q * jnp.asarray(scale, q.dtype)
    # Keys-major (B, heads, N_k, N_q): in the forward's layout XLA fuses the recomputation with
    # the forward pass's ops (measured 45 % slower in all).
    logits_t = jnp.einsum("bhkd,bhqd->bhkq", k, q_scaled).astype(jnp.float32)
    weights_t = jnp.exp(logits_t - jnp.swapaxes(row_max, -1, -2)) / jnp.swapaxes(row_sum, -1, -2)
    dv = jnp.einsum("bhkq,bhqd->bhkd", weights_t.astype(v.dtype), g)
    dweights_t = jnp.einsum("bhkd,bhqd->bhkq", v, g).astype(jnp.float32)
    # The softmax's backward needs sum_k weights * dweights per query, which is g . out (as in
    # FlashAttention): an N x head_dim product instead of an N x N one.
    g_dot_out = jnp.sum(g.astype(jnp.float32) * out.astype(jnp.float32), axis=-1)[:, :, None, :]
    dlogits_t = (weights_t * (dweights_t - g_dot_out)).astype(q.dtype)
    dq = jnp.einsum("bhkq,bhkd->bhqd", dlogits_t, k) * jnp.asarray(scale, q.dtype)
    dk = jnp.einsum("bhkq,bhqd->bhkd", dlogits_t, q_scaled)
    return dq, dk, dv


softmax_attention.defvjp(_attention_fwd, _attention_bwd)


class Attention(nn.Module):
    """Multi-head self-attention with a fused qkv projection (official layout: q, k, v blocks);
    the kernel by `attention_implementation(attention, backend, dtype)`."""

    dim: int
    num_heads: int
    dtype: Any = jnp.float32
    attention: str = "auto"

    @nn.compact
    def __call__(self, x):
        """x: (B, N, D) -> (B, N, D)."""
        qkv = nn.Dense(3 * self.dim, dtype=self.dtype, kernel_init=_dense_init(), name="qkv")(x)
        implementation = attention_implementation(self.attention, jax.default_backend(), self.dtype)
        out = attend(qkv, self.num_heads, implementation)
        return nn.Dense(self.dim, dtype=self.dtype, kernel_init=_dense_init(), name="proj")(out)


class Mlp(nn.Module):
    """fc1 -> exact GELU -> fc2."""

    dim: int
    hidden: int
    dtype: Any = jnp.float32

    @nn.compact
    def __call__(self, x):
        x = nn.Dense(self.hidden, dtype=self.dtype, kernel_init=_dense_init(), name="fc1")(x)
        x = exact_gelu(x)
        return nn.Dense(self.dim, dtype=self.dtype, kernel_init=_dense_init(), name="fc2")(x)


class SwiGLUFFN(nn.Module):
    """w12 -> split (x1, x2) -> silu(x1) * x2 -> w3; hidden = 2/3 of the MLP width, rounded up to 8."""

    dim: int
    hidden: int
    dtype: Any = jnp.float32

    @nn.compact
    def __call__(self, x):
        hidden = (int(self.hidden * 2 / 3) + 7) // 8 * 8
        x1, x2 = jnp.split(nn.Dense(2 * hidden, dtype=self.dtype, kernel_init=_dense_init(), name="w12")(x), 2, -1)
        return nn.Dense(self.dim, dtype=self.dtype, kernel_init=_dense_init(), name="w3")(jax.nn.silu(x1) * x2)


class Block(nn.Module):
    """Pre-norm transformer block: x + ls1(attn(norm1(x))), then x + ls2(ffn(norm2(x)))."""

    dim: int
    num_heads: int
    mlp_ratio: float = 4.0
    ffn: str = "mlp"
    dtype: Any = jnp.float32
    attention: str = "auto"

    @nn.compact
    def __call__(self, x):
        """x: (B, N, D) -> (B, N, D)."""
        norm = dict(epsilon=1e-6, dtype=self.dtype, use_fast_variance=False)
        ffn_cls = {"mlp": Mlp, "swiglu": SwiGLUFFN}[self.ffn]
        attention = Attention(self.dim, self.num_heads, self.dtype, self.attention, name="attn")
        y = attention(nn.LayerNorm(**norm, name="norm1")(x))
        x = x + LayerScale(self.dim, name="ls1")(y)
        y = ffn_cls(self.dim, int(self.dim * self.mlp_ratio), self.dtype, name="mlp")(
            nn.LayerNorm(**norm, name="norm2")(x)
        )
        return x + LayerScale(self.dim, name="ls2")(y)


class PatchEmbed(nn.Module):
    """Non-overlapping p x p patches -> D channels: (B, H, W, 3) -> (B, (H/p) * (W/p), D)."""

    dim: int
    patch_size: int
    dtype: Any = jnp.float32

    @nn.compact
    def __call__(self, x):
        p = self.patch_size
        y = nn.Conv(self.dim, (p, p), strides=(p, p), padding="VALID", dtype=self.dtype, name="proj")(x)
        return y.reshape(y.shape[0], -1, self.dim)


class DinoVisionTransformer(nn.Module):
    """DINOv2 ViT returning the final-normed patch tokens of the tapped blocks.

    `__call__(x)`: x (B, H, W, 3) with H, W multiples of `patch_size` -> tuple of len(taps)
    arrays (B, (H/p) * (W/p), D), row-major over the patch grid, class token dropped; each is
    also sown as 'intermediates' / `tap_{k}`.
    """

    embed_dim: int
    depth: int
    num_heads: int
    taps: Sequence[int]
    mlp_ratio: float = 4.0
    ffn: str = "mlp"
    patch_size: int = 14
    image_size: int = 518
    pos_embed_mode: str = "official"
    dtype: Any = jnp.float32
    remat: bool = False
    attention: str = "auto"

    @nn.compact
    def __call__(self, x):
        b, height, width, _ = x.shape
        p, d = self.patch_size, self.embed_dim
        grid = (height // p, width // p)
        num_pos = (self.image_size // p) ** 2 + 1
        cls_token = self.param("cls_token", nn.initializers.normal(1e-6), (1, 1, d))
        pos_embed = self.param("pos_embed", nn.initializers.truncated_normal(0.02), (1, num_pos, d))
        tokens = PatchEmbed(d, p, self.dtype, name="patch_embed")(x)
        tokens = jnp.concatenate([jnp.broadcast_to(cls_token.astype(tokens.dtype), (b, 1, d)), tokens], axis=1)
        tokens = tokens + interpolate_pos_embed(pos_embed, grid, self.pos_embed_mode).astype(tokens.dtype)

        block_cls = nn.remat(Block) if self.remat else Block
        norm = nn.LayerNorm(epsilon=1e-6, dtype=self.dtype, use_fast_variance=False, name="norm")
        outputs = []
        for i in range(self.depth):
            tokens = block_cls(d, self.num_heads, self.mlp_ratio, self.ffn, self.dtype, self.attention,
                               name=f"blocks_{i}")(tokens)
            if i in self.taps:
                out = norm(tokens)[:, 1:]
                self.sow("intermediates", f"tap_{len(outputs)}", out)
                outputs.append(out)
        return tuple(outputs)
