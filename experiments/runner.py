"""The one runner behind the paper's ablation tables (``experiments/table*.py``).

A table script declares its rows (`Arm`: a label, the training runs it needs and which metrics
to read) and calls `main`. The runner

* builds (or finds) the dataset: by default a synthetic benchmark rendered once into
  ``CACHE/data/`` for the preset's data size; or a folder-format / MS2 directory (``--data``);
* trains every run a row needs with `irdepth_jax.train.stages`, once per (config, seed): runs
  live in ``CACHE/runs/<kind>-<hash of the full config>/`` and end with ``eval_test.json``
  (the test-split metrics). A run with that file is reused (by this and the other tables: the
  Stage I model of a seed is shared by tables 1-7); a run without it resumes from its last
  checkpoint, so an interrupted experiment loses at most one checkpoint interval;
* writes ``OUT/results.md`` (Markdown: mean +- std over seeds, per-seed values, the paper's
  figures for orientation, provenance), ``OUT/results.json`` and ``OUT/figure.png`` (bars with
  error bars = std over seeds, dots = seeds).

Run kinds: ``stage1_i1`` (Stage I-1 only: the single-task reconstruction model of the paper's
table 2), ``stage1`` (I-1 then I-2; its I-1 phase is copied from the matching ``stage1_i1`` run,
so the multi-task and single-task models of a seed start from the same I-1 weights) and
``stage2`` (Depth Anything V2 on the frozen Stage I model of the same config).

Every number in a result is a *synthetic-benchmark* number unless ``--data`` names a real
dataset; the outputs say which.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import platform
import shlex
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Sequence

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DEFAULT_CACHE = os.path.join(REPO, "workdir", "experiments")
RESULTS = os.path.join(REPO, "experiments", "results")
EVAL_SPLIT = "test"
DATA_SEED = 0  # the synthetic benchmark is one fixed dataset; --seeds vary the training only

QUICK_OVERRIDES = ("stage1.steps_i1=2", "stage1.steps_i2=2", "stage2.steps=2")
"""--quick: tiny preset, one seed, two optimizer steps per phase (a smoke test, not a result)."""

DEPTH_COLUMNS = ("d1", "d2", "d3", "abs_rel", "sq_rel", "rmse")
RECON_COLUMNS = ("ssim", "psnr", "entropy")
SEG_COLUMNS = ("miou",)
COLUMN_NAMES = {"d1": "δ<1.25", "d2": "δ<1.25²", "d3": "δ<1.25³", "abs_rel": "AbsRel",
                "sq_rel": "SqRel", "rmse": "RMSE", "ssim": "SSIM", "psnr": "PSNR",
                "entropy": "Entropy", "miou": "mIoU"}
HIGHER_IS_BETTER = {"d1", "d2", "d3", "ssim", "psnr", "entropy", "miou"}


# --------------------------------------------------------------------------- declarations
@dataclasses.dataclass(frozen=True)
class Arm:
    """One row of a table.

    Attributes:
      label: the row's name (e.g. 'HSV (ours)').
      kind: which run's metrics the row reads: 'stage1_i1' | 'stage1' | 'stage2'.
      overrides: ``key=value`` config overrides of this row (on top of preset and --set).
      group: the metric group of the evaluation result: 'all' or a condition ('day', ...).
    """

    label: str
    kind: str
    overrides: tuple[str, ...] = ()
    group: str = "all"


@dataclasses.dataclass(frozen=True)
class Table:
    """A table script's declaration.

    Attributes:
      name: output folder name under experiments/results/ (e.g. 'table1_preprocessing').
      title: one-line title.
      about: what the table compares and how (Markdown, a few sentences).
      arms: the rows.
      columns: metric keys (see COLUMN_NAMES).
      paper: the paper's figures for orientation: row label -> {column: value}.
      paper_note: where those come from.
    """

    name: str
    title: str
    about: str
    arms: tuple[Arm, ...]
    columns: tuple[str, ...]
    paper: dict[str, dict[str, float]]
    paper_note: str = "Paper (private 2.3k-frame LWIR dataset, one run; orientation only)"


# --------------------------------------------------------------------------- arguments
def parse_args(table: Table, argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The command line every table script shares (``--help`` explains it)."""
    ap = argparse.ArgumentParser(
        prog=f"python experiments/{table.name}.py",
        description=f"{table.title}.\n\n{table.about}",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=(
            "Runs are cached under CACHE/runs (keyed by a hash of the full config and seed) "
            "and shared between the table scripts; a finished run is reused, an interrupted "
            "one resumes from its last checkpoint. Outputs: OUT/results.md, results.json, "
            "figure.png. Without --data the numbers are from the SYNTHETIC benchmark, not the "
            "paper's dataset."))
    ap.add_argument("--preset", default="small", choices=("tiny", "small", "paper"),
                    help="config preset (default: small)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2],
                    help="training seeds; one run per seed and row (default: 0 1 2)")
    ap.add_argument("--data", default=None,
                    help="dataset directory (folder format or MS2); default: the synthetic "
                         "benchmark, rendered once into CACHE/data for the preset's data size")
    ap.add_argument("--format", default="auto", choices=("auto", "folder", "ms2"),
                    help="format of --data (default: auto)")
    ap.add_argument("--set", dest="overrides", nargs="*", default=[], metavar="KEY=VALUE",
                    help="config overrides for every run (e.g. stage2.steps=100); recorded in "
                         "the outputs and part of the run hash")
    ap.add_argument("--out", default=None,
                    help=f"output folder (default: experiments/results/{table.name})")
    ap.add_argument("--cache", default=DEFAULT_CACHE,
                    help="where datasets, runs and the XLA compilation cache go "
                         "(default: workdir/experiments)")
    ap.add_argument("--quick", action="store_true",
                    help="smoke test: tiny preset, seed 0, 2 steps per phase (overrides "
                         "--preset/--seeds; not a result)")
    ap.add_argument("--no-progress", action="store_true", help="no progress bars")
    args = ap.parse_args(argv)
    if args.quick:
        args.preset, args.seeds = "tiny", [0]
        args.overrides = list(QUICK_OVERRIDES) + list(args.overrides)
    if len(set(args.seeds)) != len(args.seeds):
        ap.error(f"--seeds {args.seeds}: repeated seed")
    args.out = args.out or os.path.join(RESULTS, table.name)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    return args


# --------------------------------------------------------------------------- context
class Context:
    """The config, data and cache of one invocation, and the cached runs (see module doc)."""

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
        self.data_fingerprint = self._fingerprint()
        try:
            self.source = DataSource(self.data_path, args.format, raw_bits=self.base.data.raw_bits)
            # every run (and its cache key) gets the resolved bit depth, 'auto' included
            self.base = resolve_raw_bits(self.base, self.source)
        except RunError as err:
            raise SystemExit(str(err)) from None
        self.data_info["format"] = self.source.format

    # ---------------------------------------------------------------- data
    def _dataset(self) -> tuple[str, dict]:
        from irdepth_jax.data.folder import write_synthetic_dataset

        if self.args.data is not None:
            path = os.path.abspath(self.args.data)
            return path, {"source": "user", "path": path}
        d = self.base.data
        name = f"synthetic-n{d.num_frames}-l{d.num_labeled}-{d.height}x{d.width}-seed{DATA_SEED}"
        path = os.path.join(self.cache, "data", name)
        info = {"source": "synthetic", "path": path, "num_frames": d.num_frames,
                "num_labeled": d.num_labeled, "height": d.height, "width": d.width,
                "seed": DATA_SEED,
                "made_by": f"write_synthetic_dataset(path, {d.num_frames}, {d.num_labeled}, "
                           f"{d.height}, {d.width}, seed={DATA_SEED})"}
        if not os.path.exists(os.path.join(path, "manifest.json")):  # manifest is written last
            self.log(f"rendering the synthetic benchmark ({d.num_frames} frames, "
                     f"{d.height}x{d.width}) into {path}")
            write_synthetic_dataset(path, d.num_frames, d.num_labeled, d.height, d.width,
                                    seed=DATA_SEED, progress=not self.args.no_progress,
                                    overwrite=True)
        return path, info

    def _fingerprint(self) -> str:
        """Hash of the dataset's manifest (MS2: its path), part of every run's hash."""
        manifest = os.path.join(self.data_path, "manifest.json")
        if os.path.exists(manifest):
            with open(manifest, "rb") as f:
                return hashlib.sha1(f.read()).hexdigest()[:12]
        return hashlib.sha1(self.data_path.encode()).hexdigest()[:12]

    # ---------------------------------------------------------------- configs
    def config(self, arm: Arm, seed: int):
        """The run config of `arm` and `seed` for its kind (Stage I runs normalise the
        Stage II / depth sections to the base config's, so every table shares them)."""
        from irdepth_jax.config import apply_overrides

        try:
            cfg = apply_overrides(dataclasses.replace(self.base, seed=seed), list(arm.overrides))
        except ValueError as err:
            raise SystemExit(f"{arm.label}: {err}") from None
        if arm.kind in ("stage1", "stage1_i1"):
            cfg = self.stage1_config(cfg)
        if arm.kind == "stage1_i1":
            cfg = i1_config(cfg, self.base)
        return cfg

    def stage1_config(self, cfg):
        """`cfg` with the base config's Stage II / depth sections: the key of the Stage I run
        that Stage II runs of any Stage II / depth setting share."""
        return dataclasses.replace(cfg, stage2=self.base.stage2, depth=self.base.depth)

    def run_dir(self, kind: str, cfg) -> str:
        from irdepth_jax.config import to_dict

        blob = json.dumps({"kind": kind, "config": to_dict(cfg), "data": self.data_fingerprint},
                          sort_keys=True)
        return os.path.join(self.cache, "runs", f"{kind}-{hashlib.sha1(blob.encode()).hexdigest()[:12]}")

    # ---------------------------------------------------------------- runs
    def workdir(self, arm: Arm, seed: int) -> str:
        """The run directory behind `arm` for `seed`, trained first if not cached."""
        self.result(arm, seed)
        return self.run_dir(arm.kind, self.config(arm, seed))

    def result(self, arm: Arm, seed: int) -> dict:
        """The eval_test.json record of the run behind `arm` for `seed` (trained if not
        cached): {'stage1' or 'stage2': {group: metrics}, 'split', 'wall_s'}."""
        runs = {"stage1_i1": self._stage1_i1, "stage1": self._stage1, "stage2": self._stage2}
        if arm.kind not in runs:
            raise ValueError(f"{arm.label}: unknown run kind {arm.kind!r}")
        return runs[arm.kind](self.config(arm, seed))

    def _cached(self, workdir: str) -> dict | None:
        path = os.path.join(workdir, f"eval_{EVAL_SPLIT}.json")
        if os.path.exists(path):
            with open(path) as f:
                return json.load(f)
        return None

    def _finish(self, workdir: str, result: dict, started: float) -> dict:
        result = {**result, "split": EVAL_SPLIT, "wall_s": round(time.time() - started, 1)}
        tmp = os.path.join(workdir, f"eval_{EVAL_SPLIT}.json.tmp")
        with open(tmp, "w") as f:
            json.dump(result, f, indent=2)
        os.replace(tmp, os.path.join(workdir, f"eval_{EVAL_SPLIT}.json"))
        return result

    def _options(self, workdir: str, **kw):
        from irdepth_jax.train.phase import RunOptions

        return RunOptions(workdir=workdir, resume=os.path.isdir(workdir), parallel="single",
                          progress=not self.args.no_progress, eval=False, **kw)

    def _announce(self, kind: str, cfg, workdir: str, what: str) -> None:
        self.log(f"[{kind} seed {cfg.seed}] {what} {os.path.relpath(workdir, self.cache)}")

    def _stage1_i1(self, cfg) -> dict:
        from irdepth_jax.train.stages import train_stage1

        workdir = self.run_dir("stage1_i1", cfg)
        cached = self._cached(workdir)
        if cached is not None:
            return cached
        self._announce("stage1_i1", cfg, workdir, "training Stage I-1 in")
        started = time.time()
        unet = self._train(train_stage1, cfg, self._options(workdir))["unet"]
        return self._finish(workdir, {"stage1": self._eval_stage1(cfg, unet)}, started)

    def _stage1(self, cfg) -> dict:
        from irdepth_jax.train.stages import train_stage1

        workdir = self.run_dir("stage1", cfg)
        cached = self._cached(workdir)
        if cached is not None:
            return cached
        i1_ckpt = os.path.join(workdir, "checkpoints", "stage1_i1")
        if not os.path.isdir(i1_ckpt):
            i1_cfg = i1_config(cfg, self.base)
            self._stage1_i1(i1_cfg)
            os.makedirs(os.path.dirname(i1_ckpt), exist_ok=True)
            shutil.copytree(os.path.join(self.run_dir("stage1_i1", i1_cfg), "checkpoints",
                                         "stage1_i1"), i1_ckpt)
        self._announce("stage1", cfg, workdir, "training Stage I-2 in")
        started = time.time()
        opts = self._options(workdir)
        opts.resume = True  # continues from the copied I-1 checkpoint
        unet = self._train(train_stage1, cfg, opts)["unet"]
        return self._finish(workdir, {"stage1": self._eval_stage1(cfg, unet)}, started)

    def _stage2(self, cfg) -> dict:
        from irdepth_jax.evaluators import evaluate_stage2
        from irdepth_jax.train.stages import train_stage2

        workdir = self.run_dir("stage2", cfg)
        cached = self._cached(workdir)
        if cached is not None:
            return cached
        s1_cfg = self.stage1_config(cfg)
        self._stage1(s1_cfg)
        self._announce("stage2", cfg, workdir,
                       f"training Stage II ({cfg.stage2.preprocessing}, sky loss "
                       f"{'on' if cfg.stage2.sky_loss else 'off'}) in")
        started = time.time()
        out = self._train(train_stage2, cfg, self._options(
            workdir, stage1_checkpoint=self.run_dir("stage1", s1_cfg)))
        result = self._eval(evaluate_stage2, cfg, out["unet"], out["depth"])
        return self._finish(workdir, {"stage2": result}, started)

    def _train(self, fn, cfg, opts) -> dict:
        from irdepth_jax.errors import Interrupted, RunError

        try:
            return fn(cfg, self.source, opts)
        except Interrupted as err:
            self.log(f"{err}\nre-run the same command to continue")
            raise SystemExit(130) from None
        except RunError as err:
            raise SystemExit(str(err)) from None

    def _eval_stage1(self, cfg, unet) -> dict:
        """Stage I metrics: reconstruction on the depth test split, mIoU (tables 3 and 6) on the
        segmentation test split (the paper's independent 600/100/100 split)."""
        from irdepth_jax.evaluators import evaluate_stage1

        return self._eval(evaluate_stage1, cfg, unet,
                          seg_frames=self.source.seg_frames(EVAL_SPLIT))

    def _eval(self, fn, cfg, *models, **kw) -> dict:
        from irdepth_jax.train.parallel import DataParallel

        dataset, indices = self.source.frames(EVAL_SPLIT)
        if len(indices) == 0:
            raise SystemExit(f"--data {self.data_path}: no {EVAL_SPLIT} frames")
        return fn(cfg, *models, dataset, indices, DataParallel("single"), **kw)


def enable_compilation_cache(path: str | None) -> None:
    """Points JAX's persistent compilation cache at `path` (None: off), also after earlier
    compilations in this process. Compiled steps are then reused across runs and processes
    (same computation -> same key), which is most of a short run's time on a CPU."""
    import jax
    from jax.experimental.compilation_cache import compilation_cache as cc

    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    jax.config.update("jax_compilation_cache_dir", path)
    cc.reset_cache()


def context(preset: str = "small", seeds: Sequence[int] = (0,), quick: bool = False,
            data: str | None = None, overrides: Sequence[str] = (), cache: str = DEFAULT_CACHE,
            progress: bool = False) -> Context:
    """A `Context` without a command line (for notebooks): same caching as the scripts."""
    table = Table("notebook", "notebook", "", (), (), {})
    argv = ["--preset", preset, "--seeds", *map(str, seeds), "--cache", cache, "--set", *overrides]
    argv += (["--data", data] if data else []) + (["--quick"] if quick else [])
    argv += [] if progress else ["--no-progress"]
    return Context(parse_args(table, argv))


def i1_config(cfg, base):
    """The Stage I-1-only config of `cfg`: the I-2 phase has 0 steps and every I-2-only field
    is the base config's, so runs that differ only in I-2 settings share one I-1 run."""
    s1, b1 = cfg.stage1, base.stage1
    return dataclasses.replace(cfg, stage1=dataclasses.replace(
        s1, steps_i2=0, epochs_i2=b1.epochs_i2, multitask=b1.multitask, w_rec=b1.w_rec,
        w_seg=b1.w_seg, stage12_learning_rate=b1.stage12_learning_rate,
        seg_lr_multiplier=b1.seg_lr_multiplier, seg_labels=b1.seg_labels,
        synthetic_labeled=b1.synthetic_labeled))


# --------------------------------------------------------------------------- provenance
def hardware() -> dict:
    """CPU model, cores, platform and library versions of this machine."""
    import jax

    cpu = platform.processor() or "unknown"
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "platform": platform.platform(),
            "python": platform.python_version(), "jax": jax.__version__,
            "devices": [str(d) for d in jax.devices()][:1] + (
                [f"... {len(jax.devices())} devices"] if len(jax.devices()) > 1 else []),
            "backend": jax.default_backend()}


def git_commit() -> str:
    """HEAD commit of the repository (+ '-dirty' with uncommitted changes to the code: the
    package, the experiment scripts and pyproject.toml; not the results they write), or
    'unknown'."""
    code = ["irdepth_jax", "experiments", ":!experiments/results", "pyproject.toml"]
    try:
        head = subprocess.run(["git", "-C", REPO, "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", REPO, "status", "--porcelain", "--untracked-files=no",
                                "--", *code], capture_output=True, text=True,
                               check=True).stdout.strip()
        return head + ("-dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


# --------------------------------------------------------------------------- summary
def summarise(values: list[float]) -> dict:
    """{'mean', 'std' (sample std, 0 for one seed), 'n'} of finite values (NaN if none)."""
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], np.float64)
    if v.size == 0:
        return {"mean": float("nan"), "std": float("nan"), "n": 0}
    return {"mean": float(v.mean()), "std": float(v.std(ddof=1)) if v.size > 1 else 0.0,
            "n": int(v.size)}


def _fmt(x: float, col: str) -> str:
    if x is None or not np.isfinite(x):
        return "-"
    return f"{x:.2f}" if col in ("psnr", "rmse") else f"{x:.3f}"


def markdown(table: Table, record: dict) -> str:
    """The results.md text of a finished table."""
    cols = table.columns
    head = "| " + " | ".join(["row"] + [COLUMN_NAMES[c] + (" ↑" if c in HIGHER_IS_BETTER else " ↓")
                                        for c in cols]) + " |"
    rule = "|---" * (len(cols) + 1) + "|"
    data = record["data"]
    origin = ("SYNTHETIC benchmark (rendered scenes, not the paper's dataset)"
              if data["source"] == "synthetic" else f"dataset {data['path']} ({data['format']})")
    lines = [f"# {table.title}", "",
             f"**Data: {origin}.** Mean ± std over seeds {record['seeds']} "
             f"(preset `{record['preset']}`{', QUICK smoke test: not a result' if record['quick'] else ''}), "
             f"test split.", "", table.about, "", head, rule]
    for row in record["rows"]:
        cells = [f"{_fmt(row['summary'][c]['mean'], c)} ± {_fmt(row['summary'][c]['std'], c)}"
                 for c in cols]
        lines.append(f"| {row['label']} | " + " | ".join(cells) + " |")
    lines += ["", "Per seed:", "", "| row | seed | " + " | ".join(COLUMN_NAMES[c] for c in cols) + " |",
              "|---" * (len(cols) + 2) + "|"]
    for row in record["rows"]:
        for seed, values in row["per_seed"].items():
            lines.append(f"| {row['label']} | {seed} | "
                         + " | ".join(_fmt(values.get(c), c) for c in cols) + " |")
    if table.paper:
        lines += ["", f"{table.paper_note}:", "",
                  "| row | " + " | ".join(COLUMN_NAMES[c] for c in cols) + " |",
                  "|---" * (len(cols) + 1) + "|"]
        for label, values in table.paper.items():
            lines.append(f"| {label} | " + " | ".join(_fmt(values.get(c), c) for c in cols) + " |")
    hw = record["hardware"]
    lines += ["", "Provenance:", "",
              f"- command: `{record['command']}`",
              f"- preset: `{record['preset']}`; overrides: "
              f"{', '.join(f'`{o}`' for o in record['overrides']) or 'none'}",
              f"- seeds: {record['seeds']}",
              f"- data: {data.get('made_by', data['path'])} ({data['source']}, {data['format']})",
              f"- hardware: {hw['cpu']}, {hw['cores']} cores, {hw['backend']}; jax {hw['jax']}, "
              f"python {hw['python']}; {hw['platform']}",
              f"- code: git {record['git']}; wall time of this invocation "
              f"{record['wall_s']:.0f} s (cached runs count 0); training + evaluation time of "
              f"the runs read here, as measured when each ran: {record['runs_wall_s']:.0f} s",
              ""]
    return "\n".join(lines)


def figure(table: Table, record: dict, path: str) -> None:
    """Bar chart per metric: bars = rows (grouped by condition when rows have groups), error
    bars = std over seeds, dots = individual seeds."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows, cols = record["rows"], table.columns
    ncols = min(len(cols), 3)
    nrows = -(-len(cols) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(3.4 * ncols + 0.6, 2.9 * nrows + 1.2),
                             squeeze=False)
    for ax in axes.flat[len(cols):]:
        ax.set_visible(False)
    colors = plt.get_cmap("tab10").colors
    groups = list(dict.fromkeys(r["group"] for r in rows))
    series = list(dict.fromkeys(r["series"] for r in rows))
    width = 0.8 / len(series)
    for ax, col in zip(axes.flat, cols):
        for r in rows:
            gi, si = groups.index(r["group"]), series.index(r["series"])
            x = gi + (si - (len(series) - 1) / 2) * width
            s = r["summary"][col]
            ax.bar(x, s["mean"], width * 0.9, yerr=s["std"], capsize=3, color=colors[si % 10],
                   label=r["series"] if gi == 0 else None, alpha=0.85)
            seeds = [v.get(col) for v in r["per_seed"].values()]
            ax.plot([x] * len(seeds), seeds, "k.", ms=3)
        ax.set_title(COLUMN_NAMES[col] + (" ↑" if col in HIGHER_IS_BETTER else " ↓"), fontsize=10)
        ax.set_xticks(range(len(groups)))
        ax.set_xticklabels(groups if len(groups) > 1 else [""], fontsize=8)
        ax.tick_params(axis="y", labelsize=8)
        finite = [v for r in rows for v in [r["summary"][col]["mean"]] if np.isfinite(v)]
        if col in ("d1", "d2", "d3", "ssim") and finite and min(finite) > 0.5:
            ax.set_ylim(min(finite) - 0.1, 1.0)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(series), 6), fontsize=8,
               frameon=False)
    synthetic = record["data"]["source"] == "synthetic"
    fig.suptitle(f"{table.title}\n{'SYNTHETIC benchmark' if synthetic else record['data']['path']}"
                 f", preset {record['preset']}, seeds {record['seeds']}"
                 f"{' (QUICK smoke test)' if record['quick'] else ''}", fontsize=10)
    fig.tight_layout(rect=(0, 0.06 if nrows > 1 else 0.1, 1, 0.93 if nrows > 1 else 0.88))
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --------------------------------------------------------------------------- entry point
def main(table: Table, argv: Sequence[str] | None = None) -> dict:
    """Runs (or reuses) every run `table` needs for each seed and writes its outputs.

    Returns the results.json record.
    """
    args = parse_args(table, argv)
    started = time.time()
    ctx = Context(args)
    rows = []
    for arm in table.arms:
        per_seed = {}
        for seed in args.seeds:
            ctx.log(f"[{table.name}] {arm.label}: seed {seed}")
            record = ctx.result(arm, seed)
            result = record["stage2" if arm.kind == "stage2" else "stage1"]
            if arm.group not in result:
                raise SystemExit(f"{arm.label}: no '{arm.group}' frames in the {EVAL_SPLIT} split "
                                 f"of {ctx.data_path} (groups: {sorted(result)})")
            group = result[arm.group]
            per_seed[str(seed)] = {c: group[c] for c in table.columns} | {
                "count": group["count"],
                "run": os.path.basename(ctx.run_dir(arm.kind, ctx.config(arm, seed))),
                "run_wall_s": record["wall_s"]}
        label = arm.label if arm.group == "all" else f"{arm.label} ({arm.group})"
        rows.append({"label": label, "series": arm.label, "group": arm.group, "kind": arm.kind,
                     "overrides": list(arm.overrides), "per_seed": per_seed,
                     "summary": {c: summarise([v[c] for v in per_seed.values()])
                                 for c in table.columns}})
    record = {
        "table": table.name, "title": table.title, "synthetic": ctx.data_info["source"] == "synthetic",
        "quick": bool(args.quick),
        "command": " ".join(["python", f"experiments/{table.name}.py"] + [shlex.quote(a) for a in args.argv]),
        "preset": args.preset, "overrides": list(args.overrides), "seeds": list(args.seeds),
        "split": EVAL_SPLIT, "data": ctx.data_info, "hardware": hardware(), "git": git_commit(),
        "columns": list(table.columns), "rows": rows, "paper": table.paper,
        "wall_s": round(time.time() - started, 1),
        "runs_wall_s": round(sum({v["run"]: v["run_wall_s"] for r in rows
                                  for v in r["per_seed"].values()}.values()), 1),
    }
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "results.json"), "w") as f:
        json.dump(record, f, indent=2)
    with open(os.path.join(args.out, "results.md"), "w") as f:
        f.write(markdown(table, record))
    figure(table, record, os.path.join(args.out, "figure.png"))
    ctx.log(f"[{table.name}] wrote {args.out}/results.md, results.json, figure.png "
            f"({record['wall_s']:.0f} s)")
    return record


# --------------------------------------------------------------------------- reading results
@dataclasses.dataclass(frozen=True)
class Claim:
    """A comparison the paper makes: row `ours` beats row `baseline` on `column`.

    Rows are named by (series label, group) of a table's results.json; `paper` names the two
    rows of the table's `paper` dict."""

    table: str
    text: str
    ours: tuple[str, str]
    baseline: tuple[str, str]
    column: str
    paper: tuple[str, str]


def _claims() -> tuple[Claim, ...]:
    t1 = [Claim("table1_preprocessing", f"HSV beats {b} ({COLUMN_NAMES[c]})", ("HSV (ours)", "all"),
                (row, "all"), c, ("HSV (ours)", paper_row))
          for b, row, paper_row in (("HE", "HE", "HE"), ("CLAHE", "CLAHE", "CLAHE"),
                                    ("the camera chain", "camera-like (IRCBA stand-in)",
                                     "IRCBA (camera)"))
          for c in ("d1", "abs_rel")]
    t2 = [Claim("table2_multitask_reconstruction", f"multi-task beats single-task ({COLUMN_NAMES[c]})",
                ("multi-task (I-1 + I-2)", "all"), ("single-task (I-1 only)", "all"), c,
                ("multi-task", "single-task")) for c in RECON_COLUMNS]
    t3 = [Claim("table3_multitask_segmentation", "multi-task beats single-task (mIoU)",
                ("multi-task", "all"), ("single-task", "all"), "miou", ("multi-task", "single-task"))]
    t4 = [Claim("table4_illumination", f"IR beats RGB at {cond} ({COLUMN_NAMES[c]})",
                ("IR (HSV)", cond), ("RGB", cond), c, (f"IR ({cond})", f"RGB ({cond})"))
          for cond in ("day", "dusk", "night") for c in ("d1", "rmse")]
    t5 = [Claim("table5_rgg_reconstruction", f"RGG helps reconstruction ({COLUMN_NAMES[c]})",
                ("with RGG", "all"), ("without RGG", "all"), c, ("with RGG", "without RGG"))
          for c in RECON_COLUMNS]
    t6 = [Claim("table6_rgg_segmentation", "RGG helps segmentation (mIoU)", ("with RGG", "all"),
                ("without RGG", "all"), "miou", ("with RGG", "without RGG"))]
    t7 = [Claim("table7_sky_loss", f"the sky loss helps depth ({COLUMN_NAMES[c]})",
                ("with sky loss", "all"), ("without sky loss", "all"), c,
                ("with sky loss", "without sky loss")) for c in ("d1", "abs_rel")]
    return tuple(t1 + t2 + t3 + t4 + t5 + t6 + t7)


CLAIMS = _claims()
"""The paper's comparisons, checked by `check_claims` (notebooks/ablations.ipynb, README)."""


def load_results(results_dir: str) -> dict[str, dict]:
    """{table name: results.json record} of every ``<results_dir>/<name>/results.json``."""
    out = {}
    for name in sorted(os.listdir(results_dir)):
        path = os.path.join(results_dir, name, "results.json")
        if os.path.isfile(path):
            with open(path) as f:
                out[name] = json.load(f)
    return out


def check_claims(records: dict[str, dict], claims: Sequence[Claim] = CLAIMS) -> list[dict]:
    """Each claim of a loaded table with its paired per-seed differences.

    The difference is ``ours - baseline`` signed so that positive = in the paper's favour
    (lower-is-better columns are negated). Returns dicts: claim, table, column, diff_mean,
    diff_std (sample std over seeds), n, agree (seeds with a positive difference), verdict
    ('holds' all seeds agree, 'opposite' none, 'mixed' otherwise) and paper_diff.
    """
    out = []
    for c in claims:
        record = records.get(c.table)
        if record is None:
            continue
        rows = {(r["series"], r["group"]): r["per_seed"] for r in record["rows"]}
        sign = 1.0 if c.column in HIGHER_IS_BETTER else -1.0
        ours, base = rows[c.ours], rows[c.baseline]
        diffs = [sign * (ours[s][c.column] - base[s][c.column]) for s in ours if s in base]
        summary = summarise(diffs)
        agree = sum(d > 0 for d in diffs)
        paper = record["paper"]
        out.append({"claim": c.text, "table": c.table, "column": c.column,
                    "diff_mean": summary["mean"], "diff_std": summary["std"], "n": summary["n"],
                    "agree": agree,
                    "verdict": "holds" if agree == len(diffs) else "opposite" if agree == 0
                    else "mixed",
                    "paper_diff": sign * (paper[c.paper[0]][c.column]
                                          - paper[c.paper[1]][c.column])})
    return out
