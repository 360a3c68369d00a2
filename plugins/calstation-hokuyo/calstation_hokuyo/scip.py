"""SCIP 2.0 wire format: sums, value encodings and reply framing (Hokuyo C-42-03320B).

Pure functions over bytes, shared by the driver (:mod:`calstation_hokuyo.driver`) and the emulator
(:mod:`calstation_hokuyo.emulator`), so both sides of a test speak exactly the same bytes.

- Request: ``COMMAND + parameters [+ ";" + string] + LF``.
- Reply: the echoed request + LF, ``status(2) + sum`` + LF, data lines each ``data + sum`` + LF,
  and one more LF (every reply ends in LF LF).
- Sum: ``chr((sum(bytes) & 0x3F) + 0x30)``; for ``KEY:VALUE;S`` lines the ``;`` is not summed.
- Values: 2, 3 or 4 characters of 6 bits each, most significant first, each char = bits + 0x30.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from calstation.errors import DeviceTimeout, DriverError

LF = b"\n"
DATA_LINE_CHARS = 64
"""A data line carries at most 64 characters before its sum."""

TIMESTAMP_WRAP_MS = 1 << 24
"""The sensor's millisecond timestamp is 24 bits wide (it wraps after ≈ 4.66 h)."""

STATUS_MEANINGS: dict[str, str] = {
    "00": "command accepted",
    "01": "parameter 1 is not a number / laser malfunction (BM)",
    "02": "parameter 2 is not a number / already in that state",
    "03": "parameter 3 is not a number / not in time-adjust mode",
    "04": "end step out of range",
    "05": "end step smaller than start step",
    "06": "scan interval is not a number",
    "07": "number of scans is not a number",
    "0A": "unable to create transmission data or reply packet",
    "0B": "buffer shortage",
    "0C": "input error: command too long or malformed",
    "0D": "undefined command",
    "0E": "command not allowed in this state",
    "0F": "unknown parameter",
    "0G": "communication error",
    "0H": "parameter out of range",
    "0I": "sensor busy",
    "10": "laser is off",
    "99": "scan data follows",
}
"""What a reply status means; statuses 50–98 are hardware errors."""


class HokuyoError(DriverError):
    """A Hokuyo SCIP 2.0 device could not be talked to or reported an error."""


class ScipChecksumError(HokuyoError):
    """A reply line's sum does not match its data (a corrupted byte on the wire)."""


class ScipProtocolError(HokuyoError):
    """A reply does not have the SCIP 2.0 shape (wrong echo, missing lines, bad characters)."""


class ScipStatusError(HokuyoError):
    """The device answered a command with an error status."""

    def __init__(self, command: str, status: str) -> None:
        self.command = command
        self.status = status
        meaning = STATUS_MEANINGS.get(status)
        if meaning is None and status.isdigit() and 50 <= int(status) <= 98:
            meaning = "hardware error"
        super().__init__(
            f"Hokuyo answered {command!r} with status {status} ({meaning or 'unknown status'})"
        )


class ScipTimeout(HokuyoError, DeviceTimeout):
    """The device did not finish a reply in time."""


# --- sums and values -----------------------------------------------------------------------------
def checksum(data: bytes) -> bytes:
    """The one-character SCIP sum of ``data``: ``(sum & 0x3F) + 0x30``."""
    return bytes(((sum(data) & 0x3F) + 0x30,))


def encode_value(value: int, chars: int) -> bytes:
    """Encode a non-negative integer in ``chars`` (2, 3 or 4) SCIP characters."""
    if chars not in (2, 3, 4):
        raise ValueError(f"SCIP values have 2, 3 or 4 characters, not {chars}")
    value = int(value)
    if not 0 <= value < 1 << (6 * chars):
        raise ValueError(f"{value} does not fit in {chars} SCIP characters")
    return bytes(((value >> (6 * (chars - 1 - i))) & 0x3F) + 0x30 for i in range(chars))


def encode_values(values: NDArray[np.integer] | list[int], chars: int) -> bytes:
    """Encode an array of non-negative integers, ``chars`` characters each, concatenated."""
    arr = np.asarray(values, dtype=np.int64)
    if arr.size and (arr.min() < 0 or arr.max() >= 1 << (6 * chars)):
        raise ValueError(f"values out of range for {chars} SCIP characters")
    shifts = 6 * np.arange(chars - 1, -1, -1, dtype=np.int64)
    digits = ((arr[:, None] >> shifts[None, :]) & 0x3F) + 0x30
    return digits.astype(np.uint8).tobytes()


def decode_value(data: bytes) -> int:
    """Decode one 2-, 3- or 4-character SCIP value."""
    return int(decode_values(data, len(data))[0])


def decode_values(data: bytes, chars: int) -> NDArray[np.int64]:
    """Decode concatenated ``chars``-character values (sums already stripped) into an array."""
    if chars not in (2, 3, 4):
        raise ValueError(f"SCIP values have 2, 3 or 4 characters, not {chars}")
    if len(data) % chars:
        raise ScipProtocolError(
            f"{len(data)} data characters is not a whole number of {chars}-character values"
        )
    raw = np.frombuffer(data, dtype=np.uint8).astype(np.int64) - 0x30
    if raw.size and (raw.min() < 0 or raw.max() > 0x3F):
        raise ScipProtocolError("data contains characters outside the SCIP range 0x30–0x6F")
    digits = raw.reshape(-1, chars)
    out = np.zeros(len(digits), dtype=np.int64)
    for i in range(chars):
        out = (out << 6) | digits[:, i]
    return out


# --- lines ---------------------------------------------------------------------------------------
def with_sum(data: bytes) -> bytes:
    """A data line: ``data + sum + LF``."""
    return data + checksum(data) + LF


def kv_line(key: str, value: str) -> bytes:
    """A ``KEY:VALUE;S`` line of VV/PP/II (the ``;`` is not summed), with its LF."""
    body = f"{key}:{value}".encode("ascii")
    return body + b";" + checksum(body) + LF


def data_lines(payload: bytes) -> bytes:
    """Split encoded scan data into lines of at most 64 characters, each with its sum and LF."""
    return b"".join(
        with_sum(payload[i : i + DATA_LINE_CHARS])
        for i in range(0, len(payload), DATA_LINE_CHARS)
    )


def reply(echo: bytes, status: str, body: bytes = b"") -> bytes:
    """A whole reply: echo LF, status+sum LF, ``body`` (already framed lines), final LF."""
    st = status.encode("ascii")
    return echo + LF + st + checksum(st) + LF + body + LF


# --- parsing -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Reply:
    """One parsed reply: the echo (without LF), the status, and the data lines (sums checked and
    stripped)."""

    echo: bytes
    status: str
    lines: list[bytes] = field(default_factory=list)

    def payload(self) -> bytes:
        """Data lines joined (a value may be split across two lines)."""
        return b"".join(self.lines)

    def fields(self) -> dict[str, str]:
        """``KEY:VALUE`` lines of VV/PP/II as a mapping."""
        out: dict[str, str] = {}
        for line in self.lines:
            key, sep, value = line.decode("ascii", "replace").partition(":")
            if sep:
                out[key] = value
        return out


def check_line(line: bytes, command: str = "", kv: bool = False) -> bytes:
    """Verify the sum of one received line (without LF) and return its data.

    ``kv``: a ``KEY:VALUE;S`` line of VV/PP/II (the ``;`` is not summed and is stripped).
    Raises :class:`ScipChecksumError` naming the line.
    """
    if len(line) < 2:
        raise ScipProtocolError(f"reply to {command!r}: line {line!r} is too short to carry a sum")
    data, got = line[:-1], line[-1:]
    if kv and data.endswith(b";"):
        data = data[:-1]
    if checksum(data) == got:
        return data
    raise ScipChecksumError(
        f"reply to {command!r}: bad sum on line {line!r} (expected "
        f"{checksum(data).decode('ascii', 'replace')!r}, got {got.decode('ascii', 'replace')!r})"
    )


def parse_reply(block: bytes, command: str = "", kv: bool = False) -> Reply:
    """Parse one reply block (everything up to and including the final LF LF).

    Checks every sum (``kv``: data lines are ``KEY:VALUE;S`` lines, as in VV/PP/II). The status
    line of SCIP 2.0 carries a sum; a bare 2-character status (some
    firmware answers ``QT`` during streaming that way) is accepted too.
    """
    text = block[:-1] if block.endswith(LF + LF) else block
    parts = text.split(LF)
    if parts and parts[-1] == b"":
        parts.pop()
    if len(parts) < 2:
        raise ScipProtocolError(f"reply to {command!r} has no status line: {block!r}")
    echo, status_line, *rest = parts
    if len(status_line) == 3:
        status = check_line(status_line, command).decode("ascii", "replace")
    elif len(status_line) == 2:
        status = status_line.decode("ascii", "replace")
    else:
        raise ScipProtocolError(f"reply to {command!r}: malformed status line {status_line!r}")
    return Reply(echo=echo, status=status, lines=[check_line(r, command, kv) for r in rest])


def scan_payload(reply_: Reply, chars: int) -> tuple[int, NDArray[np.int64]]:
    """(sensor timestamp ms, values) of a GD/GS/MD/MS scan reply; ``chars`` = 3 (D) or 2 (S)."""
    payload = reply_.payload()
    if len(payload) < 4:
        raise ScipProtocolError("scan reply carries no timestamp")
    return decode_value(payload[:4]), decode_values(payload[4:], chars)
