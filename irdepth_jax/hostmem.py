"""Host memory: keep what the process frees for its next allocations (glibc malloc on Linux).

XLA:CPU allocates each call's scratch memory as one block (a ViT-S train step on 2 images of
518x518: 2 GB; the `paper` UNet at batch 4: 4.3 GB) and frees it when the call returns. glibc
serves blocks over 32 MB with a fresh mmap and returns them with munmap, so every call starts
on untouched pages, and the kernel zeroes each on first touch: about a million page faults per
train step, a quarter to a third of its time (measured: ViT-S step 4.5 s, 1.7 s of it in the
kernel; 3.7-4.0 s and 0.1 s with this set), and more when another process has just freed memory.
`keep_freed_memory` makes malloc serve everything from one heap that never shrinks, so after
the first step the same pages are reused. PyTorch's CPU allocator gains alike (the official
Depth Anything V2 train step: 6.5 -> 4.6 s), so the benchmarks set it on both sides.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

DISABLE_ENV = "IRDEPTH_DEFAULT_MALLOC"
"""Set to 1 to leave malloc as it is (the CLI and the experiment scripts then do not call
`keep_freed_memory`)."""

_M_TRIM_THRESHOLD, _M_MMAP_MAX, _M_ARENA_MAX = -1, -4, -8  # glibc's mallopt parameters


def keep_freed_memory() -> bool:
    """Makes glibc's malloc keep freed memory for reuse, for the rest of the process: one arena
    (threads share it), no mmap for large blocks, no trimming of the heap. The process's
    resident memory then stays at its peak (as a GPU framework's caching allocator does).

    Call it before JAX starts its CPU client (its threads take an arena when they start);
    calling it again is harmless. Returns True if it took effect; False on other C libraries
    and systems, or when the `IRDEPTH_DEFAULT_MALLOC` environment variable is 1.
    """
    if os.environ.get(DISABLE_ENV) == "1" or not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    if not hasattr(libc, "gnu_get_libc_version"):  # musl and others: no such options
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    # -1 as the trim threshold is SIZE_MAX inside glibc: never give the heap's top back
    return all(mallopt(param, value) == 1 for param, value in
               ((_M_ARENA_MAX, 1), (_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, -1)))
