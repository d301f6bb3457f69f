"""JAX's persistent compilation cache: one setup for the CLI, the experiments and the tests."""

from __future__ import annotations


def enable_compilation_cache(path: str | None) -> None:
    """Points JAX's persistent compilation cache at `path` (None: off), also after earlier
    compilations in this process. Compiled steps are then reused across runs and processes
    (same computation -> same key), which is most of a short run's time on a CPU."""
    import jax
    from jax.experimental.compilation_cache import compilation_cache as cc

    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    jax.config.update("jax_compilation_cache_dir", path)
    cc.reset_cache()
