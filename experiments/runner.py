"""The one runner behind the paper's ablation tables (``experiments/table*.py``).

A table script declares its rows (`Arm`: a label, the training run it needs and which metrics
to read) and calls `main`, which

* builds (or finds) the data: by default the synthetic benchmark (training frames for the
  preset plus a separate, larger evaluation set, rendered once into ``CACHE/data/``); or a
  folder-format / MS2 directory (``--data``; MS2 is evaluated with the literature's protocol);
* trains and evaluates every run a row needs, once per (config, seed), through
  `irdepth_experiments.cache.Context` (runs are shared between tables and resume when interrupted);
* writes ``OUT/results.md``, ``results.json``, ``frames.npz`` and ``figure.png``
  (`irdepth_experiments.report`).

Every number in a result is a *synthetic-benchmark* number unless ``--data`` names a real
dataset; the outputs say which.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import shlex
import sys
import time
from collections.abc import Sequence

import numpy as np

from irdepth_experiments.cache import (
    COMMITTED_RUNS,
    DEFAULT_CACHE,
    EVAL_SPLIT,
    REPO,
    Context,
    cache_relative,
    code_versions,
    commit_run,
    git_commit,
)
from irdepth_experiments.report import hardware, summarise, write_outputs
from irdepth_jax.hostmem import keep_freed_memory

RESULTS = os.path.join(REPO, "experiments", "results")
EVAL_FRAMES = 1500
"""Frames of the synthetic evaluation set (500 per lighting condition): ~20 s to render at the
`small` size, a few seconds per run to evaluate; per-frame noise of a mean over them is small
next to the seed-to-seed spread."""

QUICK_OVERRIDES = ("data.height=32", "data.width=48", "stage1.steps_i1=2", "stage1.steps_i2=2",
                   "stage2.steps=2")
QUICK_EVAL_FRAMES = 24
"""--quick: tiny preset at 32x48 frames, one seed, two optimizer steps per phase, 24 evaluation
frames (a smoke test, not a result; the test suite's frame size, so that its compiled steps
are the suite's other runs')."""

DEPTH_COLUMNS = ("d1", "d2", "d3", "abs_rel", "sq_rel", "rmse")
SKY_COLUMNS = ("sky_far", "skyline_abs_rel")
"""`metrics.SKY_METRICS`: the share of true-sky pixels predicted at >= 0.9 x the sky reference
depth, and AbsRel within 3 px of the skyline (the depth metrics exclude the sky itself)."""
RECON_COLUMNS = ("ssim", "psnr", "entropy")
SEG_COLUMNS = ("miou",)


# --------------------------------------------------------------------------- declarations
@dataclasses.dataclass(frozen=True)
class Arm:
    """One row of a table.

    Attributes:
      label: the row's name (e.g. 'HSV (ours)').
      kind: which run's metrics the row reads: 'stage1_i1' | 'stage1' | 'stage2'.
      overrides: ``key=value`` config overrides of this row (on top of preset and --set).
      group: the metric group of the evaluation result: 'all' or a condition ('day', ...).
      metrics: which metrics of the run: None (the kind's: 'stage1' or 'stage2', the
        protocol's alignment) or 'stage2_median' (depth median-scaled per image).
      equal_steps: a 'stage1_i1' row trained for as many optimizer steps as the Stage I run
        (I-1 + I-2) of the same seed and settings: the single-task control given the
        multi-task arm's training length (``stage1.steps_i1`` set to it).
    """

    label: str
    kind: str
    overrides: tuple[str, ...] = ()
    group: str = "all"
    metrics: str | None = None
    equal_steps: bool = False

    @property
    def key(self) -> str:
        return self.metrics or ("stage2" if self.kind == "stage2" else "stage1")


@dataclasses.dataclass(frozen=True)
class Table:
    """A table script's declaration.

    Attributes:
      name: output folder name under experiments/results/ (e.g. 'table1_preprocessing').
      title: one-line title.
      about: what the table compares and how (Markdown, a few sentences).
      arms: the rows.
      columns: metric keys (see `irdepth_experiments.report.COLUMN_NAMES`).
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
            "frames.npz, figure.png. Without --data the numbers are from the SYNTHETIC "
            "benchmark, not the paper's dataset. With an MS2 directory the MS2 protocol of the "
            "literature applies: every 10th frame of the test lists (day, night, rainy), "
            "predictions median-scaled per image, 1e-3 < gt < 80 m, clamped."))
    ap.add_argument("--preset", default="small", choices=("tiny", "small", "paper"),
                    help="config preset (default: small)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2],
                    help="training seeds; one run per seed and row (default: 0 1 2)")
    ap.add_argument("--data", default=None,
                    help="dataset directory (folder format or MS2): train on it, evaluate on its "
                         "test split; default: the synthetic benchmark")
    ap.add_argument("--format", default="auto", choices=("auto", "folder", "ms2"),
                    help="format of --data (default: auto)")
    ap.add_argument("--eval-frames", type=int, default=EVAL_FRAMES, metavar="N",
                    help=f"synthetic benchmark: frames of its evaluation set, rendered apart from "
                         f"the training data (default: {EVAL_FRAMES})")
    ap.add_argument("--set", dest="overrides", nargs="*", default=[], metavar="KEY=VALUE",
                    help="config overrides for every run (e.g. stage2.steps=100); recorded in "
                         "the outputs and part of the run hash")
    ap.add_argument("--out", default=None,
                    help=f"output folder (default: experiments/results/{table.name})")
    ap.add_argument("--cache", default=DEFAULT_CACHE,
                    help="where datasets, runs and the XLA compilation cache go "
                         "(default: workdir/experiments)")
    ap.add_argument("--quick", action="store_true",
                    help=f"smoke test: tiny preset (32x48 rendered frames), seed 0, 2 steps per phase, "
                         f"{QUICK_EVAL_FRAMES} evaluation frames (overrides --preset/--seeds/"
                         f"--eval-frames; not a result)")
    ap.add_argument("--depth-init", default="random", choices=("random", "pretrained"),
                    help="where every Stage II run's Depth Anything V2 starts: 'random' (random "
                         "weights: what the committed tables used) or 'pretrained' (pretrained "
                         "on the visible images of a separate rendered set, as the paper's "
                         "starts from the released weights; trained once into the cache, with "
                         "its gate measured: experiments/depth_network.py)")
    ap.add_argument("--no-progress", action="store_true", help="no progress bars")
    ap.add_argument("--commit-stage1", action="store_true",
                    help="copy the Stage I models the Stage II rows started from, and the "
                         "table's own Stage I-2 rows' runs (weights without the optimizer state, "
                         "~4 MB each at the small preset, and their evaluations) into "
                         "experiments/pretrained, where a clone's cache takes them instead of "
                         "training them again (~40 minutes each on the protocol, 2 cores)")
    ap.add_argument("--no-committed-runs", action="store_true",
                    help="train every run, also those committed with the repository "
                         "(experiments/pretrained: the pretrained depth network and its blank "
                         "control, about 5 hours on 2 cores), instead of copying them into the "
                         "cache")
    args = ap.parse_args(argv)
    if args.quick:
        args.preset, args.seeds, args.eval_frames = "tiny", [0], QUICK_EVAL_FRAMES
        args.overrides = list(QUICK_OVERRIDES) + list(args.overrides)
    if len(set(args.seeds)) != len(args.seeds):
        ap.error(f"--seeds {args.seeds}: repeated seed")
    if args.eval_frames < 3:
        ap.error(f"--eval-frames {args.eval_frames}: need at least 3 (one per condition)")
    args.out = args.out or os.path.join(RESULTS, table.name)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    return args


def context(preset: str = "small", seeds: Sequence[int] = (0,), quick: bool = False,
            data: str | None = None, overrides: Sequence[str] = (), cache: str = DEFAULT_CACHE,
            progress: bool = False) -> Context:
    """A `Context` without a command line (for notebooks): same caching as the scripts."""
    table = Table("notebook", "notebook", "", (), (), {})
    argv = ["--preset", preset, "--seeds", *map(str, seeds), "--cache", cache, "--set", *overrides]
    argv += (["--data", data] if data else []) + (["--quick"] if quick else [])
    argv += [] if progress else ["--no-progress"]
    return Context(parse_args(table, argv))


# --------------------------------------------------------------------------- a row
def _row_frames(ctx: Context, arm: Arm, record: dict, columns: Sequence[str]) -> dict:
    """The per-frame values of `arm`'s group in one run's evaluation: column -> (F,) float
    (for 'miou': 'seg_cm' -> (M, C, C) confusion matrices)."""
    frames = ctx.frames(record)

    def group(condition: np.ndarray) -> np.ndarray:
        return np.ones(len(condition), bool) if arm.group == "all" else condition == arm.group

    out = {}
    for col in columns:
        if col == "miou":
            out["seg_cm"] = frames["seg_cm"][group(frames["seg_condition"])].astype(np.int32)
            continue
        prefix = "" if arm.key == "stage1" else f"{arm.key}/"
        out[col] = frames[f"{prefix}{col}"][group(frames[f"{prefix}condition"])].astype(np.float32)
    return out


def _row(ctx: Context, table: Table, arm: Arm, seeds: Sequence[int], index: int, frames: dict):
    """The results.json row of `arm` (its per-frame values go into `frames`)."""
    per_seed = {}
    overrides = arm.overrides
    if arm.equal_steps:  # frame counts and lengths do not depend on the seed
        overrides += (f"stage1.steps_i1={ctx.stage1_steps(arm.overrides, seeds[0])}",)
    for seed in seeds:
        ctx.log(f"[{table.name}] {arm.label}: seed {seed}")
        record = ctx.result(arm.kind, overrides, seed)
        result = record[arm.key]
        if arm.group not in result:
            raise SystemExit(f"{arm.label}: no '{arm.group}' frames in the {EVAL_SPLIT} split "
                             f"of {ctx.eval_info['path']} (groups: {sorted(result)})")
        group = result[arm.group]
        per_seed[str(seed)] = {c: group[c] for c in table.columns} | {
            "count": group["count"], "run": record["run"],
            "code": code_versions(os.path.join(ctx.cache, "runs", record["run"])),
            "run_wall_s": round(record["train_wall_s"] + record["eval_wall_s"], 1)}
        for col, values in _row_frames(ctx, arm, record, table.columns).items():
            frames[f"{index}:{seed}:{col}"] = values
    label = arm.label if arm.group == "all" else f"{arm.label} ({arm.group})"
    return {"label": label, "series": arm.label, "group": arm.group, "kind": arm.kind,
            "metrics": arm.key, "overrides": list(overrides), "equal_steps": arm.equal_steps,
            "per_seed": per_seed,
            "summary": {c: summarise([v[c] for v in per_seed.values()]) for c in table.columns}}


def _stage1_models(ctx: Context, table: Table, seeds: Sequence[int]) -> list[dict] | None:
    """The Stage I models the table's Stage II rows started from, each once: [{'seed', 'run',
    'miou' (on the evaluation set; None without labels)}] (`claims.depth_gates` reads the Stage I gate from it);
    None for a table without Stage II rows."""
    overrides = list(dict.fromkeys(a.overrides for a in table.arms if a.kind == "stage2"))
    if not overrides:
        return None
    models = {}
    for seed in seeds:
        for o in overrides:
            record = ctx.result("stage1", o, seed)
            miou = record["stage1"]["all"].get("miou")  # None without segmentation labels
            models[record["run"]] = {"seed": seed, "run": record["run"],
                                     "miou": None if miou is None else round(miou, 4)}
    return list(models.values())


def _commit_stage1(ctx: Context, record: dict) -> None:
    """`commit_run` into `COMMITTED_RUNS` of each long Stage I run of `record`: the models its
    Stage II rows started from (`stage1_models`: with their weights, which a Stage II needs),
    and its own Stage I-2 rows' and `Arm.equal_steps` rows' runs (tables 2, 3, 5, 6: the arms
    a later run would otherwise train again for ~40 minutes each), whose records suffice to
    write the table (a run already committed with its weights, by a depth table, is left as
    it is); says so when there is none."""
    models = {m["run"]: (m["seed"], "a Stage I model that the table's Stage II rows started "
                         "from", "stage1_i2") for m in record["stage1_models"] or ()}
    for row in record["rows"]:
        if row["kind"] == "stage1" or row.get("equal_steps"):
            models |= {v["run"]: (int(seed), f"the Stage I run of its row '{row['label']}'", None)
                       for seed, v in row["per_seed"].items() if v["run"] not in models}
    if not models:
        ctx.log(f"[{record['table']}] --commit-stage1: no long Stage I run in this table (its "
                "rows are Stage I-1 runs of the preset's length, minutes to train), nothing "
                "committed")
    # the command without --out (where the tables went, often a scratch folder on one machine)
    command = re.sub(r" --out (?:'[^']*'|\S+)", "", record["command"])
    for run, (seed, what, weights) in models.items():
        if weights is None and os.path.isdir(os.path.join(COMMITTED_RUNS, run, "checkpoints")):
            continue  # committed with its weights by the table whose Stage II rows start from it
        miou = ctx.evaluation(run)["stage1"]["all"].get("miou")
        kept = ("its last checkpoint's weights (without the optimizer state) and its evaluation"
                if weights else "its records and evaluation, without weights (no Stage II row "
                "starts from it; a cache with another evaluation set trains it again)")
        made_by = (f"# Stage I model (MTSA-UNet), seed {seed}\n\nMade by `{command}` "
                   f"(git {record['git']}, with --commit-stage1): {what}; {kept}. mIoU "
                   f"{'n/a' if miou is None else round(miou, 4)} on the evaluation set "
                   f"({record['eval_data']['path']}).\n")
        path = commit_run(ctx.cache, run, COMMITTED_RUNS, made_by, weights)
        ctx.log(f"[{record['table']}] committed {os.path.relpath(path, REPO)}")


# --------------------------------------------------------------------------- entry point
def main(table: Table, argv: Sequence[str] | None = None) -> dict:
    """Runs (or reuses) every run `table` needs for each seed and writes its outputs.

    Returns the results.json record.
    """
    args = parse_args(table, argv)
    keep_freed_memory()  # as the irdepth command does (irdepth_jax.hostmem)
    started = time.time()
    ctx = Context(args)
    depth_network = None
    if args.depth_init == "pretrained":
        from irdepth_experiments.depth_network import QUICK_RECIPE, RECIPE, pretrained_depth, pretraining_gate

        recipe = QUICK_RECIPE if args.quick else RECIPE
        depth_network = pretraining_gate(ctx, recipe)
        pretrained_depth(ctx, recipe)
    frames: dict[str, np.ndarray] = {}
    rows = [_row(ctx, table, arm, args.seeds, i, frames) for i, arm in enumerate(table.arms)]
    record = {
        "table": table.name, "title": table.title, "synthetic": ctx.data_info["source"] == "synthetic",
        "quick": bool(args.quick),
        "command": " ".join(["python", f"experiments/{table.name}.py"] + [shlex.quote(a) for a in args.argv]),
        "preset": args.preset, "overrides": list(args.overrides), "seeds": list(args.seeds),
        "split": EVAL_SPLIT, "protocol": dataclasses.asdict(ctx.protocol), "data": ctx.data_info,
        "eval_data": ctx.eval_info, "hardware": hardware(), "git": git_commit(),
        "columns": list(table.columns), "rows": rows, "paper": table.paper,
        "depth_init": args.depth_init, "depth_network": depth_network,
        "stage1_models": _stage1_models(ctx, table, args.seeds),
        "wall_s": round(time.time() - started, 1),
        "runs_wall_s": round(sum({v["run"]: v["run_wall_s"] for r in rows
                                  for v in r["per_seed"].values()}.values()), 1),
    }
    record = json.loads(cache_relative(json.dumps(record), ctx.cache))  # names no machine's folders
    write_outputs(table, record, frames, args.out)
    if args.commit_stage1:
        _commit_stage1(ctx, record)
    ctx.log(f"[{table.name}] wrote {args.out}/results.md, results.json, frames.npz, figure.png "
            f"({record['wall_s']:.0f} s)")
    return record
