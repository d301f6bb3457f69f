"""What the `irdepth` commands share: the user's error (`CliError`), exit codes, how a run's
config is read (`load_config`), flags that several commands take, and the set-up of JAX."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import sys
import warnings

from irdepth_jax.errors import IrdepthError


class CliError(IrdepthError):
    """A one-line user error."""


EXIT_USAGE = 2


EXIT_INTERRUPTED = 130


EXIT_SKIPPED = 1
"""`irdepth predict`'s exit status when it skipped input files it could not read as raw frames
(the rest predicted and written)."""


EPILOG_OVERRIDES = (
    "Overrides: any number of section.key=value after the options, e.g. "
    "stage1.w_rec=0.2 unet.use_rgg=false stage2.preprocessing=clahe stage2.sky_loss=false "
    "(see irdepth_jax/config.py for every key).")


def load_config(preset: str, config_file: str | None, overrides: list[str]):
    """Preset, then a .py (defining `get_config()` or `config`) or .json config, then overrides."""
    from irdepth_jax.config import Config, apply_overrides, from_dict, get_config, to_dict, upgrade_dict

    cfg = get_config(preset)
    if config_file:
        if not os.path.isfile(config_file):
            raise CliError(f"--config {config_file}: no such file")
        if config_file.endswith(".json"):
            try:
                with open(config_file) as f:
                    doc = json.load(f)
            except json.JSONDecodeError as err:
                raise CliError(f"--config {config_file}: not valid JSON ({err})") from None
            if not isinstance(doc, dict):
                raise CliError(f"--config {config_file}: expected a JSON object (nested like "
                               "config.json)")
            doc = upgrade_dict(doc, where=f"--config {config_file}")
            cfg = from_dict(_merge(to_dict(cfg), doc, config_file))
        elif config_file.endswith(".py"):
            made = _run_config_file(config_file)
            if not isinstance(made, Config):
                raise CliError(f"--config {config_file}: defines neither get_config() nor "
                               "config returning an irdepth_jax.config.Config")
            cfg = made
        else:
            raise CliError(f"--config {config_file}: expected a .py or .json file")
    return apply_overrides(cfg, overrides)


def _run_config_file(path: str):
    """What a .py config file makes: its `get_config()`, else its `config` (else None).

    Raises CliError naming the file and line for a syntax error, or for an exception raised
    while the file runs or get_config() is called.
    """
    import traceback

    from irdepth_jax.config import renamed_hint

    scope: dict = {}
    try:
        with open(path) as f:
            exec(compile(f.read(), path, "exec"), scope)
        return scope["get_config"]() if "get_config" in scope else scope.get("config")
    except SyntaxError as err:
        raise CliError(f"--config {path}: line {err.lineno}: syntax error ({err.msg})") from None
    except SystemExit as err:  # sys.exit() in the file would end irdepth without a word
        raise CliError(f"--config {path}: the file called sys.exit({err.code!r}) while it ran; "
                       "a config file defines get_config() or config") from None
    except Exception as err:  # noqa: BLE001 - any error of the user's file, as one line
        lines = [f.lineno for f in traceback.extract_tb(err.__traceback__) if f.filename == path]
        where = f"line {lines[-1]}: " if lines else ""
        text = str(err).strip().splitlines()
        raise CliError(f"--config {path}: {where}{type(err).__name__}"
                       + (f": {text[0]}" if text else "") + renamed_hint(str(err))) from None


def _merge(base: dict, doc: dict, where: str, prefix: str = "") -> dict:
    out = dict(base)
    for key, value in doc.items():
        if key not in base:
            raise CliError(f"--config {where}: unknown config key {prefix + key!r}")
        if isinstance(base[key], dict):
            if not isinstance(value, dict):
                raise CliError(f"--config {where}: {prefix + key!r} is a section")
            out[key] = _merge(base[key], value, where, prefix + key + ".")
        else:
            out[key] = value
    return out


def checked_overrides(items: list[str]) -> list[str]:
    for item in items:
        if "=" not in item:
            raise CliError(f"unexpected argument {item!r} (overrides are key=value)")
    return items


def check_out_dir(path: str | None) -> None:
    """CliError when --out names an existing file (the outputs go into a directory)."""
    if path and os.path.exists(path) and not os.path.isdir(path):
        raise CliError(f"--out {path}: exists and is not a directory")


def parse_size(text: str) -> tuple[int, int]:
    match = re.fullmatch(r"(\d+)[xX](\d+)", text)
    if not match:
        raise argparse.ArgumentTypeError(f"size {text!r} is not HxW, e.g. 64x80")
    return int(match.group(1)), int(match.group(2))


def progress_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


def strict_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument("--strict", action="store_true",
                   help="MS2: fail when a sequence named by a split list is not on disk, or a "
                        "thermal frame has no depth file (default: read what is present, warn "
                        "once per split)")


def compile_cache_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument("--no-compile-cache", action="store_true",
                   help="do not use the persistent XLA compilation cache")


def setup_jax(args) -> None:
    """Freed host memory kept for reuse (`hostmem.keep_freed_memory`; IRDEPTH_DEFAULT_MALLOC=1
    leaves malloc alone), persistent XLA compilation cache (repeat runs skip compiling;
    JAX_COMPILATION_CACHE_DIR or ~/.cache/irdepth_jax/xla; off with --no-compile-cache) and
    multi-host init."""
    from irdepth_jax.compile_cache import default_cache_dir, enable_compilation_cache
    from irdepth_jax.hostmem import keep_freed_memory

    keep_freed_memory()

    enable_compilation_cache(None if getattr(args, "no_compile_cache", False)
                             else default_cache_dir())
    if getattr(args, "coordinator", None):
        from irdepth_jax.train.parallel import initialize_distributed
        initialize_distributed(args.coordinator, args.num_processes, args.process_id)


@contextlib.contextmanager
def one_line_warnings():
    """Within the block, each distinct `DatasetWarning` (e.g. MS2 sequences not on disk) and
    `DeprecatedKeyWarning` (a config key under its old name) is printed once as one line
    ``irdepth: warning: ...`` on stderr; other warnings as usual."""
    from irdepth_jax.config import DeprecatedKeyWarning
    from irdepth_jax.data.folder import DatasetWarning

    ours = (DatasetWarning, DeprecatedKeyWarning)
    with warnings.catch_warnings():
        for category in ours:
            warnings.simplefilter("default", category)
        show = warnings.showwarning

        def one_line(message, category, *rest, **kwargs):
            if not issubclass(category, ours):
                return show(message, category, *rest, **kwargs)
            print(f"irdepth: warning: {message}", file=sys.stderr, flush=True)

        warnings.showwarning = one_line
        yield


def run_options(args, workdir: str, resume: bool):
    from irdepth_jax.train.phase import RunOptions

    return RunOptions(workdir=workdir, resume=resume, parallel=args.parallel,
                      devices=args.devices, steps=args.steps, stop_at=args.stop_at,
                      progress=not args.no_progress,
                      stage1_checkpoint=getattr(args, "stage1_checkpoint", None))


def check_paths(args, flags: tuple[str, ...]) -> None:
    """CliError (one line naming the flag) for each of `flags` (argument names) whose path must
    exist and does not; 'inputs' (positional) is named by its path alone."""
    for flag in flags:
        value = getattr(args, flag, None)
        for path in value if isinstance(value, list) else [value]:
            if path is not None and not os.path.exists(path):
                where = "" if flag == "inputs" else f"--{flag.replace('_', '-')} "
                raise CliError(f"{where}{path}: no such file or directory")
