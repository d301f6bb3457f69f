"""A native CPU kernel for the kernel gradient of stride-1 convolutions (`native_conv.cc`),
built with the machine's C++ compiler (-O3 -march=native) and called through XLA's FFI as a
custom call. Opt-in: only a run that asks for it (`irdepth_jax.xla_cpu.NATIVE_ENV`) builds or
loads it.

XLA:CPU has no kernel-gradient convolution of its own that keeps up with oneDNN: `conv.py`
computes it as im2col matmuls, which copy each input window twice per block and run the skinny
(k*k*C_in, pixels) @ (pixels, C_out) products at about half the matmul peak. The native kernel
reads the input in place: register tiles of input x output channels accumulate each output row
with fused multiply-adds.

The built library is cached under ``$XDG_CACHE_HOME/irdepth_jax/native`` (default
``~/.cache``), keyed by the source, the compiler, jaxlib and the CPU's model and flags (a
-march=native build runs only on the CPU it was made for). Each build writes a temporary file
of its own and renames it into place, so concurrent builders (threads or processes) never write
the same file.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import math
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp
import jaxlib
import numpy as np

SOURCE = Path(__file__).with_name("native_conv.cc")
TARGET = "irdepth_conv_kernel_gradient"
FLAGS = ("-O3", "-march=native", "-std=c++17", "-shared", "-fPIC")


def cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "irdepth_jax" / "native"


def _cpu_signature() -> str:
    """The CPU's model and feature flags (what -march=native compiles for)."""
    try:
        with open("/proc/cpuinfo") as f:
            lines = [line for line in f if line.startswith(("model name", "flags", "Features", "CPU part"))]
        return "".join(sorted(set(lines)))
    except OSError:
        return platform.processor() + platform.machine()


def _compiler() -> str | None:
    return os.environ.get("CXX") or shutil.which("c++") or shutil.which("g++") or shutil.which("clang++")


def _build(compiler: str) -> Path:
    """Compiles the kernel into the cache (once per source, compiler, jaxlib and CPU); its path."""
    version = subprocess.run([compiler, "--version"], capture_output=True, text=True, timeout=60).stdout
    key = hashlib.sha256("\0".join([SOURCE.read_text(), compiler, version, jaxlib.__version__, " ".join(FLAGS),
                                    _cpu_signature()]).encode()).hexdigest()[:16]
    target = cache_dir() / f"native_conv_{key}.so"
    if target.exists():
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    handle, partial = tempfile.mkstemp(prefix=f"{target.stem}.", suffix=".tmp", dir=target.parent)
    os.close(handle)
    command = [compiler, *FLAGS, "-I", jax.ffi.include_dir(), str(SOURCE), "-o", partial]
    try:
        result = subprocess.run(command, capture_output=True, text=True, timeout=600)
        if result.returncode != 0:
            raise RuntimeError(f"{' '.join(command)} exited {result.returncode}: {result.stderr.strip()[-2000:]}")
        os.replace(partial, target)  # atomic; every builder wrote a file of its own
    finally:
        if os.path.exists(partial):
            os.unlink(partial)
    return target


@functools.cache
def _loaded() -> tuple[ctypes.CDLL | None, str]:
    """(the built and registered library, '') or (None, why not)."""
    if not sys.platform.startswith(("linux", "darwin")):
        return None, f"no build recipe for {sys.platform}"
    compiler = _compiler()
    if compiler is None:
        return None, "no C++ compiler found (set CXX)"
    try:
        library = ctypes.CDLL(str(_build(compiler)))
        jax.ffi.register_ffi_target(TARGET, jax.ffi.pycapsule(library.IrdepthConvKernelGradient), platform="cpu")
    except (OSError, RuntimeError, subprocess.SubprocessError) as e:
        return None, f"the build or load failed: {e}"
    return library, ""


def _library() -> ctypes.CDLL | None:
    return _loaded()[0]


def available() -> bool:
    """Whether the native kernel is built and registered (builds it on the first call)."""
    return _library() is not None


def unavailable_reason() -> str:
    """Why `available()` is False ('' when it is True)."""
    return _loaded()[1]


def tile_channels() -> int:
    """The kernel takes layers whose output channels are a multiple of this (32 with AVX-512,
    16 with AVX); 0 when it is not available."""
    library = _library()
    return int(library.IrdepthConvTileChannels()) if library is not None else 0


def flops_in(hlo_text: str) -> float:
    """FLOPs of the native kernel's calls in a compiled module's text (2 per multiply-add, as
    XLA counts), which XLA's cost analysis leaves out of a custom call: 2 x kh*kw*C_in*C_out x
    B*H'*W' per call (its result (kh, kw, C_in, C_out) and its second operand (B, H', W', C_out))."""
    total = 0.0
    for line in hlo_text.splitlines():
        if f'custom_call_target="{TARGET}"' not in line:
            continue
        result = re.search(r"= f32\[([\d,]+)\]", line)
        operands = re.search(r"operand_layout_constraints=\{f32\[[\d,]+\]\{[\d,]*\}, f32\[([\d,]+)\]", line)
        if not (result and operands):
            raise ValueError(f"unexpected {TARGET} call in HLO: {line.strip()[:200]}")
        weights = math.prod(int(v) for v in result.group(1).split(","))
        pixels = math.prod(int(v) for v in operands.group(1).split(",")[:3])
        total += 2.0 * weights * pixels
    return total


def kernel_gradient_native(x, g, kernel_size: tuple[int, int], pads):
    """`conv.kernel_gradient` by the native kernel: x (B, H, W, C_in) and g (B, H', W', C_out)
    float32, C_out a multiple of `tile_channels()`; pads ((top, bottom), (left, right)) ->
    (kh, kw, C_in, C_out) float32. Needs `available()`; CPU only."""
    if not available():
        raise RuntimeError(f"the native convolution kernel is not available: {unavailable_reason()}")
    (top, _), (left, _) = pads
    out = jax.ShapeDtypeStruct((*kernel_size, x.shape[-1], g.shape[-1]), jnp.float32)
    return jax.ffi.ffi_call(TARGET, out, vmap_method="sequential")(x, g, top=np.int64(top), left=np.int64(left))
