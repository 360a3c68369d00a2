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
            None, "--recipes",
            help="Folder of the recipe files the operator chooses from (default: ./recipes, "
            "else the recipes calstation ships).", show_default=False,
        ),
        db: str = typer.Option(
            None, "--db", help="Database URL (default: $CALSTATION_DB_URL or SQLite)."
        ),
        data_dir: Path = typer.Option(
            None, "--data-dir",
            help="Folder for run folders (default: $CALSTATION_HOME); runs go to "
            "DATA_DIR/runs/DATABASE_ID/N/.",
        ),
        token_file: Path = typer.Option(
            None, "--token-file",
            help="File whose first line is the station token (or set $CALSTATION_TOKEN). "
                 "Rewriting the file changes the token and ends every session.",
        ),
        allow_host: list[str] = typer.Option(
            [], "--allow-host",
            help="A host name browsers use to reach the station (its DNS name; *.domain for "
                 "every name under it). Repeatable. Requests naming any other host are refused.",
        ),
        tls_cert: Path = typer.Option(
            None, "--tls-cert", help="Serve HTTPS with this certificate (PEM; with --tls-key)."
        ),
        tls_key: Path = typer.Option(
            None, "--tls-key", help="The certificate's private key (PEM)."
        ),
    ) -> None:
        """Serve the web station: run recipes from the browser, see reports, history and trends.

        One run at a time; a run goes on when the browser is closed. Ctrl-C stops the server
        (a run in progress is aborted and the turntable stopped). See docs/security.md for
        serving on a plant network.
        """
        import uvicorn

        from calstation.errors import CalstationError
        from calstation.storage.db import calstation_home, open_database
        from calstation.web.app import create_app
        from calstation.web.hosts import check_allowed_host, is_local_host
        from calstation.web.tokens import TokenSource

        if (tls_cert is None) != (tls_key is None):
            raise CalstationError("--tls-cert and --tls-key go together")
        for path in (tls_cert, tls_key):
            if path is not None and not path.is_file():
                raise CalstationError(f"{path}: no such file")
        try:
            allowed = [check_allowed_host(h) for h in allow_host]
        except ValueError as exc:
            raise CalstationError(str(exc)) from exc
        token = TokenSource.from_environment(token_file)
        database = open_database(db)
        folder = (data_dir or calstation_home()).expanduser().resolve()
        if recipes is None:
            from calstation.recipes import SHIPPED_DIR

            recipes = Path("recipes") if Path("recipes").is_dir() else SHIPPED_DIR
        tls = tls_cert is not None
        application = create_app(database, data_dir=folder, recipes_dir=recipes.resolve(),
                                 host=host, token=token, allow_hosts=allowed, tls=tls)
        _log_to_stderr()
        shown = f"[{host}]" if ":" in host else host
        scheme = "https" if tls else "http"
        typer.echo(f"calstation station: {scheme}://{shown}:{port}/  (recipes from {recipes}, "
                   f"runs in {folder}/runs; Ctrl-C to stop)", err=True)
        if not tls and not is_local_host(host):
            typer.echo("warning: served without TLS on a network address, the station token "
                       "crosses the network in clear text (see --tls-cert, docs/security.md)",
                       err=True)
        try:
            # live pages keep an event stream open: do not wait for browsers to hang up.
            # No proxy headers: uvicorn would otherwise take X-Forwarded-For/-Proto from any
            # local process as the client's address and scheme (escaping the per-client
            # limits, forging the logged address); the station is served without a proxy.
            uvicorn.run(application, host=host, port=port, log_level="warning",
                        timeout_graceful_shutdown=3, server_header=False, proxy_headers=False,
                        ssl_certfile=str(tls_cert) if tls_cert else None,
                        ssl_keyfile=str(tls_key) if tls_key else None)
        finally:
            database.dispose()


def _log_to_stderr() -> None:
    """The station's refusals and logins, with the time, on stderr."""
    import logging

    logger = logging.getLogger("calstation.web")
    if not logger.handlers:
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
        logger.addHandler(handler)
        logger.setLevel(logging.INFO)
        logger.propagate = False
