"""The phase driver: one training phase (Stage I-1, I-2 or II) from its first or last saved
step to its end, with logging, periodic evaluation, checkpoints and a clean stop on Ctrl-C.

A phase resumes from its latest checkpoint (``resume=True``): parameters, optimizer, step, RNG
and the loader position are restored, and metrics.jsonl lines after that step are dropped, so
an interrupted and resumed run writes exactly the lines of an uninterrupted one (wall-clock
fields aside). Ctrl-C finishes the current step, saves a checkpoint and stops (a second Ctrl-C
aborts at once).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import signal
import sys
import time
from collections.abc import Callable
from typing import Any

import jax
from tqdm.auto import tqdm

from irdepth_jax.config import Config, to_dict
from irdepth_jax.data.source import BatchStream, device_batch
from irdepth_jax.errors import Interrupted, RunError
from irdepth_jax.runs.checkpoint import FINALIZED, Checkpointer
from irdepth_jax.train.parallel import DataParallel
from irdepth_jax.train.runlog import RunLog
from irdepth_jax.train.state import TrainState
from irdepth_jax.train.steps import make_train_step


@dataclasses.dataclass
class RunOptions:
    """How to run a stage (everything that is not a hyper-parameter).

    Attributes:
      workdir: the run's directory (see the module docstring).
      resume: continue the run in `workdir` (otherwise `workdir` must not hold a run).
      parallel: 'auto' (shard_map over all devices when there are several, else single),
        'single', 'shard_map' or 'pmap'.
      devices: number of devices (None: all).
      steps: total optimizer steps of each phase (overrides the config's epochs / steps).
      stop_at: stop (with a checkpoint) once this many steps of the stage are done (the stage's
        steps count on across Stage I's two phases); resume later with `resume`.
      progress: show a tqdm progress bar (process 0 only).
      stage1_checkpoint: Stage II: the Stage I run directory (or its checkpoint directory).
      eval: run the periodic evaluation (cfg.eval_every) on the validation split.
    """

    workdir: str
    resume: bool = False
    parallel: str = "auto"
    devices: int | None = None
    steps: int | None = None
    stop_at: int | None = None
    progress: bool = True
    stage1_checkpoint: str | None = None
    eval: bool = True


def steps_for(epochs: int, steps: int | None, num_frames: int, batch_size: int) -> int:
    """Total optimizer steps of a phase: `steps` when set, else epochs x batches per epoch."""
    if steps is not None:
        return int(steps)
    return int(epochs) * max(num_frames // batch_size, 1)


@dataclasses.dataclass
class Phase:
    """One training phase for `run_phase`.

    Attributes:
      name: 'stage1_i1' | 'stage1_i2' | 'stage2'.
      state: the step-0 state (host arrays), also the restore template.
      loss_key: ``(builder, *args)``: the per-device loss is ``builder(*args, axis_name)``
        (hashable, so equal set-ups reuse one compiled step).
      accum_steps: gradient accumulation micro-batches.
      batch_size: global batch per update.
      total_steps: optimizer steps of the phase.
      stream: training batches.
      frozen: non-differentiated variables (host arrays) or None.
      evaluate: ``fn(state) -> dict`` periodic eval on the validation split, or None.
      step_offset: steps of earlier phases of the same stage (for `RunOptions.stop_at`).
      meta: extra JSON fields stored in every checkpoint of the phase (e.g. where its labels
        came from, and ``started_from``: the step of the phase it continues).
      finalize: ``fn({'params', 'batch_stats'} host arrays) -> (batch_stats, record)`` applied
        to the state after the last step, before its checkpoint (Stage I: exact BatchNorm
        statistics, `train.batch_statistics`); `record` goes into that checkpoint's meta under
        `FINALIZED`. None: the last state is saved as trained.
    """

    name: str
    state: TrainState
    loss_key: tuple
    accum_steps: int
    batch_size: int
    total_steps: int
    stream: BatchStream
    frozen: Any = None
    evaluate: Callable[[TrainState], dict] | None = None
    step_offset: int = 0
    meta: dict = dataclasses.field(default_factory=dict)
    finalize: Callable[[dict], tuple[Any, dict]] | None = None


def writing_checkpoint(frame) -> bool:
    """Whether the main thread, where a signal found it at `frame`, is in checkpoint code (ours
    or orbax's): a KeyboardInterrupt there would abandon a save half-way (and orbax logs it with
    a traceback)."""
    while frame is not None:
        module = frame.f_globals.get("__name__", "")
        if module == "irdepth_jax.runs.checkpoint" or module.startswith("orbax."):
            return True
        frame = frame.f_back
    return False


class _StopFlag:
    """SIGINT -> finish the current step, checkpoint, stop. A second Ctrl-C aborts at once
    (KeyboardInterrupt), unless it arrives while a checkpoint is written: the stop that follows
    the save is already under way, so the save is let finish."""

    def __init__(self):
        self.requested = False
        self._previous = None

    def __enter__(self):
        def handler(signum, frame):
            if self.requested and not writing_checkpoint(frame):
                raise KeyboardInterrupt
            if not self.requested:
                print("irdepth: Ctrl-C: stopping after this step with a checkpoint (Ctrl-C "
                      "again to abort at once)", file=sys.stderr, flush=True)
            self.requested = True
        try:
            self._previous = signal.signal(signal.SIGINT, handler)
        except ValueError:  # not the main thread: no handler, Ctrl-C aborts
            self._previous = None
        return self

    def __exit__(self, *exc):
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)


def run_phase(phase: Phase, cfg: Config, dp: DataParallel, opts: RunOptions, log: RunLog
              ) -> TrainState:
    """Trains one phase to `phase.total_steps` (or `opts.stop_at`), resuming if asked.

    Returns the final state (host arrays). Raises `Interrupted` after a Ctrl-C checkpoint or at
    `stop_at`.
    """
    ckpt_dir = os.path.join(opts.workdir, "checkpoints", phase.name)
    ckpt = Checkpointer(ckpt_dir, phase.name, max_to_keep=cfg.keep_checkpoints,
                        save_every=cfg.checkpoint_every)
    try:
        return _run_phase(phase, cfg, dp, opts, log, ckpt)
    finally:
        ckpt.wait()
        ckpt.close()


def _run_phase(phase, cfg, dp, opts, log, ckpt) -> TrainState:
    state = dp.replicate(phase.state) if dp.mode == "shard_map" else phase.state
    start, meta = 0, {}
    if ckpt.latest_step() is not None:
        if not opts.resume:
            raise RunError(f"{ckpt.directory} already holds checkpoints; pass `resume`")
        state, meta = ckpt.restore(state)
        start = int(meta["step"])
        if start > phase.total_steps:
            raise RunError(f"{ckpt.directory} holds step {start}, beyond the {phase.total_steps} "
                           f"steps {phase.name} now has (its `steps` or epochs changed); "
                           "resume with the earlier length or use a new `workdir`")
        if meta.get("data_state") is not None:
            phase.stream.set_state(meta["data_state"])
    if opts.resume:  # lines logged after the last checkpoint are written again
        log.truncate_after(phase.name, start)
    def host_state(s):
        return dp.unreplicate(s) if dp.mode == "pmap" else s

    frozen = None if phase.frozen is None else dp.replicate(phase.frozen)
    # what the checkpoint stores: global arrays under shard_map (multi-host safe), else one copy
    frozen_to_save = frozen if dp.mode == "shard_map" else phase.frozen

    def finalized(s):
        """(`s`, the last step's state as host_state places it, with `phase.finalize` applied;
        the meta fields it adds)."""
        variables = {"params": s.params, "batch_stats": s.batch_stats}
        stats, record = phase.finalize(variables if dp.mode == "pmap" else dp.unreplicate(variables))
        stats = dp.replicate(stats) if dp.mode == "shard_map" else stats
        return s.replace(batch_stats=stats), {FINALIZED: record}

    if start >= phase.total_steps:
        state = host_state(state)
        if phase.finalize is not None and ckpt.latest_step() is not None and FINALIZED not in meta:
            log.info(phase.name, finalize=f"step {start} was saved before {phase.name} had its "
                     "final statistics: computing them now")
            state, added = finalized(state)
            ckpt.replace(start, state, {**meta, **added}, frozen=frozen_to_save)
        return state
    state = dp.replicate(state) if dp.mode != "shard_map" else state
    step_fn = _train_step(dp, phase.loss_key, phase.accum_steps)

    saved = {"step": start}
    final_meta: dict = {}

    def save(step, force=False):
        if saved["step"] == step:
            return
        meta = {**phase.meta, "config": to_dict(cfg), "data_state": phase.stream.get_state(),
                "total_steps": phase.total_steps, **final_meta}
        if ckpt.save(step, host_state(state), meta, frozen=frozen_to_save, force=force):
            saved["step"] = step

    bar = tqdm(total=phase.total_steps, initial=start, desc=phase.name, unit="step",
               disable=not (opts.progress and jax.process_index() == 0), dynamic_ncols=True)
    last_time, last_step = time.perf_counter(), start
    with _StopFlag() as stop:
        for step in range(start + 1, phase.total_steps + 1):
            batch = device_batch(next(phase.stream), phase.name, cfg)
            state, metrics = step_fn(state, dp.shard_batch(batch), frozen)
            bar.update(1)
            if step % cfg.log_every == 0 or step == phase.total_steps:
                values = dp.metrics_to_host(metrics)
                now = time.perf_counter()
                rate = phase.batch_size * (step - last_step) / max(now - last_time, 1e-9)
                last_time, last_step = now, step
                bar.set_postfix(loss=f"{values['loss']:.4f}")
                log.write({"step": step, "stage": phase.name, **values,
                           "img_per_s": rate, "time": time.time()})
                if not all(math.isfinite(v) for v in values.values()):
                    save(step, force=True)
                    raise RunError(f"{phase.name} step {step}: non-finite loss {values}; "
                                   f"checkpoint saved in {ckpt.directory}")
            if step == phase.total_steps and phase.finalize is not None:
                final, final_meta = finalized(host_state(state))
                state = dp.replicate(final) if dp.mode == "pmap" else final
            if phase.evaluate is not None and cfg.eval_every and step % cfg.eval_every == 0:
                log.write({"step": step, "stage": phase.name, "kind": "eval",
                           **phase.evaluate(host_state(state))})
            save(step, force=step == phase.total_steps)
            stop_here = opts.stop_at is not None and phase.step_offset + step == opts.stop_at
            if stop.requested or stop_here:
                save(step, force=True)
                bar.close()
                why = "interrupted" if stop.requested else f"stopped at step {opts.stop_at}"
                raise Interrupted(f"{why}: {phase.name} checkpoint at step {step} in "
                                  f"{ckpt.directory}; continue with `resume`")
    bar.close()
    return host_state(state)


@functools.lru_cache(maxsize=16)
def _train_step(dp: DataParallel, loss_key: tuple, accum_steps: int) -> Callable:
    """The wrapped train step (cached: resumed / repeated runs in a process reuse the compiled
    step; donation off so a Ctrl-C between steps always leaves a valid state to save)."""
    builder, *args = loss_key
    loss_fn = builder(*args, axis_name=dp.axis_name)
    return dp.train_step(make_train_step(loss_fn, dp.axis_name, accum_steps), donate=False)


def make_parallel(opts: RunOptions, batch_size: int = 1, accum_steps: int = 1,
                  section: str = "stage2", frames: dict[str, int] | None = None) -> DataParallel:
    """The `DataParallel` for `opts.parallel` / `opts.devices`, checked against the batch.

    Without `opts.devices`, 'auto' takes as many devices as split the batch into `accum_steps`
    equal micro-batches each: shard_map when that is more than one, else single.

    Args:
      batch_size, accum_steps: the config's `{section}.batch_size` / `.accum_steps`.
      section: 'stage1' | 'stage2', the config section named in errors.
      frames: {phase: number of training frames} to check the batch against (the loader drops
        each epoch's incomplete last batch, so a larger batch would never make a step).
    Raises RunError (one line: the sizes and what to set) when batch_size is not a multiple of
    accum_steps x devices or exceeds a phase's training frames.
    """
    for key, value in (("batch_size", batch_size), ("accum_steps", accum_steps)):
        if value < 1:
            raise RunError(f"{section}.{key}={value}: must be at least 1")
    n = opts.devices
    if n is None:
        n = max((d for d in range(1, len(jax.devices()) + 1)
                 if batch_size % (d * accum_steps) == 0), default=1)
    mode = opts.parallel if opts.parallel != "auto" else ("shard_map" if n > 1 else "single")
    dp = DataParallel(mode, num_devices=n if mode != "single" else 1)
    n, per = dp.num_devices, accum_steps * dp.num_devices
    try:
        dp.global_batch_ok(batch_size, accum_steps)
    except ValueError:
        factors = [f"{section}.accum_steps={accum_steps}"] * (accum_steps > 1) + [
            f"{n} device{'s' * (n > 1)}"]
        fixes = ([f"{section}.accum_steps={a}" for a in range(accum_steps - 1, 0, -1)
                  if batch_size % (a * n) == 0][:1]
                 + [f"`devices` {k}" for k in range(n - 1, 0, -1)
                    if batch_size % (accum_steps * k) == 0][:1]
                 + [f"{section}.batch_size={-(-batch_size // per) * per}"])
        raise RunError(f"{section}.batch_size={batch_size} is not a multiple of "
                       f"{' x '.join(factors)}: set {' or '.join(fixes)}") from None
    unit = accum_steps * (n if opts.devices else 1)  # without --devices, n follows the batch
    for phase, count in (frames or {}).items():
        if batch_size > count:
            fix = (f"{section}.batch_size={count // unit * unit}" if count >= unit else
                   f"{section}.batch_size={count}"
                   + f" and {section}.accum_steps=1" * (accum_steps > 1)
                   + " and `devices` 1" * (unit > accum_steps))
            raise RunError(f"{section}.batch_size={batch_size} is larger than the {count} "
                           f"training frames of {phase} (an epoch drops its incomplete last "
                           f"batch, so it would have no step): set {fix}")
    return dp
