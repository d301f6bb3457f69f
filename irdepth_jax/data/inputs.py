"""The raw thermal files a user names (files and folders), found, read and checked before any
model runs: what `irdepth predict` takes as input."""

from __future__ import annotations

import dataclasses
import fnmatch
import os
import sys
from collections.abc import Sequence

from irdepth_jax.errors import RunError

SKIPPED_NAMES_SHOWN = 8
"""Skipped files named in predict's summary line (the rest are counted)."""


def list_inputs(inputs: Sequence[str], pattern: str | None = None
                ) -> list[tuple[str, list[str]]]:
    """The files `inputs` name, per input: (input, its files).

    A file stands for itself; a folder for its files (not sub-folders) whose names match the
    glob `pattern` (default: every file with a `data.rawio.RAW_SUFFIXES` suffix), sorted.
    RunError (one line) for a missing path or a folder with no such file.
    """
    from irdepth_jax.data.rawio import RAW_SUFFIXES

    listed = []
    for item in inputs:
        if os.path.isdir(item):
            names = sorted(n for n in os.listdir(item) if os.path.isfile(os.path.join(item, n))
                           and (fnmatch.fnmatch(n, pattern) if pattern
                                else n.lower().endswith(RAW_SUFFIXES)))
            if not names:
                wanted = (f"--glob {pattern!r}" if pattern
                          else f"a raw frame suffix ({', '.join(RAW_SUFFIXES)})")
                raise RunError(f"{item}: no file matches {wanted}")
            listed.append((item, [os.path.join(item, n) for n in names]))
        elif os.path.isfile(item):
            listed.append((item, [item]))
        else:
            raise RunError(f"{item}: no such file or directory")
    return listed


@dataclasses.dataclass(frozen=True)
class ThermalInput:
    """One input of `irdepth predict` (a file or folder) and its raw thermal files."""

    item: str
    files: tuple[str, ...]
    frames: int
    """How many frames the files hold."""
    shapes: tuple[tuple[tuple[int, int], int], ...]
    """((H, W), number of frames of that size) of the files' frames."""


def thermal_inputs(inputs: Sequence[str], bits: int, pattern: str | None = None,
                   strict: bool = False) -> list[ThermalInput]:
    """The raw thermal files among `inputs` (files and folders, see `list_inputs`), each read
    and checked as `bits`-bit counts (`data.rawio.read_frames`), per input.

    In a folder, 8-bit and colour images (visible / NIR frames beside the thermal ones) are
    skipped and named in one ``irdepth: skipped ...`` line on stderr; with `strict` they are an
    error. A file named in `inputs` must be a thermal frame, and so must a folder hold at least
    one. Outputs are named by frame: two frames of the same name are an error.

    Raises:
      RunError / `data.rawio.RawFileError` (ValueErrors, one line naming the file).
    """
    from irdepth_jax.data.rawio import NotThermalError, read_frames

    found, skipped, owner = [], [], {}
    in_folders = 0
    for item, files in list_inputs(inputs, pattern):
        folder = os.path.isdir(item)
        in_folders += len(files) if folder else 0
        kept, frames, shapes = [], 0, {}
        for f in files:
            try:
                read = read_frames(f, bits)
            except NotThermalError as err:
                if strict or not folder:
                    hint = " (--strict: pick the thermal files with --glob)" if folder else ""
                    raise RunError(f"{err}{hint}") from None
                skipped.append(f)
                continue
            for name, raw in read:
                if name in owner:
                    raise RunError(f"{f} and {owner[name]}: same name {name!r}, their outputs "
                                     "would overwrite each other (predict them into separate "
                                     "--out folders)")
                owner[name] = f
                shapes[raw.shape] = shapes.get(raw.shape, 0) + 1
            kept.append(f)
            frames += len(read)
        if folder and not kept:
            raise RunError(f"{item}: none of its {len(files)} files is a raw thermal frame "
                             "(all 8-bit or colour images)")
        found.append(ThermalInput(item, tuple(kept), frames, tuple(shapes.items())))
    if skipped:
        names = [os.path.basename(f) for f in skipped]
        more = len(names) - SKIPPED_NAMES_SHOWN
        shown = ", ".join(names[:SKIPPED_NAMES_SHOWN]) + (f" and {more} more" if more > 0 else "")
        print(f"irdepth: skipped {len(skipped)} of {in_folders} files that are not raw thermal "
              f"frames (8-bit or colour): {shown}", file=sys.stderr)
    return found
