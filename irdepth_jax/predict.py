"""`irdepth predict`: a trained model on raw thermal files -> depth PNGs, HSV images, videos.

Frames are read ahead on a thread, grouped by size into batches of `--batch-size`, run through
`models.pipeline.run_pipeline` (the path training, eval and export use) and written by a small
thread pool while the next batch computes, so decoding, the model and encoding overlap. Each
frame size runs at one batch size (the last batch of a size is padded with its last frame), so
it compiles once.

Per frame ``NAME`` (PNG mode): ``NAME_depth.png`` (16-bit, metres x 256; a relative-depth model
writes ``NAME_depth_relative.png``, depth x 256 up to an unknown scale),
``NAME_depth_color.png`` and, for models with a UNet, ``NAME_rgb.png`` (pseudo-RGB) and
``NAME_hsv.png`` (H, S, V as its 8-bit R, G, B channels). Video mode (``--video``): one
``NAME.mp4`` per sequence (a folder of frames, a multi-page TIFF, an (N, H, W) .npy, a FLIR .seq) showing
raw tone-mapped | pseudo-RGB of the HSV image | coloured depth side by side, and with
``--depth-png`` the 16-bit depth PNGs of its frames too.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import sys
from collections.abc import Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from irdepth_jax.config import Config
from irdepth_jax.data.inputs import ThermalInput, is_folder, thermal_inputs, unreadable_summary
from irdepth_jax.data.loader import prefetch
from irdepth_jax.depth_colours import DepthColours, depth_colours
from irdepth_jax.errors import RunError
from irdepth_jax.fileio import make_dirs, write_bytes, write_png
from irdepth_jax.pointcloud import parse_intrinsics, point_cloud_ply
from irdepth_jax.predict_settings import DEFAULT_BATCH, DEFAULT_FPS


def default_batch_size() -> int:
    """`DEFAULT_BATCH` of the default JAX backend (8 for accelerators other than CPU)."""
    import jax

    return DEFAULT_BATCH.get(jax.default_backend(), DEFAULT_BATCH["gpu"])
READ_AHEAD = 2
"""Batches decoded ahead of the model."""
WRITERS = 2
"""Threads encoding and writing output files (PNG encoding releases the GIL)."""


def colorize_depth(depth: np.ndarray, max_depth: float) -> np.ndarray:
    """Depth (H, W) metres -> (H, W, 3) uint8 RGB (matplotlib 'turbo', near = red)."""
    return DepthColours(0.0, max_depth).colorize(depth, 0.0, max_depth)


def display_raw(raw: np.ndarray, bits: int) -> np.ndarray:
    """A raw frame (H, W) for display: (H, W, 3) uint8 grey, linear 1-99 % percentile stretch."""
    from irdepth_jax.imaging.tonemap import linear_tail

    return np.repeat(linear_tail(raw, 1.0, 99.0, bits)[..., None], 3, axis=-1)


# --------------------------------------------------------------------------- the model
@dataclasses.dataclass(frozen=True)
class Frame:
    """One raw frame to predict: its input file, output name, counts (H, W) uint16 and output
    folder (relative to --out)."""

    file: str
    name: str
    raw: np.ndarray
    out_dir: str = ""


class Predictor:
    """`run_pipeline` of a loaded model (`evaluate.load_model`) on batches of raw frames."""

    def __init__(self, cfg: Config, model: dict, bits: int):
        self.cfg, self.model, self.bits = cfg, model, bits
        self._compiled: dict[tuple, object] = {}
        if model["depth"] is None:  # a Stage I model: its HSV images, no depth
            self.cfg = dataclasses.replace(
                cfg, stage2=dataclasses.replace(cfg.stage2, preprocessing="hsv"))

    def _arguments(self, raw: np.ndarray) -> tuple[tuple, dict]:
        import jax.numpy as jnp

        from irdepth_jax.data.source import host_image

        image = host_image({"raw14": raw}, self.cfg.stage2.preprocessing, self.bits)
        unet = self.model["unet"]
        return ((unet, self.model["depth"], None if unet is None else jnp.asarray(raw)),
                {"image": None if image is None else jnp.asarray(image)})

    def prepare(self, batch: int, shape: tuple[int, int]) -> None:
        """Compiles the pipeline for (batch, H, W) frames and refuses (RunError) a size whose
        memory, by XLA's estimate for the compiled program, exceeds what the device has free:
        before any frame is run, instead of the kernel killing the process minutes later."""
        if (batch, *shape) in self._compiled:
            return
        from irdepth_jax.models.pipeline import run_pipeline

        if not hasattr(run_pipeline, "lower"):  # a stand-in function (tests): nothing to compile
            self._compiled[(batch, *shape)] = functools.partial(run_pipeline, cfg=self.cfg)
            return
        args, kwargs = self._arguments(np.zeros((batch, *shape), np.uint16))
        compiled = run_pipeline.lower(*args, self.cfg, **kwargs).compile()
        need, free = program_bytes(compiled), available_bytes()
        if need is not None and free is not None and need > free:
            frames = f"a batch of {batch} frames" if batch > 1 else "one frame"
            advice = "--batch-size 1, or " if batch > 1 else ""
            raise RunError(f"{frames} of {shape[0]}x{shape[1]} needs about {_bytes(need)} (XLA's "
                           f"estimate for the compiled model), more than the {_bytes(free)} free "
                           f"here; use {advice}smaller frames (crop or resize them)")
        self._compiled[(batch, *shape)] = compiled

    def dispatch(self, raw: np.ndarray) -> dict:
        """Starts the model on raw (B, H, W) uint16 (JAX runs it asynchronously); returns the
        device outputs (`run_pipeline`'s dict) to pass to `fetch`."""
        self.prepare(raw.shape[0], raw.shape[1:])
        args, kwargs = self._arguments(raw)
        return self._compiled[raw.shape](*args, **kwargs)

    def fetch(self, out: dict) -> dict[str, np.ndarray]:
        """The host arrays of `dispatch`'s outputs: 'depth' (B, H, W) metres of a depth model;
        'rgb' (pseudo-RGB, HSV -> RGB) and 'hsv' (B, H, W, 3) in [0, 1] of a model with a UNet."""
        import jax

        from irdepth_jax.imaging.color import hsv_to_rgb

        if self.model["unet"] is not None and self.cfg.stage2.preprocessing != "hsv":
            out = {**out, "rgb": hsv_to_rgb(out["hsv"])}  # its input image is not the pseudo-RGB
        keys = [k for k in ("depth", "rgb", "hsv")
                if out[k] is not None and (k == "depth" or self.model["unet"] is not None)]
        return {k: np.asarray(v) for k, v in zip(keys, jax.device_get([out[k] for k in keys]))}


def _checked(file: str, name: str, images: dict) -> dict:
    """`images` of one frame; RunError naming `file` when a value is NaN / inf (a NaN depth
    would be written as 0, "no depth")."""
    for kind, values in images.items():
        bad = int(np.size(values) - np.count_nonzero(np.isfinite(values)))
        if bad:
            raise RunError(
                f"{file}: the model predicted non-finite {kind} (NaN / inf) on {bad} of "
                f"{np.size(values)} values of frame {name!r}; stopped before writing its files")
    return images


def depth_suffix(cfg: Config) -> str:
    """The file suffix of a model's depth output: 'depth' (metres) for a metric model,
    'depth_relative' for a relative one (depth.metric=false: depth up to an unknown scale)."""
    return "depth" if cfg.depth.metric else "depth_relative"


def output_pngs(images: dict, colours: DepthColours, depth_name: str = "depth") -> dict:
    """The PNGs (OpenCV BGR order) of one frame's finite predictions, by file suffix:
    rgb, hsv (8-bit), `depth_name` (16-bit, depth x 256) and `depth_name`_color (with its
    colour bar, `colours`)."""
    pngs = {}
    if "rgb" in images:
        # reversed for OpenCV, so that the files hold R, G, B and H, S, V in channel order
        pngs["rgb"], pngs["hsv"] = _to8(images["rgb"])[..., ::-1], _to8(images["hsv"])[..., ::-1]
    if "depth" in images:
        pngs[depth_name] = depth_png(images["depth"])
        pngs[f"{depth_name}_color"] = colours.image(images["depth"])[..., ::-1]
    return pngs


def _to8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.round(x * 255), 0, 255).astype(np.uint8)


def depth_png(depth: np.ndarray) -> np.ndarray:
    """Depth (H, W) metres -> the 16-bit PNG encoding (KITTI / MS2): round(metres x 256)."""
    return np.clip(np.round(depth * 256.0), 0, 65535).astype(np.uint16)


def video_panels(raw: np.ndarray, images: dict, bits: int, colours: DepthColours) -> np.ndarray:
    """One video frame (H, k*W, 3) uint8 RGB: raw tone-mapped | pseudo-RGB (| coloured depth,
    its colour bar under the panels)."""
    panels = [display_raw(raw, bits)]
    if "rgb" in images:
        panels.append(_to8(images["rgb"]))
    if "depth" not in images:
        return np.concatenate(panels, axis=1)
    depth = colours.image(images["depth"])
    height = raw.shape[0]
    panels = [np.pad(p, ((0, depth.shape[0] - height), (0, 0), (0, 0))) for p in panels]
    return np.concatenate(panels + [depth], axis=1)


# --------------------------------------------------------------------------- batching
def _frames(sequences: Sequence[ThermalInput], bits: int, topic: str | None) -> Iterator[Frame]:
    from irdepth_jax.data.rawio import read_frames

    for sequence in sequences:
        for f in sequence.files:
            for name, raw in read_frames(f, bits, topic):
                yield Frame(f, name, raw, sequence.out_dir)


def batches(frames: Iterator[Frame], sizes: dict) -> Iterator[tuple[list[Frame], int]]:
    """Groups `frames` by frame size into batches of ``sizes[(H, W)]`` frames; yields
    (frames, real count): the last batch of a size is padded with copies of its last frame."""
    pending: dict = {}
    for frame in frames:
        group = pending.setdefault(frame.raw.shape, [])
        group.append(frame)
        if len(group) == sizes[frame.raw.shape]:
            yield pending.pop(frame.raw.shape), sizes[frame.raw.shape]
    for shape, group in pending.items():
        n = len(group)
        yield group + [group[-1]] * (sizes[shape] - n), n


def program_bytes(compiled) -> int | None:
    """Bytes a compiled JAX program holds while it runs (arguments, outputs and temporaries,
    by XLA's memory analysis), or None where the backend does not say."""
    try:
        m = compiled.memory_analysis()
        return int(m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes
                   - m.alias_size_in_bytes)
    except (AttributeError, NotImplementedError, TypeError):
        return None


def _bytes(n: int) -> str:
    return f"{n / 2**30:.1f} GiB" if n >= 2**30 else f"{n / 2**20:.0f} MiB"


def available_bytes() -> int | None:
    """Free memory of the device JAX runs on: a GPU's free bytes, or on the CPU the host's
    MemAvailable (Linux); None when unknown."""
    import jax

    device = jax.devices()[0]
    if device.platform != "cpu":
        stats = device.memory_stats() or {}
        if "bytes_limit" in stats:
            return int(stats["bytes_limit"] - stats.get("bytes_in_use", 0))
        return None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def batch_sizes(found: Sequence[ThermalInput], batch_size: int) -> dict:
    """{(H, W): frames per call}: `batch_size`, or fewer when a size has fewer frames."""
    counts: dict = {}
    for sequence in found:
        for shape, n in sequence.shapes:
            counts[shape] = counts.get(shape, 0) + n
    return {shape: min(batch_size, n) for shape, n in counts.items()}


class _Pipelined:
    """Runs the model on batches while the previous batch's results are handed to `emit`:
    ``run(batches)`` keeps one batch in flight on the device."""

    def __init__(self, predictor: Predictor, emit):
        self.predictor, self.emit = predictor, emit

    def run(self, groups: Iterator[tuple[list[Frame], int]]) -> None:
        in_flight = None
        for frames, n in groups:
            out = self.predictor.dispatch(np.stack([f.raw for f in frames]))
            if in_flight is not None:
                self._finish(*in_flight)
            in_flight = (frames[:n], out)
        if in_flight is not None:
            self._finish(*in_flight)

    def _finish(self, frames: list[Frame], out: dict) -> None:
        images = self.predictor.fetch(out)
        for i, frame in enumerate(frames):
            self.emit(frame, _checked(frame.file, frame.name, {k: v[i] for k, v in images.items()}))


class _Writers:
    """A thread pool writing PNGs; `check` raises the first failed write (in order)."""

    def __init__(self):
        self.pool = ThreadPoolExecutor(WRITERS, thread_name_prefix="irdepth-write")
        self.futures: list[tuple[str, Future]] = []
        self.written: list[str] = []

    def submit(self, path: str, image: np.ndarray) -> None:
        self.futures.append((path, self.pool.submit(write_png, path, image)))
        self.check(block=False)

    def submit_bytes(self, path: str, data: bytes) -> None:
        self.futures.append((path, self.pool.submit(write_bytes, path, data)))
        self.check(block=False)

    def check(self, block: bool = True) -> None:
        while self.futures and (block or self.futures[0][1].done()):
            path, future = self.futures.pop(0)
            future.result()
            self.written.append(path)

    def close(self) -> None:
        """Waits for every submitted write (all of them, also after an error)."""
        self.pool.shutdown(wait=True)


# --------------------------------------------------------------------------- predict
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
      files at the end. All inputs are read (and checked) before anything is written.
    Raises:
      RunError naming the input file when a prediction is not finite (NaN / inf), before that
      frame's files are written; WriteError naming the output file when it cannot be written
      (complete files or none, e.g. on a full disk). The frames before are written completely.
    """
    from irdepth_jax.config import resolved_raw_bits
    from irdepth_jax.imaging.raw import BIT_DEPTHS
    from irdepth_jax.runs.variables import load_model
    from irdepth_jax.train.workdir_lock import acquire, release

    batch_size = default_batch_size() if batch_size is None else batch_size
    if batch_size < 1:
        raise RunError(f"--batch-size {batch_size}: must be at least 1")
    if video:
        from irdepth_jax.video import fps_problem

        if fps_problem(fps):
            raise RunError(f"--fps {fps:g}: {fps_problem(fps)}")
    _check_out_is_no_input(out_dir, inputs, recursive)
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
    colours = depth_colours(depth_range, cfg.data.max_depth, not cfg.depth.metric, cmap)
    trained_bits = resolved_raw_bits(cfg)
    bits = trained_bits if raw_bits is None else raw_bits
    if bits not in BIT_DEPTHS:
        raise RunError(f"--raw-bits {bits}: choose 14 or 16")
    inputs_found = thermal_inputs(inputs, bits, pattern, strict, recursive, topic)
    found = inputs_found.sequences
    if video:
        _check_sequences(found)
    if bits != trained_bits:
        cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, raw_bits=bits))
        if cfg.unet.raw_scale == "fixed" and model["unet"] is not None:
            print(f"irdepth: note: {path} was trained on {trained_bits}-bit counts with "
                  f"unet.raw_scale=fixed; --raw-bits {bits} feeds it counts / {2**bits - 1}, "
                  "a scale it did not see in training", file=sys.stderr)
    _say_what_it_was_trained_on(path, model.get("trained_on"),
                                {shape for sequence in found for shape, _ in sequence.shapes})
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
    predictor = Predictor(cfg, model, bits)
    sizes = batch_sizes(found, batch_size)
    for shape, batch in sizes.items():  # a size too large: refused now
        predictor.prepare(batch, shape)
    make_dirs(out_dir)
    lock = acquire(out_dir, "--out folder")  # one run per folder: a frame's files are one run's
    from tqdm.auto import tqdm

    bar = tqdm(total=sum(f.frames for f in found), unit="frame", disable=not progress,
               desc="predict", file=sys.stderr)
    writers = _Writers()
    try:
        if video:
            for sequence in found:
                _predict_video(predictor, sequence, out_dir, batch_size, fps, depth_png_frames,
                               writers, bar, colours, topic)
        else:
            for sequence in found:
                make_dirs(os.path.join(out_dir, sequence.out_dir))

            def emit(frame: Frame, images: dict) -> None:
                stem = os.path.join(out_dir, frame.out_dir, frame.name)
                for kind, image in output_pngs(images, colours, depth_suffix(cfg)).items():
                    writers.submit(f"{stem}_{kind}.png", image)
                if camera is not None:
                    colors = _to8(images["rgb"]) if "rgb" in images else display_raw(frame.raw, bits)
                    writers.submit_bytes(f"{stem}.ply",
                                         point_cloud_ply(images["depth"], colors, camera))
                bar.update(1)

            _Pipelined(predictor, emit).run(
                batches(prefetch(_frames(found, bits, topic), READ_AHEAD * batch_size, "irdepth-read"), sizes))
        writers.check()
    finally:
        writers.close()
        bar.close()
        release(lock)
    summary = unreadable_summary(inputs_found)
    if summary:
        print(summary, file=sys.stderr)
    return Predicted(writers.written, inputs_found.unreadable)


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


def video_name(sequence: ThermalInput) -> str:
    """The video of a sequence, relative to --out: ``OUT_DIR.mp4`` for a folder with its own
    output folder (--recursive, or same-named inputs), else the folder's or the stack file's
    name ``.mp4`` in its output folder."""
    if is_folder(sequence.item) and sequence.out_dir:
        return os.path.normpath(sequence.out_dir) + ".mp4"
    base = os.path.basename(os.path.normpath(sequence.item))
    base = base if is_folder(sequence.item) else os.path.splitext(base)[0]
    return os.path.join(sequence.out_dir, base + ".mp4")


def _check_sequences(found: Sequence[ThermalInput]) -> None:
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


def _predict_video(predictor: Predictor, sequence: ThermalInput, out_dir: str,
                   batch_size: int, fps: float, with_depth_png: bool, writers: _Writers,
                   bar, colours: DepthColours, topic: str | None) -> None:
    """Writes the MP4 of one sequence (and its depth PNGs when asked), frames in order."""
    from irdepth_jax.video import VideoWriter

    target = os.path.join(out_dir, video_name(sequence))
    make_dirs(os.path.dirname(target))
    if with_depth_png:
        make_dirs(os.path.join(out_dir, sequence.out_dir))
    sizes = batch_sizes([sequence], batch_size)
    video = VideoWriter(target, fps)

    def emit(frame: Frame, images: dict) -> None:
        video.write(video_panels(frame.raw, images, predictor.bits, colours))
        if with_depth_png and "depth" in images:
            name = f"{frame.name}_{depth_suffix(predictor.cfg)}.png"
            writers.submit(os.path.join(out_dir, frame.out_dir, name), depth_png(images["depth"]))
        bar.update(1)

    frames = prefetch(_frames([sequence], predictor.bits, topic), READ_AHEAD * batch_size,
                      "irdepth-read")
    try:
        _Pipelined(predictor, emit).run(batches(frames, sizes))
    except KeyboardInterrupt:
        partial = video.keep_partial()
        if partial:
            print(f"irdepth: interrupted: {partial} holds {video.kept} of the "
                  f"{sequence.frames} frames (those encoded before Ctrl-C)", file=sys.stderr)
        elif video.frames:
            print(f"irdepth: interrupted: the {video.frames} frames encoded before Ctrl-C do "
                  f"not decode as a video; nothing kept of {target}", file=sys.stderr)
        raise
    except BaseException:
        video.abort()
        raise
    video.close()
    writers.written.append(target)
