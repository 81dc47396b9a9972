"""One progress protocol: library functions report through a callback, command-line tools render it.

A library function that takes long accepts ``progress: Progress | None`` and calls
``progress(task, done, total)`` (``total`` None when unknown); it never prints and never makes a bar.
A command passes a :class:`Bars`, which keeps one tqdm bar per task on stderr and, while it is open,
sends log lines above the bars instead of through them (``tqdm.contrib.logging``).
"""

from __future__ import annotations

import sys
from contextlib import ExitStack
from typing import Any, Protocol


class Progress(Protocol):
    def __call__(self, task: str, done: int, total: int | None, /) -> None: ...


class Bars:
    """Renders :class:`Progress` calls as tqdm bars, one per task; use as a context manager."""

    def __init__(self, unit: str = "it", disable: bool | None = None) -> None:
        self.unit, self.disable = unit, disable
        self.bars: dict[str, Any] = {}
        self._stack = ExitStack()

    def __enter__(self) -> Bars:
        from tqdm.contrib.logging import logging_redirect_tqdm

        self._stack.enter_context(logging_redirect_tqdm())
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
        self._stack.close()

    def __call__(self, task: str, done: int, total: int | None, /) -> None:
        from tqdm import tqdm

        bar = self.bars.get(task)
        if bar is None:
            bar = self.bars[task] = tqdm(
                total=total, desc=task, unit=self.unit, leave=True, file=sys.stderr, disable=self.disable,
                position=len(self.bars),
            )  # fmt: skip
        bar.total = total
        bar.n = done
        bar.refresh()
        if total is not None and done >= total:
            bar.close()

    def close(self) -> None:
        for bar in self.bars.values():
            bar.close()
