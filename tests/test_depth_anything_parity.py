"""Parity with PyTorch: transformers' DepthAnythingForDepthEstimation (same random weights, imported
through our loader) and torch's interpolation, layer by layer so a mismatch names its layer."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("transformers")
F = torch.nn.functional

from irdepth_experiments.torch_reference import hf_forward, hf_to_official, random_hf_model  # noqa: E402
from irdepth_jax.models.depth_anything import (  # noqa: E402
    IMAGENET_MEAN,
    IMAGENET_STD,
    DepthAnythingV2,
    depth_anything_config,
    preprocess,
    resize_depth,
    target_size,
)
from irdepth_jax.models.dinov2 import interpolate_pos_embed  # noqa: E402
from irdepth_jax.models.dpt import resize_bilinear_align_corners  # noqa: E402
from irdepth_jax.weights import load_depth_anything  # noqa: E402

pytestmark = pytest.mark.parity
REL_TOL = 1e-4  # max |ours - torch| <= REL_TOL * max |torch|, per output and per intermediate


def _nchw(x):
    return torch.from_numpy(np.ascontiguousarray(np.moveaxis(np.asarray(x), -1, 1)))


def _run_ours(cfg, params, x):
    apply = jax.jit(lambda p, x: DepthAnythingV2(cfg).apply({"params": p}, x, mutable="intermediates"))
    depth, state = apply(params, jnp.asarray(x))
    inter = state["intermediates"]
    flat = {**inter["pretrained"], **inter["depth_head"]}
    flat.update(flat.pop("scratch"))
    return np.asarray(depth), {k: np.asarray(v[0]) for k, v in flat.items()}


def _assert_parity(ours, ref, ours_feats, ref_feats):
    assert set(ours_feats) == set(ref_feats)
    for name in sorted(ref_feats, key=lambda n: (n[0], n)):  # taps, layers, rn, paths, conv1_out
        a, b = ours_feats[name], ref_feats[name]
        assert a.shape == b.shape, (name, a.shape, b.shape)
        err = np.abs(a - b).max() / np.abs(b).max()
        assert err <= REL_TOL, f"{name}: max|diff| / max = {err:.2e}"
    assert ours.shape == ref.shape and np.abs(ref).max() > 0
    err = np.abs(ours - ref).max() / np.abs(ref).max()
    assert err <= REL_TOL, f"depth: max|diff| / max = {err:.2e}"


@pytest.mark.parametrize(
    "name, hw, metric, ffn",
    [
        ("tiny", (56, 70), False, "mlp"),
        ("tiny", (98, 98), True, "mlp"),
        ("tiny", (42, 28), False, "swiglu"),  # vitg's FFN, at a size the default run affords
        ("vits", (126, 168), False, "mlp"),
        ("vits", (98, 98), True, "mlp"),
    ],
)
def test_model_parity_via_transformers_safetensors(name, hw, metric, ffn, tmp_path):
    head = dict(metric=True, max_depth=20.0) if metric else {}
    cfg = depth_anything_config(name, pos_embed_mode="transformers", ffn=ffn, **head)
    model = random_hf_model(cfg, seed=sum(hw))
    model.save_pretrained(tmp_path)  # transformers' own on-disk layout (+ config.json)
    loaded_cfg, params = load_depth_anything(tmp_path)
    assert dataclasses.replace(loaded_cfg, pos_embed_mode="transformers") == cfg
    x = np.random.default_rng(0).normal(size=(2, *hw, 3)).astype(np.float32)
    ref, ref_feats = hf_forward(model, x)
    ours, ours_feats = _run_ours(cfg, params, x)
    _assert_parity(ours, ref, ours_feats, ref_feats)


def test_official_mode_equals_transformers_at_518(tmp_path):
    # at the 37x37 pre-training grid neither implementation resamples the position embeddings
    cfg = depth_anything_config("tiny")
    model = random_hf_model(cfg, seed=5)
    model.save_pretrained(tmp_path)
    _, params = load_depth_anything(tmp_path)
    x = np.random.default_rng(1).normal(size=(1, 518, 518, 3)).astype(np.float32)
    ref, ref_feats = hf_forward(model, x)
    ours, ours_feats = _run_ours(cfg, params, x)
    _assert_parity(ours, ref, ours_feats, ref_feats)


def test_official_pth_layouts_load_to_the_same_model(tmp_path):
    cfg = depth_anything_config("tiny", pos_embed_mode="transformers")
    model = random_hf_model(cfg, seed=7)
    state = hf_to_official(model)
    torch.save(state, tmp_path / "depth_anything_v2_tiny.pth")
    loaded_cfg, params = load_depth_anything(tmp_path / "depth_anything_v2_tiny.pth",
                                             kind="relative")  # not an official name
    assert not loaded_cfg.metric
    x = np.random.default_rng(2).normal(size=(1, 70, 56, 3)).astype(np.float32)
    ref, ref_feats = hf_forward(model, x)
    ours, ours_feats = _run_ours(cfg, params, x)
    _assert_parity(ours, ref, ours_feats, ref_feats)

    metric_cfg = dataclasses.replace(cfg, metric=True, max_depth=20.0)
    metric_model = random_hf_model(metric_cfg, seed=8)
    wrapped = {"model": {f"module.{k}": v for k, v in hf_to_official(metric_model).items()}}
    torch.save(wrapped, tmp_path / "metric_ckpt.pth")
    loaded_cfg, params = load_depth_anything(tmp_path / "metric_ckpt.pth", max_depth=20)
    assert loaded_cfg.metric and loaded_cfg.max_depth == 20.0
    ref, ref_feats = hf_forward(metric_model, x)
    ours, ours_feats = _run_ours(metric_cfg, params, x)
    _assert_parity(ours, ref, ours_feats, ref_feats)


@pytest.mark.parametrize("hw", [(9, 12), (7, 7), (40, 50), (37, 20), (1, 1), (74, 74)])
def test_pos_embed_interpolation_matches_torch(hw):
    # torch in float64 is the reference: its float32 kernel rounds the sampling positions (errors
    # up to 1e-5 here), our float64-built interpolation matrices stay within 1e-6 of float64.
    g, d = 37, 5
    pos = np.random.default_rng(3).normal(size=(1, g * g + 1, d)).astype(np.float32)
    grid = torch.from_numpy(pos[:, 1:]).double().reshape(1, g, g, d).permute(0, 3, 1, 2)
    factors = ((hw[0] + 0.1) / g, (hw[1] + 0.1) / g)
    official = F.interpolate(grid, scale_factor=factors, mode="bicubic", align_corners=False)
    hf = F.interpolate(grid, size=hw, mode="bicubic", align_corners=False)
    for mode, ref in (("official", official), ("transformers", hf)):
        assert tuple(ref.shape[2:]) == hw
        ours = np.asarray(interpolate_pos_embed(jnp.asarray(pos), hw, mode))
        np.testing.assert_array_equal(ours[0, 0], pos[0, 0])
        np.testing.assert_allclose(ours[0, 1:], ref[0].permute(1, 2, 0).reshape(-1, d).numpy(), atol=1e-6)


@pytest.mark.parametrize(
    "src, dst", [((5, 7), (9, 14)), ((9, 14), (5, 7)), ((1, 4), (3, 8)), ((4, 4), (1, 1)), ((6, 6), (6, 6))]
)
def test_bilinear_align_corners_matches_torch(src, dst):
    x = np.random.default_rng(4).normal(size=(2, *src, 3)).astype(np.float32)
    ref = F.interpolate(_nchw(x), size=dst, mode="bilinear", align_corners=True).permute(0, 2, 3, 1).numpy()
    np.testing.assert_allclose(resize_bilinear_align_corners(jnp.asarray(x), dst), ref, atol=2e-6)
    depth = x[..., 0]
    ref = F.interpolate(torch.from_numpy(depth)[:, None], size=dst, mode="bilinear", align_corners=True)[:, 0].numpy()
    np.testing.assert_allclose(resize_depth(jnp.asarray(depth), dst), ref, atol=2e-6)


def test_preprocess_matches_torch_bicubic():
    img = np.random.default_rng(5).random((1, 40, 67, 3), dtype=np.float32)
    h, w = target_size(40, 67, 56)
    ref = F.interpolate(_nchw(img).double(), size=(h, w), mode="bicubic", align_corners=False)  # see pos_embed test
    ref = (ref.permute(0, 2, 3, 1).numpy() - np.asarray(IMAGENET_MEAN)) / np.asarray(IMAGENET_STD)
    np.testing.assert_allclose(preprocess(img, 56), ref, atol=5e-6)
