"""``calstation reprocess``: a campaign re-processing stored runs on Dask (:mod:`calstation.fleet`).

Thin: parse the options, start or reach the cluster, run the campaign with a progress line, then
print the flagged units (or ``--json``) and write ``--report``.
"""

from __future__ import annotations

import json
import math
import uuid
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

if TYPE_CHECKING:
    from types import TracebackType

    from rich.console import Console
    from rich.progress import TaskID

    from calstation.fleet.campaign import Tally
    from calstation.fleet.selection import Selection
    from calstation.fleet.tolerance import Tolerance

# Any: the campaign's data is calstation.fleet.view.campaign_data's, a dict[str, Any] there
CampaignData = dict[str, Any]

DB_HELP = "Database URL (default: $CALSTATION_DB_URL or SQLite in $CALSTATION_HOME)."


def register(app: typer.Typer) -> None:
    """Add the ``reprocess`` command."""

    @app.command("reprocess")
    def reprocess_cmd(
        station: list[str] = typer.Option(
            [], "--station", help="Only runs of this station (repeat for several).",
            show_default=False),
        since: str = typer.Option(None, "--since", help="Runs started on or after this date "
                                  "(YYYY-MM-DD) or ISO time, UTC."),
        until: str = typer.Option(None, "--until", help="Runs started on or before this date "
                                  "(the whole day) or before this ISO time, UTC."),
        status: list[str] = typer.Option(
            [], "--status", help="Only runs with this status: passed, failed, aborted, "
            "interrupted (repeat for several; default: all but running).", show_default=False),
        strategy: str = typer.Option(None, "--strategy", help="Fine-tuning strategy (default: "
                                     "each run's recipe's)."),
        scheduler: str = typer.Option(None, "--scheduler", help="Address of an existing Dask "
                                      "cluster's scheduler (tcp://host:8786)."),
        workers: int = typer.Option(None, "--workers", help="Worker processes of a local Dask "
                                    "cluster (default: one per core)."),
        limit: int = typer.Option(None, "--limit", help="Only the first N selected runs."),
        tolerance: list[str] = typer.Option(
            [], "--tolerance", help="Flag a change above this: mm in the work volume (0.5), or "
            "per parameter (tx=0.2 in mm, ry=0.01 in degrees); repeat for several. Default: "
            "each run's recipe's drift limits.", show_default=False),
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object (stored "
                                     "units) instead of the table."),
        report: Path = typer.Option(None, "--report", help="Write a self-contained HTML "
                                    "summary to this file."),
        link_base: str = typer.Option(None, "--link-base", help="In --report, link each run to "
                                      "its page on `calstation serve` at this URL."),
        new: bool = typer.Option(False, "--new", help="Start a new campaign even when one of "
                                 "the same selection exists (default: continue it)."),
        db: str = typer.Option(None, "--db", help=DB_HELP),
    ) -> None:
        """Re-process stored runs with today's engine, on Dask, and compare each with its
        stored H.

        Each run is calibrated again from its recordings (checked against their sha256) with its
        own recipe, exactly as `calibrate --run N`, and stored as a re-processing (never the
        accepted calibration). The same command again continues the campaign: runs already
        stored are skipped.
        """
        from calstation.fleet.selection import Selection, check_selection
        from calstation.fleet.tolerance import parse_tolerance

        sel = Selection(stations=tuple(station), since=since, until=until,
                        statuses=tuple(status), strategy=strategy, limit=limit)
        check_selection(sel)
        tol = parse_tolerance(tolerance) if tolerance else None
        _check_cluster_options(scheduler, workers)
        if report is not None:
            from calstation.atomic import check_output

            check_output(report, "report")  # refused before the campaign runs
        data, tally = _run(db, sel, tol, scheduler, workers, new)
        if report is not None:
            from calstation.atomic import write_atomic
            from calstation.fleet.view import render_report

            write_atomic(report, render_report(data, link_base), "report")
        if as_json:
            typer.echo(json.dumps(_json(data, tally), indent=2, default=_plain))
        else:
            _print(data, tally, report)


def _check_cluster_options(scheduler: str | None, workers: int | None) -> None:
    from calstation.errors import FleetError

    if scheduler is not None and workers is not None:
        raise FleetError("--scheduler and --workers: give one (--workers starts a local cluster)")
    if workers is not None and workers < 1:
        raise FleetError(f"--workers {workers}: expected 1 or more")


def _run(db_url: str | None, sel: Selection, tol: Tolerance | None, scheduler: str | None,
         workers: int | None, new: bool) -> tuple[CampaignData, Tally]:
    """Run the campaign on the cluster with a progress line on standard error; (its data for
    the selected runs, what this invocation did)."""
    from rich.console import Console

    from calstation.fleet.campaign import dask_execute, run_campaign
    from calstation.fleet.cluster import dask_client, worker_count
    from calstation.fleet.selection import select_runs
    from calstation.fleet.view import campaign_data
    from calstation.storage.db import open_database

    console = Console(stderr=True)
    database = open_database(db_url)
    try:
        with ExitStack() as stack:
            with console.status("starting the Dask cluster" if scheduler is None
                                else f"connecting to {scheduler}"):
                client = stack.enter_context(dask_client(workers, scheduler))
            n = worker_count(client)
            with _progress(console, n) as show:
                campaign_id, tally = run_campaign(
                    database, sel, tol, dask_execute(client, uuid.uuid4().hex[:8]), new=new,
                    progress=show)
        tally.workers = n
        console.print(f"re-processed {tally.done} runs in {tally.seconds():.1f} s on {n} Dask "
                      f"workers: {tally.runs_per_minute():.1f} runs/min ({tally.stored_before} "
                      f"stored before, {tally.left} left)", highlight=False)
        with database.session("reading the campaign", read_only=True) as s:
            data = campaign_data(s, campaign_id, select_runs(s, sel))
    finally:
        database.dispose()
    return data, tally


class _progress:
    """The campaign's progress on standard error: a bar of the selected runs with done,
    failed, skipped and left, and the throughput."""

    def __init__(self, console: Console, workers: int) -> None:
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        self.bar = Progress(TextColumn("{task.description}"), BarColumn(bar_width=12),
                            TextColumn("{task.fields[counts]}"), TimeElapsedColumn(),
                            console=console, transient=False)
        self.workers = workers
        self.task: TaskID | None = None

    def __enter__(self) -> Callable[[Tally], None]:
        self.bar.__enter__()
        self.task = self.bar.add_task(f"{self.workers} workers", total=None, counts="")
        return self.show

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.bar.__exit__(kind, exc, tb)

    def show(self, t: Tally) -> None:
        assert self.task is not None  # shown inside the with block
        counts = (f"{t.stored_before + t.done}/{t.selected} done, {t.failed} failed, "
                  f"{t.skipped} skipped, {t.left} left, {t.runs_per_minute():.1f} runs/min")
        self.bar.update(self.task, total=max(t.selected, 1), completed=t.stored_before + t.done,
                        counts=counts)


def _plain(value: object) -> str:
    """JSON for values json does not know (NaN is written as null by the view already)."""
    return str(value)


def _json(data: CampaignData, tally: Tally) -> dict[str, object]:
    """``--json``: the campaign, ``runs`` (each with ``resumed``: stored by an earlier
    invocation), ``totals`` and this invocation's throughput."""
    elapsed = max(1e-9, tally.seconds())
    return {
        "campaign": data["campaign"],
        "runs": [{**r, "resumed": r["run_id"] in tally.before_runs} for r in data["runs"]],
        "totals": {**data["totals"], "stored_before": tally.stored_before,
                   "done_now": tally.done, "lost": tally.lost},
        "lost_runs": tally.lost_runs,
        "throughput": {"runs": tally.done, "seconds": elapsed,
                       "runs_per_minute": 60.0 * tally.done / elapsed,
                       "workers": tally.workers},
    }


def _print(data: CampaignData, tally: Tally, report: Path | None) -> None:
    """The totals, the flagged units by serial, and where the report went."""
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    t = data["totals"]
    console = Console()
    console.print(
        f"campaign {data['campaign']['id']}: {t['selected']} runs selected; "
        f"{t['reprocessed']} re-processed, {t['skipped']} skipped, {t['failed']} failed, "
        f"{t['left']} left; {t['flagged']} flagged, {t['refused']} refused by today's engine "
        f"({tally.done} now, {tally.stored_before} stored before; "
        f"{tally.runs_per_minute():.1f} runs/min)", highlight=False)
    if data["flagged"]:
        table = Table(title=f"flagged units (above {data['campaign']['tolerance_text']})")
        for col in ("serial", "run", "station", "work volume mm", "why"):
            table.add_column(col, justify="left" if col in ("serial", "station", "why")
                             else "right")
        for r in data["flagged"]:
            moved = r.get("change_in_work_volume_m")
            table.add_row(escape(r["serial"] or "—"), str(r["run_id"]), escape(r["station"]),
                          "—" if moved is None or not math.isfinite(moved)
                          else f"{moved * 1e3:.3f}", escape("; ".join(r["flags"])))
        console.print(table)
    for r in data["runs"]:
        if r["outcome"] != "reprocessed":
            console.print(f"run {r['run_id']} {r['outcome']}: {escape(r['error'] or '')}",
                          highlight=False, soft_wrap=True)
    if tally.lost:
        console.print(f"{tally.lost} runs were lost with their Dask worker; run the command "
                      "again to re-process them", style="yellow")
    if report is not None:
        console.print(f"report written to {escape(str(report))}", highlight=False)
