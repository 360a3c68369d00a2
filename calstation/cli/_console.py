"""Shared helpers of the CLI modules (not a command module: its name starts with ``_``)."""

from __future__ import annotations

from rich.console import Console


def wide_console() -> Console:
    """A console for tables; 140 columns wide when the output is not a terminal (pipes, logs).
    Stored text (operators', recipes' and stations' names) is printed as it is: no ``:name:``
    emoji codes."""
    console = Console(emoji=False)
    return console if console.is_terminal else Console(width=140, emoji=False)
