"""Depth Anything V2 (DINOv2 ViT + DPT head) in Flax linen, with the official preprocessing.

    cfg = depth_anything_config("vits", metric=True, max_depth=80.0)
    model = DepthAnythingV2(cfg)
    params = model.init(jax.random.key(0), jnp.zeros((1, 518, 518, 3)))["params"]
    depth = model.apply({"params": params}, preprocess(rgb))          # (B, H', W')
    depth = resize_depth(depth, rgb.shape[-3:-1])                     # back to the input size

The parameter tree has two top-level keys mirroring the official checkpoint: `pretrained` (the
DINOv2 backbone) and `depth_head` (the DPT head); `irdepth_jax.weights.load_depth_anything` fills
it from released .pth or transformers .safetensors files.

Intermediate features (for parity debugging) are sown into the 'intermediates' collection:

    depth, state = model.apply({"params": params}, x, mutable="intermediates")
    inter = state["intermediates"]
    inter["pretrained"]["tap_{k}"][0]    # (B, h*w, D) normed patch tokens of tap k
    inter["depth_head"]["layer{i}"][0]   # (B, h_i, w_i, C_i) after projects / resize_layers
    inter["depth_head"]["scratch"][name][0]  # name: rn_{i} (layer{i}_rn), path_{i} (refinenet{i}),
                                             # conv1_out (output_conv1)
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from irdepth_jax.models.dinov2 import ATTENTION, POS_EMBED_MODES, DinoVisionTransformer, cubic_resize_matrix
from irdepth_jax.models.dpt import DPTHead, resize_bilinear_align_corners

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
_DTYPES = {"float32": jnp.float32, "bfloat16": jnp.bfloat16}


@dataclass(frozen=True)
class DepthAnythingConfig:
    """Architecture and numerics of a Depth Anything V2 model (defaults: `vits`, relative head).

    taps: 0-based indices of the blocks whose (final-normed) outputs feed the DPT head;
    out_channels: the 4 projection widths of the head; features: DPT fusion width;
    head_hidden: width of the last 3x3 conv (32 in every released model);
    metric: sigmoid * max_depth output (metric models) instead of ReLU (relative models);
    pos_embed_mode: 'official' (released checkpoints) or 'transformers' (HF Dinov2 resampling);
    dtype: compute dtype 'float32' | 'bfloat16' (params stay float32); remat: rematerialise blocks;
    attention: the attention kernel, `dinov2.ATTENTION` ('auto': cuDNN flash attention on GPU in
    bfloat16, XLA's in float32 on GPU, einsums on CPU; same numbers within float tolerance).
    """

    encoder: str = "vits"
    embed_dim: int = 384
    depth: int = 12
    num_heads: int = 6
    mlp_ratio: float = 4.0
    ffn: str = "mlp"  # mlp | swiglu (vitg)
    patch_size: int = 14
    image_size: int = 518  # pre-training size: a 37x37 position-embedding grid
    taps: tuple[int, ...] = (2, 5, 8, 11)
    features: int = 64
    out_channels: tuple[int, ...] = (48, 96, 192, 384)
    head_hidden: int = 32
    metric: bool = False
    max_depth: float = 80.0
    pos_embed_mode: str = "official"
    dtype: str = "float32"
    remat: bool = False
    attention: str = "auto"

    def __post_init__(self):
        problems = []
        if len(self.taps) != 4 or len(self.out_channels) != 4:
            problems.append(f"taps and out_channels need 4 entries, got {self.taps} and {self.out_channels}")
        if any(not 0 <= t < self.depth for t in self.taps) or list(self.taps) != sorted(set(self.taps)):
            problems.append(f"taps {self.taps} must be increasing block indices in [0, {self.depth})")
        if self.embed_dim % self.num_heads:
            problems.append(f"embed_dim {self.embed_dim} is not divisible by num_heads {self.num_heads}")
        if self.ffn not in ("mlp", "swiglu"):
            problems.append(f"ffn must be 'mlp' or 'swiglu', got {self.ffn!r}")
        if self.pos_embed_mode not in POS_EMBED_MODES:
            problems.append(f"pos_embed_mode must be one of {POS_EMBED_MODES}, got {self.pos_embed_mode!r}")
        if self.dtype not in _DTYPES:
            problems.append(f"dtype must be one of {tuple(_DTYPES)}, got {self.dtype!r}")
        if self.attention not in ATTENTION:
            problems.append(f"attention must be one of {ATTENTION}, got {self.attention!r}")
        if self.image_size % self.patch_size:
            problems.append(f"image_size {self.image_size} is not a multiple of patch_size {self.patch_size}")
        if problems:
            raise ValueError("DepthAnythingConfig: " + "; ".join(problems))


_PRESETS = {  # name: (embed_dim, depth, num_heads, taps, features, out_channels), then extras
    "vits": ((384, 12, 6, (2, 5, 8, 11), 64, (48, 96, 192, 384)), {}),
    "vitb": ((768, 12, 12, (2, 5, 8, 11), 128, (96, 192, 384, 768)), {}),
    "vitl": ((1024, 24, 16, (4, 11, 17, 23), 256, (256, 512, 1024, 1024)), {}),
    "vitg": ((1536, 40, 24, (9, 19, 29, 39), 384, (1536,) * 4), {"ffn": "swiglu"}),
    # Not released models: a small ViT for CPU minutes and a tiny one for CPU seconds (tests).
    "small": ((192, 6, 3, (1, 2, 4, 5), 32, (24, 48, 96, 192)), {}),
    "tiny": ((32, 4, 2, (0, 1, 2, 3), 16, (8, 16, 32, 32)), {"head_hidden": 8}),
}
_PRESET_FIELDS = ("embed_dim", "depth", "num_heads", "taps", "features", "out_channels")
ENCODERS = tuple(_PRESETS)


def depth_anything_config(name: str, **overrides) -> DepthAnythingConfig:
    """The preset `name` ('vits', 'vitb', 'vitl', 'vitg', 'small', 'tiny') with field overrides."""
    if name not in _PRESETS:
        raise ValueError(f"unknown Depth Anything encoder {name!r}; choose one of {ENCODERS}")
    unknown = set(overrides) - {f.name for f in dataclasses.fields(DepthAnythingConfig)}
    if unknown:
        raise ValueError(f"unknown DepthAnythingConfig fields: {sorted(unknown)}")
    sizes, extras = _PRESETS[name]
    return DepthAnythingConfig(**{"encoder": name, **dict(zip(_PRESET_FIELDS, sizes)), **extras, **overrides})


class DepthAnythingV2(nn.Module):
    """Depth Anything V2: images (B, H, W, 3), ImageNet-normalised, H and W multiples of 14
    -> depth (B, H, W) float32 (relative: ReLU output; metric: sigmoid * max_depth)."""

    cfg: DepthAnythingConfig

    def setup(self):
        c, dtype = self.cfg, _DTYPES[self.cfg.dtype]
        self.pretrained = DinoVisionTransformer(
            embed_dim=c.embed_dim,
            depth=c.depth,
            num_heads=c.num_heads,
            taps=c.taps,
            mlp_ratio=c.mlp_ratio,
            ffn=c.ffn,
            patch_size=c.patch_size,
            image_size=c.image_size,
            pos_embed_mode=c.pos_embed_mode,
            dtype=dtype,
            remat=c.remat,
            attention=c.attention,
        )
        self.depth_head = DPTHead(
            features=c.features,
            out_channels=c.out_channels,
            head_hidden=c.head_hidden,
            patch_size=c.patch_size,
            metric=c.metric,
            max_depth=c.max_depth,
            dtype=dtype,
        )

    def __call__(self, images: jax.Array) -> jax.Array:
        p = self.cfg.patch_size
        if images.ndim != 4 or images.shape[-1] != 3:
            raise ValueError(f"DepthAnythingV2 expects images (B, H, W, 3), got shape {images.shape}")
        if images.shape[1] % p or images.shape[2] % p:
            raise ValueError(
                f"DepthAnythingV2: image height and width must be multiples of {p}, got {images.shape[1:3]}; "
                "resize first (see preprocess)"
            )
        taps = self.pretrained(images.astype(_DTYPES[self.cfg.dtype]))
        depth = self.depth_head(taps, (images.shape[1] // p, images.shape[2] // p))
        return depth.astype(jnp.float32)


def target_size(height: int, width: int, input_size: int = 518, multiple: int = 14) -> tuple[int, int]:
    """The official 'lower_bound' resize: keep the aspect ratio, both sides >= input_size, each
    rounded (half to even, as numpy) to a multiple of `multiple`, rounded up instead if that falls
    below input_size. Returns (new_height, new_width)."""
    scale = max(input_size / height, input_size / width)

    def constrain(x: float) -> int:
        y = int(np.round(x / multiple) * multiple)
        return y if y >= input_size else int(np.ceil(x / multiple) * multiple)

    return constrain(scale * height), constrain(scale * width)


def network_input(rgb: jax.Array, size: tuple[int, int]) -> jax.Array:
    """RGB (B, H, W, 3) float in [0, 1] -> (B, h, w, 3) float32 network input: resized to `size`
    with the official a = -0.75 bicubic kernel (OpenCV INTER_CUBIC / torch bicubic, borders
    clamped, no antialiasing; two constant matrices, so it exports to ONNX as two MatMuls) and
    ImageNet-normalised. The one pre-processing of every path (training, eval, predict, export);
    `preprocess` picks the official size for it."""
    x = jnp.asarray(rgb, jnp.float32)
    height, width = x.shape[-3:-1]
    if (height, width) != tuple(size):
        rows = jnp.asarray(cubic_resize_matrix(height, size[0], height / size[0]), jnp.float32)
        cols = jnp.asarray(cubic_resize_matrix(width, size[1], width / size[1]), jnp.float32)
        hi = jax.lax.Precision.HIGHEST
        x = jnp.einsum("oh,...hwc->...owc", rows, x, precision=hi)
        x = jnp.einsum("pw,...owc->...opc", cols, x, precision=hi)
    return (x - jnp.asarray(IMAGENET_MEAN)) / jnp.asarray(IMAGENET_STD)


def preprocess(rgb: jax.Array, input_size: int = 518) -> jax.Array:
    """The official Depth Anything V2 input transform.

    rgb: (B, H, W, 3) or (H, W, 3), RGB float in [0, 1] or uint8 (divided by 255). Resized to
    `target_size(H, W, input_size)` and normalised by `network_input`. Returns (B, H', W', 3)
    float32 (no batch axis if the input had none).
    """
    x = jnp.asarray(rgb)
    if x.ndim not in (3, 4) or x.shape[-1] != 3:
        raise ValueError(f"preprocess expects RGB images (B, H, W, 3) or (H, W, 3), got shape {x.shape}")
    x = x.astype(jnp.float32) / 255.0 if x.dtype == jnp.uint8 else x.astype(jnp.float32)
    return network_input(x, target_size(*x.shape[-3:-1], input_size))


def resize_depth(depth: jax.Array, size: tuple[int, int]) -> jax.Array:
    """Resize predictions back to the image size, bilinear with align_corners=True (as official).

    depth: (B, H, W) or (H, W); size: (h, w) -> (B, h, w) or (h, w).
    """
    if depth.ndim not in (2, 3):
        raise ValueError(f"resize_depth expects depth (B, H, W) or (H, W), got shape {depth.shape}")
    x = depth[None] if depth.ndim == 2 else depth
    out = resize_bilinear_align_corners(x[..., None], tuple(size))[..., 0]
    return out[0] if depth.ndim == 2 else out
