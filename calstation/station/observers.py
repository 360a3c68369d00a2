"""Who reacts to a run: the plugins' observer hooks, and what happens once the run's end is
stored.

The station stores the run's end and hands it, as a :class:`RunEnded`, to each of its end
observers in turn: ``report.html`` written into the run folder, the plugins' ``run_finished``
hook, the operator's summary, the run's files copied to the fleet's shared store. Each observer
does one thing, and its failure is a warning to the operator, never a failed run: the run's end
is stored already. A front end may pass observers of its own to
:class:`~calstation.station.machine.Station`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

from calstation import plugins
from calstation.errors import CalstationError
from calstation.plugins.hookspecs import run_brief_payload, run_summary_payload
from calstation.station.operator import Operator
from calstation.storage.db import Database, RunStatus


@dataclass(frozen=True)
class RunEnded:
    """A run's end, as stored: its id, final status, the reason it did not pass (None when it
    did), and the summary read back from the database
    (:func:`calstation.storage.report.run_summary`)."""

    run_id: int
    status: RunStatus
    error: str | None
    summary: dict[str, Any]  # Any: storage's run mapping (as the operator's summary takes it)


EndObserver = Callable[[RunEnded], None]
"""Told of a run's end once it is stored; what it raises is a warning to the operator."""


def notify(ui: Operator, hook: str, call: Callable[[], None]) -> None:
    """Call a plugin observer hook (``call``, the ``hook`` of :mod:`calstation.plugins` with
    its payload: ``run_started``, ``step_finished``, ``run_finished``); an observer's exception
    is a warning, never a failed run."""
    try:
        call()
    except Exception as exc:
        ui.warn(f"a plugin's {hook} observer failed: {type(exc).__name__}: {exc}")


def report_html(db: Database, ui: Operator) -> EndObserver:
    """``report.html`` in the run folder, whatever the outcome; a failure is a warning."""

    def write_report_html(ended: RunEnded) -> None:
        from calstation.storage.report_html import write_run_report

        try:
            write_run_report(db, ended.run_id)
        except Exception as exc:
            ui.warn(f"could not write report.html: {type(exc).__name__}: {exc}")

    return write_report_html


def plugin_hooks(ui: Operator) -> EndObserver:
    """The plugins' ``run_finished`` hook."""

    def tell_plugins(ended: RunEnded) -> None:
        notify(ui, "run_finished", partial(
            plugins.run_finished, run_brief_payload(ended.summary), str(ended.status),
            run_summary_payload(ended.summary)))

    return tell_plugins


def operator_summary(ui: Operator) -> EndObserver:
    """The run's summary to the operator (the console's table, the web's end screen)."""

    def show_summary(ended: RunEnded) -> None:
        ui.summary(ended.summary)

    return show_summary


def upload_files(db: Database, ui: Operator) -> EndObserver:
    """Copy the run's files to the fleet's shared store when one is configured
    (``$CALSTATION_RECORDINGS_URL``, :mod:`calstation.storage.uploads`). A failure is a
    warning: the run folder keeps every file, and ``calstation upload`` sends them later."""

    def upload(ended: RunEnded) -> None:
        from calstation.storage.uploads import recordings_store, upload_run

        store = recordings_store()
        if store is None:
            return
        try:
            done = upload_run(db, ended.run_id, store)
        except CalstationError as exc:
            problem = str(exc)
        else:
            if done.ok:
                ui.info(f"files copied to {store}: {len(done.sent)} sent, "
                        f"{len(done.present)} there already")
                return
            problem = "; ".join(done.failed)
        ui.warn(f"the run's files were not all copied to {store}: "
                f"{problem}; the run folder keeps them, and `calstation upload "
                f"{ended.run_id}` sends them later")

    return upload


def default_observers(db: Database, ui: Operator) -> Sequence[EndObserver]:
    """What every run does once its end is stored, in this order: ``report.html``, the plugins'
    hook, the operator's summary, the upload."""
    return (report_html(db, ui), plugin_hooks(ui), operator_summary(ui), upload_files(db, ui))


def tell_observers(observers: Sequence[EndObserver], ended: RunEnded, ui: Operator) -> None:
    """Tell each observer of ``ended`` in turn; one that raises is a warning, and the others
    are told all the same."""
    for observer in observers:
        try:
            observer(ended)
        except Exception as exc:
            name = getattr(observer, "__name__", type(observer).__name__)
            ui.warn(f"{name} failed at the end of run {ended.run_id}: "
                    f"{type(exc).__name__}: {exc}")
