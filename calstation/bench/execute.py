"""The main-process side of a bench: tasks run in a pool of worker processes, with a progress
bar, into a record store, and what a run's metadata says about the machine and the source.

Each finished task appends one JSON record to ``records.jsonl``; ``resume`` skips tasks already
recorded.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import subprocess
import time
from collections.abc import Callable, Iterator, Sequence
from multiprocessing.pool import Pool
from pathlib import Path
from typing import TYPE_CHECKING, cast

from calstation.atomic import write_atomic
from calstation.bench.records import BenchRecord
from calstation.bench.tasks import RunMeta, Task
from calstation.bench.worker import _init_worker, run_task

if TYPE_CHECKING:
    from rich.console import Console
    from rich.progress import Progress as RichProgress, TaskID


def _thread_env(threads: int) -> dict[str, str]:
    return {
        name: str(threads)
        for name in (
            "OMP_NUM_THREADS",
            "OPENBLAS_NUM_THREADS",
            "MKL_NUM_THREADS",
            "NUMEXPR_NUM_THREADS",
        )
    }


class RecordStore:
    """``records.jsonl`` in the output folder: one JSON record per finished task, appended and
    flushed at once so an interrupted run keeps what it finished."""

    def __init__(self, path: Path, resume: bool) -> None:
        self.path = path
        self.records: dict[str, BenchRecord] = {}
        if resume and path.is_file():
            for line in path.read_text().splitlines():
                if line.strip():
                    try:
                        # cast: json.loads is untyped; the file holds this store's records
                        rec = cast("BenchRecord", json.loads(line))
                    except ValueError:
                        continue  # a line cut short by a kill
                    self.records[rec["id"]] = rec
            # rewritten without any torn line, whole or not at all: a kill meanwhile keeps
            # every record finished before
            write_atomic(path, "".join(json.dumps(r) + "\n" for r in self.records.values()),
                         "records")
        else:
            write_atomic(path, "", "records", make_parents=True)

    def add(self, record: BenchRecord) -> None:
        """Keep ``record`` and append it to the file."""
        self.records[record["id"]] = record
        with self.path.open("a") as fh:
            fh.write(json.dumps(record) + "\n")

    def of_kind(self, kind: str) -> list[BenchRecord]:
        """Every record of ``kind``."""
        return [r for r in self.records.values() if r["kind"] == kind]


ProgressFactory = Callable[[str, int], "Progress"]


class Progress:
    """A rich progress bar on a terminal; a log line every 20 s (and at the end) otherwise."""

    def __init__(self, console: Console, description: str, total: int) -> None:
        self.console = console
        self.description = description
        self.total = total
        self.done = 0
        self.failed = 0
        self.t0 = time.monotonic()
        self.last_log = self.t0
        self._bar: RichProgress | None = None
        self._task: TaskID | None = None

    def __enter__(self) -> Progress:
        if self.console.is_terminal:
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress as RichProgress,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )

            self._bar = RichProgress(
                TextColumn("[bold]{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[failed]} failed"),
                TimeElapsedColumn(),
                TimeRemainingColumn(),
                console=self.console,
            )
            self._bar.__enter__()
            self._task = self._bar.add_task(self.description, total=self.total, failed=0)
        else:
            self.console.print(f"{self.description}: {self.total} tasks")
        return self

    def advance(self, ok: bool) -> None:
        """One task finished (``ok`` False if it failed)."""
        self.done += 1
        self.failed += 0 if ok else 1
        if self._bar is not None and self._task is not None:
            self._bar.update(self._task, advance=1, failed=self.failed)
            return
        now = time.monotonic()
        if now - self.last_log >= 20.0 or self.done == self.total:
            self.last_log = now
            elapsed = now - self.t0
            eta = elapsed / self.done * (self.total - self.done) if self.done else float("nan")
            self.console.print(
                f"{self.description}: {self.done}/{self.total} done, {self.failed} failed, "
                f"{elapsed:.0f} s elapsed, ~{eta:.0f} s left"
            )

    def __exit__(self, *exc: object) -> None:
        if self._bar is not None:
            self._bar.__exit__(None, None, None)


class Executor:
    """Runs tasks in ``workers`` spawned processes (or in this process when ``workers`` is 1)."""

    def __init__(self, recipe: Path, workers: int) -> None:
        self.recipe = recipe
        self.workers = max(1, workers)
        self._pool: Pool | None = None

    def __enter__(self) -> Executor:
        if self.workers > 1:
            threads = max(1, (os.cpu_count() or 1) // self.workers)
            saved = {k: os.environ.get(k) for k in _thread_env(threads)}
            os.environ.update(_thread_env(threads))  # inherited by the spawned workers
            try:
                ctx = multiprocessing.get_context("spawn")
                self._pool = ctx.Pool(
                    self.workers, initializer=_init_worker, initargs=(str(self.recipe),)
                )
            finally:
                for k, v in saved.items():
                    if v is None:
                        os.environ.pop(k, None)
                    else:
                        os.environ[k] = v
        else:
            _init_worker(str(self.recipe))
        return self

    def map(self, tasks: Sequence[Task]) -> Iterator[BenchRecord]:
        """Results as they finish (any order)."""
        if self._pool is None:
            for t in tasks:
                yield run_task(t)
        else:
            yield from self._pool.imap_unordered(run_task, tasks, chunksize=1)

    def __exit__(self, *exc: object) -> None:
        if self._pool is not None:
            if exc[0] is None:
                self._pool.close()
            else:
                self._pool.terminate()
            self._pool.join()


def _run_phase(
    executor: Executor,
    store: RecordStore,
    tasks: Sequence[Task],
    description: str,
    console: Console,
    deadline: float | None = None,
) -> int:
    """Run the tasks not yet recorded; returns how many ran. Raises :class:`DeadlineReached`
    when ``deadline`` (Unix time) passes before they are all done."""
    todo = list({t.id: t for t in tasks if t.id not in store.records}.values())
    if not todo:
        return 0
    if deadline is not None and time.time() > deadline:
        raise DeadlineReached
    with Progress(console, description, len(todo)) as bar:
        for rec in executor.map(todo):
            store.add(rec)
            bar.advance(rec.get("status") == "ok")
            if deadline is not None and time.time() > deadline and bar.done < len(todo):
                raise DeadlineReached
    return len(todo)


def git_commit(cwd: Path | None = None) -> str:
    """``git rev-parse HEAD`` of the source tree (with ``+dirty`` if calstation's sources have
    uncommitted changes), ``$CALSTATION_SOURCE_COMMIT`` when the code runs from an export of a
    commit, or ``"unknown"``."""
    pinned = os.environ.get("CALSTATION_SOURCE_COMMIT")
    if pinned:  # running from an exported tree (git archive) of that commit
        return f"{pinned} (clean export)"
    root = cwd or Path(__file__).resolve().parents[2]
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", "--",
             "calstation", "plugins", "recipes"],
            cwd=root,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        return head + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


class DeadlineReached(Exception):
    """Raised by :func:`_run_phase` when the deadline passes in the middle of a phase (caught by
    :func:`calstation.bench.runner.run_bench`)."""


def _load() -> float | None:
    """The 1-minute load average (None where the system does not report one)."""
    try:
        return os.getloadavg()[0]
    except OSError:
        return None


def _previous_meta(out: Path) -> RunMeta | None:
    path = out / "run.json"
    try:
        # cast: json.loads is untyped; run.json is a run's metadata
        return cast("RunMeta", dict(json.loads(path.read_text()))) if path.is_file() else None
    except ValueError:
        return None
