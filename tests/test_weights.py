"""Checkpoint import/export: official key layout, layout conversions, strictness, save/load."""

import json
import sys

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from da_params import random_params
from safetensors.numpy import save_file

from irdepth_jax.models.depth_anything import depth_anything_config
from irdepth_jax.weights import (
    _official_to_path,
    load_depth_anything,
    load_params,
    save_params,
    to_official_state_dict,
)


def _official_tiny_keys(depth=4):
    """The official checkpoint's key set (REFERENCE.md section 2), written out independently."""
    keys = {"pretrained.cls_token", "pretrained.pos_embed", "pretrained.mask_token"}
    wb = lambda prefix: {f"{prefix}.weight", f"{prefix}.bias"}  # noqa: E731
    keys |= wb("pretrained.patch_embed.proj") | wb("pretrained.norm")
    for i in range(depth):
        b = f"pretrained.blocks.{i}."
        keys |= {b + "ls1.gamma", b + "ls2.gamma"}
        for m in ("norm1", "attn.qkv", "attn.proj", "norm2", "mlp.fc1", "mlp.fc2"):
            keys |= wb(b + m)
    h = "depth_head."
    for i in range(4):
        keys |= wb(f"{h}projects.{i}") | {f"{h}scratch.layer{i + 1}_rn.weight"}
        r = f"{h}scratch.refinenet{i + 1}."
        keys |= wb(r + "out_conv")
        for unit in ("resConfUnit1", "resConfUnit2"):
            keys |= wb(f"{r}{unit}.conv1") | wb(f"{r}{unit}.conv2")
    for i in (0, 1, 3):
        keys |= wb(f"{h}resize_layers.{i}")
    keys |= wb(h + "scratch.output_conv1") | wb(h + "scratch.output_conv2.0") | wb(h + "scratch.output_conv2.2")
    return keys


@pytest.fixture(scope="module")
def tiny():
    cfg = depth_anything_config("tiny")
    return cfg, random_params(cfg, seed=1)


def _assert_same_tree(a, b):
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(x, y)


def test_export_has_official_keys_and_layouts(tiny):
    _, params = tiny
    state = to_official_state_dict(params)
    assert set(state) == _official_tiny_keys()
    assert state["pretrained.patch_embed.proj.weight"].shape == (32, 3, 14, 14)  # OIHW
    assert state["pretrained.blocks.0.attn.qkv.weight"].shape == (96, 32)  # (out, in)
    assert state["depth_head.resize_layers.0.weight"].shape == (8, 8, 4, 4)  # (in, out, kh, kw)
    assert state["depth_head.resize_layers.3.weight"].shape == (32, 32, 3, 3)
    kernel = np.asarray(params["pretrained"]["blocks_2"]["attn"]["qkv"]["kernel"])
    np.testing.assert_array_equal(state["pretrained.blocks.2.attn.qkv.weight"], kernel.T)


def test_conv_transpose_conversion_matches_torch_semantics():
    # torch ConvTranspose2d with kernel = stride scatters out[s*i + k] += x[i] * w[k]: one input pixel
    # of value 1 must reproduce the torch kernel itself, unflipped.
    w_torch = np.arange(1.0, 5.0, dtype=np.float32).reshape(1, 1, 2, 2)  # (in, out, kh, kw)
    _, kernel = _official_to_path("depth_head.resize_layers.1.weight", w_torch)
    layer = nn.ConvTranspose(1, (2, 2), strides=(2, 2), padding="VALID", use_bias=False)
    out = layer.apply({"params": {"kernel": jnp.asarray(kernel)}}, jnp.ones((1, 1, 1, 1)))
    np.testing.assert_array_equal(out[0, :, :, 0], w_torch[0, 0])


def test_safetensors_official_layout_round_trip(tiny, tmp_path):
    _, params = tiny
    path = tmp_path / "tiny.safetensors"
    save_file(to_official_state_dict(params), str(path))
    cfg, loaded = load_depth_anything(path, kind="relative")
    assert cfg == depth_anything_config("tiny")  # encoder and head widths inferred from the shapes
    _assert_same_tree(loaded, params)
    cfg, _ = load_depth_anything(path, encoder="tiny", kind="metric", max_depth=20)
    assert cfg.metric and cfg.max_depth == 20.0


def test_strict_errors_list_every_problem(tiny, tmp_path):
    _, params = tiny
    state = to_official_state_dict(params)
    del state["pretrained.blocks.1.mlp.fc2.bias"]
    state["depth_head.scratch.refinenet5.out_conv.weight"] = np.zeros((16, 16, 1, 1), np.float32)
    state["depth_head.projects.2.weight"] = np.zeros((31, 32, 1, 1), np.float32)
    path = tmp_path / "bad.safetensors"
    save_file(state, str(path))
    with pytest.raises(ValueError) as err:
        load_depth_anything(path, encoder="tiny", kind="relative")
    msg = str(err.value)
    assert "missing (1): pretrained/blocks_1/mlp/fc2/bias" in msg
    assert "unexpected (1): depth_head.scratch.refinenet5.out_conv.weight" in msg
    assert "wrong shape (1): depth_head.projects.2.weight: (1, 1, 32, 31)" in msg
    with pytest.raises(ValueError, match="wrong shape"):  # a tiny checkpoint is not a vits one
        load_depth_anything(tmp_path / "bad.safetensors", encoder="vits", kind="relative")


def test_unknown_encoder_and_missing_file(tiny, tmp_path):
    _, params = tiny
    state = {k: v for k, v in to_official_state_dict(params).items() if ".blocks.3." not in k}
    save_file(state, str(tmp_path / "depth3.safetensors"))
    with pytest.raises(ValueError, match="no preset has embed_dim 32 and depth 3"):
        load_depth_anything(tmp_path / "depth3.safetensors", kind="relative")
    with pytest.raises(FileNotFoundError):
        load_depth_anything(tmp_path / "absent.safetensors")


def test_pth_official_and_metric_training_forms(tiny, tmp_path):
    torch = pytest.importorskip("torch")
    _, params = tiny
    state = {k: torch.from_numpy(v) for k, v in to_official_state_dict(params).items()}
    torch.save(state, tmp_path / "depth_anything_v2_vits.pth")  # the official relative name
    cfg, loaded = load_depth_anything(tmp_path / "depth_anything_v2_vits.pth")
    assert not cfg.metric
    _assert_same_tree(loaded, params)
    torch.save({"model": {f"module.{k}": v for k, v in state.items()}, "epoch": 3}, tmp_path / "metric.pth")
    cfg, loaded = load_depth_anything(tmp_path / "metric.pth")
    assert cfg.metric
    _assert_same_tree(loaded, params)


def test_pth_without_torch_names_the_extra(tmp_path, monkeypatch):
    (tmp_path / "x.pth").write_bytes(b"not read")
    monkeypatch.setitem(sys.modules, "torch", None)
    with pytest.raises(ImportError, match=r"irdepth_jax\[torch\]"):
        load_depth_anything(tmp_path / "x.pth")


def test_save_load_params_round_trip(tiny, tmp_path):
    _, params = tiny
    save_params(tmp_path / "p.msgpack", params)
    _assert_same_tree(load_params(tmp_path / "p.msgpack"), params)


@pytest.fixture(scope="module")
def official_state(tiny):
    torch = pytest.importorskip("torch")
    return {k: torch.from_numpy(v) for k, v in to_official_state_dict(tiny[1]).items()}


@pytest.mark.parametrize("name, metric, max_depth", [
    ("depth_anything_v2_vitl.pth", False, None),  # the official relative names
    ("depth_anything_v2_metric_hypersim_vits.pth", True, 20.0),  # metric_depth/README.md
    ("depth_anything_v2_metric_vkitti_vitl.pth", True, 80.0),
    ("vits_metric_finetune.pth", True, 35.0),  # metric, range not stated: the max_depth argument
])
def test_head_kind_from_official_file_names(official_state, tmp_path, name, metric, max_depth):
    torch = pytest.importorskip("torch")
    folder = tmp_path / "metric_runs"  # only the file's own name counts
    folder.mkdir()
    torch.save(official_state, folder / name)
    cfg, _ = load_depth_anything(folder / name, max_depth=35.0)
    assert cfg.metric == metric
    assert not metric or cfg.max_depth == max_depth


def test_transformers_config_json_states_the_kind(tiny, tmp_path):
    save_file(to_official_state_dict(tiny[1]), str(tmp_path / "model.safetensors"))
    (tmp_path / "config.json").write_text(json.dumps({"depth_estimation_type": "metric",
                                                      "max_depth": 20}))
    cfg, _ = load_depth_anything(tmp_path)
    assert cfg.metric and cfg.max_depth == 20.0
    (tmp_path / "config.json").write_text("{}")  # transformers' default type is relative
    cfg, _ = load_depth_anything(tmp_path)
    assert not cfg.metric


def test_ambiguous_and_foreign_files_are_refused_in_one_line(official_state, tmp_path):
    torch = pytest.importorskip("torch")
    torch.save(official_state, tmp_path / "model.pth")
    with pytest.raises(ValueError, match=r"model\.pth: cannot tell whether its head is metric or "
                                         r"relative.*depth\.checkpoint_kind") as err:
        load_depth_anything(tmp_path / "model.pth")
    assert "\n" not in str(err.value)
    cfg, _ = load_depth_anything(tmp_path / "model.pth", kind="metric", max_depth=30)
    assert cfg.metric and cfg.max_depth == 30.0
    with pytest.raises(ValueError, match="kind 'metrc'"):
        load_depth_anything(tmp_path / "model.pth", kind="metrc")
    (tmp_path / "depth_anything_v2_vits.pth").write_text("not weights")
    torch.save([1, 2], tmp_path / "list.pth")
    (tmp_path / "x.safetensors").write_bytes(b"\x00" * 16)
    for name, reason in (("depth_anything_v2_vits.pth", "not a PyTorch checkpoint"),
                         ("list.pth", "holds a list, not a state dict"),
                         ("x.safetensors", "not a safetensors file")):
        with pytest.raises(ValueError, match=f"{tmp_path / name}: {reason}") as err:
            load_depth_anything(tmp_path / name, kind="relative")
        assert "\n" not in str(err.value)
