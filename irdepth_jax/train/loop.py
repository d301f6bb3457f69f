"""The stage loops: Stage I (I-1 then I-2) and Stage II, with logging, eval and checkpoints.

Work directory of a run::

    WORKDIR/config.json             the full config (`config.to_dict`) of the run
    WORKDIR/metrics.jsonl           one JSON object per logged step (and per periodic eval)
    WORKDIR/tb/                     TensorBoard event files (tensorboardX)
    WORKDIR/checkpoints/<phase>/    orbax checkpoints of each phase (stage1_i1, stage1_i2, stage2)

A phase resumes from its latest checkpoint (``resume=True``): parameters, optimizer, step, RNG
and the loader position are restored, and metrics.jsonl lines after that step are dropped, so
an interrupted and resumed run writes exactly the lines of an uninterrupted one (wall-clock
fields aside). Ctrl-C finishes the current step, saves a checkpoint and stops (a second Ctrl-C
aborts at once).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import signal
import time
from collections.abc import Callable, Iterator
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from irdepth_jax.config import Config, to_dict
from irdepth_jax.imaging.tonemap import TONEMAPS
from irdepth_jax.models.pipeline import depth_model_config
from irdepth_jax.models.unet import MTSAUNet
from irdepth_jax.train.checkpoint import CheckpointError, Checkpointer, restore_model
from irdepth_jax.train.parallel import DataParallel
from irdepth_jax.train.state import TrainState, stage1_optimizer, stage2_optimizer
from irdepth_jax.train.steps import make_train_step, stage1_loss_fn, stage2_loss_fn

WALL_CLOCK_FIELDS = ("time", "img_per_s")
"""metrics.jsonl fields that depend on the machine's speed (the rest is deterministic)."""

PREPROCESSING = ("hsv", "rgb") + tuple(TONEMAPS)


class RunError(ValueError):
    """A run that cannot start (one-line message naming the file, directory or key)."""


class Interrupted(Exception):
    """Training stopped on Ctrl-C after saving a checkpoint (message says where)."""


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


# --------------------------------------------------------------------------- run directory
class RunLog:
    """metrics.jsonl + TensorBoard writer of process 0 (other processes: no-ops)."""

    def __init__(self, workdir: str):
        self.enabled = jax.process_index() == 0
        self.path = os.path.join(workdir, "metrics.jsonl")
        self._tb = None
        if self.enabled:
            from tensorboardX import SummaryWriter
            self._tb = SummaryWriter(os.path.join(workdir, "tb"))

    def truncate_after(self, stage: str, step: int) -> None:
        """Drops lines of `stage` logged after `step` (written before an interruption)."""
        if not self.enabled or not os.path.exists(self.path):
            return
        with open(self.path) as f:
            lines = [ln for ln in f if ln.strip()]
        keep = [ln for ln in lines
                if not (json.loads(ln).get("stage") == stage and json.loads(ln)["step"] > step)]
        with open(self.path, "w") as f:
            f.writelines(keep)

    def write(self, record: dict) -> None:
        if not self.enabled:
            return
        with open(self.path, "a") as f:
            f.write(json.dumps(record) + "\n")
        prefix = record["stage"] + ("/eval" if record.get("kind") == "eval" else "")
        for key, value in _flatten(record).items():
            if key not in ("step",) and isinstance(value, (int, float)):
                self._tb.add_scalar(f"{prefix}/{key}", value, record["step"])
        self._tb.flush()

    def close(self) -> None:
        if self._tb is not None:
            self._tb.close()


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}/"))
        else:
            out[f"{prefix}{k}"] = v
    return out


def prepare_workdir(workdir: str, cfg: Config, resume: bool) -> None:
    """Creates `workdir` and its config.json; refuses to overwrite a run without `resume`.

    With `resume`, the stored config must equal `cfg` (a changed hyper-parameter would make the
    resumed run a different run).
    """
    path = os.path.join(workdir, "config.json")
    exists = os.path.exists(path) or os.path.exists(os.path.join(workdir, "checkpoints"))
    if exists and not resume:
        raise RunError(f"workdir {workdir} already holds a run; pass --resume to continue it or "
                       "choose another --workdir")
    if resume and os.path.exists(path):
        with open(path) as f:
            stored = json.load(f)
        current = json.loads(json.dumps(to_dict(cfg)))
        if stored != current:
            changed = sorted(k for k in _flatten(current)
                             if _flatten(stored).get(k) != _flatten(current)[k])
            raise RunError(f"--resume: config differs from {path} in {', '.join(changed)}")
        return
    if jax.process_count() > 1:  # every process has checked before process 0 writes
        from jax.experimental import multihost_utils
        multihost_utils.sync_global_devices("irdepth:prepare_workdir")
    if jax.process_index() == 0:
        os.makedirs(workdir, exist_ok=True)
        with open(path, "w") as f:
            json.dump(to_dict(cfg), f, indent=2)


# --------------------------------------------------------------------------- data
class DataSource:
    """Frames of a dataset directory by split: our folder format or MS2.

    Args:
      path: the dataset directory.
      fmt: 'auto' (MS2 when the directory has MS2's sync_data/, else the folder format),
        'folder' or 'ms2'.
    Raises:
      RunError (one line, naming the directory) when it is not a dataset.
    """

    def __init__(self, path: str, fmt: str = "auto"):
        from irdepth_jax.data.folder import DatasetError, FolderDataset

        if fmt not in ("auto", "folder", "ms2"):
            raise RunError(f"--format {fmt!r}: choose auto, folder or ms2")
        if not os.path.isdir(path):
            raise RunError(f"--data {path}: no such directory")
        self.path = path
        self.format = fmt if fmt != "auto" else (
            "ms2" if os.path.isdir(os.path.join(path, "sync_data")) else "folder")
        self._error = DatasetError
        self._ms2: dict = {}
        self._folder = None
        if self.format == "folder":
            try:
                self._folder = FolderDataset(path)
            except (DatasetError, ValueError, OSError) as err:
                raise RunError(f"--data {path}: {_one_line(err)}") from None

    def frames(self, split: str, labeled: bool | None = None, optional: bool = False,
               stride: int = 1) -> tuple[Any, np.ndarray]:
        """(dataset, indices) of the frames of `split` (and labelled ones when `labeled`), every
        `stride`-th one (MS2: every stride-th frame of each sequence, its test protocol is 10).

        A split the dataset lacks raises RunError, or gives (None, []) when `optional`.
        """
        if stride < 1:
            raise RunError(f"stride {stride}: must be >= 1")
        try:
            if self._folder is not None:
                return self._folder, self._folder.indices(split=split, labeled=labeled)[::stride]
            from irdepth_jax.data.ms2 import MS2Dataset
            if (split, stride) not in self._ms2:
                self._ms2[split, stride] = MS2Dataset(self.path, split, stride=stride)
            ds = self._ms2[split, stride]
            return ds, ds.indices(labeled=labeled)
        except (self._error, ValueError, OSError) as err:
            if optional:
                return None, np.zeros(0, np.int64)
            raise RunError(f"--data {self.path}: {_one_line(err)}") from None

    def max_depth(self) -> float:
        """Largest depth of the training frames (metres): the sky's reference depth / 0.99."""
        dataset, _ = self.frames("train")
        return float(dataset.max_depth(split="train"))


def _one_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return text[0] if text else type(err).__name__


def phase_frames(source: DataSource, phase: str) -> tuple[Any, np.ndarray]:
    """(dataset, indices) a phase trains on: I-1 and II all training frames, I-2 the labelled
    training frames (all training frames when there are none, e.g. MS2: the cross-entropy then
    sees only ignored pixels and the segmentation branch stays as it is)."""
    dataset, idx = source.frames("train")
    if phase == "stage1_i2":
        labeled_ds, labeled_idx = source.frames("train", labeled=True)
        if len(labeled_idx):
            dataset, idx = labeled_ds, labeled_idx
    if len(idx) == 0:
        raise RunError(f"--data {source.path}: no training frames")
    return dataset, np.asarray(idx)


def host_image(batch: dict, preprocessing: str) -> np.ndarray | None:
    """The Stage II input image (B, H, W, 3) uint8 made on the host, or None for 'hsv'.

    'rgb': the aligned visible image; a tonemap name ('he', 'clahe', 'camera', ...): the
    tone-mapped raw frame replicated to three channels.
    """
    if preprocessing == "hsv":
        return None
    if preprocessing == "rgb":
        return np.asarray(batch["rgb"], np.uint8)
    fn = TONEMAPS[preprocessing]
    grey = np.stack([fn(np.asarray(raw)) for raw in batch["raw14"]])
    return np.repeat(grey[..., None], 3, axis=-1)


STAGE_KEYS = {
    "stage1_i1": ("raw14", "ir8"),
    "stage1_i2": ("raw14", "ir8", "seg"),
    "stage2": ("raw14", "depth", "valid"),
}


def device_batch(batch: dict, phase: str, cfg: Config) -> dict:
    """The arrays a phase's step needs from a loader batch (numpy, host side)."""
    out = {k: np.asarray(batch[k]) for k in STAGE_KEYS[phase]}
    if phase == "stage2":
        image = host_image(batch, cfg.stage2.preprocessing)
        if image is not None:
            out["image"] = image
    return out


def make_loader(dataset, indices, batch_size: int, seed: int, train: bool, cfg: Config):
    """A `data.loader.Loader` over `indices` for this process (global batch / process count)."""
    from irdepth_jax.data.loader import Loader

    per_process = batch_size // jax.process_count()
    return Loader(dataset, indices, batch_size=per_process, seed=seed, shuffle=train,
                  drop_remainder=train, augment=train and cfg.data.augment,
                  process_index=jax.process_index(), process_count=jax.process_count())


class BatchStream:
    """Endless batches of a `Loader`, epoch after epoch, with a resumable position."""

    def __init__(self, loader):
        self.loader = loader
        self._it: Iterator | None = None

    def __next__(self) -> dict:
        if self._it is None:
            self._it = iter(self.loader)
        try:
            return next(self._it)
        except StopIteration:
            self._it = iter(self.loader)
            return next(self._it)

    def get_state(self) -> Any:
        return self.loader.get_state()

    def set_state(self, state: Any) -> None:
        self.loader.set_state(state)
        self._it = None


def steps_for(epochs: int, steps: int | None, num_frames: int, batch_size: int) -> int:
    """Total optimizer steps of a phase: `steps` when set, else epochs x batches per epoch."""
    if steps is not None:
        return int(steps)
    return int(epochs) * max(num_frames // batch_size, 1)


# --------------------------------------------------------------------------- phase driver
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


class _StopFlag:
    """SIGINT -> finish the current step, checkpoint, stop. A second Ctrl-C aborts."""

    def __init__(self):
        self.requested = False
        self._previous = None

    def __enter__(self):
        def handler(signum, frame):
            if self.requested:
                raise KeyboardInterrupt
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
    start = 0
    if ckpt.latest_step() is not None:
        if not opts.resume:
            raise RunError(f"{ckpt.directory} already holds checkpoints; pass --resume")
        state, meta = ckpt.restore(state)
        start = int(meta["step"])
        if meta.get("data_state") is not None:
            phase.stream.set_state(meta["data_state"])
    if opts.resume:  # lines logged after the last checkpoint are written again
        log.truncate_after(phase.name, start)
    if start >= phase.total_steps:
        return dp.unreplicate(state) if dp.mode == "pmap" else state
    state = dp.replicate(state) if dp.mode != "shard_map" else state
    frozen = None if phase.frozen is None else dp.replicate(phase.frozen)
    # what the checkpoint stores: global arrays under shard_map (multi-host safe), else one copy
    frozen_to_save = frozen if dp.mode == "shard_map" else phase.frozen
    step_fn = _train_step(dp, phase.loss_key, phase.accum_steps)

    def host_state(s):
        return dp.unreplicate(s) if dp.mode == "pmap" else s

    saved = {"step": start}

    def save(step, force=False):
        if saved["step"] == step:
            return
        meta = {"config": to_dict(cfg), "data_state": phase.stream.get_state(),
                "total_steps": phase.total_steps}
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
                                  f"{ckpt.directory}; continue with --resume")
    bar.close()
    return host_state(state)


@functools.lru_cache(maxsize=16)
def _train_step(dp: DataParallel, loss_key: tuple, accum_steps: int) -> Callable:
    """The wrapped train step (cached: resumed / repeated runs in a process reuse the compiled
    step; donation off so a Ctrl-C between steps always leaves a valid state to save)."""
    builder, *args = loss_key
    loss_fn = builder(*args, axis_name=dp.axis_name)
    return dp.train_step(make_train_step(loss_fn, dp.axis_name, accum_steps), donate=False)


# --------------------------------------------------------------------------- stages
def make_parallel(opts: RunOptions, batch_size: int = 1, accum_steps: int = 1) -> DataParallel:
    """The `DataParallel` for `opts.parallel` / `opts.devices`.

    Without `opts.devices`, 'auto' takes as many devices as divide the batch (batch_size /
    accum_steps examples per micro-batch): shard_map when that is more than one, else single.
    """
    mode = opts.parallel
    n = opts.devices
    if n is None:
        per_micro = max(batch_size // max(accum_steps, 1), 1)
        n = max(d for d in range(1, len(jax.devices()) + 1)
                if per_micro % d == 0 and batch_size % (d * accum_steps) == 0)
    if mode == "auto":
        mode = "shard_map" if n > 1 else "single"
    return DataParallel(mode, num_devices=n if mode != "single" else 1)


def init_key(seed: int) -> jax.Array:
    """Parameter-initialisation key. The 'rbg' generator: XLA compiles a model's init (one
    random draw per parameter) several times faster than with the default threefry."""
    return jax.random.key(seed, impl="rbg")


@functools.partial(jax.jit, static_argnums=0)
def _init_unet(unet_cfg, key):
    return MTSAUNet(unet_cfg).init(key, jnp.zeros((1, 32, 32), jnp.uint16), train=False)


def init_unet(cfg: Config) -> dict:
    """Fresh MTSA-UNet variables {'params', 'batch_stats'} (seed cfg.seed; any frame size)."""
    variables = _init_unet(cfg.unet, init_key(cfg.seed))
    return {"params": variables["params"], "batch_stats": variables["batch_stats"]}


@functools.partial(jax.jit, static_argnums=(0, 1))
def _init_depth(da_cfg, size, key):
    from irdepth_jax.models.depth_anything import DepthAnythingV2
    return DepthAnythingV2(da_cfg).init(key, jnp.zeros(size, jnp.float32))["params"]


def init_depth(cfg: Config) -> dict:
    """Depth Anything V2 params: from `cfg.depth.checkpoint` when set (the backbone, plus the
    head when the checkpoint has the same head type), else random (seed cfg.seed + 1)."""
    da_cfg = depth_model_config(cfg)
    params = _init_depth(da_cfg, (1, cfg.depth.input_height, cfg.depth.input_width, 3),
                         init_key(cfg.seed + 1))
    if cfg.depth.checkpoint:
        from irdepth_jax.weights import load_depth_anything
        try:
            loaded_cfg, loaded = load_depth_anything(cfg.depth.checkpoint,
                                                     encoder=cfg.depth.encoder)
        except (OSError, ValueError) as err:
            raise RunError(f"depth.checkpoint {cfg.depth.checkpoint}: {_one_line(err)}") from None
        params = dict(params)
        params["pretrained"] = loaded["pretrained"]
        if loaded_cfg.metric == da_cfg.metric:
            params["depth_head"] = loaded["depth_head"]
    return params


def train_stage1(cfg: Config, source: DataSource, opts: RunOptions) -> dict:
    """Stage I-1 (reconstruction pre-training) then I-2 (soft multi-task) into `opts.workdir`.

    Returns {'unet': final variables, 'steps': {phase: total steps}}.
    """
    from irdepth_jax.evaluate import evaluate_stage1

    s1 = cfg.stage1
    dp = make_parallel(opts, s1.batch_size, s1.accum_steps)
    dp.global_batch_ok(s1.batch_size, s1.accum_steps)
    prepare_workdir(opts.workdir, cfg, opts.resume)
    log = RunLog(opts.workdir)
    try:
        val = source.frames("val", optional=True)
        variables = init_unet(cfg)
        done: dict[str, int] = {}
        for phase_name, epochs, steps in (("stage1_i1", s1.epochs_i1, s1.steps_i1),
                                          ("stage1_i2", s1.epochs_i2, s1.steps_i2)):
            dataset, idx = phase_frames(source, phase_name)
            total = steps_for(epochs, opts.steps if opts.steps is not None else steps, len(idx),
                              s1.batch_size)
            tx, lr_fns = stage1_optimizer(cfg, phase_name, variables["params"])
            state = TrainState.create(variables["params"], variables["batch_stats"], tx,
                                      jax.random.PRNGKey(cfg.seed), lr_fns)
            evaluate = ((lambda st: evaluate_stage1(cfg, _unet_vars(st), *val, dp)["all"])
                        if opts.eval and len(val[1]) else None)
            stream = BatchStream(make_loader(dataset, idx, s1.batch_size, cfg.seed, True, cfg))
            phase = Phase(phase_name, state, (stage1_loss_fn, cfg, phase_name),
                          s1.accum_steps, s1.batch_size, total, stream, evaluate=evaluate,
                          step_offset=sum(done.values()))
            variables = _unet_vars(run_phase(phase, cfg, dp, opts, log))
            done[phase_name] = total
        return {"unet": variables, "steps": done}
    finally:
        log.close()


def _unet_vars(state: TrainState) -> dict:
    return {"params": state.params, "batch_stats": state.batch_stats}


def find_stage1_checkpoint(path: str) -> str:
    """The Stage I-2 (or I-1) checkpoint directory inside a Stage I run dir (or `path` itself)."""
    for candidate in (os.path.join(path, "checkpoints", "stage1_i2"),
                      os.path.join(path, "checkpoints", "stage1_i1"), path):
        if os.path.isdir(candidate) and any(n.isdigit() for n in os.listdir(candidate)):
            return candidate
    raise RunError(f"--stage1-checkpoint {path}: no Stage I checkpoint there (expected a Stage I "
                   "workdir or its checkpoints/stage1_i2 directory)")


def load_stage1(path: str, cfg: Config) -> dict:
    """Stage I variables from a Stage I run (one-line RunError if missing or mismatched)."""
    try:
        unet, _ = restore_model(find_stage1_checkpoint(path), ("stage1_i2", "stage1_i1"),
                                init_unet(cfg))
    except CheckpointError as err:
        raise RunError(str(err)) from None
    return unet


def train_stage2(cfg: Config, source: DataSource, opts: RunOptions) -> dict:
    """Stage II: Depth Anything V2 on the frozen Stage I model's HSV images (or a baseline
    pre-processing, `cfg.stage2.preprocessing`) into `opts.workdir`.

    Returns {'unet': Stage I variables or None, 'depth': final Depth Anything V2 params}.
    """
    from irdepth_jax.evaluate import evaluate_stage2

    s2 = cfg.stage2
    if s2.preprocessing not in PREPROCESSING:
        raise RunError(f"stage2.preprocessing {s2.preprocessing!r}: choose one of {PREPROCESSING}")
    if opts.stage1_checkpoint is None and (s2.preprocessing == "hsv" or s2.sky_loss):
        raise RunError("stage 2 needs --stage1-checkpoint (for the HSV input and the sky mask); "
                       "for a baseline without it use stage2.preprocessing=he "
                       "stage2.sky_loss=false")
    unet = None if opts.stage1_checkpoint is None else load_stage1(opts.stage1_checkpoint, cfg)
    dataset, train_idx = phase_frames(source, "stage2")
    ref_depth = s2.sky_ref_factor * source.max_depth()
    val = source.frames("val", optional=True)
    dp = make_parallel(opts, s2.batch_size)
    dp.global_batch_ok(s2.batch_size)
    prepare_workdir(opts.workdir, cfg, opts.resume)
    log = RunLog(opts.workdir)
    try:
        params = init_depth(cfg)
        total = steps_for(s2.epochs, opts.steps if opts.steps is not None else s2.steps,
                          len(train_idx), s2.batch_size)
        tx, lr_fns = stage2_optimizer(cfg, params, total)
        state = TrainState.create(params, {}, tx, jax.random.PRNGKey(cfg.seed), lr_fns)
        evaluate = ((lambda st: evaluate_stage2(cfg, unet, st.params, *val, dp)["all"])
                    if opts.eval and len(val[1]) else None)
        stream = BatchStream(make_loader(dataset, train_idx, s2.batch_size, cfg.seed, True, cfg))
        frozen = None if unet is None else {"unet": unet}
        phase = Phase("stage2", state, (stage2_loss_fn, cfg, ref_depth), 1, s2.batch_size, total,
                      stream, frozen=frozen, evaluate=evaluate)
        final = run_phase(phase, cfg, dp, opts, log)
        return {"unet": unet, "depth": final.params}
    finally:
        log.close()
