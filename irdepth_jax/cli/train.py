"""`irdepth train`: one stage (stage1, stage2 or depth) into a workdir."""

from __future__ import annotations

import contextlib
import sys
import time

from irdepth_jax.cli.common import (
    EPILOG_OVERRIDES,
    CliError,
    check_paths,
    checked_overrides,
    compile_cache_flag,
    load_config,
    progress_flag,
    run_options,
    strict_flag,
)


def check(args) -> None:
    """CliError for a path given to train that does not exist."""
    check_paths(args, ("data", "stage1_checkpoint", "config"))


def add_parser(sub) -> None:
    """The `irdepth train` sub-command."""
    from irdepth_jax.config import available_presets

    p = sub.add_parser(
        "train", help="train Stage I (I-1 then I-2), Stage II, or pretrain the depth network",
        description="Train one stage into --workdir (config.json, metrics.jsonl, tb/, "
                    "checkpoints/). stage1 runs I-1 (reconstruction pre-training on the depth "
                    "train split; stage1.i1_frames=all for every frame, as the paper, at the "
                    "cost of test frames in I-1) then I-2 (soft multi-task on the labelled "
                    "frames of seg_split train; data without labels needs "
                    "stage1.seg_labels=synthetic|PATH|none); stage2 fine-tunes Depth Anything "
                    "V2 on the frozen Stage I model's HSV images (--stage1-checkpoint); depth "
                    "trains (or fine-tunes, from depth.checkpoint) Depth Anything V2 on the "
                    "dataset's visible images (rgb/) with SiLog, a depth network that Stage II "
                    "starts from with depth.checkpoint=WORKDIR. Each "
                    "stage prints what it is built from (irdepth: STAGE: ... lines, also "
                    "logged in metrics.jsonl).",
        epilog=EPILOG_OVERRIDES)
    p.add_argument("stage", choices=("stage1", "stage2", "depth"), help="which stage")
    p.add_argument("--preset", default="tiny", choices=available_presets(),
                   help="config preset, irdepth_jax/configs/NAME.py (default tiny)")
    p.add_argument("--config", help="config file: .py defining get_config() / config, or .json "
                                    "(nested like config.json; applied over the preset)")
    p.add_argument("--data", required=True, help="dataset directory (folder format or MS2)")
    p.add_argument("--format", default="auto", choices=("auto", "folder", "ms2"),
                   help="dataset format (default: auto-detect)")
    strict_flag(p)
    p.add_argument("--workdir", required=True, help="run directory")
    resume = p.add_mutually_exclusive_group()
    resume.add_argument("--resume", action="store_true",
                        help="continue the run in --workdir from its last checkpoint (an error "
                             "when it holds none)")
    resume.add_argument("--resume-or-start", action="store_true",
                        help="continue the run in --workdir if it holds one, else start it")
    p.add_argument("--stage1-checkpoint", metavar="DIR",
                   help="stage2: the Stage I workdir (or its checkpoint directory)")
    p.add_argument("--devices", type=int, help="number of devices (default: all)")
    p.add_argument("--parallel", default="auto", choices=("auto", "single", "shard_map", "pmap"),
                   help="data parallelism (default auto: shard_map when several devices)")
    p.add_argument("--steps", type=int, help="optimizer steps per phase (overrides epochs)")
    p.add_argument("--stop-at", type=int, metavar="STEP",
                   help="stop with a checkpoint after STEP steps of the stage (resume later)")
    p.add_argument("--coordinator", metavar="HOST:PORT",
                   help="multi-host: coordinator address (with --num-processes, --process-id)")
    p.add_argument("--num-processes", type=int, help="multi-host: number of processes")
    p.add_argument("--process-id", type=int, help="multi-host: this process's index")
    compile_cache_flag(p)
    progress_flag(p)
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="config overrides")
    p.set_defaults(func=run, check=check)


@contextlib.contextmanager
def _ctrl_c_while_training():
    """Ctrl-C within the block, outside a training loop (which has its own handler), e.g. while
    a stopped phase's last checkpoint is finalised: KeyboardInterrupt as usual, except while a
    checkpoint is being written (ignored with a note, so that it completes: a stop is then under
    way, or Ctrl-C can be pressed again) and once the run is aborting.

    Yields a dict whose 'aborting' is set when this handler raises, or by the caller that caught
    a KeyboardInterrupt: from then on Ctrl-C is ignored while the aborted run is torn down
    (its clean-up, its loader threads), so that it still ends with one line.
    """
    import signal

    from irdepth_jax.train.phase import writing_checkpoint

    state = {"aborting": False, "noted": False}

    def handler(signum, frame):
        if state["aborting"]:
            return
        if writing_checkpoint(frame):
            if not state["noted"]:
                print("irdepth: Ctrl-C while a checkpoint is written: ignored so that it "
                      "completes (press again to stop)", file=sys.stderr, flush=True)
            state["noted"] = True
            return
        state["aborting"] = True
        raise KeyboardInterrupt

    try:
        previous = signal.signal(signal.SIGINT, handler)
    except ValueError:  # not the main thread: Ctrl-C is not ours to handle
        previous = None
    try:
        yield state
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)


def _stage1_settings(cfg, stage1_checkpoint: str, overrides: list[str]):
    """`cfg` with the Stage I model's settings from --stage1-checkpoint (a conflicting
    ``key=value`` refused), and a note naming those that differ from the preset's."""
    from irdepth_jax.config import override_keys
    from irdepth_jax.runs.variables import take_stage1_settings

    cfg, taken = take_stage1_settings(stage1_checkpoint, cfg, override_keys(overrides))
    if taken:
        settings = " ".join(f"{key}={new}" for key, (_, new) in taken.items())
        print(f"irdepth: note: Stage II uses the Stage I model's {settings} (from "
              f"--stage1-checkpoint {stage1_checkpoint})", file=sys.stderr)
    return cfg


def run(args) -> int:
    """Trains a stage in --workdir, holding the workdir's lock (`train.workdir_lock`): a run
    that fails before recording anything leaves no trace; Ctrl-C names the last checkpoint."""
    import jax

    from irdepth_jax.data.source import DataSource
    from irdepth_jax.errors import Interrupted
    from irdepth_jax.train.stages import train_depth, train_stage1, train_stage2
    from irdepth_jax.train.workdir_lock import claim_workdir, holds_run, last_checkpoint

    cfg = load_config(args.preset, args.config, checked_overrides(args.overrides))
    if args.stage != "stage2" and args.stage1_checkpoint:
        raise CliError("--stage1-checkpoint is for train stage2")
    if args.stage1_checkpoint:
        cfg = _stage1_settings(cfg, args.stage1_checkpoint, args.overrides)
    source = DataSource(args.data, args.format, strict=args.strict, raw_bits=cfg.data.raw_bits)
    start = time.perf_counter()
    # one process takes the lock (a multi-host run's processes may share the directory)
    claim = claim_workdir(args.workdir) if jax.process_index() == 0 else contextlib.nullcontext()
    interrupted = False
    with _ctrl_c_while_training() as ctrl_c:
        try:
            with claim:
                held = holds_run(args.workdir)
                if args.resume and not held:
                    raise CliError(f"--resume: workdir {args.workdir} holds no run to continue; "
                                   "pass --resume-or-start to start one there")
                opts = run_options(args, args.workdir,
                                    held if args.resume_or_start else args.resume)
                if args.stage == "stage1":
                    result = train_stage1(cfg, source, opts)
                else:
                    (train_depth if args.stage == "depth" else train_stage2)(cfg, source, opts)
        except KeyboardInterrupt:  # the run's frames (loader threads) end with this block
            ctrl_c["aborting"] = interrupted = True
    if interrupted:
        last = last_checkpoint(args.workdir)
        raise Interrupted(f"interrupted; the last checkpoint is {last[0]} step {last[1]}, "
                          "continue with --resume" if last else
                          "interrupted before the first checkpoint; nothing to continue")
    if args.stage == "stage1":
        print(f"stage1 done ({', '.join(f'{k}: {v} steps' for k, v in result['steps'].items())}"
              f", {time.perf_counter() - start:.0f} s); checkpoints in {args.workdir}/checkpoints")
    else:
        print(f"{args.stage} done ({time.perf_counter() - start:.0f} s); checkpoints in "
              f"{args.workdir}/checkpoints/stage2")
    if args.stage == "depth":
        print(f"start Stage II from this depth network with depth.checkpoint={args.workdir}")
    return 0
