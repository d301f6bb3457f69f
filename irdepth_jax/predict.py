"""`irdepth predict`: a trained model on raw thermal files -> depth PNGs, HSV images, videos.

The steps, one module each: the inputs are found, decoded once and checked
(`data.inputs.thermal_inputs`); the model runs on batches of frames of one size
(`predict_runner`); each frame's outputs are encoded and written by a thread pool
(`predict_outputs`), or a sequence's frames go into one video (`predict_video`). Reading,
the model and writing overlap.

Per frame ``NAME`` (PNG mode): ``NAME_depth.png`` (16-bit, metres x 256, `data.depth_png`; a
relative-depth model writes ``NAME_depth_relative.png``, depth x 256 up to an unknown scale),
``NAME_depth_color.png`` and, for models with a UNet, ``NAME_rgb.png`` (pseudo-RGB) and
``NAME_hsv.png`` (H, S, V as its 8-bit R, G, B channels). Video mode (``--video``): one
``NAME.mp4`` per sequence (a folder of frames, a multi-page TIFF, an (N, H, W) .npy, a FLIR .seq) showing
raw tone-mapped | pseudo-RGB of the HSV image | coloured depth side by side, and with
``--depth-png`` the 16-bit depth PNGs of its frames too.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from collections.abc import Sequence

from irdepth_jax.config import Config
from irdepth_jax.data.inputs import FoundInputs, Frame, is_folder, thermal_inputs, unreadable_summary
from irdepth_jax.depth_colours import DepthColours, depth_colours
from irdepth_jax.errors import RunError
from irdepth_jax.fileio import make_dirs
from irdepth_jax.pointcloud import parse_intrinsics, point_cloud_ply
from irdepth_jax.predict_outputs import Writers, depth_suffix, display_raw, frame_label, output_pngs, to_uint8
from irdepth_jax.predict_runner import Predictor, batch_sizes, default_batch_size, run_frames
from irdepth_jax.predict_settings import DEFAULT_FPS
from irdepth_jax.predict_video import check_sequences, predict_video


@dataclasses.dataclass(frozen=True)
class Predicted:
    """What `predict_files` did: the files it wrote, and the input files it left out."""

    written: list[str]
    unreadable: tuple[tuple[str, str], ...]
    """(file, reason) of each input file skipped as not a readable raw frame of the run's bit
    depth (`data.inputs.FoundInputs.unreadable`)."""


def predict_files(path: str, inputs: Sequence[str], out_dir: str,
                  overrides: Sequence[str] = (), raw_bits: int | None = None,
                  pattern: str | None = None, strict: bool = False,
                  batch_size: int | None = None, video: bool = False,
                  depth_png_frames: bool = False, fps: float = DEFAULT_FPS,
                  progress: bool = False, intrinsics: str | None = None,
                  depth_range: str | None = None, cmap: str = "turbo",
                  recursive: bool = False, topic: str | None = None) -> Predicted:
    """Runs a trained model on raw frames and writes its outputs (see the module docstring).

    Args:
      path: a run's workdir or checkpoint directory.
      inputs: raw frame files and folders (formats: `data.rawio`; a stack gives NAME_pNNNN).
      out_dir: output directory.
      overrides: ``key=value`` config overrides.
      raw_bits: bit depth of the inputs' counts, 14 or 16 (default: the model's
        data.raw_bits); a frame with a count over it is skipped (`strict`: an error).
      pattern, strict, recursive: which files of a folder are read (with `recursive` those of
        its sub-folders too, their outputs in the same sub-folders of `out_dir`), and whether a
        non-thermal or unreadable one is an error (else it is skipped; see `thermal_inputs`).
      topic: the image topic of ROS bags among the inputs (None: each bag's one image topic).
      batch_size: frames per model call (frames of one size; outputs do not depend on it);
        None: `default_batch_size()`.
      video: one MP4 per input sequence instead of per-frame images; `depth_png_frames`
        adds the 16-bit depth PNGs of its frames; `fps` is its frame rate.
      progress: a progress bar (frames/s) on stderr.
      intrinsics: PNG mode: also write NAME.ply, the depth as a point cloud (one point per
        pixel with depth > 0, coloured by the pseudo-RGB image), back-projected with these
        camera intrinsics (`pointcloud.parse_intrinsics`: fx,fy,cx,cy or a calibration file).
      depth_range, cmap: how the coloured depth is drawn (`depth_colours.depth_colours`: None,
        'auto' or 'MIN:MAX'; a matplotlib colour map), with a colour bar under it.
    Returns:
      the written paths and the skipped files (`Predicted`); a line on stderr names the skipped
      files at the end, a warning counts depth values over what a depth PNG holds (written
      as 255.996 m, `data.depth_png`) and another the nearly black pseudo-RGB images
      (`predict_outputs.DarkImages`). All inputs are read (and checked) before anything is
      written, each frame decoded once (`data.inputs.FrameReader`).
    Raises:
      RunError naming the input file when a prediction is not finite (NaN / inf), before that
      frame's files are written; WriteError naming the output file when it cannot be written
      (complete files or none, e.g. on a full disk). The frames before are written completely.
    """
    from irdepth_jax.train.workdir_lock import acquire, release

    batch_size = _checked_settings(batch_size, video, fps)
    _check_out_is_no_input(out_dir, inputs, recursive)
    cfg, model, camera = _checked_model(path, overrides, video, depth_png_frames, intrinsics)
    colours = depth_colours(depth_range, cfg.data.max_depth, not cfg.depth.metric, cmap)
    bits = _bit_depth(cfg, raw_bits)
    found = thermal_inputs(inputs, bits, pattern, strict, recursive, topic)
    if video:
        check_sequences(found.sequences)
    cfg = _say_what_the_model_makes(path, cfg, model, bits, found, video)
    predictor = Predictor(cfg, model, bits)
    for shape, batch in batch_sizes(found.sequences, batch_size).items():  # too large: refused now
        predictor.prepare(batch, shape)
    make_dirs(out_dir)
    lock = acquire(out_dir, "--out folder")  # one run per folder: a frame's files are one run's
    from tqdm.auto import tqdm

    bar = tqdm(total=sum(f.frames for f in found.sequences), unit="frame", disable=not progress,
               desc="predict", file=sys.stderr)
    writers = Writers()
    try:
        if video:
            for sequence in found.sequences:
                predict_video(predictor, found, sequence, out_dir, batch_size, fps,
                              depth_png_frames, writers, bar, colours)
        else:
            _predict_pngs(predictor, found, out_dir, batch_size, writers, bar, colours, camera)
        writers.check()
    finally:
        writers.close()
        bar.close()
        release(lock)
    for counted in (writers.over_range, writers.dark_rgb):
        if counted.message():
            print(f"irdepth: WARNING: {counted.message()}", file=sys.stderr)
    if unreadable_summary(found):
        print(unreadable_summary(found), file=sys.stderr)
    return Predicted(writers.written, found.unreadable)


def _checked_settings(batch_size: int | None, video: bool, fps: float) -> int:
    """The batch size (None: `default_batch_size()`); RunError for a batch size under 1 or,
    with `video`, a frame rate a video cannot have."""
    batch_size = default_batch_size() if batch_size is None else batch_size
    if batch_size < 1:
        raise RunError(f"--batch-size {batch_size}: must be at least 1")
    if video:
        from irdepth_jax.video import fps_problem

        if fps_problem(fps):
            raise RunError(f"--fps {fps:g}: {fps_problem(fps)}")
    return batch_size


def _checked_model(path: str, overrides: Sequence[str], video: bool, depth_png_frames: bool,
                   intrinsics: str | None) -> tuple[Config, dict, object]:
    """(config, model, camera intrinsics or None) of the run at `path`; RunError for a model
    that cannot predict from raw frames, or for outputs it cannot give."""
    from irdepth_jax.runs.variables import load_model

    cfg, _, model = load_model(path, overrides)
    if model["depth"] is None and depth_png_frames:
        raise RunError(f"--depth-png: {path} is a Stage I model, it has no depth output")
    if model["depth"] is not None and cfg.stage2.preprocessing == "rgb":
        raise RunError(f"{path}: this model takes visible RGB images "
                       "(stage2.preprocessing=rgb), not raw frames")
    if model["depth"] is not None and cfg.stage2.preprocessing == "blank":
        raise RunError(f"{path}: a control model (stage2.preprocessing=blank) that never sees "
                       "the image; it predicts the same depth for every frame")
    camera = None
    if intrinsics is not None:
        camera = parse_intrinsics(intrinsics)
        if video or model["depth"] is None:
            raise RunError("--pointcloud: per-frame point clouds of a depth model (not with "
                           "--video or a Stage I model)")
    return cfg, model, camera


def _bit_depth(cfg: Config, raw_bits: int | None) -> int:
    """The bit depth the inputs are read at: `raw_bits`, or the model's data.raw_bits."""
    from irdepth_jax.config import resolved_raw_bits
    from irdepth_jax.imaging.raw import BIT_DEPTHS

    bits = resolved_raw_bits(cfg) if raw_bits is None else raw_bits
    if bits not in BIT_DEPTHS:
        raise RunError(f"--raw-bits {bits}: choose 14 or 16")
    return bits


def _say_what_the_model_makes(path: str, cfg: Config, model: dict, bits: int,
                              found: FoundInputs, video: bool) -> Config:
    """The config to predict with (data.raw_bits = `bits`); notes on stderr on what the model
    was trained on, on a bit depth it did not see, and on outputs that are not metric depth."""
    from irdepth_jax.config import resolved_raw_bits

    trained_bits = resolved_raw_bits(cfg)
    if bits != trained_bits:
        cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, raw_bits=bits))
        if cfg.unet.raw_scale == "fixed" and model["unet"] is not None:
            print(f"irdepth: note: {path} was trained on {trained_bits}-bit counts with "
                  f"unet.raw_scale=fixed; --raw-bits {bits} feeds it counts / {2**bits - 1}, "
                  "a scale it did not see in training", file=sys.stderr)
    _say_what_it_was_trained_on(path, model.get("trained_on"),
                                {shape for sequence in found.sequences for shape, _ in sequence.shapes})
    for line in model["warnings"]:
        print(f"irdepth: WARNING: {line}", file=sys.stderr)
    if model["depth"] is not None and not cfg.depth.metric:
        print(f"irdepth: note: {path} predicts relative depth (depth.metric=false): "
              "NAME_depth_relative.png holds depth x 256 up to an unknown scale, not metres; "
              "scale it to metres with known distances (irdepth eval --align median does it "
              "per image against ground truth)", file=sys.stderr)
    if model["depth"] is None:
        print(f"irdepth: note: {path} is a Stage I model, it has no depth output: "
              + ("its videos show raw | pseudo-RGB, no depth" if video else
                 "writing its pseudo-RGB and HSV images (NAME_rgb.png, NAME_hsv.png) only; "
                 "give a Stage II run for depth"), file=sys.stderr)
    return cfg


def _predict_pngs(predictor: Predictor, found: FoundInputs, out_dir: str, batch_size: int,
                  writers: Writers, bar, colours: DepthColours, camera) -> None:
    """Writes the PNGs (and with `camera` the point cloud) of every frame of `found`."""
    for sequence in found.sequences:
        make_dirs(os.path.join(out_dir, sequence.out_dir))
    depth_name = depth_suffix(predictor.cfg)

    def emit(frame: Frame, images: dict) -> None:
        stem = os.path.join(out_dir, frame.out_dir, frame.name)
        pngs = output_pngs(images, colours, depth_name, frame_label(frame), writers.over_range)
        if "rgb" in images:
            writers.dark_rgb.add(images["rgb"], frame_label(frame))
        for kind, image in pngs.items():
            writers.submit(f"{stem}_{kind}.png", image)
        if camera is not None:
            colors = (to_uint8(images["rgb"]) if "rgb" in images
                      else display_raw(frame.raw, predictor.bits))
            writers.submit_bytes(f"{stem}.ply", point_cloud_ply(images["depth"], colors, camera))
        bar.update(1)

    run_frames(predictor, found.frames(), batch_sizes(found.sequences, batch_size), emit)


def _say_what_it_was_trained_on(path: str, trained_on: dict | None, shapes: set) -> None:
    """Prints (stderr) what the model was trained on, and a warning for each way the inputs
    differ from it in kind (`runs.variables.input_warnings`); nothing for a checkpoint that
    did not record it."""
    from irdepth_jax.runs.variables import describe_trained_on, input_warnings

    if trained_on is None:
        return
    print(f"irdepth: model {path}: {describe_trained_on(trained_on)}", file=sys.stderr)
    for line in input_warnings(trained_on, shapes):
        print(f"irdepth: WARNING: {line}", file=sys.stderr)


def _check_out_is_no_input(out_dir: str, inputs: Sequence[str], recursive: bool) -> None:
    """RunError when `out_dir` is one of the input folders (with `recursive`, or inside one): a
    later run on that folder would read the outputs (16-bit NAME_depth.png among them) as raw
    frames."""
    out = os.path.realpath(out_dir)
    for item in inputs:
        folder = os.path.realpath(item)
        if is_folder(item) and (out == folder or recursive and out.startswith(folder + os.sep)):
            where = "the input folder" if out == folder else "inside the input folder"
            raise RunError(f"--out {out_dir} is {where} {item}: a later run on it would read "
                           "these outputs as raw frames; choose another --out folder")
