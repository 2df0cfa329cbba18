"""The locks of pixloc's runs: a lock file per output folder or store, taken over where its holder
(a killed run on this host) is gone."""

import contextlib
import os
import socket
from pathlib import Path
from typing import Optional

from pipeline.store import location

LOCK = ".pixloc.lock"  # in an output folder


class OutputLocked(ValueError):
    """Another run is writing to the output folder."""


@contextlib.contextmanager
def output_lock(output: Path):
    """Exclusive use of ``output`` by this process (``file_lock`` on ``output/.pixloc.lock``)."""
    output.mkdir(parents=True, exist_ok=True)
    with file_lock(output / LOCK, f"{output} is in use by another pixloc run"):
        yield


@contextlib.contextmanager
def file_lock(path: Path, busy: str):
    """Hold the lock file ``path``; a live holder's lock is refused (OutputLocked, ``busy`` and
    the holder), a dead one's (a killed run) taken over."""
    me = f"{socket.gethostname()} {os.getpid()}"
    for _ in range(2):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            holder = path.read_text().split() if path.exists() else []
            if len(holder) == 2 and holder[0] == socket.gethostname() and not _alive(int(holder[1])):
                path.unlink(missing_ok=True)  # left by a run that was killed
                continue
            raise OutputLocked(f"{busy} ({' pid '.join(holder) or 'unknown'}); wait for it to finish, or remove "
                               f"{path} if no run is going on.") from None
        with os.fdopen(fd, "w") as f:
            f.write(me)
        break
    try:
        yield
    finally:
        path.unlink(missing_ok=True)


def store_lock(store, work_dir: Optional[Path] = None):
    """The lock a build takes on its store: ``STORE.lock`` beside a local store (the store itself
    may be erased and recreated under it by --overwrite); for a store in object storage,
    ``store.lock`` in the build's local work folder, which stops a second build from this host
    only: builds from several hosts into one bucket are the caller's to serialise
    (docs/cluster.md)."""
    if location.is_url(store):
        path = Path(work_dir or location.work_dir(store)) / "store.lock"
    else:
        store = Path(store)
        path = store.with_name(store.name + ".lock")
    path.parent.mkdir(parents=True, exist_ok=True)
    return file_lock(path, f"{store} is being built by another pixloc build-map")


def work_dir_lock(work_dir: Path):
    """The lock a build takes on its work folder (``.pixloc.lock`` there): two builds of different
    stores with one --work-dir would write one COLMAP database and reconstruction at once."""
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    return file_lock(work_dir / LOCK, f"the work folder {work_dir} is in use by another pixloc build-map "
                                      "(give each build its own --work-dir)")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
