"""Deployment benchmark: `irdepth predict` throughput, and the JAX pipeline vs its ONNX export.

An untrained model of the preset (`evaluate.save_model`: speed does not depend on the weights)
predicts rendered raw frames of --size:

1. frames/s of `irdepth predict` (`predict.predict_files`: reading the 16-bit PNGs, the model,
   writing the depth / colour / HSV PNGs) at each --batches size, after a warm-up call that
   compiles; the batch sizes take turns (A, B, A, B) and the median per size is reported;
2. latency of one call on (1, H, W) frames: the jitted JAX function `raw_to_depth` against the
   same function exported to ONNX (`export.onnx_bytes`, needs the `export` extra) run by
   onnxruntime, interleaved, medians and the ratio ONNX / JAX; and the max |difference|.

    python experiments/bench_predict.py --preset paper --size 512x640 --batches 1 8
    python experiments/bench_predict.py --preset paper --dtype bfloat16 --no-onnx   # on a GPU

Prints one JSON object (also written to --out).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import tempfile
import time

import cv2
import jax
import numpy as np


def _parse_size(text: str) -> tuple[int, int]:
    h, w = text.lower().split("x")
    return int(h), int(w)


def _make_model(preset: str, dtype: str, workdir: str):
    from irdepth_jax.config import get_config
    from irdepth_jax.train.variables import init_unet, random_depth, save_model

    cfg = get_config(preset)
    cfg = dataclasses.replace(cfg, depth=dataclasses.replace(cfg.depth, dtype=dtype))
    unet, depth = init_unet(cfg), random_depth(cfg)
    save_model(workdir, cfg, unet, depth)
    return cfg, unet, depth


def _write_frames(folder: str, n: int, size: tuple[int, int]) -> np.ndarray:
    from irdepth_jax.data.synthetic import CONDITIONS, render_scene

    os.makedirs(folder)
    raws = np.stack([render_scene(k, CONDITIONS[k % 3], *size)["raw14"] for k in range(n)])
    for k, raw in enumerate(raws):
        cv2.imwrite(os.path.join(folder, f"{k:05d}.png"), raw)
    return raws


def _predict_rate(workdir: str, frames: str, out: str, batch: int) -> float:
    """frames/s of one `predict_files` call over every frame of `frames`."""
    from irdepth_jax.predict import predict_files

    n = len(os.listdir(frames))
    start = time.perf_counter()
    predict_files(workdir, [frames], out, batch_size=batch)
    return n / (time.perf_counter() - start)


def _onnx_session(cfg, unet, depth, shape):
    try:
        import onnxruntime
    except ImportError:
        return None, "onnxruntime not installed (pip install 'irdepth_jax[export]')"
    from irdepth_jax.export import ExportError, onnx_bytes
    from irdepth_jax.models.pipeline import raw_to_depth

    start = time.perf_counter()
    try:
        data = onnx_bytes(lambda raw: raw_to_depth(unet, depth, raw, cfg), shape)
    except ExportError as err:
        return None, str(err)
    convert_s = time.perf_counter() - start
    options = onnxruntime.SessionOptions()
    options.log_severity_level = 3
    session = onnxruntime.InferenceSession(data, options, providers=["CPUExecutionProvider"])
    return (session, convert_s, len(data)), None


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="paper", choices=("tiny", "small", "paper"))
    parser.add_argument("--size", type=_parse_size, default=(512, 640), metavar="HxW",
                        help="raw frame size (default 512x640, the paper's camera)")
    parser.add_argument("--frames", type=int, default=16, help="frames per predict call")
    parser.add_argument("--batches", type=int, nargs="+", default=(1, 8))
    parser.add_argument("--repeats", type=int, default=2, help="timed predict calls per batch")
    parser.add_argument("--latency-repeats", type=int, default=5)
    parser.add_argument("--dtype", default="float32", choices=("float32", "bfloat16"),
                        help="Depth Anything compute dtype (ONNX needs float32)")
    parser.add_argument("--no-onnx", action="store_true", help="skip the ONNX comparison")
    parser.add_argument("--out", help="also write the result as JSON to this file")
    args = parser.parse_args(argv)

    root = tempfile.mkdtemp(prefix="irdepth_bench_predict_")
    workdir, frames = os.path.join(root, "run"), os.path.join(root, "frames")
    cfg, unet, depth = _make_model(args.preset, args.dtype, workdir)
    raws = _write_frames(frames, args.frames, args.size)
    result = {"preset": args.preset, "size": list(args.size), "frames": args.frames,
              "dtype": args.dtype, "device": str(jax.devices()[0]),
              "backend": jax.default_backend(), "cpu_count": os.cpu_count(),
              "jax": jax.__version__}

    # 1. irdepth predict, frames/s per batch size (each compiled by a warm-up call first)
    rates: dict[int, list[float]] = {b: [] for b in args.batches}
    for b in args.batches:
        warm = os.path.join(root, f"warm{b}")
        os.makedirs(warm)
        for k in range(min(b, args.frames)):
            os.link(os.path.join(frames, f"{k:05d}.png"), os.path.join(warm, f"{k:05d}.png"))
        start = time.perf_counter()
        _predict_rate(workdir, warm, os.path.join(root, f"out_warm{b}"), b)
        result[f"predict_warmup_s_batch{b}"] = round(time.perf_counter() - start, 2)
    for r in range(args.repeats):
        for b in args.batches:
            rates[b].append(_predict_rate(workdir, frames, os.path.join(root, f"out{b}_{r}"), b))
    result["predict_frames_per_s"] = {str(b): round(statistics.median(v), 4)
                                      for b, v in rates.items()}
    result["predict_frames_per_s_all"] = {str(b): [round(x, 4) for x in v]
                                          for b, v in rates.items()}

    # 2. one call, JAX vs ONNX (onnxruntime), interleaved
    from irdepth_jax.models.pipeline import raw_to_depth

    raw = raws[:1]
    jax_fn = lambda: np.asarray(raw_to_depth(unet, depth, raw, cfg))  # noqa: E731
    want = jax_fn()  # compiles
    onnx = None
    if not args.no_onnx and args.dtype == "float32":
        onnx, why = _onnx_session(cfg, unet, depth, raw.shape)
        if onnx is None:
            result["onnx"] = f"skipped: {why}"
    times = {"jax": [], "onnx": []}
    if onnx is not None:
        session, convert_s, nbytes = onnx
        got = session.run(["depth"], {"raw": raw})[0]  # warm-up
        result["onnx_convert_s"] = round(convert_s, 1)
        result["onnx_mbytes"] = round(nbytes / 2**20, 1)
        result["onnx_max_abs_diff_m"] = float(np.max(np.abs(got - want)))
    for _ in range(args.latency_repeats):
        start = time.perf_counter()
        jax_fn()
        times["jax"].append(time.perf_counter() - start)
        if onnx is not None:
            start = time.perf_counter()
            session.run(["depth"], {"raw": raw})
            times["onnx"].append(time.perf_counter() - start)
    result["latency_ms"] = {k: round(1e3 * statistics.median(v), 1) for k, v in times.items() if v}
    if times["onnx"]:
        result["onnx_over_jax"] = round(statistics.median(times["onnx"]) /
                                        statistics.median(times["jax"]), 3)
    text = json.dumps(result, indent=2)
    print(text)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text + "\n")
    return result


if __name__ == "__main__":
    main()
