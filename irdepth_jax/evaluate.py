"""Evaluation tables of the paper and prediction on raw files.

* `evaluate_stage1`: reconstruction PSNR / SSIM / entropy against the camera's 8-bit image and
  segmentation mIoU (labelled pixels), overall and per condition (the paper's tables 2, 3, 5).
* `evaluate_stage2`: depth d1 d2 d3 AbsRel SqRel RMSE RMSE-log log10 SiLog, overall and per
  condition (tables 1, 4, 6, 7), with `metrics.DepthMetricAccumulator` (per image, then mean).
* `evaluate_run`: loads a run (workdir or checkpoint directory) and writes both as Markdown + JSON.
* `load_model` / `predict_files`: the `irdepth predict` command.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import functools
import json
import os
import sys
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from irdepth_jax.config import Config, from_dict
from irdepth_jax.fileio import make_dirs, write_bytes, write_png
from irdepth_jax.metrics import (DEPTH_METRICS, DepthMetricAccumulator, confusion_matrix,
                                 entropy, mean_iou, psnr, ssim)
from irdepth_jax.imaging.color import hsv_to_rgb
from irdepth_jax.imaging.raw import BIT_DEPTHS
from irdepth_jax.models.pipeline import (depth_from_rgb, resolved_raw_bits, unet_outputs,
                                         unet_to_hsv)
from irdepth_jax.train.checkpoint import CheckpointError, restore_items
from irdepth_jax.train.loop import (DataSource, RunError, device_batch, host_image, init_unet,
                                    random_depth)
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


def evaluate_stage1(cfg: Config, unet_vars: dict, dataset, indices, dp: DataParallel,
                    seg_frames: tuple[Any, np.ndarray] | None = None
                    ) -> dict[str, dict[str, float]]:
    """Stage I metrics: {'all': {...}, <condition>: {...}}.

    Reconstruction over `indices` of `dataset` (a depth split): psnr, ssim (mean over images,
    recon vs ir8 / 255), entropy (bits, of the reconstruction as 8-bit), count. Segmentation
    over `seg_frames` = (dataset, indices) of a segmentation split (the paper's 600/100/100
    split is independent of the depth split): miou over the labelled pixels, seg_count images;
    miou is NaN where there are none (also when `seg_frames` is None).
    """
    run = _Predictor(dp, "stage1", cfg, unet_vars)
    num_classes = cfg.unet.num_classes
    rows: dict[str, list] = {}
    for batch, n in _eval_batches(dataset, indices, dp):
        out = run({"raw14": batch["raw14"]})
        recon = np.asarray(out["recon"][:n], np.float32)
        target = batch["ir8"][:n].astype(np.float32) / 255.0
        p = np.asarray(psnr(recon[..., None], target[..., None]))
        s = np.asarray(ssim(recon[..., None], target[..., None]))
        recon8 = np.clip(np.round(recon * 255.0), 0, 255).astype(np.uint8)
        for i in range(n):
            e = float(entropy(recon8[i]))
            for group in ("all", str(batch["condition"][i])):
                rows.setdefault(group, []).append((float(p[i]), float(s[i]), e))
    cms: dict[str, np.ndarray] = {}
    seg_counts: dict[str, int] = {}
    seg_dataset, seg_indices = seg_frames if seg_frames is not None else (None, [])
    if len(seg_indices):
        for batch, n in _eval_batches(seg_dataset, seg_indices, dp):
            seg = run({"raw14": batch["raw14"]})["seg"]
            for i in range(n):
                cm = np.asarray(confusion_matrix(seg[i], batch["seg"][i], num_classes), np.int64)
                for group in ("all", str(batch["condition"][i])):
                    cms[group] = cms.get(group, 0) + cm
                    seg_counts[group] = seg_counts.get(group, 0) + 1
    result = {}
    for group in ["all"] + sorted(g for g in set(rows) | set(cms) if g != "all"):
        values = np.asarray(rows.get(group, [(np.nan, np.nan, np.nan)]), np.float64)
        labelled = group in cms and cms[group].sum() > 0
        result[group] = {"psnr": float(values[:, 0].mean()), "ssim": float(values[:, 1].mean()),
                         "entropy": float(values[:, 2].mean()),
                         "miou": float(mean_iou(cms[group])) if labelled else float("nan"),
                         "count": len(rows.get(group, [])),
                         "seg_count": seg_counts.get(group, 0)}
    return result


def evaluate_stage2(cfg: Config, unet_vars: dict | None, da_params: Any, dataset, indices,
                    dp: DataParallel, align: str | None = None) -> dict[str, dict[str, float]]:
    """Depth metrics over `indices`: {'all': {...}, <condition>: {...}}, each with the
    `DEPTH_METRICS` means, count, nonfinite_pixels and nonfinite_images
    (`metrics.DepthMetricAccumulator`).

    Ground truth: the dataset's `depth` (H, W) where `valid`, within [data.min_depth,
    data.max_depth]; predictions (H, W) are aligned per image (`align`: None, 'median' or
    'scale_shift') and then clamped to the same range."""
    frozen = None if unet_vars is None else {"unet": unet_vars}

    run = _Predictor(dp, "stage2", cfg, {"frozen": frozen, "depth": da_params})
    acc = DepthMetricAccumulator(align=align, min_depth=cfg.data.min_depth,
                                 max_depth=cfg.data.max_depth)
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
      params or None, 'segmentation': what the segmentation branch was trained on, as the
      run recorded it (`train.loop.load_stage1`), or None}).
    """
    from irdepth_jax.config import apply_overrides

    directory, stage = find_checkpoint(path)
    try:
        meta = _read_meta(directory, stage)
        cfg = apply_overrides(from_dict(meta["config"]), list(overrides))
        segmentation = meta.get("segmentation")
        if stage == "stage1_i1":
            segmentation = {"labeled_frames": 0, "why": "Stage I-1 only (no I-2 checkpoint)"}
        if stage.startswith("stage1"):
            items, _ = restore_items(directory, stage, {"model": init_unet(cfg)})
            return cfg, stage, {"unet": dict(items["model"]), "depth": None,
                                "segmentation": segmentation}
        templates = {"model": {"params": random_depth(cfg), "batch_stats": {}}}
        has_unet = cfg.stage2.preprocessing == "hsv" or cfg.stage2.sky_loss
        if has_unet:
            templates["frozen"] = {"unet": init_unet(cfg)}
        items, _ = restore_items(directory, stage, templates)
    except CheckpointError as err:
        raise RunError(str(err)) from None
    unet = dict(items["frozen"]["unet"]) if has_unet else None
    return cfg, stage, {"unet": unet, "depth": items["model"]["params"],
                        "segmentation": segmentation}


def _read_meta(directory: str, stage: str) -> dict:
    from irdepth_jax.train.checkpoint import Checkpointer
    reader = Checkpointer(directory, stage, max_to_keep=None, read_only=True)
    try:
        return reader.read_meta()
    finally:
        reader.close()


def evaluate_run(path: str, data: str, split: str = "test", fmt: str = "auto",
                 out_dir: str | None = None, overrides: Sequence[str] = (),
                 dp: DataParallel | None = None, stride: int = 1, align: str | None = None,
                 strict: bool = False) -> dict:
    """Evaluates a run on a split and writes ``eval_<split>.md`` and ``.json``.

    Args:
      path: the run's workdir or a checkpoint directory.
      data: the dataset directory (folder format or MS2).
      split: 'train' | 'val' | 'test' (MS2: also test_day / test_night / test_rainy).
      out_dir: where the tables go (default: `path`).
      stride: 1: every frame; N > 1: frames[0:-1:N] of the split's frame list (all sequences
        concatenated), as the official MS2 loader subsamples its test sets (N = 10).
      align: per-image alignment of the predicted depth before the metrics: None, 'median'
        or 'scale_shift'.
      strict: MS2: a listed sequence that is not on disk is an error (default: skipped with a
        warning).
    Returns:
      {'stage', 'split', 'protocol': {'stride', 'frames', 'align', 'clamp': [min, max] m},
      'stage1': table or None, 'stage2': table or None, 'markdown'}.
    """
    cfg, stage, model = load_model(path, overrides)
    source = DataSource(data, fmt, strict=strict, raw_bits=cfg.data.raw_bits)
    dataset, indices = source.frames(split, stride=stride)
    if len(indices) == 0:
        raise RunError(f"--data {data}: split {split!r} has no frames")
    dp = dp or DataParallel("single")
    result: dict[str, Any] = {
        "stage": stage, "split": split, "stage1": None, "stage2": None,
        "protocol": {"stride": stride, "frames": len(indices), "align": align or "none",
                     "clamp": [cfg.data.min_depth, cfg.data.max_depth]},
        "segmentation_branch": model["segmentation"]}
    if model["unet"] is not None:
        result["stage1"] = evaluate_stage1(cfg, model["unet"], dataset, indices, dp,
                                           seg_frames=source.seg_frames(split))
    if model["depth"] is not None:
        result["stage2"] = evaluate_stage2(cfg, model["unet"], model["depth"], dataset, indices,
                                           dp, align=align)
    result["markdown"] = format_tables(result)
    out_dir = out_dir or path
    make_dirs(out_dir)
    write_bytes(os.path.join(out_dir, f"eval_{split}.md"), result["markdown"].encode())
    table = {k: v for k, v in result.items() if k != "markdown"}
    write_bytes(os.path.join(out_dir, f"eval_{split}.json"), json.dumps(table, indent=2).encode())
    return result


def _table(title: str, table: dict[str, dict[str, float]], columns: Sequence[str]) -> str:
    lines = [f"### {title}", "", "| condition | " + " | ".join(columns) + " | images |",
             "|---" * (len(columns) + 2) + "|"]
    for group, values in table.items():
        cells = [str(v) if isinstance(v, int) else f"{v:.4f}" if np.isfinite(v) else "-"
                 for v in (values[c] for c in columns)]
        lines.append(f"| {group} | " + " | ".join(cells) + f" | {values['count']} |")
    return "\n".join(lines) + "\n"


def nonfinite_warning(result: dict) -> str | None:
    """One line saying how many depth predictions of an `evaluate_run` result were NaN / inf
    (their images' metrics and every mean they enter are NaN), or None when there were none."""
    depth = result.get("stage2")
    if not depth or not depth["all"]["nonfinite_images"]:
        return None
    return (f"the model predicted non-finite depth (NaN / inf) on "
            f"{depth['all']['nonfinite_pixels']} pixels of {depth['all']['nonfinite_images']} "
            f"of {result['protocol']['frames']} images; their metrics are NaN")


def format_tables(result: dict) -> str:
    """The Markdown tables of an `evaluate_run` result, with the protocol it used."""
    parts = [f"## Evaluation on split `{result['split']}` ({result['stage']} checkpoint)\n"]
    protocol = result["protocol"]
    frames = ("every frame" if protocol["stride"] == 1
              else f"frames[0:-1:{protocol['stride']}]")
    low, high = protocol["clamp"]
    parts.append(f"Protocol: {protocol['frames']} images ({frames} of the split); depth: "
                 f"alignment {protocol['align']}, predictions clamped to [{low:g}, {high:g}] m "
                 "(the valid ground-truth range).\n")
    warning = nonfinite_warning(result)
    if warning:
        parts.append(f"**Warning: {warning}.**\n")
    segmentation = result.get("segmentation_branch") or {}
    if segmentation.get("labeled_frames") == 0:
        parts.append("**The segmentation branch of this model was never trained** "
                     f"({segmentation.get('why', 'no labelled frames')}): its mIoU means "
                     "nothing, and the depth model does not use it (hue constant, no sky "
                     "loss).\n")
    if result.get("stage2") is not None:
        nonfinite = ("nonfinite_pixels", "nonfinite_images") if warning else ()
        parts.append(_table("Depth (Stage II)", result["stage2"], DEPTH_METRICS + nonfinite))
    if result.get("stage1") is not None:
        parts.append(_table("Reconstruction and segmentation (Stage I)", result["stage1"],
                            ("psnr", "ssim", "entropy", "miou")))
    return "\n".join(parts)


# --------------------------------------------------------------------------- predict
SKIPPED_NAMES_SHOWN = 8
"""Skipped files named in predict's summary line (the rest are counted)."""


def list_inputs(inputs: Sequence[str], pattern: str | None = None
                ) -> list[tuple[str, list[str]]]:
    """The files `inputs` name, per input: (input, its files).

    A file stands for itself; a folder for its files (not sub-folders) whose names match the
    glob `pattern` (default: every file with a `data.rawio.RAW_SUFFIXES` suffix), sorted.
    RunError (one line) for a missing path or a folder with no such file.
    """
    from irdepth_jax.data.rawio import RAW_SUFFIXES

    listed = []
    for item in inputs:
        if os.path.isdir(item):
            names = sorted(n for n in os.listdir(item) if os.path.isfile(os.path.join(item, n))
                           and (fnmatch.fnmatch(n, pattern) if pattern
                                else n.lower().endswith(RAW_SUFFIXES)))
            if not names:
                wanted = (f"--glob {pattern!r}" if pattern
                          else f"a raw frame suffix ({', '.join(RAW_SUFFIXES)})")
                raise RunError(f"{item}: no file matches {wanted}")
            listed.append((item, [os.path.join(item, n) for n in names]))
        elif os.path.isfile(item):
            listed.append((item, [item]))
        else:
            raise RunError(f"{item}: no such file or directory")
    return listed


def thermal_files(inputs: Sequence[str], bits: int, pattern: str | None = None,
                  strict: bool = False) -> list[str]:
    """The raw thermal files among `inputs` (files and folders, see `list_inputs`), each read
    and checked as `bits`-bit counts (`data.rawio.read_frames`).

    In a folder, 8-bit and colour images (visible / NIR frames beside the thermal ones) are
    skipped and named in one ``irdepth: skipped ...`` line on stderr; with `strict` they are an
    error. A file named in `inputs` must be a thermal frame, and so must a folder hold at least
    one. Outputs are named by frame: two frames of the same name are an error.

    Returns:
      the thermal files, in order.
    Raises:
      RunError / `data.rawio.RawFileError` (ValueErrors, one line naming the file).
    """
    from irdepth_jax.data.rawio import NotThermalError, read_frames

    kept, skipped, owner = [], [], {}
    in_folders = 0
    for item, files in list_inputs(inputs, pattern):
        folder = os.path.isdir(item)
        in_folders += len(files) if folder else 0
        thermal = 0
        for f in files:
            try:
                frames = read_frames(f, bits)
            except NotThermalError as err:
                if strict or not folder:
                    hint = " (--strict: pick the thermal files with --glob)" if folder else ""
                    raise RunError(f"{err}{hint}") from None
                skipped.append(f)
                continue
            for name, _ in frames:
                if name in owner:
                    raise RunError(f"{f} and {owner[name]}: same name {name!r}, their outputs "
                                   "would overwrite each other (predict them into separate "
                                   "--out folders)")
                owner[name] = f
            kept.append(f)
            thermal += 1
        if folder and not thermal:
            raise RunError(f"{item}: none of its {len(files)} files is a raw thermal frame "
                           "(all 8-bit or colour images)")
    if skipped:
        names = [os.path.basename(f) for f in skipped]
        more = len(names) - SKIPPED_NAMES_SHOWN
        shown = ", ".join(names[:SKIPPED_NAMES_SHOWN]) + (f" and {more} more" if more > 0 else "")
        print(f"irdepth: skipped {len(skipped)} of {in_folders} files that are not raw thermal "
              f"frames (8-bit or colour): {shown}", file=sys.stderr)
    return kept


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
                  overrides: Sequence[str] = (), raw_bits: int | None = None,
                  pattern: str | None = None, strict: bool = False) -> list[str]:
    """Runs a trained model on raw frames and writes, per frame ``NAME``:

    ``NAME_depth.png`` (16-bit, metres x 256), ``NAME_depth_color.png`` and (HSV models)
    ``NAME_rgb.png`` (pseudo-RGB) and ``NAME_hsv.png`` (H, S, V as 8-bit channels). A Stage I
    checkpoint writes the pseudo-RGB / HSV images only.

    Args:
      path: a run's workdir or checkpoint directory.
      inputs: raw frame files and folders (formats: `data.rawio`; a stack gives NAME_pNNNN).
      out_dir: output directory.
      overrides: ``key=value`` config overrides.
      raw_bits: bit depth of the inputs' counts, 14 or 16 (default: the model's
        data.raw_bits); a count over it is an error.
      pattern, strict: which files of a folder are read, and whether a non-thermal one is an
        error (see `thermal_files`).
    Returns:
      the written paths. All inputs are read (and checked) before anything is written.
    Raises:
      RunError naming the input file when a prediction is not finite (NaN / inf: a NaN depth
      would be written as 0, "no depth"), before that frame's files are written; WriteError
      naming the output file when it cannot be written (`fileio.write_png`: complete files
      or none, e.g. on a full disk). The frames before are written completely.
    """
    from irdepth_jax.data.rawio import read_frames

    cfg, _, model = load_model(path, overrides)
    if model["depth"] is not None and cfg.stage2.preprocessing == "rgb":
        raise RunError(f"{path}: this model takes visible RGB images (stage2.preprocessing=rgb), "
                       "not raw frames")
    trained_bits = resolved_raw_bits(cfg)
    bits = trained_bits if raw_bits is None else raw_bits
    if bits not in BIT_DEPTHS:
        raise RunError(f"--raw-bits {bits}: choose 14 or 16")
    files = thermal_files(inputs, bits, pattern, strict)
    if bits != trained_bits:
        cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, raw_bits=bits))
        if cfg.unet.raw_scale == "fixed" and model["unet"] is not None:
            print(f"irdepth: note: {path} was trained on {trained_bits}-bit counts with "
                  f"unet.raw_scale=fixed; --raw-bits {bits} feeds it counts / {2**bits - 1}, "
                  "a scale it did not see in training", file=sys.stderr)
    make_dirs(out_dir)
    written = []
    for f in files:
        for name, raw in read_frames(f, bits):
            images = _predict_images(model, raw, cfg, bits)
            for kind, values in images.items():
                bad = int(np.size(values) - np.count_nonzero(np.isfinite(values)))
                if bad:
                    raise RunError(
                        f"{f}: the model predicted non-finite {kind} (NaN / inf) on {bad} of "
                        f"{np.size(values)} values of frame {name!r}; stopped before writing "
                        "its files")
            for kind, image in _output_pngs(images, cfg.data.max_depth).items():
                target = os.path.join(out_dir, f"{name}_{kind}.png")
                write_png(target, image)
                written.append(target)
    return written


def _predict_images(model: dict, raw: np.ndarray, cfg: Config, bits: int) -> dict:
    """A frame's predictions as float arrays: 'rgb' (pseudo-RGB) and 'hsv' (H, W, 3) in [0, 1]
    of a model with a UNet, 'depth' (H, W) metres of a Stage II model."""
    images, rgb = {}, None
    if model["unet"] is not None:
        hsv, rgb = hsv_images(model["unet"], raw[None], cfg)
        images["rgb"], images["hsv"] = np.asarray(rgb[0]), np.asarray(hsv[0])
    if model["depth"] is not None:
        if cfg.stage2.preprocessing != "hsv":
            rgb = host_image({"raw14": raw[None]}, cfg.stage2.preprocessing, bits) / 255.0
        images["depth"] = np.asarray(depth_map(model["depth"], jnp.asarray(rgb, jnp.float32),
                                               cfg))[0]
    return images


def _output_pngs(images: dict, max_depth: float) -> dict:
    """The PNGs (OpenCV BGR order) of `_predict_images`' finite predictions, by file suffix:
    rgb, hsv (8-bit), depth (16-bit, metres x 256) and depth_color."""
    to8 = lambda x: np.clip(np.round(x * 255), 0, 255).astype(np.uint8)  # noqa: E731
    pngs = {}
    if "rgb" in images:
        pngs["rgb"], pngs["hsv"] = to8(images["rgb"])[..., ::-1], to8(images["hsv"])
    if "depth" in images:
        depth = images["depth"]
        pngs["depth"] = np.clip(np.round(depth * 256.0), 0, 65535).astype(np.uint16)
        pngs["depth_color"] = colorize_depth(depth, max_depth)[..., ::-1]
    return pngs
