"""Where a store is written: one writer per destination, what killed writers left behind, and no store inside another.

A writer owns its destination from start to finish: it holds a lock on the hidden ``.<name>.lock`` sibling, so a
second writer of the same path is refused when it starts. It writes into a hidden ``.<name>.partial-<pid>-<id>``
sibling, which the next writer of the path removes if the process that made it no longer runs.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import uuid
from collections.abc import Iterator
from pathlib import Path

from bpp.data.integrity import StoreBusy, StoreError, is_store
from bpp.utils import process_alive

try:
    import fcntl
except ImportError:  # not POSIX: writers are kept apart by the check at the rename alone
    fcntl = None

_PARTIAL_TAG = re.compile(r"(?P<pid>[0-9]+)-[^-]*")
"""The tag after ``.partial-`` in a writer's folder: the writer's process id (ASCII digits), then a random part."""


def partial_path(path: Path) -> Path:
    """A new hidden sibling of `path` for a writer in this process to write into: ``.<name>.partial-<pid>-<id>``."""
    return path.parent / f".{path.name}.partial-{os.getpid()}-{uuid.uuid4().hex[:8]}"


def remove_stale_partials(path: Path) -> list[Path]:
    """Delete the hidden ``.<name>.partial-<pid>-<id>`` folders that interrupted writers of `path` left behind: those
    whose process no longer runs. A writer still running keeps its folder, and a folder whose process id is not written
    in ASCII digits is no writer's and is left alone. Returns what was deleted."""
    removed = []
    for partial in path.parent.glob(f".{path.name}.partial-*"):
        tag = _PARTIAL_TAG.fullmatch(partial.name.rsplit(".partial-", 1)[1])
        if tag is not None and not process_alive(int(tag["pid"])) and partial.is_dir():
            shutil.rmtree(partial, ignore_errors=True)
            removed.append(partial)
    return removed


def enclosing_store(path: Path) -> Path | None:
    """The episode store (complete or not) that `path` would lie inside, if any."""
    return next((parent for parent in path.resolve().parents if is_store(parent)), None)


class DestinationLock:
    """A writer's exclusive hold on a store path: an advisory lock (flock) on the hidden sibling ``.<name>.lock``,
    which holds the writer's process id. The kernel drops it when that process ends, however it ends; the file is
    removed on release."""

    def __init__(self, path: Path):
        self.file = path.parent / f".{path.name}.lock"
        self.handle = None
        if fcntl is None:
            return
        while True:
            try:
                handle = open(self.file, "a+")  # noqa: SIM115 - held open until release
            except OSError as err:
                raise StoreError(f"{path}: cannot write there ({err.strerror}: {self.file})") from None
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as err:
                handle.seek(0)
                holder = handle.read().strip()[:100]
                handle.close()
                if err.errno in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                    raise StoreBusy(
                        f"{path} is being written by another writer ({holder or 'another process'}); wait for it to "
                        "finish, or choose another path"
                    ) from None
                return  # a file system without locks: the check at the rename remains
            try:  # the file may have been removed by a writer that finished meanwhile: then lock the new one
                same = os.stat(self.file).st_ino == os.fstat(handle.fileno()).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            handle.close()
        handle.seek(0)
        handle.truncate()
        handle.write(f"process {os.getpid()}")
        handle.flush()
        self.handle = handle

    def release(self) -> None:
        if self.handle is not None:
            with contextlib.suppress(FileNotFoundError):
                self.file.unlink()  # while still locked, so that no other writer holds a lock on a removed file
            self.handle.close()
            self.handle = None


@contextlib.contextmanager
def destination_lock(path: str | Path) -> Iterator[None]:
    """Hold, for the block, the lock a writer of `path` holds (a StoreBusy at once if another writer holds it): for
    work that fills `path` over longer than one writer lives, e.g. a journal of finished tasks that a killed
    generation resumes from."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lock = DestinationLock(path)
    try:
        yield
    finally:
        lock.release()
