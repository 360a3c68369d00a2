"""``calstation upload``: a run's files copied to the fleet's shared store (docs/fleet.md)."""

from __future__ import annotations

import typer

DB_HELP = "Database URL (default: $CALSTATION_DB_URL or SQLite in $CALSTATION_HOME)."


def register(app: typer.Typer) -> None:
    """Add the ``upload`` command."""

    @app.command("upload")
    def upload_cmd(
        run_ids: list[int] = typer.Argument(None, help="Runs to upload (default: with "
                                            "--pending, every finished run not uploaded yet).",
                                            show_default=False),
        pending: bool = typer.Option(False, "--pending", help="Every finished run with a file "
                                     "that has no shared copy yet."),
        station: str = typer.Option(None, "--station", help="With --pending: this station's."),
        to: str = typer.Option(None, "--to", help="The shared store (an fsspec URL or folder; "
                               "default $CALSTATION_RECORDINGS_URL)."),
        db: str = typer.Option(None, "--db", help=DB_HELP),
    ) -> None:
        """Copy runs' recordings and reports to the shared store, each checked (sha256) and its
        location stored. Resumable: what is there already is not sent again; the local copies
        are never touched. Exit 1 when a file could not be sent."""
        from calstation.errors import FleetError
        from calstation.storage.db import open_database
        from calstation.storage.uploads import (
            STORE_ENV,
            check_store,
            recordings_store,
            runs_to_upload,
            upload_run,
        )

        store = to or recordings_store()
        if store is None:
            raise FleetError(f"no shared store: give --to URL or set {STORE_ENV}")
        if not run_ids and not pending:
            raise FleetError("name the runs to upload, or give --pending")
        store = check_store(store)
        database = open_database(db, existing=True)
        failed = 0
        try:
            todo = list(run_ids or []) or runs_to_upload(database, station)
            for run_id in todo:
                done = upload_run(database, run_id, store, lambda m: typer.echo(f"  {m}"))
                typer.echo(f"run {run_id}: {len(done.sent)} sent, {len(done.present)} there "
                           f"already, {len(done.failed)} not sent")
                failed += len(done.failed)
                if done.unanswered:
                    typer.echo(f"stopped: {done.unanswered}", err=True)
                    break
        finally:
            database.dispose()
        if failed:
            raise typer.Exit(1)
