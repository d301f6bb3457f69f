"""Timing helpers the benchmarks share: compile timing, XLA's FLOP count, interleaved medians,
thread set-up for XLA and torch, a measured matmul peak, and `Worker`: one side of a comparison
in a process of its own."""

from __future__ import annotations

import json
import multiprocessing
import os
import time
import traceback

import jax
import jax.numpy as jnp
import numpy as np

from irdepth_jax.hostmem import keep_freed_memory
from irdepth_jax.xla_cpu import native_conv


def compiled_with_seconds(jitted, *args):
    """(the compiled executable for `args`, seconds spent tracing + compiling it)."""
    start = time.perf_counter()
    compiled = jitted.lower(*args).compile()
    return compiled, time.perf_counter() - start


def flops_of(compiled) -> float:
    """XLA's FLOP count of one call of a compiled executable (2 per multiply-add), with the
    native kernel gradient's calls, which XLA's cost analysis counts as none
    (`native_conv.flops_in`)."""
    cost = compiled.cost_analysis()
    if isinstance(cost, (list, tuple)):  # older jaxlibs: one dict per device program
        cost = cost[0]
    return float(cost["flops"]) + native_conv.flops_in(compiled.as_text())


def wall_seconds(fn) -> float:
    """Runs the zero-argument callable `fn` (which blocks until its work is done); its seconds."""
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def interleaved_samples(timers, repeats: int, warmup: int = 1) -> list[list[float]]:
    """Seconds of each timer in each of `repeats` rounds that call them in turn (A, B, A, B,
    ...), after `warmup` rounds. A timer is a zero-argument callable that runs one call and
    returns its seconds (`functools.partial(wall_seconds, fn)`, `functools.partial(worker.time,
    name)`)."""
    for _ in range(warmup):
        for timer in timers:
            timer()
    times = [[] for _ in timers]
    for _ in range(repeats):
        for timer, t in zip(timers, times):
            t.append(timer())
    return times


def interleaved_medians(timers, repeats: int, warmup: int = 1) -> list[float]:
    """Median seconds of each timer over `interleaved_samples`' rounds."""
    return [float(np.median(t)) for t in interleaved_samples(timers, repeats, warmup)]


def spread(samples) -> dict:
    """Median, min, max and the max / min - 1 spread (in %) of one timer's seconds."""
    lo, hi = float(np.min(samples)), float(np.max(samples))
    return {"median": float(np.median(samples)), "min": lo, "max": hi, "spread_pct": 100 * (hi / lo - 1)}


def torch_flops(fn) -> float:
    """FLOPs of one call of the zero-argument callable `fn` (torch work) as
    `torch.utils.flop_counter` counts them: 2 per multiply-add of convolutions and matrix
    products (forward and backward), elementwise work not counted."""
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as counter:
        fn()
    return float(counter.get_total_flops())


class Worker:
    """One side of a comparison (ours in JAX, or a PyTorch reference) in a process of its own.

    The two sides of a benchmark used to share one process, interleaved call by call. Each then
    ran among the other's threads, allocations and freed memory: measured on 2 cores, the
    `paper` UNet train step at batch 4 took 9.7 s between torch's calls and 5.5 s alone (torch's
    twin 7.7 s between ours, 6.7 s alone). In separate processes the calls are still
    interleaved (A, B, A, B: a drift in the machine's load hits both alike), but only one
    process computes at a time and neither sees the other's state.

    `setup` is an importable function (the child is started with 'spawn'); it runs in the child
    as ``setup(*args, **kwargs)`` with the thread settings in its environment, and returns ``(calls, info)``: a dict of
    zero-argument callables (each blocks until its work is done and returns its result, numpy
    or torch) and a dict of picklable facts (compile seconds, FLOPs, ...), `self.info`.
    `threads`: XLA's intra-op pool (PJRT_NPROC) and torch's intra-op threads in the child.
    `keep_memory`: the child keeps freed memory for reuse (`irdepth_jax.hostmem`), whichever
    framework it runs, as the `irdepth` command does for ours; False leaves glibc's malloc as
    it is (`info['keep_freed_memory']` says which).
    """

    def __init__(self, setup, *args, threads: int, keep_memory: bool = True, **kwargs):
        context = multiprocessing.get_context("spawn")
        self._conn, child = context.Pipe()
        self._process = context.Process(target=_worker_main,
                                        args=(child, setup, args, kwargs, keep_memory), daemon=True)
        # The child inherits the environment when it starts, before it imports anything:
        # PJRT_NPROC is read when JAX's CPU client starts, OMP_NUM_THREADS when torch's OpenMP
        # runtime loads: both sides get the same thread count, and nothing else is set for one
        # side only (OpenMP's wait policy stays the runtime's default or the caller's); on a GPU,
        # JAX takes memory as it needs it instead of 75 % of it up front, so that the other
        # side's process fits beside it.
        settings = {"PJRT_NPROC": str(threads), "OMP_NUM_THREADS": str(threads),
                    "XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
        saved = {k: os.environ.get(k) for k in settings}
        os.environ.update(settings)
        try:
            self._process.start()
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k)
                else:
                    os.environ[k] = v
        child.close()
        self._setup_name = setup.__name__
        self.info = self._ask(None)

    def _died(self) -> RuntimeError:
        self._process.join(timeout=5)
        code = self._process.exitcode
        why = " (SIGKILL: out of memory? see dmesg)" if code == -9 else ""
        return RuntimeError(f"benchmark worker {self._process.pid} ({self._setup_name}) died, "
                            f"exit code {code}{why}")

    def _ask(self, request):
        try:
            if request is not None:
                self._conn.send(request)
            status, value = self._conn.recv()
        except (EOFError, BrokenPipeError):
            raise self._died() from None
        if status == "error":
            raise RuntimeError(f"benchmark worker ({self._setup_name}) failed:\n{value}")
        return value

    def time(self, name: str) -> float:
        """Seconds of one call of `name`, measured in the child."""
        return self._ask(("time", name))

    def result(self, name: str):
        """One call's result, as numpy arrays (a tree of them)."""
        return self._ask(("result", name))

    def close(self) -> None:
        if self._process.is_alive():
            self._conn.send(("close", None))
            self._process.join(timeout=30)
        self._conn.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _as_numpy(tree):
    if isinstance(tree, dict):
        return {k: _as_numpy(v) for k, v in tree.items()}
    if isinstance(tree, (list, tuple)):
        return type(tree)(_as_numpy(v) for v in tree)
    if hasattr(tree, "detach"):  # a torch tensor
        return tree.detach().float().cpu().numpy()
    return np.asarray(tree)


def _worker_main(conn, setup, args, kwargs, keep_memory: bool) -> None:
    try:
        kept = keep_memory and keep_freed_memory()
        calls, info = setup(*args, **kwargs)
        info = {**info, "keep_freed_memory": kept}
        conn.send(("ok", info))
    except BaseException:
        conn.send(("error", traceback.format_exc()))
        return
    while True:
        command, name = conn.recv()
        if command == "close":
            return
        try:
            if command == "time":
                conn.send(("ok", wall_seconds(calls[name])))
            else:
                conn.send(("ok", _as_numpy(calls[name]())))
        except BaseException:
            conn.send(("error", traceback.format_exc()))


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


def matmul_call(n: int, framework: str, dtype: str = "float32", device: str = "cpu"):
    """A zero-argument callable running one n x n matmul in `framework` ('jax': jitted on JAX's
    default device, in `dtype`; 'torch': torch.mm on `device`), blocking until done; 2 n^3
    FLOPs per call, the machine's attainable matmul peak (`peak_gflops`)."""
    rng = np.random.default_rng(0)
    a = rng.standard_normal((n, n), dtype=np.float32)
    b = rng.standard_normal((n, n), dtype=np.float32)
    if framework == "jax":
        xa, xb = jnp.asarray(a, dtype), jnp.asarray(b, dtype)
        mm = jax.jit(jnp.matmul).lower(xa, xb).compile()
        return lambda: mm(xa, xb).block_until_ready()
    import torch

    ta, tb = (torch.from_numpy(m).to(device, getattr(torch, dtype)) for m in (a, b))

    def mm_torch():
        out = torch.mm(ta, tb)
        if device == "cuda":
            torch.cuda.synchronize()
        return out

    return mm_torch


def peak_gflops(n: int, seconds: float) -> float:
    """GFLOP/s of an n x n matmul that took `seconds`."""
    return 2.0 * n**3 / seconds / 1e9


def usable_cpus() -> int:
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def set_xla_threads(threads: int) -> None:
    """Gives XLA's CPU client `threads` intra-op threads (PJRT_NPROC, read when it starts); call
    before JAX's first computation."""
    try:  # private, checked where it exists
        from jax._src.xla_bridge import backends_are_initialized
    except ImportError:
        backends_are_initialized = lambda: False  # noqa: E731
    if backends_are_initialized() and os.environ.get("PJRT_NPROC") != str(threads):
        print(f"warning: JAX already started; XLA keeps its thread pool, not --threads {threads}")
    os.environ["PJRT_NPROC"] = str(threads)


def cpu_model() -> str:
    """The CPU's model name and widest vector extension (Linux; '' elsewhere): the ratios
    against torch differ between CPUs (AVX2-only vs AVX-512 machines), so reports say which."""
    try:
        with open("/proc/cpuinfo") as f:
            info = f.read()
    except OSError:
        return ""
    fields = {}  # the first processor's "key : value" lines
    for line in info.splitlines():
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    name, flags = fields.get("model name", ""), set(fields.get("flags", "").split())
    vector = next((f for f in ("avx512f", "avx2", "avx") if f in flags), "")
    return f"{name} ({vector})" if vector else name


def versions() -> dict:
    """jax's and (where installed) torch's versions and the CPU model, for a benchmark's report."""
    found = {"jax": jax.__version__, "cpu_model": cpu_model()}
    try:
        import torch
    except ImportError:
        return found
    return {**found, "torch": torch.__version__}


def write_json(path: str | None, figures: dict) -> None:
    """Writes a benchmark's figures to `path` (--json FILE), if given."""
    if path:
        with open(path, "w") as f:
            json.dump(figures, f, indent=1)
