"""The model side of `irdepth predict`: a loaded model compiled per frame size (refused when its
memory exceeds what the device has free), frames grouped by size into batches, and one batch on
the device while the previous batch's outputs are handed on.

Each frame size runs at one batch size (the last batch of a size is padded with its last frame),
so it compiles once.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Iterator, Sequence

import numpy as np

from irdepth_jax.config import Config
from irdepth_jax.data.inputs import Frame, ThermalInput
from irdepth_jax.data.loader import prefetch
from irdepth_jax.errors import RunError
from irdepth_jax.predict_settings import DEFAULT_BATCH

READ_AHEAD = 2
"""Batches decoded ahead of the model."""

def default_batch_size() -> int:
    """`DEFAULT_BATCH` of the default JAX backend (8 for accelerators other than CPU)."""
    import jax

    return DEFAULT_BATCH.get(jax.default_backend(), DEFAULT_BATCH["gpu"])


class Predictor:
    """`run_pipeline` of a loaded model (`runs.variables.load_model`) on batches of raw frames."""

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
        import jax

        from irdepth_jax.config import to_dict
        from irdepth_jax.program_cache import directory, keep_export, kept_export

        args, kwargs = self._arguments(np.zeros((batch, *shape), np.uint16))
        made_from = to_dict(self.cfg)
        exported = kept_export("pipeline", made_from, args, kwargs)
        if exported is None and directory() is not None and not self._uses_cudnn_attention():
            # traced into an exported program, kept, and that program compiled (once): its compile
            # in JAX's persistent cache is then the one the next start's `kept_export` asks for
            exported = _exported_pipeline(self.cfg, args, kwargs)
            if exported is not None:
                keep_export("pipeline", made_from, exported, args, kwargs)
        if exported is not None:  # kept by an earlier start (this one traces nothing) or just made
            compiled = jax.jit(exported.call).lower(*args, **kwargs).compile()
        else:  # no program cache, or a program JAX cannot export
            compiled = run_pipeline.lower(*args, self.cfg, **kwargs).compile()
        need, free = program_bytes(compiled), available_bytes()
        if need is not None and free is not None and need > free:
            frames = f"a batch of {batch} frames" if batch > 1 else "one frame"
            advice = "--batch-size 1, or " if batch > 1 else ""
            raise RunError(f"{frames} of {shape[0]}x{shape[1]} needs about {_bytes(need)} (XLA's "
                           f"estimate for the compiled model), more than the {_bytes(free)} free "
                           f"here; use {advice}smaller frames (crop or resize them)")
        self._compiled[(batch, *shape)] = compiled

    def _uses_cudnn_attention(self) -> bool:
        """Whether the pipeline holds cuDNN's fused attention, which JAX never exports (known
        before tracing it: every start would otherwise trace it twice, for the refused export
        and for the plain jit)."""
        from irdepth_jax.models.pipeline import attention_kernel

        return self.model["depth"] is not None and attention_kernel(self.cfg) == "cudnn"

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


def _exported_pipeline(cfg: Config, args: tuple, kwargs: dict):
    """`pipeline_outputs` of `cfg` as a `jax.export.Exported` for (args, kwargs), or None where
    JAX refuses to serialise it: a custom call without a compatibility guarantee in the
    program, such as cuDNN's fused attention of a bfloat16 ViT on a GPU (that pipeline is then
    compiled by the plain jit, and traced again on every start)."""
    import jax
    from jax import export

    from irdepth_jax.models.pipeline import pipeline_outputs

    try:
        return export.export(jax.jit(functools.partial(pipeline_outputs, cfg=cfg)))(*args, **kwargs)
    except ValueError as err:
        if "custom calls whose targets have no compatibility guarantees" not in str(err):
            raise
        return None


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


def run_frames(predictor: Predictor, frames: Iterator[Frame], sizes: dict,
               emit: Callable[[Frame, dict], None]) -> None:
    """Runs the model on `frames` (decoded on a thread, `READ_AHEAD` batches ahead, batched by
    `sizes` as in `batches`) and hands each frame with its finite outputs (`Predictor.fetch`'s
    arrays of that frame: depth (H, W), rgb / hsv (H, W, 3)) to `emit`, in order, while the
    next batch computes. RunError naming the input file for a NaN / inf output."""
    read_ahead = READ_AHEAD * max(sizes.values(), default=1)
    in_flight = None
    for group, n in batches(prefetch(frames, read_ahead, "irdepth-read"), sizes):
        out = predictor.dispatch(np.stack([f.raw for f in group]))
        if in_flight is not None:
            _hand_on(predictor, *in_flight, emit)
        in_flight = (group[:n], out)
    if in_flight is not None:
        _hand_on(predictor, *in_flight, emit)


def _hand_on(predictor: Predictor, frames: list[Frame], out: dict, emit) -> None:
    images = predictor.fetch(out)
    for i, frame in enumerate(frames):
        emit(frame, _checked(frame, {k: v[i] for k, v in images.items()}))


def _checked(frame: Frame, images: dict) -> dict:
    """`images` of one frame; RunError naming its file when a value is NaN / inf (a NaN depth
    would be written as 0, "no depth")."""
    for kind, values in images.items():
        bad = int(np.size(values) - np.count_nonzero(np.isfinite(values)))
        if bad:
            raise RunError(
                f"{frame.file}: the model predicted non-finite {kind} (NaN / inf) on {bad} of "
                f"{np.size(values)} values of frame {frame.name!r}; stopped before writing its files")
    return images
