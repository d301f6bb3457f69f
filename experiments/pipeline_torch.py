"""Our inference pipeline (`irdepth_jax.models.pipeline.run_pipeline` of an HSV model) in
idiomatic PyTorch eager: the opponent of experiments/bench_predict.py.

    raw (B, H, W) uint16 -> MTSAUNetIdiomatic (eval) -> soft class hue, HSV -> RGB
      -> bicubic resize to cfg.depth's input size, ImageNet norm -> official Depth Anything V2
      -> bilinear (align_corners) resize back -> depth (B, H, W) metres

The UNet is experiments/unet_idiomatic.py, the depth network the official code
(`bench_depth_anything.OFFICIAL_REPO`, a checkout that is not committed), both with our
parameter tensors; the steps in between are written
with torch built-ins as a PyTorch user writes them (F.softmax, torch.atan2, F.interpolate).
Needs torch (the [torch] extra).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from irdepth_experiments.bench_depth_anything import OFFICIAL_REPO, official_metric_model
from irdepth_experiments.unet_idiomatic import MTSAUNetIdiomatic
from irdepth_experiments.unet_torch import load_flax_params, normalize_raw
from irdepth_jax.config import Config, resolved_raw_bits
from irdepth_jax.imaging.color import CLASS_HUES
from irdepth_jax.models.depth_anything import IMAGENET_MEAN, IMAGENET_STD
from irdepth_jax.models.pipeline import depth_model_config
from irdepth_jax.weights import to_official_state_dict


def class_hue(seg_logits):
    """Soft class hue (B, 1, H, W) in [0, 1) of NCHW logits: the circular mean of the class hues
    weighted by the softmax (0 where the weighted vectors cancel)."""
    angles = 2 * math.pi * torch.tensor(CLASS_HUES, dtype=torch.float32)
    probs = F.softmax(seg_logits, dim=1)
    x = torch.einsum("bchw,c->bhw", probs, torch.cos(angles))
    y = torch.einsum("bchw,c->bhw", probs, torch.sin(angles))
    hue = torch.remainder(torch.atan2(y, x) / (2 * math.pi), 1.0)
    return torch.where(x * x + y * y > 1e-12, hue, torch.zeros_like(hue)).unsqueeze(1)


def hsv_to_rgb(h, s, v):
    """HSV maps (B, 1, H, W) in [0, 1] -> RGB (B, 3, H, W) in [0, 1] (the textbook sectors)."""
    h6 = h * 6
    sector = torch.floor(h6)
    f = h6 - sector
    p, q, t = v * (1 - s), v * (1 - s * f), v * (1 - s * (1 - f))
    sector = sector.long() % 6
    r = torch.stack([v, q, p, p, t, v], dim=0)
    g = torch.stack([t, v, v, q, p, p], dim=0)
    b = torch.stack([p, p, t, v, v, q], dim=0)
    index = sector.unsqueeze(0)
    return torch.cat([c.gather(0, index)[0] for c in (r, g, b)], dim=1)


class IdiomaticPipeline(nn.Module):
    """forward(raw (B, H, W) uint16) -> depth (B, H, W) float32 metres, `run_pipeline`'s depth
    of an HSV model with `unet_vars` and `da_params` (ours, Flax)."""

    def __init__(self, cfg: Config, unet_vars, da_params, official_repo: str = OFFICIAL_REPO):
        super().__init__()
        if cfg.stage2.preprocessing != "hsv" or cfg.stage2.hue_mode != "soft" or not cfg.depth.metric:
            raise ValueError("IdiomaticPipeline: written for HSV models with the soft hue and a metric head")
        self.cfg = cfg
        self.bits = resolved_raw_bits(cfg)
        self.unet = load_flax_params(MTSAUNetIdiomatic(cfg.unet), unet_vars).eval()
        state = {k: torch.from_numpy(v) for k, v in to_official_state_dict(da_params).items()}
        self.depth = official_metric_model(official_repo, depth_model_config(cfg), state).eval()
        self.register_buffer("mean", torch.tensor(np.asarray(IMAGENET_MEAN), dtype=torch.float32).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(np.asarray(IMAGENET_STD), dtype=torch.float32).view(1, 3, 1, 1))

    def rgb(self, raw):
        """raw (B, H, W) integer counts -> the depth network's RGB image (B, 3, H, W) in [0, 1]."""
        x = normalize_raw(raw.unsqueeze(1), self.cfg.unet.raw_scale, bits=self.bits)
        out = self.unet(x)
        return hsv_to_rgb(class_hue(out["seg_logits"]), out["saturation"].clamp(0, 1), out["recon"].clamp(0, 1))

    def depth_from_rgb(self, rgb, size):
        """RGB (B, 3, H, W) in [0, 1] -> depth (B, h, w) metres at `size` (h, w)."""
        network_size = (self.cfg.depth.input_height, self.cfg.depth.input_width)
        if tuple(rgb.shape[-2:]) != network_size:
            rgb = F.interpolate(rgb, size=network_size, mode="bicubic", align_corners=False)
        depth = self.depth((rgb - self.mean) / self.std)
        return F.interpolate(depth.unsqueeze(1), size=tuple(size), mode="bilinear", align_corners=True)[:, 0]

    def forward(self, raw):
        return self.depth_from_rgb(self.rgb(raw), raw.shape[-2:])
