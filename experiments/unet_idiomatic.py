"""The MTSA-UNet as a PyTorch user writes it: the opponent of the speed comparisons.

Plain `nn.Module`s (`nn.Conv2d`, `nn.BatchNorm2d`, `nn.ConvTranspose2d`), `torch.abs`,
`F.max_pool2d` / `F.avg_pool2d`, NCHW, no operation added to match JAX's numerics. It computes
what ours computes (eval and train mode outputs, the Stage I loss: tests/test_unet_idiomatic.py),
with the parameter tensors of ours (`irdepth_experiments.unet_torch.load_flax_params`: the module tree
has the names of the parity twin). Where it differs from ours, it does so as PyTorch does, and
nothing a speed comparison sees depends on it:

* |d| has derivative 0 at d = 0 (JAX's: 1): gradients differ where two neighbouring values are
  exactly equal;
* BatchNorm's running variance averages the unbiased batch variance (Flax's: the biased one); the
  outputs of a step do not read it.

The parity twin `experiments/unet_torch.py` undoes both (8 % more aten operator calls per train
step of the `tiny` preset) and stays the reference of the numerical tests; this one is the
reference of the benchmarks.

    from irdepth_experiments.unet_idiomatic import MTSAUNetIdiomatic
    from irdepth_experiments.unet_torch import load_flax_params
    model = load_flax_params(MTSAUNetIdiomatic(cfg.unet), variables)  # ours {'params', 'batch_stats'}
    out = model.eval()(torch.from_numpy(raw))                        # raw: uint16 (B, H, W)
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from irdepth_experiments.unet_torch import BRANCHES, normalize_raw
from irdepth_jax.config import UNetConfig


def gradient_magnitude(x):
    """|forward difference| along W plus along H of NCHW `x`, 0 on the last column / row."""
    gx = F.pad(torch.abs(x[..., :, 1:] - x[..., :, :-1]), (0, 1))
    gy = F.pad(torch.abs(x[..., 1:, :] - x[..., :-1, :]), (0, 0, 0, 1))
    return gx + gy


class DoubleConv(nn.Module):
    def __init__(self, cin: int, features: int, momentum: float):
        super().__init__()
        self.conv0 = nn.Conv2d(cin, features, 3, padding=1, bias=False)
        self.bn0 = nn.BatchNorm2d(features, momentum=momentum)
        self.conv1 = nn.Conv2d(features, features, 3, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(features, momentum=momentum)

    def forward(self, x):
        x = F.relu(self.bn0(self.conv0(x)))
        return F.relu(self.bn1(self.conv1(x)))


class RGG(nn.Module):
    def __init__(self, channels: int, alpha: float):
        super().__init__()
        self.alpha = alpha
        self.feature_proj = nn.Conv2d(channels, channels, 1)
        self.input_proj = nn.Conv2d(1, channels, 3, padding=1)
        self.attention = nn.Conv2d(channels, channels, 1)

    def forward(self, up, skip, guide):
        mixed = self.alpha * self.feature_proj(gradient_magnitude(up)) + (1 - self.alpha) * self.input_proj(guide)
        gain = 1 + torch.sigmoid(self.attention(F.relu(mixed)))
        return up * gain, skip * gain


class UpBlock(nn.Module):
    def __init__(self, cin: int, features: int, cfg: UNetConfig, momentum: float):
        super().__init__()
        self.up = nn.ConvTranspose2d(cin, features, 2, stride=2, bias=False)
        self.up_bn = nn.BatchNorm2d(features, momentum=momentum)
        self.rgg = RGG(features, cfg.rgg_alpha) if cfg.use_rgg else None
        self.fuse = DoubleConv(2 * features, features, momentum)

    def forward(self, x, skip, guide):
        x = F.relu(self.up_bn(self.up(x)))
        if self.rgg is not None:
            x, skip = self.rgg(x, skip, guide)
        return self.fuse(torch.cat([x, skip], dim=1))


class MTSAUNetIdiomatic(nn.Module):
    """forward(raw (B, H, W) uint16 counts, or a float image in [0, 1]) -> dict of NCHW float32
    tensors recon (B, 1, H, W), seg_logits (B, num_classes, H, W), saturation (B, 1, H, W),
    input_gradient (B, 1, H, W), as `irdepth_jax.models.unet.MTSAUNet`."""

    def __init__(self, cfg: UNetConfig):
        super().__init__()
        self.cfg = cfg
        momentum = 1 - cfg.bn_momentum  # Flax keeps m of the old average, PyTorch 1 - m
        widths = list(cfg.widths)
        self.enc = nn.ModuleList(DoubleConv(cin, w, momentum) for cin, w in zip([1] + widths[:-1], widths))
        self.bottleneck = DoubleConv(widths[-1], cfg.bottleneck, momentum)
        below = widths[1:] + [cfg.bottleneck]
        self.decoders = nn.ModuleDict({
            branch: nn.ModuleList(UpBlock(cin, w, cfg, momentum) for cin, w in zip(below, widths))
            for branch in BRANCHES
        })
        self.heads = nn.ModuleDict({
            branch: nn.Conv2d(widths[0], cfg.num_classes if branch == "seg" else 1, 1) for branch in BRANCHES
        })

    def forward(self, raw):
        if raw.ndim == 3:
            raw = raw.unsqueeze(1)
        x = raw.float() if raw.is_floating_point() else normalize_raw(raw, self.cfg.raw_scale)
        height, width = x.shape[-2:]
        multiple = 2 ** len(self.cfg.widths)
        x = F.pad(x, (0, -width % multiple, 0, -height % multiple), mode="replicate")
        gcm = gradient_magnitude(x)

        skips = []
        h = x
        for block in self.enc:
            h = block(h)
            skips.append(h)
            h = F.max_pool2d(h, 2)
        bottom = self.bottleneck(h)

        guides = [None] * len(skips)
        if self.cfg.use_rgg:
            g = gcm / (gcm.mean(dim=(1, 2, 3), keepdim=True) + 1e-8)
            guides = [g] + [F.avg_pool2d(g, 2**i) for i in range(1, len(skips))]
        out = {}
        for branch, (_, _, key) in BRANCHES.items():
            d = bottom
            for i in reversed(range(len(skips))):
                d = self.decoders[branch][i](d, skips[i], guides[i])
            y = self.heads[branch](d[:, :, :height, :width])
            out[key] = y if branch == "seg" else torch.sigmoid(y)
        out["input_gradient"] = gcm[:, :, :height, :width]
        return out
