"""The package's one-line errors: what the CLI prints as ``irdepth: error: ...`` (no traceback),
and the wording of its messages.

A message speaks of config keys (``stage2.preprocessing``), files and directories, and names an
option of the call that failed (a parameter, e.g. `RunOptions.resume`) in backquotes:
``"pass `resume` to continue it"``. The CLI shows such a name as its flag (``--resume``,
`with_flags`); a library caller reads the parameter's name.
"""

from __future__ import annotations

import re
from collections.abc import Mapping


class IrdepthError(Exception):
    """Base of the package's own errors: a setting, file, dataset or checkpoint that cannot be
    used, with a one-line message naming it. The CLI prints these (and only these) as
    ``irdepth: error: ...``; any other exception is a bug and keeps its traceback."""


class RunError(IrdepthError, ValueError):
    """A run that cannot start (one-line message naming the file, directory or key)."""


class ConfigError(RunError):
    """A config value or key that is not allowed (the message names the dotted key and what it
    allows)."""


class Interrupted(Exception):
    """Training stopped on Ctrl-C after saving a checkpoint (message says where)."""


def one_line(err: BaseException) -> str:
    """The first line of an error's message (its type's name when it has none)."""
    text = str(err).strip().splitlines()
    return text[0] if text else type(err).__name__


_OPTION = re.compile(r"`([a-z][a-z0-9_]*)`")


def with_flags(message: str, flags: Mapping[str, str]) -> str:
    """`message` with each option it names in backquotes written as its flag, by `flags`
    (option name -> flag, e.g. {'stage1_checkpoint': '--stage1-checkpoint'}); a name that is
    not in `flags` keeps its backquotes."""
    return _OPTION.sub(lambda m: flags.get(m.group(1), m.group(0)), message)


def counted(n: int, noun: str) -> str:
    """``'1 frame'``, ``'2 frames'``: a count and its noun, plural unless it is one."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"
