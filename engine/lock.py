"""One writer per output folder: a lock file in ``--out`` while a command writes there.

Two ``engine train`` runs into the same folder would interleave their files and both
report success. :func:`hold` creates ``<out>/.motion-splats.lock`` with ``O_EXCL`` (atomic
on every local file system) holding the owner's pid and host; a second writer is refused
in one line. A lock left by a process that no longer exists (SIGKILL, power loss) on the
same host is stale and taken over. The lock is removed on exit, error or interruption.
Taking the lock also removes temporaries a killed writer left behind
(:func:`engine.fsutil.clean_stale_temps`).
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
from pathlib import Path
from typing import Iterator

from .errors import InputError
from .fsutil import clean_stale_temps

LOCK_NAME = ".motion-splats.lock"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def _owner(path: Path) -> dict | None:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _is_stale(owner: dict | None) -> bool:
    """A lock is stale when its owner on this host is gone, or it cannot be read at all."""
    if owner is None:
        return True
    pid = owner.get("pid")
    if owner.get("host") != socket.gethostname() or not isinstance(pid, int):
        return False  # another machine (network folder): cannot tell, so respect it
    return pid != os.getpid() and not _alive(pid)


def acquire(folder: str | os.PathLike) -> Path:
    """Create the lock in ``folder`` (made if missing); raise :class:`InputError` if held."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / LOCK_NAME
    me = json.dumps({"pid": os.getpid(), "host": socket.gethostname()}).encode()
    for _ in range(2):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            owner = _owner(path)
            if _is_stale(owner):
                with contextlib.suppress(FileNotFoundError):
                    path.unlink()
                continue
            who = f"process {owner.get('pid')} on {owner.get('host')}"
            raise InputError(f"another engine command ({who}) is writing to this folder", folder,
                             "wait for it to finish or cancel it, or choose another --out") from None
        with os.fdopen(fd, "wb") as fh:
            fh.write(me)
        clean_stale_temps(folder)  # ours now: any half-written temporary is from a killed run
        return path
    raise InputError("cannot take the output folder's lock", path, "remove the lock file if no engine is running")


def release(path: Path) -> None:
    """Remove a lock this process holds (a lock taken over by another process stays)."""
    owner = _owner(path)
    if owner is not None and owner.get("pid") == os.getpid() and owner.get("host") == socket.gethostname():
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


@contextlib.contextmanager
def hold(folder: str | os.PathLike) -> Iterator[Path]:
    """``with hold(out):`` -- the folder's lock for the duration of the block.

    A folder this call created is removed again when the block leaves it empty (a
    command refused before writing anything leaves no trace).
    """
    created = not Path(folder).exists()
    path = acquire(folder)
    try:
        yield path
    finally:
        release(path)
        if created:
            with contextlib.suppress(OSError):
                Path(folder).rmdir()  # only succeeds when empty
