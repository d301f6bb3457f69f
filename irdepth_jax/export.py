"""`irdepth export`: a trained Stage II model as one file that runs without this library.

The exported function is `models.pipeline.raw_to_depth` with the checkpoint's variables closed
over (constants), for one input shape fixed at export time:

    raw (N, H, W) uint16 counts of `data.raw_bits` bits -> depth (N, H, W) float32 metres

* ``stablehlo``: the bytes of ``jax.export.export(jax.jit(fn)).serialize()``, lowered for CPU
  and CUDA; ``jax.export.deserialize(data).call(raw)`` runs it with JAX alone.
* ``onnx``: one self-contained ONNX file (opset `ONNX_OPSET`, input ``raw``, output ``depth``)
  converted by jax2onnx (the `export` extra). It converts the function's jaxpr, i.e. the lax
  primitives JAX runs, not jax2onnx's own versions of jax.numpy / jax.image functions (its
  ``jax.image.resize`` 'cubic' is ONNX Resize with a = -0.75, JAX's is a = -0.5): `_fold`
  inlines nested jits first and evaluates every equation that does not depend on ``raw`` (the
  variables' reshapes, BatchNorm scales, resize weights) once, which also makes the conversion
  several times faster.

Beside either artifact, ``FILE.json`` (`metadata`): input / output names, shapes and dtypes, the
raw bit depth, max depth, class names, the run's config and the export-time check. The check runs
the artifact and `raw_to_depth` on sample frames (rendered synthetic scenes, or ``--sample``) and
refuses the export when they differ by more than `TOLERANCE` x max depth.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from irdepth_jax.config import CLASS_NAMES, STAGE1_IMAGES, Config, resolved_raw_bits, to_dict
from irdepth_jax.errors import IrdepthError
from irdepth_jax.fileio import make_dirs, write_bytes
from irdepth_jax.models.pipeline import attention_kernel, raw_to_depth

FORMATS = ("onnx", "stablehlo")
STABLEHLO_PLATFORMS = ("cpu", "cuda")
ONNX_OPSET = 23
TOLERANCE = 1e-4
"""Largest accepted |artifact - JAX| of the export-time check, as a fraction of max depth."""
ONNX_MAX_BYTES = 2**31 - 1
"""Protobuf's limit on one ONNX file."""
_INLINE = {"jit", "pjit", "closed_call", "custom_jvp_call", "custom_vjp_call"}
"""Primitives whose sub-jaxpr `_fold` inlines (their primal computation; the rest is autodiff)."""


class ExportError(IrdepthError, ValueError):
    """A one-line export error (the CLI prints it as ``irdepth: error: ...``)."""


def metadata_path(path: str) -> str:
    """Where the JSON description of the artifact `path` goes: ``path + '.json'``."""
    return path + ".json"


def depth_function(cfg: Config, model: dict, checkpoint: str) -> Callable[[jax.Array], jax.Array]:
    """``raw (N, H, W) uint16 -> depth (N, H, W) float32``: `raw_to_depth` with the variables of
    `model` (`evaluate.load_model`) closed over. ExportError naming `checkpoint` for a model
    that is not a HSV Stage II model."""
    if model["depth"] is None:
        raise ExportError(f"`checkpoint` {checkpoint}: a Stage I model; export needs a Stage II "
                          "(depth) checkpoint")
    if cfg.stage2.preprocessing not in STAGE1_IMAGES:
        raise ExportError(
            f"`checkpoint` {checkpoint}: stage2.preprocessing={cfg.stage2.preprocessing}: its "
            "input image is made on the host (NumPy / OpenCV, or a visible camera), not by a JAX "
            f"function; only models whose input the Stage I model makes (stage2.preprocessing="
            f"{' or '.join(STAGE1_IMAGES)}) can be exported")
    unet, depth = model["unet"], model["depth"]
    return lambda raw: raw_to_depth(unet, depth, raw, cfg)


def sample_frames(shape: tuple[int, int, int], bits: int, path: str | None = None) -> np.ndarray:
    """(N, H, W) uint16 frames for the export-time check.

    Without `path`: rendered synthetic scenes (`data.synthetic.render_scene`, seeds 0..N-1;
    14-bit counts, x 4 for 16 bits; rendered at 8 x 8 or more and cropped, as the renderer's
    scenes need 8 pixels a side and the model takes any size). With it: the frames of the raw
    file (`data.rawio`, a stack gives several), repeated to N; each must be H x W (ExportError
    naming the file otherwise).
    """
    n, height, width = shape
    if path is None:
        from irdepth_jax.data.synthetic import render_scene

        frames = [render_scene(k, height=max(height, 8), width=max(width, 8))["raw14"][
                  :height, :width].astype(np.uint16) << (bits - 14) for k in range(n)]
    else:
        from irdepth_jax.data.rawio import read_frames

        frames = []
        for name, frame in read_frames(path, bits):
            if frame.shape != (height, width):
                raise ExportError(f"`sample` {path}: frame {name!r} is {frame.shape[0]}x"
                                  f"{frame.shape[1]}, the export is {height}x{width} "
                                  "(`height` / `width`)")
            frames.append(frame)
    return np.stack([frames[k % len(frames)] for k in range(n)])


def stablehlo_bytes(fn: Callable, shape: Sequence[int]) -> bytes:
    """Serialized `jax.export.Exported` of `fn` for uint16 input `shape`, for
    `STABLEHLO_PLATFORMS` (variables closed over by `fn` become constants)."""
    spec = jax.ShapeDtypeStruct(tuple(shape), jnp.uint16)
    return bytes(jax.export.export(jax.jit(fn), platforms=STABLEHLO_PLATFORMS)(spec).serialize())


def _inline(jaxpr, consts, args) -> list:
    """Evaluates `jaxpr` by binding its primitives, with the sub-jaxprs of `_INLINE`
    primitives inlined (under `jax.ensure_compile_time_eval` an equation of concrete inputs
    is computed then and there)."""
    from jax.extend.core import ClosedJaxpr, Literal

    env = dict(zip(jaxpr.constvars, consts)) | dict(zip(jaxpr.invars, args))

    def read(v):
        return v.val if isinstance(v, Literal) else env[v]

    for eqn in jaxpr.eqns:
        inputs = [read(v) for v in eqn.invars]
        sub = eqn.params.get("jaxpr", eqn.params.get("call_jaxpr"))
        if eqn.primitive.name in _INLINE and isinstance(sub, ClosedJaxpr):
            outputs = _inline(sub.jaxpr, sub.consts, inputs)
        else:
            outputs = eqn.primitive.bind(*inputs, **eqn.params)
            outputs = outputs if eqn.primitive.multiple_results else [outputs]
        env.update(zip(eqn.outvars, outputs))
    return [read(v) for v in jaxpr.outvars]


def _fold(fn: Callable, spec: jax.ShapeDtypeStruct) -> Callable:
    """`fn` (one array -> one array) as a function of lax primitives only: nested jits inlined,
    every equation that does not depend on the input evaluated once (constants)."""
    from jax.extend.core import jaxpr_as_fun

    traced = jax.make_jaxpr(fn)(spec)

    def folded(x):
        with jax.ensure_compile_time_eval():
            return _inline(traced.jaxpr, traced.consts, [x])[0]

    flat = jaxpr_as_fun(jax.make_jaxpr(folded)(spec))
    return lambda x: flat(x)[0]


def onnx_bytes(fn: Callable, shape: Sequence[int]) -> bytes:
    """One ONNX file (input ``raw`` uint16 `shape`, output ``depth``) of `fn`, by jax2onnx.
    ExportError when jax2onnx is not installed, fails on an operation, or the model exceeds
    protobuf's 2 GB."""
    try:
        from jax2onnx import to_onnx
    except ImportError:
        raise ExportError("`format` onnx needs jax2onnx and onnxruntime: pip install "
                          "'irdepth_jax[export]'") from None
    spec = jax.ShapeDtypeStruct(tuple(shape), jnp.uint16)
    quiet = [logging.getLogger(name) for name in ("onnx_ir", "jax2onnx")]
    levels = [log.level for log in quiet]
    for log in quiet:  # jax2onnx's per-value notes on shape stamping
        log.setLevel(logging.ERROR)
    try:
        model = to_onnx(_fold(fn, spec), [spec], model_name="irdepth_raw_to_depth",
                        opset=ONNX_OPSET, input_names=["raw"], output_names=["depth"])
    except Exception as err:  # noqa: BLE001 - the converter's failure, as one line
        raise ExportError(f"`format` onnx: jax2onnx failed: {_one_line(err)}") from None
    finally:
        for log, level in zip(quiet, levels):
            log.setLevel(level)
    drop_unused_initializers(model.graph)
    if model.ByteSize() > ONNX_MAX_BYTES:
        raise ExportError(f"`format` onnx: the model is {model.ByteSize() / 2**30:.1f} GB, over "
                          "the 2 GB of one ONNX file; use `format` stablehlo")
    return model.SerializeToString()


def _subgraphs(graph) -> list:
    """The graphs nested in `graph`'s nodes (the branches of If, the bodies of Loop / Scan)."""
    return [g for node in graph.node for attr in node.attribute
            for g in ([attr.g] if attr.HasField("g") else list(attr.graphs))]


def _names_read(graph) -> set[str]:
    """Every value name `graph` and the graphs nested in it read (node inputs, graph outputs;
    a nested graph may read its enclosing graphs' values)."""
    names = {name for node in graph.node for name in node.input}
    names |= {out.name for out in graph.output}
    for sub in _subgraphs(graph):
        names |= _names_read(sub)
    return names


def drop_unused_initializers(graph) -> None:
    """Removes, in place, the initializers no node reads from an ONNX graph and its nested
    graphs (jax2onnx leaves constants of the branches of `lax.cond` it simplified): onnxruntime
    would print a "Removing initializer" warning for each when it opens the file."""
    read = _names_read(graph)
    unused = [init for init in graph.initializer if init.name not in read]
    for init in unused:
        graph.initializer.remove(init)
    for sub in _subgraphs(graph):
        drop_unused_initializers(sub)


def _one_line(err: Exception) -> str:
    """``Type: first line of the message`` of a third-party error."""
    text = str(err).strip().splitlines()
    return type(err).__name__ + (f": {text[0]}" if text else "")


def run_artifact(fmt: str, data: bytes, raw: np.ndarray) -> np.ndarray:
    """Runs an exported artifact (its bytes) on raw frames: StableHLO with
    `jax.export.deserialize`, ONNX with onnxruntime (CPU). Returns depth (N, H, W) float32."""
    if fmt == "stablehlo":
        return np.asarray(jax.export.deserialize(bytearray(data)).call(raw))
    import onnxruntime

    options = onnxruntime.SessionOptions()
    options.log_severity_level = 3  # errors only
    session = onnxruntime.InferenceSession(data, options, providers=["CPUExecutionProvider"])
    return session.run(["depth"], {"raw": raw})[0]


def export_model(checkpoint: str, fmt: str, height: int, width: int, batch: int, out: str,
                 sample: str | None = None) -> dict:
    """Exports the Stage II model of `checkpoint` (a workdir or checkpoint directory) to `out`
    and its description to `metadata_path(out)`.

    Args:
      fmt: 'onnx' or 'stablehlo'.
      height, width, batch: the fixed input shape (batch, height, width).
      sample: a raw frame file for the check (default: rendered synthetic frames).
    Returns:
      the metadata written (see the module docstring); ``check.max_abs_diff`` is the largest
      |artifact - JAX| depth difference on the sample frames, in metres.
    Raises:
      ExportError (one line) for a bad argument or model (one that would run a GPU-only kernel
      included), a converter failure, or a check
      over `TOLERANCE` x max depth (nothing is written then); RunError from `load_model`.
    """
    from irdepth_jax.runs.variables import load_model

    if fmt not in FORMATS:
        raise ExportError(f"`format` {fmt}: choose one of {', '.join(FORMATS)}")
    for name, value in (("height", height), ("width", width), ("batch", batch)):
        if value < 1:
            raise ExportError(f"`{name}` {value}: must be at least 1")
    if os.path.isdir(out):
        raise ExportError(f"`out` {out}: is a directory (expected the artifact's file name)")
    cfg, _, model = load_model(checkpoint)
    fn = depth_function(cfg, model, checkpoint)
    if fmt == "onnx" and cfg.depth.dtype != "float32":
        raise ExportError(f"`format` onnx: `checkpoint` {checkpoint} computes in "
                          f"depth.dtype={cfg.depth.dtype}, which onnxruntime's CPU kernels "
                          "(Einsum) do not take; use `format` stablehlo")
    if attention_kernel(cfg) == "cudnn":
        raise ExportError(f"`checkpoint` {checkpoint} computes in depth.dtype={cfg.depth.dtype}, "
                          "whose attention on this GPU is cuDNN's fused kernel: a custom call "
                          "that jax.export cannot serialise and a CPU cannot run; export on the "
                          "CPU (JAX_PLATFORMS=cpu): the artifact is lowered for CPUs and GPUs alike")
    bits = resolved_raw_bits(cfg)
    shape = (batch, height, width)
    raw = sample_frames(shape, bits, sample)
    data = (stablehlo_bytes if fmt == "stablehlo" else onnx_bytes)(fn, shape)
    try:
        depth = run_artifact(fmt, data, raw)
    except Exception as err:  # noqa: BLE001 - the runtime's refusal, as one line
        raise ExportError(f"`format` {fmt}: the exported model does not run: "
                          f"{_one_line(err)}") from None
    diff = float(np.max(np.abs(depth - np.asarray(fn(raw)))))
    max_depth = float(cfg.depth.max_depth)
    tolerance = TOLERANCE * max_depth
    if not diff <= tolerance:
        raise ExportError(f"`format` {fmt}: the exported model differs from the JAX pipeline by "
                          f"{diff:.3g} m on the sample frames (tolerance {tolerance:.3g} m = "
                          f"{TOLERANCE:g} x max depth); nothing written")
    meta = {
        "format": fmt,
        "file": os.path.basename(out),
        "platforms": list(STABLEHLO_PLATFORMS) if fmt == "stablehlo" else None,
        "onnx_opset": ONNX_OPSET if fmt == "onnx" else None,
        "input": {"name": "raw", "shape": list(shape), "dtype": "uint16",
                  "raw_bits": bits, "range": [0, 2**bits - 1]},
        "output": {"name": "depth", "shape": list(shape), "dtype": "float32",
                   "units": "metres" if cfg.depth.metric else "relative"},
        "max_depth": max_depth,
        "class_names": list(CLASS_NAMES),
        "checkpoint": os.path.abspath(checkpoint),
        "check": {"sample": sample or "synthetic", "frames": batch, "max_abs_diff": diff,
                  "tolerance": tolerance},
        "versions": _versions(fmt),
        "config": to_dict(cfg),
    }
    make_dirs(os.path.dirname(os.path.abspath(out)))
    write_bytes(out, data)
    write_bytes(metadata_path(out), (json.dumps(meta, indent=2) + "\n").encode())
    return meta


def _versions(fmt: str) -> dict:
    """Versions of the tools that made (and checked) an artifact of `fmt`."""
    from importlib.metadata import version

    names = ("jax", "jaxlib") + (("jax2onnx", "onnx", "onnxruntime") if fmt == "onnx" else ())
    return {name: version(name) for name in names}
