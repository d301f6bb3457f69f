"""The datasets and the cached training runs behind the tables.

Layout of a cache directory (``--cache``, default ``workdir/experiments``):

* ``data/synthetic-...``: the synthetic benchmark's training data (the preset's frame count and
  size, dataset seed `DATA_SEED`) and, apart from it, its evaluation set ``data/eval-...``
  (`--eval-frames` test frames, all labelled, dataset seed `EVAL_SEED`: evaluation is cheap, so
  the test set is large and the metrics' frame noise small); each is rendered into a temporary
  folder beside it and renamed into place whole, so runners sharing a cache never read a
  half-written dataset;
* ``runs/<kind>-<hash>/``: one training run per (kind, full config, training data); the hash
  covers every config field, so a run is reused by every table that needs it (the Stage I model
  of a seed is shared by tables 1-7) and an interrupted run resumes from its last checkpoint;
* ``runs/.../eval-<hash>.json`` + ``.npz``: the run's metrics on one evaluation set under one
  protocol (aggregated, and per frame for `irdepth_experiments.claims`);
* ``xla/``: JAX's persistent compilation cache.

Runs committed with the repository (`COMMITTED_RUNS`) are copied into a cache that lacks them
instead of being trained (unless ``--no-committed-runs``).

Run kinds: ``stage1_i1`` (Stage I-1 only: the single-task model of table 2), ``stage1`` (I-1
then I-2; its I-1 phase is copied from the matching ``stage1_i1`` run, so the multi-task and
single-task models of a seed start from the same I-1 weights), ``stage2`` (Depth Anything V2
on the frozen Stage I model of the same seed: every Stage II row of a table starts from the same
Stage I checkpoint and the same Depth Anything initialisation, a paired design) and ``depth``
(`irdepth train depth`: Depth Anything V2 pretrained on the visible images of a separate
rendered set, ``data/pretrain-...``; with ``--depth-init pretrained`` every Stage II run starts
from it, as the paper's from the released weights: `irdepth_experiments.depth_network`).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import glob
import hashlib
import json
import os
import shutil
import subprocess
import tempfile
import time
from collections.abc import Callable

import numpy as np

from irdepth_experiments import run_metrics
from irdepth_jax.compile_cache import enable_compilation_cache

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DEFAULT_CACHE = os.path.join(REPO, "workdir", "experiments")
EVAL_SPLIT = "test"
DATA_SEED = 0  # the synthetic benchmark is one fixed dataset; --seeds vary the training only
EVAL_SEED = 1  # its evaluation set: other scenes of the same distribution
PRETRAIN_SEED = 2  # the depth pretraining set (visible images + depth): other scenes again
MS2_STRIDE = 10  # the MS2 protocol evaluates every 10th test frame
COMMITTED_RUNS = os.path.join(REPO, "experiments", "pretrained")
"""Runs committed with the repository (`commit_run`), each under its cache name
(``<kind>-<hash>``): the pretrained depth network of `irdepth_experiments.depth_network` (its
weights, without the optimizer state) and the evaluations of it and of its blank control; the
protocol's Stage I models (``runner --commit-stage1``: weights and evaluations) and the long
Stage I runs of tables 2, 3, 5 and 6's own rows (records and evaluations only: no Stage II starts
from them), with the commands that made them. Each took from 40 minutes (a Stage I model) to hours (the depth
network) on a 2-core machine; a cache that lacks one of these runs starts from the committed
copy (same config, same rendered data, same key) instead of training it."""
CODE_FILE = "code.json"
"""A run's record of the package code that trained it: [{'git', 'digest'}], one entry per
version, in order (more than one: the run was resumed after the package changed)."""
COMMITTED_FILES = ("config.json", "trained.json", "data_fingerprint.json", "metrics.jsonl", CODE_FILE,
                   "eval-*.json", "eval-*.npz")
"""What `commit_run` copies of a run's records (paths inside the cache made relative to it)."""


def git_commit() -> str:
    """HEAD commit of the repository (+ '-dirty' with uncommitted changes to the code: the
    package, the experiment scripts and pyproject.toml; not the results and committed runs they
    write), or 'unknown'."""
    code = ["irdepth_jax", "experiments", ":!experiments/results", ":!experiments/pretrained",
            "pyproject.toml"]
    try:
        head = subprocess.run(["git", "-C", REPO, "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", REPO, "status", "--porcelain", "--untracked-files=no",
                                "--", *code], capture_output=True, text=True,
                               check=True).stdout.strip()
        return head + ("-dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


@functools.lru_cache(maxsize=1)
def code_digest() -> str:
    """sha1 (12 hex digits) of the package's sources (`irdepth_jax/**/*.py` and the native CPU
    kernel's `*.cc`, paths and contents): the code that renders, trains and evaluates a run,
    whether committed or not."""
    digest = hashlib.sha1()
    package = os.path.join(REPO, "irdepth_jax")
    sources = [path for pattern in ("*.py", "*.cc")
               for path in glob.glob(os.path.join(package, "**", pattern), recursive=True)]
    for path in sorted(sources):
        digest.update(os.path.relpath(path, package).encode() + b"\0")
        with open(path, "rb") as f:
            digest.update(f.read() + b"\0")
    return digest.hexdigest()[:12]


def code_versions(workdir: str) -> list[dict] | None:
    """The run's `CODE_FILE` record, or None for a run trained before it was kept."""
    path = os.path.join(workdir, CODE_FILE)
    if not os.path.exists(path):
        return None
    with open(path) as f:
        return json.load(f)


def cache_relative(text: str, cache: str) -> str:
    """`text` with the paths inside the experiment cache `cache` made relative to it and the
    cache itself named `<cache>` (a committed record names no machine's folders)."""
    cache = cache.rstrip(os.sep)
    return text.replace(cache + os.sep, "").replace(cache, "<cache>")


def commit_run(cache: str, run: str, into: str, made_by: str, weights: str | None = None) -> str:
    """Copies the run ``CACHE/runs/<run>`` into ``<into>/<run>`` (replacing it): its records
    (`COMMITTED_FILES`, text through `cache_relative`), a MADE_BY.md of `made_by`, and with
    `weights` (a checkpoint folder: 'stage1_i2', 'stage2') that folder's last checkpoint without
    its optimizer state (the `train` item, twice the weights' size); returns the directory."""
    source, target = os.path.join(cache, "runs", run), os.path.join(into, run)
    shutil.rmtree(target, ignore_errors=True)
    os.makedirs(target)
    for pattern in COMMITTED_FILES:
        for path in glob.glob(os.path.join(source, pattern)):
            if path.endswith((".json", ".jsonl")):
                with open(path) as f:
                    text = cache_relative(f.read(), cache)
                with open(os.path.join(target, os.path.basename(path)), "w") as f:
                    f.write(text)
            else:
                shutil.copy2(path, target)
    if weights is not None:
        checkpoints = os.path.join(source, "checkpoints", weights)
        last = max((d for d in os.listdir(checkpoints) if d.isdigit()), key=int)
        copied = os.path.join(target, "checkpoints", weights, last)
        shutil.copytree(os.path.join(checkpoints, last), copied,
                        ignore=lambda directory, names: ["train"] if directory.endswith(last) else [])
        meta = os.path.join(copied, "meta", "metadata")  # the run's config and provenance
        if os.path.exists(meta):
            with open(meta) as f:
                text = cache_relative(f.read(), cache)
            with open(meta, "w") as f:
                f.write(text)
    with open(os.path.join(target, "MADE_BY.md"), "w") as f:
        f.write(cache_relative(made_by, cache))
    return target


@dataclasses.dataclass(frozen=True)
class Protocol:
    """How a run is evaluated: which frames, and the per-image alignment of the depth metrics.

    Attributes:
      name: 'synthetic' (our evaluation set, metric depth, no alignment), 'folder' (a user's
        folder dataset's test split, no alignment) or 'ms2' (the MS2 literature protocol: every
        10th frame of the test lists, day / night / rainy, predictions median-scaled per image,
        valid 1e-3 < gt < 80 m, clamped).
      stride: every `stride`-th frame of the split.
      align: the alignment of the reported depth metrics (None or 'median'); the
        median-scaled metrics are always stored too (`stage2_median`), as a diagnostic of scale.
    """

    name: str
    stride: int = 1
    align: str | None = None


class Context:
    """The config, data and cache of one invocation, and the cached runs (see module doc).

    Args:
      args: the parsed command line of `irdepth_experiments.runner.parse_args`.
      log: where progress lines go.
    """

    def __init__(self, args: argparse.Namespace, log: Callable[[str], None] = print):
        import jax

        from irdepth_jax.config import apply_overrides, get_config
        from irdepth_jax.data.source import DataSource, resolve_raw_bits
        from irdepth_jax.errors import RunError

        self.args, self.log = args, log
        try:
            self.base = apply_overrides(get_config(args.preset), args.overrides)
        except ValueError as err:
            raise SystemExit(f"--set: {err}") from None
        self.cache = os.path.abspath(args.cache)
        os.makedirs(self.cache, exist_ok=True)
        if not jax.config.jax_compilation_cache_dir:
            enable_compilation_cache(os.path.join(self.cache, "xla"))
        self.data_path, self.data_info = self._dataset()
        try:
            self.source = DataSource(self.data_path, args.format, raw_bits=self.base.data.raw_bits)
            # every run (and its cache key) gets the resolved bit depth, 'auto' included
            self.base = resolve_raw_bits(self.base, self.source)
            self.data_info["format"] = self.source.format
            self.eval_source, self.eval_info = self._eval_set()
        except RunError as err:
            raise SystemExit(str(err)) from None
        self.protocol = (Protocol("ms2", MS2_STRIDE, "median") if self.source.format == "ms2"
                         else Protocol("synthetic" if args.data is None else "folder"))
        self.data_fingerprint = _fingerprint(self.data_path)
        self.pretraining_data, self.pretraining_frames = None, 0
        self.stage2_depth_checkpoint: str | None = None  # `irdepth_experiments.depth_network`
        self.eval_key = hashlib.sha1(json.dumps(
            {"data": _fingerprint(self.eval_info["path"]), "split": EVAL_SPLIT,
             "protocol": dataclasses.asdict(self.protocol), "metrics": EVAL_METRICS_VERSION},
            sort_keys=True).encode()).hexdigest()[:12]
        self.stage1_eval_key = hashlib.sha1(
            f"{self.eval_key} {STAGE1_MODEL_VERSION}".encode()).hexdigest()[:12]

    def eval_file(self, run: str, suffix: str = ".json") -> str:
        """The name of run `run`'s evaluation file on this evaluation set (`suffix` '.json': the
        record, '.npz': its per-frame metrics); a Stage I run's is keyed by
        `STAGE1_MODEL_VERSION` too."""
        key = self.stage1_eval_key if run.startswith("stage1") else self.eval_key
        return f"eval-{key}{suffix}"

    def eval_path(self, run: str, suffix: str = ".json") -> str:
        """Where `eval_file` of run `run` is in this cache."""
        return os.path.join(self.cache, "runs", run, self.eval_file(run, suffix))

    # ---------------------------------------------------------------- data
    def _dataset(self) -> tuple[str, dict]:
        if self.args.data is not None:
            path = os.path.abspath(self.args.data)
            return path, {"source": "user", "path": path}
        d = self.base.data
        return self._render(f"synthetic-n{d.num_frames}-l{d.num_labeled}", d.num_frames,
                            d.num_labeled, DATA_SEED, split=None)

    def _eval_set(self):
        """(DataSource, info) of the evaluation frames: the synthetic benchmark's own test set,
        or the user's dataset (its test split)."""
        from irdepth_jax.data.source import DataSource

        if self.args.data is not None:
            return self.source, dict(self.data_info)
        n = self.args.eval_frames
        path, info = self._render(f"eval-n{n}", n, n, EVAL_SEED, split=EVAL_SPLIT)
        source = DataSource(path, "folder", raw_bits=self.base.data.raw_bits)
        return source, {**info, "format": source.format}

    def pretraining_source(self, frames: int):
        """(DataSource, info) of the depth pretraining set: `frames` rendered frames (visible
        image + depth, all in the train split) of scenes apart from the training and evaluation
        sets (dataset seed `PRETRAIN_SEED`), at the base config's size and scene distribution."""
        from irdepth_jax.data.source import DataSource

        path, info = self._render(f"pretrain-n{frames}", frames, 0, PRETRAIN_SEED, split="train")
        return DataSource(path, "folder", raw_bits=self.base.data.raw_bits), info

    def _render(self, name: str, n: int, labeled: int, seed: int, split: str | None):
        from irdepth_jax.data.synthetic_dataset import write_synthetic_dataset

        d = self.base.data
        scenes = "" if d.scenes == "street" else f"-{d.scenes}"  # the 'street' caches keep their names
        path = os.path.join(self.cache, "data", f"{name}-{d.height}x{d.width}-seed{seed}{scenes}")
        info = {"source": "synthetic", "path": path, "num_frames": n, "num_labeled": labeled,
                "height": d.height, "width": d.width, "seed": seed, "split": split, "scenes": d.scenes,
                "made_by": f"write_synthetic_dataset(path, {n}, {labeled}, {d.height}, {d.width}, "
                           f"seed={seed}, split={split!r}, scenes={d.scenes!r})"}
        if os.path.exists(os.path.join(path, "manifest.json")):
            return path, info
        if os.path.exists(path):
            raise SystemExit(f"{path}: an incomplete dataset (no manifest.json: a render "
                             "interrupted by an older version); delete it and re-run")
        # rendered beside its place and renamed into it, whole: runners on one --cache that
        # render it at once never see (or rewrite) a half-written dataset; the first rename wins
        self.log(f"rendering {n} synthetic frames ({d.height}x{d.width}) into {path}")
        os.makedirs(os.path.dirname(path), exist_ok=True)
        rendering = tempfile.mkdtemp(prefix=f"{os.path.basename(path)}.rendering-",
                                     dir=os.path.dirname(path))
        try:
            write_synthetic_dataset(rendering, n, labeled, d.height, d.width, seed=seed,
                                    progress=not self.args.no_progress, split=split,
                                    scenes=d.scenes)
            with contextlib.suppress(OSError):  # another runner's rename came first
                os.rename(rendering, path)
        finally:
            shutil.rmtree(rendering, ignore_errors=True)
        if not os.path.exists(os.path.join(path, "manifest.json")):
            raise SystemExit(f"{path}: could not move the rendered dataset into place")
        return path, info

    # ---------------------------------------------------------------- configs
    def config(self, kind: str, overrides: tuple[str, ...], seed: int):
        """The run config of a row (`kind`, its `overrides`) for `seed` (Stage I runs normalise
        the Stage II / depth sections to the base config's, so every table shares them; depth
        pretraining runs the UNet / Stage I sections to the preset's, so the tables' Stage I
        settings share one pretrained network)."""
        from irdepth_jax.config import apply_overrides, get_config

        try:
            cfg = apply_overrides(dataclasses.replace(self.base, seed=seed), list(overrides))
        except ValueError as err:
            raise SystemExit(f"{' '.join(overrides)}: {err}") from None
        if kind in ("stage1", "stage1_i1"):
            cfg = self.stage1_config(cfg)
        if kind == "stage1_i1":
            cfg = i1_config(cfg, self.base)
        if kind == "depth":  # trains no UNet: one pretrained network whatever the Stage I settings
            preset = get_config(self.args.preset)
            cfg = dataclasses.replace(cfg, unet=preset.unet, stage1=preset.stage1)
        if kind == "stage2" and self.stage2_depth_checkpoint is not None:
            cfg = dataclasses.replace(cfg, depth=dataclasses.replace(
                cfg.depth, checkpoint=self.stage2_depth_checkpoint))
        return cfg

    def stage1_config(self, cfg):
        """`cfg` with the base config's Stage II / depth sections: the key of the Stage I run
        that Stage II runs of any Stage II / depth setting share."""
        return dataclasses.replace(cfg, stage2=self.base.stage2, depth=self.base.depth)

    def stage1_steps(self, overrides: tuple[str, ...], seed: int) -> int:
        """Optimizer steps of the Stage I run (I-1 + I-2) of a row's `overrides` for `seed`, as
        `irdepth_jax.train.stages.train_stage1` counts them on the benchmark's training data."""
        from irdepth_jax.data.source import phase_frames, stage1_i2_frames
        from irdepth_jax.train.stages import stage1_totals

        cfg = self.config("stage1", overrides, seed)
        frames = {"stage1_i1": len(phase_frames(self.source, "stage1_i1", cfg)[1]),
                  "stage1_i2": len(stage1_i2_frames(self.source, cfg)[1])}
        return sum(stage1_totals(cfg, frames).values())

    def run_dir(self, kind: str, cfg, data: str | None = None) -> str:
        """The cache directory of the run of `kind` with config `cfg`, trained on the benchmark's
        training data (or the dataset at `data`)."""
        from irdepth_jax.config import to_dict

        config = to_dict(cfg)
        checkpoint = config["depth"]["checkpoint"]
        if checkpoint and os.path.isabs(checkpoint) and checkpoint.startswith(self.cache + os.sep):
            config["depth"]["checkpoint"] = os.path.relpath(checkpoint, self.cache)  # movable cache
        fingerprint = self.data_fingerprint if data is None else _fingerprint(data)
        key = {"kind": kind, "config": config, "data": fingerprint}
        if kind == "stage2":  # trained on a Stage I model's images and sky mask
            key["stage1_model"] = STAGE1_MODEL_VERSION
        blob = json.dumps(key, sort_keys=True)
        return os.path.join(self.cache, "runs", f"{kind}-{hashlib.sha1(blob.encode()).hexdigest()[:12]}")

    # ---------------------------------------------------------------- runs
    def result(self, kind: str, overrides: tuple[str, ...], seed: int) -> dict:
        """The evaluation record of a row's run for `seed` (trained and evaluated if not
        cached): {'stage1' | 'stage2' | 'stage2_median': {group: metrics}, 'protocol',
        'train_wall_s', 'eval_wall_s', 'run'}."""
        cfg = self.config(kind, overrides, seed)
        workdir = self.run_dir(kind, cfg, self.pretraining_data if kind == "depth" else None)
        self._adopt_committed(workdir)
        path = self.eval_path(os.path.basename(workdir))
        if os.path.exists(path):
            return self.evaluation(os.path.basename(workdir))
        train = {"stage1_i1": self._stage1_i1, "stage1": self._stage1, "stage2": self._stage2,
                 "depth": self._depth}
        if kind not in train:
            raise ValueError(f"unknown run kind {kind!r}")
        train_wall_s = train[kind](cfg)
        self.log(f"[{kind} seed {seed}] evaluating on {self.eval_info['path']} "
                 f"({self.protocol.name} protocol)")
        started = time.time()
        dataset, indices = self._eval_frames()
        if kind.startswith("stage1"):
            metrics, frames = run_metrics.stage1_metrics(cfg, workdir, dataset, indices,
                                                         self.eval_source.seg_frames(EVAL_SPLIT))
        else:
            metrics, frames = run_metrics.stage2_metrics(cfg, workdir, dataset, indices,
                                                         self.protocol.align, self.source.max_depth())
        record = {**metrics, "protocol": dataclasses.asdict(self.protocol), "split": EVAL_SPLIT,
                  "eval_data": self.eval_info["path"], "run": os.path.basename(workdir),
                  "train_wall_s": train_wall_s, "eval_wall_s": round(time.time() - started, 1)}
        np.savez_compressed(path[:-len(".json")] + ".npz", **frames)
        _write_json(path, record)  # last: its presence means the run is complete
        return record

    def _adopt_committed(self, workdir: str, weights: bool = False) -> None:
        """Copies the committed run of `workdir`'s name (`COMMITTED_RUNS`) into the cache when
        the cache has no such run (whole: copied beside it, then renamed into place). A committed
        run without weights (its records only) is taken only where its evaluation is the one
        asked for (this cache's evaluation set) and no weights are needed (`weights` False)."""
        committed = os.path.join(COMMITTED_RUNS, os.path.basename(workdir))
        if self.args.no_committed_runs or os.path.exists(workdir) or not os.path.isdir(committed):
            return
        if not os.path.isdir(os.path.join(committed, "checkpoints")) and (
                weights or not os.path.exists(os.path.join(
                    committed, self.eval_file(os.path.basename(workdir))))):
            return
        self.log(f"using the committed run {os.path.relpath(committed, REPO)} (see its "
                 "MADE_BY.md; --no-committed-runs trains it instead)")
        os.makedirs(os.path.dirname(workdir), exist_ok=True)
        copying = tempfile.mkdtemp(prefix=f"{os.path.basename(workdir)}.copying-",
                                   dir=os.path.dirname(workdir))
        try:
            shutil.copytree(committed, copying, dirs_exist_ok=True)
            with contextlib.suppress(OSError):  # another runner's copy came first
                os.rename(copying, workdir)
        finally:
            shutil.rmtree(copying, ignore_errors=True)

    def workdir(self, kind: str, overrides: tuple[str, ...], seed: int) -> str:
        """The directory of a row's run for `seed` (trained and evaluated first if not cached)."""
        return os.path.join(self.cache, "runs", self.result(kind, overrides, seed)["run"])

    def evaluation(self, run: str) -> dict:
        """The evaluation record `result` saved for the cached run named `run`."""
        with open(self.eval_path(run)) as f:
            return json.load(f)

    def frames(self, record: dict) -> dict[str, np.ndarray]:
        """The per-frame metrics saved beside an evaluation record of `result`."""
        with np.load(self.eval_path(record["run"], ".npz")) as f:
            return {k: f[k] for k in f.files}

    def _options(self, workdir: str, **kw):
        from irdepth_jax.train.phase import RunOptions

        return RunOptions(workdir=workdir, resume=os.path.isdir(workdir), parallel="single",
                          progress=not self.args.no_progress, eval=False, **kw)

    def _trained(self, workdir: str) -> float | None:
        """Training wall time of a finished run in `workdir`, None if it has not finished."""
        path = os.path.join(workdir, "trained.json")
        if not os.path.exists(path):
            return None
        with open(path) as f:
            return json.load(f)["wall_s"]

    def _train(self, fn, kind: str, cfg, opts, source=None) -> float:
        """Runs `fn(cfg, source, opts)` (once: a finished run is only timed) on `source` (default:
        the benchmark's training data); returns the training wall time."""
        from irdepth_jax.errors import Interrupted, RunError
        from irdepth_jax.train.workdir_lock import WorkdirLocked, acquire, release

        done = self._trained(opts.workdir)
        if done is not None and not _unfinalised(opts.workdir):
            return done
        os.makedirs(opts.workdir, exist_ok=True)
        try:  # the workdir lock of `irdepth train`: one runner trains a cached run
            lock = acquire(opts.workdir, "cached run")
        except WorkdirLocked as err:
            raise SystemExit(f"{err} (another runner on this --cache trains it; re-run this "
                             "command when it has finished)") from None
        try:
            done = self._trained(opts.workdir)  # finished while this runner waited for the lock
            unfinalised = _unfinalised(opts.workdir)
            if done is not None and not unfinalised:
                return done
            if unfinalised and not os.path.isdir(os.path.join(opts.workdir, "checkpoints", unfinalised[0])):
                raise SystemExit(f"{opts.workdir}: a copy of a committed run made before Stage I "
                                 "models had exact BatchNorm statistics, without the weights to "
                                 "compute them; delete it to take the committed run again")
            self.log(f"[{kind} seed {cfg.seed}] " + (
                "computing the exact BatchNorm statistics of the finished phases "
                f"{', '.join(unfinalised)} in " if done is not None else "training in ")
                + os.path.relpath(opts.workdir, self.cache))
            self._record_code(opts.workdir, kind, cfg.seed)
            started = time.time()
            if done is not None:  # finished: only its last checkpoints are rewritten
                opts = dataclasses.replace(opts, resume=True)
            try:
                fn(cfg, self.source if source is None else source, opts)
            except Interrupted as err:
                self.log(f"{err}\nre-run the same command to continue")
                raise SystemExit(130) from None
            except RunError as err:
                raise SystemExit(str(err)) from None
            if done is not None:
                return done
            wall_s = round(time.time() - started, 1)
            _write_json(os.path.join(opts.workdir, "trained.json"), {"wall_s": wall_s})
        finally:
            release(lock)
        return wall_s

    def _record_code(self, workdir: str, kind: str, seed: int) -> None:
        """Adds this package version to the run's `CODE_FILE` unless it is the last one there,
        and says so loudly when it continues a run that other code trained so far (a run resumed
        after the package changed, or a Stage I on an I-1 run of other code): a rounding-level
        change of the code moves a Stage I by as much as a seed does, so such a run is neither
        version's and a fresh run of the same command may differ. A run with checkpoints but no
        record was trained before records were kept: 'unknown'."""
        versions = code_versions(workdir)
        if versions is None:
            versions = ([{"git": "unknown", "digest": "unknown"}]
                        if os.path.isdir(os.path.join(workdir, "checkpoints")) else [])
        now = {"git": git_commit(), "digest": code_digest()}
        if versions and versions[-1]["digest"] == now["digest"]:
            return
        if versions:
            last = versions[-1]
            self.log(f"[{kind} seed {seed}] WARNING: {os.path.relpath(workdir, self.cache)} was "
                     f"trained so far by other package code (git {last['git']}, digest "
                     f"{last['digest']}) than continues it now (git {now['git']}, digest "
                     f"{now['digest']}): its result is neither version's (recorded in its "
                     f"{CODE_FILE} and in the table's provenance); delete the run to train it "
                     "with this code alone")
        _write_json(os.path.join(workdir, CODE_FILE), versions + [now])

    def _stage1_i1(self, cfg) -> float:
        from irdepth_jax.train.stages import train_stage1

        workdir = self.run_dir("stage1_i1", cfg)
        return self._train(train_stage1, "stage1_i1", cfg, self._options(workdir))

    def _stage1(self, cfg) -> float:
        from irdepth_jax.train.stages import train_stage1

        workdir = self.run_dir("stage1", cfg)
        self._adopt_committed(workdir, weights=True)  # before its I-1 phase is copied in
        i1_ckpt = os.path.join(workdir, "checkpoints", "stage1_i1")
        if self._trained(workdir) is not None and not os.path.isdir(os.path.dirname(i1_ckpt)):
            raise SystemExit(f"{workdir} holds a committed run's records without its weights (its "
                             "evaluation only), and this run needs the weights: delete that "
                             "folder to train it")
        if self._trained(workdir) is None and not os.path.isdir(i1_ckpt):
            i1_cfg = i1_config(cfg, self.base)
            self._stage1_i1(i1_cfg)
            os.makedirs(os.path.dirname(i1_ckpt), exist_ok=True)
            i1_run = self.run_dir("stage1_i1", i1_cfg)
            shutil.copytree(os.path.join(i1_run, "checkpoints", "stage1_i1"), i1_ckpt)
            if os.path.exists(os.path.join(i1_run, CODE_FILE)):  # the code that trained I-1
                shutil.copy2(os.path.join(i1_run, CODE_FILE), workdir)
        opts = self._options(workdir)
        opts.resume = True  # continues from the copied I-1 checkpoint
        return self._train(train_stage1, "stage1", cfg, opts)

    def _stage2(self, cfg) -> float:
        from irdepth_jax.train.stages import train_stage2

        s1_cfg = self.stage1_config(cfg)
        self._stage1(s1_cfg)
        workdir = self.run_dir("stage2", cfg)
        return self._train(train_stage2, "stage2", cfg, self._options(
            workdir, stage1_checkpoint=self.run_dir("stage1", s1_cfg)))

    def _depth(self, cfg) -> float:
        from irdepth_jax.train.stages import train_depth

        if self.pretraining_data is None:
            raise ValueError("a 'depth' run needs Context.use_pretraining_set first")
        source, _ = self.pretraining_source(self.pretraining_frames)
        workdir = self.run_dir("depth", cfg, self.pretraining_data)
        return self._train(train_depth, "depth", cfg, self._options(workdir), source=source)

    def use_pretraining_set(self, frames: int) -> dict:
        """Renders (once) the depth pretraining set of `frames` frames that 'depth' runs train
        on; returns its info record."""
        _, info = self.pretraining_source(frames)
        self.pretraining_data, self.pretraining_frames = info["path"], frames
        return info

    # ---------------------------------------------------------------- evaluation
    def _eval_frames(self):
        dataset, indices = self.eval_source.frames(EVAL_SPLIT, stride=self.protocol.stride)
        if len(indices) == 0:
            raise SystemExit(f"{self.eval_info['path']}: no {EVAL_SPLIT} frames")
        return dataset, indices


EVAL_METRICS_VERSION = 2
"""Part of the evaluation cache key: 2 added the sky metrics, so older evaluations are redone."""

STAGE1_MODEL_VERSION = 2
"""Part of the key of Stage I evaluations and of Stage II runs: 2 is a Stage I model whose
phases end with exact BatchNorm statistics (`irdepth_jax.train.batch_statistics`). A finished
Stage I run of version 1 (running averages) gets them when it is next used (`_unfinalised`),
and is evaluated again; the Stage II runs on it are trained again."""


def _unfinalised(workdir: str) -> list[str]:
    """The Stage I phases of the run in `workdir` whose last checkpoint holds running-average
    BatchNorm statistics (finished before `STAGE1_MODEL_VERSION` 2), the I-1 phase first;
    a run that is not a Stage I run: none."""
    from irdepth_jax.runs.checkpoint import FINALIZED, has_checkpoint, read_meta

    if not os.path.basename(workdir).startswith("stage1"):
        return []
    phases = []
    for phase in ("stage1_i1", "stage1_i2"):
        directory = os.path.join(workdir, "checkpoints", phase)
        if has_checkpoint(directory) and FINALIZED not in read_meta(directory):
            phases.append(phase)
    if phases == ["stage1_i2"] and not has_checkpoint(os.path.join(workdir, "checkpoints", "stage1_i1")):
        phases.insert(0, "stage1_i1")  # a committed copy: its I-2 weights only
    return phases


def _fingerprint(path: str) -> str:
    """Hash of a dataset's manifest (MS2: its path)."""
    manifest = os.path.join(path, "manifest.json")
    if os.path.exists(manifest):
        with open(manifest, "rb") as f:
            return hashlib.sha1(f.read()).hexdigest()[:12]
    return hashlib.sha1(path.encode()).hexdigest()[:12]


def _write_json(path: str, obj) -> None:
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=2)
    os.replace(tmp, path)


def i1_config(cfg, base):
    """The Stage I-1-only config of `cfg`: the I-2 phase has 0 steps and every I-2-only field
    is the base config's, so runs that differ only in I-2 settings share one I-1 run."""
    s1, b1 = cfg.stage1, base.stage1
    return dataclasses.replace(cfg, stage1=dataclasses.replace(
        s1, steps_i2=0, epochs_i2=b1.epochs_i2, multitask=b1.multitask, w_rec=b1.w_rec,
        w_seg=b1.w_seg, i2_learning_rate=b1.i2_learning_rate,
        seg_lr_multiplier=b1.seg_lr_multiplier, seg_labels=b1.seg_labels,
        synthetic_labeled=b1.synthetic_labeled))
