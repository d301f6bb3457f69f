"""Depth Anything V2 in JAX: configs, shapes, errors, numerics options, preprocessing (no torch)."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from da_params import random_params

from irdepth_jax.models.depth_anything import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    DepthAnythingV2,
    depth_anything_config,
    preprocess,
    resize_depth,
    target_size,
)
from irdepth_jax.models.dinov2 import (
    _cubic_weights,
    attend,
    attention_implementation,
    cubic_resize_matrix,
    interpolate_pos_embed,
)
from irdepth_jax.weights import expected_shapes


@pytest.fixture(scope="module")
def tiny():
    cfg = depth_anything_config("tiny")
    return cfg, random_params(cfg)


@pytest.mark.parametrize(
    "name, published",  # parameter counts published with the released checkpoints, and their rounding
    [("vits", (24.8e6, 1e5)), ("vitb", (97.5e6, 1e5)), ("vitl", (335.3e6, 1e5)), ("vitg", (1.3e9, 1e8))],
)
def test_preset_parameter_counts(name, published):
    cfg = depth_anything_config(name)
    ours = sum(int(np.prod(s)) for s in expected_shapes(cfg).values())
    # the released files also hold mask_token (D) and the unused refinenet4.resConfUnit1 (2 3x3 convs)
    official = ours + cfg.embed_dim + 2 * (cfg.features**2 * 9 + cfg.features)
    count, unit = published
    assert round(official / unit) * unit == pytest.approx(count), official


def test_preset_overrides_and_validation():
    cfg = depth_anything_config("vitl", metric=True, max_depth=20.0)
    assert (cfg.embed_dim, cfg.depth, cfg.num_heads, cfg.taps) == (1024, 24, 16, (4, 11, 17, 23))
    assert cfg.metric and cfg.max_depth == 20.0
    assert depth_anything_config("vitg").ffn == "swiglu"
    with pytest.raises(ValueError, match="unknown Depth Anything encoder"):
        depth_anything_config("vith")
    with pytest.raises(ValueError, match="unknown DepthAnythingConfig fields"):
        depth_anything_config("vits", heads=3)
    with pytest.raises(ValueError, match="taps"):
        depth_anything_config("tiny", taps=(0, 1, 2, 9))
    with pytest.raises(ValueError, match="pos_embed_mode"):
        depth_anything_config("tiny", pos_embed_mode="timm")


def test_param_tree_mirrors_official_checkpoint(tiny):
    _, params = tiny
    assert set(params) == {"pretrained", "depth_head"}
    bb, head = params["pretrained"], params["depth_head"]
    assert bb["pos_embed"].shape == (1, 37 * 37 + 1, 32)
    assert bb["blocks_3"]["attn"]["qkv"]["kernel"].shape == (32, 96)
    assert head["resize_layers_0"]["kernel"].shape == (4, 4, 8, 8)
    assert "resize_layers_2" not in head
    assert "bias" not in head["scratch"]["layer1_rn"]


def test_shapes_heads_and_errors(tiny):
    cfg, params = tiny
    x = jax.random.normal(jax.random.key(1), (2, 42, 56, 3))
    rel = jax.jit(DepthAnythingV2(cfg).apply)({"params": params}, x)
    metric_cfg = depth_anything_config("tiny", metric=True, max_depth=20.0)
    met = jax.jit(DepthAnythingV2(metric_cfg).apply)({"params": params}, x)
    assert rel.shape == met.shape == (2, 42, 56) and rel.dtype == jnp.float32
    assert float(rel.min()) >= 0.0
    assert 0.0 < float(met.min()) and float(met.max()) < 20.0
    with pytest.raises(ValueError, match="multiples of 14"):
        DepthAnythingV2(cfg).apply({"params": params}, jnp.zeros((1, 42, 50, 3)))
    with pytest.raises(ValueError, match=r"\(B, H, W, 3\)"):
        DepthAnythingV2(cfg).apply({"params": params}, jnp.zeros((1, 42, 42, 1)))


def test_intermediates_collection(tiny):
    cfg, params = tiny
    apply = jax.jit(lambda p, x: DepthAnythingV2(cfg).apply({"params": p}, x, mutable="intermediates"))
    _, state = apply(params, jnp.zeros((1, 28, 42, 3)))
    inter = state["intermediates"]
    assert inter["pretrained"]["tap_3"][0].shape == (1, 6, 32)
    assert inter["depth_head"]["layer1"][0].shape == (1, 8, 12, 8)  # 4x the 2x3 patch grid
    assert inter["depth_head"]["layer4"][0].shape == (1, 1, 2, 32)  # stride-2 conv: ceil(2/2), ceil(3/2)
    assert inter["depth_head"]["scratch"]["path_1"][0].shape == (1, 16, 24, 16)


def test_bfloat16_close_to_float32(tiny):
    cfg, params = tiny
    x = jax.random.normal(jax.random.key(2), (1, 56, 56, 3))
    f32 = jax.jit(DepthAnythingV2(cfg).apply)({"params": params}, x)
    bf16_model = DepthAnythingV2(depth_anything_config("tiny", dtype="bfloat16"))
    bf16 = jax.jit(bf16_model.apply)({"params": params}, x)
    assert bf16.dtype == jnp.float32
    assert float(jnp.abs(bf16 - f32).max()) <= 0.05 * float(jnp.abs(f32).max())


def test_remat_same_outputs_and_gradients(tiny):
    cfg, params = tiny
    x = jax.random.normal(jax.random.key(3), (2, 28, 28, 3))

    def loss_fn(model):
        return jax.jit(jax.value_and_grad(lambda p: jnp.mean(model.apply({"params": p}, x) ** 2)))

    loss, grads = loss_fn(DepthAnythingV2(cfg))(params)
    loss_r, grads_r = loss_fn(DepthAnythingV2(depth_anything_config("tiny", remat=True)))(params)
    np.testing.assert_allclose(loss_r, loss, rtol=1e-6)
    assert jax.tree.structure(grads) == jax.tree.structure(grads_r)
    for g, g_r in zip(jax.tree.leaves(grads), jax.tree.leaves(grads_r)):
        np.testing.assert_allclose(g_r, g, rtol=1e-5, atol=1e-7)
    assert float(jnp.abs(grads["pretrained"]["blocks_0"]["attn"]["qkv"]["kernel"]).max()) > 0


def test_attention_kernel_by_backend():
    """'auto' = einsums on CPU, cuDNN flash attention on GPU for bf16 / fp16, XLA's kernel on GPU
    in float32 (cuDNN takes no float32); an explicit choice is kept; a wrong one is refused."""
    assert attention_implementation("auto", "cpu", jnp.float32) == "einsum"
    assert attention_implementation("auto", "cpu", jnp.bfloat16) == "einsum"
    assert attention_implementation("auto", "gpu", jnp.bfloat16) == "cudnn"
    assert attention_implementation("auto", "gpu", jnp.float16) == "cudnn"
    assert attention_implementation("auto", "gpu", jnp.float32) == "xla"
    assert attention_implementation("xla", "cpu", jnp.float32) == "xla"
    with pytest.raises(ValueError, match="attention 'flash'"):
        attention_implementation("flash", "cpu", jnp.float32)
    with pytest.raises(ValueError, match="attention must be one of"):
        depth_anything_config("tiny", attention="flash")


def test_attention_kernels_agree(tiny):
    """The einsums and jax.nn.dot_product_attention give the same attention, by hand-written
    softmax(q k^T / sqrt(d)) v, and the same model output."""
    qkv = jax.random.normal(jax.random.key(0), (2, 7, 3 * 3 * 8))  # B, N, (q k v) x 3 heads x 8
    q, k, v = np.moveaxis(np.asarray(qkv).reshape(2, 7, 3, 3, 8), 2, 0)
    logits = np.einsum("bqhd,bkhd->bhqk", q, k) / np.sqrt(8)
    weights = np.exp(logits - logits.max(-1, keepdims=True))
    expected = np.einsum("bhqk,bkhd->bqhd", weights / weights.sum(-1, keepdims=True), v)
    for implementation in ("einsum", "xla"):
        got = jax.jit(attend, static_argnums=(1, 2))(qkv, 3, implementation)
        np.testing.assert_allclose(got, expected.reshape(2, 7, 24), rtol=1e-5, atol=1e-6)
    cfg, params = tiny
    x = jax.random.normal(jax.random.key(3), (1, 28, 42, 3))
    outputs = [jax.jit(DepthAnythingV2(depth_anything_config("tiny", attention=a)).apply)(
        {"params": params}, x) for a in ("einsum", "xla")]
    np.testing.assert_allclose(outputs[1], outputs[0], rtol=1e-5, atol=1e-6)


def test_cubic_kernel_hand_values():
    # a = -0.75 at t = 0.5: near(0.5) = (1.25 * 0.5 - 2.25) * 0.25 + 1, far(1.5) = -0.09375
    np.testing.assert_allclose(_cubic_weights(np.array([0.5]))[0], [-0.09375, 0.59375, 0.59375, -0.09375])
    np.testing.assert_allclose(_cubic_weights(np.array([0.0]))[0], [0, 1, 0, 0], atol=1e-15)
    # 2x upsampling of 4 samples: output 3 reads x = 1.25 (taps 0..3 at t = 0.25); output 0 reads
    # x = -0.25 (taps -2..1 at t = 0.75, the three left of 0 clamped onto sample 0)
    m = cubic_resize_matrix(4, 8, 0.5)
    np.testing.assert_allclose(m[3], [-0.10546875, 0.87890625, 0.26171875, -0.03515625])
    np.testing.assert_allclose(m[0], [-0.03515625 + 0.26171875 + 0.87890625, -0.10546875, 0, 0])
    np.testing.assert_allclose(m[::-1, ::-1], m)  # mirror symmetric
    np.testing.assert_allclose(cubic_resize_matrix(10, 23, 10 / 23).sum(1), 1.0)
    np.testing.assert_allclose(cubic_resize_matrix(7, 7, 1.0), np.eye(7), atol=1e-15)


def test_pos_embed_interpolation_modes():
    pos = jax.random.normal(jax.random.key(4), (1, 37 * 37 + 1, 8))
    assert interpolate_pos_embed(pos, (37, 37)) is pos
    official = interpolate_pos_embed(pos, (9, 12), "official")
    hf = interpolate_pos_embed(pos, (9, 12), "transformers")
    assert official.shape == hf.shape == (1, 9 * 12 + 1, 8)
    np.testing.assert_array_equal(official[0, 0], pos[0, 0])  # class-token row untouched
    assert float(jnp.abs(official - hf).max()) > 1e-3  # the +0.1 offset moves the samples


@pytest.mark.parametrize("hw, expected", [((480, 640), (518, 686)), ((256, 320), (518, 644)), ((518, 518), (518, 518))])
def test_target_size_official_rule(hw, expected):
    # 480x640: scale 518/480, width 690.67 -> 49.33 * 14 rounds to 686; 256x320: 647.5 -> 46.25 -> 644
    assert target_size(*hw) == expected


def test_preprocess_matches_opencv():
    rng = np.random.default_rng(0)
    img = rng.random((2, 61, 47, 3), dtype=np.float32)
    out = np.asarray(preprocess(img, input_size=70))
    h, w = target_size(61, 47, 70)
    assert out.shape == (2, h, w, 3) and h % 14 == 0 and w % 14 == 0
    for b in range(2):
        ref = (cv2.resize(img[b], (w, h), interpolation=cv2.INTER_CUBIC) - IMAGENET_MEAN) / IMAGENET_STD
        np.testing.assert_allclose(out[b], ref, atol=2e-5)
    img_u8 = (img[0] * 255).astype(np.uint8)
    np.testing.assert_allclose(preprocess(img_u8, 70), preprocess(img_u8 / np.float32(255), 70), atol=1e-6)
    with pytest.raises(ValueError, match="RGB"):
        preprocess(np.zeros((10, 10)))


def test_preprocess_jits():
    img = jnp.ones((1, 30, 40, 3)) * 0.5
    out = jax.jit(preprocess, static_argnums=1)(img, 28)
    grey = (0.5 - np.asarray(IMAGENET_MEAN)) / np.asarray(IMAGENET_STD)
    np.testing.assert_allclose(out, np.broadcast_to(grey, out.shape), atol=1e-5)


def test_resize_depth_align_corners_hand_values():
    d = jnp.array([[0.0, 2.0], [4.0, 6.0]])
    out = resize_depth(d, (3, 3))
    np.testing.assert_allclose(out, [[0, 1, 2], [2, 3, 4], [4, 5, 6]], atol=1e-6)
    batch = jax.jit(resize_depth, static_argnums=1)(jnp.stack([d, 2 * d]), (3, 5))
    np.testing.assert_allclose(batch[1, :, 0], [0, 4, 8], atol=1e-6)  # corners map onto corners
    np.testing.assert_allclose(batch[1, 0], [0, 1, 2, 3, 4], atol=1e-6)
    np.testing.assert_allclose(resize_depth(d, (2, 2)), d, atol=1e-6)
