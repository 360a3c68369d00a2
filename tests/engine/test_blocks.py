"""Per-return passes a block at a time, on every core (calstation.engine.blocks): the blocks'
results in order, positions offset to the whole, and a process started by fork gets a pool of
its own."""

from __future__ import annotations

import multiprocessing
import threading

import numpy as np
import pytest

from calstation.engine import blocks


def test_the_blocks_come_back_in_order_and_cover_every_return_once(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(blocks, "BLOCK", 7)
    seen = blocks.by_blocks(lambda rows: (rows.start, rows.stop), 50)
    assert seen == [(i, min(i + 7, 50)) for i in range(0, 50, 7)]
    # no returns: one empty block, so that a pass gives its own empty results
    assert blocks.by_blocks(lambda rows: rows, 0) == [slice(0, 0)]


def test_positions_found_in_blocks_are_those_found_in_the_whole(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    values = np.random.default_rng(3).normal(size=10_001)
    whole = np.flatnonzero(values > 0.5)
    for block in (1, 13, 4096, 20_000):
        monkeypatch.setattr(blocks, "BLOCK", block)
        found = blocks.positions(lambda rows: np.flatnonzero(values[rows] > 0.5), values.size)
        np.testing.assert_array_equal(found, whole)
    assert blocks.positions(lambda rows: np.flatnonzero(values[rows] > 9), 0).size == 0


def test_the_blocks_run_side_by_side(monkeypatch: pytest.MonkeyPatch) -> None:
    """Two blocks wait for each other: they can only both finish if they run at once."""
    monkeypatch.setattr(blocks, "BLOCK", 1)
    if blocks.pool("blocks")._max_workers < 2:
        pytest.skip("this process may run on one core only")
    both = threading.Barrier(2, timeout=60)
    assert blocks.by_blocks(lambda rows: both.wait() >= 0, 2) == [True, True]


def _child(out: multiprocessing.Queue) -> None:  # type: ignore[type-arg]
    blocks.BLOCK = 3
    out.put(blocks.positions(lambda rows: np.arange(rows.stop - rows.start), 10).tolist())


def test_a_forked_process_gets_a_pool_of_its_own(monkeypatch: pytest.MonkeyPatch) -> None:
    """The parent's pool threads do not exist in a child started by fork: a pool it
    inherited would take the blocks and never run them."""
    monkeypatch.setattr(blocks, "BLOCK", 3)
    assert len(blocks.by_blocks(lambda rows: rows, 10)) == 4  # the parent's pool is up
    ctx = multiprocessing.get_context("fork")
    out = ctx.Queue()
    child = ctx.Process(target=_child, args=(out,))
    child.start()
    try:
        assert out.get(timeout=60) == list(range(10))
    finally:
        child.join(timeout=30)
        if child.is_alive():
            child.kill()
