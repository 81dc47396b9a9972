"""One base for the project's errors.

Every exception the project raises on purpose derives from :class:`RoomcapError` and keeps its builtin
parent (``FormatError`` is still a ``ValueError``, ``ModelError`` a ``FileNotFoundError``), so callers
that catch the builtin keep working and a command-line tool catches the whole family once
(:func:`core.cli.guarded`).
"""

from __future__ import annotations


class RoomcapError(Exception):
    """An error whose message says what is wrong and what to do; shown to users without a traceback."""


class InputError(RoomcapError, ValueError):
    """A value given by the user (an argument, a file's content) is out of range or inconsistent."""
