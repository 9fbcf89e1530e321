"""Errors the engine reports to users.

Every problem with user input is an :class:`InputError` that names the offending file
and says how to fix it; the CLI turns it into one clear line (and one ``error`` event on
the JSON-lines protocol) instead of a traceback.
"""

from __future__ import annotations

import os


class EngineError(Exception):
    """Base class of errors the CLI reports without a traceback."""

    exit_code = 1


class InputError(EngineError):
    """Bad user input: a missing/unreadable/malformed file or an invalid option.

    Parameters
    ----------
    problem : str
        What is wrong, in one sentence.
    path : str or os.PathLike, optional
        The file or folder the problem is in.
    fix : str, optional
        What the user should do about it.
    """

    exit_code = 2

    def __init__(self, problem: str, path: str | os.PathLike | None = None, fix: str | None = None):
        self.problem = problem
        self.path = None if path is None else os.fspath(path)
        self.fix = fix
        super().__init__(self.message)

    @property
    def message(self) -> str:
        text = f"{self.path}: {self.problem}" if self.path else self.problem
        if self.fix:
            text += f" Fix: {self.fix}"
        return text


class Cancelled(EngineError):
    """The run was interrupted (SIGINT/SIGTERM or a cancel request) after saving state."""

    exit_code = 130


#: what to do about an ``OSError``, by errno name
_OS_FIXES = {
    "ENOSPC": "free disk space (or choose a folder on another disk) and run the command again",
    "EDQUOT": "free space within your disk quota and run the command again",
    "EACCES": "choose a folder you can write to, or fix its permissions",
    "EPERM": "choose a folder you can write to, or fix its permissions",
    "EROFS": "the disk is read-only: choose a folder on a writable disk",
    "ENOTDIR": "a part of the path is a file, not a folder: choose another path",
    "EEXIST": "a part of the path exists as a file, not a folder: choose another path",
    "EISDIR": "the path is a folder: give a file name",
    "ENAMETOOLONG": "use a shorter path",
    "ENOENT": "check the path exists",
}


def describe_os_error(exc: OSError) -> tuple[str, str | None, str]:
    """``(message, path, fix)`` for an ``OSError`` a command did not handle itself."""
    import errno

    name = errno.errorcode.get(exc.errno or 0, "")
    path = exc.filename if exc.filename is None else os.fspath(exc.filename)
    what = exc.strerror or str(exc)
    where = f"{path}: " if path else ""
    fix = _OS_FIXES.get(name, "check the path, its permissions and the free disk space")
    return f"{where}cannot write or read this path ({what}). Fix: {fix}", path, fix
