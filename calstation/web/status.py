"""Who holds each station this server runs, for every page: the run, its operator, where it was
started from and since when, read from the station locks (:mod:`calstation.station.lock`) that
every front end takes, so a run started in a terminal shows on the web pages as well.

:class:`StationStatus` reads the locks at most once per :data:`REFRESH_S` however many pages
ask, and puts what it read into the operator page's live state when it changed, so the open
pages follow without a reload.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypedDict

from calstation import display
from calstation.errors import CalstationError
from calstation.storage.db import Database

REFRESH_S = 2.0
"""The locks are read again when the last reading is older than this."""


class Holder(TypedDict):
    """Who holds a station: the run (None while it starts), operator, recipe, front end, host
    and since when (UTC ISO-8601, and in seconds since the epoch)."""

    run_id: int | None
    operator: str
    recipe: str | None
    front_end: str
    host: str
    since: str
    since_epoch: float


class StationEntry(TypedDict):
    """A station of this server: whether it is held, by whom, in words."""

    station: str
    held: bool
    holder: Holder | None
    text: str


def recipe_stations(recipes_dir: Path) -> list[str]:
    """The ``station.id`` of each recipe of the recipes folder (the stations this server runs)."""
    import yaml

    out: set[str] = set()
    for path in sorted(recipes_dir.glob("*.yaml")) if recipes_dir.is_dir() else []:
        try:
            data = yaml.safe_load(path.read_text(encoding="utf-8"))
            out.add(str(data["station"]["id"]))
        except (OSError, yaml.YAMLError, KeyError, TypeError):
            continue
    return sorted(out)


def holder_text(station: str, h: Holder | None) -> str:
    """The station's state in words: ``station sim-01 is free``, or who holds it: ``station
    sim-01 is in use by run 12 (operator alice, recipe sim-periodicity) from calstation run in
    terminal /dev/pts/3 on host bench-3, since 2026-05-04 09:00 UTC`` (how long ago is shown
    beside it, ticking)."""
    if h is None:
        return f"station {station} is free"
    run = f"run {h['run_id']}" if h["run_id"] else "a run starting"
    recipe = f", recipe {h['recipe']}" if h["recipe"] else ""
    return (f"station {station} is in use by {run} (operator {h['operator']}{recipe}) from "
            f"{h['front_end']} on host {h['host']}, since {display.when(h['since'])}")


def age(entry: StationEntry, now: float | None = None) -> str:
    """How long the station of ``entry`` has been held: ``3 min 05 s``; empty when free."""
    h = entry["holder"]
    if not h:
        return ""
    return display.duration((now or time.time()) - h["since_epoch"])


class StationStatus:
    """The holders of the stations of ``stations()`` (see the module docstring)."""

    def __init__(self, db: Database, stations: Callable[[], list[str]],
                 publish: Callable[[list[StationEntry]], None]) -> None:
        self.db, self.stations, self.publish = db, stations, publish
        self._lock = threading.Lock()
        self._read_at = -1e9
        self._current: list[StationEntry] = []

    def current(self) -> list[StationEntry]:
        """Each station with ``held`` and, when held, its ``holder`` (run_id, operator,
        front_end, host, since, recipe) and ``text`` in words; read again when older than
        :data:`REFRESH_S`."""
        with self._lock:
            if time.monotonic() - self._read_at < REFRESH_S:
                return self._current
            self._read_at = time.monotonic()
        fresh = self._read()
        with self._lock:
            changed = _key(fresh) != _key(self._current)
            self._current = fresh
        if changed:
            self.publish(fresh)
        return fresh

    def refresh(self) -> None:
        """Read the locks again now (a run of this server has just given its station back):
        the pages show it free at once, not up to :data:`REFRESH_S` later."""
        with self._lock:
            self._read_at = -1e9
        self.current()

    def held(self, station: str) -> StationEntry | None:
        """The entry of ``station`` when it is held, else None."""
        return next((s for s in self.current() if s["station"] == station and s["held"]),
                    None)

    def _read(self) -> list[StationEntry]:
        import datetime as dt

        from calstation.station.lock import station_holder

        out: list[StationEntry] = []
        for station in self.stations():
            try:
                found = station_holder(self.db, station)
            except CalstationError:  # the database is away: say nothing rather than fail
                found = None
            if found is not None and not found.get("alive", True):
                found = None  # a lock left by a process that has ended: the next start clears it
            h: Holder | None = None
            if found is not None:
                h = {"run_id": found["run_id"], "operator": found["operator"],
                     "recipe": found["recipe"], "front_end": found["front_end"],
                     "host": found["host"], "since": found["since"],
                     "since_epoch": dt.datetime.fromisoformat(found["since"]).timestamp()}
            out.append({"station": station, "held": h is not None, "holder": h,
                        "text": holder_text(station, h)})
        return out


def _key(entries: list[StationEntry]) -> list[tuple[str, Holder | None]]:
    return [(e["station"], e["holder"]) for e in entries]
