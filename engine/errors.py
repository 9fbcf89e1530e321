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
