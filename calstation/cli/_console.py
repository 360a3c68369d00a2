"""Shared helpers of the CLI modules (not a command module: its name starts with ``_``)."""

from __future__ import annotations

import unicodedata
from typing import Any

from rich.console import Console


def wide_console() -> Console:
    """A console for tables; 140 columns wide when the output is not a terminal (pipes, logs).
    Stored text (operators', recipes' and stations' names) is printed as it is: no ``:name:``
    emoji codes."""
    console = Console(emoji=False)
    return console if console.is_terminal else Console(width=140, emoji=False)


_UNSAFE = {"Cc", "Cf", "Cs", "Co", "Zl", "Zp"}


# Any: the data comes back in its own shape (a str, or lists and mappings of stored values)
def terminal_safe(data: Any) -> Any:
    """``data`` (strings, and lists and mappings of them) with every control or format
    character (ESC, a line break, a bidirectional override) shown as its escape (``\\x1b``):
    text stored by others (an operator's name, a serial, an error) can never move the cursor,
    recolour or clear the terminal that lists it."""
    if isinstance(data, str):
        if not any(unicodedata.category(ch) in _UNSAFE for ch in data):
            return data
        return "".join(ch.encode("unicode_escape").decode("ascii")
                       if unicodedata.category(ch) in _UNSAFE else ch for ch in data)
    if isinstance(data, dict):
        return {k: terminal_safe(v) for k, v in data.items()}
    if isinstance(data, list | tuple):
        return type(data)(terminal_safe(v) for v in data)
    return data
