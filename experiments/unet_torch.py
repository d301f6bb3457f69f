"""PyTorch twin of our MTSA-UNet (`irdepth_jax.models.unet`), the reference of the benchmarks.

Same layers, parameter count and forward as `MTSAUNet` in eval mode (running BatchNorm
statistics) and in train mode (batch statistics, running averages updated as Flax does), and a
backward that is a twin too (tests/test_unet_torch.py: outputs and SGD-updated parameters to
~1e-5 in float32, outputs and gradients to 1e-9 with float64 networks). Tensors are NCHW: raw
(B, H, W) or (B, 1, H, W) in, outputs (B, C, H, W) out, keyed as ours.

    from irdepth_experiments.unet_torch import MTSAUNetTorch, load_flax_params
    model = MTSAUNetTorch(cfg.unet)               # cfg.unet: irdepth_jax.config.UNetConfig
    load_flax_params(model, variables)            # our {'params', 'batch_stats'}
    out = model.eval()(torch.from_numpy(raw))     # raw: uint16 (B, H, W) counts

Where a PyTorch built-in differs from what JAX computes, the twin follows JAX:

* BatchNorm: Flax's running var averages the *biased* batch variance, PyTorch's the unbiased one
  (n / (n - 1) larger); `BatchNorm2d` below undoes the factor after PyTorch's update (a C-element
  operation). Momentum: Flax m == PyTorch 1 - m (0.9 == 0.1); epsilon 1e-5 in both.
* |d| in the GCM: JAX differentiates |0| as 1, PyTorch as 0; `_abs` is ``where(d < 0, -d, d)``,
  whose derivative at 0 is JAX's. (The GCM of ReLU features, in RGG, has many exact zeros, but
  mostly between two zeros, where the ReLU's derivative stops the difference either way; it
  matters where two neighbouring features are equal and positive.)
* Transposed conv: our `Upsample2x` kernel (2, 2, in, out) is PyTorch's ConvTranspose2d(k=2,
  s=2) weight (in, out, 2, 2) transposed, *without* a spatial flip (its docstring: it is a matmul
  + depth-to-space, not `nn.ConvTranspose`).

Needs torch (the [torch] extra); irdepth_jax never imports this module.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from irdepth_jax.config import UNetConfig

BRANCHES = {
    # twin branch: (Flax decoder prefix, Flax head, output key); a renamed Flax branch is one line
    "recon": ("dec_recon", "head_recon", "recon"),
    "seg": ("dec_seg", "head_seg", "seg_logits"),
    "grad": ("dec_grad", "head_saturation", "saturation"),
}
"""Decoder branches, in our TASKS order: the twin names them ``decoders.<branch>.<level>`` and
``heads.<branch>``; the rest of the tree (``enc<i>`` -> ``enc.<i>``, ``bottleneck``, and every
block's children) has the same names in both."""

RAW_BITS = 14
"""Bit depth `MTSAUNet` normalises integer counts with (normalize_raw's default)."""


def _abs(d):
    """|d| with JAX's derivative (1 at d = 0; `torch.abs` gives 0 there)."""
    return torch.where(d < 0, -d, d)


def gradient_magnitude(x):
    """GCM of NCHW `x` (irdepth_jax.imaging.gradients): |forward difference| along W plus along H,
    0 on the last column / row."""
    gx = F.pad(_abs(x[..., :, 1:] - x[..., :, :-1]), (0, 1))
    gy = F.pad(_abs(x[..., 1:, :] - x[..., :-1, :]), (0, 0, 0, 1))
    return gx + gy


def normalize_raw(raw, mode: str, low: float = 1.0, high: float = 99.0, bits: int = RAW_BITS):
    """Integer counts (B, 1, H, W) -> float32 in [0, 1] (irdepth_jax.imaging.raw.normalize_raw)."""
    x = raw.to(torch.float32)
    if mode == "fixed":
        return torch.clamp(x / (2**bits - 1), 0.0, 1.0)
    if mode != "percentile":
        raise ValueError(f"normalize_raw: unknown mode {mode!r}")
    q = torch.tensor([low / 100.0, high / 100.0], dtype=torch.float32)
    lo, hi = torch.quantile(x.flatten(2), q, dim=-1, keepdim=True)  # linear, as jnp.percentile
    lo, hi = lo[..., None], hi[..., None]
    span = hi - lo
    safe_span = torch.where(span > 0, span, torch.ones_like(span))
    return torch.where(span > 0, torch.clamp((x - lo) / safe_span, 0.0, 1.0), torch.zeros_like(x))


class BatchNorm2d(nn.BatchNorm2d):
    """`nn.BatchNorm2d` with Flax's running-variance update (biased batch variance).

    Args:
      channels: C.
      flax_momentum: Flax's momentum (running = m * running + (1 - m) * batch).
    """

    def __init__(self, channels: int, flax_momentum: float):
        super().__init__(channels, eps=1e-5, momentum=1.0 - flax_momentum)

    def forward(self, x):
        if not self.training:
            return super().forward(x)
        keep = 1.0 - self.momentum
        old = self.running_var.clone()
        y = super().forward(x)  # running_var = keep * old + momentum * n / (n - 1) * var
        n = x.numel() // x.shape[1]
        with torch.no_grad():  # a new tensor: autograd saved the updated one for the backward
            self.running_var = keep * old + (self.running_var - keep * old) * ((n - 1) / n)
        return y


class DoubleConv(nn.Module):
    """2 x (3x3 conv, BatchNorm, ReLU)."""

    def __init__(self, cin: int, features: int, momentum: float):
        super().__init__()
        self.conv0 = nn.Conv2d(cin, features, 3, padding=1, bias=False)
        self.bn0 = BatchNorm2d(features, momentum)
        self.conv1 = nn.Conv2d(features, features, 3, padding=1, bias=False)
        self.bn1 = BatchNorm2d(features, momentum)

    def forward(self, x):
        x = F.relu(self.bn0(self.conv0(x)))
        return F.relu(self.bn1(self.conv1(x)))


class RGG(nn.Module):
    """irdepth_jax.models.rgg.RGG: A = sigmoid(Conv1x1_a(ReLU(alpha Conv1x1_f(GCM(U)) +
    (1 - alpha) Conv3x3_g(G)))), U' = U (1 + A), S' = S (1 + A)."""

    def __init__(self, channels: int, alpha: float):
        super().__init__()
        self.alpha = alpha
        self.feature_proj = nn.Conv2d(channels, channels, 1)
        self.input_proj = nn.Conv2d(1, channels, 3, padding=1)
        self.attention = nn.Conv2d(channels, channels, 1)

    def forward(self, up, skip, input_grad):
        mixed = self.alpha * self.feature_proj(gradient_magnitude(up)) + (
            1.0 - self.alpha
        ) * self.input_proj(input_grad)
        gain = 1.0 + torch.sigmoid(self.attention(F.relu(mixed)))
        return up * gain, skip * gain


class UpBlock(nn.Module):
    """Transposed 2x2 conv (stride 2, no bias), BN, ReLU, [RGG], concat with the skip, double conv."""

    def __init__(self, cin: int, features: int, cfg: UNetConfig):
        super().__init__()
        self.up = nn.ConvTranspose2d(cin, features, 2, stride=2, bias=False)
        self.up_bn = BatchNorm2d(features, cfg.bn_momentum)
        self.rgg = RGG(features, cfg.rgg_alpha) if cfg.use_rgg else None
        self.fuse = DoubleConv(2 * features, features, cfg.bn_momentum)

    def forward(self, x, skip, input_grad):
        x = F.relu(self.up_bn(self.up(x)))
        if self.rgg is not None:
            x, skip = self.rgg(x, skip, input_grad)
        return self.fuse(torch.cat([x, skip], dim=1))


class MTSAUNetTorch(nn.Module):
    """The MTSA-UNet (irdepth_jax.models.unet.MTSAUNet) in PyTorch, NCHW.

    forward(raw): raw (B, H, W) or (B, 1, H, W); integer counts are normalised as ours
    (cfg.raw_scale, 14 bits), a float image in [0, 1] is used as is. Returns a dict of float32
    tensors: recon (B, 1, H, W), seg_logits (B, num_classes, H, W), saturation (B, 1, H, W),
    input_gradient (B, 1, H, W) (key names from `BRANCHES`). Train mode (``model.train()``) uses
    batch statistics and updates the running averages, as ours with mutable=['batch_stats'].
    A model made ``.double()`` runs the network in float64, as ours with float64 parameters
    does; the input normalisation, its GCM and the RGG guides stay float32 in both.
    """

    def __init__(self, cfg: UNetConfig):
        super().__init__()
        self.cfg = cfg
        widths, m = cfg.widths, cfg.bn_momentum
        self.enc = nn.ModuleList(
            DoubleConv(1 if i == 0 else widths[i - 1], w, m) for i, w in enumerate(widths)
        )
        self.bottleneck = DoubleConv(widths[-1], cfg.bottleneck, m)
        below = list(widths[1:]) + [cfg.bottleneck]  # channels coming up into level i
        self.decoders = nn.ModuleDict(
            {
                branch: nn.ModuleList(UpBlock(below[i], w, cfg) for i, w in enumerate(widths))
                for branch in BRANCHES
            }
        )
        self.heads = nn.ModuleDict(
            {
                branch: nn.Conv2d(widths[0], cfg.num_classes if branch == "seg" else 1, 1)
                for branch in BRANCHES
            }
        )

    def preprocess(self, raw):
        """raw -> (x, gcm, guides): the normalised input edge-padded to a multiple of 2^stages
        (B, 1, H', W'), its GCM, and the RGG guide of every level (GCM / its per-image mean,
        average-pooled to the level; Nones without RGG). Float32, as ours computes them."""
        cfg = self.cfg
        if raw.ndim == 3:
            raw = raw[:, None]
        if raw.ndim != 4 or raw.shape[1] != 1:
            raise ValueError(f"expected raw (B, H, W) or (B, 1, H, W), got shape {tuple(raw.shape)}")
        if raw.is_floating_point():
            x = raw.to(torch.float32)
        else:
            x = normalize_raw(raw, cfg.raw_scale)
        height, width = x.shape[2:]
        multiple = 2 ** len(cfg.widths)
        x = F.pad(x, (0, -width % multiple, 0, -height % multiple), mode="replicate")
        gcm = gradient_magnitude(x)
        if not cfg.use_rgg:
            return x, gcm, [None] * len(cfg.widths)
        g = gcm / (gcm.mean(dim=(1, 2, 3), keepdim=True) + 1e-8)
        return x, gcm, [F.avg_pool2d(g, 2**i) if i else g for i in range(len(cfg.widths))]

    def forward(self, raw):
        height, width = raw.shape[-2:]
        x, gcm, guides = self.preprocess(raw)
        dtype = self.heads["recon"].weight.dtype  # float32 (float64 after .double(): an oracle)
        guides = [None if g is None else g.to(dtype) for g in guides]
        skips = []
        h = x.to(dtype)
        for block in self.enc:
            h = block(h)
            skips.append(h)
            h = F.max_pool2d(h, 2)
        bottom = self.bottleneck(h)

        out = {}
        for branch, (_, _, key) in BRANCHES.items():
            d = bottom
            for i in reversed(range(len(self.cfg.widths))):
                d = self.decoders[branch][i](d, skips[i], guides[i])
            y = self.heads[branch](d[:, :, :height, :width])
            out[key] = y if branch == "seg" else torch.sigmoid(y)
        out["input_gradient"] = gcm[:, :, :height, :width]
        return out


def _twin_prefix(flax_name: str) -> str:
    """Twin module path of one top-level Flax module name."""
    if flax_name.startswith("enc"):
        return f"enc.{int(flax_name[3:])}"
    if flax_name == "bottleneck":
        return flax_name
    for branch, (decoder, head, _) in BRANCHES.items():
        if flax_name == head:
            return f"heads.{branch}"
        if flax_name.startswith(decoder + "_up") and flax_name[len(decoder) + 3:].isdigit():
            return f"decoders.{branch}.{int(flax_name[len(decoder) + 3:])}"
    raise KeyError(f"no twin for the Flax module {flax_name!r} (see BRANCHES)")


def _leaves(tree, path=()):
    for key, value in tree.items():
        if hasattr(value, "items"):
            yield from _leaves(value, path + (key,))
        else:
            yield path + (key,), np.asarray(value)


def flax_to_torch_state(variables, dtype=torch.float32) -> dict[str, torch.Tensor]:
    """Our Flax ``{'params', 'batch_stats'}`` as the twin's state dict (`dtype` tensors).

    Conv kernels HWIO -> OIHW; `Upsample2x` kernels (2, 2, in, out) -> ConvTranspose2d weights
    (in, out, 2, 2), no flip; BatchNorm scale / bias / mean / var -> weight / bias / running_mean /
    running_var; biases as they are.
    """
    state = {}
    for collection, renames in (
        ("params", {"scale": "weight", "bias": "bias", "kernel": "weight"}),
        ("batch_stats", {"mean": "running_mean", "var": "running_var"}),
    ):
        for path, value in _leaves(variables.get(collection, {})):
            module = ".".join([_twin_prefix(path[0]), *path[1:-1]])
            if path[-1] == "kernel":
                axes = (2, 3, 0, 1) if path[-2] == "up" else (3, 2, 0, 1)
                value = value.transpose(axes)
            state[f"{module}.{renames[path[-1]]}"] = torch.tensor(value, dtype=dtype)
    return state


def load_flax_params(model: MTSAUNetTorch, variables) -> MTSAUNetTorch:
    """Copies our Flax variables into `model` (in place); returns it.

    Raises:
      ValueError: a twin parameter or running statistic has no Flax counterpart, or the other
        way round (PyTorch's num_batches_tracked counters are left alone).
      RuntimeError: (PyTorch's) a shape differs.
    """
    state = flax_to_torch_state(variables)
    missing, unexpected = model.load_state_dict(state, strict=False)
    missing = [k for k in missing if not k.endswith("num_batches_tracked")]
    if missing or unexpected:
        raise ValueError(f"load_flax_params: twin without Flax values {missing}, "
                         f"Flax values without a twin {unexpected}")
    return model
