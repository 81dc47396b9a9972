"""File IO with schema tags and atomic writes: defined in :mod:`core.fileio`, below every stage.

This module keeps the name the stages and users import (``from capture.fileio import FormatError``).
"""

from core.fileio import *  # noqa: F403
