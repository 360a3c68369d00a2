"""``calstation serve``: the web station (operator page, run reports, history, trends)."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    """Add the ``serve`` command."""

    @app.command("serve")
    def serve(
        host: str = typer.Option(
            "127.0.0.1", "--host",
            help="Address to listen on. Any non-loopback address needs the station token.",
        ),
        port: int = typer.Option(8470, "--port", help="TCP port."),
        recipes: Path = typer.Option(
            Path("recipes"), "--recipes",
            help="Folder of the recipe files the operator chooses from.",
        ),
        db: str = typer.Option(
            None, "--db", help="Database URL (default: $CALSTATION_DB_URL or SQLite)."
        ),
        data_dir: Path = typer.Option(
            None, "--data-dir",
            help="Folder for run folders (default: $CALSTATION_HOME); runs go to DATA_DIR/runs/N/.",
        ),
        token_file: Path = typer.Option(
            None, "--token-file",
            help="File whose first line is the station token (or set $CALSTATION_TOKEN).",
        ),
    ) -> None:
        """Serve the web station: run recipes from the browser, see reports, history and trends.

        One run at a time; a run goes on when the browser is closed. Ctrl-C stops the server
        (a run in progress is aborted and the turntable stopped).
        """
        import uvicorn

        from calstation.storage.db import calstation_home, open_database
        from calstation.web.app import create_app
        from calstation.web.security import load_token

        token = load_token(token_file)
        database = open_database(db)
        folder = (data_dir or calstation_home()).expanduser().resolve()
        application = create_app(database, data_dir=folder, recipes_dir=recipes.resolve(),
                                 host=host, token=token)
        shown = f"[{host}]" if ":" in host else host
        typer.echo(f"calstation station: http://{shown}:{port}/  (recipes from {recipes}, "
                   f"runs in {folder}/runs; Ctrl-C to stop)", err=True)
        try:
            # live pages keep an event stream open: do not wait for browsers to hang up
            uvicorn.run(application, host=host, port=port, log_level="warning",
                        timeout_graceful_shutdown=3)
        finally:
            database.dispose()
