"""Kernel gradient of a 3x3 stride-1 NHWC convolution: XLA:CPU's own vs `xla_cpu.conv`'s, and
PyTorch's (`torch.nn.grad.conv2d_weight`) when torch is installed, on this machine (jitted; the
sides interleaved in one process, medians of 7 calls after one warm-up).

    python experiments/bench_conv_grad.py

Prints one line per layer shape (batch, height, width, C_in, C_out) of the UNet / DPT head:
XLA's ms, ours ms and which of `conv.kernel_gradient`'s five ways ours took, ours without the
native kernel (the XLA ways; ours takes it where it builds), PyTorch's ms and the ratio.
Measured 2026-12-03
on a 2-core Intel Xeon (AVX-512), commit eebdcf8: (4, 256, 320, 64, 32) 355 vs 192 ms (row
blocks); (1, 256, 320, 32, 32) 52 vs 30 ms; (2, 518, 518, 32, 32) 353 vs 168 ms;
(4, 128, 160, 128, 64) 306 vs 107 ms; (1, 64, 80, 256, 128) 45 vs 23 ms (by tap);
(1, 16, 20, 512, 512) 8.6 vs 6.8 ms (im2col); (1, 256, 320, 1, 32) 2.1 vs 1.7 ms (im2col).
On the 2-core AMD EPYC (AVX-512) of the same day's second session (commit 08658cc's kernels),
ours / PyTorch: (4, 256, 320, 64, 32) 277 vs 83 ms (3.3); (2, 518, 518, 32, 32) 228 vs 71 ms
(3.2); (4, 128, 160, 128, 64) 151 vs 78 ms (1.9); (1, 64, 80, 256, 128) 1.5; (1, 16, 20, 512,
512) 0.89; (1, 256, 320, 1, 32) 0.25. On 2026-12-02's 2-core AMD EPYC (AVX2),
before the channels-first layouts: (4, 256, 320, 64, 32) 2,529 vs 341 ms; (2, 518, 518, 32, 32)
3,052 vs 209 ms. Use it to re-tune `conv.BLOCK_PIXELS`, `conv.MIN_LOOP_PIXELS`,
`conv.IM2COL_BYTES` and `conv.CHANNELS_FIRST_MAX_OUT` on another CPU.
"""

import functools
import importlib.util

import jax
import numpy as np
from jax import lax

from irdepth_experiments.bench_common import interleaved_medians, usable_cpus, wall_seconds
from irdepth_jax.hostmem import keep_freed_memory
from irdepth_jax.xla_cpu import conv, native_conv

SHAPES = [(4, 256, 320, 64, 32), (1, 256, 320, 32, 32), (2, 518, 518, 32, 32),
          (4, 128, 160, 128, 64), (1, 64, 80, 256, 128), (1, 16, 20, 512, 512), (1, 256, 320, 1, 32)]
"""(batch, height, width, C_in, C_out) of the timed layers."""


def kernel_gradient_fn(conv_fn):
    """Jitted (x (B,H,W,Ci), kernel (3,3,Ci,Co), output gradient (B,H,W,Co)) -> kernel gradient."""

    def grad(x, kernel, g):
        _, vjp = jax.vjp(lambda k: conv_fn(x, k, (1, 1), ((1, 1), (1, 1)),
                                           dimension_numbers=("NHWC", "HWIO", "NHWC")), kernel)
        return vjp(g)[0]

    return jax.jit(grad)


def torch_kernel_gradient_call(x, kernel, g):
    """A zero-argument call of PyTorch's kernel gradient (`torch.nn.grad.conv2d_weight`, oneDNN on
    CPU) of the same layer, NCHW, with the process's intra-op threads."""
    import torch

    x_t, g_t = (torch.from_numpy(np.ascontiguousarray(a.transpose(0, 3, 1, 2))) for a in (x, g))
    shape = (kernel.shape[3], kernel.shape[2], *kernel.shape[:2])
    return lambda: torch.nn.grad.conv2d_weight(x_t, shape, g_t, padding=1)


def main() -> None:
    keep_freed_memory()
    native = native_conv.available()
    ours = kernel_gradient_fn(functools.partial(conv.conv_general_dilated, native=native))
    xla, xla_ways = kernel_gradient_fn(lax.conv_general_dilated), kernel_gradient_fn(conv.conv_general_dilated)
    with_torch = importlib.util.find_spec("torch") is not None
    if with_torch:
        import torch

        torch.set_num_threads(usable_cpus())
    rng = np.random.default_rng(0)
    for b, h, w, ci, co in SHAPES:
        args = (rng.random((b, h, w, ci), np.float32), rng.random((3, 3, ci, co), np.float32),
                rng.random((b, h, w, co), np.float32))
        calls = [lambda fn=fn: fn(*args).block_until_ready() for fn in (xla, ours, xla_ways)]
        if with_torch:
            calls.append(torch_kernel_gradient_call(*args))
        seconds = interleaved_medians([functools.partial(wall_seconds, c) for c in calls],
                                      repeats=7, warmup=1)
        method = conv.kernel_gradient_method((b, h, w, ci), (b, h, w, co), (3, 3), native=native)
        line = (f"{(b, h, w, ci, co)}: XLA {1e3 * seconds[0]:.1f} ms, ours ({method}) {1e3 * seconds[1]:.1f} ms,"
                f" ours without the native kernel {1e3 * seconds[2]:.1f} ms")
        if with_torch:
            theirs = calls[3]().numpy().transpose(2, 3, 1, 0)  # (Co, Ci, kh, kw) -> HWIO
            diff = np.abs(theirs - np.asarray(ours(*args))).max() / np.abs(theirs).max()
            line += (f", PyTorch {1e3 * seconds[3]:.1f} ms (ours / PyTorch {seconds[1] / seconds[3]:.2f};"
                     f" max |diff| / max |theirs| {diff:.1e})")
        print(line, flush=True)


if __name__ == "__main__":
    main()
