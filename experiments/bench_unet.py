"""Times the MTSA-UNet per input size: jit compile times (init, forward, train step) and
forward / train-step wall time per image.

    python experiments/bench_unet.py --preset paper --sizes 256x320 512x640 --batch 1 --repeats 3

The train step is a full Stage I update: forward in train mode (batch statistics), L1
reconstruction + cross-entropy + L1 saturation loss, backward, AdaDelta update. Inputs are
random uint16 raw frames (timings do not depend on the content). Times are wall-clock medians
over --repeats calls after one warm-up call, on whatever device JAX picks.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

from irdepth_jax.config import get_config
from irdepth_jax.models.unet import MTSAUNet


def parse_size(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        message = f"size must look like 256x320 (HxW), got {text!r}"
        raise argparse.ArgumentTypeError(message) from None
    return h, w


def timed(fn, *args, repeats: int) -> float:
    """Median wall-clock seconds of `fn(*args)` over `repeats` calls (after warm-up)."""
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def compiled_with_seconds(jitted, *args):
    """(the compiled executable for `args`, seconds spent tracing + compiling it)."""
    start = time.perf_counter()
    compiled = jitted.lower(*args).compile()
    return compiled, time.perf_counter() - start


def bench_size(model, size, batch: int, repeats: int) -> dict:
    h, w = size
    rng = np.random.default_rng(0)
    raw = jnp.asarray(rng.integers(2000, 9000, (batch, h, w)), jnp.uint16)
    target = jnp.asarray(rng.random((batch, h, w, 1)), jnp.float32)
    labels = jnp.asarray(rng.integers(0, model.cfg.num_classes, (batch, h, w)), jnp.int32)
    init, init_s = compiled_with_seconds(jax.jit(model.init), jax.random.key(0), raw)
    variables = init(jax.random.key(0), raw)
    tx = optax.adadelta(learning_rate=1.0)
    opt_state = tx.init(variables["params"])

    forward = jax.jit(functools.partial(model.apply, train=False))

    def loss_fn(params, batch_stats, raw, target, labels):
        out, updates = model.apply(
            {"params": params, "batch_stats": batch_stats}, raw, train=True, mutable=["batch_stats"]
        )
        ce = optax.softmax_cross_entropy_with_integer_labels(out["seg_logits"], labels).mean()
        loss = (
            jnp.abs(out["recon"] - target).mean()
            + ce
            + jnp.abs(out["saturation"] - out["input_gradient"]).mean()
        )
        return loss, updates["batch_stats"]

    @jax.jit
    def train_step(params, batch_stats, opt_state, raw, target, labels):
        (loss, batch_stats), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            params, batch_stats, raw, target, labels
        )
        updates, opt_state = tx.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), batch_stats, opt_state, loss

    # data passed as arguments: closed-over arrays would become constants XLA tries to fold
    step_args = (variables["params"], variables["batch_stats"], opt_state, raw, target, labels)
    forward, fwd_s = compiled_with_seconds(forward, variables, raw)
    train_step, train_s = compiled_with_seconds(train_step, *step_args)
    return {
        "compile_init_s": init_s,
        "compile_fwd_s": fwd_s,
        "compile_train_s": train_s,
        "fwd_ms_per_img": 1e3 * timed(forward, variables, raw, repeats=repeats) / batch,
        "train_ms_per_img": 1e3 * timed(train_step, *step_args, repeats=repeats) / batch,
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--preset", default="paper", help="config preset (paper | small | tiny)")
    parser.add_argument(
        "--sizes", nargs="+", type=parse_size, default=[(256, 320), (512, 640)], help="HxW sizes"
    )
    parser.add_argument("--batch", type=int, default=1, help="images per call")
    parser.add_argument("--repeats", type=int, default=3, help="timed calls per measurement")
    parser.add_argument("--no-rgg", action="store_true", help="time the use_rgg=False ablation")
    args = parser.parse_args(argv)

    cfg = get_config(args.preset).unet
    if args.no_rgg:
        cfg = dataclasses.replace(cfg, use_rgg=False)
    model = MTSAUNet(cfg)
    device = jax.devices()[0]
    print(
        f"MTSA-UNet preset={args.preset} use_rgg={cfg.use_rgg} batch={args.batch} "
        f"repeats={args.repeats} device={device.platform}:{device.device_kind}"
    )
    columns = ("compile init s", "compile fwd s", "compile train s", "fwd ms/img", "train ms/img")
    header = " | ".join([f"{'size':>9}"] + list(columns))
    print(header)
    print("-" * len(header))
    for size in args.sizes:
        r = bench_size(model, size, args.batch, args.repeats)
        print(
            " | ".join(
                [f"{size[0]:>4}x{size[1]:<4}"]
                + [f"{value:>{len(name)}.1f}" for name, value in zip(columns, r.values())]
            )
        )


if __name__ == "__main__":
    main()
