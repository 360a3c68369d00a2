"""The ``calstation`` command line. Thin: parse, validate, call the library.

Each command group lives in its own module of this package with a ``register(app)`` function
(found by :func:`_build`, so adding a module adds its commands); heavy imports (open3d)
happen inside the commands so that ``calstation --help`` stays instant. Plugins add commands
through the ``calstation_register_commands`` hook.
"""

from __future__ import annotations

import atexit
import gc
import importlib
import pkgutil
import sys

import typer

from calstation.errors import CalstationError

app = typer.Typer(
    name="calstation",
    help="Calibrate a static line-scanning lidar against a motorised turntable.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


OPTIONAL_PORT_OPTIONS = {"--foxglove": "8765"}
"""Options whose value may be left out (``--foxglove`` alone means its default port)."""


def optional_port(argv: list[str]) -> list[str]:
    """``argv`` with the default value inserted after an option of
    :data:`OPTIONAL_PORT_OPTIONS` that is not followed by a number (click has no optional
    option values through typer)."""
    out: list[str] = []
    for i, arg in enumerate(argv):
        out.append(arg)
        default = OPTIONAL_PORT_OPTIONS.get(arg)
        if default is not None and (i + 1 == len(argv) or not argv[i + 1].isdigit()):
            out.append(default)
    return out


def _build() -> None:
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        importlib.import_module(f"{__name__}.{info.name}").register(app)
    from calstation import plugins

    plugins.register_commands(app)


def command_group(cli: typer.Typer, name: str, help: str) -> typer.Typer:
    """The sub-app ``calstation NAME`` of ``cli``, created with ``help`` by whichever caller comes
    first (several plugins add commands to one group, e.g. ``calstation emulate``)."""
    for group in cli.registered_groups:
        if group.name == name and group.typer_instance is not None:
            return group.typer_instance
    sub = typer.Typer(help=help, no_args_is_help=True)
    cli.add_typer(sub, name=name)
    return sub


QUICK_COMMANDS = frozenset({"history", "show", "recipes", "version", "plugins"})
"""Commands (and groups) that read, print and end within a second. They run with Python's cyclic
garbage collector off, as ``--help`` does: the collections that their imports trigger, and the
interpreter's last ones over every imported module at exit, took a quarter of their time and free
nothing that the exit does not (docs/performance.md, *Start-up*). Every other command, the
plugins' included, turns it back on before it starts."""

_collector = {"was_on": True}
"""Whether the collector was on when :func:`main` was called (it is left as it was found)."""


def _print_version(asked: bool) -> None:
    """``--version``: print calstation's version and end."""
    if asked:
        from calstation import __version__

        typer.echo(f"calstation {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    ctx: typer.Context,
    version: bool = typer.Option(
        False, "--version", is_eager=True, callback=_print_version,
        help="Print calstation's version and exit.",
    ),
) -> None:
    """Calibrate a static line-scanning lidar against a motorised turntable."""
    if ctx.invoked_subcommand not in QUICK_COMMANDS and _collector["was_on"]:
        gc.enable()


def main(argv: list[str] | None = None) -> None:
    """Entry point of the ``calstation`` script (``argv`` from the command line when None):
    errors print as one clear message, exit code 2."""
    _collector["was_on"] = gc.isenabled()
    gc.disable()
    try:
        _run(sys.argv[1:] if argv is None else argv)
    finally:
        quick = not gc.isenabled()
        if _collector["was_on"]:
            gc.enable()
        if quick and argv is None:
            # The process ends with the command: what the command leaves is freed by the exit
            # without a last search for reference cycles among every imported module's objects.
            atexit.register(gc.freeze)


def _run(argv: list[str]) -> None:
    from rich.console import Console

    err = Console(stderr=True)
    try:
        _build()
        app(args=optional_port(argv))
    except CalstationError as exc:
        from rich.markup import escape

        flag = f"--{exc.option.replace('_', '-')}: " if exc.option else ""
        err.print(f"[bold red]error:[/] {escape(flag + str(exc))}", highlight=False,
                  soft_wrap=True)
        sys.exit(getattr(exc, "exit_code", 2))
    except KeyboardInterrupt:
        err.print("[bold yellow]interrupted[/]")
        sys.exit(130)
