"""Which stored runs a campaign re-processes, and the key that finds the campaign again."""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass

from sqlalchemy import select
from sqlalchemy.orm import Session

from calstation.errors import FleetError
from calstation.storage.db import Run, RunStatus, Station

RUN_STATUSES = (RunStatus.PASSED, RunStatus.FAILED, RunStatus.ABORTED, RunStatus.INTERRUPTED,
                RunStatus.RUNNING)
"""The statuses a run can have; ``--status`` takes these."""

DEFAULT_STATUSES = (RunStatus.PASSED, RunStatus.FAILED, RunStatus.ABORTED, RunStatus.INTERRUPTED)
"""Without ``--status``: every run but those still running."""


@dataclass(frozen=True)
class Selection:
    """The runs of a campaign: of ``stations`` (all when empty), started from ``since`` and
    before the end of ``until`` (dates or ISO times, UTC), with one of ``statuses`` (every
    finished one when empty), the first ``limit`` of them in run order; re-processed with
    ``strategy`` (each run's recipe's when None)."""

    stations: tuple[str, ...] = ()
    since: str | None = None
    until: str | None = None
    statuses: tuple[str, ...] = ()
    strategy: str | None = None
    limit: int | None = None

    def as_dict(self) -> dict[str, object]:
        """The selection as stored with the campaign (sorted, so equal selections are equal)."""
        data: dict[str, object] = asdict(self)
        data["stations"] = sorted(self.stations)
        data["statuses"] = sorted(self.statuses)
        return data

    def key(self) -> str:
        """sha256 of what the campaign computes (the selection and the strategy): the same
        command finds its campaign again and continues it."""
        text = json.dumps(self.as_dict(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()


def check_selection(sel: Selection) -> None:
    """:class:`FleetError` for a status that does not exist, a limit below 1 or a date that is
    not one."""
    from calstation.storage.qa import QueryError, parse_date

    for status in sel.statuses:
        if status not in RUN_STATUSES:
            raise FleetError(f"--status {status!r}: expected one of {', '.join(RUN_STATUSES)}")
    if sel.limit is not None and sel.limit < 1:
        raise FleetError(f"--limit {sel.limit}: expected 1 or more")
    try:
        for name, value in (("--since", sel.since), ("--until", sel.until)):
            if value:
                parse_date(value, name)
    except QueryError as exc:
        raise FleetError(str(exc)) from None


def select_runs(session: Session, sel: Selection) -> list[int]:
    """The ids of the runs ``sel`` selects, in run order."""
    from calstation.storage.qa import parse_date

    stmt = select(Run.id).join(Station, Run.station_id == Station.id).order_by(Run.id)
    if sel.stations:
        stmt = stmt.where(Station.name.in_(sel.stations))
    stmt = stmt.where(Run.status.in_(sel.statuses or DEFAULT_STATUSES))
    if sel.since:
        stmt = stmt.where(Run.started_at >= parse_date(sel.since, "--since"))
    if sel.until:
        stmt = stmt.where(Run.started_at < parse_date(sel.until, "--until", end=True))
    if sel.limit is not None:
        stmt = stmt.limit(sel.limit)
    return [int(i) for i in session.scalars(stmt)]
