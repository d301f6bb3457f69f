"""What a training run reads, summarised so that a resumed run can check it reads the same data.

A fingerprint of the frames of a phase (``{phase: (dataset, indices)}``): per phase the number
of frames and a hash of their ids, a hash of the names and sizes of the files they are read
from, and a hash of the dataset's index files (a folder dataset's manifest.json, MS2's split
lists). `fingerprint_changes` names what differs between two fingerprints. No file contents are
hashed beyond the index files: a fingerprint costs one ``stat`` per file.
"""

from __future__ import annotations

import hashlib
import json
import os
import pathlib
from collections.abc import Iterable

INDEX_FILES = ("manifest.json", "train_list.txt", "val_list.txt", "test_day_list.txt",
               "test_night_list.txt", "test_rainy_list.txt")


def _digest(items: Iterable) -> str:
    return hashlib.sha1(json.dumps(list(items)).encode()).hexdigest()[:16]


def _files(dataset, ids: list[str]) -> list[tuple[str, int]]:
    """(path relative to the dataset's root, size) of the files frames `ids` are read from."""
    root = pathlib.Path(dataset.root)
    used = set(ids)
    records = [r for r in dataset.records if r["id"] in used]
    if records and "raw_path" in records[0]:  # MS2: each record names its files
        paths = [pathlib.Path(r[k]) for r in records for k in ("raw_path", "depth_path")]
        return sorted((str(p.relative_to(root)), p.stat().st_size) for p in paths)
    wanted = {f"{i}.png" for i in ids}  # a folder dataset: FIELD/ID.png
    return sorted((f"{sub.name}/{e.name}", e.stat().st_size)
                  for sub in os.scandir(root) if sub.is_dir()
                  for e in os.scandir(sub.path) if e.name in wanted)


def data_fingerprint(frames: dict) -> dict:
    """The fingerprint of ``{phase: (dataset, indices)}`` (see the module docstring); a dataset
    without ``records`` and ``root`` (e.g. frames mixed from several sources) is counted only."""
    out = {}
    for phase, (dataset, idx) in frames.items():
        entry = {"frames": len(idx)}
        if hasattr(dataset, "records") and hasattr(dataset, "root"):
            ids = [dataset.records[int(i)]["id"] for i in idx]
            root = pathlib.Path(dataset.root)
            index = hashlib.sha1()
            for name in INDEX_FILES:
                if (root / name).is_file():
                    index.update(name.encode() + b"\0" + (root / name).read_bytes())
            entry.update(root=str(root), ids=_digest(ids), files=_digest(_files(dataset, ids)),
                         index=index.hexdigest()[:16])
        out[phase] = entry
    return out


def fingerprint_changes(recorded: dict, now: dict) -> list[str]:
    """What differs from `recorded` in `now`, one phrase per phase, e.g.
    ``stage1_i1: 11 frames added (21 -> 32)``; empty when nothing does."""
    changes = []
    for phase, was in recorded.items():
        new = now.get(phase)
        if new is None:
            continue
        what = []
        if new["frames"] != was["frames"]:
            diff = new["frames"] - was["frames"]
            what.append(f"{abs(diff)} frames {'added' if diff > 0 else 'removed'} "
                        f"({was['frames']} -> {new['frames']})")
        elif new.get("ids") != was.get("ids"):
            what.append("other frames (their ids differ)")
        if new.get("files") != was.get("files") and not what:
            what.append("files of its frames changed size")
        if new.get("index") != was.get("index"):
            what.append("the manifest / split lists changed")
        if what:
            changes.append(f"{phase}: {', '.join(what)}")
    return changes
