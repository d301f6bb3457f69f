"""The evaluators: the paper's metrics of a model over dataset frames, run data-parallel.

* `evaluate_stage1`: reconstruction PSNR / SSIM / entropy against the camera's 8-bit image and
  segmentation mIoU (labelled pixels), overall and per condition (the paper's tables 2, 3, 5, 6).
* `evaluate_stage2`: depth d1 d2 d3 AbsRel SqRel RMSE RMSE-log log10 SiLog, overall and per
  condition (tables 1, 4, 7), with `metrics.DepthMetricAccumulator` (per image, then mean).

Training calls them for its periodic evaluation; `evaluate.evaluate_run` for a finished run.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from irdepth_jax.config import CLASS_NAMES, Config
from irdepth_jax.data.source import device_batch
from irdepth_jax.image_metrics import confusion_matrix, entropy, mean_iou, psnr, ssim
from irdepth_jax.metrics import DepthMetricAccumulator
from irdepth_jax.models.pipeline import run_pipeline, unet_outputs
from irdepth_jax.train.parallel import DataParallel

EVAL_BATCH = 8


def _eval_batches(dataset, indices, dp: DataParallel, batch_size: int = EVAL_BATCH):
    """Batches of all `indices` (in order), padded to a multiple of the devices; yields
    (batch dict of numpy arrays, number of real rows)."""
    size = -(-batch_size // dp.num_devices) * dp.num_devices
    for start in range(0, len(indices), size):
        chunk = [int(i) for i in indices[start:start + size]]
        samples = [dataset[i] for i in chunk]
        n = len(samples)
        samples += [samples[0]] * (size - n)
        yield {k: np.stack([np.asarray(s[k]) for s in samples]) for k in samples[0]}, n


def _local_rows(x: np.ndarray) -> np.ndarray:
    """This process's contiguous rows of a global batch (all rows with one process)."""
    count, index = jax.process_count(), jax.process_index()
    per = x.shape[0] // count
    return x[index * per:(index + 1) * per]


@functools.lru_cache(maxsize=32)
def _eval_step(dp: DataParallel, kind: str, cfg: Config):
    """The wrapped predict function (cached: periodic evals reuse the compiled step)."""
    return dp.eval_step(functools.partial(_PREDICT[kind], cfg))


class _Predictor:
    """A predict function wrapped for `dp`, with the variables placed once."""

    def __init__(self, dp: DataParallel, kind: str, cfg: Config, variables):
        self.dp, self.step = dp, _eval_step(dp, kind, cfg)
        self.variables = dp.replicate(variables)

    def __call__(self, batch: dict) -> dict:
        local = {k: _local_rows(v) for k, v in batch.items()}
        return self.dp.gather(self.step(self.variables, self.dp.shard_batch(local)))


def _predict_stage1(cfg: Config, variables: dict, batch: dict) -> dict:
    """recon (B, H, W) and seg (B, H, W) int32 of the UNet on batch['raw14']."""
    out = unet_outputs(variables, batch["raw14"], cfg)
    return {"recon": out["recon"][..., 0],
            "seg": jnp.argmax(out["seg_logits"], axis=-1).astype(jnp.int32)}


def _predict_stage2(cfg: Config, variables: dict, batch: dict) -> dict:
    """depth (B, H, W) of the Stage II model ({'frozen', 'depth'} variables)."""
    frozen = variables["frozen"]
    out = run_pipeline(None if frozen is None else frozen["unet"], variables["depth"],
                       batch.get("raw14"), cfg, image=batch.get("image"))
    return {"depth": out["depth"]}


_PREDICT = {"stage1": _predict_stage1, "stage2": _predict_stage2}


def evaluate_stage1(cfg: Config, unet_vars: dict, dataset, indices, dp: DataParallel,
                    seg_frames: tuple[Any, np.ndarray] | None = None, per_frame: bool = False):
    """Stage I metrics: {'all': {...}, <condition>: {...}}.

    Reconstruction over `indices` of `dataset` (a depth split): psnr, ssim (mean over images,
    recon vs ir8 / 255), entropy (bits, of the reconstruction as 8-bit), count. Segmentation
    over `seg_frames` = (dataset, indices) of a segmentation split (the paper's 600/100/100
    split is independent of the depth split): miou over the labelled pixels, seg_count images;
    miou is NaN where there are none (also when `seg_frames` is None).

    per_frame=True returns (metrics, frames) with frames = {'psnr', 'ssim', 'entropy': (N,)
    float64, 'condition': (N,) str, 'seg_cm': (M, C, C) int64 confusion matrix of each
    segmentation frame, 'seg_condition': (M,) str}: what `irdepth_experiments.claims` pairs per seed.
    """
    run = _Predictor(dp, "stage1", cfg, unet_vars)
    num_classes = cfg.unet.num_classes
    cms, seg_conditions = [], []

    def add_segmentation(batch, seg, n):
        cms.extend(np.asarray(confusion_matrix(seg[i], batch["seg"][i], num_classes), np.int64)
                   for i in range(n))
        seg_conditions.extend(str(c) for c in batch["condition"][:n])

    seg_dataset, seg_indices = seg_frames if seg_frames is not None else (None, [])
    # the same frames (e.g. a fully labelled evaluation set): one forward pass serves both
    same_frames = seg_dataset is dataset and np.array_equal(seg_indices, indices)
    recon_rows, conditions = [], []
    for batch, n in _eval_batches(dataset, indices, dp):
        out = run({"raw14": batch["raw14"]})
        recon = np.asarray(out["recon"][:n], np.float32)
        target = batch["ir8"][:n].astype(np.float32) / 255.0
        p = np.asarray(psnr(recon[..., None], target[..., None]))
        s = np.asarray(ssim(recon[..., None], target[..., None]))
        recon8 = np.clip(np.round(recon * 255.0), 0, 255).astype(np.uint8)
        recon_rows += [(p[i], s[i], float(entropy(recon8[i]))) for i in range(n)]
        conditions += [str(c) for c in batch["condition"][:n]]
        if same_frames:
            add_segmentation(batch, out["seg"], n)
    if len(seg_indices) and not same_frames:
        for batch, n in _eval_batches(seg_dataset, seg_indices, dp):
            add_segmentation(batch, run({"raw14": batch["raw14"]})["seg"], n)
    values = np.asarray(recon_rows, np.float64).reshape(-1, 3)
    frames = {"psnr": values[:, 0], "ssim": values[:, 1], "entropy": values[:, 2],
              "condition": np.asarray(conditions, str),
              "seg_cm": np.asarray(cms, np.int64).reshape(-1, num_classes, num_classes),
              "seg_condition": np.asarray(seg_conditions, str)}
    result = {}
    for group in ["all"] + sorted(set(conditions + seg_conditions)):
        rec = slice(None) if group == "all" else frames["condition"] == group
        seg = slice(None) if group == "all" else frames["seg_condition"] == group
        cm = frames["seg_cm"][seg].sum(axis=0)
        count, seg_count = len(values[rec]), len(frames["seg_cm"][seg])
        means = values[rec].mean(axis=0) if count else np.full(3, np.nan)
        result[group] = {"psnr": float(means[0]), "ssim": float(means[1]),
                         "entropy": float(means[2]),
                         "miou": float(mean_iou(cm)) if seg_count and cm.sum() > 0 else float("nan"),
                         "count": count, "seg_count": seg_count}
    return (result, frames) if per_frame else result


def accumulate_depth(cfg: Config, unet_vars: dict | None, da_params: Any, dataset, indices,
                     dp: DataParallel, accumulators, sky_accumulators=()) -> None:
    """Feeds the Stage II model's depth of every frame of `indices` to each
    `metrics.DepthMetricAccumulator` of `accumulators` (one prediction, several alignments) and
    each `metrics.SkyMetricAccumulator` of `sky_accumulators`.

    Ground truth: the dataset's `depth` (H, W) where `valid`, and for the sky metrics its
    labels' sky class where the frame is labelled; each accumulator applies its own range,
    alignment and clamp."""
    frozen = None if unet_vars is None else {"unet": unet_vars}
    run = _Predictor(dp, "stage2", cfg, {"frozen": frozen, "depth": da_params})
    for batch, n in _eval_batches(dataset, indices, dp):
        inputs = device_batch(batch, "stage2", cfg)
        inputs.pop("depth"), inputs.pop("valid")
        depth = run(inputs)["depth"][:n]
        conditions = [str(c) for c in batch["condition"][:n]]
        for acc in accumulators:
            acc.update(depth, batch["depth"][:n], batch["valid"][:n], conditions=conditions)
        for acc in sky_accumulators:
            acc.update(depth, batch["depth"][:n], batch["valid"][:n],
                       batch["seg"][:n] == CLASS_NAMES.index("sky"), batch["labeled"][:n], conditions)


def evaluate_stage2(cfg: Config, unet_vars: dict | None, da_params: Any, dataset, indices,
                    dp: DataParallel, align: str | None = None) -> dict[str, dict[str, float]]:
    """Depth metrics over `indices`: {'all': {...}, <condition>: {...}}, each with the
    `DEPTH_METRICS` means, count, nonfinite_pixels and nonfinite_images
    (`metrics.DepthMetricAccumulator`).

    Ground truth: the dataset's `depth` (H, W) where `valid`, within [data.min_depth,
    data.max_depth]; predictions (H, W) are aligned per image (`align`: None, 'median' or
    'scale_shift') and then clamped to the same range."""
    acc = DepthMetricAccumulator(align=align, min_depth=cfg.data.min_depth,
                                 max_depth=cfg.data.max_depth)
    accumulate_depth(cfg, unet_vars, da_params, dataset, indices, dp, [acc])
    return acc.result()
