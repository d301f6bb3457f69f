"""Warm starts that trace nothing: what tracing a Flax model gives (the shapes of its variables,
its exported program) kept beside JAX's compilation cache.

JAX's persistent cache keeps XLA's compile, not JAX's trace, and tracing the `paper` models
(two restore templates and the pipeline's first call) was about half of a warm `irdepth
predict`'s CPU time (docs/benchmarks.md). Entries are keyed by what they are made from (the
config, the argument shapes, the backend) and by a digest of this package's source and of the
jax and flax versions: a changed model is a new key, never a stale program. A missing,
unreadable or unwritable entry only means tracing again. Off when the compilation cache is off
(`compile_cache.enable_compilation_cache(None)`, `--no-compile-cache`).
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import tempfile
from collections.abc import Callable, Mapping
from typing import Any

SUFFIX = "-programs"
"""The program cache is the compilation cache's directory with this suffix."""


@functools.cache
def source_digest() -> str:
    """sha1 (hex) of this package's Python files (relative path and content) and of the jax and
    flax versions: part of every key."""
    import flax
    import jax

    digest = hashlib.sha1(f"jax {jax.__version__} flax {flax.__version__}".encode())
    root = os.path.dirname(os.path.abspath(__file__))
    for folder, subfolders, files in os.walk(root):
        subfolders.sort()
        for name in sorted(f for f in files if f.endswith(".py")):
            path = os.path.join(folder, name)
            digest.update(os.path.relpath(path, root).encode())
            with open(path, "rb") as f:
                digest.update(f.read())
    return digest.hexdigest()


def directory() -> str | None:
    """The program cache's directory (the compilation cache's + `SUFFIX`), or None when JAX's
    persistent compilation cache is off."""
    import jax

    xla = jax.config.jax_compilation_cache_dir
    if not jax.config.jax_enable_compilation_cache or not xla:
        return None
    return os.fspath(xla).rstrip("/\\") + SUFFIX


def entry_key(*parts: Any) -> str:
    """The key of an entry made from `parts` (JSON-able; others by their str) by this source."""
    blob = json.dumps([source_digest(), *parts], sort_keys=True, default=str)
    return hashlib.sha1(blob.encode()).hexdigest()[:24]


def _read(path: str) -> bytes | None:
    try:
        with open(path, "rb") as f:
            return f.read()
    except OSError:
        return None


def _write(path: str, data: bytes) -> None:
    """Writes `data` to `path` whole (a temporary file renamed into place); a cache that cannot
    be written is skipped."""
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=os.path.dirname(path), prefix=".writing-")
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except OSError:
        pass


def _shapes_to_json(tree: Any) -> Any:
    import jax

    if isinstance(tree, Mapping):
        if not all(isinstance(k, str) for k in tree):
            raise TypeError("only string keys")
        return {k: _shapes_to_json(v) for k, v in tree.items()}
    if isinstance(tree, jax.ShapeDtypeStruct) and tree.sharding is None:
        return {"__shape__": list(tree.shape), "__dtype__": str(tree.dtype)}
    raise TypeError(f"not a tree of dicts of ShapeDtypeStructs: {type(tree).__name__}")


def _shapes_from_json(tree: Any) -> Any:
    import jax
    import numpy as np

    if "__shape__" in tree:
        return jax.ShapeDtypeStruct(tuple(tree["__shape__"]), np.dtype(tree["__dtype__"]))
    return {k: _shapes_from_json(v) for k, v in tree.items()}


def cached_shapes(name: str, made_from: Any, make: Callable[[], Any]) -> Any:
    """`make()`: a tree (nested dicts) of ShapeDtypeStructs, e.g. a model's variables by
    `jax.eval_shape`, read from the cache when an entry of (`name`, `made_from`) is kept there,
    else made and kept.

    Args:
      name: what the tree is ('unet_shapes').
      made_from: what it is made from besides this source (a config as a dict).
      make: makes the tree (traces the model).
    """
    folder = directory()
    if folder is None:
        return make()
    path = os.path.join(folder, f"{name}-{entry_key(name, made_from)}.json")
    data = _read(path)
    if data is not None:
        try:
            return _shapes_from_json(json.loads(data))
        except (ValueError, TypeError, KeyError):
            pass  # a damaged entry: made again below
    tree = make()
    try:
        _write(path, json.dumps(_shapes_to_json(tree)).encode())
    except TypeError:
        pass  # a tree of other containers is not kept
    return tree


def _export_path(name: str, made_from: Any, args: tuple, kwargs: Mapping[str, Any]) -> str | None:
    import jax

    folder = directory()
    if folder is None:
        return None
    leaves, tree = jax.tree.flatten((args, dict(kwargs)))
    spec = [[list(x.shape), str(x.dtype)] for x in leaves]
    key = entry_key(name, made_from, str(tree), spec, jax.default_backend())
    return os.path.join(folder, f"{name}-{key}.jaxexport")


def kept_export(name: str, made_from: Any, args: tuple, kwargs: Mapping[str, Any]):
    """The `jax.export.Exported` kept by `keep_export` for (`name`, `made_from`, the
    arguments' tree, shapes and dtypes, the backend), or None (none kept, unreadable, or the
    cache off). Call it as `exported.call(*args, **kwargs)` (jitted: JAX's persistent cache
    then holds its compile)."""
    from jax import export

    path = _export_path(name, made_from, args, kwargs)
    data = None if path is None else _read(path)
    if data is None:
        return None
    try:
        return export.deserialize(bytearray(data))
    except Exception:  # a damaged or foreign entry, whatever the error: as if none
        return None


def keep_export(name: str, made_from: Any, exported, args: tuple, kwargs: Mapping[str, Any]) -> None:
    """Writes `exported` (a `jax.export.Exported`, e.g. `jax.export.export(fn)(*args,
    **kwargs)`) into the cache for `kept_export`; nothing when the cache is off.

    Args:
      name: what the program is ('pipeline').
      made_from: what it computes besides this source (a config as a dict).
      exported: the program.
      args, kwargs: the arguments it was exported for (arrays, ShapeDtypeStructs or None).
    """
    path = _export_path(name, made_from, args, kwargs)
    if path is not None:
        _write(path, bytes(exported.serialize()))
