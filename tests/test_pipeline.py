"""raw -> MTSA-UNet -> HSV -> RGB -> Depth Anything V2 as pure jit-able functions; Stage II loss."""


import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from irdepth_jax.config import SKY_CLASS, apply_overrides, get_config
from irdepth_jax.data.synthetic import render_scene
from irdepth_jax.imaging.color import CLASS_HUES
from irdepth_jax.imaging.tonemap import clahe
from irdepth_jax.models.depth_anything import IMAGENET_MEAN, IMAGENET_STD
from irdepth_jax.models.pipeline import (depth_from_rgb, depth_input, hsv_pseudo_rgb,
                                         predict_depth, sky_mask, unet_outputs, unet_to_hsv)
from irdepth_jax.train.loop import host_image, init_unet, random_depth
from irdepth_jax.train.steps import stage2_loss_fn

CFG = get_config("tiny")


def fake_outputs(seed=0, shape=(2, 8, 10)):
    rng = np.random.default_rng(seed)
    return {"seg_logits": jnp.asarray(rng.normal(size=shape + (6,)) * 4, jnp.float32),
            "saturation": jnp.asarray(rng.uniform(size=shape + (1,)), jnp.float32),
            "recon": jnp.asarray(rng.uniform(size=shape + (1,)), jnp.float32)}


def test_hsv_channels_and_rgb_match_opencv():
    out = fake_outputs()
    hsv = np.asarray(jax.jit(unet_to_hsv, static_argnums=1)(out, "argmax"))
    labels = np.argmax(np.asarray(out["seg_logits"]), -1)
    np.testing.assert_allclose(hsv[..., 0], np.asarray(CLASS_HUES)[labels], atol=1e-6)
    np.testing.assert_allclose(hsv[..., 1], out["saturation"][..., 0])
    np.testing.assert_allclose(hsv[..., 2], out["recon"][..., 0])
    rgb = np.asarray(jax.jit(hsv_pseudo_rgb, static_argnums=1)(out, "soft"))
    soft = np.asarray(unet_to_hsv(out, "soft"))
    for b in range(soft.shape[0]):
        ref = cv2.cvtColor(np.stack([soft[b, ..., 0] * 360, soft[b, ..., 1], soft[b, ..., 2]],
                                    -1).astype(np.float32), cv2.COLOR_HSV2RGB)
        np.testing.assert_allclose(rgb[b], ref, atol=1e-5)


def test_sky_mask_and_depth_input():
    logits = np.zeros((1, 2, 2, 6), np.float32)
    logits[0, 0, 0, SKY_CLASS] = 5
    logits[0, 1, 1, 3], logits[0, 1, 0, 4] = 5, 1
    logits[0, 0, 1, SKY_CLASS], logits[0, 0, 1, 2] = 1, 2
    np.testing.assert_array_equal(sky_mask(logits)[0], [[True, False], [False, False]])
    rgb = np.random.default_rng(0).uniform(size=(2, 28, 42, 3)).astype(np.float32)
    same = depth_input(rgb, (28, 42))
    expected = (rgb - np.asarray(IMAGENET_MEAN)) / np.asarray(IMAGENET_STD)
    np.testing.assert_allclose(same, expected, rtol=1e-5, atol=1e-6)
    assert depth_input(rgb, (14, 70)).shape == (2, 14, 70, 3)


@pytest.fixture(scope="module")
def models():
    return init_unet(CFG), random_depth(CFG)


@pytest.fixture(scope="module")
def frames():
    scenes = [render_scene(i, "day", 32, 48) for i in range(2)]
    return {k: np.stack([s[k] for s in scenes]) for k in ("raw14", "depth", "valid", "seg")}


def test_predict_depth_jit(models, frames):
    unet, da = models
    run = jax.jit(predict_depth, static_argnums=3)
    out = run(unet, da, frames["raw14"], CFG)
    assert out["depth"].shape == (2, 32, 48) and out["rgb"].shape == (2, 32, 48, 3)
    depth = np.asarray(out["depth"])
    assert np.all(depth > 0) and np.all(depth < CFG.depth.max_depth)
    # the same as composing the pieces by hand
    manual = jax.jit(lambda u, d, raw: depth_from_rgb(d, hsv_pseudo_rgb(
        unet_outputs(u, raw, CFG), CFG.stage2.hue_mode), CFG))(unet, da, frames["raw14"])
    np.testing.assert_allclose(depth, manual, rtol=1e-4, atol=1e-4)
    np.testing.assert_array_equal(out["sky"], np.asarray(out["seg"]) == SKY_CLASS)


def test_stage2_loss_freezes_stage1_and_uses_its_sky(models, frames):
    unet, da = models
    ref = 70.0
    loss_fn = stage2_loss_fn(CFG, ref)
    batch = {k: frames[k] for k in ("raw14", "depth", "valid")}

    def total(params, frozen):
        return loss_fn(params, {}, frozen, batch, jax.random.PRNGKey(0))

    (loss, (metrics, _)), (g_da, g_frozen) = jax.jit(
        jax.value_and_grad(total, argnums=(0, 1), has_aux=True))(da, {"unet": unet})
    assert all(float(jnp.abs(g).max()) == 0 for g in jax.tree.leaves(g_frozen))
    assert max(float(jnp.abs(g).max()) for g in jax.tree.leaves(g_da)) > 0
    out = jax.jit(predict_depth, static_argnums=3)(unet, da, frames["raw14"], CFG)
    pred, sky = np.asarray(out["depth"]), np.asarray(out["sky"])
    per_image = [np.abs(pred[b][sky[b]] / ref - 1).mean() for b in range(2) if sky[b].any()]
    expected_sky = np.mean(per_image) if per_image else 0.0
    assert float(metrics["sky"]) == pytest.approx(expected_sky, rel=1e-4, abs=1e-6)
    assert float(loss) == pytest.approx(float(metrics["silog"]) + CFG.stage2.lambda_sky *
                                        expected_sky, rel=1e-5)


def test_baseline_preprocessing_images(frames):
    image = host_image({"raw14": frames["raw14"]}, "clahe")
    assert image.shape == (2, 32, 48, 3) and image.dtype == np.uint8
    np.testing.assert_array_equal(image[1, ..., 2], clahe(frames["raw14"][1]))
    rgb = np.zeros((2, 32, 48, 3), np.uint8)
    assert host_image({"rgb": rgb}, "rgb") is not None
    assert host_image({"raw14": frames["raw14"]}, "hsv") is None
    cfg = apply_overrides(CFG, ["stage2.preprocessing=clahe", "stage2.sky_loss=false"])
    loss_fn = stage2_loss_fn(cfg, 70.0)
    batch = {"raw14": frames["raw14"], "depth": frames["depth"], "valid": frames["valid"],
             "image": image}
    da = random_depth(cfg)
    loss, (metrics, _) = jax.jit(loss_fn)(da, {}, None, batch, jax.random.PRNGKey(0))
    assert np.isfinite(float(loss)) and "sky" not in metrics
