"""Creating, starting and resuming runs: the entry points the console and the web station call.

:func:`create_run` stores a ``running`` run of a recipe and makes its folder; :func:`start_run`
creates one and executes it; :func:`resume_run` continues a stored run at its first unfinished
step, with the recipe stored with it, refusing one that another live process executes
(:func:`resumable_run`). The execution itself is :class:`calstation.station.machine.Station`.

Both hold the station's lock (:mod:`calstation.station.lock`) from before the run is created
until its drivers are closed: a second start on the same station, from any front end, is
refused naming who holds it.
"""

from __future__ import annotations

import os
import signal
import socket
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType

from sqlalchemy import select
from sqlalchemy.orm import Session

from calstation.errors import AbortRun, StationError
from calstation.plugins.recipe_checks import check_plugins
from calstation.recipes import LoadedRecipe, parse_recipe
from calstation.station.lock import (
    Holder,
    StationHold,
    process_alive,
    take_station,
    taken_over_note,
    terminal_front_end,
)
from calstation.station.machine import Station
from calstation.station.operator import Operator
from calstation.storage.db import (
    Database,
    Run,
    RunStatus,
    Step,
    StepStatus,
    calstation_home,
    get_or_create_station,
    journal,
)
from calstation.storage.db.fields import operator_name, unit_serial
from calstation.storage.report import find_run


def data_dir_default() -> Path:
    """Where run folders go: ``$CALSTATION_HOME`` (see
    :func:`calstation.storage.db.calstation_home`)."""
    return calstation_home()


def start_run(
    loaded: LoadedRecipe,
    db: Database,
    ui: Operator,
    *,
    operator: str,
    data_dir: Path | None = None,
    serial: str | None = None,
    front_end: str | None = None,
) -> tuple[int, str]:
    """Create a run of ``loaded`` and execute it; returns (run id, final status).

    :func:`prepare_run`, then :meth:`PreparedRun.execute` in this thread (``front_end``
    defaults to ``calstation run`` in this terminal).
    """
    prepared = prepare_run(loaded, db, ui, operator=operator, data_dir=data_dir, serial=serial,
                           front_end=front_end or terminal_front_end("calstation run"))
    return prepared.run_id, prepared.execute()


def prepare_run(
    loaded: LoadedRecipe,
    db: Database,
    ui: Operator,
    *,
    operator: str,
    front_end: str,
    data_dir: Path | None = None,
    serial: str | None = None,
) -> PreparedRun:
    """Everything before a new run of ``loaded`` executes: the recipe validated against the
    installed plugins, the station's lock taken for ``operator`` through ``front_end``
    (:class:`~calstation.station.lock.StationBusy` when another run holds it), the run created
    (its folder ``<data_dir>/runs/<database identity>/<run id>/``, :func:`new_run_folder`) and
    named in the lock. ``serial`` is the unit's serial number when the operator gives it (else
    the lidar's, read at preflight). The operator's name and the serial are checked as every
    front end checks them (:mod:`calstation.storage.db.fields`). Execute it with
    :meth:`PreparedRun.execute`, in any thread (the web station's runs have one each), or give
    the station back with :meth:`PreparedRun.release`."""
    operator, serial = operator_name(operator), unit_serial(serial)
    check_plugins(loaded)
    hold = hold_station(db, loaded.recipe.station.id, Holder.here(operator, front_end), ui)
    try:
        run_id = create_run(loaded, db, operator=operator, unattended=ui.unattended,
                            data_dir=data_dir, serial=serial)
        hold.attach(run_id)
    except BaseException:
        hold.release()
        raise
    return PreparedRun(db, run_id, loaded, ui, hold, run_folder(db, run_id), resumed=False)


class PreparedRun:
    """A run ready to execute (:func:`prepare_run`, :func:`prepare_resume`): the station is
    held for it. :meth:`execute` runs it once and gives the station back, however it ends;
    :meth:`release` gives it back without running it."""

    def __init__(self, db: Database, run_id: int, loaded: LoadedRecipe, ui: Operator,
                 hold: StationHold, run_dir: Path, *, resumed: bool) -> None:
        self.db, self.run_id, self.loaded, self.ui = db, run_id, loaded, ui
        self.hold, self.run_dir, self.resumed = hold, run_dir, resumed

    def execute(self) -> str:
        """Run it (:class:`~calstation.station.machine.Station`); the final status. The
        database's faults during the run go to the run folder's ``database.log`` and its waits
        to the run's operator, in this run's thread only."""
        try:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            verb = "resuming run" if self.resumed else "run"
            recipe = "" if self.resumed else (f" of recipe {self.loaded.recipe.name} on station "
                                              f"{self.loaded.recipe.station.id}")
            self.ui.info(f"{verb} {self.run_id}{recipe}; recordings in {self.run_dir}")
            with self.db.run_scope(self.run_dir / "database.log", self.ui.warn), \
                    _signals_abort():
                return Station(self.db, self.run_id, self.loaded, self.ui).run()
        finally:
            self.hold.release()

    def release(self) -> None:
        """Give the station back without running (idempotent)."""
        self.hold.release()


def hold_station(db: Database, station: str, holder: Holder, ui: Operator,
                 force: bool = False) -> StationHold:
    """:func:`~calstation.station.lock.take_station`, telling ``ui`` when a lock left by a
    process that ended was cleared."""
    hold = take_station(db, station, holder, force=force)
    if hold.taken_over is not None:
        ui.warn(taken_over_note(hold.taken_over))
    return hold


def run_folder(db: Database, run_id: int) -> Path:
    """The folder of run ``run_id``, as its row records it (:class:`StationError` when there is
    no such run)."""
    with db.session("reading the run", read_only=True) as s:
        run = s.get(Run, run_id)
        if run is None:
            raise StationError(f"no run {run_id} in the database")
        return Path(run.data_dir)


def create_run(
    loaded: LoadedRecipe,
    db: Database,
    *,
    operator: str,
    unattended: bool,
    data_dir: Path | None = None,
    serial: str | None = None,
) -> int:
    """Create (and commit) a ``running`` run of ``loaded`` and its folder; returns its id.

    ``serial`` is the unit's serial number when the operator gives it. The operator's name and
    the serial are checked as every front end checks them
    (:mod:`calstation.storage.db.fields`: :class:`~calstation.errors.TextError`).

    The recipe is validated against the installed plugins first. Execute it with
    ``Station(db, run_id, loaded, ui).run()``.
    """
    operator, serial = operator_name(operator), unit_serial(serial)
    check_plugins(loaded)
    base = (data_dir or data_dir_default()).expanduser().resolve()
    station_id = get_or_create_station(db, loaded.recipe.station.id)
    identity = db.identity
    with db.session("creating the run") as s:
        run = Run(
            station_id=station_id,
            recipe_name=loaded.recipe.name,
            recipe_path=str(loaded.path.resolve()) if loaded.path else None,
            recipe_text=loaded.text,
            recipe_sha256=loaded.sha256,
            operator=operator,
            unit_serial=serial,
            unattended=unattended,
            data_dir="",
            status=RunStatus.RUNNING,
        )
        s.add(run)
        s.flush()
        run.data_dir = str(new_run_folder(base, identity, run.id))
        run_id = run.id
    return run_id


def new_run_folder(base: Path, identity: str, run_id: int) -> Path:
    """A folder of its own for run ``run_id`` of the database ``identity``, made now:
    ``<base>/runs/<identity>/<run id>/``, or ``<run id>-2``, ``-3``... should that one hold files
    already (a copy of the database that went on numbering runs in the same place). Never a
    folder another run has written to; the run's row records which it is."""
    parent = base / "runs" / identity
    try:
        parent.mkdir(parents=True, exist_ok=True)
        for n in range(1, 1000):
            folder = parent / (str(run_id) if n == 1 else f"{run_id}-{n}")
            try:
                folder.mkdir()
                return folder
            except FileExistsError:
                if folder.is_dir() and not any(folder.iterdir()):
                    return folder  # made for this run id by a creation that was rolled back
    except OSError as exc:
        raise StationError(
            f"cannot make the folder of run {run_id} in {parent}: {exc.strerror or exc}"
        ) from None
    raise StationError(f"{parent} holds 999 folders named for run {run_id}: clear it up")


def resumable_run(session: Session, run_id: int, force: bool) -> Run:
    """Run ``run_id`` from ``session`` if it may be resumed: :class:`StationError` when there
    is none, it already passed, or another live process executes it (unless ``force``)."""
    run = find_run(session, run_id)
    if run is None:
        raise StationError(f"no run {run_id} in the database")
    if run.status == RunStatus.PASSED:
        raise StationError(f"run {run_id} already passed; nothing to resume")
    _check_not_running_elsewhere(run, force)
    return run


def _check_not_running_elsewhere(run: Run, force: bool) -> None:
    """Refuse to resume a run another live process is executing (two processes, one motor)."""
    if run.status != RunStatus.RUNNING or force or run.pid is None:
        return
    if run.host == socket.gethostname():
        if run.pid != os.getpid() and process_alive(run.pid):
            raise StationError(
                f"run {run.id} is being executed by process {run.pid} on this host; stop it "
                "first (or force the resumption if that process id now belongs to something "
                "else)", option="force"
            )
        return
    raise StationError(
        f"run {run.id} was last executed on host {run.host!r} (process {run.pid}); resume it "
        "there, or force the resumption if that process is gone", option="force"
    )


def resume_run(run_id: int, db: Database, ui: Operator, *, force: bool = False,
               hold: StationHold | None = None, front_end: str | None = None) -> str:
    """Continue run ``run_id`` at its first unfinished step; returns the final status.

    :func:`prepare_resume` (``front_end`` defaults to ``calstation resume`` in this terminal;
    ``hold``: the caller holds the station already), then :meth:`PreparedRun.execute`.
    """
    prepared = prepare_resume(run_id, db, ui, force=force, hold=hold,
                              front_end=front_end or terminal_front_end("calstation resume"))
    return prepared.execute()


def prepare_resume(run_id: int, db: Database, ui: Operator, *, front_end: str,
                   force: bool = False, hold: StationHold | None = None) -> PreparedRun:
    """Everything before a stored run continues at its first unfinished step.

    The recipe is the one stored with the run (not the file, which may have changed since).
    Recordings of finished steps are re-used after their sha256 is checked. A run still being
    executed by a live process is refused unless ``force`` (:func:`resumable_run`). The
    station's lock is taken for the run's operator through ``front_end`` unless the caller
    holds it already (``hold``, released with the run either way).
    """
    try:
        for note in journal.recover(db):  # results journalled by an earlier process, first
            ui.info(note)
        with db.session() as s:
            run = resumable_run(s, run_id, force)
            text, path, operator = run.recipe_text, run.recipe_path, run.operator
            run_dir = Path(run.data_dir)
        source = f"recipe of run {run_id}"
        base_dir = Path(path).parent if path else None
        loaded = LoadedRecipe(parse_recipe(text, source, base_dir), Path(path) if path else None,
                              text)
        check_plugins(loaded)
        if hold is None:
            hold = hold_station(db, loaded.recipe.station.id, Holder.here(operator, front_end),
                                ui, force=force)
        hold.attach(run_id)
    except BaseException:
        if hold is not None:
            hold.release()
        raise
    return PreparedRun(db, run_id, loaded, ui, hold, run_dir, resumed=True)


@contextmanager
def _signals_abort() -> Iterator[None]:
    """SIGTERM aborts the run like Ctrl-C (so the motor is stopped and the run recorded)."""

    def handler(signum: int, frame: FrameType | None) -> None:
        raise AbortRun(f"aborted by signal {signal.Signals(signum).name}")

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def wait_for_step(
    db: Database, run_id: int, step: str, timeout_s: float = 60.0,
    status: StepStatus = StepStatus.RUNNING,
) -> bool:
    """Poll until ``step`` of ``run_id`` has an attempt with ``status`` (for tests and tools)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with db.session("reading the steps", read_only=True) as s:
            found = s.scalars(
                select(Step.id).where(
                    Step.run_id == run_id, Step.name == step, Step.status == status
                )
            ).first()
        if found is not None:
            return True
        time.sleep(0.05)
    return False
