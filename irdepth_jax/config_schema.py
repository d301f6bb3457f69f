"""The config's dataclasses: what a preset (`irdepth_jax/configs/NAME.py`) builds.

A module of their own, importing nothing of the package but its errors, so that the presets,
which `irdepth_jax.config.get_config` loads, import them without importing `config` back. Use
them through `irdepth_jax.config` (the same classes).

Every field is typed; a setting with a fixed set of values is a `Literal` (the aliases below,
which the library modules take their lists of names from). A `Config` checks itself when it is
made (`check_config`: a preset, `dataclasses.replace`, overrides, a loaded config.json), so a
wrong value is refused once, where it is given, with a `ConfigError` naming the key and what it
allows.
"""

from __future__ import annotations

import dataclasses
import functools
import numbers
import types
import typing
from dataclasses import dataclass, field
from typing import Literal

from irdepth_jax.errors import ConfigError

RawScale = Literal["fixed", "percentile"]
"""`unet.raw_scale`: counts / (2^bits - 1), or a per-image 1-99 % percentile clip."""
Encoder = Literal["vits", "vitb", "vitl", "vitg", "small", "tiny"]
"""`depth.encoder`: the Depth Anything V2 sizes (`models.depth_anything`); small and tiny are
not released models (CPU minutes / seconds)."""
LoadHead = Literal["auto", True, False]
"""`depth.load_head`: what `depth.checkpoint` contributes beyond the backbone."""
CheckpointKind = Literal["auto", "metric", "relative"]
"""`depth.checkpoint_kind`: the head kind of `depth.checkpoint`."""
ComputeDtype = Literal["float32", "bfloat16"]
"""`depth.dtype`: the Depth Anything compute dtype."""
DataSourceKind = Literal["synthetic", "folder", "ms2"]
"""`data.source`."""
Scenes = Literal["street", "varied"]
"""`data.scenes`: the synthetic renderer's scene distributions."""
RawBits = Literal[14, 16, "auto"]
"""`data.raw_bits`: the bit depth of the raw counts, or 'auto' (resolved when training starts)."""
Optimizer = Literal["adadelta", "adamw"]
"""`stage1.optimizer`."""
I1Frames = Literal["train", "all"]
"""`stage1.i1_frames`."""
PixelLoss = Literal["l1", "l2"]
"""`stage1.recon_loss`, `stage2.sky_loss_kind`."""
Preprocessing = Literal["hsv", "value", "rgb", "blank", "linear", "he", "clahe", "plateau",
                        "double_plateau", "dde", "camera"]
"""`stage2.preprocessing`: the Stage I images (`config.STAGE1_IMAGES`), the visible image, a
constant grey control, and the tonemaps of the raw frame (`imaging.tonemap.TONEMAPS`)."""
HueMode = Literal["soft", "argmax", "constant"]
"""`stage2.hue_mode`: the Hue channel from the class probabilities (`imaging.color.class_hue`)."""


@dataclass(frozen=True)
class UNetConfig:
    """MTSA-UNet sizes and switches."""

    widths: tuple[int, ...] = (32, 64, 128, 256)  # encoder stage channels
    bottleneck: int = 512
    num_classes: int = 6
    use_rgg: bool = True  # False: plain skip connections (the paper's ablation)
    rgg_alpha: float = 0.5  # balance of feature guidance vs input-gradient guidance
    bn_momentum: float = 0.9
    raw_scale: RawScale = "fixed"  # 'fixed' (counts / 2^14) or 'percentile' (per-image 1-99 % clip)


@dataclass(frozen=True)
class DepthConfig:
    """Depth Anything V2 choice (see `irdepth_jax.models.depth_anything_config`)."""

    encoder: Encoder = "vits"
    metric: bool = True  # metric head (sigmoid * max_depth) vs relative head (ReLU)
    max_depth: float = 80.0
    input_height: int = 252  # network input, multiples of 14
    input_width: int = 322
    checkpoint: str | None = None  # released .pth / .safetensors to start Stage II from
    # What `checkpoint` contributes: 'auto' = the backbone always, the head only when the file's
    # head kind (metric / relative) is this config's (a released metric checkpoint is used whole;
    # official metric fine-tuning starts from a relative one, backbone only); True = the head
    # too (refused when its kind differs); False = the backbone only.
    load_head: LoadHead = "auto"
    # Head kind of `checkpoint`: 'auto' = what the file says (a transformers config.json's
    # depth_estimation_type; a file name with metric / hypersim (max_depth 20) / vkitti (80) is
    # metric, the official depth_anything_v2_vit{s,b,l,g}.pth relative; the metric-training
    # {'model': {'module.*'}} form metric; anything else is refused as ambiguous), or 'metric' /
    # 'relative' to state it.
    checkpoint_kind: CheckpointKind = "auto"
    dtype: ComputeDtype = "float32"  # compute dtype (params stay float32)
    remat: bool = False  # rematerialise transformer blocks to save memory


@dataclass(frozen=True)
class DataConfig:
    """Where the frames come from and how they are shaped."""

    source: DataSourceKind = "synthetic"
    path: str | None = None  # dataset root for folder / ms2
    height: int = 256
    width: int = 320
    num_frames: int = 2292  # synthetic: total frames (Stage II split 1500/400/392)
    num_labeled: int = 800  # synthetic: labelled frames (600/100/100)
    # synthetic: the renderer's scene distribution, 'street' (one straight street, a level camera
    # at ~1.5 m: what every committed result used) or 'varied' (camera height 1.3-1.7 m,
    # horizon and roll per frame; crossings, open ground, close obstacles).
    scenes: Scenes = "street"
    augment: bool = True
    min_depth: float = 1e-3
    max_depth: float = 80.0
    # Bit depth of the raw counts: 14 (most LWIR cores), 16 (radiometric cameras that use the
    # full range) or 'auto' (16 when a training frame exceeds 14 bits, else 14; resolved once at
    # the start of training and stored resolved in the run's config, so predict uses the same).
    raw_bits: RawBits = 14


@dataclass(frozen=True)
class Stage1Config:
    """Stage I: MTSA-UNet pre-training (I-1) and soft multi-task fine-tuning (I-2)."""

    optimizer: Optimizer = "adadelta"
    learning_rate: float = 1.0  # I-1 rate (AdaDelta's customary 1.0; always explicit)
    i2_learning_rate: float = 0.1  # I-2 rate of encoder + reconstruction + gradient branch
    seg_lr_multiplier: float = 10.0  # I-2 segmentation branch rate = multiplier x the rate above
    weight_decay: float = 1e-4  # adamw only
    accum_steps: int = 4  # gradient accumulation (micro-batches per update)
    batch_size: int = 4  # per update, before accumulation split
    epochs_i1: int = 50
    epochs_i2: int = 50
    steps_i1: int | None = None  # overrides epochs when set
    steps_i2: int | None = None
    # Frames of I-1 (self-supervised, no labels): 'train' (default: the depth train split, so the
    # val / test frames of tables 2 and 5 stay unseen) or 'all' (the paper's "full dataset").
    i1_frames: I1Frames = "train"
    # Segmentation labels of I-2: 'dataset' (its seg_split == train frames), 'synthetic'
    # (rendered labelled scenes at the data's frame size, added to the dataset's frames: for data
    # without labels, e.g. MS2), a folder-format dataset path (its seg_split == train frames,
    # added likewise), or 'none' (I-2 without segmentation: Stage II must then use
    # stage2.hue_mode=constant and stage2.sky_loss=false). No labels at all is an error.
    seg_labels: str = "dataset"
    synthetic_labeled: int = 200  # frames rendered for seg_labels=synthetic
    recon_loss: PixelLoss = "l1"
    w_rec: float = 0.1  # I-2 weight of the reconstruction loss
    w_seg: float = 1.0  # I-2 weight of the cross-entropy
    w_grad: float = 1.0  # weight of the gradient branch loss (logged loss_gradient), relative to recon
    grad_target_scale: float = 0.25  # saturation target = clip(GCM(ir8 / 255) / scale, 0, 1)
    # False: the single-task segmentation baseline of table 3 (I-2 with CE only, recon / gradient
    # branches frozen); table 2's single-task reconstruction baseline is the I-1 checkpoint.
    multitask: bool = True


@dataclass(frozen=True)
class Stage2Config:
    """Stage II: Depth Anything V2 fine-tuning on the HSV pseudo-RGB image."""

    # hsv (ours) | value (its V channel alone, grey) | rgb (aligned visible image) | blank (a
    # constant grey control) | a tonemap of the raw frame (irdepth_jax.imaging.tonemap.TONEMAPS)
    preprocessing: Preprocessing = "hsv"
    learning_rate: float = 5e-6  # backbone rate; the head gets head_lr_multiplier x this
    head_lr_multiplier: float = 10.0
    weight_decay: float = 0.01
    poly_power: float = 0.9
    batch_size: int = 4
    epochs: int = 50
    steps: int | None = None  # overrides epochs when set
    silog_lambda: float = 0.5
    sky_loss: bool = True
    lambda_sky: float = 0.1
    sky_loss_kind: PixelLoss = "l1"  # of the relative error pred / ref_depth - 1
    # sky target depth = factor x min(largest training depth, data.max_depth, depth.max_depth)
    sky_ref_factor: float = 0.99
    # soft (circular mean of class hues) | argmax | constant (hue 0: no segmentation in the
    # input, for a Stage I whose segmentation branch was not trained)
    hue_mode: HueMode = "soft"


@dataclass(frozen=True)
class Config:
    """Everything a run needs."""

    name: str = "paper"
    seed: int = 0
    unet: UNetConfig = field(default_factory=UNetConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    data: DataConfig = field(default_factory=DataConfig)
    stage1: Stage1Config = field(default_factory=Stage1Config)
    stage2: Stage2Config = field(default_factory=Stage2Config)
    log_every: int = 10
    eval_every: int = 500
    checkpoint_every: int = 500
    keep_checkpoints: int = 3

    def __post_init__(self):
        check_config(self)


def check_config(cfg: Config) -> None:
    """Refuses a config with a value its field's annotation does not allow: a `Literal` value
    outside its set, or another type (an int is a float; a numpy integer an int; a bool is
    neither).

    Raises:
      ConfigError: one line naming the dotted key, the value and what the key allows.
    """
    for top in dataclasses.fields(cfg):
        value = getattr(cfg, top.name)
        if dataclasses.is_dataclass(value):
            for sub in dataclasses.fields(value):
                _check_value(f"{top.name}.{sub.name}", getattr(value, sub.name),
                             field_type(type(value), sub.name))
        else:
            _check_value(top.name, value, field_type(Config, top.name))


@functools.cache
def _hints(cls: type) -> dict[str, typing.Any]:
    return typing.get_type_hints(cls)


def field_type(cls: type, name: str) -> typing.Any:
    """The resolved annotation of field `name` of a config dataclass `cls`."""
    return _hints(cls)[name]


def field_options(annotation: typing.Any) -> tuple[tuple, tuple]:
    """(literal values, types) an annotation allows: ``RawBits`` -> ((14, 16, 'auto'), ());
    ``int | None`` -> ((), (int, NoneType)); ``tuple[int, ...]`` -> ((), (tuple[int, ...],))."""
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is typing.Union:
        parts = [field_options(a) for a in typing.get_args(annotation)]
        return tuple(v for p in parts for v in p[0]), tuple(t for p in parts for t in p[1])
    if typing.get_origin(annotation) is Literal:
        return typing.get_args(annotation), ()
    return (), (annotation,)


def _shown(value: typing.Any) -> str:
    """A `Literal` value as an override writes it: true / false, numbers and words bare."""
    return str(value).lower() if isinstance(value, bool) else str(value)


_TYPE_WORDS = {bool: "true or false", int: "an integer", float: "a number", str: "a string",
               type(None): "none"}


def _is_instance(value: typing.Any, kind: typing.Any) -> bool:
    if typing.get_origin(kind) is tuple:
        return isinstance(value, tuple) and all(_is_instance(v, typing.get_args(kind)[0])
                                                for v in value)
    if kind is bool:
        return isinstance(value, bool)
    if kind in (int, float):
        number = numbers.Integral if kind is int else numbers.Real
        return isinstance(value, number) and not isinstance(value, bool)
    return isinstance(value, kind)


def _check_value(key: str, value: typing.Any, annotation: typing.Any) -> None:
    literals, kinds = field_options(annotation)
    if any(type(value) is type(v) and value == v for v in literals):
        return
    if any(_is_instance(value, k) for k in kinds):
        return
    allowed = [_shown(v) for v in literals] + [
        _TYPE_WORDS.get(k, "a tuple of integers like (1, 2)") for k in kinds]
    what = (f"choose one of {', '.join(allowed)}" if literals and len(allowed) > 1
            else f"expected {' or '.join(allowed)}")
    raise ConfigError(f"{key}={value!r}: {what}")
