"""The QA engineer's commands: ``history``, ``show``, ``export``, ``trend``.

Storage is metres and radians; tables show millimetres and degrees; ``--json`` and exports give
exactly what is stored.
"""

from __future__ import annotations

import datetime as dt
import itertools
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer
from rich.markup import escape

from calstation import display
from calstation.cli._console import terminal_safe, wide_console

if TYPE_CHECKING:
    from matplotlib.figure import Figure
    from rich.console import Console

    from calstation.storage.qa import TrendPoint
    from calstation.storage.report import HistoryItem

    class Listed(HistoryItem):
        """A run as ``history`` lists it: with why it did not pass (None when it did)."""

        failure_reason: str | None

H_PARAMS = ("tx", "ty", "tz", "rx", "ry", "rz")
CUBE_PARAMS = ("edge_error", "obb_error", "flatness_rms")
DB_HELP = "Database URL (default: $CALSTATION_DB_URL or SQLite in $CALSTATION_HOME)."


def _parse_since(text: str) -> dt.datetime:
    from calstation.errors import CalstationError

    try:
        t = dt.datetime.fromisoformat(text)
    except ValueError:
        raise CalstationError(
            f"--since {text!r}: expected a date (YYYY-MM-DD) or ISO time (YYYY-MM-DDTHH:MM)"
        ) from None
    return t if t.tzinfo else t.replace(tzinfo=dt.UTC)


def _colour(status: str) -> str:
    """A run's or a step's status as the tables colour it."""
    from calstation.storage.db.models import RunStatus  # not at start-up: SQLAlchemy's

    colours: dict[str, str] = {RunStatus.PASSED: "green", RunStatus.FAILED: "red"}
    return colours.get(status, "yellow")


def failure_reason(run: HistoryItem) -> str:
    """Why a run did not pass, in one line: its error, else the cube check's failures."""
    from calstation.storage.db.models import RunStatus

    if run["status"] == RunStatus.PASSED:
        return ""
    if run.get("error"):
        return str(run["error"]).splitlines()[0]
    cube = run.get("cube_check")
    if cube and not cube["passed"]:
        return "cube check: " + "; ".join(cube.get("failures") or ["failed"])
    return ""


SHOWN = ("tx", "ty", "tz", "ry", "rz")
"""The parameters the history lists (rx is the gauge, held at 0)."""


def _value(r: HistoryItem, p: str) -> str:
    """A run's final value of ``p`` as the history shows it (— without a calibration)."""
    c = r["calibration"]
    if c is None:
        return display.MISSING
    if p in (c.get("not_estimated") or ()):
        return display.NOT_ESTIMATED
    return display.number(p, c["H"][p], unit=False)


def _edge(r: HistoryItem) -> str:
    cube = r["cube_check"]
    return display.number("edge_error", cube["edge_error"], unit=False) if cube \
        else display.MISSING


def print_history(rows: list[Listed], console: Console) -> None:
    """The runs (``history --json``'s rows) as a table with a labelled column per parameter
    when it fits ``console``; else one block per run, its items (``station sim-01``,
    ``tx 15.605 mm``) wrapped between items, never within a word or a number."""
    from rich import box
    from rich.table import Table

    table = Table(title="Runs", caption="edge: the cube's face-fit edge error",
                  box=box.SIMPLE_HEAD, pad_edge=False, collapse_padding=True)
    for col in ("run", "station", "serial", "started (UTC)", "operator", "recipe", "status"):
        table.add_column(col, no_wrap=True)
    for p in (*SHOWN, "edge_error"):
        table.add_column(display.quantity(p).heading.replace("edge error", "edge"),
                         justify="right", no_wrap=True)
    for r in rows:
        colour = _colour(r["status"])
        table.add_row(
            str(r["id"]), escape(r["station"]), escape(r["unit_serial"] or "—"),
            display.when(r["started_at"]).removesuffix(" UTC"), escape(r["operator"]),
            escape(r["recipe_name"]), f"[{colour}]{r['status']}[/]",
            *(_value(r, p) for p in SHOWN), _edge(r))
    natural = console.measure(table, options=console.options.update_width(10_000)).maximum
    if natural <= console.width:
        console.print(table)
    else:
        console.print("[bold]Runs[/]")
        for r in rows:
            _print_run_block(r, console)
    for r in rows:
        if r["failure_reason"]:
            console.print(escape(f"run {r['id']} ({r['status']}): {r['failure_reason']}"),
                          highlight=False)


def _print_run_block(r: HistoryItem, console: Console) -> None:
    """One run in a few lines of labelled items, wrapped between items."""
    colour = _colour(r["status"])
    items = [f"run {r['id']}", f"[{colour}]{r['status']}[/]", display.when(r["started_at"]),
             f"station {escape(r['station'])}", f"serial {escape(r['unit_serial'] or '—')}",
             f"operator {escape(r['operator'])}", f"recipe {escape(r['recipe_name'])}"]
    c = r["calibration"]
    for p in SHOWN:
        shown = _value(r, p)
        unit = "" if c is None or shown == display.NOT_ESTIMATED else display.quantity(p).unit
        items.append(f"{p} {shown}{'' if not unit or unit == '°' else ' '}{unit}")
    items.append(f"edge {_edge(r)}{' mm' if r['cube_check'] else ''}")
    from rich.text import Text

    lines: list[str] = []
    for item in items:
        width = Text.from_markup(item).cell_len
        if lines and Text.from_markup(lines[-1]).cell_len + 2 + width <= console.width - 2:
            lines[-1] += "  " + item
        else:
            lines.append(item)
    for i, line in enumerate(lines):
        console.print(("" if i == 0 else "  ") + line, highlight=False, no_wrap=True,
                      overflow="fold", crop=False)
    console.print()


def register(app: typer.Typer) -> None:
    """Add ``history``, ``show``, ``export`` and ``trend``."""

    @app.command("history")
    def history(
        station: str = typer.Option(None, "--station", help="Only this station."),
        since: str = typer.Option(None, "--since", help="Only runs started since DATE (UTC)."),
        status: str = typer.Option(
            None,
            "--status",
            help="Only runs with this status (running/passed/failed/aborted/interrupted).",
        ),
        serial: str = typer.Option(None, "--serial", help="Only runs of this unit serial."),
        limit: int = typer.Option(200, "--limit", help="At most this many runs (newest)."),
        as_json: bool = typer.Option(False, "--json", help="JSON (stored values: m, rad)."),
        db: str = typer.Option(None, "--db", help=DB_HELP),
    ) -> None:
        """List runs, newest first, with their final calibration and cube check."""
        from sqlalchemy import select

        from calstation.storage.db import Run, Station, open_database
        from calstation.storage.report import history_item, with_results

        database = open_database(db, read_only=True)
        rows: list[Listed] = []
        with database.session("reading the runs", read_only=True) as s:
            stmt = with_results(select(Run).join(Station).order_by(Run.id.desc()).limit(limit))
            if station:
                stmt = stmt.where(Station.name == station)
            if status:
                stmt = stmt.where(Run.status == status)
            if serial:
                stmt = stmt.where(Run.unit_serial == serial)
            if since:
                stmt = stmt.where(Run.started_at >= _parse_since(since))
            for run in s.scalars(stmt):
                item: Listed = {**history_item(run), "failure_reason": None}
                item["failure_reason"] = failure_reason(item) or None
                rows.append(item)
        database.dispose()
        if as_json:
            typer.echo(json.dumps(rows, indent=2))
            return
        print_history(terminal_safe(rows), wide_console())

    @app.command("show")
    def show(
        run_id: int = typer.Argument(..., help="Run id (see `calstation history`)."),
        as_json: bool = typer.Option(False, "--json", help="JSON: everything stored."),
        db: str = typer.Option(None, "--db", help=DB_HELP),
    ) -> None:
        """Everything about one run: steps, calibrations, cube check, recordings."""
        from rich.table import Table

        from calstation.cli._operator import render_summary
        from calstation.storage.db import open_database
        from calstation.storage.report import get_run, run_summary

        database = open_database(db, read_only=True)
        with database.session("reading the runs", read_only=True) as s:
            summary = run_summary(get_run(s, run_id))
        database.dispose()
        if as_json:
            typer.echo(json.dumps(summary, indent=2))
            return
        summary = terminal_safe(summary)
        console = wide_console()
        console.print(escape(
            f"run {summary['id']}: station {summary['station']}, unit serial "
            f"{summary['unit_serial'] or '— (not known)'}, recipe {summary['recipe_name']} "
            f"(sha256 {summary['recipe_sha256'][:12]}…), operator {summary['operator']}"
            f"{' (unattended)' if summary['unattended'] else ''}, started "
            f"{display.when(summary['started_at'], True)}, finished "
            f"{display.when(summary['finished_at'], True)}"),
            highlight=False,
        )
        steps = Table(title="Steps")
        for col in ("step", "attempt", "status", "started", "finished", "error"):
            steps.add_column(col)
        for st in summary["steps"]:
            colour = _colour(st["status"])
            steps.add_row(st["name"], str(st["attempt"]), f"[{colour}]{st['status']}[/]",
                          (st["started_at"] or "")[11:19], (st["finished_at"] or "")[11:19],
                          st["error"] or "")
        console.print(steps)
        arts = Table(title="Artifacts")
        for col in ("kind", "path", "bytes", "sha256", "status"):
            arts.add_column(col)
        for a in summary["artifacts"]:
            arts.add_row(a["kind"], a["path"], str(a["size_bytes"]), a["sha256"][:16] + "…",
                         a.get("status") or "complete")
        console.print(arts)
        report = Path(summary["data_dir"] or ".") / "report.html"
        if summary["data_dir"] and report.is_file():
            console.print(f"report: {escape(str(report))}", highlight=False, soft_wrap=True)
        stop = summary.get("motor_stop")
        if stop:
            console.print(f"motor stopped by {stop['how']} (run {stop['reason']})"
                          + ("" if stop["ok"] else f": {'; '.join(stop['errors'])}"),
                          highlight=False)
        render_summary(console, summary)

    @app.command("export")
    def export(
        run_id: int = typer.Argument(..., help="Run id."),
        fmt: str = typer.Option(
            "yaml", "--format", "-f",
            help="yaml | json | csv | tf | urdf | xacro | ros2-yaml | ros2-params (values in "
            "m, rad; quaternions x y z w). tf: static_transform_publisher arguments, both "
            "directions; urdf: a <robot> file with the two links and the joint; xacro: a macro "
            "adding the joint between links you name; ros2-yaml: a "
            "geometry_msgs/TransformStamped; ros2-params: a ROS 2 parameter file with the "
            "transform, the lidar's range model and the time offset. The range model, when "
            "estimated, is in every format (a comment in tf, urdf, xacro, ros2-yaml).",
        ),
        fragment: bool = typer.Option(
            False, "--fragment",
            help="urdf: only the links and the joint, to paste inside your own <robot>.",
        ),
        parent: str = typer.Option(
            "lidar", "--parent",
            help="urdf, ros2-yaml: the parent frame, lidar (pose of P in L) or platform "
            "(the inverse).",
        ),
        lidar_frame: str = typer.Option("lidar", "--lidar-frame", help="Frame id of L."),
        platform_frame: str = typer.Option("platform", "--platform-frame", help="Frame id of P."),
        platter_frame: str = typer.Option("platter", "--platter-frame", help="Frame id of D."),
        out: Path = typer.Option(None, "--out", "-o", help="Write to this file (default stdout)."),
        db: str = typer.Option(None, "--db", help=DB_HELP),
    ) -> None:
        """Export a run's final calibration (yaml/json load with `calibrate`/`verify`)."""
        from calstation.atomic import check_output, write_atomic
        from calstation.storage.db import open_database
        from calstation.storage.report import export_calibration, get_run
        from calstation.storage.ros import Frames

        if parent not in ("lidar", "platform"):
            raise typer.BadParameter(
                f"parent must be 'lidar' or 'platform', got {parent!r}", param_hint="--parent"
            )
        if fragment and fmt != "urdf":
            raise typer.BadParameter(
                f"a fragment is a URDF form: give --format urdf, not {fmt}",
                param_hint="--fragment",
            )
        frames = Frames(lidar_frame, platform_frame, platter_frame)
        if out is not None:
            check_output(out, "export")  # refused before the database is opened
        database = open_database(db, read_only=True)
        with database.session("reading the runs", read_only=True) as s:
            text = export_calibration(get_run(s, run_id), fmt, parent=parent, frames=frames,
                                      fragment=fragment)
        database.dispose()
        if out is None:
            typer.echo(text, nl=False)
        else:
            write_atomic(out, text, "export")
            typer.echo(f"wrote {out}", err=True)

    @app.command("trend")
    def trend(
        station: str = typer.Option(..., "--station", help="Station id."),
        param: str = typer.Option(
            ..., "--param", help=f"One of {', '.join(H_PARAMS + CUBE_PARAMS)}."
        ),
        png: Path = typer.Option(
            None, "--png", help="Plot file (default: trend-STATION-PARAM.png here)."
        ),
        serial: str = typer.Option(None, "--serial", help="Only runs of this unit serial."),
        as_json: bool = typer.Option(False, "--json", help="JSON (stored units)."),
        db: str = typer.Option(None, "--db", help=DB_HELP),
    ) -> None:
        """A parameter over a station's accepted calibrations: table, PNG plot by date, drift flags.

        Drift is flagged when the change from the station's previous accepted calibration
        exceeds the run's recipe limits (qa.drift_translation, qa.drift_rotation_deg); cube
        metrics are flagged above the recipe's cube limits.
        """
        from rich.table import Table

        from calstation.errors import CalstationError

        if param not in H_PARAMS + CUBE_PARAMS:
            raise CalstationError(
                f"--param {param!r}: expected one of {', '.join(H_PARAMS + CUBE_PARAMS)}"
            )
        points = trend_points(station, param, db, serial=serial)
        if as_json:
            typer.echo(json.dumps(points, indent=2))
        else:
            q = display.quantity(param)
            table = Table(title=f"{param} of station {station} ({q.unit})")
            for col in ("run", "date (UTC)", "serial", param, "Δ vs previous", "limit", "drift"):
                table.add_column(col)
            for p in terminal_safe(points):
                flag = "[bold red]DRIFT[/]" if p["flagged"] else "ok"
                table.add_row(
                    str(p["run_id"]), display.when(p["date"], True).removesuffix(" UTC"),
                    p["unit_serial"] or "—", display.number(param, p["value"], unit=False),
                    display.number(param, p["delta"], signed=True, unit=False),
                    display.number(param, p["limit"], unit=False), flag)
            wide_console().print(table)
        if not points:
            which = f" and unit {serial}" if serial else ""
            typer.echo(f"no accepted calibrations for station {station}{which}", err=True)
            raise typer.Exit(1)
        path = png or Path(f"trend-{station}-{param}.png")
        plot_trend(points, station, param, path)
        typer.echo(f"plot: {path}", err=True)


def trend_points(
    station: str, param: str, db: str | None, serial: str | None = None
) -> list[TrendPoint]:
    """The accepted calibrations of ``station`` (of unit ``serial`` only, when given), oldest
    first, with drift vs the previous one: :func:`calstation.storage.qa.trend_points`, as the web
    station's trend page shows them."""
    from calstation.storage.db import open_database
    from calstation.storage.qa import trend_points as query

    database = open_database(db, read_only=True)
    try:
        with database.session("reading the runs", read_only=True) as s:
            points = query(s, station, param, serial)
    finally:
        database.dispose()
    return points


def plot_trend(points: list[TrendPoint], station: str, param: str, path: Path) -> None:
    """PNG: the parameter over time (x = the run's start date, UTC; mm or deg), drifted runs in
    red, the allowed band around each previous value shaded."""
    import matplotlib.pyplot as plt

    from calstation.atomic import atomic_output

    fig = trend_figure(points, station, param)
    try:
        with atomic_output(path, "plot") as tmp:
            fig.savefig(tmp, dpi=120, format="png")
    finally:
        plt.close(fig)


def _date(point: TrendPoint) -> dt.datetime:
    """When the run of a trend's point started (a stored run always has its start)."""
    if point["date"] is None:
        raise ValueError(f"run {point['run_id']} has no start time")
    return dt.datetime.fromisoformat(point["date"])


def trend_figure(points: list[TrendPoint], station: str, param: str) -> Figure:
    """The matplotlib figure of :func:`plot_trend` (x axis: dates)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.dates as mdates
    import matplotlib.pyplot as plt

    q = display.quantity(param)

    def scale(v: float) -> float:
        return q.shown(v)

    unit = q.unit
    # Any: matplotlib's stubs take no datetimes, which it plots on a date axis
    xs: list[Any] = [_date(p) for p in points]
    ys = [scale(p["value"]) for p in points]
    fig, ax = plt.subplots(figsize=(8, 4))
    ax.plot(xs, ys, "-o", color="tab:blue", label=param)
    if param not in CUBE_PARAMS:
        for i, ((x0, prev), (x1, cur)) in enumerate(itertools.pairwise(zip(xs, points,
                                                                              strict=True))):
            lo = scale(prev["value"] - cur["limit"])
            hi = scale(prev["value"] + cur["limit"])
            ax.fill_between([x0, x1], [lo, lo], [hi, hi], color="tab:green", alpha=0.12,
                            step="post", label="allowed drift" if i == 0 else None)
    else:
        ax.axhline(scale(points[-1]["limit"]), color="tab:red", ls="--", label="limit")
    bad = [(x, y) for x, y, p in zip(xs, ys, points, strict=True) if p["flagged"]]
    if bad:
        ax.scatter([b[0] for b in bad], [b[1] for b in bad], color="tab:red", zorder=3, s=60,
                   label="drift")
    for x, y, p in zip(xs, ys, points, strict=True):
        ax.annotate(str(p["run_id"]), (x, y), textcoords="offset points", xytext=(0, 6),
                    ha="center", fontsize=7, color="0.4")
    locator = mdates.AutoDateLocator()  # type: ignore[no-untyped-call]
    ax.xaxis.set_major_locator(locator)
    ax.xaxis.set_major_formatter(mdates.ConciseDateFormatter(locator))  # type: ignore[no-untyped-call]
    ax.set_xlabel("run start (UTC); labels: run ids")
    ax.set_ylabel(f"{param} [{unit}]")
    ax.set_title(f"{param} of station {station}")
    ax.grid(True, alpha=0.3)
    ax.legend()
    fig.tight_layout()
    return fig
