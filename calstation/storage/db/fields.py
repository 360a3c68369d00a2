"""The text people type that a run stores: the operator's name and the unit's serial, checked
once for every front end (``calstation run``, the web station, its API) against what the
database's columns hold (``run.operator``, ``run.unit_serial``: ``String(100)``).

A value is normalised (Unicode NFC, surrounding spaces removed) and refused, in one sentence,
when it is too long for its column or holds a character no name or serial has: a control
character (ESC would repaint a terminal that lists it), a line break, a format or private-use
character, a space other than U+0020. PostgreSQL refuses a value longer than its column, so the
same limit everywhere keeps a SQLite station and a PostgreSQL fleet alike.
"""

from __future__ import annotations

import unicodedata

from calstation.errors import TextError
from calstation.storage.db.models import Run

NAME_LENGTH: int = Run.__table__.c.operator.type.length  # type: ignore[attr-defined]
"""The most characters an operator's name holds (the ``run.operator`` column)."""

SERIAL_LENGTH: int = Run.__table__.c.unit_serial.type.length  # type: ignore[attr-defined]
"""The most characters a unit serial holds (the ``run.unit_serial`` column)."""

_FORBIDDEN = {"Cc", "Cf", "Cs", "Co", "Cn", "Zl", "Zp"}
_NAME_PUNCTUATION = " .'’-_,()@"
_SERIAL_PUNCTUATION = " ._:/#+-"


def _shown(ch: str) -> str:
    return f"U+{ord(ch):04X}" + (f" ({unicodedata.name(ch)})" if unicodedata.name(ch, "") else "")


def printable(value: str) -> str:
    """``value`` (NFC) if it has no control, format, private-use, unassigned or surrogate
    character and no line break; spaces other than U+0020 are refused too (:class:`TextError`
    naming the character)."""
    value = unicodedata.normalize("NFC", value)
    for ch in value:
        category = unicodedata.category(ch)
        if category in _FORBIDDEN or (category == "Zs" and ch != " "):
            raise TextError(f"character {_shown(ch)} is not allowed here")
    return value


def _bounded(value: str, what: str, length: int) -> str:
    if len(value) > length:
        raise TextError(f"{what} is {len(value)} characters long; at most {length} are stored")
    return value


def operator_name(value: str) -> str:
    """An operator's name as stored: 1 to :data:`NAME_LENGTH` characters, letters of any
    script, digits, spaces and ``.'’-_,()@``. :class:`TextError` says what is wrong."""
    value = _bounded(value.strip(), "the operator's name", NAME_LENGTH)
    if not value:
        raise TextError("enter the operator's name")
    try:
        value = printable(value)
    except TextError as exc:
        raise TextError(f"the operator's name: {exc}") from None
    for ch in value:
        if not (ch.isalnum() or ch in _NAME_PUNCTUATION or unicodedata.category(ch)[0] == "M"):
            raise TextError(f"the operator's name: {_shown(ch)} is not allowed in a name "
                            f"(letters, digits, spaces and {_NAME_PUNCTUATION.strip()})")
    return value


def unit_serial(value: str | None) -> str | None:
    """A unit serial as stored: None for none (or an empty one); else up to
    :data:`SERIAL_LENGTH` characters, starting with a letter or digit, then letters, digits,
    spaces and ``._:/#+-`` (ASCII). :class:`TextError` says what is wrong."""
    if value is None:
        return None
    value = _bounded(value.strip(), "the unit serial", SERIAL_LENGTH)
    if not value:
        return None
    for i, ch in enumerate(value):
        ok = ch.isascii() and (ch.isalnum() or (i > 0 and ch in _SERIAL_PUNCTUATION))
        if not ok:
            raise TextError(f"the unit serial: {_shown(ch)} is not allowed in a serial (ASCII "
                            f"letters and digits first, then also {_SERIAL_PUNCTUATION.strip()} "
                            "and spaces)")
    return value
