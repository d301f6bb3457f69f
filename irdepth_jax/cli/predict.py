"""`irdepth predict`: depth maps (and videos, point clouds) from raw thermal frames."""

from __future__ import annotations

import os

from irdepth_jax.cli.common import (
    EXIT_SKIPPED,
    CliError,
    check_out_dir,
    check_paths,
    checked_overrides,
    compile_cache_flag,
    progress_flag,
)
from irdepth_jax.errors import counted


def check(args) -> None:
    """CliError for an --out that is a file, a path that does not exist, or flags that do not
    go together."""
    check_out_dir(args.out)
    check_paths(args, ("checkpoint", "inputs"))
    if args.pointcloud != (args.intrinsics is not None):
        raise CliError("--pointcloud needs --intrinsics fx,fy,cx,cy (or a calibration file)"
                       if args.pointcloud else "--intrinsics is for --pointcloud")
    if args.depth_png and not args.video:
        raise CliError("--depth-png adds per-frame depth PNGs to --video (without --video "
                       "every frame's PNGs are written anyway)")


def add_parser(sub) -> None:
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
    compile_cache_flag(p)
    progress_flag(p)
    p.set_defaults(func=run, check=check, overrides=[])


def run(args) -> int:
    from irdepth_jax.predict import predict_files

    result = predict_files(args.checkpoint, args.inputs, args.out, checked_overrides(args.overrides),
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
