"""Evaluation tables of the paper and prediction on raw files.

* `evaluate_stage1`: reconstruction PSNR / SSIM / entropy against the camera's 8-bit image and
  segmentation mIoU (labelled pixels), overall and per condition (the paper's tables 2, 3, 5).
* `evaluate_stage2`: depth d1 d2 d3 AbsRel SqRel RMSE RMSE-log log10 SiLog, overall and per
  condition (tables 1, 4, 6, 7), with `metrics.DepthMetricAccumulator` (per image, then mean).
* `evaluate_run`: loads a run (workdir or checkpoint directory) and writes both as Markdown + JSON.
* `load_model` / `predict_files`: the `irdepth predict` command.
"""

from __future__ import annotations

import functools
import json
import os
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from irdepth_jax.config import Config, from_dict
from irdepth_jax.metrics import (DEPTH_METRICS, DepthMetricAccumulator, confusion_matrix,
                                 entropy, mean_iou, psnr, ssim)
from irdepth_jax.imaging.color import hsv_to_rgb
from irdepth_jax.models.pipeline import depth_from_rgb, unet_outputs, unet_to_hsv
from irdepth_jax.train.checkpoint import CheckpointError, restore_items
from irdepth_jax.train.loop import (DataSource, RunError, device_batch, host_image, init_depth,
                                    init_unet)
from irdepth_jax.train.parallel import DataParallel
from irdepth_jax.train.steps import stage2_image

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
    rgb, _ = stage2_image(variables["frozen"], batch, cfg)
    return {"depth": depth_from_rgb(variables["depth"], rgb, cfg)}


_PREDICT = {"stage1": _predict_stage1, "stage2": _predict_stage2}


def evaluate_stage1(cfg: Config, unet_vars: dict, dataset, indices, dp: DataParallel
                    ) -> dict[str, dict[str, float]]:
    """Stage I metrics over `indices`: {'all': {...}, <condition>: {...}}.

    Per group: psnr, ssim (mean over images, recon vs ir8 / 255), entropy (bits, of the
    reconstruction as 8-bit), miou (labelled pixels; NaN without labels), count.
    """

    run = _Predictor(dp, "stage1", cfg, unet_vars)
    num_classes = cfg.unet.num_classes
    rows: dict[str, list] = {}
    cms: dict[str, np.ndarray] = {}
    for batch, n in _eval_batches(dataset, indices, dp):
        out = run({"raw14": batch["raw14"]})
        recon = np.asarray(out["recon"][:n], np.float32)
        target = batch["ir8"][:n].astype(np.float32) / 255.0
        p = np.asarray(psnr(recon[..., None], target[..., None]))
        s = np.asarray(ssim(recon[..., None], target[..., None]))
        recon8 = np.clip(np.round(recon * 255.0), 0, 255).astype(np.uint8)
        for i in range(n):
            e = float(entropy(recon8[i]))
            cm = np.asarray(confusion_matrix(out["seg"][i], batch["seg"][i], num_classes),
                            np.int64)
            for group in ("all", str(batch["condition"][i])):
                rows.setdefault(group, []).append((float(p[i]), float(s[i]), e))
                cms[group] = cms.get(group, 0) + cm
    result = {}
    for group in ["all"] + sorted(g for g in rows if g != "all"):
        values = np.asarray(rows[group], np.float64)
        labelled = cms[group].sum() > 0
        result[group] = {"psnr": float(values[:, 0].mean()), "ssim": float(values[:, 1].mean()),
                         "entropy": float(values[:, 2].mean()),
                         "miou": float(mean_iou(cms[group])) if labelled else float("nan"),
                         "count": int(len(values))}
    return result


def evaluate_stage2(cfg: Config, unet_vars: dict | None, da_params: Any, dataset, indices,
                    dp: DataParallel) -> dict[str, dict[str, float]]:
    """Depth metrics over `indices`: {'all': {...}, <condition>: {...}} (`DEPTH_METRICS` + count).

    Ground truth: the dataset's `depth` where `valid`, within [data.min_depth, data.max_depth]."""
    frozen = None if unet_vars is None else {"unet": unet_vars}

    run = _Predictor(dp, "stage2", cfg, {"frozen": frozen, "depth": da_params})
    acc = DepthMetricAccumulator(min_depth=cfg.data.min_depth, max_depth=cfg.data.max_depth)
    for batch, n in _eval_batches(dataset, indices, dp):
        inputs = device_batch(batch, "stage2", cfg)
        inputs.pop("depth"), inputs.pop("valid")
        out = run(inputs)
        acc.update(out["depth"][:n], batch["depth"][:n], batch["valid"][:n],
                   conditions=[str(c) for c in batch["condition"][:n]])
    return acc.result()


# --------------------------------------------------------------------------- runs
def find_checkpoint(path: str) -> tuple[str, str]:
    """(checkpoint directory, stage) of a workdir (its latest stage) or a checkpoint directory."""
    for phase in ("stage2", "stage1_i2", "stage1_i1"):
        candidate = os.path.join(path, "checkpoints", phase)
        if os.path.isdir(candidate) and any(n.isdigit() for n in os.listdir(candidate)):
            return candidate, phase
    if os.path.isdir(path) and any(n.isdigit() for n in os.listdir(path)):
        meta_stage = _peek_stage(path)
        return path, meta_stage
    raise RunError(f"{path}: no checkpoint (expected a run's --workdir or a checkpoint directory)")


def _peek_stage(directory: str) -> str:
    from irdepth_jax.train.checkpoint import Checkpointer
    reader = Checkpointer(directory, "stage2", max_to_keep=None, read_only=True)
    try:
        return str(reader.read_meta().get("stage"))
    except CheckpointError as err:
        raise RunError(str(err)) from None
    finally:
        reader.close()


def load_model(path: str, overrides: Sequence[str] = ()) -> tuple[Config, str, dict]:
    """Loads a trained model for evaluation / prediction.

    Args:
      path: a run's workdir or one of its checkpoint directories.
      overrides: ``key=value`` config overrides (e.g. data.max_depth).
    Returns:
      (config of the run, stage, {'unet': Stage I variables or None, 'depth': Depth Anything V2
      params or None}).
    """
    from irdepth_jax.config import apply_overrides

    directory, stage = find_checkpoint(path)
    try:
        meta = _read_meta(directory, stage)
        cfg = apply_overrides(from_dict(meta["config"]), list(overrides))
        if stage.startswith("stage1"):
            items, _ = restore_items(directory, stage, {"model": init_unet(cfg)})
            return cfg, stage, {"unet": dict(items["model"]), "depth": None}
        templates = {"model": {"params": init_depth(cfg), "batch_stats": {}}}
        has_unet = cfg.stage2.preprocessing == "hsv" or cfg.stage2.sky_loss
        if has_unet:
            templates["frozen"] = {"unet": init_unet(cfg)}
        items, _ = restore_items(directory, stage, templates)
    except CheckpointError as err:
        raise RunError(str(err)) from None
    unet = dict(items["frozen"]["unet"]) if has_unet else None
    return cfg, stage, {"unet": unet, "depth": items["model"]["params"]}


def _read_meta(directory: str, stage: str) -> dict:
    from irdepth_jax.train.checkpoint import Checkpointer
    reader = Checkpointer(directory, stage, max_to_keep=None, read_only=True)
    try:
        return reader.read_meta()
    finally:
        reader.close()


def evaluate_run(path: str, data: str, split: str = "test", fmt: str = "auto",
                 out_dir: str | None = None, overrides: Sequence[str] = (),
                 dp: DataParallel | None = None, stride: int = 1) -> dict:
    """Evaluates a run on a split and writes ``eval_<split>.md`` and ``.json``.

    Args:
      path: the run's workdir or a checkpoint directory.
      data: the dataset directory (folder format or MS2).
      split: 'train' | 'val' | 'test' (MS2: also test_day / test_night / test_rainy).
      out_dir: where the tables go (default: `path`).
      stride: evaluate every stride-th frame (MS2: of each sequence; its protocol is 10).
    Returns:
      {'stage', 'split', 'stage1': table or None, 'stage2': table or None, 'markdown'}.
    """
    cfg, stage, model = load_model(path, overrides)
    source = DataSource(data, fmt)
    dataset, indices = source.frames(split, stride=stride)
    if len(indices) == 0:
        raise RunError(f"--data {data}: split {split!r} has no frames")
    dp = dp or DataParallel("single")
    result: dict[str, Any] = {"stage": stage, "split": split, "stage1": None, "stage2": None}
    if model["unet"] is not None:
        result["stage1"] = evaluate_stage1(cfg, model["unet"], dataset, indices, dp)
    if model["depth"] is not None:
        result["stage2"] = evaluate_stage2(cfg, model["unet"], model["depth"], dataset, indices,
                                           dp)
    result["markdown"] = format_tables(result)
    out_dir = out_dir or path
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(out_dir, f"eval_{split}.md"), "w") as f:
        f.write(result["markdown"])
    with open(os.path.join(out_dir, f"eval_{split}.json"), "w") as f:
        json.dump({k: v for k, v in result.items() if k != "markdown"}, f, indent=2)
    return result


def _table(title: str, table: dict[str, dict[str, float]], columns: Sequence[str]) -> str:
    lines = [f"### {title}", "", "| condition | " + " | ".join(columns) + " | images |",
             "|---" * (len(columns) + 2) + "|"]
    for group, values in table.items():
        cells = [f"{values[c]:.4f}" if np.isfinite(values[c]) else "-" for c in columns]
        lines.append(f"| {group} | " + " | ".join(cells) + f" | {values['count']} |")
    return "\n".join(lines) + "\n"


def format_tables(result: dict) -> str:
    """The Markdown tables of an `evaluate_run` result."""
    parts = [f"## Evaluation on split `{result['split']}` ({result['stage']} checkpoint)\n"]
    if result.get("stage2") is not None:
        parts.append(_table("Depth (Stage II)", result["stage2"], DEPTH_METRICS))
    if result.get("stage1") is not None:
        parts.append(_table("Reconstruction and segmentation (Stage I)", result["stage1"],
                            ("psnr", "ssim", "entropy", "miou")))
    return "\n".join(parts)


# --------------------------------------------------------------------------- predict
RAW_SUFFIXES = (".png", ".tif", ".tiff", ".npy")


def list_inputs(inputs: Sequence[str]) -> list[str]:
    """Files named in `inputs` (folders: their .png / .tif / .tiff / .npy files, sorted); a
    RunError for a missing path, no frames, or two files with the same name stem."""
    files = []
    for item in inputs:
        if os.path.isdir(item):
            files += sorted(os.path.join(item, n) for n in os.listdir(item)
                            if n.lower().endswith(RAW_SUFFIXES))
        elif os.path.isfile(item):
            files.append(item)
        else:
            raise RunError(f"{item}: no such file or directory")
    if not files:
        raise RunError(f"no raw frames (.png, .tif, .npy) in {', '.join(inputs)}")
    seen = {}
    for f in files:  # outputs are named by stem: two inputs must not write the same files
        stem = os.path.splitext(os.path.basename(f))[0]
        if stem in seen:
            raise RunError(f"{f} and {seen[stem]}: same name {stem!r}, their outputs would "
                           "overwrite each other (predict them into separate --out folders)")
        seen[stem] = f
    return files


def read_raw(path: str) -> np.ndarray:
    """A raw 14-bit frame (H, W) uint16 from PNG / TIFF / NPY; RunError naming the file if it is
    not one (8-bit, colour, float, over 14 bits)."""
    import cv2

    from irdepth_jax.imaging.raw import check_raw14

    if path.lower().endswith(".npy"):
        raw = np.load(path, allow_pickle=False)
    else:
        raw = cv2.imread(path, cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise RunError(f"{path}: not a readable image")
    if raw.ndim != 2:
        raise RunError(f"{path}: shape {raw.shape}, expected a single-channel raw frame (H, W)")
    if raw.dtype == np.uint8:
        raise RunError(f"{path}: 8-bit image; predict needs the raw 14-bit counts "
                       "(16-bit PNG / TIFF or .npy)")
    try:
        check_raw14(raw)
    except ValueError as err:
        raise RunError(f"{path}: {str(err).splitlines()[0]}") from None
    return raw.astype(np.uint16)


def colorize_depth(depth: np.ndarray, max_depth: float) -> np.ndarray:
    """Depth (H, W) metres -> (H, W, 3) uint8 RGB (matplotlib 'turbo', near = red)."""
    from matplotlib import colormaps

    x = 1.0 - np.clip(depth / max(max_depth, 1e-6), 0.0, 1.0)
    return (colormaps["turbo"](x)[..., :3] * 255).astype(np.uint8)


@functools.partial(jax.jit, static_argnums=2)
def hsv_images(unet_vars: dict, raw: jax.Array, cfg: Config) -> tuple[jax.Array, jax.Array]:
    """(HSV, pseudo-RGB), each (B, H, W, 3) in [0, 1], of raw frames (B, H, W); jitted."""
    hsv = unet_to_hsv(unet_outputs(unet_vars, raw, cfg), cfg.stage2.hue_mode)
    return hsv, hsv_to_rgb(hsv)


depth_map = jax.jit(depth_from_rgb, static_argnums=2)
"""`depth_from_rgb(da_params, rgb, cfg)` jitted: RGB (B, H, W, 3) in [0, 1] -> depth (B, H, W) m."""


def predict_files(path: str, inputs: Sequence[str], out_dir: str,
                  overrides: Sequence[str] = ()) -> list[str]:
    """Runs a trained model on raw frames and writes, per input ``NAME``:

    ``NAME_depth.png`` (16-bit, metres x 256), ``NAME_depth_color.png`` and (HSV models)
    ``NAME_rgb.png`` (pseudo-RGB) and ``NAME_hsv.png`` (H, S, V as 8-bit channels). A Stage I
    checkpoint writes the pseudo-RGB / HSV images only.

    Returns the written paths. All inputs are read (and checked) before anything is written.
    """
    import cv2

    files = list_inputs(inputs)
    raws = [read_raw(f) for f in files]
    cfg, _, model = load_model(path, overrides)
    if model["depth"] is not None and cfg.stage2.preprocessing == "rgb":
        raise RunError(f"{path}: this model takes visible RGB images (stage2.preprocessing=rgb), "
                       "not raw frames")
    os.makedirs(out_dir, exist_ok=True)
    written = []
    to8 = lambda x: np.clip(np.round(np.asarray(x[0]) * 255), 0, 255).astype(np.uint8)  # noqa: E731
    for name, raw in zip(files, raws):
        stem = os.path.join(out_dir, os.path.splitext(os.path.basename(name))[0])
        rgb = None
        if model["unet"] is not None:
            hsv, rgb = hsv_images(model["unet"], raw[None], cfg)
            cv2.imwrite(stem + "_rgb.png", to8(rgb)[..., ::-1])
            cv2.imwrite(stem + "_hsv.png", to8(hsv))
            written += [stem + "_rgb.png", stem + "_hsv.png"]
        if model["depth"] is not None:
            if cfg.stage2.preprocessing != "hsv":
                rgb = host_image({"raw14": raw[None]}, cfg.stage2.preprocessing) / 255.0
            depth = np.asarray(depth_map(model["depth"], jnp.asarray(rgb, jnp.float32), cfg))[0]
            counts = np.clip(np.round(depth * 256.0), 0, 65535).astype(np.uint16)
            cv2.imwrite(stem + "_depth.png", counts)
            cv2.imwrite(stem + "_depth_color.png",
                        colorize_depth(depth, cfg.data.max_depth)[..., ::-1])
            written += [stem + "_depth.png", stem + "_depth_color.png"]
    return written
