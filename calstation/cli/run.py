"""``calstation run`` and ``calstation resume``: the operator's guided run."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import typer

if TYPE_CHECKING:
    from calstation.storage.db import Database

EXIT_FAILED = 1
EXIT_ABORTED = 3


def _exit_code(status: str) -> int:
    from calstation.storage.db.models import RunStatus

    codes: dict[str, int] = {RunStatus.PASSED: 0, RunStatus.FAILED: EXIT_FAILED}
    return codes.get(status, EXIT_ABORTED)


def _say_report(database: Database, run_id: int) -> None:
    """Where the run's report is (``report.html`` in its folder), when it was written."""
    from rich.console import Console
    from rich.markup import escape

    from calstation.storage.db import Run

    with database.session("reading the run", read_only=True) as s:
        run = s.get(Run, run_id)
        folder = Path(run.data_dir) if run is not None else None
    if folder is not None and (folder / "report.html").is_file():
        Console().print(f"report: {escape(str(folder / 'report.html'))}", highlight=False,
                        soft_wrap=True)


@contextmanager
def _live_view(port: int | None) -> Iterator[None]:
    """The live view on ``port`` for the duration of the block (nothing when None)."""
    if port is None:
        yield
        return
    from rich.console import Console

    from calstation.recordings.liveview import start_live_view

    view = start_live_view(port)
    Console(stderr=True).print(f"live view: open [bold]{view.url}[/] in Foxglove")
    try:
        yield
    finally:
        view.close()


def register(app: typer.Typer) -> None:
    """Add the ``run`` and ``resume`` commands."""

    @app.command("run")
    def run(
        recipe: Path = typer.Argument(..., help="Recipe YAML file."),
        yes: bool = typer.Option(
            False, "--yes", "-y",
            help="Unattended: never ask; fixtures are placed by the fixture-placed hook "
            "(the simulator places them itself).",
        ),
        operator: str = typer.Option(
            None, "--operator", help="Operator name (default: $CALSTATION_OPERATOR or login)."
        ),
        serial: str = typer.Option(
            None, "--serial",
            help="Serial number of the unit calibrated (default: the one the lidar reports).",
        ),
        db: str = typer.Option(
            None, "--db", help="Database URL (default: $CALSTATION_DB_URL or SQLite)."
        ),
        data_dir: Path = typer.Option(
            None, "--data-dir",
            help="Folder for run folders (default: $CALSTATION_HOME); "
            "recordings go to DATA_DIR/runs/DATABASE_ID/RUN_ID/.",
        ),
        foxglove: int | None = typer.Option(
            None, "--foxglove", metavar="[PORT]",
            help="Stream every scan live over the Foxglove WebSocket protocol on "
            "127.0.0.1:PORT (default 8765); open ws://127.0.0.1:PORT in Foxglove.",
        ),
    ) -> None:
        """Run a recipe on the station: guided (prompts) or unattended (--yes).

        Exit code 0 when the run passed, 1 when it failed, 3 when it was aborted, 4 when another
        run holds the station.
        """
        from calstation.cli._operator import ConsoleOperator
        from calstation.recipes import load_recipe
        from calstation.station.operator import default_operator
        from calstation.station.runs import start_run
        from calstation.storage.db import open_database

        loaded = load_recipe(recipe)
        database = open_database(db)
        try:
            with _live_view(foxglove):
                run_id, status = start_run(
                    loaded, database, ConsoleOperator(unattended=yes),
                    operator=operator or default_operator(), data_dir=data_dir, serial=serial,
                )
            _say_report(database, run_id)
        finally:
            database.dispose()
        raise typer.Exit(_exit_code(status))

    @app.command("resume")
    def resume(
        run_id: int = typer.Argument(..., help="The run to continue."),
        yes: bool = typer.Option(False, "--yes", "-y", help="Unattended (see `run`)."),
        db: str = typer.Option(None, "--db", help="Database URL."),
        force: bool = typer.Option(
            False, "--force",
            help="Resume even if the run's recorded process still seems alive (or ran on "
            "another host).",
        ),
        foxglove: int | None = typer.Option(
            None, "--foxglove", metavar="[PORT]",
            help="Stream every scan live over the Foxglove WebSocket protocol on "
            "127.0.0.1:PORT (default 8765); open ws://127.0.0.1:PORT in Foxglove.",
        ),
    ) -> None:
        """Continue a crashed or failed run at its first unfinished step, re-using its recordings.

        Exit code 0 when the run passed, 1 when it failed, 3 when it was aborted, 4 when another
        run holds the station.
        """
        from calstation.cli._operator import ConsoleOperator
        from calstation.station.runs import resume_run
        from calstation.storage.db import open_database

        database = open_database(db, existing=True)
        try:
            with _live_view(foxglove):
                status = resume_run(
                    run_id, database, ConsoleOperator(unattended=yes), force=force
                )
            _say_report(database, run_id)
        finally:
            database.dispose()
        raise typer.Exit(_exit_code(status))
