"""One base for the project's errors.

Every exception the project raises on purpose derives from :class:`RoomcapError` and keeps its builtin
parent (``FormatError`` is still a ``ValueError``, ``ModelError`` a ``FileNotFoundError``), so callers
that catch the builtin keep working and a command-line tool catches the whole family once
(:func:`roomcap.core.cli.guarded`).
"""

from __future__ import annotations

import os


class RoomcapError(Exception):
    """An error whose message says what is wrong and what to do; shown to users without a traceback."""


class InputError(RoomcapError, ValueError):
    """A value given by the user (an argument, a file's content) is out of range or inconsistent."""


class UnknownNameError(RoomcapError, KeyError):
    """A name (model set, skeleton, camera, joint) that is not among the known ones; the message lists them.

    A ``KeyError`` for callers that catch one, but printed as its sentence (``KeyError`` quotes it).
    """

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class FormatError(RoomcapError, ValueError):
    """A file that is not what it claims to be: names the file, the field and the fix."""

    def __init__(self, path: str | os.PathLike[str] | None, field: str | None, problem: str, fix: str = ""):
        self.path = None if path is None else str(path)
        self.field = field
        where = f"{self.path}" if self.path else "<input>"
        if field:
            where += f": field '{field}'"
        msg = f"{where}: {problem}"
        if fix:
            msg += f" {fix}"
        super().__init__(msg)


class SchemaError(FormatError):
    """The file's schema tag is missing, names another format or a version this code cannot read."""
