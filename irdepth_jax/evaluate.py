"""`irdepth eval`: a trained run evaluated on a dataset split, written as Markdown + JSON tables.

`evaluate_run` loads the run (`runs.variables.load_model`), runs the evaluators
(`evaluators.evaluate_stage1` / `evaluate_stage2`) on the split with the MS2 protocol options
(stride, alignment, clamping) and writes ``eval_<split>.md`` / ``.json``; `format_tables`
renders a result, `nonfinite_warning` says when predictions were NaN / inf.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from typing import Any

import numpy as np

from irdepth_jax.data.source import DataSource
from irdepth_jax.errors import RunError, counted
from irdepth_jax.evaluators import evaluate_stage1, evaluate_stage2
from irdepth_jax.fileio import make_dirs, write_bytes
from irdepth_jax.metrics import DEPTH_METRICS
from irdepth_jax.runs.variables import describe_trained_on, input_warnings, load_model
from irdepth_jax.train.parallel import DataParallel


def evaluate_run(path: str, data: str, split: str = "test", fmt: str = "auto",
                 out_dir: str | None = None, overrides: Sequence[str] = (),
                 dp: DataParallel | None = None, stride: int = 1, align: str | None = "auto",
                 strict: bool = False, gt: str | None = None) -> dict:
    """Evaluates a run on a split and writes ``eval_<split>.md`` and ``.json``.

    Args:
      path: the run's workdir or a checkpoint directory.
      data: the dataset directory (folder format or MS2).
      split: 'train' | 'val' | 'test' (MS2: also test_day / test_night / test_rainy).
      out_dir: where the tables go (default: `path`).
      stride: 1: every frame; N > 1: frames[0:-1:N] of the split's frame list (all sequences
        concatenated), as the official MS2 loader subsamples its test sets (N = 10).
      align: per-image alignment of the predicted depth before the metrics: None, 'median'
        or 'scale_shift'; 'auto': median for a relative-depth model (depth.metric=false),
        none for a metric one (`depth_alignment`).
      strict: MS2: a listed sequence that is not on disk is an error (default: skipped with a
        warning).
      gt: MS2: the depth label version the metrics compare with (`data.ms2.DEPTH_LABELS`;
        None: depth_filtered); recorded as protocol.ground_truth.
    Returns:
      {'stage', 'split', 'trained_on' (`read_trained_on`), 'warnings' (a model of an older
      version: `statistics_warnings`; the ways the split's frames differ in kind from the
      training frames: `input_warnings`), 'protocol': {'stride',
      'frames', 'align', 'clamp': [min, max] m,
      'depth': 'metric' | 'relative', 'reconstruction': what PSNR / SSIM compare with}, 'stage1':
      table or None (no psnr / ssim for MS2, which has no camera 8-bit image), 'stage2': table
      or None, 'markdown'}.
    """
    cfg, stage, model = load_model(path, overrides)
    align = depth_alignment(path, cfg, model["depth"] is not None, align)
    source = DataSource(data, fmt, strict=strict, raw_bits=cfg.data.raw_bits, depth_label=gt)
    dataset, indices = source.frames(split, stride=stride)
    if len(indices) == 0:
        raise RunError(f"`data` {data}: split {split!r} has no frames")
    described = source.describe(split)
    dp = dp or DataParallel("single")
    result: dict[str, Any] = {
        "stage": stage, "split": split, "stage1": None, "stage2": None,
        "protocol": {"stride": stride, "frames": len(indices), "align": align or "none",
                     "clamp": [cfg.data.min_depth, cfg.data.max_depth],
                     "depth": "metric" if cfg.depth.metric else "relative",
                     "ground_truth": (f"MS2 {gt or 'depth_filtered'}" if source.format == "ms2"
                                      else "the folder dataset's depth/"),
                     "reconstruction": (None if source.format == "ms2"
                                        else "the dataset's 8-bit camera image (ir8)")},
        "segmentation_branch": model["segmentation"], "trained_on": model.get("trained_on"),
        "warnings": model["warnings"] + input_warnings(
            model.get("trained_on"), {tuple(described["frame_size"])}, described["kind"])}
    if model["unet"] is not None:
        result["stage1"] = evaluate_stage1(cfg, model["unet"], dataset, indices, dp,
                                           seg_frames=source.seg_frames(split))
        if source.format == "ms2":  # ir8 is our own tone map of the raw frame: no ground truth
            result["stage1"] = {group: {k: v for k, v in row.items() if k not in ("psnr", "ssim")}
                                for group, row in result["stage1"].items()}
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


def depth_alignment(path: str, cfg, has_depth: bool, align: str | None) -> str | None:
    """The per-image alignment eval applies (None, 'median' or 'scale_shift'): `align`, where
    'auto' is median for a relative-depth model (depth.metric=false: depth up to an unknown
    scale) and none for a metric one. RunError for a relative model without an alignment (its
    metrics in metres would mean nothing)."""
    relative = has_depth and not cfg.depth.metric
    if align == "auto":
        return "median" if relative else None
    if relative and align in (None, "none"):
        raise RunError(f"{path}: a relative-depth model (depth.metric=false) predicts depth up "
                       "to an unknown scale; evaluate it with `align` median or scale_shift")
    return None if align == "none" else align


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
    relative = (" (a relative-depth model: depth up to an unknown scale, aligned per image)"
                if protocol.get("depth") == "relative" else "")
    parts.append(f"Protocol: {counted(protocol['frames'], 'image')} ({frames} of the split); depth: "
                 f"alignment {protocol['align']}{relative}, predictions clamped to [{low:g}, "
                 f"{high:g}] m (the valid ground-truth range)"
                 + (f"; ground truth: {protocol['ground_truth']}" if "ground_truth" in protocol
                    else "") + ".\n")
    if "trained_on" in result:
        parts.append(f"Model: {describe_trained_on(result['trained_on'])}.\n")
    for line in result.get("warnings", []):
        parts.append(f"**Warning: {line}.**\n")
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
    if result.get("stage1") is not None and protocol.get("reconstruction", "ir8") is None:
        parts.append(_table("Segmentation and reconstruction entropy (Stage I)", result["stage1"],
                            ("entropy", "miou")))
        parts.append("PSNR / SSIM left out: this dataset has no 8-bit camera image to compare "
                     "the reconstruction with (only this tool's own tone map of the raw frame).\n")
    elif result.get("stage1") is not None:
        parts.append(_table("Reconstruction and segmentation (Stage I)", result["stage1"],
                            ("psnr", "ssim", "entropy", "miou")))
    return "\n".join(parts)
