"""Per-return passes over a whole scan, a block of returns at a time, on every core.

A pass over a scan's millions of returns (turn each into a frame, test it against a region or
a model) is a chain of NumPy operations, each of which reads and writes arrays of the scan's
length. Taken a block at a time, the temporaries of the chain stay in the processor's cache,
and the blocks run on the station computer's cores side by side (NumPy releases the GIL in
its loops): on the 2-core reference machine a pass takes a half to a third of its whole-array
time, and its temporaries are a block's, not the scan's (docs/performance.md).

The blocks' results are exactly the whole-array pass's: each return's result depends only on
that return. A pass that needs all the returns at once (a median, a random subset) makes it
after the blocks, from what they return.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

BLOCK = 1 << 16
"""Returns per block: a block's temporaries (tens of arrays of this length) stay within a
core's cache; from 2¹⁵ to 2¹⁸ the passes of the cube stage took within 10 % of each other."""

T = TypeVar("T")

_pools: dict[tuple[int, str], ThreadPoolExecutor] = {}


def pool(name: str, workers: int | None = None) -> ThreadPoolExecutor:
    """This process's thread pool ``name``, of ``workers`` threads (default: one per core it
    may run on). A process started by fork gets its own: its parent's threads did not come
    with it, and a pool it inherited would take work and never run it. A task on one pool may
    wait for another pool's tasks, never for its own pool's (the blocks' pool is that of
    :func:`by_blocks`; :func:`calstation.engine.neighbours.pair` has its own)."""
    key = (os.getpid(), name)
    found = _pools.get(key)
    if found is None:
        if workers is None:
            cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
            workers = max(1, cores or os.cpu_count() or 1)
        found = ThreadPoolExecutor(max_workers=workers, thread_name_prefix=f"calstation-{name}")
        _pools[key] = found
    return found


def by_blocks(fn: Callable[[slice], T], n: int) -> list[T]:
    """``[fn(s) for s in the slices of range(n), BLOCK by BLOCK]``, in order, the blocks on
    every core; one empty block when n is 0, so that a pass over no returns gives its own
    empty results. ``fn`` must not depend on the other blocks, nor call this function."""
    slices = [slice(i, min(i + BLOCK, n)) for i in range(0, max(n, 1), BLOCK)]
    if len(slices) <= 1:
        return [fn(s) for s in slices]
    futures = [pool("blocks").submit(fn, s) for s in slices]
    return [f.result() for f in futures]


def positions(fn: Callable[[slice], NDArray[np.intp]], n: int) -> NDArray[np.intp]:
    """The positions (in range(n)) ``fn`` finds block by block, ``fn(s)`` returning them
    within its block ``s`` (0 at ``s.start``), in increasing order."""
    parts = by_blocks(lambda s: fn(s) + s.start, n)
    out: NDArray[np.intp] = np.concatenate(parts).astype(np.intp, copy=False)
    return out


def stacked(parts: Sequence[tuple[NDArray[Any], ...]]) -> tuple[NDArray[Any], ...]:
    """The blocks' tuples of arrays joined, array by array (``parts`` from
    :func:`by_blocks`)."""
    return tuple(np.concatenate(column) for column in zip(*parts, strict=True))
