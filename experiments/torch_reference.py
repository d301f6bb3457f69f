"""PyTorch reference for the parity tests and benchmarks: transformers'
DepthAnythingForDepthEstimation built from our config with random weights, its intermediate
features, and its weights in the official layout.

Needs torch + transformers (the [parity] extra); import it only from tests marked `parity` and
from benchmarks.
"""

from __future__ import annotations

import numpy as np
import torch
from transformers import DepthAnythingConfig as HFConfig
from transformers import DepthAnythingForDepthEstimation, Dinov2Config

from irdepth_jax.models.depth_anything import DepthAnythingConfig


def hf_config(cfg: DepthAnythingConfig) -> HFConfig:
    """The transformers config of the same architecture (stage k+1 = output of block k)."""
    backbone = Dinov2Config(
        hidden_size=cfg.embed_dim,
        num_hidden_layers=cfg.depth,
        num_attention_heads=cfg.num_heads,
        mlp_ratio=int(cfg.mlp_ratio),
        use_swiglu_ffn=cfg.ffn == "swiglu",
        image_size=cfg.image_size,
        patch_size=cfg.patch_size,
        out_indices=[t + 1 for t in cfg.taps],
        reshape_hidden_states=False,
    )
    return HFConfig(
        backbone_config=backbone,
        patch_size=cfg.patch_size,
        reassemble_hidden_size=cfg.embed_dim,
        neck_hidden_sizes=list(cfg.out_channels),
        fusion_hidden_size=cfg.features,
        head_hidden_size=cfg.head_hidden,
        depth_estimation_type="metric" if cfg.metric else "relative",
        # transformers multiplies by max_depth for both head types (1 = relative); its config types it int
        max_depth=int(cfg.max_depth) if cfg.metric else 1,
    )


def random_hf_model(cfg: DepthAnythingConfig, seed: int = 0) -> DepthAnythingForDepthEstimation:
    """An eval-mode transformers model whose every tensor is random at a signal-preserving scale
    (weights ~ N(0, 1/fan_in), biases, norms and layer scales perturbed), so no path is trivial."""
    torch.manual_seed(seed)
    model = DepthAnythingForDepthEstimation(hf_config(cfg)).eval()
    transposed = {f"{n}.weight" for n, m in model.named_modules() if isinstance(m, torch.nn.ConvTranspose2d)}
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.endswith("lambda1"):
                p.copy_(0.5 + 0.2 * torch.randn_like(p))
            elif "norm" in name and name.endswith("weight"):
                p.copy_(1.0 + 0.2 * torch.randn_like(p))
            elif p.ndim >= 2 and "embeddings" not in name:
                fan_in = p.shape[0] if name in transposed else p[0].numel()  # ConvTranspose: (in, out, k, k)
                p.copy_(torch.randn_like(p) / fan_in**0.5)
            else:
                p.copy_(0.3 * torch.randn_like(p))
    return model


def hf_forward(model, images_nhwc: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Depth (B, H, W) and intermediates in NHWC, keyed as our 'intermediates' collection:
    tap_k (B, N, D), layer{i}, rn_{i}, path_{i}, conv1_out."""
    feats: dict[str, np.ndarray] = {}

    def keep(name, transform):
        return lambda _m, _inp, out: feats.__setitem__(name, transform(out))

    nhwc = lambda t: t.detach().permute(0, 2, 3, 1).numpy()  # noqa: E731
    taps = lambda o: [t[:, 1:].detach().numpy() for t in o.feature_maps]  # noqa: E731 (drop the class token)
    hooks = [model.backbone.register_forward_hook(keep("taps", taps))]
    for i in range(4):
        hooks.append(model.neck.reassemble_stage.layers[i].register_forward_hook(keep(f"layer{i + 1}", nhwc)))
        hooks.append(model.neck.convs[i].register_forward_hook(keep(f"rn_{i + 1}", nhwc)))
        hooks.append(model.neck.fusion_stage.layers[i].register_forward_hook(keep(f"path_{4 - i}", nhwc)))
    hooks.append(model.head.conv1.register_forward_hook(keep("conv1_out", nhwc)))
    try:
        with torch.inference_mode():
            depth = model(pixel_values=torch.from_numpy(np.ascontiguousarray(images_nhwc.transpose(0, 3, 1, 2))))
    finally:
        for h in hooks:
            h.remove()
    for k, tap in enumerate(feats.pop("taps")):
        feats[f"tap_{k}"] = tap
    return depth.predicted_depth.numpy(), feats


def hf_to_official(model) -> dict[str, torch.Tensor]:
    """The transformers model's weights renamed to the official Depth Anything V2 .pth layout
    (written independently of irdepth_jax.weights, from the official module tree)."""
    sd = model.state_dict()
    out = {
        "pretrained.cls_token": sd["backbone.embeddings.cls_token"],
        "pretrained.pos_embed": sd["backbone.embeddings.position_embeddings"],
        "pretrained.mask_token": sd["backbone.embeddings.mask_token"],
    }
    for leaf in ("weight", "bias"):
        out[f"pretrained.patch_embed.proj.{leaf}"] = sd[f"backbone.embeddings.patch_embeddings.projection.{leaf}"]
        out[f"pretrained.norm.{leaf}"] = sd[f"backbone.layernorm.{leaf}"]
        for b in range(model.config.backbone_config.num_hidden_layers):
            src, dst = f"backbone.encoder.layer.{b}.", f"pretrained.blocks.{b}."
            if f"{src}attention.q_proj.{leaf}" in sd:  # transformers >= 5.2x
                qkv = [sd[f"{src}attention.{n}_proj.{leaf}"] for n in "qkv"]
                proj = sd[f"{src}attention.o_proj.{leaf}"]
            else:  # the names of earlier versions (5.17 among them) and of the Hub's files
                qkv = [sd[f"{src}attention.attention.{n}.{leaf}"] for n in ("query", "key", "value")]
                proj = sd[f"{src}attention.output.dense.{leaf}"]
            out[f"{dst}attn.qkv.{leaf}"] = torch.cat(qkv, 0)
            out[f"{dst}attn.proj.{leaf}"] = proj
            for n in ("norm1", "norm2", "mlp.fc1", "mlp.fc2"):
                out[f"{dst}{n}.{leaf}"] = sd[f"{src}{n}.{leaf}"]
        for i in range(4):
            out[f"depth_head.projects.{i}.{leaf}"] = sd[f"neck.reassemble_stage.layers.{i}.projection.{leaf}"]
            if i != 2:
                out[f"depth_head.resize_layers.{i}.{leaf}"] = sd[f"neck.reassemble_stage.layers.{i}.resize.{leaf}"]
            ref = f"depth_head.scratch.refinenet{4 - i}."
            out[f"{ref}out_conv.{leaf}"] = sd[f"neck.fusion_stage.layers.{i}.projection.{leaf}"]
            for r in (1, 2):
                for c in (1, 2):
                    hf = f"neck.fusion_stage.layers.{i}.residual_layer{r}.convolution{c}.{leaf}"
                    out[f"{ref}resConfUnit{r}.conv{c}.{leaf}"] = sd[hf]
        for ours, theirs in (("output_conv1", "conv1"), ("output_conv2.0", "conv2"), ("output_conv2.2", "conv3")):
            out[f"depth_head.scratch.{ours}.{leaf}"] = sd[f"head.{theirs}.{leaf}"]
    for b in range(model.config.backbone_config.num_hidden_layers):
        for s in (1, 2):
            out[f"pretrained.blocks.{b}.ls{s}.gamma"] = sd[f"backbone.encoder.layer.{b}.layer_scale{s}.lambda1"]
    for i in range(4):
        out[f"depth_head.scratch.layer{i + 1}_rn.weight"] = sd[f"neck.convs.{i}.weight"]
    return {k: v.clone() for k, v in out.items()}
