"""``calstation db``: where the run database is, and migrating it."""

from __future__ import annotations

import typer

DbOption = typer.Option(
    None,
    "--db",
    help="Database URL (default: $CALSTATION_DB_URL, else SQLite in $CALSTATION_HOME).",
    show_default=False,
)


def register(app: typer.Typer) -> None:
    """Add the ``db`` command group."""
    db_app = typer.Typer(help="The run database: location and migrations.", no_args_is_help=True)
    app.add_typer(db_app, name="db")

    @db_app.command("upgrade")
    def upgrade(
        db: str | None = DbOption,
        revision: str = typer.Option("head", help="Target revision."),
    ) -> None:
        """Apply the database migrations (creates the database if needed)."""
        from calstation.storage.db import Database

        database = Database(db)
        before, after = database.upgrade(revision)
        typer.echo(f"{database!r}: {before or 'empty'} → {after}")
        database.dispose()

    @db_app.command("downgrade")
    def downgrade(
        revision: str = typer.Argument(..., help="Target revision (see `alembic history`)."),
        db: str | None = DbOption,
    ) -> None:
        """Undo migrations down to REVISION, keeping every row (refused where rows would go)."""
        from calstation.storage.db import Database

        database = Database(db)
        before, after = database.downgrade(revision)
        typer.echo(f"{database!r}: {before or 'empty'} → {after or 'empty'}")
        database.dispose()

    @db_app.command("info")
    def info(db: str | None = DbOption) -> None:
        """Print the database URL and its revision."""
        from calstation.storage.db import Database, head_revision, known_revisions

        database = Database(db, read_only=True)
        current = database.current_revision()
        head = head_revision()
        if current == head:
            state = "up to date"
        elif current is not None and current not in known_revisions():
            state = "unknown to this calstation: migrated by a newer version"
        else:
            state = "needs `calstation db upgrade`"
        typer.echo(f"url:      {database.engine.url.render_as_string(hide_password=True)}")
        typer.echo(f"revision: {current or 'none'} (head {head}, {state})")
        database.dispose()
