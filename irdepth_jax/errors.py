"""The package's one-line errors: what the CLI prints as ``irdepth: error: ...`` (no traceback)."""

from __future__ import annotations


class RunError(ValueError):
    """A run that cannot start (one-line message naming the file, directory or key)."""


class Interrupted(Exception):
    """Training stopped on Ctrl-C after saving a checkpoint (message says where)."""


def one_line(err: BaseException) -> str:
    """The first line of an error's message (its type's name when it has none)."""
    text = str(err).strip().splitlines()
    return text[0] if text else type(err).__name__
