"""JAX's persistent compilation cache, set up in one place (the CLI, the experiment scripts,
notebooks): compiled steps are reused across runs and processes (same computation -> same key),
which is most of a short run's time on a CPU."""

from __future__ import annotations

import os

DEFAULT_DIR = os.path.join(os.path.expanduser("~"), ".cache", "irdepth_jax", "xla")
"""The CLI's cache when JAX_COMPILATION_CACHE_DIR names none."""

MIN_COMPILE_TIME_S = 0.5
"""Computations that compiled faster than this are not written to the cache."""


def default_cache_dir() -> str:
    """The directory JAX_COMPILATION_CACHE_DIR names (JAX reads it into
    ``jax_compilation_cache_dir``) when set, else `DEFAULT_DIR`."""
    import jax

    return jax.config.jax_compilation_cache_dir or DEFAULT_DIR


def enable_compilation_cache(path: str | None, min_compile_time_s: float = MIN_COMPILE_TIME_S
                             ) -> None:
    """Points JAX's persistent compilation cache at `path` (made when first written), or turns
    it off (`path` None). Takes effect also after earlier compilations in this process (JAX
    otherwise fixes the cache at its first compilation).

    Args:
      path: cache directory, or None for no persistent cache.
      min_compile_time_s: only computations that took at least this long to compile are
        written (`jax_persistent_cache_min_compile_time_secs`).
    """
    import jax
    from jax.experimental.compilation_cache import compilation_cache

    jax.config.update("jax_enable_compilation_cache", path is not None)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_time_s))
    jax.config.update("jax_compilation_cache_dir", None if path is None else os.fspath(path))
    compilation_cache.reset_cache()
