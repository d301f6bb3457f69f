"""The `irdepth` command: synth, train, eval, predict, export, quickstart.

Every error a user can cause (unknown config key, a directory that is not a dataset, a
checkpoint of another stage or shape, an 8-bit file given to predict, a workdir that already
holds a run) is printed as one line ``irdepth: error: ...`` with exit code 2, before anything is
written. Only the package's own errors (`irdepth_jax.errors.IrdepthError` and its subclasses)
are reported so; any other exception is a bug and ends with its traceback. Ctrl-C during
training saves a checkpoint and exits with code 130. `irdepth predict` exits with code 1 when
it skipped input files it could not read (the others are written). Set IRDEPTH_DEBUG=1 to
get the traceback instead of the one-line message.

This module is the parser (`build_parser`) and the entry point (`main`); the commands are
implemented in `irdepth_jax.cli_commands`.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import sys
import warnings

from irdepth_jax.cli_commands import (
    EXIT_SKIPPED,
    CliError,
    check_usage,
    cmd_eval,
    cmd_export,
    cmd_predict,
    cmd_quickstart,
    cmd_synth,
    cmd_train,
    load_config,
)

__all__ = ["EXIT_INTERRUPTED", "EXIT_SKIPPED", "EXIT_USAGE", "CliError", "build_parser", "load_config", "main"]

EXIT_USAGE = 2
EXIT_INTERRUPTED = 130

EPILOG_OVERRIDES = (
    "Overrides: any number of section.key=value after the options, e.g. "
    "stage1.w_rec=0.2 unet.use_rgg=false stage2.preprocessing=clahe stage2.sky_loss=false "
    "(see irdepth_jax/config.py for every key).")


# --------------------------------------------------------------------------- helpers
def _setup_jax(args) -> None:
    """Freed host memory kept for reuse (`hostmem.keep_freed_memory`; IRDEPTH_DEFAULT_MALLOC=1
    leaves malloc alone), persistent XLA compilation cache (repeat runs skip compiling;
    JAX_COMPILATION_CACHE_DIR or ~/.cache/irdepth_jax/xla; off with --no-compile-cache) and
    multi-host init."""
    from irdepth_jax.compile_cache import default_cache_dir, enable_compilation_cache
    from irdepth_jax.hostmem import keep_freed_memory

    keep_freed_memory()

    enable_compilation_cache(None if getattr(args, "no_compile_cache", False)
                             else default_cache_dir())
    if getattr(args, "coordinator", None):
        from irdepth_jax.train.parallel import initialize_distributed
        initialize_distributed(args.coordinator, args.num_processes, args.process_id)


def _parse_size(text: str) -> tuple[int, int]:
    match = re.fullmatch(r"(\d+)[xX](\d+)", text)
    if not match:
        raise argparse.ArgumentTypeError(f"size {text!r} is not HxW, e.g. 64x80")
    return int(match.group(1)), int(match.group(2))


@contextlib.contextmanager
def _one_line_warnings():
    """Within the block, each distinct `DatasetWarning` (e.g. MS2 sequences not on disk) and
    `DeprecatedKeyWarning` (a config key under its old name) is printed once as one line
    ``irdepth: warning: ...`` on stderr; other warnings as usual."""
    from irdepth_jax.config import DeprecatedKeyWarning
    from irdepth_jax.data.folder import DatasetWarning

    ours = (DatasetWarning, DeprecatedKeyWarning)
    with warnings.catch_warnings():
        for category in ours:
            warnings.simplefilter("default", category)
        show = warnings.showwarning

        def one_line(message, category, *rest, **kwargs):
            if not issubclass(category, ours):
                return show(message, category, *rest, **kwargs)
            print(f"irdepth: warning: {message}", file=sys.stderr, flush=True)

        warnings.showwarning = one_line
        yield


# --------------------------------------------------------------------------- parser
def _progress_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


def _strict_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument("--strict", action="store_true",
                   help="MS2: fail when a sequence named by a split list is not on disk, or a "
                        "thermal frame has no depth file (default: read what is present, warn "
                        "once per split)")


def _compile_cache_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument("--no-compile-cache", action="store_true",
                   help="do not use the persistent XLA compilation cache")


def _add_synth(sub) -> None:
    """The `irdepth synth` sub-command."""
    p = sub.add_parser("synth", help="render a synthetic LWIR dataset (our folder format)",
                       description="Render procedural LWIR street scenes (raw 14-bit, 8-bit, RGB, "
                                   "LiDAR-like depth, labels) into a folder dataset.")
    p.add_argument("--out", required=True, help="dataset directory (absent or empty)")
    p.add_argument("--n", type=int, default=96, help="number of frames (default 96)")
    p.add_argument("--labeled", type=int, default=None,
                   help="frames with segmentation labels (default: half of --n)")
    p.add_argument("--size", type=_parse_size, default=(64, 80), metavar="HxW",
                   help="frame size, e.g. 256x320 (default 64x80)")
    p.add_argument("--seed", type=int, default=0, help="dataset seed (default 0)")
    p.add_argument("--scenes", choices=("street", "varied"), default="street",
                   help="scene distribution: 'street' (one straight street, a level camera at "
                        "~1.5 m; the default and what the committed results used) or 'varied' "
                        "(camera height 1.3-1.7 m, horizon row and roll per frame, one field of "
                        "view; crossings, open ground, close obstacles)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing dataset")
    _progress_flag(p)
    p.set_defaults(func=cmd_synth)


def _add_train(sub) -> None:
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
    _strict_flag(p)
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
    _compile_cache_flag(p)
    _progress_flag(p)
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="config overrides")
    p.set_defaults(func=cmd_train)


def _add_eval(sub) -> None:
    """The `irdepth eval` sub-command."""
    from irdepth_jax.config import MS2_DEPTH_LABELS

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
    _strict_flag(p)
    p.add_argument("--stride", type=int, default=1, metavar="N",
                   help="evaluate frames[0:-1:N] of the split's frame list (all sequences "
                        "concatenated), as the official MS2 loader does; the MS2 test protocol "
                        "is --stride 10 (default 1: every frame)")
    p.add_argument("--align", default="auto", choices=("auto", "none", "median", "scale_shift"),
                   help="per-image alignment of the predicted depth before the metrics: "
                        "median scaling or least-squares scale and shift (default auto: none "
                        "for a metric model, median for a relative one, depth.metric=false, "
                        "which refuses none); predictions are then clamped to "
                        "[data.min_depth, data.max_depth]")
    p.add_argument("--gt", metavar="NAME", choices=tuple(MS2_DEPTH_LABELS),
                   help="MS2: the depth label version to compare with: "
                        f"{', '.join(MS2_DEPTH_LABELS)} (default depth_filtered; published "
                        "numbers differ by about 0.04 AbsRel between them)")
    p.add_argument("--out", help="where eval_<split>.md / .json go (default: the run directory)")
    _compile_cache_flag(p)
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE",
                   help="config overrides (e.g. data.max_depth=50)")
    p.set_defaults(func=cmd_eval)


def _add_predict(sub) -> None:
    """The `irdepth predict` sub-command."""
    from irdepth_jax.predict_settings import DEFAULT_BATCH, DEFAULT_FPS


    p = sub.add_parser("predict", help="depth maps from raw thermal frames",
                       description="Run a trained model on raw thermal frames: 16-bit PNG, "
                                   "16-bit TIFF (multi-page: one frame per page), .npy ((H, W) "
                                   "or (N, H, W)), FLIR .fff / .seq (needs the flir extra: "
                                   "pip install 'irdepth_jax[flir]'), FLIR radiometric JPEG "
                                   "and DJI R-JPEG (.jpg), ROS 1 / ROS 2 bags (--topic), or "
                                   "folders of them. "
                                   "Writes NAME_depth.png (16-bit, metres x 256), "
                                   "NAME_depth_color.png and the pseudo-RGB / HSV images "
                                   "(a stack's frames are NAME_p0000, NAME_p0001, ...); "
                                   "frames of the same name from different inputs go to "
                                   "sub-folders of --out named after their folders. "
                                   "Each file is written whole or not at all: a failed write "
                                   "(e.g. a full disk) stops with an error naming the file. "
                                   "A checkpoint with NaN / inf weights is refused, and a "
                                   "frame whose prediction is NaN / inf stops the run with an "
                                   "error naming its input file before its files are written "
                                   "(a NaN depth is never written as 0, 'no depth'); the "
                                   "frames before it are complete. With --video, each "
                                   "sequence (a folder of frames, a multi-page TIFF, an "
                                   "(N, H, W) .npy, a FLIR .seq) becomes NAME.mp4: raw "
                                   "tone-mapped | pseudo-RGB of the HSV image | coloured "
                                   "depth, side by side (needs pip install "
                                   "'irdepth_jax[video]').")
    p.add_argument("--checkpoint", required=True,
                   help="a Stage II (or Stage I) workdir or checkpoint directory")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--raw-bits", type=int, choices=(14, 16),
                   help="bit depth of the frames' counts (default: the model's data.raw_bits); "
                        "a frame with a count over it is skipped, never clipped (see --strict)")
    p.add_argument("--glob", metavar="PATTERN",
                   help="in folders, read the files matching PATTERN, e.g. '*_thr.png' "
                        "(default: every .png .tif .tiff .npy .fff .seq .jpg .jpeg .bag file and ROS 2 "
                        "bag folder)")
    p.add_argument("--strict", action="store_true",
                   help="stop at the first file that is not a raw thermal frame of the run's "
                        "bit depth: an 8-bit or colour file in a folder, counts over --raw-bits "
                        "(never clipped), an unreadable file (default: skip it; the 8-bit and "
                        "colour ones are named in one line before the run, the others with "
                        f"their reasons in one line at its end, and the exit status is then "
                        f"{EXIT_SKIPPED})")
    p.add_argument("--topic", metavar="TOPIC",
                   help="ROS 1 / ROS 2 bags: the thermal image topic, e.g. /thermal/image_raw "
                        "(mono16 sensor_msgs/Image; default: the bag's one image topic; needs "
                        "pip install 'irdepth_jax[rosbag]')")
    p.add_argument("--recursive", "-r", action="store_true",
                   help="read the folders' sub-folders too; the outputs mirror the tree under "
                        "--out")
    p.add_argument("--batch-size", type=int, default=None, metavar="N",
                   help=f"frames per model call (default {DEFAULT_BATCH['cpu']} on a CPU, the "
                        f"fastest measured there; {DEFAULT_BATCH['gpu']} on a GPU); frames are grouped "
                        "by size, and the outputs do not depend on N")
    p.add_argument("--video", action="store_true",
                   help="write one MP4 per input sequence instead of per-frame images")
    p.add_argument("--depth-png", action="store_true",
                   help="with --video: also write each frame's 16-bit NAME_depth.png")
    p.add_argument("--fps", type=float, default=DEFAULT_FPS,
                   help=f"frame rate of the videos (default {DEFAULT_FPS:g})")
    p.add_argument("--depth-range", metavar="auto|MIN:MAX",
                   help="depth range of the coloured depth image and its colour bar, in metres "
                        "(default 0:data.max_depth; auto: each frame's own, the default for a "
                        "relative-depth model)")
    p.add_argument("--cmap", default="turbo",
                   help="matplotlib colour map of the coloured depth (default turbo: near red, "
                        "far blue)")
    p.add_argument("--pointcloud", action="store_true",
                   help="also write NAME.ply per frame: one point per pixel with depth, "
                        "coloured by the pseudo-RGB image (needs --intrinsics)")
    p.add_argument("--intrinsics", metavar="fx,fy,cx,cy|FILE",
                   help="the thermal camera's intrinsics in pixels, or a calibration file "
                        "(MS2's calib.npy: its K_thrL; or a .npy 3x3 matrix)")
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="raw frames or folders")
    _compile_cache_flag(p)
    _progress_flag(p)
    p.set_defaults(func=cmd_predict, overrides=[])


def _add_export(sub) -> None:
    """The `irdepth export` sub-command."""
    p = sub.add_parser("export", help="a Stage II model as one ONNX or StableHLO file",
                       description="Export raw (N, H, W) uint16 counts -> depth (N, H, W) "
                                   "float32 metres (the whole HSV pipeline, variables as "
                                   "constants) for one fixed input shape, and FILE.json beside "
                                   "it (shapes, dtypes, raw bit depth, max depth, class names, "
                                   "config). The artifact is checked against the JAX pipeline "
                                   "on sample frames and refused when they differ by more than "
                                   "1e-4 x max depth. onnx needs pip install "
                                   "'irdepth_jax[export]'.")
    p.add_argument("--checkpoint", required=True,
                   help="a Stage II workdir or checkpoint directory (stage2.preprocessing=hsv)")
    p.add_argument("--format", required=True, choices=("onnx", "stablehlo"),
                   help="onnx (jax2onnx, runs in onnxruntime) or stablehlo "
                        "(jax.export, runs with JAX alone)")
    p.add_argument("--height", type=int, required=True, help="frame height of the input")
    p.add_argument("--width", type=int, required=True, help="frame width of the input")
    p.add_argument("--batch", type=int, default=1, help="frames per call (default 1)")
    p.add_argument("--out", required=True, help="the artifact's file (FILE.json goes beside it)")
    p.add_argument("--sample", metavar="FILE",
                   help="raw frame file (HxW) for the export-time check (default: rendered "
                        "synthetic frames)")
    _compile_cache_flag(p)
    p.set_defaults(func=cmd_export)


def _add_quickstart(sub) -> None:
    """The `irdepth quickstart` sub-command."""
    from irdepth_jax.config import available_presets

    p = sub.add_parser("quickstart", help="synth -> Stage I -> Stage II -> eval on a tiny model",
                       description="The whole pipeline on synthetic data with the tiny preset: "
                                   "render a dataset, train Stage I (I-1, I-2) and Stage II, "
                                   "print the test tables and the untrained -> trained change. "
                                   "A few minutes on a laptop CPU.")
    p.add_argument("--workdir", default="irdepth_quickstart",
                   help="new directory for data, runs and tables (default ./irdepth_quickstart)")
    p.add_argument("--preset", default="tiny", choices=available_presets(),
                   help="config preset, irdepth_jax/configs/NAME.py (default tiny)")
    p.add_argument("--devices", type=int, help="number of devices (default: all)")
    _compile_cache_flag(p)
    _progress_flag(p)
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="config overrides")
    p.set_defaults(func=cmd_quickstart)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="irdepth",
        description="Monocular depth from raw 14-bit thermal frames: MTSA-UNet -> HSV -> "
                    "Depth Anything V2 (JAX/Flax).",
        epilog="Start with `irdepth quickstart`; `irdepth COMMAND --help` for each command.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in (_add_synth, _add_train, _add_eval, _add_predict, _add_export, _add_quickstart):
        add(sub)
    for command in sub.choices.values():  # how the library's errors name options (errors.py)
        command.set_defaults(flags={a.dest: a.option_strings[-1] for a in command._actions
                                    if a.option_strings})
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
    try:  # before JAX and the model are loaded: a mistyped path is reported at once
        check_usage(args)
    except CliError as err:
        print(f"irdepth: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    from irdepth_jax.errors import Interrupted, IrdepthError, one_line, with_flags

    try:
        _setup_jax(args)
        with _one_line_warnings():
            return args.func(args)
    except Interrupted as stop:
        print(f"irdepth: {with_flags(str(stop), args.flags)}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except KeyboardInterrupt:
        print("irdepth: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except IrdepthError as err:  # the package's own errors; anything else is a bug: traceback
        if os.environ.get("IRDEPTH_DEBUG"):
            raise
        print(f"irdepth: error: {with_flags(one_line(err), args.flags)}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
