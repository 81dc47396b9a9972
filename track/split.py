"""Per-track work over contiguous parts of a batch, run by threads at once (:class:`Split`).

The particle filter's hot loops treat every track, and every row of its samples, on its own: the GRU's
products and gates (rows), the weights, resampling and refinement (tracks). Each of those kernels releases
the GIL (numba ``nogil``, numpy's BLAS), so a batch cut into parts runs on as many cores as there are
parts, and gives the same bits as the whole batch: every part computes the same operations on the same
numbers, and the random draws are made for the whole batch before it is cut.

Matrix products are the exception: a BLAS kernel's summation order for one row depends on the shape of the
product it is part of (OpenBLAS's Haswell and Zen kernels treat a product's last rows with other kernels),
so parts whose row counts follow the number of threads give other bits for other thread counts. The
products therefore run over a fixed partition of the batch (:func:`blocked_matmul`: blocks of
:data:`BLAS_BLOCK_ROWS` rows from the batch's first row, whatever the number of threads), threads take whole
blocks (``Split.map(..., block=BLAS_BLOCK_ROWS)``), and BLAS runs one thread inside every block
(:func:`blas_single`, for any number of parts: its own threads split a product by shape as well). This is
the usual way to make a parallel reduction reproducible: the partition is fixed, only who computes which
block changes. It costs about nothing at 256 rows (a 4800-row batch: 2.68 ms of products in one call,
2.68 ms in blocks), where a compiled kernel with a fixed loop order would cost three times as much.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import AbstractContextManager
from typing import TypeVar

import numpy as np

T = TypeVar("T")

MAX_AUTO_THREADS = 4  # a frame's batch (16 tracks x 300 samples) gains little from more parts
BLAS_BLOCK_ROWS = 256  # rows of one fixed block of a batch's matrix products (:func:`blocked_matmul`)

_controller = None  # threadpoolctl's controller, found on first use


def blas_single() -> AbstractContextManager:
    """A context in which BLAS runs one thread (about 7 us a context): a product's bits then depend on
    its shape alone, and the parts' products start no threads of their own."""
    global _controller
    if _controller is None:
        from threadpoolctl import ThreadpoolController

        _controller = ThreadpoolController()
    return _controller.limit(limits=1, user_api="blas")


def blocked_matmul(a: np.ndarray, w: np.ndarray, block: int = BLAS_BLOCK_ROWS) -> np.ndarray:
    """``a @ w`` (a: (n, k) rows of a batch starting at a multiple of ``block``) computed block by block
    of ``block`` rows: each row's bits depend on its place in the fixed partition of the whole batch, not
    on how the batch was cut into parts (call it with BLAS at one thread, :func:`blas_single`)."""
    n = len(a)
    if n <= block:
        return a @ w
    out = np.empty((n, w.shape[1]), np.result_type(a, w))
    for lo in range(0, n, block):
        np.matmul(a[lo : lo + block], w, out=out[lo : lo + block])
    return out


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
    function on each part at once, the first part in the calling thread, the others in a pool's. With
    ``block``, the parts are made of whole blocks of ``block`` items (a fixed partition of ``range(n)``).

    >>> s = Split(2)
    >>> s.parts(5)
    [(0, 3), (3, 5)]
    >>> s.map(lambda lo, hi: list(range(lo, hi)), 5)
    [[0, 1, 2], [3, 4]]
    >>> Split(1).parts(5)
    [(0, 5)]
    >>> Split(3).parts(10, block=4)
    [(0, 4), (4, 8), (8, 10)]
    >>> Split(2).parts(10, block=4)
    [(0, 8), (8, 10)]
    """

    def __init__(self, threads: int = 1):
        self.threads = auto_threads(threads)
        # the pool's threads end when the split (its tracker) is dropped
        self._pool = ThreadPoolExecutor(self.threads - 1, "roomcap-split") if self.threads > 1 else None

    def parts(self, n: int, block: int = 1) -> list[tuple[int, int]]:
        """Contiguous (lo, hi) ranges covering ``range(n)`` in order, made of nearly equal numbers of whole
        blocks of ``block`` items (the last block the rest); the first part (the calling thread's, which
        starts first) the larger where they cannot be equal."""
        if block < 1:
            raise ValueError(f"block must be >= 1, got {block}")
        nb = -(-n // block)  # blocks
        k = max(1, min(self.threads, nb))
        cuts = [min(n, block * -(-nb * i // k)) for i in range(k + 1)]
        return [(cuts[i], cuts[i + 1]) for i in range(k)]

    def map(self, fn: Callable[[int, int], T], n: int, block: int = 1) -> list[T]:
        """``[fn(lo, hi) for (lo, hi) in parts(n, block)]``, the parts computed at once."""
        parts = self.parts(n, block)
        if self._pool is None or len(parts) == 1:
            return [fn(lo, hi) for lo, hi in parts]
        futures = [self._pool.submit(fn, lo, hi) for lo, hi in parts[1:]]
        first = fn(*parts[0])
        return [first] + [f.result() for f in futures]

    def blas_single(self) -> AbstractContextManager:
        """A context in which BLAS runs one thread (:func:`blas_single`), for any number of parts: the
        products' bits must not depend on BLAS's own threads either."""
        return blas_single()
