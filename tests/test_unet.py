"""MTSA-UNet: shapes, ranges, gradients, BatchNorm modes, presets, RGG switch, pmap BN sync.

`jax.jit(model.init)` takes ~17 s to compile on a quiet 2-core CPU (XLA compiles one threefry
program per kernel, ~90 of them, whatever the widths), so these tests take the variable tree's
structure from `jax.eval_shape(model.init, ...)` (which traces the real init) and fill it from
numpy with the same scales (LeCun-normal kernels, zero biases, unit BN scales and variances).
"""

import dataclasses
import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import traverse_util

from irdepth_jax.config import get_config
from irdepth_jax.imaging.gradients import gradient_magnitude
from irdepth_jax.imaging.raw import normalize_raw
from irdepth_jax.models.rgg import RGG
from irdepth_jax.models.unet import MTSAUNet, Upsample2x, max_pool_2x2

H, W = 50, 70  # not multiples of 16


def param_count(tree):
    return sum(int(np.prod(x.shape)) for x in jax.tree.leaves(tree))


def numpy_variables(model, raw, seed=0):
    """Variables of `model` for input `raw`, with init's structure and scales, from numpy."""
    rng = np.random.default_rng(seed)

    def fill(path, leaf):
        name = path[-1].key
        if name == "kernel":
            std = 1.0 / np.sqrt(np.prod(leaf.shape[:-1]))
            return jnp.asarray(rng.normal(0.0, std, leaf.shape), leaf.dtype)
        return (jnp.ones if name in ("scale", "var") else jnp.zeros)(leaf.shape, leaf.dtype)

    shapes = jax.eval_shape(model.init, jax.random.key(0), raw)
    return jax.tree_util.tree_map_with_path(fill, shapes)


def without_rgg(variables):
    flat = traverse_util.flatten_dict(variables)
    return traverse_util.unflatten_dict({k: v for k, v in flat.items() if "rgg" not in k})


@pytest.fixture(scope="module")
def tiny():
    cfg = get_config("tiny").unet
    model = MTSAUNet(cfg)
    rng = np.random.default_rng(0)
    counts = jnp.asarray(rng.integers(3000, 6000, (2, H, W)), jnp.uint16)
    image = normalize_raw(counts, cfg.raw_scale)  # what models.pipeline.unet_input gives the UNet
    return cfg, model, image, numpy_variables(model, image)


def apply_fn(model, train):
    if train:
        return jax.jit(functools.partial(model.apply, train=True, mutable=["batch_stats"]))
    return jax.jit(functools.partial(model.apply, train=False))


def check_outputs(out, batch, num_classes):
    assert out["recon"].shape == (batch, H, W, 1)
    assert out["saturation"].shape == (batch, H, W, 1)
    assert out["input_gradient"].shape == (batch, H, W, 1)
    assert out["seg_logits"].shape == (batch, H, W, num_classes)
    for value in out.values():
        assert value.dtype == jnp.float32 and np.isfinite(value).all()
    for key in ("recon", "saturation"):
        assert 0.0 <= float(out[key].min()) and float(out[key].max()) <= 1.0


def test_tiny_train_step_shapes_ranges_and_finite_grads(tiny):
    cfg, model, raw, variables = tiny
    count = param_count(variables['params'])
    print(f"\ntiny MTSA-UNet parameters: {count}")
    assert 1_000 <= count <= 10_000, "the tiny preset should have a few thousand parameters"

    def loss_fn(params):
        out, updates = model.apply(
            {"params": params, "batch_stats": variables["batch_stats"]},
            raw,
            train=True,
            mutable=["batch_stats"],
        )
        labels = jnp.zeros(out["seg_logits"].shape[:-1], jnp.int32)
        log_probs = jax.nn.log_softmax(out["seg_logits"])
        ce = -jnp.mean(jnp.take_along_axis(log_probs, labels[..., None], -1))
        loss = jnp.mean(jnp.abs(out["recon"] - 0.5)) + ce + jnp.mean(out["saturation"] ** 2)
        return loss, (out, updates)

    (loss, (out, updates)), grads = jax.jit(jax.value_and_grad(loss_fn, has_aux=True))(
        variables["params"]
    )
    check_outputs(out, 2, cfg.num_classes)
    assert np.isfinite(loss)
    for path, g in traverse_util.flatten_dict(grads).items():
        assert np.isfinite(g).all(), path
    for module in ("head_recon", "head_seg", "head_saturation", "enc0", "dec_seg_up0"):
        assert sum(float(jnp.abs(g).sum()) for g in jax.tree.leaves(grads[module])) > 0, module
    # the input gradient is the GCM of the input image
    np.testing.assert_allclose(out["input_gradient"], gradient_magnitude(raw[..., None]), atol=1e-6)


def test_batchnorm_train_updates_stats_and_eval_uses_running_stats(tiny):
    cfg, model, raw, variables = tiny
    other = raw.at[1].set(raw[1] ** 2)  # same first image, different second one
    train, evaluate = apply_fn(model, True), apply_fn(model, False)

    out_train, updates = train(variables, raw)
    out_train_other, _ = train(variables, other)
    out_eval, out_eval_other = evaluate(variables, raw), evaluate(variables, other)
    # train mode normalises with batch statistics: image 0 depends on image 1
    assert np.abs(out_train["recon"][0] - out_train_other["recon"][0]).max() > 1e-4
    # eval mode uses the running statistics: images are independent
    np.testing.assert_allclose(out_eval["recon"][0], out_eval_other["recon"][0], atol=1e-6)
    assert np.abs(out_eval["recon"] - out_train["recon"]).max() > 1e-4

    # first BatchNorm: new mean = momentum * 0 + (1 - momentum) * batch mean of conv0's output
    x = jnp.pad(raw[..., None], ((0, 0), (0, 14), (0, 10), (0, 0)), mode="edge")  # 50x70 -> 64x80
    conv0 = nn.Conv(cfg.widths[0], (3, 3), use_bias=False).apply(
        {"params": variables["params"]["enc0"]["conv0"]}, x
    )
    new_mean = updates["batch_stats"]["enc0"]["bn0"]["mean"]
    expected = (1 - cfg.bn_momentum) * conv0.mean((0, 1, 2))
    np.testing.assert_allclose(new_mean, expected, rtol=1e-4, atol=1e-7)


def test_the_unet_takes_a_normalised_image_not_counts(tiny):
    """(B, H, W) and (B, H, W, 1) give the same; integer counts are refused (their bit depth is
    the pipeline's to know: models.pipeline.unet_input), as are other shapes."""
    cfg, model, image, variables = tiny
    evaluate = apply_fn(model, False)
    out = evaluate(variables, image)
    check_outputs(out, 2, cfg.num_classes)
    out_nhwc = evaluate(variables, image[..., None])
    for key in out:
        np.testing.assert_array_equal(out[key], out_nhwc[key])
    counts = jnp.asarray(np.random.default_rng(1).integers(3000, 6000, (2, H, W)), jnp.uint16)
    with pytest.raises(ValueError, match="expected a float image in \\[0, 1\\], got uint16; normalise raw counts"):
        model.apply(variables, counts)
    with pytest.raises(ValueError, match="expected an image"):
        model.apply(variables, jnp.zeros((2, H, W, 3)))


def test_paper_preset_channel_widths():
    cfg = get_config("paper").unet
    assert cfg.widths == (32, 64, 128, 256) and cfg.bottleneck == 512 and cfg.num_classes == 6
    shapes = jax.eval_shape(
        MTSAUNet(cfg).init, jax.random.key(0), jax.ShapeDtypeStruct((1, 32, 32), jnp.float32)
    )["params"]
    kernels = {
        "/".join(k[:-1]): v.shape
        for k, v in traverse_util.flatten_dict(shapes).items()
        if k[-1] == "kernel"
    }
    expected = {
        "enc0/conv0": (3, 3, 1, 32),
        "enc0/conv1": (3, 3, 32, 32),
        "enc1/conv0": (3, 3, 32, 64),
        "enc2/conv0": (3, 3, 64, 128),
        "enc3/conv1": (3, 3, 256, 256),
        "bottleneck/conv0": (3, 3, 256, 512),
        "bottleneck/conv1": (3, 3, 512, 512),
        "head_recon": (1, 1, 32, 1),
        "head_seg": (1, 1, 32, 6),
        "head_saturation": (1, 1, 32, 1),
    }
    for task in ("recon", "seg", "grad"):
        expected[f"dec_{task}_up3/up"] = (2, 2, 512, 256)
        expected[f"dec_{task}_up3/fuse/conv0"] = (3, 3, 512, 256)
        expected[f"dec_{task}_up0/up"] = (2, 2, 64, 32)
        expected[f"dec_{task}_up0/fuse/conv1"] = (3, 3, 32, 32)
        expected[f"dec_{task}_up0/rgg/input_proj"] = (3, 3, 1, 32)
    for name, shape in expected.items():
        assert kernels[name] == shape, name
    print(f"\npaper MTSA-UNet parameters: {param_count(shapes)}")


def test_rgg_switch_changes_param_tree_and_output(tiny):
    cfg, model, raw, variables = tiny
    plain = MTSAUNet(dataclasses.replace(cfg, use_rgg=False))
    spec = jax.ShapeDtypeStruct(raw.shape, raw.dtype)
    def param_tree(m):
        return traverse_util.flatten_dict(jax.eval_shape(m.init, jax.random.key(0), spec)["params"])

    tree_rgg, tree_plain = param_tree(model), param_tree(plain)
    rgg_keys = set(tree_rgg) - set(tree_plain)
    assert set(tree_plain) < set(tree_rgg)
    blocks = {f"dec_{t}_up{i}" for t in ("recon", "seg", "grad") for i in range(4)}
    assert {k[0] for k in rgg_keys} == blocks
    assert all(k[1] == "rgg" for k in rgg_keys)

    out_rgg = apply_fn(model, False)(variables, raw)
    out_plain = apply_fn(plain, False)(without_rgg(variables), raw)
    check_outputs(out_plain, 2, cfg.num_classes)
    assert np.abs(out_rgg["recon"] - out_plain["recon"]).max() > 1e-4


def test_rgg_attention_scales_both_inputs_by_one_plus_a():
    rng = jax.random.split(jax.random.key(1), 4)
    up = jax.random.normal(rng[0], (1, 8, 8, 3))
    skip = jax.random.normal(rng[1], (1, 8, 8, 3))
    grad = jnp.abs(jax.random.normal(rng[2], (1, 8, 8, 1)))
    params = RGG(alpha=0.5).init(rng[3], up, skip, grad)
    half = jax.jit(RGG(alpha=0.5).apply)
    features_only = jax.jit(RGG(alpha=1.0).apply)
    new_up, new_skip = half(params, up, skip, grad)
    scale_up, scale_skip = new_up / up, new_skip / skip
    np.testing.assert_allclose(scale_up, scale_skip, rtol=1e-5)
    assert float(scale_up.min()) > 1.0 and float(scale_up.max()) < 2.0
    # the input-gradient branch matters unless alpha = 1
    assert np.abs(half(params, up, skip, grad * 5)[0] - new_up).max() > 1e-5
    np.testing.assert_allclose(
        features_only(params, up, skip, grad * 5)[0],
        features_only(params, up, skip, grad)[0],
        atol=1e-6,
    )


@pytest.mark.multidevice
def test_pmap_batchnorm_statistics_match_the_whole_batch(tiny, four_devices):
    cfg, _, _, variables = tiny
    raw = jnp.asarray(np.random.default_rng(5).uniform(0.2, 0.4, (4, H, W)), jnp.float32)
    raw = raw.at[2:].set(raw[2:] / 2)  # device-local statistics would differ clearly
    mapped = MTSAUNet(cfg, axis_name="batch")
    step = jax.pmap(
        functools.partial(mapped.apply, train=True, mutable=["batch_stats"]),
        axis_name="batch",
        in_axes=(None, 0),
        devices=four_devices[:2],
    )
    out_pmap, upd_pmap = step(variables, raw.reshape(2, 2, H, W))
    out_one, upd_one = apply_fn(MTSAUNet(cfg), True)(variables, raw)
    np.testing.assert_allclose(
        np.asarray(out_pmap["recon"]).reshape(4, H, W, 1), out_one["recon"], atol=2e-5
    )
    np.testing.assert_allclose(
        np.asarray(out_pmap["seg_logits"]).reshape(4, H, W, -1), out_one["seg_logits"], atol=1e-4
    )
    for path, stat in traverse_util.flatten_dict(upd_one["batch_stats"]).items():
        per_device = traverse_util.flatten_dict(upd_pmap["batch_stats"])[path]
        np.testing.assert_allclose(per_device[0], stat, rtol=1e-3, atol=1e-5, err_msg=str(path))
        np.testing.assert_allclose(per_device[1], stat, rtol=1e-3, atol=1e-5, err_msg=str(path))


def test_upsample2x_matches_torch_conv_transpose():
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(7)
    x = rng.normal(size=(2, 3, 5, 4)).astype(np.float32)  # NHWC
    weight = rng.normal(size=(4, 6, 2, 2)).astype(np.float32)  # torch (in, out, kh, kw)
    ref = torch.nn.functional.conv_transpose2d(
        torch.from_numpy(x.transpose(0, 3, 1, 2)), torch.from_numpy(weight), stride=2
    ).numpy().transpose(0, 2, 3, 1)
    ours = Upsample2x(6).apply({"params": {"kernel": weight.transpose(2, 3, 0, 1)}}, x)
    np.testing.assert_allclose(ours, ref, atol=1e-5)


def test_max_pool_2x2_matches_flax_values_and_gradients():
    x = jnp.asarray(np.random.default_rng(8).normal(size=(2, 6, 8, 3)), jnp.float32)
    pool = functools.partial(nn.max_pool, window_shape=(2, 2), strides=(2, 2))
    np.testing.assert_array_equal(max_pool_2x2(x), pool(x))
    weights = jnp.arange(2 * 3 * 4 * 3, dtype=jnp.float32).reshape(2, 3, 4, 3)
    grad_ours = jax.grad(lambda v: jnp.sum(max_pool_2x2(v) * weights))(x)
    grad_flax = jax.grad(lambda v: jnp.sum(pool(v) * weights))(x)
    np.testing.assert_array_equal(grad_ours, grad_flax)
