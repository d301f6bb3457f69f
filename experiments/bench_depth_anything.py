"""Depth Anything V2, ours (jitted Flax) vs the PyTorch references, on the same random weights:
forward latency per input size against transformers and the official code, and one Stage II
training step (SiLog + AdamW, metric head) against the official metric-depth model.

    python experiments/bench_depth_anything.py --encoder vits --sizes 518x518 364x644 \\
        --train-batch 2 --threads 2 --json experiments/results/bench_depth_anything.json

--official-repo: a checkout of github.com/DepthAnything/Depth-Anything-V2 (the official code is
not a package; its `metric_depth/depth_anything_v2` is imported from there); default
experiments/third_party/Depth-Anything-V2 or $IRDEPTH_OFFICIAL_DA (`OFFICIAL_REPO`; never
committed). --references official (or transformers) compares against that one only; the train
step runs against the official code when it is a reference, else against transformers' port.
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
float32) and --amp (torch autocast bf16 on the official side); see docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
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

from irdepth_experiments.bench_common import (
    Worker,
    compiled_with_seconds,
    flops_of,
    interleaved_medians,
    matmul_call,
    peak_gflops,
    usable_cpus,
    versions,
    write_json,
)
from irdepth_experiments.bench_unet import parse_size
from irdepth_jax.losses import silog_loss
from irdepth_jax.models.depth_anything import DepthAnythingV2, depth_anything_config
from irdepth_jax.weights import load_depth_anything
from irdepth_jax.xla_cpu import training_layers

OFFICIAL_REPO = os.environ.get("IRDEPTH_OFFICIAL_DA", os.path.join(
    os.path.dirname(os.path.abspath(__file__)), "third_party", "Depth-Anything-V2"))
"""Where the official code is looked for: a checkout of github.com/DepthAnything/Depth-Anything-V2
(never committed here: experiments/third_party/ is git-ignored; a device run carries it) or the
folder IRDEPTH_OFFICIAL_DA names. Without it the PyTorch side is transformers' port."""


def official_code_present(repo: str = OFFICIAL_REPO) -> bool:
    """Whether `repo` holds the official metric-depth model code."""
    return os.path.isfile(os.path.join(repo, "metric_depth", "depth_anything_v2", "dpt.py"))
MAX_DEPTH = 80.0
ADAMW = {"learning_rate": 5e-6, "weight_decay": 0.01}


def official_metric_model(repo: str, cfg, state_dict):
    """The official metric-depth DepthAnythingV2 of the checkout `repo`, with `state_dict`."""
    if not official_code_present(repo):
        raise SystemExit(f"--official-repo {repo}: no official Depth Anything V2 code there (a checkout of "
                         "github.com/DepthAnything/Depth-Anything-V2; or IRDEPTH_OFFICIAL_DA=DIR)")
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
        with training_layers():  # the layers the library's own train step uses
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


def torch_train_step(model, amp: bool, forward=None):
    """The PyTorch side's train step: `silog_loss_torch` of `forward(images)` (default
    `model(images)`, the official model's call), torch.optim.AdamW."""
    import torch

    forward = forward or model

    optimizer = torch.optim.AdamW(model.parameters(), lr=ADAMW["learning_rate"],
                                  weight_decay=ADAMW["weight_decay"])
    device_type = next(model.parameters()).device.type

    def step(images, depth, valid):
        model.train()
        optimizer.zero_grad(set_to_none=True)
        with torch.autocast(device_type, dtype=torch.bfloat16, enabled=amp):
            pred = forward(images)
        loss = silog_loss_torch(pred.float(), depth, valid)
        loss.backward()
        optimizer.step()
        if device_type == "cuda":
            torch.cuda.synchronize()
        return loss

    return step


def forward_name(size) -> str:
    return f"forward_{size[0]}x{size[1]}"


def bench_inputs(sizes, batch: int, train_size, train_batch: int):
    """The same random images (B, H, W, 3) per size, and the train step's images, depths in
    [1, MAX_DEPTH) and valid mask, for every side."""
    images = {tuple(size): np.random.default_rng(0).normal(size=(batch, *size, 3)).astype(np.float32)
              for size in sizes}
    rng = np.random.default_rng(1)
    h, w = train_size
    train = (rng.normal(size=(train_batch, h, w, 3)).astype(np.float32),
             rng.uniform(1.0, MAX_DEPTH, (train_batch, h, w)).astype(np.float32),
             rng.random((train_batch, h, w)) < 0.9)
    return images, train


def setup_ours(weights: str | None, encoder: str, mode: str, dtype: str, remat: bool, sizes,
               batch: int, train_size, train_batch: int, peak_size: int):
    """`Worker` set-up of our side: weights from the transformers model saved at `weights`
    (None: random, key 0), position embeddings resampled as `mode`; calls 'forward_HxW' per
    size, 'train' (when train_batch) and 'matmul'; info: compile seconds and FLOPs per call."""
    cfg = dataclasses.replace(depth_anything_config(encoder, metric=True, max_depth=MAX_DEPTH),
                              pos_embed_mode=mode, dtype=dtype, remat=remat)
    model = DepthAnythingV2(cfg)
    images, (x, depth, valid) = bench_inputs(sizes, batch, train_size, train_batch)
    if weights:
        _, params = load_depth_anything(weights, kind="metric", max_depth=MAX_DEPTH)
    else:
        x0 = jnp.zeros((1, *(sizes[0] if sizes else train_size), 3), jnp.float32)
        params = jax.jit(model.init)(jax.random.key(0), x0)["params"]
    calls, info = {}, {}
    for size, array in images.items():
        xs = jnp.asarray(array)
        forward, compile_s = compiled_with_seconds(jax.jit(model.apply), {"params": params}, xs)
        name = forward_name(size)
        calls[name] = functools.partial(lambda f, xs: f({"params": params}, xs).block_until_ready(),
                                        forward, xs)
        info[name] = {"compile_s": compile_s, "flops": flops_of(forward)}
    if train_batch:
        tx = optax.adamw(**ADAMW)
        step_args = (params, tx.init(params), jnp.asarray(x), jnp.asarray(depth), jnp.asarray(valid))
        step, compile_s = compiled_with_seconds(make_train_step(model, tx), *step_args)
        calls["train"] = lambda: jax.block_until_ready(step(*step_args)[-1])
        info["train"] = {"compile_s": compile_s, "flops": flops_of(step)}
    calls["matmul"] = matmul_call(peak_size, "jax", dtype)
    device = jax.devices()[0]
    info["device"] = f"{device.platform}:{device.device_kind}"
    return calls, info


def setup_reference(kind: str, weights: str, official_repo: str | None, encoder: str, amp: bool,
                    sizes, batch: int, train_size, train_batch: int, peak_size: int):
    """`Worker` set-up of a PyTorch side, `kind` 'transformers' (its port) or 'official' (the
    official metric model, `official_repo`), forward and (train_batch > 0) 'train', with the
    weights saved at `weights`; on CUDA when torch sees a GPU. The same call names as
    `setup_ours`."""
    import torch
    from transformers import DepthAnythingForDepthEstimation

    from irdepth_experiments.torch_reference import hf_to_official

    device = "cuda" if torch.cuda.is_available() else "cpu"
    hf = DepthAnythingForDepthEstimation.from_pretrained(weights).eval()
    if kind == "official":
        cfg = depth_anything_config(encoder, metric=True, max_depth=MAX_DEPTH)
        model = official_metric_model(official_repo, cfg, hf_to_official(hf)).to(device).eval()
    else:
        model = hf.to(device)
    images, train = bench_inputs(sizes, batch, train_size, train_batch)

    def forward(pixels):
        with torch.inference_mode(), torch.autocast(device, torch.bfloat16, enabled=amp):
            out = model(pixel_values=pixels).predicted_depth if kind == "transformers" else model(pixels)
        if device == "cuda":
            torch.cuda.synchronize()
        return out

    calls = {}
    for size, array in images.items():
        pixels = torch.from_numpy(np.ascontiguousarray(array.transpose(0, 3, 1, 2))).to(device)
        calls[forward_name(size)] = functools.partial(forward, pixels)
    if train_batch:
        x, depth, valid = (torch.from_numpy(np.ascontiguousarray(a)).to(device)
                           for a in (train[0].transpose(0, 3, 1, 2), *train[1:]))
        step = torch_train_step(model, amp, None if kind == "official" else
                                lambda pixels: model(pixel_values=pixels).predicted_depth)
        calls["train"] = lambda: step(x, depth, valid)
    calls["matmul"] = matmul_call(peak_size, "torch", "bfloat16" if amp else "float32", device)
    return calls, {"threads": torch.get_num_threads(), "torch_device": device}


def bench_pair(name, timers, flops, repeats, warmup, batch) -> dict:
    seconds = interleaved_medians(timers, repeats, warmup)
    row = {"reference": name, "batch": batch, "ours_ms": 1e3 * seconds[0],
           "ours_images_per_s": batch / seconds[0], "ours_gflops": flops / seconds[0] / 1e9}
    if len(timers) > 1:
        row.update(theirs_ms=1e3 * seconds[1], theirs_images_per_s=batch / seconds[1],
                   ours_over_theirs=seconds[0] / seconds[1])
    return row


def _parse_args(argv) -> argparse.Namespace:
    """The command line (`--help` explains it)."""
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--encoder", default="vits", help="vits | vitb | vitl | vitg | small | tiny")
    parser.add_argument("--sizes", nargs="*", type=parse_size, default=[(518, 518), (364, 644)],
                        help="HxW forward input sizes, multiples of 14 (none: the train step only)")
    parser.add_argument("--batch", type=int, default=1, help="images per forward call")
    parser.add_argument("--train-batch", type=int, default=2, help="images per train step (0: none)")
    parser.add_argument("--train-size", type=parse_size, default=(518, 518), help="train-step HxW")
    parser.add_argument("--dtype", default="float32", choices=("float32", "bfloat16"),
                        help="our compute dtype (params stay float32)")
    parser.add_argument("--amp", action="store_true", help="torch autocast bf16 (the official side)")
    parser.add_argument("--remat", action="store_true", help="rematerialise our ViT blocks")
    parser.add_argument("--official-repo", metavar="DIR", default=OFFICIAL_REPO,
                        help="checkout of the official code (default: experiments/third_party/"
                             "Depth-Anything-V2 or $IRDEPTH_OFFICIAL_DA; not committed)")
    parser.add_argument("--references", nargs="+", choices=("transformers", "official"),
                        default=["transformers", "official"],
                        help="the PyTorch sides to compare with; the train step runs against the "
                             "official code when it is one of them, else against transformers")
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--threads", type=int, default=usable_cpus(),
                        help="intra-op threads of torch and XLA (CPU)")
    parser.add_argument("--peak-size", type=int, default=2048,
                        help="N of the N x N peak matmul (8192 suits a GPU)")
    parser.add_argument("--no-torch", action="store_true", help="time ours only")
    parser.add_argument("--default-malloc", action="store_true",
                        help="leave glibc's malloc as it is in both sides' processes (default: both "
                             "keep freed memory for reuse, irdepth_jax.hostmem)")
    parser.add_argument("--json", metavar="FILE", help="also write the figures to FILE")
    return parser.parse_args(argv)


def _print_table(rows: list[dict], peak: float) -> None:
    """Prints one line per row (and adds its share of the matmul `peak` as 'peak_pct')."""
    print(f"{'kind':>10} | {'reference':>12} | {'size':>9} | batch | ours ms | theirs ms | ours/theirs "
          f"| GFLOP/s | % peak | compile s | max diff")
    for r in rows:
        r["peak_pct"] = 100 * r["ours_gflops"] / peak
        cells = [f"{r['kind']:>10}", f"{r['reference']:>12}", f"{r['size'][0]:>4}x{r['size'][1]:<4}",
                 f"{r['batch']:>5}", f"{r['ours_ms']:>7.1f}"]
        for key, spec, width in (("theirs_ms", ".1f", 9), ("ours_over_theirs", ".2f", 11)):
            cells.append(f"{r[key]:>{width}{spec}}" if key in r else f"{'-':>{width}}")
        cells += [f"{r['ours_gflops']:>7.1f}", f"{r['peak_pct']:>6.0f}", f"{r['compile_s']:>9.1f}"]
        diff = r.get("max_diff_over_max")  # None: nothing to compare (train step, --no-torch)
        cells.append(f"{'-':>8}" if diff is None else f"{diff:>8.1e}")
        print(" | ".join(cells))


def main(argv=None) -> dict:
    args = _parse_args(argv)
    with_torch = not args.no_torch
    summary = {"encoder": args.encoder, "dtype": args.dtype, "amp": args.amp, "threads": args.threads,
               "processes": "one per side (Worker)", "keep_freed_memory": not args.default_malloc,
               "cpu": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
               **versions()}
    print("Depth Anything V2: " + " ".join(f"{k}={v}" for k, v in summary.items()))
    shape = dict(sizes=args.sizes, batch=args.batch, train_size=args.train_size,
                 train_batch=args.train_batch, peak_size=args.peak_size)
    # ours against the official code uses its position-embedding resampling, against
    # transformers the transformers one: every pair computes the same function
    refs = {name: name for name in args.references} if with_torch else {"none": "official"}
    train_ref = ("official" if "official" in refs else "transformers") if with_torch else "none"
    rows = []
    with tempfile.TemporaryDirectory() as weights, contextlib.ExitStack() as stack:
        if with_torch:
            from irdepth_experiments.torch_reference import random_hf_model

            base = depth_anything_config(args.encoder, metric=True, max_depth=MAX_DEPTH)
            random_hf_model(dataclasses.replace(base, pos_embed_mode="transformers")).save_pretrained(weights)
        for ref_name, mode in refs.items():
            ours = stack.enter_context(Worker(
                setup_ours, weights if with_torch else None, args.encoder, mode, args.dtype,
                args.remat, **{**shape, "train_batch": shape["train_batch"] if ref_name == train_ref else 0},
                threads=args.threads, keep_memory=not args.default_malloc))
            sides = [ours]
            if with_torch:
                sides.append(stack.enter_context(Worker(
                    setup_reference, ref_name, weights, args.official_repo, args.encoder, args.amp,
                    **{**shape, "train_batch": shape["train_batch"] if ref_name == train_ref else 0},
                    threads=args.threads, keep_memory=not args.default_malloc)))
            if "matmul_peak" not in summary:
                seconds = interleaved_medians([functools.partial(s.time, "matmul") for s in sides],
                                              args.repeats, args.warmup)
                summary["device"] = ours.info["device"]
                summary["matmul_peak"] = {"size": args.peak_size, "dtype": args.dtype,
                                          "xla_gflops": peak_gflops(args.peak_size, seconds[0])}
                if with_torch:
                    summary["matmul_peak"]["torch_gflops"] = peak_gflops(args.peak_size, seconds[1])
                    summary["torch_device"] = sides[1].info["torch_device"]
                print(f"device {summary['device']}; matmul peak, {args.dtype} {args.peak_size}^2: "
                      + ", ".join(f"{k} {v:.1f} GFLOP/s" for k, v in summary["matmul_peak"].items()
                                  if k.endswith("gflops")))
            sizes = {forward_name(size): size for size in args.sizes}
            names = list(sizes)
            if args.train_batch and ref_name == train_ref:
                names.append("train")
            for name in names:
                diff = None
                if with_torch and name != "train":
                    ref = sides[1].result(name).reshape(args.batch, -1)
                    out = ours.result(name).reshape(args.batch, -1)
                    diff = float(np.abs(out - ref).max() / np.abs(ref).max())
                train = name == "train"
                row = bench_pair(ref_name, [functools.partial(s.time, name) for s in sides],
                                 ours.info[name]["flops"], args.repeats, args.warmup,
                                 args.train_batch if train else args.batch)
                row.update(kind="train_step" if train else "forward",
                           size=list(args.train_size if train else sizes[name]),
                           compile_s=ours.info[name]["compile_s"], max_diff_over_max=diff)
                rows.append(row)
            stack.close()

    _print_table(rows, summary["matmul_peak"]["xla_gflops"])
    summary.update(results=rows)
    write_json(args.json, summary)
    return summary


if __name__ == "__main__":
    main()
