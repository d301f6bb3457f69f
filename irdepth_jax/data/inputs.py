"""The raw thermal files a user names (files and folders), found, read and checked before any
model runs: what `irdepth predict` takes as input.

Each file is decoded once (`FrameReader`): `thermal_inputs` decodes and checks every file, and
keeps the decoded frames (up to `KEPT_BYTES`) for the run, which takes them from there
(`FoundInputs.frames`) in input order.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import os
import sys
from collections.abc import Iterator, Sequence

import numpy as np

from irdepth_jax.errors import RunError, counted

SKIPPED_NAMES_SHOWN = 8
"""Skipped files named in predict's summary lines (the rest are counted)."""
KEPT_BYTES = 2**30
"""Bytes of decoded frames `thermal_inputs` keeps for the run: the frames of the first files,
up to this size; a file beyond it is decoded again when the run reaches it, so that a long
sequence is streamed, not held in memory."""


@dataclasses.dataclass(frozen=True)
class ListedFolder:
    """The files of one input (a file, a folder, or with `recursive` one folder of its tree)."""

    item: str
    """The input as named by the user."""
    path: str
    """The file, or the folder these files are in."""
    relative: str
    """`path`'s folder relative to `item` ('' for `item` itself or a file)."""
    files: tuple[str, ...]


def list_inputs(inputs: Sequence[str], pattern: str | None = None,
                recursive: bool = False) -> list[ListedFolder]:
    """The files `inputs` name.

    A file (or a ROS 2 bag's folder, `data.rosbag.is_bag`) stands for itself; a folder for its
    files (and ROS 2 bags) whose names match the glob `pattern` (default: every file with a
    `data.rawio.RAW_SUFFIXES` suffix), sorted: those directly in it, or with `recursive` those
    of every folder of its tree (one entry per folder that has such files, in sorted order;
    symbolic links to folders are not followed).
    RunError (one line) for a missing path or a folder (tree) with no such file.
    """
    from irdepth_jax.data.rawio import RAW_SUFFIXES
    from irdepth_jax.data.rosbag import is_bag

    def wanted(name: str) -> bool:
        return fnmatch.fnmatch(name, pattern) if pattern else name.lower().endswith(RAW_SUFFIXES)

    listed = []
    for item in inputs:
        if is_folder(item):
            found = []
            for folder, subfolders, names in os.walk(item):
                bags = [n for n in subfolders if is_bag(os.path.join(folder, n))]
                subfolders[:] = [] if not recursive else sorted(set(subfolders) - set(bags))
                files = tuple(os.path.join(folder, n) for n in sorted(names + bags)
                              if (pattern is None and n in bags or wanted(n))
                              and os.path.exists(os.path.join(folder, n)))
                relative = os.path.relpath(folder, item)
                if files:
                    found.append(ListedFolder(item, folder, "" if relative == "." else relative,
                                              files))
            if not found:
                what = (f"--glob {pattern!r}" if pattern
                        else f"a raw frame suffix ({', '.join(RAW_SUFFIXES)})")
                where = " or its sub-folders" if recursive else ""
                hint = "" if recursive else " (--recursive reads its sub-folders too)"
                raise RunError(f"{item}: no file{where} matches {what}{hint}")
            listed.extend(found)
        elif os.path.exists(item):
            listed.append(ListedFolder(item, item, "", (item,)))
        else:
            raise RunError(f"{item}: no such file or directory")
    return listed


@dataclasses.dataclass(frozen=True)
class ThermalInput:
    """One sequence of `irdepth predict`'s inputs (a file, a folder, or a folder of a tree read
    with --recursive) and its raw thermal files."""

    item: str
    """The file or folder."""
    files: tuple[str, ...]
    frames: int
    """How many frames the files hold."""
    shapes: tuple[tuple[tuple[int, int], int], ...]
    """((H, W), number of frames of that size) of the files' frames."""
    out_dir: str = ""
    """Where its outputs go, relative to --out ('' for --out itself)."""


@dataclasses.dataclass(frozen=True)
class Frame:
    """One raw frame to predict: its input file, output name, counts (H, W) uint16 and output
    folder (relative to --out)."""

    file: str
    name: str
    raw: np.ndarray
    out_dir: str = ""


class FrameReader:
    """Decodes raw files (`data.rawio.read_frames`, `bits`-bit counts, a ROS bag's `topic`) and
    keeps what it decoded, up to `kept_bytes` (default `KEPT_BYTES`), until the run takes it:
    each frame decoded once."""

    def __init__(self, bits: int, topic: str | None = None, kept_bytes: int | None = None):
        self.bits, self.topic = bits, topic
        self.kept_bytes = KEPT_BYTES if kept_bytes is None else kept_bytes
        self._kept: dict[str, list[tuple[str, np.ndarray]]] = {}
        self._kept_total = 0

    def scan(self, file: str) -> list[tuple[str, tuple[int, int]]]:
        """[(frame name, (H, W))] of `file`, decoded and checked now (its frames kept when they
        fit). Raises `data.rawio.RawFileError` / `NotThermalError`."""
        frames = self._read(file)
        size = sum(raw.nbytes for _, raw in frames)
        if self._kept_total + size <= self.kept_bytes:
            self._kept[file], self._kept_total = frames, self._kept_total + size
        return [(name, raw.shape) for name, raw in frames]

    def frames(self, sequences: Sequence[ThermalInput]) -> Iterator[Frame]:
        """The frames of `sequences`, in order: those `scan` kept (handed over once, then
        released), the others decoded now."""
        for sequence in sequences:
            for file in sequence.files:
                kept = self._kept.pop(file, None)
                for name, raw in self._read(file) if kept is None else kept:
                    yield Frame(file, name, raw, sequence.out_dir)

    def _read(self, file: str) -> list[tuple[str, np.ndarray]]:
        from irdepth_jax.data.rawio import read_frames

        return read_frames(file, self.bits, self.topic)


@dataclasses.dataclass(frozen=True)
class FoundInputs:
    """`thermal_inputs`' answer: the sequences to predict and the files left out."""

    sequences: tuple[ThermalInput, ...]
    unreadable: tuple[tuple[str, str], ...]
    """(file, reason) of each file skipped as not a readable raw frame of the run's bit depth
    (e.g. counts over 14 bits), in the order read."""
    listed: int
    """How many files the inputs name."""
    reader: FrameReader = dataclasses.field(compare=False, repr=False)
    """The reader that decoded them; its frames go to the run (`frames`)."""

    def frames(self, sequences: Sequence[ThermalInput] | None = None) -> Iterator[Frame]:
        """The frames of `sequences` (default: all of them) in order, each decoded once."""
        return self.reader.frames(self.sequences if sequences is None else sequences)


def is_folder(path: str) -> bool:
    """Whether `path` is a folder of inputs (a folder that is not a ROS 2 bag)."""
    from irdepth_jax.data.rosbag import is_bag

    return os.path.isdir(path) and not is_bag(path)


def thermal_inputs(inputs: Sequence[str], bits: int, pattern: str | None = None,
                   strict: bool = False, recursive: bool = False,
                   topic: str | None = None) -> FoundInputs:
    """The raw thermal files among `inputs` (files and folders, see `list_inputs`), each read
    and checked as `bits`-bit counts (`data.rawio.read_frames`; `topic`: a ROS bag's image
    topic).

    In a folder, 8-bit and colour images (visible / NIR frames beside the thermal ones) are
    skipped and named in one ``irdepth: skipped ...`` line on stderr; with `strict` they are an
    error, and a file named in `inputs` must be a thermal frame. Any other file that is not a
    readable raw frame of `bits` bits (a count over 2^bits - 1, which is never clipped: it
    would be read at the wrong scale; a corrupt file) is left out and returned in
    `FoundInputs.unreadable`, or with `strict` an error; so is a run in which no frame is left.

    Outputs are named by frame (`ThermalInput.out_dir` / NAME): with `recursive` each folder of
    a tree goes to its relative path under --out. When frames of the same name come from
    different inputs, each input gets its own sub-folder of --out named after its folder (a
    file's folder), with as many parent folders as make the names distinct (a note on stderr
    says so); two frames of the same name from one input folder are an error.

    Raises:
      RunError / `data.rawio.RawFileError` (ValueErrors, one line naming the file).
    """
    from irdepth_jax.data.rawio import NotThermalError, RawFileError

    reader = FrameReader(bits, topic)
    listed = list_inputs(inputs, pattern, recursive)
    not_thermal, unreadable, read = [], [], []
    seen: dict = {}
    for entry in listed:
        folder = is_folder(entry.item)
        kept, frames = [], []
        for f in entry.files:
            real = os.path.realpath(f)
            if real in seen:
                raise RunError(f"{f}: named twice (in {seen[real]} and {entry.item}); name each "
                               "file once")
            seen[real] = entry.item
            try:
                frames.append(reader.scan(f))
            except NotThermalError as err:
                if strict or not folder:
                    hint = " (--strict: pick the thermal files with --glob)" if folder else ""
                    raise RunError(f"{err}{hint}") from None
                not_thermal.append(f)
                continue
            except RawFileError as err:
                if strict:
                    raise RunError(f"{err} (--strict: stopped at the first unreadable file)"
                                   ) from None
                message = str(err)
                unreadable.append((f, message[len(f) + 2:] if message.startswith(f"{f}: ")
                                   else message))
                continue
            kept.append(f)
        read.append((entry, kept, frames))
    for item in dict.fromkeys(e.item for e in listed if is_folder(e.item)):
        files = {f for e in listed if e.item == item for f in e.files}
        if files <= set(not_thermal):
            raise RunError(f"{item}: none of its {len(files)} files is a raw thermal frame "
                           "(all 8-bit or colour images)")
    _say_skipped(not_thermal, sum(len(e.files) for e in listed if is_folder(e.item)))
    if not any(kept for _, kept, _ in read):
        first, reason = unreadable[0]
        more = f" ({counted(len(unreadable) - 1, 'more file')} not readable either)" \
            if len(unreadable) > 1 else ""
        raise RunError(f"{first}: {reason}{more}; no frame left to predict")
    out_dirs = _output_folders(read)
    sequences = []
    for (entry, kept, frames), out_dir in zip(read, out_dirs):
        if not kept:
            continue
        shapes: dict = {}
        for shape in (shape for file_frames in frames for _, shape in file_frames):
            shapes[shape] = shapes.get(shape, 0) + 1
        sequences.append(ThermalInput(entry.path, tuple(kept), sum(shapes.values()),
                                      tuple(shapes.items()), out_dir))
    return FoundInputs(tuple(sequences), tuple(unreadable), sum(len(e.files) for e in listed),
                       reader)


def _output_folders(read: list) -> list[str]:
    """The output folder (relative to --out) of each listed folder of `thermal_inputs`: its
    relative path in its input's tree, under a folder per input when two inputs have frames of
    the same name (`_short_names`). RunError for two frames of one output name."""
    def owners(out_dirs):
        owner: dict = {}
        for (entry, kept, frames), out_dir in zip(read, out_dirs):
            for f, file_frames in zip(kept, frames):
                for name, _ in file_frames:
                    owner.setdefault(os.path.join(out_dir, name), []).append((entry.item, f))
        return {key: files for key, files in owner.items() if len(files) > 1}

    out_dirs = [entry.relative for entry, _, _ in read]
    clashes = owners(out_dirs)
    if any(len({item for item, _ in files}) > 1 for files in clashes.values()):
        homes = {entry.item: os.path.realpath(entry.item if is_folder(entry.item)
                                              else os.path.dirname(entry.item) or ".")
                 for entry, _, _ in read}
        names = _short_names(set(homes.values()))
        out_dirs = [os.path.join(names[homes[entry.item]], entry.relative) for entry, _, _ in read]
        key, files = next(iter(clashes.items()))
        folders = sorted({names[home] + "/" for home in homes.values()})
        print(f"irdepth: note: {files[0][1]} and {files[1][1]} have the same name "
              f"{os.path.basename(key)!r}: each input's outputs go to its own sub-folder of "
              f"--out ({', '.join(folders)})", file=sys.stderr)
        clashes = owners(out_dirs)
    for key, files in clashes.items():
        raise RunError(f"{files[1][1]} and {files[0][1]}: same name {os.path.basename(key)!r}, "
                       "their outputs would overwrite each other (predict them into separate "
                       "--out folders)")
    return out_dirs


def _short_names(folders: set[str]) -> dict[str, str]:
    """{folder: its last path components, as few as make the names distinct} of distinct
    absolute paths."""
    parts = {f: f.strip(os.sep).split(os.sep) for f in folders}

    def name(folder: str) -> str:
        mine = parts[folder]
        for k in range(1, len(mine) + 1):
            if all(parts[other][-k:] != mine[-k:] for other in parts if other != folder):
                return os.path.join(*mine[-k:])
        return os.path.join(*mine) or "input"

    return {f: name(f) for f in parts}


def _say_skipped(not_thermal: list[str], in_folders: int) -> None:
    """The ``irdepth: skipped ...`` line of the 8-bit / colour files left out of folders."""
    if not not_thermal:
        return
    print(f"irdepth: skipped {len(not_thermal)} of {in_folders} files that are not raw thermal "
          f"frames (8-bit or colour): {_names(os.path.basename(f) for f in not_thermal)}",
          file=sys.stderr)


def unreadable_summary(found: FoundInputs) -> str | None:
    """The line that ends a run with files left out as unreadable (`FoundInputs.unreadable`):
    how many, and each file with its reason (the first `SKIPPED_NAMES_SHOWN`)."""
    if not found.unreadable:
        return None
    return (f"irdepth: skipped {len(found.unreadable)} of {found.listed} files, not readable "
            f"as raw frames: {_names([f'{f} ({reason})' for f, reason in found.unreadable], '; ')}")


def _names(names, sep: str = ", ") -> str:
    names = list(names)
    more = len(names) - SKIPPED_NAMES_SHOWN
    return sep.join(names[:SKIPPED_NAMES_SHOWN]) + (f" and {more} more" if more > 0 else "")
