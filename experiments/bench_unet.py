"""Times the MTSA-UNet against its PyTorch twin (experiments/unet_torch.py) per input size and
batch: forward and train-step wall time, the GFLOP/s they reach (XLA's FLOP count) as a fraction
of the machine's measured matmul peak, and jit compile times (init, forward, train step).

    python experiments/bench_unet.py --preset paper --sizes 256x320 512x640 --batch 1 4 \\
        --repeats 5 --threads 2 --json experiments/results/bench_unet.json

Prints the matmul peak (a jitted float32 N x N matmul, N = --peak-size, and torch.mm of the
same), then one row per (size, batch): ours ms, torch ms, ours / torch for the forward and the
train step, with our GFLOP/s and % of the XLA peak; then the compile times and how far the two
forwards are apart (max |ours - torch| over the outputs). --json FILE writes every figure (also
per-image times, and the twin's GFLOP/s on our FLOP count: the same arithmetic).

Forward: eval mode (running BatchNorm statistics); torch under inference_mode. Train step: a
full Stage I update in both: forward in train mode (batch statistics), L1 reconstruction +
cross-entropy + L1 saturation-vs-input-gradient loss, backward, AdaDelta update (optax.adadelta
and torch.optim.Adadelta with `ADADELTA`). Both run the same weights (ours, random, copied into
the twin) on the same random uint16 raw frames (timings do not depend on the content). Times are
wall-clock medians over --repeats calls after --warmup untimed ones, ours and the twin's calls
interleaved (A, B, A, B, ...) so that a drift in the machine's load hits both alike.

Threads: --threads N (default: the CPUs this process may run on) gives both N intra-op
threads: torch.set_num_threads(N), and XLA's CPU thread pool through the PJRT_NPROC
environment variable, which jaxlib reads when its CPU client starts (so it must be set before
JAX's first computation; this script sets it first thing, and prints the size of the pool it
got). OpenMP: torch's threads wait passively (OMP_WAIT_POLICY=PASSIVE, unless the environment
sets it): with the default spinning, torch's calls interleaved with XLA's in one process were up
to 50x slower (measured on a busy 2-core machine: a 256^2 matmul 0.3 ms alone, 15 ms between XLA
calls; 0.4 ms passive). OMP_WAIT_POLICY=ACTIVE compares. --no-torch times ours only.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import os
import platform

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
    xla_pool_threads,
)
from irdepth_jax.config import get_config
from irdepth_jax.models.unet import MTSAUNet

ADADELTA = {"learning_rate": 1.0, "rho": 0.9, "eps": 1e-6}
"""Stage I's AdaDelta (irdepth_jax.train.state) for both; torch.optim.Adadelta calls the rate lr."""


def parse_size(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        message = f"size must look like 256x320 (HxW), got {text!r}"
        raise argparse.ArgumentTypeError(message) from None
    return h, w


def stage1_loss(out, target, labels):
    """Our side of the benchmark's Stage I loss (NHWC outputs of MTSAUNet)."""
    ce = optax.softmax_cross_entropy_with_integer_labels(out["seg_logits"], labels).mean()
    return (
        jnp.abs(out["recon"] - target).mean()
        + ce
        + jnp.abs(out["saturation"] - out["input_gradient"]).mean()
    )


def stage1_loss_torch(out, target, labels):
    """The twin's side of `stage1_loss` (NCHW outputs; target (B, 1, H, W), labels (B, H, W))."""
    import torch.nn.functional as F

    return (
        (out["recon"] - target).abs().mean()
        + F.cross_entropy(out["seg_logits"], labels)
        + (out["saturation"] - out["input_gradient"]).abs().mean()
    )


def make_train_step(model: MTSAUNet, tx: optax.GradientTransformation):
    """Jitted (params, batch_stats, opt_state, raw, target, labels) -> the same updated + loss."""

    def loss_fn(params, batch_stats, raw, target, labels):
        out, updates = model.apply(
            {"params": params, "batch_stats": batch_stats}, raw, train=True, mutable=["batch_stats"]
        )
        return stage1_loss(out, target, labels), updates["batch_stats"]

    @jax.jit
    def train_step(params, batch_stats, opt_state, raw, target, labels):
        (loss, batch_stats), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            params, batch_stats, raw, target, labels
        )
        updates, opt_state = tx.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), batch_stats, opt_state, loss

    return train_step


def make_torch_train_step(model, optimizer):
    """The twin's train step: (raw, target, labels) tensors -> loss tensor (updates in place)."""

    def step(raw, target, labels):
        model.train()
        optimizer.zero_grad(set_to_none=True)
        loss = stage1_loss_torch(model(raw), target, labels)
        loss.backward()
        optimizer.step()
        return loss

    return step


def bench_case(model, size, batch: int, repeats: int, warmup: int, with_torch: bool) -> dict:
    h, w = size
    rng = np.random.default_rng(0)
    raw_np = rng.integers(2000, 9000, (batch, h, w)).astype(np.uint16)
    target_np = rng.random((batch, h, w, 1), dtype=np.float32)
    labels_np = rng.integers(0, model.cfg.num_classes, (batch, h, w)).astype(np.int32)
    raw, target, labels = jnp.asarray(raw_np), jnp.asarray(target_np), jnp.asarray(labels_np)

    init, init_s = compiled_with_seconds(jax.jit(model.init), jax.random.key(0), raw)
    variables = init(jax.random.key(0), raw)
    tx = optax.adadelta(**ADADELTA)
    opt_state = tx.init(variables["params"])
    # data passed as arguments: closed-over arrays would become constants XLA tries to fold
    step_args = (variables["params"], variables["batch_stats"], opt_state, raw, target, labels)
    forward, fwd_s = compiled_with_seconds(
        jax.jit(functools.partial(model.apply, train=False)), variables, raw
    )
    train_step, train_s = compiled_with_seconds(make_train_step(model, tx), *step_args)
    fwd_fns = [lambda: jax.block_until_ready(forward(variables, raw))]
    train_fns = [lambda: jax.block_until_ready(train_step(*step_args))]

    result = {
        "size": [h, w], "batch": batch,
        "compile_init_s": init_s, "compile_fwd_s": fwd_s, "compile_train_s": train_s,
        "fwd_flops": flops_of(forward), "train_flops": flops_of(train_step),
    }
    if with_torch:
        import torch

        from experiments.unet_torch import MTSAUNetTorch, load_flax_params

        twin = load_flax_params(MTSAUNetTorch(model.cfg), jax.device_get(variables))
        t_raw = torch.from_numpy(raw_np)
        t_target = torch.from_numpy(np.ascontiguousarray(target_np.transpose(0, 3, 1, 2)))
        t_labels = torch.from_numpy(labels_np.astype(np.int64))
        ours = forward(variables, raw)
        with torch.inference_mode():
            theirs = twin.eval()(t_raw)
        result["fwd_max_abs_diff"] = max(
            float(np.abs(np.asarray(ours[k]) - theirs[k].permute(0, 2, 3, 1).numpy()).max())
            for k in ours
        )

        def torch_forward():
            twin.eval()
            with torch.inference_mode():
                twin(t_raw)

        adadelta = dict(ADADELTA)
        optimizer = torch.optim.Adadelta(twin.parameters(), lr=adadelta.pop("learning_rate"), **adadelta)
        torch_step = make_torch_train_step(twin, optimizer)
        fwd_fns.append(torch_forward)
        train_fns.append(lambda: torch_step(t_raw, t_target, t_labels))

    fwd = interleaved_medians(fwd_fns, repeats, warmup)
    train = interleaved_medians(train_fns, repeats, warmup)
    for name, seconds in (("fwd", fwd), ("train", train)):
        result[f"{name}_ours_ms"] = 1e3 * seconds[0]
        result[f"{name}_ours_ms_per_img"] = 1e3 * seconds[0] / batch
        result[f"{name}_ours_gflops"] = result[f"{name}_flops"] / seconds[0] / 1e9
        if with_torch:
            result[f"{name}_torch_ms"] = 1e3 * seconds[1]
            result[f"{name}_torch_ms_per_img"] = 1e3 * seconds[1] / batch
            result[f"{name}_ours_over_torch"] = seconds[0] / seconds[1]
            result[f"{name}_torch_gflops"] = result[f"{name}_flops"] / seconds[1] / 1e9
    return result


def _cell(value, spec: str, width: int) -> str:
    return f"{'-':>{width}}" if value is None else f"{value:>{width}{spec}}"


def print_tables(results: list[dict], peak: float) -> None:
    columns = [  # (header, key, format)
        ("fwd ours ms", "fwd_ours_ms", ".1f"), ("fwd torch ms", "fwd_torch_ms", ".1f"),
        ("fwd ours/torch", "fwd_ours_over_torch", ".2f"), ("fwd GFLOP/s", "fwd_ours_gflops", ".1f"),
        ("fwd % peak", "fwd_peak_pct", ".0f"),
        ("train ours ms", "train_ours_ms", ".1f"), ("train torch ms", "train_torch_ms", ".1f"),
        ("train ours/torch", "train_ours_over_torch", ".2f"),
        ("train GFLOP/s", "train_ours_gflops", ".1f"), ("train % peak", "train_peak_pct", ".0f"),
    ]
    compile_columns = [
        ("compile init s", "compile_init_s", ".1f"), ("compile fwd s", "compile_fwd_s", ".1f"),
        ("compile train s", "compile_train_s", ".1f"), ("fwd GFLOP", "fwd_flops_g", ".2f"),
        ("train GFLOP", "train_flops_g", ".2f"), ("max |ours - torch|", "fwd_max_abs_diff", ".1e"),
    ]
    for r in results:
        for name in ("fwd", "train"):
            r[f"{name}_peak_pct"] = 100.0 * r[f"{name}_ours_gflops"] / peak
            r[f"{name}_flops_g"] = r[f"{name}_flops"] / 1e9
    for table in (columns, compile_columns):
        header = " | ".join([f"{'size':>9}", "batch"] + [name for name, _, _ in table])
        print(header)
        print("-" * len(header))
        for r in results:
            cells = [f"{r['size'][0]:>4}x{r['size'][1]:<4}", f"{r['batch']:>5}"]
            cells += [_cell(r.get(key), spec, len(name)) for name, key, spec in table]
            print(" | ".join(cells))
        print()


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--preset", default="paper", help="config preset (paper | small | tiny)")
    parser.add_argument(
        "--sizes", nargs="+", type=parse_size, default=[(256, 320), (512, 640)], help="HxW sizes"
    )
    parser.add_argument("--batch", nargs="+", type=int, default=[1, 4], help="images per call")
    parser.add_argument("--repeats", type=int, default=5, help="timed calls per measurement")
    parser.add_argument("--warmup", type=int, default=2, help="untimed calls before them")
    parser.add_argument(
        "--threads", type=int, default=usable_cpus(),
        help="intra-op threads of torch and XLA (default: the CPUs this process may use)",
    )
    parser.add_argument("--peak-size", type=int, default=2048, help="N of the N x N peak matmul")
    parser.add_argument("--no-rgg", action="store_true", help="time the use_rgg=False ablation")
    parser.add_argument("--no-torch", action="store_true", help="time ours only (no PyTorch twin)")
    parser.add_argument("--json", metavar="FILE", help="also write the figures to FILE")
    args = parser.parse_args(argv)

    with_torch = not args.no_torch
    versions = set_threads(args.threads, with_torch)

    cfg = get_config(args.preset).unet
    if args.no_rgg:
        cfg = dataclasses.replace(cfg, use_rgg=False)
    model = MTSAUNet(cfg)
    device = jax.devices()[0]
    summary = {
        "preset": args.preset, "use_rgg": cfg.use_rgg, "repeats": args.repeats,
        "threads": args.threads, "device": f"{device.platform}:{device.device_kind}",
        "cpu": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(), **versions,
    }
    title = "MTSA-UNet vs its PyTorch twin" if with_torch else "MTSA-UNet"
    print(f"{title}: " + " ".join(f"{k}={v}" for k, v in summary.items()))
    peak = matmul_peak(args.peak_size, args.repeats, args.warmup, with_torch)
    summary["xla_pool_threads"] = xla_pool_threads()
    print(f"XLA intra-op pool threads: {summary['xla_pool_threads']}; matmul peak, float32 "
          f"{args.peak_size}^2: XLA {peak['xla_gflops']:.1f} GFLOP/s"
          + (f", torch {peak['torch_gflops']:.1f} GFLOP/s" if with_torch else ""))
    print("times: medians per call (the whole batch); GFLOP/s and % peak: ours, from XLA's FLOP count")
    print()
    results = [
        bench_case(model, size, batch, args.repeats, args.warmup, with_torch)
        for size in args.sizes
        for batch in args.batch
    ]
    print_tables(results, peak["xla_gflops"])
    summary.update(matmul_peak=peak, results=results)
    write_json(args.json, summary)
    return summary


if __name__ == "__main__":
    main()
