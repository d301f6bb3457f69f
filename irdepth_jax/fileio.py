"""Output files that are complete or absent, never torn, and errors that say the disk is full.

`write_bytes` writes a temporary file beside the target, checks every write, flushes it to disk
(``fsync``) and renames it over the target (``os.replace``, atomic): a failure (a full disk,
a quota, a read-only directory) removes the temporary file, leaves whatever was under the
target's name untouched, and raises `WriteError` naming the target. `write_png` encodes an image
with OpenCV first (``cv2.imencode``, checked too); every PNG the package writes goes through it.

`disk_full` recognises a full disk in errors raised elsewhere (orbax / TensorStore report it as a
ValueError carrying the OS error code as text), `describe_disk` names the mount point of a path
and its free space, for the one-line messages.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import uuid

import numpy as np

from irdepth_jax.errors import IrdepthError

FULL_DISK_ERRNOS = (errno.ENOSPC, errno.EDQUOT)


class WriteError(IrdepthError, OSError, ValueError):
    """An output file that could not be written (one-line message naming it); nothing partial
    is left under its name. A ValueError too, so the CLI reports it as a one-line error."""


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Writes `data` to `path` atomically: all of it, or nothing (see the module docstring).

    Raises WriteError naming `path` (and, for a full disk, its mount point and free space).
    """
    path = os.fspath(path)
    folder, name = os.path.split(os.path.abspath(path))
    tmp = os.path.join(folder, f".{name}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except OSError as err:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        disk = f" on {describe_disk(folder)}" if disk_full(err) else ""
        raise WriteError(f"{path}: not written: {err.strerror or err}{disk}") from err


def write_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """Encodes `image` as PNG (OpenCV channel order: BGR) and writes it with `write_bytes`."""
    import cv2

    ok, encoded = cv2.imencode(".png", image)
    if not ok:
        raise WriteError(f"{os.fspath(path)}: not written: OpenCV cannot encode a "
                         f"{image.dtype} {image.shape} image as PNG")
    write_bytes(path, encoded.tobytes())


def make_dirs(path: str | os.PathLike) -> None:
    """``os.makedirs(path, exist_ok=True)``, a failure raised as WriteError naming `path`."""
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as err:
        raise WriteError(f"{os.fspath(path)}: cannot create the directory: "
                         f"{err.strerror or err}") from err


def disk_full(err: BaseException | None) -> bool:
    """Whether `err`, or an error it was raised from, says the disk (or a quota) is full: an
    OSError with errno ENOSPC / EDQUOT, or TensorStore's text of one (``[os_error_code='28']``,
    "No space left on device") in the ValueError orbax raises."""
    seen = set()
    while err is not None and id(err) not in seen:
        seen.add(id(err))
        if isinstance(err, OSError) and err.errno in FULL_DISK_ERRNOS:
            return True
        text = str(err)
        if any(os.strerror(code) in text or f"os_error_code='{code}'" in text
               for code in FULL_DISK_ERRNOS):
            return True
        err = err.__cause__ or err.__context__
    return False


def mount_point(path: str | os.PathLike) -> str:
    """The mount point of the file system that holds `path` (or would hold it)."""
    path = os.path.realpath(path)
    while not os.path.ismount(path):
        path = os.path.dirname(path)
    return path


def describe_disk(path: str | os.PathLike) -> str:
    """``"the disk mounted at M (X MiB free)"`` for the file system of `path`."""
    mount = mount_point(path)
    try:
        free = f" ({shutil.disk_usage(mount).free / 2**20:.1f} MiB free)"
    except OSError:
        free = ""
    return f"the disk mounted at {mount}{free}"
