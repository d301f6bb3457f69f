"""The CPU training layers against independent references, under jit, on tiny shapes.

`irdepth_jax.xla_cpu`: `flax.linen.Conv` under the CPU layer interceptor (`layers.intercept`)
against plain `flax.linen.Conv` (parameters, forward, gradients; each of the kernel gradient's
four XLA ways (the fifth, the native kernel: test_native_conv.py), the 1x1 einsum, the stride-2
fallback), `kernel_gradient`'s im2col, per-tap, row-block (both layouts) and Winograd ways and
`input_gradient` against autodiff of `lax.conv_general_dilated`, `upsample_by_matmul` against its
formula in numpy loops, `ConvTranspose` and `Dense` under the interceptor against plain Flax,
`training_layers`' choice (CPU only, native only when asked for).

`irdepth_jax.models.dinov2`: `softmax_attention` (custom VJP) against the plain softmax formula and
its autodiff (float32, and float64 on inputs where the float32 softmax is exact), `exact_gelu`
against `jax.nn.gelu` and the hand formula, `gradient_fence` / `after` / `materialize`, and the
tiny Depth Anything V2's parameter gradients with and without the interceptor.
"""

import functools
import math

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from da_params import random_params
from jax import lax

from irdepth_jax import xla_cpu
from irdepth_jax.errors import RunError
from irdepth_jax.models import dinov2
from irdepth_jax.models.depth_anything import depth_anything_config
from irdepth_jax.models.dinov2 import DinoVisionTransformer
from irdepth_jax.models.unet import upsample_by_matmul
from irdepth_jax.xla_cpu import conv, layers

NHWC = ("NHWC", "HWIO", "NHWC")


def assert_close(got, want, rtol=1e-5, what=""):
    """max |got - want| <= rtol * max |want|, leaf by leaf (same tree structure and shapes)."""
    assert jax.tree.structure(got) == jax.tree.structure(want), what
    for path, a, b in zip(jax.tree_util.tree_flatten_with_path(want)[0], jax.tree.leaves(got),
                          jax.tree.leaves(want)):
        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
        assert a.shape == b.shape, (what, path[0])
        scale = np.abs(b).max()
        assert scale > 0, (what, path[0], "reference is all zeros: the check would be vacuous")
        err = np.abs(a - b).max()
        assert err <= rtol * scale, f"{what} {jax.tree_util.keystr(path[0])}: max err {err:.3g}, max |ref| {scale:.3g}"


def assert_bitwise(got, want, what=""):
    assert jax.tree.structure(got) == jax.tree.structure(want), what
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
        a, b = np.asarray(a), np.asarray(b)
        assert a.dtype == b.dtype and a.shape == b.shape, what
        assert np.array_equal(a, b), f"{what}: not bitwise equal, max diff {np.abs(a - b).max():.3g}"


def random(shape, seed, scale=1.0, dtype=jnp.float32):
    return jnp.asarray(np.random.default_rng(seed).normal(0.0, scale, shape), dtype)


def under_cpu_layers(fn):
    """`fn` called with the CPU layer replacements installed (XLA ways only)."""

    def wrapped(*args, **kwargs):
        with nn.intercept_methods(functools.partial(layers.intercept, native=False)):
            return fn(*args, **kwargs)

    return wrapped


class Fast:
    """A Flax module's init / apply under `under_cpu_layers`."""

    def __init__(self, module):
        self.init, self.apply = under_cpu_layers(module.init), under_cpu_layers(module.apply)


# ------------------------------------------------------------------------------------------- Conv
CONV_CASES = {
    # name: (input shape, Conv keyword arguments); 3 -> 4 channels throughout: initialising a new
    # kernel shape compiles the initialiser again
    "3x3_same_nobias": ((2, 9, 11, 3), dict(features=4, kernel_size=(3, 3), padding="SAME", use_bias=False)),
    "3x3_explicit_bias": ((2, 9, 11, 3), dict(features=4, kernel_size=(3, 3), padding=((1, 1), (1, 1)))),
    "1x1_same": ((2, 9, 11, 3), dict(features=4, kernel_size=(1, 1))),
    "1x1_explicit": ((2, 9, 11, 3), dict(features=4, kernel_size=(1, 1), padding=((0, 0), (0, 0)))),
    "1x1_same_large": ((1, 130, 130, 3), dict(features=4, kernel_size=(1, 1))),
    "5x5_asym_small": ((1, 12, 10, 3), dict(features=4, kernel_size=(5, 5), padding=((2, 1), (0, 3)))),
    # 1 x 129 x 129 output pixels >= MIN_LOOP_PIXELS: the row-block kernel-gradient loop (the
    # test makes the im2col budget zero for the cases named *_loop and *_by_tap)
    "5x5_asym_loop": ((1, 130, 130, 3), dict(features=4, kernel_size=(5, 5), padding=((2, 1), (0, 3)))),
    "3x3_same_loop": ((1, 130, 130, 3), dict(features=4, kernel_size=(3, 3), padding="SAME", use_bias=False)),
    # the Winograd kernel gradient (the test makes its channel threshold zero), odd sizes
    "3x3_asym_winograd": ((2, 9, 11, 3), dict(features=4, kernel_size=(3, 3), padding=((2, 0), (0, 1)))),
    # 100 x 100 output pixels < MIN_LOOP_PIXELS: one matmul per tap
    "3x3_same_by_tap": ((1, 100, 100, 3), dict(features=4, kernel_size=(3, 3), padding="SAME")),
    # stride 2 falls back to lax.conv_general_dilated
    "3x3_stride2": ((1, 130, 130, 3), dict(features=4, kernel_size=(3, 3), strides=(2, 2), padding=((1, 1), (1, 1)))),
    "1x1_stride2": ((2, 9, 11, 3), dict(features=4, kernel_size=(1, 1), strides=(2, 2))),
}


def output_size(shape, kwargs):
    """(H', W') of a stride-1 conv of a (B, H, W, C) input."""
    kh, kw = kwargs["kernel_size"]
    padding = kwargs.get("padding", "SAME")
    pads = lax.padtype_to_pads(shape[1:3], (kh, kw), (1, 1), padding) if isinstance(padding, str) else padding
    return shape[1] + sum(pads[0]) - kh + 1, shape[2] + sum(pads[1]) - kw + 1


@pytest.mark.parametrize("case", list(CONV_CASES))
def test_conv_matches_flax_conv(case, monkeypatch):
    shape, kwargs = CONV_CASES[case]
    if case.endswith(("_loop", "_by_tap")):
        monkeypatch.setattr(conv, "IM2COL_BYTES", 0)
    if case.endswith("_winograd"):
        monkeypatch.setattr(conv, "WINOGRAD_MIN_CHANNELS", 0)
    ours, flax_conv = Fast(nn.Conv(**kwargs)), nn.Conv(**kwargs)
    x = random(shape, 1)
    key = jax.random.key(3)
    params = ours.init(key, x)
    assert_bitwise(params, flax_conv.init(key, x), "init")
    if "bias" in params["params"]:  # initialised to zeros: make it count
        params = {"params": {**params["params"], "bias": random(params["params"]["bias"].shape, 4)}}

    y = jax.jit(ours.apply)(params, x)
    y_ref = jax.jit(flax_conv.apply)(params, x)
    one_by_one = kwargs["kernel_size"] == (1, 1) and "strides" not in kwargs
    if one_by_one:  # an einsum (test_1x1_conv_is_an_einsum), not a convolution
        assert_close(y, y_ref, 1e-6, "forward")
    else:
        assert_bitwise(y, y_ref, "forward")

    w = random(y_ref.shape, 5)

    def loss_fn(module):
        return lambda p, x: jnp.sum(w * module.apply(p, x))

    grads = jax.jit(jax.grad(loss_fn(ours), (0, 1)))(params, x)
    grads_ref = jax.jit(jax.grad(loss_fn(flax_conv), (0, 1)))(params, x)
    assert_close(grads, grads_ref, 1e-5, "gradients")

    # the case exercises the path it is named for: the kernel gradient's fori_loop (a scan)
    # exactly for the cases named *_loop and *_winograd; the im2col or one matmul per tap for
    # the others
    if not one_by_one:
        jaxpr = str(jax.make_jaxpr(jax.grad(loss_fn(ours), (0, 1)))(params, x))
        assert ("scan[" in jaxpr or "while[" in jaxpr) == case.endswith(("_loop", "_winograd"))
        if "strides" not in kwargs:
            expected = ("row_blocks" if case.endswith("_loop") else
                        "winograd" if case.endswith("_winograd") else
                        "by_tap" if case.endswith("_by_tap") else "im2col")
            out_shape = (shape[0], *output_size(shape, kwargs), kwargs["features"])
            assert conv.kernel_gradient_method(shape, out_shape, kwargs["kernel_size"]) == expected


@pytest.mark.parametrize("padding", [((0, 0), (0, 0)), "SAME", "VALID"])
def test_1x1_conv_is_an_einsum(padding):
    x = random((2, 9, 11, 3), 1)
    kernel = random((1, 1, 3, 5), 2)
    jaxpr = str(jax.make_jaxpr(lambda x, k: conv.conv_general_dilated(x, k, (1, 1), padding, dimension_numbers=NHWC))(
        x, kernel))
    assert "conv_general_dilated" not in jaxpr and "dot_general" in jaxpr


def test_conv_general_dilated_is_lax_outside_nhwc():
    """Other layouts and grouped convs are lax.conv_general_dilated itself (bitwise)."""
    x, k = random((2, 3, 12, 10), 1), random((4, 3, 3, 3), 2)  # NCHW / OIHW
    args = ((1, 1), ((1, 1), (1, 1)))
    got = jax.jit(lambda x, k: conv.conv_general_dilated(x, k, *args, dimension_numbers=("NCHW", "OIHW", "NCHW")))
    want = jax.jit(lambda x, k: lax.conv_general_dilated(x, k, *args, dimension_numbers=("NCHW", "OIHW", "NCHW")))
    assert_bitwise(got(x, k), want(x, k))
    x, k = random((1, 130, 130, 4), 1), random((3, 3, 2, 6), 2)  # 2 groups, NHWC, above the loop size
    got = jax.jit(lambda x, k: conv.conv_general_dilated(x, k, *args, dimension_numbers=NHWC, feature_group_count=2))
    want = jax.jit(lambda x, k: lax.conv_general_dilated(x, k, *args, dimension_numbers=NHWC, feature_group_count=2))
    assert_bitwise(got(x, k), want(x, k))


# ------------------------------------------------------------------------------- kernel_gradient
def stride1_case(kernel_size, pads):
    """A stride-1 conv's input (2, 11, 7, 3), kernel (kh, kw, 3, 4) and output gradient."""
    kh, kw = kernel_size
    out_h, out_w = 11 + sum(pads[0]) - kh + 1, 7 + sum(pads[1]) - kw + 1
    return random((2, 11, 7, 3), 1), random((kh, kw, 3, 4), 2), random((2, out_h, out_w, 4), 3)


@pytest.mark.parametrize("kernel_size, pads", [((3, 3), ((1, 1), (1, 1))), ((3, 3), ((2, 0), (0, 1))),
                                               ((3, 2), ((2, 0), (0, 1))), ((5, 5), ((2, 1), (0, 3)))])
def test_kernel_gradient_matches_autodiff(kernel_size, pads):
    x, kernel, g = stride1_case(kernel_size, pads)
    out_h, out_w = g.shape[1:3]

    def conv_of_kernel(k):
        return lax.conv_general_dilated(x, k, (1, 1), pads, dimension_numbers=NHWC)

    want = jax.jit(lambda g: jax.vjp(conv_of_kernel, kernel)[1](g)[0])(g)
    static = dict(static_argnums=(2, 3))
    ways = {"kernel_gradient": jax.jit(conv.kernel_gradient, static_argnums=(2, 3, 4)),
            "im2col": jax.jit(conv.kernel_gradient_im2col, **static),
            "by_tap": jax.jit(conv.kernel_gradient_by_tap, **static)}
    loop = jax.jit(conv.kernel_gradient_row_blocks, static_argnums=(2, 3, 4, 5))
    # rows per block: 1 (block_pixels 1), 3 (not dividing out_h), all in one block with zero rows
    for block_pixels in (1, 6 * out_w, 10_000):
        rows = max(1, round(block_pixels / (2 * out_w)))
        assert block_pixels != 6 * out_w or out_h % rows
        for channels_first in (True, False):
            ways[f"row_blocks, {block_pixels} pixels per block, channels_first={channels_first}"] = (
                functools.partial(loop, block_pixels=block_pixels, channels_first=channels_first))
    if kernel_size == (3, 3):
        # blocks of one tile row (2 output rows), of two or three, all in one block
        winograd = jax.jit(conv.kernel_gradient_winograd, static_argnums=(2, 3))
        for block_pixels in (1, 60, 10_000):
            ways[f"winograd, {block_pixels} pixels per block"] = (
                lambda x, g, _, pads, block_pixels=block_pixels: winograd(x, g, pads, block_pixels))
    for name, way in ways.items():
        got = way(x, g, kernel_size, pads)
        assert got.shape == kernel.shape and got.dtype == jnp.float32
        assert_close(got, want, 1e-5, f"kernel gradient, {name}")


def test_winograd_kernel_gradient_in_float64_and_where_it_is_taken(x64):
    """The Winograd way in float64 matches the direct sum to float64 rounding (its transforms
    and sums stay float64), and is the way of the `paper` UNet's wide 3x3 layers only."""
    pads = ((1, 1), (1, 1))
    x, g = random((2, 9, 12, 5), 1, dtype=jnp.float64), random((2, 9, 12, 6), 2, dtype=jnp.float64)
    want = jax.jit(conv.kernel_gradient_im2col, static_argnums=(2, 3))(x, g, (3, 3), pads)
    got = jax.jit(conv.kernel_gradient_winograd, static_argnums=(2, 3))(x, g, pads, 30)
    assert got.dtype == jnp.float64
    assert_close(got, want, 1e-13, "float64 Winograd kernel gradient")
    method = conv.kernel_gradient_method
    assert method((1, 64, 80, 256), (1, 64, 80, 128), (3, 3)) == "winograd"
    assert method((1, 128, 160, 64), (1, 128, 160, 64), (3, 3)) != "winograd"
    assert method((1, 64, 80, 256), (1, 64, 80, 128), (5, 5)) != "winograd"


@pytest.mark.parametrize("kernel_size, pads", [((3, 3), ((1, 1), (1, 1))), ((3, 2), ((2, 0), (0, 1))),
                                               ((5, 5), ((2, 1), (0, 3))), ((3, 3), ((3, 0), (1, 4)))])
def test_input_gradient_matches_autodiff(kernel_size, pads):
    """The flipped-kernel convolution, and XLA's own where a padding exceeds kh - 1 (last case)."""
    x, kernel, g = stride1_case(kernel_size, pads)
    want = jax.jit(lambda g: jax.vjp(
        lambda x: lax.conv_general_dilated(x, kernel, (1, 1), pads, dimension_numbers=NHWC), x)[1](g)[0])(g)
    got = jax.jit(conv.input_gradient, static_argnums=(2,))(g, kernel, pads)
    assert got.shape == x.shape
    assert_close(got, want, 1e-5, "input gradient")


# ---------------------------------------------------------------------------- upsample / ConvTranspose
@pytest.mark.parametrize("k", [2, 4])
def test_upsample_by_matmul_formula(k):
    x = random((2, 3, 2, 3), 1)
    kernel = random((k, k, 3, 5), 2)
    got = np.asarray(jax.jit(upsample_by_matmul)(x, kernel))
    xn, kn = np.asarray(x, np.float64), np.asarray(kernel, np.float64)
    b, h, w, c_in = xn.shape
    want = np.zeros((b, k * h, k * w, kn.shape[-1]))
    for bi in range(b):
        for i in range(h):
            for j in range(w):
                for p in range(k):
                    for q in range(k):
                        for o in range(kn.shape[-1]):
                            want[bi, k * i + p, k * j + q, o] = sum(xn[bi, i, j, c] * kn[p, q, c, o]
                                                                    for c in range(c_in))
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("k", [2, 4])
def test_conv_transpose_matches_flax(k):
    x = random((2, 3, 5, 3), 1)
    flax_ct = nn.ConvTranspose(6, (k, k), strides=(k, k), padding="VALID")
    ours = Fast(flax_ct)
    key = jax.random.key(7)
    params = ours.init(key, x)
    assert_bitwise(params, flax_ct.init(key, x), "init")
    params = {"params": {**params["params"], "bias": random((6,), 4)}}
    y = jax.jit(ours.apply)(params, x)
    y_ref = jax.jit(flax_ct.apply)(params, x)
    assert y.shape == y_ref.shape == (2, 3 * k, 5 * k, 6)
    assert_close(y, y_ref, 1e-6, "forward")
    assert "conv_general_dilated" not in str(jax.make_jaxpr(ours.apply)(params, x))  # the matmul
    w = random(y.shape, 5)
    grads = jax.jit(jax.grad(lambda p, x: jnp.sum(w * ours.apply(p, x)), (0, 1)))(params, x)
    grads_ref = jax.jit(jax.grad(lambda p, x: jnp.sum(w * flax_ct.apply(p, x)), (0, 1)))(params, x)
    assert_close(grads, grads_ref, 1e-5, "gradients")


@pytest.mark.parametrize("shape", [(2, 5, 3), (7, 3)])
def test_dense_matches_flax_dense(shape):
    """Same parameters; forward and gradients through the 1x1 matmul's custom VJP (on CPU)."""
    x = random(shape, 1)
    ours, flax_dense = Fast(nn.Dense(6)), nn.Dense(6)
    params = ours.init(jax.random.key(3), x)
    assert_bitwise(params, flax_dense.init(jax.random.key(3), x), "init")
    params = {"params": {**params["params"], "bias": random((6,), 4)}}
    assert "custom_vjp_call" in str(jax.make_jaxpr(ours.apply)(params, x))
    y = jax.jit(ours.apply)(params, x)
    assert_close(y, jax.jit(flax_dense.apply)(params, x), 1e-6, "forward")
    w = random(y.shape, 5)
    grads = jax.jit(jax.grad(lambda p, x: jnp.sum(w * ours.apply(p, x)), (0, 1)))(params, x)
    grads_ref = jax.jit(jax.grad(lambda p, x: jnp.sum(w * flax_dense.apply(p, x)), (0, 1)))(params, x)
    assert_close(grads, grads_ref, 1e-5, "gradients")


def test_dot_general_is_lax_outside_a_last_axis_matmul():
    x, k = random((4, 3, 5), 1), random((4, 6), 2)  # contracts x's first axis
    numbers = (((0,), (0,)), ((), ()))
    assert "custom_vjp_call" not in str(jax.make_jaxpr(lambda x, k: conv.dot_general(x, k, numbers))(x, k))
    assert_bitwise(jax.jit(lambda x, k: conv.dot_general(x, k, numbers))(x, k),
                   jax.jit(lambda x, k: lax.dot_general(x, k, numbers))(x, k))


# ---------------------------------------------------------------------------------- attention
def plain_attention(q, k, v, scale):
    """The plain formula, as `attend` lays it out: softmax in float32, autodiff's backward."""
    logits = jnp.einsum("bhqd,bhkd->bhqk", q * jnp.asarray(scale, q.dtype), k).astype(jnp.float32)
    weights = jax.nn.softmax(logits, axis=-1)
    return jnp.einsum("bhqk,bhkd->bhqd", weights.astype(v.dtype), v)


def attention_and_grads(fn, q, k, v, w, scale):
    value = jax.jit(fn, static_argnums=3)(q, k, v, scale)
    grads = jax.jit(jax.grad(lambda q, k, v: jnp.sum(w * fn(q, k, v, scale)), (0, 1, 2)))(q, k, v)
    return value, grads


def test_softmax_attention_float32():
    b, heads, n, d = 2, 3, 7, 8
    q, k, v = (random((b, heads, n, d), seed, 2.0) for seed in (1, 2, 3))  # scale 2: peaked weights
    w = random((b, heads, n, d), 4)
    out, grads = attention_and_grads(dinov2.softmax_attention, q, k, v, w, d**-0.5)
    out_ref, grads_ref = attention_and_grads(plain_attention, q, k, v, w, d**-0.5)
    assert_bitwise(out, out_ref, "forward")
    assert_close(grads, grads_ref, 1e-5, "gradients")


@pytest.fixture
def x64():
    before = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    try:
        yield
    finally:
        jax.config.update("jax_enable_x64", before)


def test_softmax_attention_float64_where_the_float32_softmax_is_exact(x64):
    """The backward formula to ~1e-12 in float64.

    The softmax runs in float32 even for float64 inputs (forward and backward), and the custom
    backward takes sum_k weights * dweights as g . out (the two differ by float32 rounding): on
    random float64 inputs both its gradient and autodiff's agree only to ~3e-7 (dq, dk). So the
    inputs are built for the float32 steps to be exact: every query's logits are 800 for two keys
    and below 60 for the rest, so the weights are exactly 1/2, 1/2 and 0 (exp(-740) underflows in
    float32), and v and the output cotangent hold small integers, so dweights = v . g, g . out
    and the weights' gradient are exact dyadic numbers; k's other coordinates are arbitrary
    float64 (they reach dq), carried by float64 einsums. Then the custom gradient, autodiff of the
    formula with the float32 softmax, and autodiff of an all-float64 softmax (which differs by
    weights ~exp(-740)) must agree to float64 rounding.
    """
    b, heads, n, d = 1, 2, 8, 4  # scale 0.5: exact
    rng = np.random.default_rng(0)
    key_slot = np.arange(n) % d  # key j is attended by the queries whose slot m == j mod d
    k = rng.uniform(-3, 3, (b, heads, n, d))
    k[..., np.arange(n), key_slot] = 40.0
    query_slot = rng.integers(0, d, (b, heads, n))
    q = np.where(np.arange(d) == query_slot[..., None], 40.0, 0.0)  # q_i = 40 e_m: logit 0.5*40*k_jm
    # q has one nonzero coordinate per row, so dq's other coordinates come from k's random ones
    v = rng.integers(-4, 5, (b, heads, n, d)).astype(np.float64)
    w = rng.integers(-4, 5, (b, heads, n, d)).astype(np.float64)
    q, k, v, w = (jnp.asarray(a, jnp.float64) for a in (q, k, v, w))

    def all_float64_attention(q, k, v, scale):
        return jnp.einsum("bhqk,bhkd->bhqd", jax.nn.softmax(jnp.einsum("bhqd,bhkd->bhqk", q * scale, k)), v)

    out, grads = attention_and_grads(dinov2.softmax_attention, q, k, v, w, 0.5)
    assert out.dtype == jnp.float64 and all(g.dtype == jnp.float64 for g in grads)
    # the construction holds: two keys of weight 1/2 per query
    weights = jax.nn.softmax(jnp.einsum("bhqd,bhkd->bhqk", q * 0.5, k).astype(jnp.float32))
    assert set(np.unique(np.asarray(weights)).tolist()) == {0.0, 0.5}
    for reference in (plain_attention, all_float64_attention):
        out_ref, grads_ref = attention_and_grads(reference, q, k, v, w, 0.5)
        assert_close(out, out_ref, 1e-12, f"forward vs {reference.__name__}")
        assert_close(grads, grads_ref, 1e-12, f"gradients vs {reference.__name__}")


# --------------------------------------------------------------------------- gelu / fence / after
def test_exact_gelu_forward_and_gradient():
    x = jnp.concatenate([jnp.linspace(-10.0, 10.0, 401), random((200,), 1, 3.0)])
    assert_bitwise(jax.jit(dinov2.exact_gelu)(x), jax.jit(lambda x: jax.nn.gelu(x, approximate=False))(x))
    w = random(x.shape, 2)
    grad = jax.jit(jax.grad(lambda x: jnp.sum(w * dinov2.exact_gelu(x))))(x)
    grad_ref = jax.jit(jax.grad(lambda x: jnp.sum(w * jax.nn.gelu(x, approximate=False))))(x)
    assert_close(grad, grad_ref, 1e-6, "vs autodiff")
    # by hand: d/dx x Phi(x) = Phi(x) + x phi(x), in float64
    xs = np.asarray(x, np.float64)
    cdf = np.array([0.5 * math.erfc(-t / math.sqrt(2.0)) for t in xs])
    pdf = np.exp(-0.5 * xs * xs) / math.sqrt(2.0 * math.pi)
    assert_close(grad, np.asarray(w, np.float64) * (cdf + xs * pdf), 1e-6, "vs formula")


def test_gradient_fence_and_after():
    x, w = random((2, 5, 4), 1), random((2, 5, 4), 2)
    assert_bitwise(jax.jit(layers.gradient_fence)(x), x, "fence forward")
    grad = jax.jit(jax.grad(lambda x: jnp.sum(w * layers.gradient_fence(x))))(x)
    assert_bitwise(grad, w, "fence gradient")
    assert_bitwise(jax.jit(conv.materialize)(w), w, "materialize")
    assert np.isnan(np.asarray(jax.jit(conv.materialize)(w.at[0, 0, 0].set(jnp.nan)))).all()
    # the conditional that makes XLA:CPU compute the array whole survives optimisation
    hlo = jax.jit(lambda x: conv.materialize(x * 2.0) + 1.0).lower(x).compile().as_text()
    assert "conditional(" in hlo
    g = random((3, 6), 3, 1e3)
    assert_bitwise(jax.jit(dinov2.after)(x, g), x, "after")
    # XLA keeps the dependence (it cannot fold x + 0 * g[0]): an inf there spreads
    assert np.isnan(np.asarray(jax.jit(dinov2.after)(x, g.at[0, 0].set(jnp.inf)))).all()


# ------------------------------------------------------------------------ whole backbone, tiny
def test_vit_gradients_match_plain_autodiff(monkeypatch):
    """The tiny preset's DINOv2 backbone (4 blocks, every block tapped), where all custom VJPs
    sit (the DPT head has none; the full model would double the compile time): under the CPU
    layers (dense layers, block fences) against plain Flax with plain attention and GELU."""
    cfg = depth_anything_config("tiny")
    params = random_params(cfg)["pretrained"]
    vit = DinoVisionTransformer(cfg.embed_dim, cfg.depth, cfg.num_heads, cfg.taps, cfg.mlp_ratio, cfg.ffn,
                                cfg.patch_size, cfg.image_size, cfg.pos_embed_mode)
    images = random((1, 28, 42, 3), 1)
    weights = [random((1, 6, cfg.embed_dim), 2 + i) for i in range(len(cfg.taps))]

    def gradients(apply):
        # a fresh function each time: jit traces it again, with whatever dinov2's names hold now
        def loss(params):
            taps = apply({"params": params}, images)
            return sum(jnp.sum(w * t) for w, t in zip(weights, taps))

        compiled = jax.jit(jax.grad(loss)).lower(params).compile()
        return str(jax.make_jaxpr(loss)(params)), compiled(params)

    jaxpr, grads = gradients(under_cpu_layers(vit.apply))
    # per block: attention, GELU, the fence before it, 4 dense layers
    assert jaxpr.count("custom_vjp_call") == 7 * cfg.depth
    monkeypatch.setattr(dinov2, "softmax_attention", plain_attention)
    monkeypatch.setattr(dinov2, "exact_gelu", lambda x: jax.nn.gelu(x, approximate=False))
    jaxpr_ref, grads_ref = gradients(vit.apply)
    assert "custom_vjp_call" not in jaxpr_ref
    assert_close(grads, grads_ref, 1e-5, "parameter gradients")


# --------------------------------------------------------------------------- the one choice
def test_training_layers_are_chosen_by_backend_and_an_opt_in(monkeypatch):
    """On CPU the interceptor, without the native kernel unless asked for; never built by
    default; a bad value or an unavailable kernel refused, naming the variable."""
    built = []
    monkeypatch.setattr(xla_cpu.native_conv, "available", lambda: built.append(1) or False)
    monkeypatch.setattr(xla_cpu.native_conv, "unavailable_reason", lambda: "no C++ compiler found")
    x = random((1, 8, 8, 1), 1)
    model = nn.Conv(2, (3, 3))
    params = model.init(jax.random.key(0), x)
    monkeypatch.delenv(xla_cpu.NATIVE_ENV, raising=False)

    def jaxpr():
        with xla_cpu.training_layers():
            return str(jax.make_jaxpr(model.apply)(params, x))

    assert "custom_vjp_call" in jaxpr() and built == []
    monkeypatch.setenv(xla_cpu.NATIVE_ENV, "yes")
    with pytest.raises(RunError, match=f"{xla_cpu.NATIVE_ENV}='yes': expected 0 or 1"):
        jaxpr()
    monkeypatch.setenv(xla_cpu.NATIVE_ENV, "1")
    with pytest.raises(RunError, match="not available: no C\\+\\+ compiler found"):
        jaxpr()
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert "custom_vjp_call" not in jaxpr()  # never on another backend, whatever is asked
