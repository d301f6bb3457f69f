"""Inference, the deployment path: our pipeline against idiomatic PyTorch eager and against our
ONNX export in onnxruntime, per frame size; and the time to first depth of `irdepth predict`.

    python experiments/bench_predict.py --preset paper --sizes 256x320 512x640 --repeats 7 \\
        --threads 2 --json experiments/results/bench_predict.json

An untrained model of the preset (speed does not depend on the weights; every side builds the
same random weights, and the max |depth difference| to ours is printed) runs raw (1, H, W)
uint16 frames to depth:

1. per size, three sides, each in its own process (`bench_common.Worker`), calls interleaved
   (A, B, C, A, B, C, ...), --repeats after --warmup: `run_pipeline` jitted (ours), the same
   pipeline in PyTorch eager (experiments/pipeline_torch.py: the idiomatic UNet + the official
   Depth Anything V2 code, inference_mode), and `irdepth export`'s ONNX model (`raw_to_depth`)
   in onnxruntime (CPU provider, --threads intra-op threads). Latency: the median seconds of one
   call of batch 1 (spread: max / min - 1); frames/s: its inverse, the steady rate of one frame
   after another. Where the time goes: ours and torch also time the UNet part (raw -> RGB image)
   and the depth part (RGB -> depth) apart, with XLA's FLOP count of each;
2. time to first depth: `irdepth predict` on one frame of the first size, a new process from
   start to exit (its PNGs checked written), with an empty compilation cache (cold) and then
   with the cache that run filled (warm, the median of --ttfd-repeats; each start's seconds
   in `warm_s_all`). --ttfd-only measures this alone:

       python experiments/bench_predict.py --preset paper --sizes 256x320 --ttfd-only \
           --json experiments/results/bench_predict_ttfd.json

Threads: --threads N for every side (XLA's pool, torch's OpenMP, onnxruntime's intra-op).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import os
import platform
import subprocess
import sys
import tempfile
import time

import cv2
import jax
import numpy as np

from irdepth_experiments.bench_common import (
    Worker,
    compiled_with_seconds,
    flops_of,
    interleaved_samples,
    spread,
    usable_cpus,
    versions,
    write_json,
)
from irdepth_experiments.bench_unet import parse_size

SIDES = ("ours", "torch", "onnx")


def make_model(preset: str, dtype: str, workdir: str | None = None, overrides=()):
    """(cfg, unet variables, Depth Anything params) of an untrained model of `preset`, the
    Depth Anything compute dtype `dtype`; saved as a run at `workdir` when given (what
    `irdepth predict` reads). Deterministic: every process builds the same weights."""
    from irdepth_jax.config import apply_overrides, get_config
    from irdepth_jax.runs.variables import init_unet, random_depth
    from irdepth_jax.train.state import save_model

    cfg = apply_overrides(get_config(preset), list(overrides))
    cfg = dataclasses.replace(cfg, depth=dataclasses.replace(cfg.depth, dtype=dtype))
    unet, depth = init_unet(cfg), random_depth(cfg)
    if workdir:
        save_model(workdir, cfg, unet, depth)
    return cfg, unet, depth


def bench_frames(n: int, size: tuple[int, int]) -> np.ndarray:
    """(n, H, W) uint16 rendered 14-bit raw frames (the synthetic scenes)."""
    from irdepth_jax.data.synthetic import CONDITIONS, render_scene

    return np.stack([render_scene(k, CONDITIONS[k % 3], *size)["raw14"] for k in range(n)])


def write_frames(folder: str, n: int, size: tuple[int, int]) -> np.ndarray:
    """Writes `bench_frames` as 16-bit PNGs 00000.png ... into `folder` (made); returns them."""
    os.makedirs(folder)
    raws = bench_frames(n, size)
    for k, raw in enumerate(raws):
        cv2.imwrite(os.path.join(folder, f"{k:05d}.png"), raw)
    return raws


def setup_ours(preset: str, size, overrides=()):
    """`Worker` set-up: 'pipeline' (jitted run_pipeline, its depth), 'unet' (raw -> the RGB
    image) and 'depth' (RGB -> depth), batch 1; info: compile seconds and XLA's FLOP counts."""
    import jax.numpy as jnp

    from irdepth_jax.models.pipeline import depth_from_rgb, run_pipeline

    cfg, unet, depth = make_model(preset, "float32", overrides=overrides)
    raw = jnp.asarray(bench_frames(1, size))
    pipeline, pipeline_s = compiled_with_seconds(jax.jit(lambda u, d, r: run_pipeline(u, d, r, cfg)["depth"]),
                                                 unet, depth, raw)
    to_rgb, _ = compiled_with_seconds(jax.jit(lambda u, r: run_pipeline(u, None, r, cfg)["rgb"]), unet, raw)
    rgb = to_rgb(unet, raw)
    to_depth, _ = compiled_with_seconds(jax.jit(lambda d, x: depth_from_rgb(d, x, cfg)), depth, rgb)
    calls = {"pipeline": lambda: np.asarray(pipeline(unet, depth, raw)),
             "unet": lambda: to_rgb(unet, raw).block_until_ready(),
             "depth": lambda: to_depth(depth, rgb).block_until_ready()}
    info = {"compile_pipeline_s": pipeline_s, "pipeline_flops": flops_of(pipeline),
            "unet_flops": flops_of(to_rgb), "depth_flops": flops_of(to_depth)}
    return calls, info


def setup_torch(preset: str, size, overrides=()):
    """`Worker` set-up of the PyTorch eager pipeline: the same calls as `setup_ours`."""
    import torch

    from irdepth_experiments.bench_common import torch_flops
    from irdepth_experiments.pipeline_torch import IdiomaticPipeline

    cfg, unet, depth = make_model(preset, "float32", overrides=overrides)
    model = IdiomaticPipeline(cfg, jax.device_get(unet), jax.device_get(depth))
    raw = torch.from_numpy(bench_frames(1, size).astype(np.int32))  # torch has no uint16 arithmetic
    with torch.inference_mode():
        rgb = model.rgb(raw)

    def run(fn, *args):
        with torch.inference_mode():
            return fn(*args)

    calls = {"pipeline": functools.partial(run, model, raw), "unet": functools.partial(run, model.rgb, raw),
             "depth": functools.partial(run, model.depth_from_rgb, rgb, size)}
    return calls, {"pipeline_torch_flops": torch_flops(calls["pipeline"]), "threads": torch.get_num_threads()}


def setup_onnx(preset: str, size, threads: int, overrides=()):
    """`Worker` set-up of the ONNX export (`raw_to_depth`) in onnxruntime: 'pipeline'."""
    import onnxruntime

    from irdepth_jax.export import onnx_bytes
    from irdepth_jax.models.pipeline import raw_to_depth

    cfg, unet, depth = make_model(preset, "float32", overrides=overrides)
    raw = bench_frames(1, size)
    start = time.perf_counter()
    data = onnx_bytes(lambda r: raw_to_depth(unet, depth, r, cfg), raw.shape)
    convert_s = time.perf_counter() - start
    options = onnxruntime.SessionOptions()
    options.log_severity_level = 3
    options.intra_op_num_threads = threads
    session = onnxruntime.InferenceSession(data, options, providers=["CPUExecutionProvider"])
    calls = {"pipeline": lambda: session.run(["depth"], {"raw": raw})[0]}
    return calls, {"onnx_convert_s": convert_s, "onnx_mbytes": len(data) / 2**20}


def bench_size(preset: str, size, repeats: int, warmup: int, threads: int, sides, overrides=()) -> dict:
    """Latency / frames/s of every side at one size (see the module docstring, part 1)."""
    setups = {"ours": (setup_ours, ()), "torch": (setup_torch, ()), "onnx": (setup_onnx, (threads,))}
    row = {"size": list(size)}
    with contextlib.ExitStack() as stack:
        workers = {name: stack.enter_context(Worker(setups[name][0], preset, size, *setups[name][1],
                                                    overrides=overrides, threads=threads))
                   for name in sides}
        for name, worker in workers.items():
            row.update({k: v for k, v in worker.info.items() if k != "keep_freed_memory"})
        want = workers["ours"].result("pipeline")
        for name in sides[1:]:
            got = workers[name].result("pipeline")
            row[f"{name}_max_abs_diff_m"] = float(np.abs(got - want).max())
        row["max_depth_m"] = float(np.abs(want).max())
        samples = interleaved_samples([functools.partial(w.time, "pipeline") for w in workers.values()],
                                      repeats, warmup)
        for name, seconds in zip(workers, samples):
            row[f"{name}_seconds"] = spread(seconds)
            row[f"{name}_latency_ms"] = 1e3 * row[f"{name}_seconds"]["median"]
            row[f"{name}_frames_per_s"] = 1.0 / row[f"{name}_seconds"]["median"]
        parts = [name for name in ("ours", "torch") if name in workers]
        for part in ("unet", "depth"):
            samples = interleaved_samples([functools.partial(workers[n].time, part) for n in parts], repeats, warmup)
            for name, seconds in zip(parts, samples):
                row[f"{name}_{part}_ms"] = 1e3 * float(np.median(seconds))
    for name in sides[1:]:
        row[f"ours_over_{name}"] = row["ours_latency_ms"] / row[f"{name}_latency_ms"]
    return row


def time_to_first_depth(preset: str, size, repeats: int, overrides=()) -> dict:
    """Seconds from starting `irdepth predict` on one frame to its exit, cold and warm cache."""
    result = {"size": list(size)}
    with tempfile.TemporaryDirectory() as root:
        workdir, frames, cache = (os.path.join(root, n) for n in ("run", "frames", "cache"))
        make_model(preset, "float32", workdir, overrides)
        write_frames(frames, 1, size)
        env = {**os.environ, "JAX_COMPILATION_CACHE_DIR": cache}

        def run(k: int) -> float:
            out = os.path.join(root, f"out{k}")
            start = time.perf_counter()
            subprocess.run([sys.executable, "-m", "irdepth_jax.cli", "predict", "--checkpoint", workdir,
                            "--out", out, "--no-progress", os.path.join(frames, "00000.png")],
                           check=True, env=env, stdout=subprocess.DEVNULL)
            seconds = time.perf_counter() - start
            pngs = [f for f in os.listdir(out) if f.endswith(".png") and "depth" in f]
            if not pngs:
                raise RuntimeError(f"irdepth predict wrote no depth PNG into {out}")
            return seconds

        result["cold_s"] = run(0)
        warm = [run(k + 1) for k in range(repeats)]
        result["warm_s"] = float(np.median(warm))
        result["warm_s_all"] = warm
    return result


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="paper")
    parser.add_argument("--sizes", nargs="+", type=parse_size, default=[(256, 320), (512, 640)], help="HxW")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--threads", type=int, default=usable_cpus())
    parser.add_argument("--sides", nargs="+", choices=SIDES, default=list(SIDES),
                        help="ours and which opponents (ours always runs)")
    parser.add_argument("--ttfd-repeats", type=int, default=3,
                        help="warm `irdepth predict` runs (0: none); the first of them is a process's second start")
    parser.add_argument("--ttfd-only", action="store_true",
                        help="only the time to first depth (of the first --sizes), no per-frame sides")
    parser.add_argument("--json", metavar="FILE")
    parser.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="config overrides of the preset")
    args = parser.parse_args(argv)
    sides = ["ours"] + [s for s in args.sides if s != "ours"]
    summary = {"preset": args.preset, "overrides": args.overrides, "repeats": args.repeats, "threads": args.threads,
               "processes": "one per side (Worker)", "cpu": platform.processor() or platform.machine(),
               "cpu_count": os.cpu_count(), **versions(), "results": []}
    print("inference: " + " ".join(f"{k}={v}" for k, v in summary.items() if k != "results"), flush=True)
    for size in [] if args.ttfd_only else args.sizes:
        row = bench_size(args.preset, size, args.repeats, args.warmup, args.threads, sides, args.overrides)
        summary["results"].append(row)
        write_json(args.json, summary)
        cells = [f"{name} {row[f'{name}_latency_ms']:.0f} ms ({row[f'{name}_frames_per_s']:.2f} frames/s, "
                 f"spread {row[f'{name}_seconds']['spread_pct']:.0f} %)" for name in sides]
        print(f"{size[0]}x{size[1]}: " + "; ".join(cells), flush=True)
        print("  " + ", ".join(f"ours / {n} {row[f'ours_over_{n}']:.2f}" for n in sides[1:])
              + f"; ours: UNet part {row['ours_unet_ms']:.0f} ms ({row['unet_flops'] / 1e9:.1f} GFLOP), "
              f"depth part {row['ours_depth_ms']:.0f} ms ({row['depth_flops'] / 1e9:.1f} GFLOP)"
              + (f"; torch: UNet {row['torch_unet_ms']:.0f} ms, depth {row['torch_depth_ms']:.0f} ms"
                 if "torch" in sides else ""), flush=True)
    if args.ttfd_repeats:
        ttfd = time_to_first_depth(args.preset, args.sizes[0], args.ttfd_repeats, args.overrides)
        summary["time_to_first_depth"] = ttfd
        print(f"irdepth predict, one {ttfd['size'][0]}x{ttfd['size'][1]} frame, process start to exit: "
              f"cold cache {ttfd['cold_s']:.1f} s, warm cache {ttfd['warm_s']:.1f} s")
    write_json(args.json, summary)
    return summary


if __name__ == "__main__":
    main()
