"""Times the MTSA-UNet against idiomatic PyTorch (experiments/unet_idiomatic.py) per input size
and batch: forward and train-step wall time, the GFLOP/s they reach (XLA's FLOP count) as a fraction
of the machine's measured matmul peak, and jit compile times (init, forward, train step).

    python experiments/bench_unet.py --preset paper --sizes 256x320 --batch 1 \\
        --repeats 7 --threads 2 --json experiments/results/bench_unet_idiomatic.json

Prints the matmul peak (a jitted float32 N x N matmul, N = --peak-size, and torch.mm of the
same), then one row per (size, batch): ours ms, torch ms, ours / torch for the forward and the
train step, with our GFLOP/s and % of the XLA peak; then the compile times and how far the two
forwards are apart (max |ours - torch| over the outputs). --json FILE writes every figure (also
per-image times, each side's min / max / spread over the repeats, and the twin's GFLOP/s on our
FLOP count: the same arithmetic).

Opponent: --opponent idiomatic (default) is the model as a PyTorch user writes it; --opponent
parity the parity twin of the numerical tests (experiments/unet_torch.py), which carries
operations that only match JAX's numerics (more operator calls and elementwise writes): the right
reference for tests, the wrong one for a speed claim. Equal work: each case compares XLA's FLOP
count of our forward and train step with torch.utils.flop_counter's of the opponent's; the
counts must agree within `EQUAL_WORK_TOLERANCE` (XLA counts elementwise operations too, torch's
counter only convolutions and matrix products), or the case fails. The train step's count for
this check is the model's own arithmetic (the step traced with plain Flax layers,
`train_nominal_flops`); the step timed runs the library's CPU training layers
(`xla_cpu.training_layers`), whose Winograd kernel gradients compute the same gradients with
fewer multiply-adds (`train_flops`, what GFLOP/s and % of peak are computed from).

Forward: eval mode (running BatchNorm statistics); torch under inference_mode. Train step: a
full Stage I update in both: forward in train mode (batch statistics), L1 reconstruction +
cross-entropy + L1 saturation-vs-input-gradient loss, backward, AdaDelta update (optax.adadelta
and torch.optim.Adadelta with `ADADELTA`). Both run the same weights (ours, random, copied into
the twin) on the same random images, 14-bit counts normalised as the pipeline's `unet_input`
does (timings do not depend on the content). Times are
wall-clock medians over --repeats calls after --warmup untimed ones, ours and the twin's calls
interleaved (A, B, A, B, ...) so that a drift in the machine's load hits both alike.

Processes: each side runs in a process of its own (`bench_common.Worker`), the parent only
alternates their calls; in one process each side ran among the other's threads and freed
memory (measured: our batch-4 train step 9.7 s between the twin's calls, 5.5 s alone).
Threads: --threads N (default: the CPUs this process may run on) gives both N intra-op
threads: OMP_NUM_THREADS for torch, and XLA's CPU thread pool through PJRT_NPROC (read when
jaxlib's CPU client starts; the pool's size is printed); nothing else is set for one side only.
--no-torch times ours only.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import os
import platform

import jax
import jax.numpy as jnp
import numpy as np
import optax

from irdepth_experiments.bench_common import (
    Worker,
    compiled_with_seconds,
    flops_of,
    interleaved_samples,
    matmul_call,
    peak_gflops,
    spread,
    torch_flops,
    usable_cpus,
    versions,
    write_json,
    xla_pool_threads,
)
from irdepth_jax.config import get_config
from irdepth_jax.models.unet import MTSAUNet
from irdepth_jax.runs.variables import init_key
from irdepth_jax.xla_cpu import native_requested, training_layers

ADADELTA = {"learning_rate": 1.0, "rho": 0.9, "eps": 1e-6}
"""Stage I's AdaDelta (irdepth_jax.train.state) for both; torch.optim.Adadelta calls the rate lr."""

EQUAL_WORK_TOLERANCE = 0.15
"""Largest accepted |XLA's FLOPs / torch's - 1| of a forward or train step (the train step's
nominal count, plain Flax layers). The counts differ by design: XLA's skips the zero padding of
3x3 convolutions (which torch's counter counts) and counts elementwise operations (which
torch's does not). Measured with the idiomatic opponent, `paper` at 256x320: XLA / torch 0.990
forward, 0.995 train step (the outputs agree to 2e-7); a missing decoder branch would be ~0.7."""

OPPONENTS = ("idiomatic", "parity")


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


def make_train_step(model: MTSAUNet, tx: optax.GradientTransformation, library_layers: bool = True):
    """Jitted (params, batch_stats, opt_state, raw, target, labels) -> the same updated + loss;
    with the layers the library's own train step uses (`library_layers`), or plain Flax's."""

    def loss_fn(params, batch_stats, raw, target, labels):
        with training_layers() if library_layers else contextlib.nullcontext():
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


def unet_config(preset: str, use_rgg: bool):
    return dataclasses.replace(get_config(preset).unet, use_rgg=use_rgg)


def bench_inputs(num_classes: int, size, batch: int):
    """The same random images, targets and labels for both sides: (B, H, W) float32 (14-bit
    counts / (2^14 - 1), the UNet's input, which the twins use as is), (B, H, W, 1) float32,
    (B, H, W) int32 (timings do not depend on the content)."""
    rng = np.random.default_rng(0)
    h, w = size
    return ((rng.integers(2000, 9000, (batch, h, w)) / (2**14 - 1)).astype(np.float32),
            rng.random((batch, h, w, 1), dtype=np.float32),
            rng.integers(0, num_classes, (batch, h, w)).astype(np.int32))


def init_variables(model: MTSAUNet, raw):
    """Our random weights (`init_key(0)`, as the library's models), the ones both sides run;
    (variables, compile seconds)."""
    init, seconds = compiled_with_seconds(jax.jit(model.init), init_key(0), raw)
    return init(init_key(0), raw), seconds


def setup_ours(preset: str, use_rgg: bool, size, batch: int, peak_size: int, train_only: bool = False):
    """`Worker` set-up of our side: calls 'forward' (eval mode), 'train' (one AdaDelta step)
    and 'matmul'; info: compile seconds, XLA's FLOP counts, the XLA pool's threads, device.
    `train_only`: the 'train' call and its info alone (no forward, matmul or plain-layer step
    compiled: the GPU run's Stage I figure)."""
    model = MTSAUNet(unet_config(preset, use_rgg))
    raw, target, labels = (jnp.asarray(a) for a in bench_inputs(model.cfg.num_classes, size, batch))
    variables, init_s = init_variables(model, raw)
    tx = optax.adadelta(**ADADELTA)
    # data passed as arguments: closed-over arrays would become constants XLA tries to fold
    step_args = (variables["params"], variables["batch_stats"], tx.init(variables["params"]), raw,
                 target, labels)
    train_step, train_s = compiled_with_seconds(make_train_step(model, tx), *step_args)
    train = {"train": lambda: jax.block_until_ready(train_step(*step_args)[-1])}
    if train_only:
        return train, {"compile_init_s": init_s, "compile_train_s": train_s, "train_flops": flops_of(train_step)}
    forward, fwd_s = compiled_with_seconds(jax.jit(functools.partial(model.apply, train=False)),
                                           variables, raw)
    device = jax.devices()[0]
    calls = {"forward": lambda: jax.block_until_ready(forward(variables, raw)), **train,
             "matmul": matmul_call(peak_size, "jax")}
    info = {"compile_init_s": init_s, "compile_fwd_s": fwd_s, "compile_train_s": train_s,
            "fwd_flops": flops_of(forward), "train_flops": flops_of(train_step),
            "train_nominal_flops": flops_of(make_train_step(model, tx, library_layers=False)
                                            .lower(*step_args).compile()),
            "xla_pool_threads": xla_pool_threads(), "device": f"{device.platform}:{device.device_kind}"}
    return calls, info


def torch_model(cfg, opponent: str):
    """The PyTorch opponent (`OPPONENTS`) of config `cfg`, random weights."""
    if opponent == "idiomatic":
        from irdepth_experiments.unet_idiomatic import MTSAUNetIdiomatic

        return MTSAUNetIdiomatic(cfg)
    if opponent == "parity":
        from irdepth_experiments.unet_torch import MTSAUNetTorch

        return MTSAUNetTorch(cfg)
    raise ValueError(f"unknown opponent {opponent!r} (one of {OPPONENTS})")


def setup_twin(preset: str, use_rgg: bool, size, batch: int, peak_size: int, opponent: str = "idiomatic"):
    """`Worker` set-up of the PyTorch opponent with our weights: the same calls as `setup_ours`
    (forward outputs NCHW); info: torch's FLOP counts of one forward and one train step (on a
    copy of the model, so that the timed one starts from our weights)."""
    import copy

    import torch

    from irdepth_experiments.unet_torch import load_flax_params

    cfg = unet_config(preset, use_rgg)
    raw, target, labels = bench_inputs(cfg.num_classes, size, batch)
    variables, _ = init_variables(MTSAUNet(cfg), jnp.asarray(raw))
    twin = load_flax_params(torch_model(cfg, opponent), jax.device_get(variables))
    t_raw = torch.from_numpy(raw)
    t_target = torch.from_numpy(np.ascontiguousarray(target.transpose(0, 3, 1, 2)))
    t_labels = torch.from_numpy(labels.astype(np.int64))
    adadelta = dict(ADADELTA)
    optimizer = torch.optim.Adadelta(twin.parameters(), lr=adadelta.pop("learning_rate"), **adadelta)
    train_step = make_torch_train_step(twin, optimizer)

    def forward(model=twin):
        model.eval()
        with torch.inference_mode():
            return model(t_raw)

    counted = copy.deepcopy(twin)
    counted_opt = torch.optim.Adadelta(counted.parameters(), lr=ADADELTA["learning_rate"], **adadelta)
    flops = {"fwd_torch_flops": torch_flops(lambda: forward(counted)),
             "train_torch_flops": torch_flops(lambda: make_torch_train_step(counted, counted_opt)(
                 t_raw, t_target, t_labels))}
    calls = {"forward": forward, "train": lambda: train_step(t_raw, t_target, t_labels),
             "matmul": matmul_call(peak_size, "torch")}
    return calls, {"threads": torch.get_num_threads(), "torch": torch.__version__, **flops}


def check_equal_work(result: dict) -> None:
    """Writes `<fwd|train>_xla_over_torch_flops` into a case's `result` (the train step's of its
    nominal count, plain Flax layers); raises RuntimeError where the two FLOP counts differ by
    more than `EQUAL_WORK_TOLERANCE`."""
    for key, ours in (("fwd", "fwd_flops"), ("train", "train_nominal_flops")):
        ratio = result[ours] / result[f"{key}_torch_flops"]
        result[f"{key}_xla_over_torch_flops"] = ratio
        if abs(ratio - 1) > EQUAL_WORK_TOLERANCE:
            raise RuntimeError(f"unequal work: {key} XLA {result[ours]:.4g} FLOPs, torch "
                               f"{result[f'{key}_torch_flops']:.4g} (ratio {ratio:.3f}, tolerance "
                               f"{EQUAL_WORK_TOLERANCE})")


def bench_case(cfg_args: tuple, size, batch: int, repeats: int, warmup: int, threads: int,
               with_torch: bool, peak_size: int | None, keep_memory: bool = True,
               one_at_a_time: bool = False, opponent: str = "idiomatic") -> dict:
    """One (size, batch): ours and (with_torch) the `opponent`, each in its own `Worker`, their
    calls interleaved. Measures the matmul peak too when `peak_size` is given. `one_at_a_time`:
    for cases where the two processes do not fit in memory together, ours runs all its calls and
    exits before the twin's process starts (medians of each, not interleaved)."""
    args = (*cfg_args, size, batch, peak_size or 256)
    setups = [(setup_ours, {})] + ([(setup_twin, {"opponent": opponent})] if with_torch else [])
    calls = ["forward", "train"] + (["matmul"] if peak_size else [])
    result = {"size": list(size), "batch": batch, "interleaved": not one_at_a_time}
    if one_at_a_time:
        samples, forwards, infos = {name: [] for name in calls}, [], []
        for setup, kwargs in setups:
            with Worker(setup, *args, threads=threads, keep_memory=keep_memory, **kwargs) as side:
                infos.append(side.info)
                forwards.append(side.result("forward") if with_torch else None)
                for name in calls:
                    samples[name] += interleaved_samples([functools.partial(side.time, name)],
                                                         repeats, warmup)
    else:
        with contextlib.ExitStack() as stack:
            sides = [stack.enter_context(Worker(setup, *args, threads=threads, keep_memory=keep_memory,
                                                **kwargs)) for setup, kwargs in setups]
            infos = [side.info for side in sides]
            forwards = [side.result("forward") for side in sides] if with_torch else []
            samples = {name: interleaved_samples([functools.partial(s.time, name) for s in sides],
                                                 repeats, warmup) for name in calls}
    seconds = {name: [float(np.median(t)) for t in times] for name, times in samples.items()}
    result.update(infos[0])
    if with_torch:
        result.update({k: infos[1][k] for k in ("fwd_torch_flops", "train_torch_flops")})
        check_equal_work(result)
        ours, theirs = forwards
        result["fwd_max_abs_diff"] = max(float(np.abs(v - theirs[k].transpose(0, 2, 3, 1)).max())
                                         for k, v in ours.items())
    for name, key in (("forward", "fwd"), ("train", "train")):
        ours_s = seconds[name][0]
        result[f"{key}_ours_seconds"] = spread(samples[name][0])
        if with_torch:
            result[f"{key}_torch_seconds"] = spread(samples[name][1])
        result[f"{key}_ours_ms"] = 1e3 * ours_s
        result[f"{key}_ours_ms_per_img"] = 1e3 * ours_s / batch
        result[f"{key}_ours_gflops"] = result[f"{key}_flops"] / ours_s / 1e9
        if with_torch:
            torch_s = seconds[name][1]
            result[f"{key}_torch_ms"] = 1e3 * torch_s
            result[f"{key}_torch_ms_per_img"] = 1e3 * torch_s / batch
            result[f"{key}_ours_over_torch"] = ours_s / torch_s
            result[f"{key}_torch_gflops"] = result[f"{key}_flops"] / torch_s / 1e9
    if peak_size:
        result["matmul_peak"] = {"size": peak_size,
                                 "xla_gflops": peak_gflops(peak_size, seconds["matmul"][0])}
        if with_torch:
            result["matmul_peak"]["torch_gflops"] = peak_gflops(peak_size, seconds["matmul"][1])
            result["torch_threads"] = infos[1]["threads"]
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
        ("fwd XLA/torch FLOPs", "fwd_xla_over_torch_flops", ".3f"),
        ("train XLA/torch FLOPs", "train_xla_over_torch_flops", ".3f"),
    ]
    spread_columns = [(f"{key} {side} spread %", key, side) for key in ("fwd", "train") for side in ("ours", "torch")]
    for r in results:
        for name in ("fwd", "train"):
            r[f"{name}_peak_pct"] = 100.0 * r[f"{name}_ours_gflops"] / peak
            r[f"{name}_flops_g"] = r[f"{name}_flops"] / 1e9
    for r in results:
        for _, key, side in spread_columns:
            if f"{key}_{side}_seconds" in r:
                r[f"{key}_{side}_spread_pct"] = r[f"{key}_{side}_seconds"]["spread_pct"]
    spread_table = [(name, f"{key}_{side}_spread_pct", ".0f") for name, key, side in spread_columns]
    for table in (columns, compile_columns, spread_table):
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
    parser.add_argument("--repeats", type=int, default=7, help="timed calls per measurement")
    parser.add_argument("--warmup", type=int, default=2, help="untimed calls before them")
    parser.add_argument(
        "--threads", type=int, default=usable_cpus(),
        help="intra-op threads of torch and XLA (default: the CPUs this process may use)",
    )
    parser.add_argument("--peak-size", type=int, default=2048, help="N of the N x N peak matmul")
    parser.add_argument("--no-rgg", action="store_true", help="time the use_rgg=False ablation")
    parser.add_argument("--no-torch", action="store_true", help="time ours only (no PyTorch twin)")
    parser.add_argument("--opponent", choices=OPPONENTS, default="idiomatic",
                        help="the PyTorch model timed against ours (default: idiomatic; parity: the "
                             "numerical tests' twin)")
    parser.add_argument("--default-malloc", action="store_true",
                        help="leave glibc's malloc as it is in both sides' processes (default: both "
                             "keep freed memory for reuse, irdepth_jax.hostmem)")
    parser.add_argument("--one-at-a-time", action="store_true",
                        help="run ours, then the twin, never both processes at once (for sizes "
                             "where the two do not fit in memory together, e.g. 512x640 batch 4 "
                             "in 24 GiB); times are then not interleaved")
    parser.add_argument("--json", metavar="FILE", help="also write the figures to FILE")
    args = parser.parse_args(argv)

    with_torch = not args.no_torch
    cfg_args = (args.preset, not args.no_rgg)
    summary = {
        "preset": args.preset, "use_rgg": cfg_args[1], "repeats": args.repeats,
        "threads": args.threads,
        "processes": "one per side (Worker)" + (", one at a time" if args.one_at_a_time else ""),
        "keep_freed_memory": not args.default_malloc,
        "opponent": args.opponent if with_torch else None,
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "runtime default"),
        "native_cpu_kernel": native_requested(),  # the opt-in C++ kernel gradient (NATIVE_ENV)
        "cpu": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(), **versions(),
    }
    title = f"MTSA-UNet vs PyTorch ({args.opponent})" if with_torch else "MTSA-UNet"
    print(f"{title}: " + " ".join(f"{k}={v}" for k, v in summary.items()))
    results = []
    for size in args.sizes:
        for batch in args.batch:
            peak = args.peak_size if not results else None
            results.append(bench_case(cfg_args, size, batch, args.repeats, args.warmup,
                                      args.threads, with_torch, peak, not args.default_malloc,
                                      args.one_at_a_time, args.opponent))
            if peak:
                summary["matmul_peak"] = results[-1].pop("matmul_peak")
                summary["device"] = results[-1]["device"]
                summary["xla_pool_threads"] = results[-1]["xla_pool_threads"]
                summary["torch_threads"] = results[-1].get("torch_threads")
                mm = summary["matmul_peak"]
                print(f"device {summary['device']}; XLA intra-op pool threads: "
                      f"{summary['xla_pool_threads']}; matmul peak, float32 {args.peak_size}^2: "
                      f"XLA {mm['xla_gflops']:.1f} GFLOP/s"
                      + (f", torch {mm['torch_gflops']:.1f} GFLOP/s" if with_torch else ""))
                print("times: medians per call (the whole batch); GFLOP/s and % peak: ours, from "
                      "XLA's FLOP count")
            r = results[-1]
            print(f"{size[0]}x{size[1]} batch {batch}: forward {r['fwd_ours_ms']:.0f} ms"
                  + (f" (torch {r['fwd_torch_ms']:.0f})" if with_torch else "")
                  + f", train step {r['train_ours_ms']:.0f} ms"
                  + (f" (torch {r['train_torch_ms']:.0f})" if with_torch else ""), flush=True)
            write_json(args.json, {**summary, "results": results})  # kept if a later case fails
    print()
    print_tables(results, summary["matmul_peak"]["xla_gflops"])
    summary.update(results=results)
    write_json(args.json, summary)
    return summary


if __name__ == "__main__":
    main()
