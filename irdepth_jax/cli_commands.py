"""The `irdepth` commands' implementations (`cmd_<name>(args) -> exit code`, `args` from
`irdepth_jax.cli.build_parser`) and how a run's config is read (`load_config`). A user's error
is a `CliError` (one line; `irdepth_jax.cli.main` prints it)."""

from __future__ import annotations

import contextlib
import json
import os
import sys
import time

from irdepth_jax.errors import IrdepthError, counted


class CliError(IrdepthError):
    """A one-line user error."""


# --------------------------------------------------------------------------- config
def load_config(preset: str, config_file: str | None, overrides: list[str]):
    """Preset, then a .py (defining `get_config()` or `config`) or .json config, then overrides."""
    from irdepth_jax.config import Config, apply_overrides, from_dict, get_config, to_dict, upgrade_dict

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
            if not isinstance(doc, dict):
                raise CliError(f"--config {config_file}: expected a JSON object (nested like "
                               "config.json)")
            doc = upgrade_dict(doc, where=f"--config {config_file}")
            cfg = from_dict(_merge(to_dict(cfg), doc, config_file))
        elif config_file.endswith(".py"):
            made = _run_config_file(config_file)
            if not isinstance(made, Config):
                raise CliError(f"--config {config_file}: defines neither get_config() nor "
                               "config returning an irdepth_jax.config.Config")
            cfg = made
        else:
            raise CliError(f"--config {config_file}: expected a .py or .json file")
    return apply_overrides(cfg, overrides)


def _run_config_file(path: str):
    """What a .py config file makes: its `get_config()`, else its `config` (else None).

    Raises CliError naming the file and line for a syntax error, or for an exception raised
    while the file runs or get_config() is called.
    """
    import traceback

    from irdepth_jax.config import renamed_hint

    scope: dict = {}
    try:
        with open(path) as f:
            exec(compile(f.read(), path, "exec"), scope)
        return scope["get_config"]() if "get_config" in scope else scope.get("config")
    except SyntaxError as err:
        raise CliError(f"--config {path}: line {err.lineno}: syntax error ({err.msg})") from None
    except SystemExit as err:  # sys.exit() in the file would end irdepth without a word
        raise CliError(f"--config {path}: the file called sys.exit({err.code!r}) while it ran; "
                       "a config file defines get_config() or config") from None
    except Exception as err:  # noqa: BLE001 - any error of the user's file, as one line
        lines = [f.lineno for f in traceback.extract_tb(err.__traceback__) if f.filename == path]
        where = f"line {lines[-1]}: " if lines else ""
        text = str(err).strip().splitlines()
        raise CliError(f"--config {path}: {where}{type(err).__name__}"
                       + (f": {text[0]}" if text else "") + renamed_hint(str(err))) from None


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


def _check_out_dir(path: str | None) -> None:
    """CliError when --out names an existing file (the outputs go into a directory)."""
    if path and os.path.exists(path) and not os.path.isdir(path):
        raise CliError(f"--out {path}: exists and is not a directory")


PATH_FLAGS = {"train": ("data", "stage1_checkpoint", "config"),
              "eval": ("checkpoint", "workdir", "data"),
              "predict": ("checkpoint", "inputs"),
              "export": ("checkpoint", "sample")}
"""The flags of each command that name paths which must exist (`check_usage`)."""


def check_usage(args) -> None:
    """CliError (one line naming the flag) for a path that must exist and does not, an --out
    that is a file, or flags that do not go together: checked before anything is imported or
    loaded, so that a usage error is reported within a second, not after JAX and the model."""
    if args.command == "synth":
        _check_synth(args)
    if args.command in ("eval", "predict"):
        _check_out_dir(args.out)
    for flag in PATH_FLAGS.get(args.command, ()):
        value = getattr(args, flag, None)
        for path in value if isinstance(value, list) else [value]:
            if path is not None and not os.path.exists(path):
                where = "" if flag == "inputs" else f"--{flag.replace('_', '-')} "
                raise CliError(f"{where}{path}: no such file or directory")
    if args.command == "predict" and args.pointcloud != (args.intrinsics is not None):
        raise CliError("--pointcloud needs --intrinsics fx,fy,cx,cy (or a calibration file)"
                       if args.pointcloud else "--intrinsics is for --pointcloud")
    if args.command == "predict" and args.depth_png and not args.video:
        raise CliError("--depth-png adds per-frame depth PNGs to --video (without --video "
                       "every frame's PNGs are written anyway)")


def _run_options(args, workdir: str, resume: bool):
    from irdepth_jax.train.phase import RunOptions

    return RunOptions(workdir=workdir, resume=resume, parallel=args.parallel,
                      devices=args.devices, steps=args.steps, stop_at=args.stop_at,
                      progress=not args.no_progress,
                      stage1_checkpoint=getattr(args, "stage1_checkpoint", None))


# --------------------------------------------------------------------------- commands
def _check_synth(args) -> None:
    """CliError for `irdepth synth` counts that do not go together or an --out that holds
    files (without --overwrite); --labeled defaults to half of --n."""
    if args.n < 1:
        raise CliError(f"--n {args.n}: render at least one frame")
    if args.labeled is None:
        args.labeled = args.n // 2
    if not 0 <= args.labeled <= args.n:
        raise CliError(f"--labeled {args.labeled}: choose 0 to --n ({args.n})")
    if os.path.isdir(args.out) and os.listdir(args.out) and not args.overwrite:
        raise CliError(f"--out {args.out}: directory exists and is not empty; choose another "
                       "path, or pass --overwrite to replace the dataset")


def cmd_synth(args) -> int:
    from irdepth_jax.data.synthetic_dataset import write_synthetic_dataset

    height, width = args.size
    path = write_synthetic_dataset(args.out, args.n, args.labeled, height, width, seed=args.seed,
                                   progress=not args.no_progress, overwrite=args.overwrite,
                                   scenes=args.scenes)
    print(f"wrote {counted(args.n, 'frame')} ({args.labeled} labelled, {height}x{width}, "
          f"{args.scenes} scenes) to {path}")
    return 0


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


def cmd_train(args) -> int:
    """Trains a stage in --workdir, holding the workdir's lock (`train.workdir_lock`): a run
    that fails before recording anything leaves no trace; Ctrl-C names the last checkpoint."""
    import jax

    from irdepth_jax.data.source import DataSource
    from irdepth_jax.errors import Interrupted
    from irdepth_jax.train.stages import train_depth, train_stage1, train_stage2
    from irdepth_jax.train.workdir_lock import claim_workdir, holds_run, last_checkpoint

    cfg = load_config(args.preset, args.config, _overrides(args.overrides))
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
                opts = _run_options(args, args.workdir,
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


def cmd_eval(args) -> int:
    from irdepth_jax.evaluate import evaluate_run, nonfinite_warning

    path = args.checkpoint or args.workdir
    result = evaluate_run(path, args.data, args.split, args.format, out_dir=args.out,
                          overrides=_overrides(args.overrides), stride=args.stride,
                          align=args.align,
                          strict=args.strict, gt=args.gt)
    print(result["markdown"])
    for line in result["warnings"]:
        print(f"irdepth: WARNING: {line}", file=sys.stderr)
    warning = nonfinite_warning(result)
    if warning:
        print(f"irdepth: WARNING: {warning}", file=sys.stderr)
    out = args.out or path
    print(f"tables written to {out}/eval_{args.split}.md and .json")
    return 0


EXIT_SKIPPED = 1
"""`irdepth predict`'s exit status when it skipped input files it could not read as raw frames
(the rest predicted and written)."""


def cmd_predict(args) -> int:
    from irdepth_jax.predict import predict_files

    result = predict_files(args.checkpoint, args.inputs, args.out, _overrides(args.overrides),
                           raw_bits=args.raw_bits, pattern=args.glob, strict=args.strict,
                           batch_size=args.batch_size, video=args.video,
                           depth_png_frames=args.depth_png, fps=args.fps,
                           progress=not args.no_progress, intrinsics=args.intrinsics,
                           depth_range=args.depth_range, cmap=args.cmap,
                           recursive=args.recursive, topic=args.topic)
    written = result.written
    videos = sum(f.endswith(".mp4") for f in written)
    what = (f"{counted(videos, 'video')} and {counted(len(written) - videos, 'file')}"
            if args.video else counted(len(written), "file"))
    if not args.video and not any("_depth" in os.path.basename(f) for f in written):
        what += " (pseudo-RGB and HSV images, no depth: a Stage I model)"
    print(f"wrote {what} to {args.out}")
    return EXIT_SKIPPED if result.unreadable else 0


def cmd_export(args) -> int:
    """Writes the Stage II model as one ONNX / StableHLO file (+ FILE.json), checked against
    the JAX pipeline (`irdepth_jax.export`)."""
    from irdepth_jax.export import export_model, metadata_path

    meta = export_model(args.checkpoint, args.format, args.height, args.width, args.batch,
                        args.out, sample=args.sample)
    check = meta["check"]
    kind = "synthetic frame" if args.sample is None else "sample frame"
    print(f"max |{args.format} - JAX| = {check['max_abs_diff']:.3g} m on "
          f"{counted(check['frames'], kind)} (tolerance "
          f"{check['tolerance']:.3g} m)")
    print(f"wrote {args.out} and {metadata_path(args.out)}")
    return 0


def cmd_quickstart(args) -> int:
    """synth -> stage1 (I-1, I-2) -> stage2 -> eval (`workflow.train_and_evaluate`), with the
    untrained -> trained change."""
    from irdepth_jax.workflow import improvement_lines, train_and_evaluate

    work = args.workdir
    if os.path.isdir(work) and os.listdir(work):
        raise CliError(f"--workdir {work} exists and is not empty; choose another directory")
    cfg = load_config(args.preset, None, _overrides(args.overrides))
    result = train_and_evaluate(cfg, work, devices=args.devices, progress=not args.no_progress)
    print(result["tables"])
    print("\n".join(improvement_lines(result)))
    print(f"quickstart finished in {result['seconds']:.0f} s; data, runs and tables "
          f"({work}/stage2/eval_test.md) are in {work}")
    print("\n".join(quickstart_next_steps(work, result["config"])))
    return 0


def quickstart_next_steps(work: str, cfg) -> list[str]:
    """What the quickstart made, and the commands that train a model for real frames."""
    d = cfg.data
    return [
        f"What it made: {work}/data ({d.num_frames} synthetic frames of {d.height}x{d.width}), "
        f"{work}/stage1 and {work}/stage2: a {cfg.name} model trained on synthetic frames, its "
        "depth network from random weights. It shows the pipeline runs; its depth on real "
        "camera frames means nothing (predict and eval warn so).",
        "Next, a model for real frames: MS2 (or a folder dataset, docs/data.md: --data "
        "FOLDER) and the released Depth Anything V2 weights "
        "(depth_anything_v2_metric_vkitti_vits.pth):",
        "  irdepth train stage1 --preset paper --data MS2_ROOT --workdir runs/s1 "
        "stage1.seg_labels=synthetic",
        "  irdepth train stage2 --preset paper --data MS2_ROOT --workdir runs/s2 "
        "--stage1-checkpoint runs/s1 depth.checkpoint=depth_anything_v2_metric_vkitti_vits.pth",
        "  irdepth eval --workdir runs/s2 --data MS2_ROOT --split test_day --stride 10",
        "  irdepth predict --checkpoint runs/s2 --out preds MS2_ROOT/sync_data/SEQ/thr/img_left"]
