"""`irdepth predict --video`: one MP4 per input sequence (a folder of frames, a multi-page TIFF,
an (N, H, W) .npy, a FLIR .seq, a ROS bag) showing raw tone-mapped | pseudo-RGB | coloured
depth side by side, and with ``--depth-png`` the 16-bit depth PNGs of its frames too."""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence

from irdepth_jax.data.depth_png import encode_depth
from irdepth_jax.data.inputs import FoundInputs, Frame, ThermalInput, is_folder
from irdepth_jax.depth_colours import DepthColours
from irdepth_jax.errors import RunError
from irdepth_jax.fileio import make_dirs
from irdepth_jax.predict_outputs import Writers, depth_suffix, frame_label, video_panels
from irdepth_jax.predict_runner import Predictor, batch_sizes, run_frames


def video_name(sequence: ThermalInput) -> str:
    """The video of a sequence, relative to --out: ``OUT_DIR.mp4`` for a folder with its own
    output folder (--recursive, or same-named inputs), else the folder's or the stack file's
    name ``.mp4`` in its output folder."""
    if is_folder(sequence.item) and sequence.out_dir:
        return os.path.normpath(sequence.out_dir) + ".mp4"
    base = os.path.basename(os.path.normpath(sequence.item))
    base = base if is_folder(sequence.item) else os.path.splitext(base)[0]
    return os.path.join(sequence.out_dir, base + ".mp4")


def check_sequences(found: Sequence[ThermalInput]) -> None:
    """RunError for an input that is not one sequence: a single frame, or frames of several
    sizes; or two inputs that would write the same video."""
    names: dict = {}
    for sequence in found:
        if sequence.frames < 2:
            raise RunError(f"--video: {sequence.item} holds one frame; a video is made of a "
                           "folder of frames, a multi-page TIFF, an (N, H, W) .npy or a FLIR "
                           ".seq")
        if len(sequence.shapes) > 1:
            sizes = ", ".join(f"{h}x{w}" for (h, w), _ in sorted(sequence.shapes))
            raise RunError(f"--video: {sequence.item} has frames of several sizes ({sizes}); "
                           "one video holds one frame size")
        name = video_name(sequence)
        if name in names:
            raise RunError(f"--video: {sequence.item} and {names[name]} would both write "
                           f"{name} (predict them into separate --out folders)")
        names[name] = sequence.item


def predict_video(predictor: Predictor, found: FoundInputs, sequence: ThermalInput,
                  out_dir: str, batch_size: int, fps: float, with_depth_png: bool,
                  writers: Writers, bar, colours: DepthColours) -> None:
    """Writes the MP4 of one sequence of `found` (and its depth PNGs when asked), frames in
    order; on Ctrl-C keeps the frames encoded so far when they decode as a video."""
    from irdepth_jax.video import VideoWriter

    target = os.path.join(out_dir, video_name(sequence))
    make_dirs(os.path.dirname(target))
    if with_depth_png:
        make_dirs(os.path.join(out_dir, sequence.out_dir))
    video = VideoWriter(target, fps)

    def emit(frame: Frame, images: dict) -> None:
        video.write(video_panels(frame.raw, images, predictor.bits, colours))
        if "rgb" in images:
            writers.dark_rgb.add(images["rgb"], frame_label(frame))
        if with_depth_png and "depth" in images:
            name = os.path.join(out_dir, frame.out_dir,
                                f"{frame.name}_{depth_suffix(predictor.cfg)}.png")
            writers.submit(name, encode_depth(images["depth"], name=frame_label(frame),
                                              over_range=writers.over_range))
        bar.update(1)

    try:
        run_frames(predictor, found.frames([sequence]), batch_sizes([sequence], batch_size), emit)
    except KeyboardInterrupt:
        _say_what_was_kept(video, sequence, target)
        raise
    except BaseException:
        video.abort()
        raise
    video.close()
    writers.written.append(target)


def _say_what_was_kept(video, sequence: ThermalInput, target: str) -> None:
    """After Ctrl-C: keeps the encoded frames as a partial video, and says so on stderr."""
    partial = video.keep_partial()
    if partial:
        print(f"irdepth: interrupted: {partial} holds {video.kept} of the "
              f"{sequence.frames} frames (those encoded before Ctrl-C)", file=sys.stderr)
    elif video.frames:
        print(f"irdepth: interrupted: the {video.frames} frames encoded before Ctrl-C do "
              f"not decode as a video; nothing kept of {target}", file=sys.stderr)
