"""One run per station, whatever starts it: the station lock.

A station is one turntable. Two processes driving it at once — a web station and a terminal,
two terminals, two web stations over one database — would fight over the motor, so every front
end takes the station's lock before it creates (or resumes) a run, and gives it back once the
run's drivers are closed: :func:`take_station` over the ``station_lock`` table (one row per
held station, :class:`~calstation.storage.db.StationLock`), in one transaction that holds the
database's write lock (SQLite) or the row's lock (PostgreSQL), so that of two starts exactly one
wins. The other is refused at once with :class:`StationBusy`, which names who holds the station,
from where and since when.

A lock survives its holder's crash as a row, and is *detected* as stale rather than waited on:

- a holder on this host is gone when its process is (its id is not alive, or now belongs to a
  process started at another time: the kernel's start time is stored with the lock);
- a holder on another host renews ``heartbeat_at`` every :data:`HEARTBEAT_S` seconds while it
  lives; one silent for :data:`STALE_AFTER_S` is gone.

A stale lock is taken over, and the taker is told whose it was.
"""

from __future__ import annotations

import datetime as dt
import os
import socket
import threading
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypedDict

from sqlalchemy import delete, select, update
from sqlalchemy.exc import IntegrityError, SQLAlchemyError

from calstation.errors import DatabaseError, StationError
from calstation.storage.db import Database, Run, StationLock, get_or_create_station, utcnow
from calstation.storage.db.journal import process_alive as process_alive

HEARTBEAT_S = 15.0
"""How often a holder renews its lock's ``heartbeat_at``."""

STALE_AFTER_S = 90.0
"""A lock held from another host whose heartbeat is older than this is stale (six missed
heartbeats: a holder busy in a long transaction is not taken for dead)."""

_HELD: set[str] = set()
"""Tokens of the locks this process holds (a lock of this process's id with another token was
left by it earlier, by a run thread that died)."""


class LockRecord(TypedDict):
    """A station's lock as plain data (:func:`describe`): the station, its run, who holds it
    from where (front end, host, process and when it started), the lock's token, since when
    and its last heartbeat (UTC ISO-8601)."""

    station: str
    run_id: int | None
    operator: str
    recipe: str | None
    front_end: str
    host: str
    pid: int
    process_started: str | None
    token: str
    since: str
    heartbeat_at: str


class StationBusy(StationError):
    """The station is held by another run (``holder``: who, from where, since when)."""

    exit_code = 4

    def __init__(self, message: str, holder: LockRecord) -> None:
        super().__init__(message)
        self.holder = holder


@dataclass(frozen=True)
class Holder:
    """Who takes a station: the operator, the front end (from where), this host and process."""

    operator: str
    front_end: str
    host: str
    pid: int
    process_started: str | None

    @classmethod
    def here(cls, operator: str, front_end: str) -> Holder:
        """This process, for ``operator``, through ``front_end`` (``calstation run`` …)."""
        pid = os.getpid()
        return cls(operator[:100], front_end[:300], socket.gethostname(), pid,
                   process_start(pid))


def terminal_front_end(command: str) -> str:
    """``command`` (``calstation run``) with the terminal it was typed in, when there is one."""
    for fd in (0, 1, 2):
        try:
            return f"{command} in terminal {os.ttyname(fd)}"
        except OSError:
            continue
    return f"{command} (no terminal)"


def process_start(pid: int) -> str | None:
    """When process ``pid`` started, as the kernel counts it (clock ticks since boot, with the
    boot's id), or None where the system does not say (then only whether ``pid`` lives is
    known)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text(encoding="ascii", errors="replace")
        boot = Path("/proc/sys/kernel/random/boot_id").read_text(encoding="ascii").strip()
    except OSError:
        return None
    # the command name (field 2) is in parentheses and may hold spaces: count after it
    fields = stat[stat.rfind(")") + 2:].split()
    return f"{boot[:8]}:{fields[19]}" if len(fields) > 19 else None


def holder_alive(lock: StationLock, now: dt.datetime | None = None) -> bool:
    """Whether the holder of ``lock`` still lives."""
    if lock.host == socket.gethostname():
        pid = int(lock.pid)
        if pid == os.getpid():
            return lock.token in _HELD
        if not process_alive(pid):
            return False
        started, recorded = process_start(pid), lock.process_started
        return started is None or recorded is None or started == recorded
    beat = _aware(lock.heartbeat_at)
    return ((now or utcnow()) - beat).total_seconds() < STALE_AFTER_S


def _aware(t: dt.datetime) -> dt.datetime:
    return t if t.tzinfo is not None else t.replace(tzinfo=dt.UTC)


def describe(lock: StationLock, station: str, run: Run | None) -> LockRecord:
    """The lock as plain data: station, run, operator, recipe, front end, host, pid, since."""
    return {
        "station": station, "run_id": lock.run_id, "operator": lock.operator,
        "recipe": run.recipe_name if run is not None else None,
        "front_end": lock.front_end, "host": lock.host, "pid": lock.pid,
        "process_started": lock.process_started, "token": lock.token,
        "since": _aware(lock.acquired_at).isoformat(timespec="seconds"),
        "heartbeat_at": _aware(lock.heartbeat_at).isoformat(timespec="seconds"),
    }


def busy_message(h: LockRecord, now: dt.datetime | None = None) -> str:
    """One sentence: who holds the station, from where, since when, and what to do."""
    since = dt.datetime.fromisoformat(h["since"])
    ago = max(0, int(((now or utcnow()) - since).total_seconds()))
    age = f"{ago} s" if ago < 120 else f"{ago // 60} min" if ago < 7200 else f"{ago // 3600} h"
    run = f"run {h['run_id']}" if h["run_id"] else "a run starting"
    recipe = f", recipe {h['recipe']}" if h.get("recipe") else ""
    return (
        f"station {h['station']} is in use: {run} (operator {h['operator']}{recipe}) from "
        f"{h['front_end']} on host {h['host']} (process {h['pid']}), since "
        f"{since.strftime('%Y-%m-%d %H:%M:%S')} UTC ({age} ago). One run drives a turntable at "
        "a time: wait for that run to end, or abort it where it was started"
    )


class StationHold:
    """A held station lock: :meth:`attach` the run, :meth:`release` when its drivers are
    closed (also on leaving a ``with`` block). Renews its heartbeat in a daemon thread."""

    def __init__(self, db: Database, station: str, station_id: int, token: str,
                 taken_over: LockRecord | None) -> None:
        self.db, self.station, self.station_id, self.token = db, station, station_id, token
        self.taken_over = taken_over
        """the stale lock this one replaced (:func:`describe`), None when the station was free"""
        self._stop = threading.Event()
        self._beat = threading.Thread(target=self._heartbeat, daemon=True,
                                      name=f"calstation-station-lock-{station}")
        self._beat.start()

    def attach(self, run_id: int) -> None:
        """Name the run the station is held for (shown to whoever is refused)."""
        with self.db.session("naming the station's run") as s:
            s.execute(update(StationLock).where(StationLock.station_id == self.station_id,
                                                StationLock.token == self.token)
                      .values(run_id=run_id))

    def release(self) -> None:
        """Give the station back (idempotent). A database that is away leaves the row, which
        the next taker finds stale once this process has ended."""
        if self._stop.is_set():
            return
        self._stop.set()
        _HELD.discard(self.token)
        try:
            with self.db.engine.begin() as conn:
                conn.execute(delete(StationLock).where(
                    StationLock.station_id == self.station_id, StationLock.token == self.token))
        except SQLAlchemyError:
            pass

    def __enter__(self) -> StationHold:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def _heartbeat(self) -> None:
        # never through Database.session: a busy database must not warn the operator for this
        while not self._stop.wait(HEARTBEAT_S):
            try:
                with self.db.engine.begin() as conn:
                    conn.execute(update(StationLock).where(
                        StationLock.station_id == self.station_id,
                        StationLock.token == self.token).values(heartbeat_at=utcnow()))
            except SQLAlchemyError:
                continue


def take_station(db: Database, station: str, holder: Holder, *, force: bool = False
                 ) -> StationHold:
    """Take ``station``'s lock for ``holder``; :class:`StationBusy` (naming the holder) when a
    live holder has it. A stale lock (its holder died) is taken over; ``force`` takes over even
    a lock whose holder seems alive (``resume --force``: only when that process is known to be
    gone)."""
    station_id = get_or_create_station(db, station)
    token = uuid.uuid4().hex
    for attempt in range(3):
        try:
            taken_over = _take(db, station, station_id, holder, token, force)
        except DatabaseError as exc:
            # PostgreSQL: two first takes of a free station both insert; one loses, then reads
            if attempt == 2 or not isinstance(exc.__cause__, IntegrityError):
                raise
            continue
        _HELD.add(token)
        return StationHold(db, station, station_id, token, taken_over)
    raise StationError(f"could not take station {station}")  # not reached


def _take(db: Database, station: str, station_id: int, holder: Holder, token: str,
          force: bool) -> LockRecord | None:
    with db.session(f"taking station {station}") as s:
        row = s.scalars(select(StationLock).where(StationLock.station_id == station_id)
                        .with_for_update()).first()
        previous = None
        if row is not None:
            previous = describe(row, station, s.get(Run, row.run_id) if row.run_id else None)
            if not force and holder_alive(row):
                raise StationBusy(busy_message(previous), previous)
            s.delete(row)
            s.flush()
        now = utcnow()
        s.add(StationLock(station_id=station_id, token=token, run_id=None,
                          operator=holder.operator, front_end=holder.front_end,
                          host=holder.host, pid=holder.pid,
                          process_started=holder.process_started, acquired_at=now,
                          heartbeat_at=now))
        return previous


def station_holder(
    db: Database, station: str
) -> dict[str, Any] | None:  # Any: a LockRecord and ``alive``, as the web's status reads it
    """Who holds ``station`` now (:func:`describe`, with ``alive``), or None when free."""
    from calstation.storage.db import Station

    with db.session("reading the station locks", read_only=True) as s:
        row = s.scalars(select(StationLock).join(Station, Station.id == StationLock.station_id)
                        .where(Station.name == station)).first()
        if row is None:
            return None
        return {**describe(row, station, s.get(Run, row.run_id) if row.run_id else None),
                "alive": holder_alive(row)}


def taken_over_note(previous: LockRecord) -> str:
    """What the taker of a stale lock is told."""
    run = f"run {previous['run_id']}" if previous["run_id"] else "a run"
    return (f"station {previous['station']} was still marked in use by {run} from "
            f"{previous['front_end']} on host {previous['host']} (process {previous['pid']}), "
            "which has ended: its lock is cleared")
