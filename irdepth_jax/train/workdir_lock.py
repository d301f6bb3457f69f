"""Who owns a run directory, and what it holds: the workdir lock and the clean-up of a run that
made nothing.

One training run at a time per workdir: `claim_workdir` takes ``WORKDIR/irdepth.lock``, a file
holding the owner's ``{"pid", "host"}``, created atomically (``O_CREAT | O_EXCL``) and removed
when the run ends, however it ends. A lock left by a process of this host that no longer runs
(a killed run) is taken over with a one-line note; a live owner, or one on another host (whose
liveness cannot be checked), is a `WorkdirLocked` error naming it. A run that fails or is
interrupted before it has recorded anything (no checkpoint, no logged step) removes what it
created, so that re-running the same command is not refused as "already holds a run"; a
user's existing files are never touched.

No JAX here: the CLI checks a workdir before anything heavy starts.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import socket
import sys
from collections.abc import Iterator

from irdepth_jax.errors import IrdepthError, RunError

LOCK_NAME = "irdepth.lock"
PHASES = ("stage1_i1", "stage1_i2", "stage2")
"""Checkpoint directories of a workdir (``checkpoints/<phase>``), in training order."""


class WorkdirLocked(IrdepthError, ValueError):
    """The workdir is in use by another run (one-line message naming its pid and host)."""


def holds_run(workdir: str) -> bool:
    """Whether `workdir` holds a run (its config.json or checkpoints/), started or finished."""
    return any(os.path.exists(os.path.join(workdir, name))
               for name in ("config.json", "checkpoints"))


def last_checkpoint(workdir: str) -> tuple[str, int] | None:
    """(directory, step) of the last finished checkpoint in `workdir` (of the latest phase),
    or None. Orbax names a finished step directory by its number; unfinished ones carry a
    ``.orbax-checkpoint-tmp`` suffix and are not counted."""
    for phase in reversed(PHASES):
        directory = os.path.join(workdir, "checkpoints", phase)
        steps = [int(n) for n in _listdir(directory) if n.isdigit()]
        if steps:
            return directory, max(steps)
    return None


def held_stages(workdir: str) -> set[str]:
    """Stages ('stage1', 'stage2') whose traces are in `workdir`: checkpoint directories and
    metrics.jsonl records (lines that are not JSON are skipped here)."""
    names = set(_listdir(os.path.join(workdir, "checkpoints")))
    for record in _records(os.path.join(workdir, "metrics.jsonl")):
        names.add(str(record.get("stage", "")))
    return {stage for stage in ("stage1", "stage2") if any(n.startswith(stage) for n in names)}


def _recorded_anything(workdir: str) -> bool:
    """Whether a run has left something worth keeping: a checkpoint or a logged step."""
    return last_checkpoint(workdir) is not None or any(
        isinstance(r.get("step"), int) and r["step"] > 0
        for r in _records(os.path.join(workdir, "metrics.jsonl")))


def _listdir(path: str) -> list[str]:
    return os.listdir(path) if os.path.isdir(path) else []


def _records(path: str) -> Iterator[dict]:
    if not os.path.exists(path):
        return
    with open(path) as f:
        for line in f:
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(record, dict):
                yield record


# --------------------------------------------------------------------------- the lock
def _owner() -> dict:
    return {"pid": os.getpid(), "host": socket.gethostname()}


def _alive(pid: int) -> bool:
    """Whether process `pid` of this host runs (a process of another user counts as running)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def acquire(workdir: str, what: str = "workdir") -> str:
    """Takes the lock of `workdir` (which must exist); returns the lock file's path. `what`
    names the directory in messages (e.g. "--out folder" for predict's outputs).

    Raises WorkdirLocked naming the owner when another live run holds it (or one on another
    host, or an unreadable lock file); takes over, with a note on stderr, the lock of a process
    of this host that no longer runs.
    """
    path = os.path.join(workdir, LOCK_NAME)
    mine = json.dumps(_owner())
    for _ in range(3):  # a stale lock is removed, then the O_EXCL creation is retried
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            pass
        else:
            with os.fdopen(fd, "w") as f:
                f.write(mine + "\n")
            return path
        try:
            with open(path) as f:
                text = f.read()
        except FileNotFoundError:  # released meanwhile
            continue
        try:
            owner = json.loads(text)
            pid, host = int(owner["pid"]), str(owner["host"])
        except (ValueError, KeyError, TypeError):
            raise WorkdirLocked(f"{what} {workdir} has an unreadable lock file {path}; delete "
                                f"it if no run is using this {what}") from None
        if host != socket.gethostname() or _alive(pid):
            raise WorkdirLocked(
                f"{what} {workdir} is in use by another run (pid {pid} on {host}, lock "
                f"{path}); wait for it to end, or delete the lock if that run is gone")
        with contextlib.suppress(FileNotFoundError):
            with open(path) as f:
                still_stale = f.read() == text  # not replaced by a run that just took over
            if still_stale:
                os.remove(path)
                print(f"irdepth: taking over the lock {path} of pid {pid} on {host}, which no "
                      "longer runs", file=sys.stderr, flush=True)
    raise WorkdirLocked(f"{what} {workdir}: could not take the lock {path} (another run keeps "
                        "taking it)")


def release(path: str) -> None:
    """Removes the lock file at `path` if this process still owns it."""
    with contextlib.suppress(FileNotFoundError, ValueError):
        with open(path) as f:
            owner = json.loads(f.read())
        if owner == _owner():
            os.remove(path)


@contextlib.contextmanager
def claim_workdir(workdir: str) -> Iterator[None]:
    """Runs the block as the only run in `workdir` (created if missing).

    The lock is held for the block. If the block raises (an error, Ctrl-C) before anything was
    recorded in the workdir (no checkpoint, no logged step), what the block created there is
    removed: the workdir itself when this call created it, else the entries it added.
    """
    if os.path.exists(workdir) and not os.path.isdir(workdir):
        raise RunError(f"`workdir` {workdir}: exists and is not a directory")
    created = not os.path.exists(workdir)
    os.makedirs(workdir, exist_ok=True)
    before = set(os.listdir(workdir))
    lock = acquire(workdir)
    try:
        yield
    except BaseException:
        if not _recorded_anything(workdir):
            if created:
                shutil.rmtree(workdir, ignore_errors=True)
            else:
                for name in set(os.listdir(workdir)) - before - {LOCK_NAME}:
                    target = os.path.join(workdir, name)
                    if os.path.isdir(target) and not os.path.islink(target):
                        shutil.rmtree(target, ignore_errors=True)
                    else:
                        os.remove(target)
        raise
    finally:
        release(lock)
