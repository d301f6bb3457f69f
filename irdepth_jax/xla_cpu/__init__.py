"""Faster training on XLA:CPU: the models' layers re-implemented for its gradients (`layers`,
`conv`) and an opt-in C++ kernel (`native_conv`).

The models are plain Flax; `training_layers` is the one place that chooses how their layers are
computed while a training loss is traced. The choice depends only on the backend (the same for
every process of a run) and on `NATIVE_ENV`, and a multi-process run refuses the native kernel,
so all processes of one run trace the same program.
"""

from __future__ import annotations

import contextlib
import functools
import os

import flax.linen as nn
import jax

from irdepth_jax.errors import RunError
from irdepth_jax.xla_cpu import layers, native_conv

NATIVE_ENV = "IRDEPTH_NATIVE_CPU_KERNEL"
"""Set to 1 to let CPU training take the C++ kernel gradient (`native_conv`, built with the
machine's compiler on first use); unset or 0 (the default): pure XLA."""


def native_requested() -> bool:
    """Whether `NATIVE_ENV` asks for the native kernel ('1'); RunError for a value other than
    unset, '', '0' or '1'."""
    value = os.environ.get(NATIVE_ENV, "").strip()
    if value not in ("", "0", "1"):
        raise RunError(f"environment variable {NATIVE_ENV}={value!r}: expected 0 or 1")
    return value == "1"


def training_layers() -> contextlib.AbstractContextManager:
    """The context a training loss is traced in: on a CPU backend the layer replacements of
    `layers` (with the native kernel when `native_requested()`); on any other backend nothing.

    Raises RunError when the native kernel is asked for but cannot be used (a multi-process
    run, or no compiler / a failed build: the reason in the message), rather than tracing a
    program other than the one asked for.
    """
    if jax.default_backend() != "cpu":
        return contextlib.nullcontext()
    native = native_requested()
    if native and jax.process_count() > 1:
        raise RunError(f"{NATIVE_ENV}=1: the native kernel is built per host and is refused in a "
                          f"multi-process run ({jax.process_count()} processes); unset it")
    if native and not native_conv.available():
        raise RunError(f"{NATIVE_ENV}=1: the native convolution kernel is not available: "
                          f"{native_conv.unavailable_reason()}")
    return nn.intercept_methods(functools.partial(layers.intercept, native=native))
