"""MTSA-UNet (paper section 3.2): a shared UNet encoder and three task decoders.

    image (B, H, W[, 1]) in [0, 1] -> edge-pad to a multiple of 2^stages
      encoder: per stage 2 x (3x3 conv, BN, ReLU) -> skip, then 2x2 max-pool; widths cfg.widths
      bottleneck: 2 x (3x3 conv, BN, ReLU) to cfg.bottleneck channels
      3 decoders (recon, seg, gradient), each with one up block per stage, deepest first:
        2x2 stride-2 transposed conv, BN, ReLU -> [RGG] -> concat with skip -> double conv
      heads: 1x1 conv (+ sigmoid for recon and gradient) -> crop back to (H, W)

Sizes: any H, W work. The input is edge-padded (replicating the last row / column) to the next
multiple of 16 (2^len(widths)) and every output is cropped back, so real sensor sizes (640x512,
640x480, 384x288, ...) need no resizing. Edge padding makes the GCM of the padded image equal the
GCM of the original inside the crop (the border difference is 0 either way).
"""

from __future__ import annotations

import flax.linen as nn
import jax.numpy as jnp

from irdepth_jax.config import UNetConfig
from irdepth_jax.imaging.gradients import gradient_magnitude, resize_gradient
from irdepth_jax.models.rgg import RGG

TASKS = ("recon", "seg", "gradient")
"""Decoder branches: reconstruction (-> Value), segmentation (-> Hue), gradient (the radiation-
gradient structure map -> Saturation)."""

MODULE_NAMES = {"recon": ("dec_recon", "head_recon"), "seg": ("dec_seg", "head_seg"),
                "gradient": ("dec_grad", "head_saturation")}
"""Parameter-tree names of each branch's decoder blocks (``<decoder>_up<i>``) and head. The
gradient branch keeps the names it has always been trained under: Flax draws every module's
initial weights from an RNG derived from the module's name, so renaming its modules would
change every newly trained model (and the committed experiment results) with no change in
behaviour."""


def max_pool_2x2(x):
    """2x2 max-pool with stride 2: (B, h, w, C) -> (B, h/2, w/2, C); h and w must be even.

    Same values and gradients (up to ties) as `nn.max_pool(x, (2, 2), strides=(2, 2))`, as a
    reshape and a max, whose backward pass XLA compiles to a plain comparison (nn.max_pool's,
    select_and_scatter, was several times slower on XLA:CPU).
    """
    b, h, w, c = x.shape
    return x.reshape(b, h // 2, 2, w // 2, 2, c).max(axis=(2, 4))


def pad_edge(x, pad_h: int, pad_w: int):
    """(B, H, W, C) -> (B, H + pad_h, W + pad_w, C), repeating the last row and column.

    The values of ``jnp.pad(x, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)), mode='edge')`` without
    its zero-size intermediate arrays, which the ONNX export (jax2onnx) mis-shapes.
    """
    if pad_h:
        x = jnp.concatenate([x, jnp.repeat(x[:, -1:], pad_h, axis=1)], axis=1)
    if pad_w:
        x = jnp.concatenate([x, jnp.repeat(x[:, :, -1:], pad_w, axis=2)], axis=2)
    return x


def upsample_by_matmul(x, kernel):
    """A transposed convolution whose stride equals its kernel: each input pixel becomes a k x k
    block, out[b, k i + p, k j + q, o] = sum_c x[b, i, j, c] kernel[p, q, c, o].

    x: (B, h, w, C_in); kernel: (k, k, C_in, C_out) -> (B, k h, k w, C_out): one matmul and a
    depth-to-space reshape.
    """
    k = kernel.shape[0]
    b, h, w, c = x.shape
    features = kernel.shape[-1]
    y = x.reshape(-1, c) @ kernel.transpose(2, 0, 1, 3).reshape(c, k * k * features)
    y = y.reshape(b, h, w, k, k, features).transpose(0, 1, 3, 2, 4, 5)
    return y.reshape(b, k * h, k * w, features)


class Upsample2x(nn.Module):
    """Transposed 2x2 convolution with stride 2, no bias: (B, h, w, C) -> (B, 2h, 2w, features).

    out[b, 2i + p, 2j + q, o] = sum_c x[b, i, j, c] * kernel[p, q, c, o] (`upsample_by_matmul`);
    this is PyTorch's ConvTranspose2d(k=2, s=2) with kernel = weight.transpose(2, 3, 0, 1), no
    spatial flip.
    """

    features: int

    @nn.compact
    def __call__(self, x):
        kernel = self.param(
            "kernel", nn.initializers.lecun_normal(), (2, 2, x.shape[-1], self.features)
        )
        return upsample_by_matmul(x, kernel)


class DoubleConv(nn.Module):
    """2 x (3x3 conv, BatchNorm, ReLU): (B, h, w, *) -> (B, h, w, features)."""

    features: int
    bn_momentum: float = 0.9
    axis_name: str | None = None

    @nn.compact
    def __call__(self, x, train: bool):
        for i in range(2):
            x = nn.Conv(self.features, (3, 3), use_bias=False, name=f"conv{i}")(x)
            x = nn.BatchNorm(
                use_running_average=not train,
                momentum=self.bn_momentum,
                axis_name=self.axis_name,
                name=f"bn{i}",
            )(x)
            x = nn.relu(x)
        return x


class UpBlock(nn.Module):
    """Transposed conv x2, BN, ReLU, [RGG], skip fusion (concat), double conv.

    (B, h, w, *) and skip (B, 2h, 2w, features) -> (B, 2h, 2w, features).
    """

    features: int
    use_rgg: bool
    rgg_alpha: float = 0.5
    bn_momentum: float = 0.9
    axis_name: str | None = None

    @nn.compact
    def __call__(self, x, skip, input_grad, train: bool):
        x = Upsample2x(self.features, name="up")(x)
        x = nn.BatchNorm(
            use_running_average=not train,
            momentum=self.bn_momentum,
            axis_name=self.axis_name,
            name="up_bn",
        )(x)
        x = nn.relu(x)
        if self.use_rgg:
            x, skip = RGG(self.rgg_alpha, name="rgg")(x, skip, input_grad)
        x = jnp.concatenate([x, skip], axis=-1)
        return DoubleConv(self.features, self.bn_momentum, self.axis_name, name="fuse")(x, train)


class MTSAUNet(nn.Module):
    """Multi-task structure-aware UNet (Stage I).

    Attributes:
      cfg: `irdepth_jax.config.UNetConfig` (widths, bottleneck, num_classes, use_rgg, rgg_alpha,
        bn_momentum; its raw_scale is the pipeline's, `models.pipeline.unet_input`).
      axis_name: mapped axis over which every BatchNorm averages its batch statistics (under
        pmap / shard_map); None for a single device.

    Parameter tree (what optimizer partitions match on): ``enc0..enc{n-1}``, ``bottleneck``,
    ``dec_{recon,seg,grad}_up{i}`` (children ``up``, ``up_bn``, ``fuse``, and ``rgg`` when
    cfg.use_rgg), ``head_recon``, ``head_seg``, ``head_saturation`` (`MODULE_NAMES`).
    """

    cfg: UNetConfig
    axis_name: str | None = None

    @nn.compact
    def __call__(self, image, train: bool = False):
        """Runs the three branches.

        Args:
          image: (B, H, W) or (B, H, W, 1) float, the normalised thermal image in [0, 1]: raw
            counts are normalised by `models.pipeline.unet_input` (which knows their bit depth
            and the config's scaling); integer input is refused.
          train: BatchNorm uses batch statistics and updates `batch_stats` (apply with
            mutable=['batch_stats']); otherwise it uses the running averages.

        Returns:
          dict of float32 arrays:
            recon (B, H, W, 1) in [0, 1], reconstructed grey image (1x1 conv + sigmoid);
            seg_logits (B, H, W, num_classes);
            saturation (B, H, W, 1) in [0, 1], the gradient branch's structure map (1x1 conv +
              sigmoid), the HSV image's Saturation channel;
            input_gradient (B, H, W, 1), GCM of the normalised input.
        """
        cfg = self.cfg
        if image.ndim == 3:
            image = image[..., None]
        if image.ndim != 4 or image.shape[-1] != 1:
            raise ValueError(
                f"MTSAUNet: expected an image (B, H, W) or (B, H, W, 1), got shape {image.shape}"
            )
        if not jnp.issubdtype(image.dtype, jnp.floating):
            raise ValueError(
                f"MTSAUNet: expected a float image in [0, 1], got {image.dtype}; normalise raw "
                "counts with models.pipeline.unet_input (their bit depth is data.raw_bits)"
            )
        x = image.astype(jnp.float32)
        height, width = x.shape[1:3]
        multiple = 2 ** len(cfg.widths)
        pad_h, pad_w = -height % multiple, -width % multiple
        x = pad_edge(x, pad_h, pad_w)
        gcm = gradient_magnitude(x)  # inside the crop, equal to the GCM of the unpadded input

        skips = []
        h = x
        for i, features in enumerate(cfg.widths):
            h = DoubleConv(features, cfg.bn_momentum, self.axis_name, name=f"enc{i}")(h, train)
            skips.append(h)
            h = max_pool_2x2(h)
        bottom = DoubleConv(cfg.bottleneck, cfg.bn_momentum, self.axis_name, name="bottleneck")(
            h, train
        )

        if cfg.use_rgg:
            # Guidance from the input's GCM, divided by its per-image mean: a scene spans a few
            # hundred counts of 2^14 or 2^16, so the GCM is ~1e-3 and would barely move the attention.
            g = gcm / (jnp.mean(gcm, axis=(1, 2, 3), keepdims=True) + 1e-8)
            guides = [resize_gradient(g, s.shape[1:3]) for s in skips]
        else:
            guides = [None] * len(skips)

        features = {}
        for task in TASKS:
            d = bottom
            for i in reversed(range(len(cfg.widths))):
                d = UpBlock(
                    cfg.widths[i],
                    cfg.use_rgg,
                    cfg.rgg_alpha,
                    cfg.bn_momentum,
                    self.axis_name,
                    name=f"{MODULE_NAMES[task][0]}_up{i}",
                )(d, skips[i], guides[i], train)
            features[task] = d[:, :height, :width]

        def head(task: str, channels: int):
            return nn.Conv(channels, (1, 1), name=MODULE_NAMES[task][1])(features[task])

        return {
            "recon": nn.sigmoid(head("recon", 1)),
            "seg_logits": head("seg", cfg.num_classes),
            "saturation": nn.sigmoid(head("gradient", 1)),
            "input_gradient": gcm[:, :height, :width],
        }
