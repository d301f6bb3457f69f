"""The config's dataclasses: what a preset (`irdepth_jax/configs/NAME.py`) builds.

A module of their own, importing nothing of the package, so that the presets, which
`irdepth_jax.config.get_config` loads, import them without importing `config` back. Use them
through `irdepth_jax.config` (the same classes).
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class UNetConfig:
    """MTSA-UNet sizes and switches."""

    widths: tuple[int, ...] = (32, 64, 128, 256)  # encoder stage channels
    bottleneck: int = 512
    num_classes: int = 6
    use_rgg: bool = True  # False: plain skip connections (the paper's ablation)
    rgg_alpha: float = 0.5  # balance of feature guidance vs input-gradient guidance
    bn_momentum: float = 0.9
    raw_scale: str = "fixed"  # 'fixed' (counts / 2^14) or 'percentile' (per-image 1-99 % clip)


@dataclass(frozen=True)
class DepthConfig:
    """Depth Anything V2 choice (see `irdepth_jax.models.depth_anything_config`)."""

    encoder: str = "vits"  # vits | vitb | vitl | vitg | tiny
    metric: bool = True  # metric head (sigmoid * max_depth) vs relative head (ReLU)
    max_depth: float = 80.0
    input_height: int = 252  # network input, multiples of 14
    input_width: int = 322
    checkpoint: str | None = None  # released .pth / .safetensors to start Stage II from
    # What `checkpoint` contributes: 'auto' = the backbone always, the head only when the file's
    # head kind (metric / relative) is this config's (a released metric checkpoint is used whole;
    # official metric fine-tuning starts from a relative one, backbone only); 'true' = the head
    # too (refused when its kind differs); 'false' = the backbone only.
    load_head: str = "auto"
    # Head kind of `checkpoint`: 'auto' = what the file says (a transformers config.json's
    # depth_estimation_type; a file name with metric / hypersim (max_depth 20) / vkitti (80) is
    # metric, the official depth_anything_v2_vit{s,b,l,g}.pth relative; the metric-training
    # {'model': {'module.*'}} form metric; anything else is refused as ambiguous), or 'metric' /
    # 'relative' to state it.
    checkpoint_kind: str = "auto"
    dtype: str = "float32"  # compute dtype: float32 | bfloat16 (params stay float32)
    remat: bool = False  # rematerialise transformer blocks to save memory


@dataclass(frozen=True)
class DataConfig:
    """Where the frames come from and how they are shaped."""

    source: str = "synthetic"  # synthetic | folder | ms2
    path: str | None = None  # dataset root for folder / ms2
    height: int = 256
    width: int = 320
    num_frames: int = 2292  # synthetic: total frames (Stage II split 1500/400/392)
    num_labeled: int = 800  # synthetic: labelled frames (600/100/100)
    # synthetic: the renderer's scene distribution, 'street' (one straight street, a level camera
    # at ~1.5 m: what every committed result used) or 'varied' (camera height 1.3-1.7 m,
    # horizon and roll per frame; crossings, open ground, close obstacles).
    scenes: str = "street"
    augment: bool = True
    min_depth: float = 1e-3
    max_depth: float = 80.0
    # Bit depth of the raw counts: 14 (most LWIR cores), 16 (radiometric cameras that use the
    # full range) or 'auto' (16 when a training frame exceeds 14 bits, else 14; resolved once at
    # the start of training and stored resolved in the run's config, so predict uses the same).
    raw_bits: int | str = 14


@dataclass(frozen=True)
class Stage1Config:
    """Stage I: MTSA-UNet pre-training (I-1) and soft multi-task fine-tuning (I-2)."""

    optimizer: str = "adadelta"  # adadelta | adamw
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
    i1_frames: str = "train"
    # Segmentation labels of I-2: 'dataset' (its seg_split == train frames), 'synthetic'
    # (rendered labelled scenes at the data's frame size, added to the dataset's frames: for data
    # without labels, e.g. MS2), a folder-format dataset path (its seg_split == train frames,
    # added likewise), or 'none' (I-2 without segmentation: Stage II must then use
    # stage2.hue_mode=constant and stage2.sky_loss=false). No labels at all is an error.
    seg_labels: str = "dataset"
    synthetic_labeled: int = 200  # frames rendered for seg_labels=synthetic
    recon_loss: str = "l1"  # l1 | l2
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
    # constant grey control) | a tonemap of the raw frame: he | clahe | camera | linear | plateau |
    # double_plateau | dde (irdepth_jax.imaging.tonemap.TONEMAPS)
    preprocessing: str = "hsv"
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
    sky_loss_kind: str = "l1"  # l1 | l2 of the relative error pred / ref_depth - 1
    # sky target depth = factor x min(largest training depth, data.max_depth, depth.max_depth)
    sky_ref_factor: float = 0.99
    # soft (circular mean of class hues) | argmax | constant (hue 0: no segmentation in the
    # input, for a Stage I whose segmentation branch was not trained)
    hue_mode: str = "soft"


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
