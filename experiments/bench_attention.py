"""ViT-S self-attention alone: ours (`models.dinov2.softmax_attention`, jitted; the path XLA:CPU
takes) vs PyTorch's `scaled_dot_product_attention` (what transformers' Dinov2 calls) and the
plain softmax(q k^T) v of the official DINOv2 code without xFormers, forward and forward +
backward, on this machine (one process, the sides interleaved, medians after one warm-up).

    python experiments/bench_attention.py [--repeats 15]

Prints one line per (what, batch, tokens): ms of each side and ours / SDPA. Shapes: 6 heads of
64, 1370 tokens (518x518) and 1197 (364x644); forward at batch 1, forward + backward at batch 2
(the Stage II train step's). A jax.profiler trace with `--xla_cpu_enable_xprof_traceme=true`
shows the fused attention (one YNNPACK fusion per block) about twice as long as it takes
untraced (ViT-S forward at 518x518: 45 ms per block traced; removing attention from the model
saves 22 ms per block), so time attention here rather than from a trace.
"""

import argparse
import functools

import jax
import jax.numpy as jnp
import numpy as np

from irdepth_experiments.bench_common import interleaved_medians, usable_cpus, wall_seconds
from irdepth_jax.hostmem import keep_freed_memory
from irdepth_jax.models.dinov2 import softmax_attention

HEADS, HEAD_DIM = 6, 64
CASES = [("forward", 1, 1370), ("forward", 1, 1197), ("forward+backward", 2, 1370), ("forward+backward", 2, 1197)]
"""(what, batch, tokens) of the timed calls."""


def ours_call(what: str, q, k, v, g):
    """A zero-argument call of our attention on (B, heads, N, head_dim) arrays: the output, or
    (when `what` is 'forward+backward') the gradients of sum(out * g) with respect to q, k, v."""
    scale = HEAD_DIM**-0.5
    if what == "forward":
        fn = jax.jit(lambda q, k, v: softmax_attention(q, k, v, scale))
        return lambda: fn(q, k, v).block_until_ready()
    # g passed as an argument: closed over, it would be a constant that XLA tries to fold
    fn = jax.jit(jax.grad(lambda q, k, v, g: jnp.sum(softmax_attention(q, k, v, scale) * g), (0, 1, 2)))
    return lambda: jax.block_until_ready(fn(q, k, v, g))


def torch_calls(what: str, q, k, v, g):
    """Zero-argument calls {'sdpa': ..., 'plain': ...} of PyTorch's attention on the same arrays."""
    import torch

    tq, tk, tv, tg = (torch.from_numpy(np.array(a)) for a in (q, k, v, g))
    scale = HEAD_DIM**-0.5
    kernels = {"sdpa": torch.nn.functional.scaled_dot_product_attention,
               "plain": lambda q, k, v: torch.softmax((q * scale) @ k.transpose(-2, -1), dim=-1) @ v}

    def call(kernel):
        if what == "forward":
            with torch.no_grad():
                return kernel(tq, tk, tv)
        leaves = [a.detach().requires_grad_() for a in (tq, tk, tv)]
        kernel(*leaves).backward(tg)
        return [a.grad for a in leaves]

    return {name: functools.partial(call, kernel) for name, kernel in kernels.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args()
    keep_freed_memory()
    import torch

    torch.set_num_threads(usable_cpus())
    rng = np.random.default_rng(0)
    for what, batch, tokens in CASES:
        q, k, v, g = (jnp.asarray(rng.standard_normal((batch, HEADS, tokens, HEAD_DIM), np.float32))
                      for _ in range(4))
        calls = {"ours": ours_call(what, q, k, v, g), **torch_calls(what, q, k, v, g)}
        seconds = dict(zip(calls, interleaved_medians(
            [functools.partial(wall_seconds, c) for c in calls.values()], args.repeats, warmup=1)))
        print(f"{what}, batch {batch}, {tokens} tokens: " +
              ", ".join(f"{name} {1e3 * s:.1f} ms" for name, s in seconds.items()) +
              f"; ours / SDPA {seconds['ours'] / seconds['sdpa']:.2f}", flush=True)


if __name__ == "__main__":
    main()
