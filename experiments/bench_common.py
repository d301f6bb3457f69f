"""Timing helpers the benchmarks share: compile timing, XLA's FLOP count, interleaved medians,
thread set-up for XLA and torch, and a measured matmul peak."""

from __future__ import annotations

import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np


def compiled_with_seconds(jitted, *args):
    """(the compiled executable for `args`, seconds spent tracing + compiling it)."""
    start = time.perf_counter()
    compiled = jitted.lower(*args).compile()
    return compiled, time.perf_counter() - start


def flops_of(compiled) -> float:
    """XLA's FLOP count of one call of a compiled executable (2 per multiply-add)."""
    cost = compiled.cost_analysis()
    if isinstance(cost, (list, tuple)):  # older jaxlibs: one dict per device program
        cost = cost[0]
    return float(cost["flops"])


def interleaved_medians(fns, repeats: int, warmup: int = 1) -> list[float]:
    """Median wall-clock seconds of each zero-argument callable (each blocks until done), over
    `repeats` rounds that call them in turn (A, B, A, B, ...), after `warmup` rounds."""
    for _ in range(warmup):
        for fn in fns:
            fn()
    times = [[] for _ in fns]
    for _ in range(repeats):
        for fn, t in zip(fns, times):
            start = time.perf_counter()
            fn()
            t.append(time.perf_counter() - start)
    return [float(np.median(t)) for t in times]


def xla_pool_threads() -> int | None:
    """Threads of XLA's CPU intra-op pool in this process (Linux; None elsewhere), to check that
    PJRT_NPROC took effect."""
    try:
        tasks = os.listdir("/proc/self/task")
    except OSError:
        return None
    count = 0
    for task in tasks:
        try:
            with open(f"/proc/self/task/{task}/comm") as f:
                count += f.read().startswith("tf_XLAEigen")
        except OSError:
            pass
    return count


def matmul_peak(n: int, repeats: int, warmup: int, with_torch: bool, dtype: str = "float32") -> dict:
    """GFLOP/s of an n x n matmul in `dtype` on JAX's default device, jitted, and, if asked,
    torch.mm of the float32 arrays on the CPU (medians)."""
    rng = np.random.default_rng(0)
    a = rng.standard_normal((n, n), dtype=np.float32)
    b = rng.standard_normal((n, n), dtype=np.float32)
    xa, xb = jnp.asarray(a, dtype), jnp.asarray(b, dtype)
    mm = jax.jit(jnp.matmul).lower(xa, xb).compile()
    fns = [lambda: mm(xa, xb).block_until_ready()]
    if with_torch:
        import torch

        ta, tb = torch.from_numpy(a), torch.from_numpy(b)
        fns.append(lambda: torch.mm(ta, tb))
    seconds = interleaved_medians(fns, repeats, warmup)
    flops = 2.0 * n**3
    result = {"size": n, "dtype": dtype, "xla_gflops": flops / seconds[0] / 1e9}
    if with_torch:
        result["torch_gflops"] = flops / seconds[1] / 1e9
    return result


def usable_cpus() -> int:
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1



def set_threads(threads: int, with_torch: bool) -> dict:
    """Gives XLA and (if asked) torch `threads` intra-op threads; call before JAX's first
    computation. XLA: PJRT_NPROC, read when its CPU client starts. torch: set_num_threads, with
    OpenMP's threads waiting passively (OMP_WAIT_POLICY=PASSIVE unless the environment sets it:
    spinning OpenMP threads interleaved with XLA's calls in one process made torch up to 50x
    slower on a busy 2-core machine). Returns the versions and the policy, for the report."""
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized() and os.environ.get("PJRT_NPROC") != str(threads):
        print(f"warning: JAX already started; XLA keeps its thread pool, --threads {threads} "
              "applies to torch only")
    os.environ["PJRT_NPROC"] = str(threads)
    versions = {"jax": jax.__version__}
    if with_torch:
        omp_policy = os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
        import torch

        torch.set_num_threads(threads)
        versions.update(torch=torch.__version__, omp_wait_policy=omp_policy)
    return versions


def write_json(path: str | None, figures: dict) -> None:
    """Writes a benchmark's figures to `path` (--json FILE), if given."""
    if path:
        with open(path, "w") as f:
            json.dump(figures, f, indent=1)
