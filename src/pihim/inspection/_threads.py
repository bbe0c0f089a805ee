"""Ordered maps on threads for the compiled fits (private).

The pose alignments and the canting refinements are many independent calls
of compiled kernels that release the GIL (:mod:`pihim.inspection._kernels`),
so two cores run two of them at once. Each call computes what it would on
one thread: the results, taken in order, are the same for any number of
threads.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterable, Iterator
from typing import Any


@contextlib.contextmanager
def ordered_map(limit: int = 4) -> Iterator[Callable[[Callable[[Any], Any], Iterable[Any]], list[Any]]]:
    """``run(fn, items) -> [fn(item) ...]`` in order, on as many threads as numba may use.

    ``NUMBA_NUM_THREADS`` (one per CPU, or what the caller set: 1 in a
    campaign's workers), at most ``limit``; with one, in this thread.
    """
    import numba

    threads = max(1, min(int(limit), int(numba.config.NUMBA_NUM_THREADS)))
    if threads < 2:
        yield lambda fn, items: [fn(item) for item in items]
        return
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(threads) as pool:
        yield lambda fn, items: list(pool.map(fn, items))
