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
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from irdepth_jax.config import IGNORE_LABEL, Config, to_dict
from irdepth_jax.fileio import describe_disk, disk_full, write_bytes
from irdepth_jax.imaging.tonemap import TONEMAPS
from irdepth_jax.models.pipeline import depth_model_config, resolved_raw_bits
from irdepth_jax.models.unet import MTSAUNet
from irdepth_jax.train.checkpoint import CheckpointError, Checkpointer, restore_model
from irdepth_jax.train.parallel import DataParallel
from irdepth_jax.train.state import TrainState, stage1_optimizer, stage2_optimizer
from irdepth_jax.train.steps import make_train_step, stage1_loss_fn, stage2_loss_fn
from irdepth_jax.train.workdir_lock import holds_run, last_checkpoint

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
        keep = [json.dumps(r) + "\n" for r in read_metrics(self.path)
                if not (r.get("stage") == stage and r["step"] > step)]
        write_bytes(self.path, "".join(keep).encode())  # a kill here keeps the old file

    def info(self, stage: str, **fields) -> None:
        """States what a run is built from (weights loaded, labels used, resolved settings):
        printed to stderr as ``irdepth: STAGE: key: value`` lines and logged as one
        ``{"step": 0, "stage", "kind": "info", ...}`` record of metrics.jsonl (once: a resumed
        run that finds the same record does not write it again)."""
        if not self.enabled:
            return
        record = json.loads(json.dumps({"step": 0, "stage": stage, "kind": "info", **fields}))
        for key, value in fields.items():
            print(f"irdepth: {stage}: {key}: {value}", file=sys.stderr, flush=True)
        if os.path.exists(self.path):
            with open(self.path) as f:
                if any(ln.strip() and json.loads(ln) == record for ln in f):
                    return
        with open(self.path, "a") as f:
            f.write(json.dumps(record) + "\n")

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


def read_metrics(path: str) -> list[dict]:
    """The records of a metrics.jsonl, rewriting the file without a torn last line.

    A last line that is not JSON is what a run killed while logging leaves: it is dropped from
    the file, with a note on stderr. A line that is not JSON elsewhere raises RunError naming
    the file and the line.
    """
    with open(path) as f:
        lines = [(n, ln) for n, ln in enumerate(f, 1) if ln.strip()]
    records = []
    for k, (number, line) in enumerate(lines):
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError as err:
            if k < len(lines) - 1:
                raise RunError(f"{path} line {number}: not a JSON record ({err.msg}); repair "
                               "or delete that line") from None
            print(f"irdepth: dropping the torn last line {number} of {path} (left by an "
                  "interrupted run)", file=sys.stderr, flush=True)
            write_bytes(path, "".join(json.dumps(r) + "\n" for r in records).encode())
    return records


def prepare_workdir(workdir: str, cfg: Config, resume: bool) -> None:
    """Creates `workdir` and its config.json; refuses to overwrite a run without `resume`.

    With `resume`, the stored config must equal `cfg` (a changed hyper-parameter would make the
    resumed run a different run), and a torn last line of metrics.jsonl is dropped
    (`read_metrics`).
    """
    path = os.path.join(workdir, "config.json")
    if holds_run(workdir) and not resume:
        raise RunError(f"workdir {workdir} already holds a run; pass --resume to continue it or "
                       "choose another --workdir")
    metrics = os.path.join(workdir, "metrics.jsonl")
    if resume and jax.process_index() == 0 and os.path.exists(metrics):
        read_metrics(metrics)
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
        write_bytes(path, json.dumps(to_dict(cfg), indent=2).encode())


# --------------------------------------------------------------------------- data
class DataSource:
    """Frames of a dataset directory by split: our folder format or MS2.

    Args:
      path: the dataset directory.
      fmt: 'auto' (MS2 when the directory has MS2's sync_data/, else the folder format),
        'folder' or 'ms2'.
      strict: MS2: a sequence of a split list that is not on disk is an error (default: the
        split is read without it, with one `DatasetWarning` per split naming the missing ones).
      raw_bits: bit depth of the raw counts (`DataConfig.raw_bits`: 14, 16 or 'auto'); every
        frame read is checked against it ('auto': up to 16 bits until `use_raw_bits` resolves
        it).
    Raises:
      RunError (one line, naming the directory) when it is not a dataset.
    """

    def __init__(self, path: str, fmt: str = "auto", strict: bool = False,
                 raw_bits: int | str = 14):
        from irdepth_jax.data.folder import DatasetError, FolderDataset
        from irdepth_jax.data.rawio import accepted_bits

        if fmt not in ("auto", "folder", "ms2"):
            raise RunError(f"--format {fmt!r}: choose auto, folder or ms2")
        if not os.path.isdir(path):
            raise RunError(f"--data {path}: no such directory")
        try:
            accepted_bits(raw_bits)
        except ValueError as err:
            raise RunError(str(err)) from None
        self.path, self.strict, self.raw_bits = path, strict, raw_bits
        self.format = fmt if fmt != "auto" else (
            "ms2" if os.path.isdir(os.path.join(path, "sync_data")) else "folder")
        self._error = DatasetError
        self._ms2: dict = {}
        self._folder = None
        if self.format == "folder":
            try:
                self._folder = FolderDataset(path, raw_bits=raw_bits)
            except (DatasetError, ValueError, OSError) as err:
                raise RunError(f"--data {path}: {_one_line(err)}") from None

    def frames(self, split: str, labeled: bool | None = None, optional: bool = False,
               stride: int = 1) -> tuple[Any, np.ndarray]:
        """(dataset, indices) of the frames of `split` (and labelled ones when `labeled`); with
        `stride` N > 1 only `indices[0:-1:N]` of the split's frames, in either format (the
        official MS2 test protocol, N = 10: `data.ms2.subsample`).

        A split the dataset lacks raises RunError, or gives (None, []) when `optional` (but
        a listed MS2 sequence missing under `strict` always raises).
        """
        from irdepth_jax.data.ms2 import MissingSequencesError, MS2Dataset, subsample

        if stride < 1:
            raise RunError(f"stride {stride}: must be >= 1")
        try:
            if self._folder is not None:
                return self._folder, subsample(
                    self._folder.indices(split=split, labeled=labeled), stride)
            if split not in self._ms2:
                self._ms2[split] = MS2Dataset(self.path, split, strict=self.strict,
                                              raw_bits=self.raw_bits)
            ds = self._ms2[split]
            return ds, subsample(ds.indices(labeled=labeled), stride)
        except (self._error, ValueError, OSError) as err:
            if optional and not isinstance(err, MissingSequencesError):
                return None, np.zeros(0, np.int64)
            raise RunError(f"--data {self.path}: {_one_line(err)}") from None

    def seg_frames(self, seg_split: str) -> tuple[Any, np.ndarray]:
        """(dataset, indices) of the labelled frames of segmentation split `seg_split` (train /
        val / test: the paper's 600/100/100 split, independent of the depth split); no frames
        for a dataset without labels (MS2)."""
        if self._folder is None or seg_split not in ("train", "val", "test"):
            return None, np.zeros(0, np.int64)
        return self._folder, self._folder.indices(labeled=True, seg_split=seg_split)

    def all_frames(self) -> tuple[Any, np.ndarray]:
        """(dataset, indices) of every frame of every split (Stage I-1 with i1_frames=all)."""
        if self._folder is not None:
            return self._folder, self._folder.indices()
        from irdepth_jax.data.mixed import ConcatFrames
        parts = [self.frames(split, optional=True) for split in ("train", "val", "test")]
        dataset = ConcatFrames(parts)
        return dataset, np.arange(len(dataset))

    def use_raw_bits(self, raw_bits: int | str) -> int:
        """Checks every frame read from now on against `raw_bits` (14, 16 or 'auto'), 'auto'
        resolved from the training frames (`data.rawio.detect_raw_bits`: 16 when a count exceeds
        14 bits); returns the bit depth, 14 or 16."""
        from irdepth_jax.data.rawio import detect_raw_bits

        self._set_raw_bits(raw_bits)
        if raw_bits == "auto":
            self._set_raw_bits(detect_raw_bits(*self.frames("train")))
        return int(self.raw_bits)

    def _set_raw_bits(self, raw_bits: int | str) -> None:
        from irdepth_jax.data.rawio import accepted_bits

        accepted = accepted_bits(raw_bits)
        self.raw_bits = raw_bits
        for dataset in [self._folder, *self._ms2.values()]:
            if dataset is not None:
                dataset.raw_bits = accepted

    def max_depth(self) -> float:
        """Largest depth of the training frames (metres)."""
        dataset, _ = self.frames("train")
        return float(dataset.max_depth(split="train"))


def _one_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return text[0] if text else type(err).__name__


def resolve_raw_bits(cfg: Config, source: DataSource) -> Config:
    """`cfg` with data.raw_bits as 14 or 16 ('auto' resolved from the training frames by
    `DataSource.use_raw_bits`, which then checks every frame against it), so that config.json
    and the checkpoints store the bit depth the model is trained on and predict reuses it."""
    bits = source.use_raw_bits(cfg.data.raw_bits)
    return dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, raw_bits=bits))


def phase_frames(source: DataSource, phase: str, cfg: Config) -> tuple[Any, np.ndarray]:
    """(dataset, indices) a phase trains on.

    * stage1_i1: the depth train split, or every frame with ``stage1.i1_frames=all``;
    * stage1_i2: the labelled frames of segmentation split train, plus the frames of
      ``stage1.seg_labels`` when it names another source (`stage1_i2_frames`);
    * stage2: the depth train split.
    """
    if phase == "stage1_i2":
        return stage1_i2_frames(source, cfg)[:2]
    if phase == "stage1_i1" and cfg.stage1.i1_frames == "all":
        dataset, idx = source.all_frames()
    elif phase == "stage1_i1" and cfg.stage1.i1_frames != "train":
        raise RunError(f"stage1.i1_frames {cfg.stage1.i1_frames!r}: choose train or all")
    else:
        dataset, idx = source.frames("train")
    if len(idx) == 0:
        raise RunError(f"--data {source.path}: no training frames")
    return dataset, np.asarray(idx)


def stage1_i2_frames(source: DataSource, cfg: Config) -> tuple[Any, np.ndarray, dict]:
    """(dataset, indices, description) of Stage I-2 by `cfg.stage1.seg_labels`.

    'dataset': the frames with seg_split == train. 'synthetic' or a folder dataset's path: those
    frames plus the extra source's labelled frames (rendered at the data's size / resized to it);
    when the dataset itself has no labels, its unlabelled train frames are mixed in, so the
    reconstruction and gradient branches keep seeing the real data. 'none': the depth train
    frames, labels ignored. Without any label (and seg_labels != 'none') a RunError says what to
    pass. The description (logged, and stored in the I-2 checkpoints) says where the labels came
    from and how many labelled frames there are (0: the segmentation branch stays untrained).
    """
    from irdepth_jax.data.mixed import ConcatFrames, SyntheticLabeled

    choice = cfg.stage1.seg_labels
    if choice == "none":
        dataset, idx = source.frames("train")
        return dataset, np.asarray(idx), {"seg_labels": "none", "labeled_frames": 0,
                                          "why": "trained with stage1.seg_labels=none"}
    own_ds, own_idx = source.seg_frames("train")
    parts, described = [(own_ds, own_idx)], {"dataset": int(len(own_idx))}
    train_ds, train_idx = source.frames("train")
    size = tuple(np.shape(train_ds[int(train_idx[0])]["raw14"]))  # extra frames get this size
    if choice == "synthetic":
        extra = SyntheticLabeled(cfg.stage1.synthetic_labeled, *size, cfg.seed,
                                 cfg.data.raw_bits)
        parts.append((extra, np.arange(len(extra))))
        described["synthetic"] = len(extra)
    elif choice != "dataset":
        if not os.path.isdir(choice):
            raise RunError(f"stage1.seg_labels {choice!r}: choose dataset, synthetic, none or "
                           "the path of a labelled folder-format dataset")
        extra_ds, extra_idx = DataSource(choice, "folder",
                                         raw_bits=cfg.data.raw_bits).seg_frames("train")
        if len(extra_idx) == 0:
            raise RunError(f"stage1.seg_labels {choice}: no labelled frames with seg_split "
                           "train there")
        parts.append((extra_ds, extra_idx))
        described[choice] = int(len(extra_idx))
    labeled = sum(described.values())
    if labeled == 0:
        raise RunError(
            f"--data {source.path}: no segmentation labels (no labelled frame with seg_split "
            "train), so Stage I-2 would leave the segmentation branch untrained while Stage II "
            "takes its Hue channel and sky mask from it. Pass stage1.seg_labels=synthetic "
            "(rendered labelled scenes), stage1.seg_labels=PATH (a labelled folder dataset), "
            "or stage1.seg_labels=none (then Stage II needs stage2.hue_mode=constant "
            "stage2.sky_loss=false)")
    if len(parts) > 1 and len(own_idx) == 0:
        parts[0] = (train_ds, train_idx)
    if len(parts) == 1:
        return own_ds, np.asarray(own_idx), {"seg_labels": choice, "labeled_frames": labeled}
    mixed = ConcatFrames(parts, size=size)
    return mixed, np.arange(len(mixed)), {"seg_labels": choice, "labeled_frames": labeled,
                                          "labeled_by_source": described,
                                          "frames": len(mixed)}


def host_image(batch: dict, preprocessing: str, bits: int = 14) -> np.ndarray | None:
    """The Stage II input image (B, H, W, 3) uint8 made on the host, or None for 'hsv'.

    'rgb': the aligned visible image; a tonemap name ('he', 'clahe', 'camera', ...): the
    tone-mapped raw frame (B, H, W) of `bits`-bit counts replicated to three channels.
    """
    if preprocessing == "hsv":
        return None
    if preprocessing == "rgb":
        return np.asarray(batch["rgb"], np.uint8)
    fn = TONEMAPS[preprocessing]
    grey = np.stack([fn(np.asarray(raw), bits=bits) for raw in batch["raw14"]])
    if "brightness" in batch:  # the augmentation's factor, as ir8 / rgb got it
        factor = np.asarray(batch["brightness"], np.float32).reshape(-1, 1, 1)
        grey = np.clip(np.rint(grey * factor), 0, 255).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=-1)


STAGE_KEYS = {
    "stage1_i1": ("raw14", "ir8"),
    "stage1_i2": ("raw14", "ir8", "seg"),
    "stage2": ("raw14", "depth", "valid"),
}


def device_batch(batch: dict, phase: str, cfg: Config) -> dict:
    """The arrays a phase's step needs from a loader batch (numpy, host side)."""
    out = {k: np.asarray(batch[k]) for k in STAGE_KEYS[phase] + ("brightness",) if k in batch}
    if phase == "stage1_i2" and cfg.stage1.seg_labels == "none":
        out["seg"] = np.full_like(out["seg"], IGNORE_LABEL)
    if phase == "stage2":
        image = host_image(batch, cfg.stage2.preprocessing, resolved_raw_bits(cfg))
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
      meta: extra JSON fields stored in every checkpoint of the phase (e.g. where its labels
        came from, and ``started_from``: the step of the phase it continues).
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


def writing_checkpoint(frame) -> bool:
    """Whether the main thread, where a signal found it at `frame`, is in checkpoint code (ours
    or orbax's): a KeyboardInterrupt there would abandon a save half-way (and orbax logs it with
    a traceback)."""
    while frame is not None:
        module = frame.f_globals.get("__name__", "")
        if module == "irdepth_jax.train.checkpoint" or module.startswith("orbax."):
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
    start = 0
    if ckpt.latest_step() is not None:
        if not opts.resume:
            raise RunError(f"{ckpt.directory} already holds checkpoints; pass --resume")
        state, meta = ckpt.restore(state)
        start = int(meta["step"])
        if start > phase.total_steps:
            raise RunError(f"{ckpt.directory} holds step {start}, beyond the {phase.total_steps} "
                           f"steps {phase.name} now has (its --steps or epochs changed); "
                           "resume with the earlier length or use a new --workdir")
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
        meta = {**phase.meta, "config": to_dict(cfg), "data_state": phase.stream.get_state(),
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
                 + [f"--devices {k}" for k in range(n - 1, 0, -1)
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
                   + " and --devices 1" * (unit > accum_steps))
            raise RunError(f"{section}.batch_size={batch_size} is larger than the {count} "
                           f"training frames of {phase} (an epoch drops its incomplete last "
                           f"batch, so it would have no step): set {fix}")
    return dp


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


def random_depth(cfg: Config) -> dict:
    """Random Depth Anything V2 params of `cfg.depth` (seed cfg.seed + 1): Stage II's start
    without a checkpoint, and the template a Stage II checkpoint is restored into."""
    return _init_depth(depth_model_config(cfg),
                       (1, cfg.depth.input_height, cfg.depth.input_width, 3),
                       init_key(cfg.seed + 1))


def init_depth(cfg: Config) -> tuple[dict, dict[str, str]]:
    """Stage II's starting Depth Anything V2 params and a description of where they came from.

    Without `depth.checkpoint`: `random_depth`. With it: the backbone from the file, and its
    head by `depth.load_head`: 'auto' when the file's head kind (`depth.checkpoint_kind`, see
    `weights.load_depth_anything`) is the one `depth.metric` trains, else a random head (how the
    official metric fine-tuning starts from a relative checkpoint); 'true' the file's head,
    refused when the kinds differ; 'false' a random head.

    Returns (params, {'backbone': str, 'head': str}, plus 'max_depth': str when a loaded metric
    head was trained for another range than `depth.max_depth`), for `RunLog.info`. Raises
    RunError (one line naming the key or the file) for a bad setting, a missing, unreadable or
    ambiguous file, or load_head=true with the other head kind.
    """
    d = cfg.depth
    params = random_depth(cfg)
    if not d.checkpoint:
        return params, {"backbone": "random init (no depth.checkpoint)",
                        "head": "random init (no depth.checkpoint)"}
    load_head = str(d.load_head).lower()
    if load_head not in ("auto", "true", "false"):
        raise RunError(f"depth.load_head {d.load_head!r}: choose auto, true or false")
    from irdepth_jax.weights import load_depth_anything
    try:
        file_cfg, loaded = load_depth_anything(d.checkpoint, encoder=d.encoder,
                                               kind=d.checkpoint_kind, max_depth=d.max_depth)
    except (OSError, ValueError) as err:
        raise RunError(f"depth.checkpoint: {_one_line(err)}") from None
    file_kind, kind = ("metric" if m else "relative" for m in (file_cfg.metric, d.metric))
    params = {**params, "pretrained": loaded["pretrained"]}
    described = {"backbone": f"loaded from {d.checkpoint} (encoder {d.encoder})"}
    if load_head == "false":
        described["head"] = "random init: depth.load_head=false"
    elif file_kind != kind and load_head == "true":
        raise RunError(f"depth.load_head=true: {d.checkpoint} holds a {file_kind} head, "
                       f"depth.metric={str(d.metric).lower()} trains a {kind} one: set "
                       "depth.load_head=auto (backbone only), the other depth.metric, or "
                       "depth.checkpoint_kind if the file's kind is misread")
    elif file_kind != kind:
        described["head"] = (f"random init: {d.checkpoint} holds a {file_kind} head, "
                             f"depth.metric={str(d.metric).lower()} trains a {kind} one "
                             "(backbone only, as the official metric fine-tuning starts)")
    else:
        params["depth_head"] = loaded["depth_head"]
        depth_range = f", max_depth {file_cfg.max_depth:g} m" if file_cfg.metric else ""
        described["head"] = f"loaded from {d.checkpoint} ({file_kind}{depth_range})"
        if file_cfg.metric and file_cfg.max_depth != d.max_depth:
            described["max_depth"] = (
                f"warning: the head was trained for max_depth {file_cfg.max_depth:g} m; "
                f"depth.max_depth={d.max_depth:g} scales its output by "
                f"{d.max_depth / file_cfg.max_depth:.3g}")
    return params, described


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
                    "continue with --resume" if last else
                    "no checkpoint was finished; free space, then run again with "
                    "--resume-or-start")
            raise RunError(f"no space left on {describe_disk(opts.workdir)}, which holds "
                           f"--workdir {opts.workdir}: {then}") from err
    return run


@_full_disk_in_one_line
def train_stage1(cfg: Config, source: DataSource, opts: RunOptions) -> dict:
    """Stage I-1 (reconstruction pre-training) then I-2 (soft multi-task) into `opts.workdir`.

    Returns {'unet': final variables, 'steps': {phase: total steps}}.
    """
    from irdepth_jax.evaluate import evaluate_stage1
    from irdepth_jax.train.validate import check_run

    cfg = resolve_raw_bits(cfg, source)
    check_run(cfg, source, opts, "stage1")
    s1 = cfg.stage1
    i2_dataset, i2_idx, seg_info = stage1_i2_frames(source, cfg)  # refuses before any write
    frames = {"stage1_i1": phase_frames(source, "stage1_i1", cfg),
              "stage1_i2": (i2_dataset, i2_idx)}
    dp = make_parallel(opts, s1.batch_size, s1.accum_steps, "stage1",
                       {phase: len(idx) for phase, (_, idx) in frames.items()})
    totals = {phase: steps_for(epochs, opts.steps if opts.steps is not None else steps,
                               len(frames[phase][1]), s1.batch_size)
              for phase, epochs, steps in (("stage1_i1", s1.epochs_i1, s1.steps_i1),
                                           ("stage1_i2", s1.epochs_i2, s1.steps_i2))}
    if opts.resume:
        _check_i2_continues_i1(opts.workdir, totals["stage1_i1"])
    prepare_workdir(opts.workdir, cfg, opts.resume)
    log = RunLog(opts.workdir)
    try:
        log.info("stage1", raw_bits=cfg.data.raw_bits,
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
            tx, lr_fns = stage1_optimizer(cfg, phase_name, variables["params"])
            state = TrainState.create(variables["params"], variables["batch_stats"], tx,
                                      jax.random.PRNGKey(cfg.seed), lr_fns)
            evaluate = ((lambda st: evaluate_stage1(cfg, _unet_vars(st), *val, dp,
                                                    seg_frames=val_seg)["all"])
                        if opts.eval and len(val[1]) else None)
            stream = BatchStream(make_loader(dataset, idx, s1.batch_size, cfg.seed, True, cfg))
            meta = ({"segmentation": seg_info, "started_from": {"stage1_i1": i1_step}}
                    if phase_name == "stage1_i2" else {})
            phase = Phase(phase_name, state, (stage1_loss_fn, cfg, phase_name),
                          s1.accum_steps, s1.batch_size, total, stream, evaluate=evaluate,
                          step_offset=sum(done.values()), meta=meta)
            final = run_phase(phase, cfg, dp, opts, log)
            variables = _unet_vars(final)
            if phase_name == "stage1_i1":  # the step I-2 starts from
                i1_step = int(np.asarray(final.step).reshape(-1)[0])
            done[phase_name] = total
        return {"unet": variables, "steps": done}
    finally:
        log.close()


def _check_i2_continues_i1(workdir: str, i1_total: int) -> None:
    """RunError (before anything is trained) when the run's I-2 checkpoints started from I-1 at
    another step than the I-1 length asked for now: after `--steps 4` then `--resume --steps 8`,
    I-1 would be extended to 8 while I-2 went on from its start at I-1 step 4, giving neither
    run. Checkpoints written before ``started_from`` was recorded are not checked."""
    from irdepth_jax.train.checkpoint import Checkpointer

    directory = os.path.join(workdir, "checkpoints", "stage1_i2")
    if not os.path.isdir(directory) or not any(n.isdigit() for n in os.listdir(directory)):
        return
    reader = Checkpointer(directory, "stage1_i2", max_to_keep=None, read_only=True)
    try:
        started = reader.read_meta().get("started_from", {}).get("stage1_i1")
    except CheckpointError as err:
        raise RunError(str(err)) from None
    finally:
        reader.close()
    if started is not None and started != i1_total:
        raise RunError(
            f"{directory}: Stage I-2 started from stage1_i1 at step {started}, but stage1_i1 "
            f"would now run to step {i1_total} (--steps or epochs changed): the result would be "
            f"neither run. Delete {directory} to run I-2 again from the new I-1, or resume "
            f"with the earlier length")


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


def load_stage1(path: str, cfg: Config) -> tuple[dict, dict]:
    """Stage I variables from a Stage I run and what its segmentation branch was trained on:
    ``{'labeled_frames': N, ...}`` (0 after I-1 only or I-2 without labels; None for an I-2
    checkpoint written before this was recorded). One-line RunError if missing or mismatched,
    or trained on raw counts of another bit depth than `cfg.data.raw_bits`."""
    try:
        unet, meta = restore_model(find_stage1_checkpoint(path), ("stage1_i2", "stage1_i1"),
                                   init_unet(cfg))
    except CheckpointError as err:
        raise RunError(str(err)) from None
    # checkpoints written before data.raw_bits existed were trained on 14-bit counts
    trained_bits = meta.get("config", {}).get("data", {}).get("raw_bits", 14)
    if trained_bits != cfg.data.raw_bits:
        raise RunError(f"--stage1-checkpoint {path}: Stage I was trained on {trained_bits}-bit "
                       f"raw counts, this run has data.raw_bits={cfg.data.raw_bits}; use "
                       f"data.raw_bits={trained_bits} (the same data) or retrain Stage I")
    if meta.get("stage") == "stage1_i1":
        return unet, {"labeled_frames": 0, "why": "Stage I-1 only (no I-2 checkpoint)"}
    return unet, meta.get("segmentation") or {"labeled_frames": None,
                                              "why": "not recorded (older checkpoint)"}


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
        raise RunError(f"--stage1-checkpoint {where}: the segmentation branch was never trained "
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

    Returns {'unet': Stage I variables or None, 'depth': final Depth Anything V2 params}.
    """
    from irdepth_jax.evaluate import evaluate_stage2
    from irdepth_jax.train.validate import check_run

    cfg = resolve_raw_bits(cfg, source)
    check_run(cfg, source, opts, "stage2")
    s2 = cfg.stage2
    if s2.preprocessing not in PREPROCESSING:
        raise RunError(f"stage2.preprocessing {s2.preprocessing!r}: choose one of {PREPROCESSING}")
    if opts.stage1_checkpoint is None and (s2.preprocessing == "hsv" or s2.sky_loss):
        raise RunError("stage 2 needs --stage1-checkpoint (for the HSV input and the sky mask); "
                       "for a baseline without it use stage2.preprocessing=he "
                       "stage2.sky_loss=false")
    unet, segmentation = None, {"labeled_frames": None, "why": "no Stage I model"}
    if opts.stage1_checkpoint is not None:
        unet, segmentation = load_stage1(opts.stage1_checkpoint, cfg)
        check_segmentation_use(cfg, segmentation, opts.stage1_checkpoint)
    dataset, train_idx = phase_frames(source, "stage2", cfg)
    ref_depth = sky_reference_depth(cfg, source.max_depth())
    val = source.frames("val", optional=True)
    dp = make_parallel(opts, s2.batch_size, frames={"stage2": len(train_idx)})
    params, depth_init = init_depth(cfg)  # a bad depth.checkpoint is refused before any write
    prepare_workdir(opts.workdir, cfg, opts.resume)
    log = RunLog(opts.workdir)
    try:
        log.info("stage2", raw_bits=cfg.data.raw_bits)
        log.info("stage2", stage1=opts.stage1_checkpoint, segmentation_branch=segmentation,
                 hue_mode=s2.hue_mode, sky_loss=(f"on, reference depth {ref_depth:.2f} m"
                                                 if s2.sky_loss else "off"))
        log.info("stage2", **depth_init)
        total = steps_for(s2.epochs, opts.steps if opts.steps is not None else s2.steps,
                          len(train_idx), s2.batch_size)
        tx, lr_fns = stage2_optimizer(cfg, params, total)
        state = TrainState.create(params, {}, tx, jax.random.PRNGKey(cfg.seed), lr_fns)
        evaluate = ((lambda st: evaluate_stage2(cfg, unet, st.params, *val, dp)["all"])
                    if opts.eval and len(val[1]) else None)
        stream = BatchStream(make_loader(dataset, train_idx, s2.batch_size, cfg.seed, True, cfg))
        frozen = None if unet is None else {"unet": unet}
        phase = Phase("stage2", state, (stage2_loss_fn, cfg, ref_depth), 1, s2.batch_size, total,
                      stream, frozen=frozen, evaluate=evaluate,
                      meta={"segmentation": segmentation})
        final = run_phase(phase, cfg, dp, opts, log)
        return {"unet": unet, "depth": final.params}
    finally:
        log.close()
