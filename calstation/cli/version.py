"""``calstation version``."""

from __future__ import annotations

import typer


def register(app: typer.Typer) -> None:
    """Add the ``version`` command."""

    @app.command("version")
    def version() -> None:
        """Print calstation's version."""
        from calstation import __version__

        typer.echo(f"calstation {__version__}")
