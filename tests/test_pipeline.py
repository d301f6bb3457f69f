"""raw -> MTSA-UNet -> HSV -> RGB -> Depth Anything V2: `run_pipeline`, the one inference path,
checked against an independent composition (OpenCV colour conversion and resize, a hand-written
align-corners bilinear), and the Stage II loss that trains through it."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from irdepth_jax.config import SKY_CLASS, apply_overrides, get_config
from irdepth_jax.data.source import host_image
from irdepth_jax.data.synthetic import render_scene
from irdepth_jax.imaging.color import CLASS_HUES
from irdepth_jax.imaging.tonemap import clahe
from irdepth_jax.models.depth_anything import IMAGENET_MEAN, IMAGENET_STD, DepthAnythingV2, network_input
from irdepth_jax.models.pipeline import depth_model_config, raw_to_depth, run_pipeline, unet_outputs, unet_to_hsv
from irdepth_jax.runs.variables import init_unet, random_depth
from irdepth_jax.train.steps import stage2_loss_fn

CFG = get_config("tiny")


def fake_outputs(seed=0, shape=(2, 8, 10)):
    rng = np.random.default_rng(seed)
    return {"seg_logits": jnp.asarray(rng.normal(size=shape + (6,)) * 4, jnp.float32),
            "saturation": jnp.asarray(rng.uniform(size=shape + (1,)), jnp.float32),
            "recon": jnp.asarray(rng.uniform(size=shape + (1,)), jnp.float32)}


def opencv_rgb(hsv: np.ndarray) -> np.ndarray:
    """HSV (B, H, W, 3) in [0, 1] -> RGB by OpenCV (hue in degrees)."""
    return np.stack([cv2.cvtColor(np.stack([h[..., 0] * 360, h[..., 1], h[..., 2]], -1)
                                  .astype(np.float32), cv2.COLOR_HSV2RGB) for h in hsv])


def align_corners_bilinear(x: np.ndarray, size) -> np.ndarray:
    """(B, H, W) -> (B, h, w), output o reads input o * (in - 1) / (out - 1), by hand."""
    def axis(a, n_out, ax):
        n_in = a.shape[ax]
        src = np.arange(n_out) * ((n_in - 1) / (n_out - 1))
        lo = np.floor(src).astype(int)
        hi = np.minimum(lo + 1, n_in - 1)
        shape = [1] * a.ndim
        shape[ax] = n_out
        t = (src - lo).reshape(shape)
        return np.take(a, lo, ax) * (1 - t) + np.take(a, hi, ax) * t
    return axis(axis(x, size[0], 1), size[1], 2)


def test_hsv_channels_and_rgb_match_opencv():
    out = fake_outputs()
    hsv = np.asarray(jax.jit(unet_to_hsv, static_argnums=1)(out, "argmax"))
    labels = np.argmax(np.asarray(out["seg_logits"]), -1)
    np.testing.assert_allclose(hsv[..., 0], np.asarray(CLASS_HUES)[labels], atol=1e-6)
    np.testing.assert_allclose(hsv[..., 1], out["saturation"][..., 0])
    np.testing.assert_allclose(hsv[..., 2], out["recon"][..., 0])


def test_network_input_is_opencv_bicubic_then_imagenet_normalisation():
    """One pre-processing for training and inference: OpenCV's INTER_CUBIC (a = -0.75, the
    official transform), down and up, then (x - mean) / std."""
    rgb = np.random.default_rng(0).uniform(size=(2, 28, 42, 3)).astype(np.float32)
    norm = lambda x: (x - np.asarray(IMAGENET_MEAN)) / np.asarray(IMAGENET_STD)  # noqa: E731
    run = jax.jit(network_input, static_argnums=1)
    np.testing.assert_allclose(run(rgb, (28, 42)), norm(rgb), rtol=1e-5, atol=1e-6)
    for size in ((14, 70), (56, 28)):
        ref = np.stack([cv2.resize(x, size[::-1], interpolation=cv2.INTER_CUBIC) for x in rgb])
        np.testing.assert_allclose(run(rgb, size), norm(ref), atol=2e-5)


@pytest.fixture(scope="module")
def models():
    return init_unet(CFG), random_depth(CFG)


@pytest.fixture(scope="module")
def frames():
    scenes = [render_scene(i, "day", 32, 48) for i in range(2)]
    return {k: np.stack([s[k] for s in scenes]) for k in ("raw14", "depth", "valid", "seg")}


def test_run_pipeline_equals_an_independent_composition(models, frames):
    """UNet -> HSV (ours) -> RGB by OpenCV -> resize by OpenCV -> the ViT -> hand-written
    align-corners resize: the same depth as the jitted pipeline."""
    unet, da = models
    out = run_pipeline(unet, da, frames["raw14"], CFG)
    depth = np.asarray(out["depth"])
    assert depth.shape == (2, 32, 48) and out["rgb"].shape == (2, 32, 48, 3)
    assert np.all(depth > 0) and np.all(depth < CFG.depth.max_depth)

    outputs = jax.jit(unet_outputs, static_argnums=2)(unet, frames["raw14"], CFG)
    hsv = np.asarray(unet_to_hsv(outputs, CFG.stage2.hue_mode))
    rgb = opencv_rgb(hsv)
    np.testing.assert_allclose(out["rgb"], rgb, atol=1e-4)  # OpenCV float32 hue sectors
    np.testing.assert_allclose(out["hsv"], hsv, atol=1e-4)  # fused differently by XLA
    size = (CFG.depth.input_height, CFG.depth.input_width)
    x = np.stack([cv2.resize(r, size[::-1], interpolation=cv2.INTER_CUBIC) for r in rgb])
    x = (x - np.asarray(IMAGENET_MEAN)) / np.asarray(IMAGENET_STD)
    small = jax.jit(DepthAnythingV2(depth_model_config(CFG)).apply)({"params": da}, jnp.asarray(x))
    manual = align_corners_bilinear(np.asarray(small, np.float64), (32, 48))
    np.testing.assert_allclose(depth, manual, rtol=1e-4, atol=1e-4)
    seg = np.argmax(np.asarray(outputs["seg_logits"]), -1)
    np.testing.assert_array_equal(out["seg"], seg)
    np.testing.assert_array_equal(out["sky"], seg == SKY_CLASS)
    # the export's function: the same program less the unused outputs (XLA fuses it otherwise)
    np.testing.assert_allclose(raw_to_depth(unet, da, frames["raw14"], CFG), depth, rtol=1e-6)


def test_run_pipeline_of_a_stage1_model_and_of_a_baseline(models, frames):
    unet, da = models
    stage1 = run_pipeline(unet, None, frames["raw14"], CFG)
    assert stage1["depth"] is None and stage1["hsv"].shape == (2, 32, 48, 3)
    cfg = apply_overrides(CFG, ["stage2.preprocessing=clahe", "stage2.sky_loss=false"])
    image = host_image({"raw14": frames["raw14"]}, "clahe")
    out = run_pipeline(None, da, None, cfg, image=image)
    assert out["hsv"] is None and out["sky"] is None
    np.testing.assert_allclose(out["rgb"], image / np.float32(255), atol=1e-7)
    with pytest.raises(ValueError, match="pass it as `image`"):
        run_pipeline(None, da, None, cfg)
    # 'value': the HSV image's V channel as grey, made by the same Stage I model
    value = run_pipeline(unet, da, frames["raw14"], apply_overrides(CFG, ["stage2.preprocessing=value"]))
    np.testing.assert_array_equal(value["rgb"], np.repeat(np.asarray(stage1["hsv"])[..., 2:], 3, -1))
    assert host_image({"raw14": frames["raw14"]}, "value") is None
    with pytest.raises(ValueError, match="needs the Stage I model"):
        run_pipeline(None, da, frames["raw14"], CFG)


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
    out = run_pipeline(unet, da, frames["raw14"], CFG)
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
    blank = host_image({"raw14": frames["raw14"]}, "blank")
    assert blank.shape == (2, 32, 48, 3) and blank.dtype == np.uint8 and (blank == 128).all()
    cfg = apply_overrides(CFG, ["stage2.preprocessing=clahe", "stage2.sky_loss=false"])
    loss_fn = stage2_loss_fn(cfg, 70.0)
    batch = {"raw14": frames["raw14"], "depth": frames["depth"], "valid": frames["valid"],
             "image": image}
    da = random_depth(cfg)
    loss, (metrics, _) = jax.jit(loss_fn)(da, {}, None, batch, jax.random.PRNGKey(0))
    assert np.isfinite(float(loss)) and "sky" not in metrics


@pytest.mark.parametrize("raw_scale", ["fixed", "percentile"])
def test_16_bit_counts_are_normalised_once_by_the_pipeline_to_their_full_scale(raw_scale):
    """`unet_outputs` (the public path from counts) gives the UNet 16-bit counts / (2^16 - 1)
    with data.raw_bits=16, not a 14-bit reading of them; the UNet itself takes only the image."""
    from irdepth_jax.models.unet import MTSAUNet

    cfg = apply_overrides(CFG, ["data.raw_bits=16", f"unet.raw_scale={raw_scale}"])
    unet = init_unet(cfg)
    counts = np.random.default_rng(3).integers(20000, 60000, (1, 16, 20)).astype(np.uint16)
    got = jax.jit(unet_outputs, static_argnums=2)(unet, jnp.asarray(counts), cfg)
    image = counts.astype(np.float64) / (2**16 - 1)
    if raw_scale == "percentile":
        lo, hi = np.percentile(image, [1, 99])
        image = np.clip((image - lo) / (hi - lo), 0, 1)
    np.testing.assert_allclose(got["input_gradient"][..., 0],
                               np.abs(np.diff(image, axis=2, append=image[:, :, -1:]))
                               + np.abs(np.diff(image, axis=1, append=image[:, -1:])), atol=2e-6)
    want = MTSAUNet(cfg.unet).apply(unet, jnp.asarray(image, jnp.float32))
    for key in want:
        np.testing.assert_allclose(got[key], want[key], atol=2e-5, err_msg=key)
    # a 14-bit reading would clip every one of these counts to 1: a flat image, no gradient
    assert (counts / (2**14 - 1)).min() > 1.0 and float(got["input_gradient"].max()) > 0.1


def test_blank_control_runs_the_network_once_with_the_full_batch_loss_and_gradient(frames):
    """stage2.preprocessing=blank: the depth network runs on one frame and its map is repeated;
    the loss and its gradient equal the full batch's through the network (another
    preprocessing, same image), and a batch whose images differ gives NaN, not a wrong map."""
    blank = host_image({"raw14": frames["raw14"]}, "blank")
    batch = {"raw14": frames["raw14"], "depth": frames["depth"], "valid": frames["valid"],
             "image": blank}
    grad_fns, results, flops = {}, {}, {}
    for preprocessing in ("blank", "rgb"):  # 'rgb' runs the network on every frame
        cfg = apply_overrides(CFG, [f"stage2.preprocessing={preprocessing}", "stage2.sky_loss=false"])
        loss_fn = stage2_loss_fn(cfg, 70.0)
        grad_fns[preprocessing] = jax.jit(jax.value_and_grad(lambda p, b, f=loss_fn: f(p, {}, None, b, None)[0]))
        params = random_depth(cfg)
        flops[preprocessing] = grad_fns[preprocessing].lower(params, batch).cost_analysis()["flops"]
        results[preprocessing] = grad_fns[preprocessing](params, batch)
    assert flops["blank"] < 0.6 * flops["rgb"]  # one frame of two through the network
    (loss_blank, g_blank), (loss_full, g_full) = results["blank"], results["rgb"]
    assert float(loss_blank) == pytest.approx(float(loss_full), rel=1e-5)
    for a, b in zip(jax.tree.leaves(g_blank), jax.tree.leaves(g_full), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=2e-4, atol=1e-7)
    mixed = blank.copy()
    mixed[1] = 0
    loss_mixed, _ = grad_fns["blank"](params, {**batch, "image": mixed})
    assert np.isnan(float(loss_mixed))
