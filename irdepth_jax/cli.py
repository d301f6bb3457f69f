"""The `irdepth` command: synth, train, eval, predict, quickstart.

Every error a user can cause (unknown config key, a directory that is not a dataset, a
checkpoint of another stage or shape, an 8-bit file given to predict, a workdir that already
holds a run) is printed as one line ``irdepth: error: ...`` with exit code 2, before anything is
written. Ctrl-C during training saves a checkpoint and exits with code 130. Set IRDEPTH_DEBUG=1 to
get the traceback instead of the one-line message.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time

EXIT_USAGE = 2
EXIT_INTERRUPTED = 130

EPILOG_OVERRIDES = (
    "Overrides: any number of section.key=value after the options, e.g. "
    "stage1.w_rec=0.2 unet.use_rgg=false stage2.preprocessing=clahe stage2.sky_loss=false "
    "(see irdepth_jax/config.py for every key).")


class CliError(Exception):
    """A one-line user error."""


# --------------------------------------------------------------------------- helpers
def _setup_jax(args) -> None:
    """Persistent XLA compilation cache (repeat runs skip compiling; JAX_COMPILATION_CACHE_DIR
    or ~/.cache/irdepth_jax/xla) and multi-host init."""
    import jax

    if not getattr(args, "no_compile_cache", False) and not jax.config.jax_compilation_cache_dir:
        jax.config.update("jax_compilation_cache_dir", os.path.join(
            os.path.expanduser("~"), ".cache", "irdepth_jax", "xla"))
    if getattr(args, "coordinator", None):
        from irdepth_jax.train.parallel import initialize_distributed
        initialize_distributed(args.coordinator, args.num_processes, args.process_id)


def load_config(preset: str, config_file: str | None, overrides: list[str]):
    """Preset, then a .py (defining `get_config()` or `config`) or .json config, then overrides."""
    from irdepth_jax.config import Config, apply_overrides, from_dict, get_config, to_dict

    cfg = get_config(preset)
    if config_file:
        if not os.path.isfile(config_file):
            raise CliError(f"--config {config_file}: no such file")
        if config_file.endswith(".json"):
            try:
                with open(config_file) as f:
                    doc = json.load(f)
            except json.JSONDecodeError as err:
                raise CliError(f"--config {config_file}: not valid JSON ({err})") from None
            cfg = from_dict(_merge(to_dict(cfg), doc, config_file))
        elif config_file.endswith(".py"):
            scope: dict = {}
            with open(config_file) as f:
                exec(compile(f.read(), config_file, "exec"), scope)
            made = scope["get_config"]() if "get_config" in scope else scope.get("config")
            if not isinstance(made, Config):
                raise CliError(f"--config {config_file}: defines neither get_config() nor "
                               "config returning an irdepth_jax.config.Config")
            cfg = made
        else:
            raise CliError(f"--config {config_file}: expected a .py or .json file")
    return apply_overrides(cfg, overrides)


def _merge(base: dict, doc: dict, where: str, prefix: str = "") -> dict:
    out = dict(base)
    for key, value in doc.items():
        if key not in base:
            raise CliError(f"--config {where}: unknown config key {prefix + key!r}")
        if isinstance(base[key], dict):
            if not isinstance(value, dict):
                raise CliError(f"--config {where}: {prefix + key!r} is a section")
            out[key] = _merge(base[key], value, where, prefix + key + ".")
        else:
            out[key] = value
    return out


def _overrides(items: list[str]) -> list[str]:
    for item in items:
        if "=" not in item:
            raise CliError(f"unexpected argument {item!r} (overrides are key=value)")
    return items


def _parse_size(text: str) -> tuple[int, int]:
    match = re.fullmatch(r"(\d+)[xX](\d+)", text)
    if not match:
        raise argparse.ArgumentTypeError(f"size {text!r} is not HxW, e.g. 64x80")
    return int(match.group(1)), int(match.group(2))


def _run_options(args, workdir: str):
    from irdepth_jax.train.loop import RunOptions

    return RunOptions(workdir=workdir, resume=args.resume, parallel=args.parallel,
                      devices=args.devices, steps=args.steps, stop_at=args.stop_at,
                      progress=not args.no_progress,
                      stage1_checkpoint=getattr(args, "stage1_checkpoint", None))


# --------------------------------------------------------------------------- commands
def cmd_synth(args) -> int:
    from irdepth_jax.data.folder import write_synthetic_dataset

    height, width = args.size
    path = write_synthetic_dataset(args.out, args.n, args.labeled, height, width, seed=args.seed,
                                   progress=not args.no_progress, overwrite=args.overwrite)
    print(f"wrote {args.n} frames ({args.labeled} labelled, {height}x{width}) to {path}")
    return 0


def cmd_train(args) -> int:
    from irdepth_jax.train.loop import DataSource, train_stage1, train_stage2

    cfg = load_config(args.preset, args.config, _overrides(args.overrides))
    if args.stage == "stage1" and args.stage1_checkpoint:
        raise CliError("--stage1-checkpoint is for train stage2")
    source = DataSource(args.data, args.format)
    opts = _run_options(args, args.workdir)
    start = time.perf_counter()
    if args.stage == "stage1":
        result = train_stage1(cfg, source, opts)
        print(f"stage1 done ({', '.join(f'{k}: {v} steps' for k, v in result['steps'].items())}"
              f", {time.perf_counter() - start:.0f} s); checkpoints in {args.workdir}/checkpoints")
    else:
        train_stage2(cfg, source, opts)
        print(f"stage2 done ({time.perf_counter() - start:.0f} s); checkpoints in "
              f"{args.workdir}/checkpoints/stage2")
    return 0


def cmd_eval(args) -> int:
    from irdepth_jax.evaluate import evaluate_run

    path = args.checkpoint or args.workdir
    result = evaluate_run(path, args.data, args.split, args.format, out_dir=args.out,
                          overrides=_overrides(args.overrides), stride=args.stride)
    print(result["markdown"])
    out = args.out or path
    print(f"tables written to {out}/eval_{args.split}.md and .json")
    return 0


def cmd_predict(args) -> int:
    from irdepth_jax.evaluate import predict_files

    written = predict_files(args.checkpoint, args.inputs, args.out, _overrides(args.overrides))
    print(f"wrote {len(written)} files to {args.out}")
    return 0


def cmd_quickstart(args) -> int:
    """synth -> stage1 (I-1, I-2) -> stage2 -> eval on the tiny preset, with before/after."""
    from irdepth_jax.data.folder import write_synthetic_dataset
    from irdepth_jax.evaluate import evaluate_run, evaluate_stage1, evaluate_stage2
    from irdepth_jax.train.loop import (DataSource, RunOptions, init_depth, init_unet,
                                        make_parallel, train_stage1, train_stage2)

    work = args.workdir
    if os.path.isdir(work) and os.listdir(work):
        raise CliError(f"--workdir {work} exists and is not empty; choose another directory")
    cfg = load_config(args.preset, None, _overrides(args.overrides))
    start = time.perf_counter()
    d = cfg.data
    data = os.path.join(work, "data")
    print(f"[1/4] synthetic dataset: {d.num_frames} frames ({d.num_labeled} labelled), "
          f"{d.height}x{d.width} -> {data}")
    write_synthetic_dataset(data, d.num_frames, d.num_labeled, d.height, d.width, seed=cfg.seed,
                            progress=not args.no_progress)
    source = DataSource(data)
    common = dict(devices=args.devices, progress=not args.no_progress)
    print("[2/4] Stage I: I-1 reconstruction pre-training, I-2 soft multi-task")
    s1 = train_stage1(cfg, source, RunOptions(os.path.join(work, "stage1"), **common))
    print("[3/4] Stage II: Depth Anything V2 on the HSV pseudo-RGB")
    train_stage2(cfg, source, RunOptions(os.path.join(work, "stage2"), **common,
                                              stage1_checkpoint=os.path.join(work, "stage1")))
    print("[4/4] evaluation on the test split")
    dp = make_parallel(RunOptions(work, **common), cfg.stage2.batch_size)
    dataset, test = source.frames("test")
    before1 = evaluate_stage1(cfg, init_unet(cfg), dataset, test, dp)["all"]
    before2 = evaluate_stage2(cfg, s1["unet"], init_depth(cfg), dataset, test, dp)["all"]
    result = evaluate_run(os.path.join(work, "stage2"), data, "test", dp=dp)
    after1, after2 = result["stage1"]["all"], result["stage2"]["all"]
    print(result["markdown"])
    print("untrained -> trained (test split):")
    print(f"  Stage I  PSNR {before1['psnr']:.2f} -> {after1['psnr']:.2f} dB, "
          f"SSIM {before1['ssim']:.3f} -> {after1['ssim']:.3f}, "
          f"mIoU {before1['miou']:.3f} -> {after1['miou']:.3f}")
    print(f"  Stage II d1 {before2['d1']:.3f} -> {after2['d1']:.3f}, "
          f"AbsRel {before2['abs_rel']:.3f} -> {after2['abs_rel']:.3f}")
    print(f"quickstart finished in {time.perf_counter() - start:.0f} s; data, runs and tables "
          f"({work}/stage2/eval_test.md) are in {work}")
    return 0


# --------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="irdepth",
        description="Monocular depth from raw 14-bit thermal frames: MTSA-UNet -> HSV -> "
                    "Depth Anything V2 (JAX/Flax).",
        epilog="Start with `irdepth quickstart`; `irdepth COMMAND --help` for each command.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def progress_flag(p):
        p.add_argument("--no-progress", action="store_true", help="no progress bars")

    def compile_cache_flag(p):
        p.add_argument("--no-compile-cache", action="store_true",
                       help="do not use the persistent XLA compilation cache")

    p = sub.add_parser("synth", help="render a synthetic LWIR dataset (our folder format)",
                       description="Render procedural LWIR street scenes (raw 14-bit, 8-bit, RGB, "
                                   "LiDAR-like depth, labels) into a folder dataset.")
    p.add_argument("--out", required=True, help="dataset directory (absent or empty)")
    p.add_argument("--n", type=int, default=96, help="number of frames (default 96)")
    p.add_argument("--labeled", type=int, default=48,
                   help="frames with segmentation labels (default 48)")
    p.add_argument("--size", type=_parse_size, default=(64, 80), metavar="HxW",
                   help="frame size, e.g. 256x320 (default 64x80)")
    p.add_argument("--seed", type=int, default=0, help="dataset seed (default 0)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing dataset")
    progress_flag(p)
    p.set_defaults(func=cmd_synth)

    p = sub.add_parser(
        "train", help="train Stage I (I-1 then I-2) or Stage II",
        description="Train one stage into --workdir (config.json, metrics.jsonl, tb/, "
                    "checkpoints/). stage1 runs I-1 (reconstruction pre-training, all frames) "
                    "then I-2 (soft multi-task, labelled frames); stage2 fine-tunes Depth "
                    "Anything V2 on the frozen Stage I model's HSV images (--stage1-checkpoint).",
        epilog=EPILOG_OVERRIDES)
    p.add_argument("stage", choices=("stage1", "stage2"), help="which stage")
    p.add_argument("--preset", default="tiny", choices=("tiny", "small", "paper"),
                   help="config preset (default tiny)")
    p.add_argument("--config", help="config file: .py defining get_config() / config, or .json "
                                    "(nested like config.json; applied over the preset)")
    p.add_argument("--data", required=True, help="dataset directory (folder format or MS2)")
    p.add_argument("--format", default="auto", choices=("auto", "folder", "ms2"),
                   help="dataset format (default: auto-detect)")
    p.add_argument("--workdir", required=True, help="run directory")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --workdir from its last checkpoint")
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
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("eval", help="metric tables of a trained run (Markdown + JSON)",
                       description="Evaluate a run on a split: depth d1 d2 d3 AbsRel SqRel RMSE "
                                   "RMSE-log log10 SiLog (Stage II) and PSNR SSIM entropy mIoU "
                                   "(Stage I), overall and per condition.")
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--workdir", help="a run directory (its latest stage is evaluated)")
    where.add_argument("--checkpoint", help="a checkpoint directory")
    p.add_argument("--data", required=True, help="dataset directory (folder format or MS2)")
    p.add_argument("--format", default="auto", choices=("auto", "folder", "ms2"),
                   help="dataset format (default: auto-detect)")
    p.add_argument("--split", default="test", help="split to evaluate (default test)")
    p.add_argument("--stride", type=int, default=1, metavar="N",
                   help="evaluate every N-th frame (MS2: of each sequence; the MS2 test "
                        "protocol is --stride 10; default 1: all frames)")
    p.add_argument("--out", help="where eval_<split>.md / .json go (default: the run directory)")
    compile_cache_flag(p)
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE",
                   help="config overrides (e.g. data.max_depth=50)")
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("predict", help="depth maps from raw 14-bit frames",
                       description="Run a trained model on raw 14-bit frames (16-bit PNG / TIFF "
                                   "or .npy files, or folders of them). Writes NAME_depth.png "
                                   "(16-bit, metres x 256), NAME_depth_color.png and the "
                                   "pseudo-RGB / HSV images.")
    p.add_argument("--checkpoint", required=True,
                   help="a Stage II (or Stage I) workdir or checkpoint directory")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="raw frames or folders")
    compile_cache_flag(p)
    p.set_defaults(func=cmd_predict, overrides=[])

    p = sub.add_parser("quickstart", help="synth -> Stage I -> Stage II -> eval on a tiny model",
                       description="The whole pipeline on synthetic data with the tiny preset: "
                                   "render a dataset, train Stage I (I-1, I-2) and Stage II, "
                                   "print the test tables and the untrained -> trained change. "
                                   "A few minutes on a laptop CPU.")
    p.add_argument("--workdir", default="irdepth_quickstart",
                   help="new directory for data, runs and tables (default ./irdepth_quickstart)")
    p.add_argument("--preset", default="tiny", choices=("tiny", "small", "paper"),
                   help="config preset (default tiny)")
    p.add_argument("--devices", type=int, help="number of devices (default: all)")
    compile_cache_flag(p)
    progress_flag(p)
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="config overrides")
    p.set_defaults(func=cmd_quickstart)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `irdepth` console script; returns the exit code."""
    parser = build_parser()
    # Overrides may come anywhere after the command (argparse would only take them in one run).
    args, extra = parser.parse_known_args(argv)
    unknown = [a for a in extra if a.startswith("-") or "=" not in a
               or not hasattr(args, "overrides") or args.command == "predict"]
    if unknown:
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    if extra:
        args.overrides = list(args.overrides) + extra
    from irdepth_jax.data.folder import DatasetError
    from irdepth_jax.train.checkpoint import CheckpointError
    from irdepth_jax.train.loop import Interrupted, RunError

    try:
        _setup_jax(args)
        return args.func(args)
    except Interrupted as stop:
        print(f"irdepth: {stop}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except KeyboardInterrupt:
        print("irdepth: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (CliError, RunError, CheckpointError, DatasetError, ValueError) as err:
        if os.environ.get("IRDEPTH_DEBUG"):
            raise
        message = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        print(f"irdepth: error: {message}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
