"""Per-track work over contiguous parts of a batch, run by threads at once (:class:`Split`).

The particle filter's hot loops treat every track, and every row of its samples, on its own: the GRU's
products and gates (rows), the weights, resampling and refinement (tracks). Each of those kernels releases
the GIL (numba ``nogil``, numpy's BLAS), so a batch cut into parts runs on as many cores as there are
parts, and gives the same bits as the whole batch: every part computes the same operations on the same
numbers, and the random draws are made for the whole batch before it is cut. BLAS then runs one thread
per part (:meth:`Split.blas_single`): its own threads would compete with the parts for the cores.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import AbstractContextManager, nullcontext
from typing import TypeVar

T = TypeVar("T")

MAX_AUTO_THREADS = 4  # a frame's batch (16 tracks x 300 samples) gains little from more parts


def available_cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def auto_threads(threads: int) -> int:
    """``threads`` itself, or for 0 the available cores up to :data:`MAX_AUTO_THREADS` and up to
    ``OMP_NUM_THREADS`` when that is set (``reprocess`` sets it to each worker's share of the cores when
    it runs sessions at once)."""
    if threads < 0:
        raise ValueError(f"threads must be >= 0 (0 = one per core), got {threads}")
    if threads:
        return threads
    cap = MAX_AUTO_THREADS
    omp = os.environ.get("OMP_NUM_THREADS", "").strip()
    if omp.isdigit() and int(omp) > 0:
        cap = min(cap, int(omp))
    return min(available_cores(), cap)


class Split:
    """Cuts ``n`` items (tracks, or rows of samples) into at most ``threads`` contiguous parts and runs a
    function on each part at once, the first part in the calling thread, the others in a pool's.

    >>> s = Split(2)
    >>> s.parts(5)
    [(0, 3), (3, 5)]
    >>> s.map(lambda lo, hi: list(range(lo, hi)), 5)
    [[0, 1, 2], [3, 4]]
    >>> Split(1).parts(5)
    [(0, 5)]
    """

    def __init__(self, threads: int = 1):
        self.threads = auto_threads(threads)
        # the pool's threads end when the split (its tracker) is dropped
        self._pool = ThreadPoolExecutor(self.threads - 1, "roomcap-split") if self.threads > 1 else None
        self._blas = None  # threadpoolctl's controller, found on first use

    def parts(self, n: int) -> list[tuple[int, int]]:
        """Contiguous (lo, hi) ranges of nearly equal size covering ``range(n)``, in order; the first (the
        calling thread's, which starts first) the larger where they cannot be equal."""
        k = max(1, min(self.threads, n))
        cuts = [-(-n * i // k) for i in range(k + 1)]
        return [(cuts[i], cuts[i + 1]) for i in range(k)]

    def map(self, fn: Callable[[int, int], T], n: int) -> list[T]:
        """``[fn(lo, hi) for (lo, hi) in parts(n)]``, the parts computed at once."""
        parts = self.parts(n)
        if self._pool is None or len(parts) == 1:
            return [fn(lo, hi) for lo, hi in parts]
        futures = [self._pool.submit(fn, lo, hi) for lo, hi in parts[1:]]
        first = fn(*parts[0])
        return [first] + [f.result() for f in futures]

    def blas_single(self) -> AbstractContextManager:
        """A context in which BLAS runs one thread (when this split runs more than one part at once), so that
        the parts' matrix products do not start threads of their own (about 7 us a context)."""
        if self._pool is None:
            return nullcontext()
        if self._blas is None:
            from threadpoolctl import ThreadpoolController

            self._blas = ThreadpoolController()
        return self._blas.limit(limits=1, user_api="blas")
