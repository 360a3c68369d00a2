"""``calstation plugins``: every loaded plugin, the hooks it implements, drivers and strategies."""

from __future__ import annotations

import json

import typer

from calstation.cli._console import wide_console


def register(app: typer.Typer) -> None:
    """Add the ``plugins`` command."""

    @app.command("plugins")
    def plugins_command(
        as_json: bool = typer.Option(False, "--json", help="Print JSON instead of tables."),
    ) -> None:
        """List each plugin and its hooks, and the drivers and strategies they register."""
        from rich.table import Table

        from calstation import plugins

        infos = plugins.plugin_report()
        drivers = plugins.drivers()
        strategies = plugins.strategies()
        if as_json:
            out = {
                "plugins": [
                    {"name": i.name, "source": i.source, "version": i.version,
                     "hooks": list(i.hooks)}
                    for i in infos
                ],
                "drivers": [
                    {"kind": e.kind, "name": e.name, "plugin": e.plugin}
                    for e in sorted(drivers.values(), key=lambda e: (e.kind, e.name))
                ],
                "strategies": [
                    {"name": name, "fixture": getattr(s, "fixture", None),
                     "plugin": plugins.strategy_plugin(name),
                     "options": _options_schema(s)}
                    for name, s in sorted(strategies.items())
                ],
            }
            typer.echo(json.dumps(out, indent=2))
            return
        console = wide_console()
        table = Table(title="Plugins")
        table.add_column("plugin")
        table.add_column("source")
        table.add_column("hooks")
        for i in infos:
            source = i.source + (f" {i.version}" if i.version else "")
            table.add_row(i.name, source, "\n".join(i.hooks) or "(none)")
        console.print(table)
        dtable = Table(title="Drivers")
        for col in ("kind", "name", "plugin"):
            dtable.add_column(col)
        for e in sorted(drivers.values(), key=lambda e: (e.kind, e.name)):
            dtable.add_row(e.kind, e.name, e.plugin)
        console.print(dtable)
        stable = Table(title="Fine-tuning strategies")
        stable.add_column("name")
        stable.add_column("fixture")
        stable.add_column("plugin")
        stable.add_column("options")
        for name, s in sorted(strategies.items()):
            options = _options_schema(s)
            stable.add_row(name, str(getattr(s, "fixture", "")), plugins.strategy_plugin(name),
                           "(unchecked)" if options is None else ", ".join(options) or "(none)")
        console.print(stable)


def _options_schema(strategy: object) -> list[str] | None:
    """The option names of a strategy's ``options_model`` (None: it declares none)."""
    from calstation.plugins.cost_strategies import options_model_of

    model = options_model_of(strategy)
    return None if model is None else list(model.model_fields)
