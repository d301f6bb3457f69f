"""The package's one-line errors: what the CLI prints as ``irdepth: error: ...`` (no traceback),
and the wording of its messages."""

from __future__ import annotations


class RunError(ValueError):
    """A run that cannot start (one-line message naming the file, directory or key)."""


class Interrupted(Exception):
    """Training stopped on Ctrl-C after saving a checkpoint (message says where)."""


def one_line(err: BaseException) -> str:
    """The first line of an error's message (its type's name when it has none)."""
    text = str(err).strip().splitlines()
    return text[0] if text else type(err).__name__


def counted(n: int, noun: str) -> str:
    """``'1 frame'``, ``'2 frames'``: a count and its noun, plural unless it is one."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"
