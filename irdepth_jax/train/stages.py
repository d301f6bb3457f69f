"""The stages of the paper's training: Stage I (I-1 reconstruction pre-training, then I-2 soft
multi-task weighting) and Stage II (Depth Anything V2 on the frozen Stage I model's HSV images,
SiLog + sky loss), each a sequence of `phase.run_phase` calls into one workdir; and depth
pretraining (`train_depth`: Depth Anything V2 on visible images with depth, the starting point a
Stage II takes with ``depth.checkpoint=RUN_DIR``).
"""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Callable

import jax
import numpy as np

from irdepth_jax.config import STAGE1_IMAGES, Config
from irdepth_jax.data.fingerprint import data_fingerprint
from irdepth_jax.data.source import (
    BatchStream,
    DataSource,
    make_loader,
    phase_frames,
    resolve_raw_bits,
    stage1_i2_frames,
)
from irdepth_jax.errors import RunError
from irdepth_jax.evaluators import evaluate_stage1, evaluate_stage2
from irdepth_jax.fileio import describe_disk, disk_full
from irdepth_jax.runs.checkpoint import CheckpointError, find_checkpoint, has_checkpoint, read_meta
from irdepth_jax.runs.variables import (
    STAGE1_STAGES,
    STALE_STATISTICS,
    init_depth,
    init_unet,
    load_stage1,
    stage1_statistics,
    take_stage1_settings,
)
from irdepth_jax.train.batch_statistics import phase_batch_stats
from irdepth_jax.train.phase import Phase, RunOptions, make_parallel, run_phase, steps_for
from irdepth_jax.train.runlog import RunLog, check_same_data, prepare_workdir, record_data
from irdepth_jax.train.state import TrainState, stage1_optimizer, stage2_optimizer
from irdepth_jax.train.steps import stage1_loss_fn, stage2_loss_fn
from irdepth_jax.train.validate import check_run
from irdepth_jax.train.workdir_lock import last_checkpoint


def _full_disk_in_one_line(train: Callable) -> Callable:
    """Decorates a stage's training function: an error that says the disk is full (a checkpoint
    save that failed, in orbax's background thread or not; a metrics.jsonl, config.json or
    TensorBoard write) becomes one RunError line naming the workdir's disk and the last
    finished checkpoint. That one restores: orbax names a step directory only once it is
    complete, and a resumed run drops a torn last metrics line."""
    @functools.wraps(train)
    def run(cfg: Config, source: DataSource, opts: RunOptions):
        try:
            return train(cfg, source, opts)
        except Exception as err:
            if not disk_full(err):
                raise
            last = last_checkpoint(opts.workdir)
            then = (f"the last good checkpoint is {last[0]} step {last[1]}; free space, then "
                    "continue with `resume`" if last else
                    "no checkpoint was finished; free space, then run again with "
                    "`resume_or_start`")
            raise RunError(f"no space left on {describe_disk(opts.workdir)}, which holds "
                           f"`workdir` {opts.workdir}: {then}") from err
    return run


def stage1_totals(cfg: Config, frames: dict[str, int], steps: int | None = None) -> dict[str, int]:
    """{'stage1_i1' | 'stage1_i2': optimizer steps} of a Stage I run of `cfg` with `frames`
    {phase: training frames}; `steps` (a run's --steps) replaces the config's step counts."""
    s1 = cfg.stage1
    return {phase: steps_for(epochs, steps if steps is not None else configured, frames[phase],
                             s1.batch_size)
            for phase, epochs, configured in (("stage1_i1", s1.epochs_i1, s1.steps_i1),
                                              ("stage1_i2", s1.epochs_i2, s1.steps_i2))}


@_full_disk_in_one_line
def train_stage1(cfg: Config, source: DataSource, opts: RunOptions) -> dict:
    """Stage I-1 (reconstruction pre-training) then I-2 (soft multi-task) into `opts.workdir`.

    Each phase ends with exact BatchNorm statistics of its final weights
    (`train.batch_statistics`), stored in its last checkpoint; resuming a run finished without
    them computes them.

    Returns {'unet': final variables, 'steps': {phase: total steps}}.
    """

    cfg = resolve_raw_bits(cfg, source)
    check_run(cfg, source, opts, "stage1")
    s1 = cfg.stage1
    i2_dataset, i2_idx, seg_info = stage1_i2_frames(source, cfg)  # refuses before any write
    frames = {"stage1_i1": phase_frames(source, "stage1_i1", cfg),
              "stage1_i2": (i2_dataset, i2_idx)}
    counts = {phase: len(idx) for phase, (_, idx) in frames.items()}
    dp = make_parallel(opts, s1.batch_size, s1.accum_steps, "stage1", counts)
    totals = stage1_totals(cfg, counts, opts.steps)
    if opts.resume:
        _check_i2_continues_i1(opts.workdir, totals["stage1_i1"])
    _prepare_workdir(opts, cfg, "stage1", source, frames)
    trained_on = source.describe()
    log = RunLog(opts.workdir)
    try:
        log.info("stage1", parallel=dp.describe(), raw_bits=cfg.data.raw_bits,
                 i1_frames=f"{len(frames['stage1_i1'][1])} ({s1.i1_frames})",
                 segmentation_labels=seg_info)
        val = source.frames("val", optional=True)
        val_seg = source.seg_frames("val")
        variables = init_unet(cfg)
        done: dict[str, int] = {}
        i1_step = 0
        for phase_name in ("stage1_i1", "stage1_i2"):
            dataset, idx = frames[phase_name]
            total = totals[phase_name]
            tx, lr_fns = stage1_optimizer(cfg, phase_name)
            state = TrainState.create(variables["params"], variables["batch_stats"], tx,
                                      jax.random.PRNGKey(cfg.seed), lr_fns)
            evaluate = ((lambda st: evaluate_stage1(cfg, _unet_vars(st), *val, dp,
                                                    seg_frames=val_seg)["all"])
                        if opts.eval and len(val[1]) else None)
            stream = BatchStream(make_loader(dataset, idx, s1.batch_size, cfg.seed, True, cfg))
            meta = ({"segmentation": seg_info, "started_from": {"stage1_i1": i1_step}}
                    if phase_name == "stage1_i2" else {})
            meta["trained_on"] = {"data": trained_on, "frames": len(idx),
                                  "steps": {**done, phase_name: total}}
            phase = Phase(phase_name, state, (stage1_loss_fn, cfg, phase_name),
                          s1.accum_steps, s1.batch_size, total, stream, evaluate=evaluate,
                          step_offset=sum(done.values()), meta=meta,
                          finalize=phase_batch_stats(cfg, dataset, idx, phase_name))
            final = run_phase(phase, cfg, dp, opts, log)
            variables = _unet_vars(final)
            if phase_name == "stage1_i1":  # the step I-2 starts from
                i1_step = int(np.asarray(final.step).reshape(-1)[0])
            done[phase_name] = total
        return {"unet": variables, "steps": done}
    finally:
        log.close()


def _prepare_workdir(opts: RunOptions, cfg: Config, stage: str, source: DataSource,
                     frames: dict) -> None:
    """`prepare_workdir`, and the fingerprint of the frames `stage` trains on ({phase: (dataset,
    indices)}) recorded when the run starts, checked on a resume (refused when it changed)."""
    fingerprint = data_fingerprint(frames)
    if opts.resume:
        check_same_data(opts.workdir, stage, fingerprint, source.path)
    prepare_workdir(opts.workdir, cfg, opts.resume)
    if not opts.resume:
        record_data(opts.workdir, stage, fingerprint)


def _check_i2_continues_i1(workdir: str, i1_total: int) -> None:
    """RunError (before anything is trained) when the run's I-2 checkpoints started from I-1 at
    another step than the I-1 length asked for now: after `--steps 4` then `--resume --steps 8`,
    I-1 would be extended to 8 while I-2 went on from its start at I-1 step 4, giving neither
    run. Checkpoints written before ``started_from`` was recorded are not checked."""
    directory = os.path.join(workdir, "checkpoints", "stage1_i2")
    if not has_checkpoint(directory):
        return
    try:
        started = read_meta(directory).get("started_from", {}).get("stage1_i1")
    except CheckpointError as err:
        raise RunError(str(err)) from None
    if started is not None and started != i1_total:
        raise RunError(
            f"{directory}: Stage I-2 started from stage1_i1 at step {started}, but stage1_i1 "
            f"would now run to step {i1_total} (`steps` or epochs changed): the result would be "
            f"neither run. Delete {directory} to run I-2 again from the new I-1, or resume "
            f"with the earlier length")


def train_depth(cfg: Config, source: DataSource, opts: RunOptions) -> dict:
    """Depth pretraining: Depth Anything V2 trained (or fine-tuned, from `depth.checkpoint`) on
    the dataset's aligned visible images (rgb/; or, with ``stage2.preprocessing=blank``, a constant
    grey image: the control of the pretraining gate) with SiLog, the official parameter groups
    (backbone at `stage2.learning_rate`, head at `head_lr_multiplier` x it) and Stage II's
    schedule, into `opts.workdir`. It is Stage II with ``stage2.preprocessing=rgb``, no sky loss
    and no Stage I model, so it resumes, runs multi-device and is evaluated like Stage II; a
    Stage II starts from it with ``depth.checkpoint=RUN_DIR`` as from a released checkpoint.

    Returns {'unet': None, 'depth': final Depth Anything V2 params}.
    """
    if opts.stage1_checkpoint is not None:
        raise RunError("`stage1_checkpoint`: train depth trains on visible images, without a "
                       "Stage I model")
    if cfg.stage2.preprocessing not in ("hsv", "rgb", "blank"):  # hsv: the presets' default
        raise RunError(f"stage2.preprocessing={cfg.stage2.preprocessing}: train depth trains on "
                       "the visible images (rgb), or on a constant grey image (blank: the control "
                       "that measures what the scene layout alone gives); the thermal inputs are "
                       "train stage2's")
    image = "blank" if cfg.stage2.preprocessing == "blank" else "rgb"
    stage2 = dataclasses.replace(cfg.stage2, preprocessing=image, sky_loss=False)
    return train_stage2(dataclasses.replace(cfg, stage2=stage2), source, opts)


def _unet_vars(state: TrainState) -> dict:
    return {"params": state.params, "batch_stats": state.batch_stats}


def check_segmentation_use(cfg: Config, segmentation: dict, where: str) -> None:
    """RunError when Stage II would take its Hue channel or sky mask from a segmentation branch
    that saw no labelled frame (it outputs noise: on MS2 its 'sky' covered 36 % of the pixels
    against 11.5 % true); names the switches that make the run valid."""
    if segmentation.get("labeled_frames") != 0:
        return
    s2 = cfg.stage2
    uses = []
    if s2.preprocessing == "hsv" and s2.hue_mode != "constant":
        uses.append("its Hue channel (pass stage2.hue_mode=constant)")
    if s2.sky_loss:
        uses.append("its sky mask (pass stage2.sky_loss=false)")
    if uses:
        raise RunError(f"`stage1_checkpoint` {where}: the segmentation branch was never trained "
                       f"({segmentation.get('why', 'no labelled frames')}), yet Stage II would "
                       f"use {' and '.join(uses)}; or retrain Stage I with "
                       "stage1.seg_labels=synthetic or =PATH")


def sky_reference_depth(cfg: Config, train_max_depth: float) -> float:
    """The sky term's target depth: sky_ref_factor x the largest depth a prediction may reach and
    the metrics count: min(largest training depth, data.max_depth, and depth.max_depth for the
    metric head, whose sigmoid never reaches it). Uncapped, one far LiDAR return (120 m against a
    head capped at 80 m) leaves a sky term that cannot reach zero and saturates the head."""
    ceiling = min(train_max_depth, cfg.data.max_depth)
    if cfg.depth.metric:
        ceiling = min(ceiling, cfg.depth.max_depth)
    return cfg.stage2.sky_ref_factor * ceiling


@_full_disk_in_one_line
def train_stage2(cfg: Config, source: DataSource, opts: RunOptions) -> dict:
    """Stage II: Depth Anything V2 on the frozen Stage I model's HSV images (or a baseline
    pre-processing, `cfg.stage2.preprocessing`) into `opts.workdir`.

    The settings that define the Stage I model (`config.STAGE1_MODEL_KEYS`) are taken from
    `opts.stage1_checkpoint` (`take_stage1_settings`), so the run's config describes the model
    it trains on.

    Returns {'unet': Stage I variables or None, 'depth': final Depth Anything V2 params}.
    """

    taken = {}
    if opts.stage1_checkpoint is not None:
        cfg, taken = take_stage1_settings(opts.stage1_checkpoint, cfg)
    cfg = resolve_raw_bits(cfg, source)
    check_run(cfg, source, opts, "stage2")
    s2 = cfg.stage2
    if opts.stage1_checkpoint is None and (s2.preprocessing in STAGE1_IMAGES or s2.sky_loss):
        raise RunError(f"stage 2 needs `stage1_checkpoint` (for the {s2.preprocessing} input and "
                       "the sky mask); "
                       "for a baseline without it use stage2.preprocessing=he "
                       "stage2.sky_loss=false")
    unet, segmentation = None, {"labeled_frames": None, "why": "no Stage I model"}
    stage1_trained_on = stage1_batch_stats = None
    if opts.stage1_checkpoint is not None:
        unet, segmentation = load_stage1(opts.stage1_checkpoint, cfg)
        stage1_meta = read_meta(find_checkpoint(opts.stage1_checkpoint, STAGE1_STAGES)[0])
        stage1_trained_on = stage1_meta.get("trained_on")
        stage1_batch_stats = stage1_statistics(stage1_meta)
        check_segmentation_use(cfg, segmentation, opts.stage1_checkpoint)
    dataset, train_idx = phase_frames(source, "stage2", cfg)
    ref_depth = sky_reference_depth(cfg, source.max_depth())
    val = source.frames("val", optional=True)
    dp = make_parallel(opts, s2.batch_size, frames={"stage2": len(train_idx)})
    params, depth_init = init_depth(cfg)  # a bad depth.checkpoint is refused before any write
    _prepare_workdir(opts, cfg, "stage2", source, {"stage2": (dataset, train_idx)})
    log = RunLog(opts.workdir)
    try:
        log.info("stage2", parallel=dp.describe(), raw_bits=cfg.data.raw_bits)
        if unet is not None:
            log.info("stage2", stage1=opts.stage1_checkpoint, segmentation_branch=segmentation,
                     hue_mode=s2.hue_mode)
        if unet is not None and stage1_batch_stats is None:
            log.info("stage2", warning=f"`stage1_checkpoint` {opts.stage1_checkpoint}: {STALE_STATISTICS}, "
                     "and they make the images this run trains on: resume it once first (train "
                     "stage1 with `resume`)")
        if taken:
            log.info("stage2", settings_from_stage1={k: f"{v[1]} (was {v[0]})" for k, v in taken.items()})
        log.info("stage2", input=s2.preprocessing,
                 sky_loss=f"on, reference depth {ref_depth:.2f} m" if s2.sky_loss else "off")
        log.info("stage2", **depth_init)
        total = steps_for(s2.epochs, opts.steps if opts.steps is not None else s2.steps,
                          len(train_idx), s2.batch_size)
        tx, lr_fns = stage2_optimizer(cfg, total)
        state = TrainState.create(params, {}, tx, jax.random.PRNGKey(cfg.seed), lr_fns)
        evaluate = ((lambda st: evaluate_stage2(cfg, unet, st.params, *val, dp)["all"])
                    if opts.eval and len(val[1]) else None)
        stream = BatchStream(make_loader(dataset, train_idx, s2.batch_size, cfg.seed, True, cfg))
        frozen = None if unet is None else {"unet": unet}
        trained_on = {"data": source.describe(), "frames": len(train_idx),
                      "steps": {"stage2": total}, "depth_network": depth_init,
                      "stage1": stage1_trained_on, "stage1_batch_stats": stage1_batch_stats}
        phase = Phase("stage2", state, (stage2_loss_fn, cfg, ref_depth), 1, s2.batch_size, total,
                      stream, frozen=frozen, evaluate=evaluate,
                      meta={"segmentation": segmentation, "trained_on": trained_on})
        final = run_phase(phase, cfg, dp, opts, log)
        return {"unet": unet, "depth": final.params}
    finally:
        log.close()
