"""Import released Depth Anything V2 weights into `DepthAnythingV2` params; save/load converted params.

Source layouts:
  * official PyTorch .pth (`pretrained.*`, `depth_head.*`), also the metric-training form
    `{'model': {'module.pretrained.*', ...}}`; reading it needs torch (the `[torch]` extra);
  * HF transformers .safetensors (`backbone.*`, `neck.*`, `head.*`, legacy `attention.attention.query`
    or v5 `attention.q_proj` names), read with the safetensors numpy API (no torch); a
    `config.json` beside it supplies taps, head type and max_depth;
  * the official key layout in a .safetensors file (what `to_official_state_dict` + safetensors'
    `save_file` write; no torch needed).

Relative and metric heads have the same tensors (the relative head ends in ReLU, the metric one
in sigmoid x max_depth), so the head type is read from what surrounds them: a transformers
`config.json` (`depth_estimation_type`, `max_depth`; absent type = relative, as in transformers),
the official file names (DepthAnything/Depth-Anything-V2 README:
`depth_anything_v2_vit{s,b,l,g}.pth` are relative; its metric_depth/README:
`depth_anything_v2_metric_{hypersim,vkitti}_vit{s,b,l}.pth`, max_depth 20 m for Hypersim, 80 m
for Virtual KITTI), or the metric-training form. Anything else is ambiguous and needs the kind
stated (`kind=`, `depth.checkpoint_kind`).

Transformers keys are first renamed to the official layout (q/k/v fused into qkv, refinenet order
reversed), then every official key maps onto our tree by turning `name.N` into `name_N`:
conv weights OIHW -> HWIO, ConvTranspose (in, out, kh, kw) -> (kh, kw, in, out) with both spatial
axes flipped, linear (out, in) -> (in, out), LayerNorm weight -> scale. The conversion is strict:
missing, unexpected and wrongly shaped keys are all listed in one error. The only keys dropped are
the two that no forward pass uses: `pretrained.mask_token` and `refinenet4.resConfUnit1.*`.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import typing
from collections.abc import Mapping

import flax.serialization
import jax
import jax.numpy as jnp
import numpy as np
from flax import traverse_util

from irdepth_jax.config_schema import CheckpointKind
from irdepth_jax.models.depth_anything import (
    ENCODERS,
    DepthAnythingConfig,
    DepthAnythingV2,
    depth_anything_config,
)

_RELATIVE_NAME = re.compile(r"^depth_anything_v2_vit[sblg]\.pth$")
_METRIC_NAME_MAX_DEPTH = {"hypersim": 20.0, "vkitti": 80.0}  # metric_depth/README.md, dist_train.sh
CHECKPOINT_KINDS = typing.get_args(CheckpointKind)
_UNUSED = re.compile(r"^(pretrained\.mask_token|depth_head\.scratch\.refinenet4\.resConfUnit1\..*)$")
_CONV_TRANSPOSE = re.compile(r"^depth_head\.resize_layers\.[01]\.weight$")

# transformers name -> official name; a third element marks one part of a fused official tensor
# (parts are concatenated along the output axis in the order given).
_L, _B = r"backbone\.encoder\.layer\.(\d+)\.", r"pretrained.blocks.\1."
_WB = r"\.(weight|bias)"
_HF_RULES: list[tuple[str, object, int | None]] = [
    (r"backbone\.embeddings\.cls_token", "pretrained.cls_token", None),
    (r"backbone\.embeddings\.mask_token", "pretrained.mask_token", None),
    (r"backbone\.embeddings\.position_embeddings", "pretrained.pos_embed", None),
    (r"backbone\.embeddings\.patch_embeddings\.projection" + _WB, r"pretrained.patch_embed.proj.\1", None),
    (_L + r"norm([12])" + _WB, _B + r"norm\2.\3", None),
    (_L + r"attention\.(?:attention\.query|q_proj)" + _WB, _B + r"attn.qkv.\2", 0),
    (_L + r"attention\.(?:attention\.key|k_proj)" + _WB, _B + r"attn.qkv.\2", 1),
    (_L + r"attention\.(?:attention\.value|v_proj)" + _WB, _B + r"attn.qkv.\2", 2),
    (_L + r"attention\.(?:output\.dense|o_proj)" + _WB, _B + r"attn.proj.\2", None),
    (_L + r"layer_scale([12])\.lambda1", _B + r"ls\2.gamma", None),
    (_L + r"mlp\.(fc[12])" + _WB, _B + r"mlp.\2.\3", None),
    (_L + r"mlp\.weights_in" + _WB, _B + r"mlp.w12.\2", None),
    (_L + r"mlp\.gate_proj" + _WB, _B + r"mlp.w12.\2", 0),
    (_L + r"mlp\.up_proj" + _WB, _B + r"mlp.w12.\2", 1),
    (_L + r"mlp\.(?:weights_out|down_proj)" + _WB, _B + r"mlp.w3.\2", None),
    (r"backbone\.layernorm" + _WB, r"pretrained.norm.\1", None),
    (r"neck\.reassemble_stage\.layers\.(\d)\.projection" + _WB, r"depth_head.projects.\1.\2", None),
    (r"neck\.reassemble_stage\.layers\.(\d)\.resize" + _WB, r"depth_head.resize_layers.\1.\2", None),
    (r"neck\.convs\.(\d)\.weight", lambda m: f"depth_head.scratch.layer{int(m[1]) + 1}_rn.weight", None),
    (
        r"neck\.fusion_stage\.layers\.(\d)\.projection" + _WB,
        lambda m: f"depth_head.scratch.refinenet{4 - int(m[1])}.out_conv.{m[2]}",
        None,
    ),
    (
        r"neck\.fusion_stage\.layers\.(\d)\.residual_layer([12])\.convolution([12])" + _WB,
        lambda m: f"depth_head.scratch.refinenet{4 - int(m[1])}.resConfUnit{m[2]}.conv{m[3]}.{m[4]}",
        None,
    ),
    (r"head\.conv1" + _WB, r"depth_head.scratch.output_conv1.\1", None),
    (r"head\.conv2" + _WB, r"depth_head.scratch.output_conv2.0.\1", None),
    (r"head\.conv3" + _WB, r"depth_head.scratch.output_conv2.2.\1", None),
]
_HF_COMPILED = [(re.compile(p + "$"), repl, part) for p, repl, part in _HF_RULES]


def _to_numpy(tensor) -> np.ndarray:
    return tensor.detach().cpu().float().numpy() if hasattr(tensor, "detach") else np.asarray(tensor)


def _read_pth(path: str) -> tuple[dict[str, np.ndarray], bool]:
    """Official .pth -> (state dict, wrapped) where wrapped marks the metric-training form."""
    try:
        import torch
    except ImportError as err:
        raise ImportError(
            f"reading the PyTorch checkpoint {path!r} needs torch: pip install 'irdepth_jax[torch]' "
            "(or convert it once and use load_params)"
        ) from err
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises pickle, zip and runtime errors for a foreign file
        reason = next(iter(str(err).strip().splitlines()), type(err).__name__)
        raise ValueError(f"{path}: not a PyTorch checkpoint ({reason})") from None
    wrapped = isinstance(state, Mapping) and "model" in state and isinstance(state["model"], Mapping)
    if wrapped:
        state = {k.removeprefix("module."): v for k, v in state["model"].items()}
    if not isinstance(state, Mapping):
        raise ValueError(f"{path}: holds a {type(state).__name__}, not a state dict")
    return {k: _to_numpy(v) for k, v in state.items()}, wrapped


def _stated_head(path: str, hf_config: dict | None,
                 wrapped: bool) -> tuple[str | None, float | None]:
    """What a checkpoint's surroundings say of its head: (kind 'metric' / 'relative' or None when
    nothing says, max_depth or None) from a transformers config.json, the metric-training form or
    the official file name (see the module docstring)."""
    name = os.path.basename(path).lower()
    if hf_config is not None:
        if hf_config.get("depth_estimation_type", "relative") == "metric":
            return "metric", hf_config.get("max_depth")
        return "relative", None
    dataset = next((d for d in _METRIC_NAME_MAX_DEPTH if d in name), None)
    if wrapped or dataset or "metric" in name:
        return "metric", _METRIC_NAME_MAX_DEPTH.get(dataset)
    return ("relative" if _RELATIVE_NAME.match(name) else None), None


def _hf_to_official(state: Mapping[str, np.ndarray]) -> tuple[dict[str, np.ndarray], list[str]]:
    """Rename transformers keys to the official layout. Returns (official dict, unmatched keys)."""
    out, parts, unmatched = {}, {}, []
    for key, value in state.items():
        for pattern, repl, part in _HF_COMPILED:
            m = pattern.match(key)
            if m:
                name = repl(m) if callable(repl) else m.expand(repl)
                if part is None:
                    out[name] = value
                else:
                    parts.setdefault(name, {})[part] = (key, value)
                break
        else:
            unmatched.append(key)
    for name, got in parts.items():
        n_parts = 3 if ".attn.qkv." in name else 2
        if sorted(got) != list(range(n_parts)):
            unmatched.extend(f"{k} (its companions for {name} are missing)" for k, _ in got.values())
            continue
        out[name] = np.concatenate([got[i][1] for i in range(n_parts)], axis=0)
    return out, unmatched


def _official_to_path(key: str, value: np.ndarray) -> tuple[tuple[str, ...], np.ndarray]:
    """One official key/array -> (our param path, array in Flax layout)."""
    path: list[str] = []
    for part in key.split("."):
        if part.isdigit() and path:
            path[-1] = f"{path[-1]}_{part}"
        else:
            path.append(part)
    if path[-1] == "weight":
        if value.ndim == 4 and _CONV_TRANSPOSE.match(key):
            value = value.transpose(2, 3, 0, 1)[::-1, ::-1]
        elif value.ndim == 4:
            value = value.transpose(2, 3, 1, 0)
        elif value.ndim == 2:
            value = value.T
        path[-1] = "scale" if value.ndim == 1 else "kernel"
    return tuple(path), np.ascontiguousarray(value, dtype=np.float32)


def _infer_config(state: Mapping[str, np.ndarray], encoder, taps=None) -> DepthAnythingConfig:
    """Config from an official-layout state dict: encoder by (embed_dim, depth), FFN type and head
    widths by the tensors present and their shapes."""
    if isinstance(encoder, DepthAnythingConfig):
        return encoder
    if isinstance(encoder, str):
        return depth_anything_config(encoder)
    needed = [
        "pretrained.cls_token",
        "pretrained.pos_embed",
        "pretrained.patch_embed.proj.weight",
        "depth_head.scratch.layer1_rn.weight",
        "depth_head.scratch.output_conv2.0.weight",
    ] + [f"depth_head.projects.{i}.weight" for i in range(4)]
    absent = [k for k in needed if k not in state]
    if absent:
        raise ValueError(f"cannot infer the encoder: the checkpoint lacks {absent}; pass encoder=")
    dim = state["pretrained.cls_token"].shape[-1]
    depth = len({k.split(".")[2] for k in state if k.startswith("pretrained.blocks.")})
    presets = {n: depth_anything_config(n) for n in ENCODERS}
    name = next((n for n, c in presets.items() if (c.embed_dim, c.depth) == (dim, depth)), None)
    if name is None:
        raise ValueError(
            f"no preset has embed_dim {dim} and depth {depth} (presets: {ENCODERS}); "
            "pass encoder=DepthAnythingConfig(...)"
        )
    patch = state["pretrained.patch_embed.proj.weight"].shape[-1]
    grid = int(round((state["pretrained.pos_embed"].shape[1] - 1) ** 0.5))
    overrides = dict(
        ffn="swiglu" if any(".mlp.w12." in k for k in state) else "mlp",
        patch_size=patch,
        image_size=grid * patch,
        features=state["depth_head.scratch.layer1_rn.weight"].shape[0],
        out_channels=tuple(state[f"depth_head.projects.{i}.weight"].shape[0] for i in range(4)),
        head_hidden=state["depth_head.scratch.output_conv2.0.weight"].shape[0],
    )
    if taps is not None:
        overrides["taps"] = tuple(taps)
    return depth_anything_config(name, **overrides)


def expected_shapes(cfg: DepthAnythingConfig) -> dict[tuple[str, ...], tuple[int, ...]]:
    """Flat {param path: shape} of `DepthAnythingV2(cfg)` (no computation: jax.eval_shape)."""
    p = cfg.patch_size
    shapes = jax.eval_shape(DepthAnythingV2(cfg).init, jax.random.key(0), jnp.zeros((1, p, p, 3)))["params"]
    return {k: tuple(v.shape) for k, v in traverse_util.flatten_dict(shapes).items()}


def convert_official(state: Mapping[str, np.ndarray], cfg: DepthAnythingConfig) -> dict:
    """Official-layout state dict -> params of `DepthAnythingV2(cfg)` (strict; raises ValueError
    listing every missing, unexpected and wrongly shaped key)."""
    expected = expected_shapes(cfg)
    flat, source, unexpected = {}, {}, []
    for key, value in state.items():
        if _UNUSED.match(key):
            continue
        path, array = _official_to_path(key, np.asarray(value))
        if path in expected:
            flat[path], source[path] = array, key
        else:
            unexpected.append(key)
    missing = ["/".join(p) for p in expected if p not in flat]
    wrong = [
        f"{source[p]}: {flat[p].shape} (as {'/'.join(p)}), expected {expected[p]}"
        for p in flat
        if flat[p].shape != expected[p]
    ]
    if missing or unexpected or wrong:
        lines = [f"checkpoint does not match Depth Anything V2 '{cfg.encoder}':"]
        for title, keys in (("missing", missing), ("unexpected", unexpected), ("wrong shape", wrong)):
            if keys:
                lines.append(f"  {title} ({len(keys)}): " + ", ".join(sorted(keys)))
        raise ValueError("\n".join(lines))
    return jax.tree.map(jnp.asarray, traverse_util.unflatten_dict(flat))


def load_depth_anything(
    path: str | os.PathLike,
    encoder: str | DepthAnythingConfig | None = None,
    kind: str = "auto",
    max_depth: float | None = None,
) -> tuple[DepthAnythingConfig, dict]:
    """Load released Depth Anything V2 weights: (cfg, params) for `DepthAnythingV2(cfg).apply`.

    path: an official .pth / .pt file, a .safetensors file (transformers or official key layout),
    or a directory holding `model.safetensors`. encoder: a preset name, a full config, or None to
    infer it from the shapes (encoder from embed_dim and depth, head widths from the head's
    weights; taps from a transformers `config.json` when present). kind: the head type, 'auto'
    (what the file states: a transformers config.json, the metric-training ('model' + 'module.')
    form, an official file name; see the module docstring), 'metric' or 'relative'. max_depth:
    the metric head's range when the file does not state it (else the file's); None: the
    config's (80 m for a preset). cfg.metric / cfg.max_depth say what was read.
    Returns float32 params; raises ValueError (first line names the file) when the kind is
    ambiguous, the file is not a checkpoint, or keys mismatch (every one listed).
    """
    if kind not in CHECKPOINT_KINDS:
        raise ValueError(f"checkpoint kind {kind!r} (depth.checkpoint_kind / kind=): choose "
                         f"{', '.join(CHECKPOINT_KINDS)}")
    path = os.fspath(path)
    if os.path.isdir(path):
        path = os.path.join(path, "model.safetensors")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no checkpoint at {path!r}")
    hf_config: dict | None = None
    wrapped = False
    if path.endswith(".safetensors"):
        from safetensors.numpy import load_file

        try:
            state = load_file(path)
        except Exception as err:  # SafetensorError for a foreign file
            raise ValueError(f"{path}: not a safetensors file ({err})") from None
        official = any(k.startswith(("pretrained.", "depth_head.")) for k in state)
        state, unmatched = (dict(state), []) if official else _hf_to_official(state)
        config_json = os.path.join(os.path.dirname(path), "config.json")
        if os.path.isfile(config_json):
            with open(config_json) as f:
                hf_config = json.load(f)
    else:
        state, wrapped = _read_pth(path)
        unmatched = []
    if unmatched:
        raise ValueError(f"{path}: keys not in the Depth Anything V2 layout ({len(unmatched)}): {sorted(unmatched)}")
    stated_kind, stated_depth = _stated_head(path, hf_config, wrapped)
    if kind == "auto" and stated_kind is None:
        raise ValueError(f"{path}: cannot tell whether its head is metric or relative (not an "
                         "official file name, no transformers config.json): set "
                         "depth.checkpoint_kind (kind=) to metric or relative")
    metric = (stated_kind if kind == "auto" else kind) == "metric"
    out_indices = (hf_config or {}).get("backbone_config", {}).get("out_indices")
    cfg = _infer_config(state, encoder, taps=[i - 1 for i in out_indices] if out_indices else None)
    max_depth = stated_depth or max_depth or cfg.max_depth
    cfg = dataclasses.replace(cfg, metric=metric, max_depth=float(max_depth))
    try:
        params = convert_official(state, cfg)
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None
    return cfg, params


def save_params(path: str | os.PathLike, params) -> None:
    """Write a params pytree (nested dicts of arrays) to `path` as flax msgpack."""
    with open(path, "wb") as f:
        f.write(flax.serialization.msgpack_serialize(jax.tree.map(np.asarray, params)))


def load_params(path: str | os.PathLike) -> dict:
    """Read params written by `save_params` (nested dicts of float arrays)."""
    with open(path, "rb") as f:
        return jax.tree.map(jnp.asarray, flax.serialization.msgpack_restore(f.read()))


def to_official_state_dict(params) -> dict[str, np.ndarray]:
    """Params of `DepthAnythingV2` -> the official PyTorch state dict (numpy arrays), loadable by the
    official `DepthAnythingV2.load_state_dict` (the two never-used tensors are added as zeros)."""
    state = {}
    for path, value in traverse_util.flatten_dict(params).items():
        key = ".".join(re.sub(r"_(\d+)$", r".\1", part) for part in path)
        value = np.array(value, dtype=np.float32)  # a writable copy (torch.from_numpy warns otherwise)
        if path[-1] in ("kernel", "scale"):
            key = key.rsplit(".", 1)[0] + ".weight"
            if value.ndim == 4 and _CONV_TRANSPOSE.match(key):
                value = value[::-1, ::-1].transpose(2, 3, 0, 1)
            elif value.ndim == 4:
                value = value.transpose(3, 2, 0, 1)
            elif value.ndim == 2:
                value = value.T
        state[key] = np.ascontiguousarray(value)
    dim = state["pretrained.cls_token"].shape[-1]
    state["pretrained.mask_token"] = np.zeros((1, dim), np.float32)
    for unit in ("conv1", "conv2"):
        for leaf in ("weight", "bias"):
            twin = state[f"depth_head.scratch.refinenet4.resConfUnit2.{unit}.{leaf}"]
            state[f"depth_head.scratch.refinenet4.resConfUnit1.{unit}.{leaf}"] = np.zeros_like(twin)
    return state
