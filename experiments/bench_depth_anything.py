"""Forward latency of Depth Anything V2: our jitted Flax model vs the PyTorch reference.

Both run the same random weights (transformers' DepthAnythingForDepthEstimation, exported with
save_pretrained and imported with irdepth_jax.weights.load_depth_anything) on the same input; the
script also reports how far apart the two predictions are. Needs the [parity] extra (torch +
transformers) for the reference; --no-torch times ours only.

    python experiments/bench_depth_anything.py --encoder vits --size 518 518 --dtype float32
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

from irdepth_jax.models.depth_anything import DepthAnythingV2, depth_anything_config
from irdepth_jax.weights import load_depth_anything


def _time(fn, warmup: int, repeats: int) -> list[float]:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return times


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--encoder", default="vits", help="preset: vits | vitb | vitl | vitg | small | tiny")
    parser.add_argument("--size", type=int, nargs=2, default=(518, 518), metavar=("H", "W"), help="multiples of 14")
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--dtype", default="float32", choices=("float32", "bfloat16"), help="our compute dtype")
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--threads", type=int, default=os.cpu_count(), help="torch intra-op threads")
    parser.add_argument("--torch-attn", default="sdpa", choices=("sdpa", "eager"), help="transformers attention")
    parser.add_argument("--no-torch", action="store_true", help="time our model only (random init)")
    parser.add_argument("--out", help="also write the result as JSON to this file")
    args = parser.parse_args(argv)

    cfg = depth_anything_config(args.encoder, pos_embed_mode="transformers")
    x = np.random.default_rng(0).normal(size=(args.batch, *args.size, 3)).astype(np.float32)
    result = dict(
        encoder=args.encoder, size=list(args.size), batch=args.batch, dtype=args.dtype,
        device=str(jax.devices()[0]), cpu_count=os.cpu_count(),
    )

    ref = None
    if args.no_torch:
        params = jax.jit(DepthAnythingV2(cfg).init)(jax.random.key(0, impl="rbg"), jnp.asarray(x[:1]))["params"]
    else:
        import torch

        from experiments.torch_reference import random_hf_model

        torch.set_num_threads(args.threads)
        model = random_hf_model(cfg)
        model.backbone.set_attn_implementation(args.torch_attn)  # the DINOv2 backbone's attention
        with tempfile.TemporaryDirectory() as tmp:
            model.save_pretrained(tmp)
            _, params = load_depth_anything(tmp)
        pixels = torch.from_numpy(np.ascontiguousarray(x.transpose(0, 3, 1, 2)))

        def torch_forward():
            with torch.inference_mode():
                return model(pixel_values=pixels).predicted_depth

        times = _time(torch_forward, args.warmup, args.repeats)
        ref = torch_forward().numpy()
        result.update(torch_threads=args.threads, torch_ms=1e3 * statistics.median(times),
                      torch_attn=model.backbone.config._attn_implementation)

    cfg = dataclasses.replace(cfg, dtype=args.dtype)
    forward = jax.jit(DepthAnythingV2(cfg).apply)
    images = jnp.asarray(x)
    start = time.perf_counter()
    out = forward({"params": params}, images).block_until_ready()
    result["jax_compile_s"] = time.perf_counter() - start
    times = _time(lambda: forward({"params": params}, images).block_until_ready(), args.warmup, args.repeats)
    result["jax_ms"] = 1e3 * statistics.median(times)
    if ref is not None:
        result["jax_over_torch"] = result["jax_ms"] / result["torch_ms"]
        result["max_abs_diff_over_max"] = float(np.abs(np.asarray(out) - ref).max() / np.abs(ref).max())
    print(json.dumps(result, indent=1))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
    return result


if __name__ == "__main__":
    main()
