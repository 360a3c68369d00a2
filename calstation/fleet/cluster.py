"""The Dask cluster a campaign runs on: a ``LocalCluster`` of worker processes on this machine
(``--workers N``), or an existing cluster's scheduler (``--scheduler tcp://host:8786``).

A local cluster listens on 127.0.0.1 only and has no dashboard; its workers are processes with
one thread each (the engine is numpy and SciPy: one process per core) and inherit this process's
environment (``PYTHONPATH``, ``CALSTATION_HOME``, the ``AWS_*`` credentials). Workers of an
existing cluster need calstation (and its plugins) installed, and must reach the recordings:
the paths stored in the database, or their shared copies' fsspec URLs.

:func:`completed` hands back the results as they arrive and gives up, with a clear error, when
none arrived for :data:`STALL_TIMEOUT_S` (a cluster without workers, workers that hang).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterable, Iterator, Mapping, Sized
from contextlib import contextmanager
from types import ModuleType
from typing import Protocol, TypeVar, cast

from calstation.errors import FleetError

STALL_TIMEOUT_S = 900.0
"""Longest wait for the next result (s) before a campaign gives up
(``CALSTATION_CAMPAIGN_STALL_S`` overrides)."""

CONNECT_TIMEOUT_S = 30.0
"""Longest wait for an existing cluster's scheduler to answer (s)."""


T = TypeVar("T")
R = TypeVar("R")


class DaskFuture(Protocol):
    """What :func:`completed` uses of a ``distributed.Future``."""

    def exception(self) -> BaseException | None: ...

    def result(self) -> object: ...

    def release(self) -> None: ...


class DaskClient(Protocol):
    """What a campaign uses of a ``distributed.Client``."""

    def submit(self, fn: Callable[[T], R], task: T, *, key: str, pure: bool) -> DaskFuture: ...

    def scheduler_info(self, *, n_workers: int) -> Mapping[str, object]: ...

    def cancel(self, futures: list[DaskFuture]) -> None: ...

    def close(self) -> None: ...


def stall_timeout_s() -> float:
    """``$CALSTATION_CAMPAIGN_STALL_S``, else :data:`STALL_TIMEOUT_S`."""
    env = os.environ.get("CALSTATION_CAMPAIGN_STALL_S")
    try:
        return float(env) if env else STALL_TIMEOUT_S
    except ValueError:
        raise FleetError(f"CALSTATION_CAMPAIGN_STALL_S={env!r}: expected seconds") from None


@contextmanager
def dask_client(workers: int | None = None, scheduler: str | None = None
                ) -> Iterator[DaskClient]:
    """A ``distributed.Client`` on a new local cluster of ``workers`` processes (default: one
    per core; their standard output is this process's standard error), or on the cluster whose
    scheduler is at ``scheduler``; closed (and the local cluster stopped) on leaving."""
    import distributed

    dist: ModuleType = distributed  # untyped: its attributes are not checked
    if scheduler is not None and workers is not None:
        raise FleetError("--scheduler and --workers: give one (--workers starts a local cluster)")
    if workers is not None and workers < 1:
        raise FleetError(f"--workers {workers}: expected 1 or more")
    if scheduler is not None:
        try:
            client = dist.Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError) as exc:
            raise FleetError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
        try:
            yield client
        finally:
            client.close()
        return
    from calstation.quiet import stdout_to_stderr

    n = workers or os.cpu_count() or 1
    # the worker processes inherit descriptor 1 as it is when they start: standard error, so
    # that what the engine's libraries print there (Open3D's C++ warnings) never lands in this
    # process's standard output (a --json)
    with stdout_to_stderr():
        cluster = dist.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                    host="127.0.0.1", dashboard_address=None,
                                    silence_logs=logging.ERROR)
    try:
        client = dist.Client(cluster)
        try:
            yield client
        finally:
            client.close()
    finally:
        cluster.close()


def worker_count(client: DaskClient) -> int:
    """How many workers the cluster has now."""
    workers = client.scheduler_info(n_workers=-1).get("workers", {})
    return len(workers) if isinstance(workers, Sized) else 0


def completed(
    client: DaskClient,
    fn: Callable[[T], R],
    tasks: Iterable[T],
    key: Callable[[T], str],
    stall_s: float | None = None,
) -> Iterator[tuple[T, R | None, BaseException | None]]:
    """Submit ``fn(task)`` for each task (Dask key ``key(task)``) and yield ``(task, result,
    None)`` or ``(task, None, error)`` as each finishes, in finishing order. Raises
    :class:`FleetError` when nothing finished for ``stall_s`` seconds (default
    :func:`stall_timeout_s`); the futures left are cancelled on any exit."""
    import distributed

    dist: ModuleType = distributed  # untyped: its attributes are not checked
    stall = stall_timeout_s() if stall_s is None else stall_s
    pending = {client.submit(fn, task, key=key(task), pure=False): task for task in tasks}
    try:
        while pending:
            try:
                done, _ = dist.wait(list(pending), timeout=stall, return_when="FIRST_COMPLETED")
            except TimeoutError:
                done = set()
            if not done:
                raise FleetError(
                    f"no result for {stall:g} s with {len(pending)} runs left "
                    f"({worker_count(client)} Dask workers): the cluster has no workers, or they "
                    "hang; the results stored so far are kept (run the command again to go on)"
                )
            for future in done:
                task = pending.pop(future)
                error = future.exception()
                # what fn returned, sent back by the worker (distributed's results are untyped)
                yield task, None if error is not None else cast(R, future.result()), error
                future.release()
    finally:
        if pending:
            client.cancel(list(pending))
