"""Depth Anything V2, ours (jitted Flax) vs the PyTorch references, on the same random weights:
forward latency per input size against transformers and the official code, and one Stage II
training step (SiLog + AdamW, metric head) against the official metric-depth model.

    python experiments/bench_depth_anything.py --encoder vits --sizes 518x518 364x644 \\
        --train-batch 2 --official-repo PATH/TO/Depth-Anything-V2 --threads 2 \\
        --json experiments/results/bench_depth_anything.json

--official-repo: a checkout of github.com/DepthAnything/Depth-Anything-V2 (the official code is
not a package; its `metric_depth/depth_anything_v2` is imported from there). Without it only
transformers is compared (forward only: transformers has no metric-training step to compare).
Needs the [parity] extra (torch + transformers); --no-torch times ours only.

Weights: a random transformers model (experiments/torch_reference.py), saved and imported by
irdepth_jax.weights for ours, renamed to the official .pth layout for the official model
(`hf_to_official`), all metric heads (sigmoid x max_depth) so that forward and train step run
the same network. Ours uses the official position-embedding resampling against the official
code and the transformers one against transformers, so every pair computes the same function
(max |difference| / max |depth| printed). Times: medians of --repeats calls after --warmup, the
two sides interleaved (A, B, A, B); the train step is forward in train mode, the SiLog loss on
random depth in [1, max_depth), backward and an AdamW update (lr 5e-6, weight decay 0.01) in
both. Prints one row per (reference, size) with ours ms, theirs ms and ours / theirs, XLA's
FLOP count as GFLOP/s and % of the measured matmul peak (an N x N matmul in --dtype on the
same device: on a GPU, the fraction is the step's MFU against what the chip's matmul reaches).

GPU: the same command on a CUDA machine, with --dtype bfloat16 (our compute dtype; params stay
float32) and --amp (torch autocast bf16 on the official side); see README "Benchmarks".
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import os
import platform
import sys
import tempfile
import types

import jax
import jax.numpy as jnp
import numpy as np
import optax

from experiments.bench_common import (
    compiled_with_seconds,
    flops_of,
    interleaved_medians,
    matmul_peak,
    set_threads,
    usable_cpus,
    write_json,
)
from experiments.bench_unet import parse_size
from irdepth_jax.losses import silog_loss
from irdepth_jax.models.depth_anything import DepthAnythingV2, depth_anything_config
from irdepth_jax.weights import load_depth_anything

MAX_DEPTH = 80.0
ADAMW = {"learning_rate": 5e-6, "weight_decay": 0.01}


def official_metric_model(repo: str, cfg, state_dict):
    """The official metric-depth DepthAnythingV2 of the checkout `repo`, with `state_dict`."""
    if cfg.encoder not in ("vits", "vitb", "vitl", "vitg"):
        raise SystemExit(f"--official-repo: the official code builds vits/vitb/vitl/vitg, not {cfg.encoder!r}")
    sys.path.insert(0, os.path.join(repo, "metric_depth"))  # the official code is not a package
    if importlib.util.find_spec("torchvision") is None:
        # dpt.py imports torchvision's Compose for its image loader only (not used here)
        stub = types.ModuleType("torchvision.transforms")
        stub.Compose = None
        sys.modules.update({"torchvision": types.ModuleType("torchvision"), "torchvision.transforms": stub})
    from depth_anything_v2.dpt import DepthAnythingV2 as Official

    model = Official(encoder=cfg.encoder, features=cfg.features, out_channels=list(cfg.out_channels),
                     max_depth=cfg.max_depth)
    model.load_state_dict(state_dict, strict=True)
    return model


def make_train_step(model: DepthAnythingV2, tx):
    """Jitted (params, opt_state, images, depth, valid) -> (params, opt_state, loss)."""

    def loss_fn(params, images, depth, valid):
        return silog_loss(model.apply({"params": params}, images), depth, valid)

    @jax.jit
    def step(params, opt_state, images, depth, valid):
        loss, grads = jax.value_and_grad(loss_fn)(params, images, depth, valid)
        updates, opt_state = tx.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    return step


def silog_loss_torch(pred, depth, valid, lambd: float = 0.5):
    """SiLogLoss of the official metric_depth/util/loss.py, written out (that module sits in
    the training script's package): sqrt(mean(d^2) - lambd * mean(d)^2), d = log depth - log pred
    over the valid pixels."""
    import torch

    d = torch.log(depth[valid]) - torch.log(pred[valid])
    return torch.sqrt((d**2).mean() - lambd * d.mean() ** 2)


def torch_train_step(model, amp: bool):
    """The official side: `silog_loss_torch`, torch.optim.AdamW."""
    import torch

    optimizer = torch.optim.AdamW(model.parameters(), lr=ADAMW["learning_rate"],
                                  weight_decay=ADAMW["weight_decay"])
    device_type = next(model.parameters()).device.type

    def step(images, depth, valid):
        model.train()
        optimizer.zero_grad(set_to_none=True)
        with torch.autocast(device_type, dtype=torch.bfloat16, enabled=amp):
            pred = model(images)
        loss = silog_loss_torch(pred.float(), depth, valid)
        loss.backward()
        optimizer.step()
        if device_type == "cuda":
            torch.cuda.synchronize()
        return loss

    return step


def bench_pair(name, ours, theirs, flops, repeats, warmup, batch) -> dict:
    seconds = interleaved_medians([ours, theirs] if theirs else [ours], repeats, warmup)
    row = {"reference": name, "batch": batch, "ours_ms": 1e3 * seconds[0],
           "ours_images_per_s": batch / seconds[0], "ours_gflops": flops / seconds[0] / 1e9}
    if theirs:
        row.update(theirs_ms=1e3 * seconds[1], theirs_images_per_s=batch / seconds[1],
                   ours_over_theirs=seconds[0] / seconds[1])
    return row


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--encoder", default="vits", help="vits | vitb | vitl | vitg | small | tiny")
    parser.add_argument("--sizes", nargs="+", type=parse_size, default=[(518, 518), (364, 644)],
                        help="HxW input sizes, multiples of 14")
    parser.add_argument("--batch", type=int, default=1, help="images per forward call")
    parser.add_argument("--train-batch", type=int, default=2, help="images per train step (0: none)")
    parser.add_argument("--train-size", type=parse_size, default=(518, 518), help="train-step HxW")
    parser.add_argument("--dtype", default="float32", choices=("float32", "bfloat16"),
                        help="our compute dtype (params stay float32)")
    parser.add_argument("--amp", action="store_true", help="torch autocast bf16 (the official side)")
    parser.add_argument("--remat", action="store_true", help="rematerialise our ViT blocks")
    parser.add_argument("--official-repo", metavar="DIR", help="checkout of the official code")
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--threads", type=int, default=usable_cpus(),
                        help="intra-op threads of torch and XLA (CPU)")
    parser.add_argument("--no-torch", action="store_true", help="time ours only")
    parser.add_argument("--json", metavar="FILE", help="also write the figures to FILE")
    args = parser.parse_args(argv)
    with_torch = not args.no_torch
    versions = set_threads(args.threads, with_torch)

    base = depth_anything_config(args.encoder, metric=True, max_depth=MAX_DEPTH)
    device = jax.devices()[0]
    summary = {"encoder": args.encoder, "dtype": args.dtype, "amp": args.amp, "threads": args.threads,
               "device": f"{device.platform}:{device.device_kind}",
               "cpu": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
               **versions}
    print("Depth Anything V2: " + " ".join(f"{k}={v}" for k, v in summary.items()))
    on_cpu = device.platform == "cpu"
    peak = matmul_peak(2048 if on_cpu else 8192, args.repeats, args.warmup, False, args.dtype)
    print(f"matmul peak, {args.dtype} {peak['size']}^2: XLA {peak['xla_gflops']:.1f} GFLOP/s")

    references, params = {}, None
    if with_torch:
        import torch

        from experiments.torch_reference import hf_to_official, random_hf_model

        torch_device = "cuda" if device.platform == "gpu" else "cpu"
        hf = random_hf_model(dataclasses.replace(base, pos_embed_mode="transformers"))
        with tempfile.TemporaryDirectory() as tmp:
            hf.save_pretrained(tmp)
            _, params = load_depth_anything(tmp, kind="metric", max_depth=MAX_DEPTH)
        references["transformers"] = ("transformers", hf.to(torch_device).eval())
        if args.official_repo:
            official = official_metric_model(args.official_repo, base, hf_to_official(hf.cpu()))
            references["official"] = ("official", official.to(torch_device).eval())
            hf.to(torch_device)
    ours_cfg = {mode: dataclasses.replace(base, pos_embed_mode=mode, dtype=args.dtype,
                                          remat=args.remat) for mode in ("official", "transformers")}
    if params is None:
        x0 = jnp.zeros((1, *args.sizes[0], 3), jnp.float32)
        params = jax.jit(DepthAnythingV2(base).init)(jax.random.key(0), x0)["params"]

    rows = []
    for h, w in args.sizes:
        x = np.random.default_rng(0).normal(size=(args.batch, h, w, 3)).astype(np.float32)
        images = jnp.asarray(x)
        for ref_name, (mode, model) in (references or {"none": ("official", None)}).items():
            forward, compile_s = compiled_with_seconds(
                jax.jit(DepthAnythingV2(ours_cfg[mode]).apply), {"params": params}, images)
            ours = lambda: forward({"params": params}, images).block_until_ready()  # noqa: E731
            theirs, diff = None, None
            if model is not None:
                pixels = torch.from_numpy(np.ascontiguousarray(x.transpose(0, 3, 1, 2))).to(torch_device)

                def theirs(model=model, pixels=pixels, ref_name=ref_name):
                    with torch.inference_mode(), torch.autocast(torch_device, torch.bfloat16, enabled=args.amp):
                        out = model(pixel_values=pixels).predicted_depth if ref_name == "transformers" \
                            else model(pixels)
                    if torch_device == "cuda":
                        torch.cuda.synchronize()
                    return out

                ref = theirs().float().cpu().numpy().reshape(args.batch, h, w)
                out = np.asarray(forward({"params": params}, images))
                diff = float(np.abs(out - ref).max() / np.abs(ref).max())
            row = bench_pair(ref_name, ours, theirs, flops_of(forward), args.repeats, args.warmup,
                             args.batch)
            row.update(kind="forward", size=[h, w], compile_s=compile_s, max_diff_over_max=diff)
            rows.append(row)

    if args.train_batch:
        h, w = args.train_size
        rng = np.random.default_rng(1)
        x = rng.normal(size=(args.train_batch, h, w, 3)).astype(np.float32)
        depth = rng.uniform(1.0, MAX_DEPTH, (args.train_batch, h, w)).astype(np.float32)
        valid = rng.random((args.train_batch, h, w)) < 0.9
        tx = optax.adamw(**ADAMW)
        step_args = (params, tx.init(params), jnp.asarray(x), jnp.asarray(depth), jnp.asarray(valid))
        step, compile_s = compiled_with_seconds(
            make_train_step(DepthAnythingV2(ours_cfg["official"]), tx), *step_args)
        ours = lambda: jax.block_until_ready(step(*step_args))  # noqa: E731
        theirs = None
        if "official" in references:
            model = references["official"][1]
            t = [torch.from_numpy(np.ascontiguousarray(a)).to(torch_device)
                 for a in (x.transpose(0, 3, 1, 2), depth, valid)]
            official_step = torch_train_step(model, args.amp)
            theirs = lambda: official_step(*t)  # noqa: E731
        row = bench_pair("official" if theirs else "none", ours, theirs, flops_of(step), args.repeats,
                         args.warmup, args.train_batch)
        row.update(kind="train_step", size=[h, w], compile_s=compile_s)
        rows.append(row)

    print(f"{'kind':>10} | {'reference':>12} | {'size':>9} | batch | ours ms | theirs ms | ours/theirs "
          f"| GFLOP/s | % peak | compile s | max diff")
    for r in rows:
        pct = 100 * r["ours_gflops"] / peak["xla_gflops"]
        r["peak_pct"] = pct
        cells = [f"{r['kind']:>10}", f"{r['reference']:>12}", f"{r['size'][0]:>4}x{r['size'][1]:<4}",
                 f"{r['batch']:>5}", f"{r['ours_ms']:>7.1f}",
                 f"{r.get('theirs_ms', float('nan')):>9.1f}", f"{r.get('ours_over_theirs', float('nan')):>11.2f}",
                 f"{r['ours_gflops']:>7.1f}", f"{pct:>6.0f}",
                 f"{r['compile_s']:>9.1f}"]
        diff = r.get("max_diff_over_max")  # None: nothing to compare (train step, --no-torch)
        cells.append(f"{'-':>8}" if diff is None else f"{diff:>8.1e}")
        print(" | ".join(cells))
    summary.update(matmul_peak=peak, results=rows)
    write_json(args.json, summary)
    return summary


if __name__ == "__main__":
    main()
