"""The `irdepth` command: synth, train, eval, predict, export, quickstart.

Every error a user can cause (unknown config key, a directory that is not a dataset, a
checkpoint of another stage or shape, an 8-bit file given to predict, a workdir that already
holds a run) is printed as one line ``irdepth: error: ...`` with exit code 2, before anything is
written. Only the package's own errors (`irdepth_jax.errors.IrdepthError` and its subclasses)
are reported so; any other exception is a bug and ends with its traceback. Ctrl-C during
training saves a checkpoint and exits with code 130. `irdepth predict` exits with code 1 when
it skipped input files it could not read (the others are written). Set IRDEPTH_DEBUG=1 to
get the traceback instead of the one-line message.

This module is the parser (`build_parser`) and the entry point (`main`); each command is a module
of this package, `irdepth_jax.cli.<command>`, with its parser (`add_parser`), its checks made
before JAX is imported (`check`) and its implementation (`run`); what they share is in
`irdepth_jax.cli.common`.
"""

from __future__ import annotations

import argparse
import os
import sys

from irdepth_jax.cli import eval, export, predict, quickstart, synth, train
from irdepth_jax.cli.common import (
    EXIT_INTERRUPTED,
    EXIT_SKIPPED,
    EXIT_USAGE,
    CliError,
    load_config,
    one_line_warnings,
    setup_jax,
)

__all__ = ["EXIT_INTERRUPTED", "EXIT_SKIPPED", "EXIT_USAGE", "CliError", "build_parser", "load_config", "main"]

COMMANDS = (synth, train, eval, predict, export, quickstart)
"""The command modules, in the order `irdepth --help` lists them."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="irdepth",
        description="Monocular depth from raw 14-bit thermal frames: MTSA-UNet -> HSV -> "
                    "Depth Anything V2 (JAX/Flax).",
        epilog="Start with `irdepth quickstart`; `irdepth COMMAND --help` for each command.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS:
        command.add_parser(sub)
    for command in sub.choices.values():  # how the library's errors name options (errors.py)
        command.set_defaults(flags={a.dest: a.option_strings[-1] for a in command._actions
                                    if a.option_strings})
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `irdepth` console script; returns the exit code."""
    parser = build_parser()
    # Overrides may come anywhere after the command (argparse would only take them in one run).
    args, extra = parser.parse_known_args(argv)
    unknown = [a for a in extra if a.startswith("-") or "=" not in a
               or not hasattr(args, "overrides") or args.command == "predict"]
    if unknown:
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    if extra:
        args.overrides = list(args.overrides) + extra
    try:  # before JAX and the model are loaded: a mistyped path is reported at once
        args.check(args)
    except CliError as err:
        print(f"irdepth: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    from irdepth_jax.errors import Interrupted, IrdepthError, one_line, with_flags

    try:
        setup_jax(args)
        with one_line_warnings():
            return args.func(args)
    except Interrupted as stop:
        print(f"irdepth: {with_flags(str(stop), args.flags)}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except KeyboardInterrupt:
        print("irdepth: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except IrdepthError as err:  # the package's own errors; anything else is a bug: traceback
        if os.environ.get("IRDEPTH_DEBUG"):
            raise
        print(f"irdepth: error: {with_flags(one_line(err), args.flags)}", file=sys.stderr)
        return EXIT_USAGE

