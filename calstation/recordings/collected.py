"""What the reader collects from a recording before it builds the :class:`Recording`.

:class:`Collected` gathers the messages' parts one message at a time (the version-2 decoding in
:mod:`calstation.recordings.reader`, the version-1 one in :mod:`calstation.recordings.v1`);
:class:`Lines` holds the per-line and per-point arrays both versions assemble from them. Both are
the reader's working state, not part of the public API.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calstation.drivers import TurntableStatus

Buffer = bytes | memoryview
"""Packed array bytes as a message holds them (a view into the file's bytes where possible)."""


@dataclass
class Collected:
    """What the reader gathered, message by message, before assembling the arrays.

    Version 1 fills the line lists from one JSON message per line; version 2 from a
    ``LidarLineTiming`` (timing lists) and a ``LaserScan`` (``scan_*`` lists) per line, paired
    in order when assembling.
    """

    metadata: dict[str, dict[str, Any]] = field(default_factory=dict)  # Any: decoded JSON
    attachments: dict[str, bytes] = field(default_factory=dict)
    v2: bool | None = None
    line_ts: list[int] = field(default_factory=list)
    line_period: list[float] = field(default_factory=list)
    line_count: list[int] = field(default_factory=list)
    line_offsets: list[Buffer | None] = field(default_factory=list)
    azimuth: list[Buffer] = field(default_factory=list)
    range_: list[Buffer] = field(default_factory=list)
    valid: list[Buffer] = field(default_factory=list)
    invalid_range: list[Buffer] = field(default_factory=list)
    intensity: list[Buffer | None] = field(default_factory=list)
    scan_ts: list[int] = field(default_factory=list)
    enc_t: list[int] = field(default_factory=list)
    enc_c: list[int] = field(default_factory=list)
    enc_t_buf: list[Buffer] = field(default_factory=list)
    enc_c_buf: list[Buffer] = field(default_factory=list)
    turntable: list[TurntableStatus] = field(default_factory=list)
    clean: bool = False
    problem: str = ""
    timing_parts: list[tuple[Any, ...]] = field(default_factory=list)  # Any: the parts' types
    """version 2: each ``LidarLineTiming``'s parts, as one tuple (``line_*``, ``azimuth``,
    ``valid``, ``invalid_range``)"""
    scan_parts: list[tuple[Any, ...]] = field(default_factory=list)
    """version 2: each ``LaserScan``'s parts, as one tuple (``scan_ts``, ``range_``,
    ``intensity``)"""

    def spread_parts(self) -> None:
        """Spread the version-2 messages' tuples over the line lists, field by field (one
        append per message while reading, one transposition here)."""
        if self.timing_parts:
            (self.line_ts, self.line_period, self.line_count, self.azimuth, self.valid,
             self.line_offsets, self.invalid_range) = map(list, zip(*self.timing_parts,
                                                                    strict=True))
        if self.scan_parts:
            self.scan_ts, self.range_, self.intensity = map(list, zip(*self.scan_parts,
                                                                      strict=True))
        self.timing_parts, self.scan_parts = [], []



@dataclass
class Lines:
    """The per-line and per-point arrays of a recording, before the
    :class:`~calstation.recordings.recorded.Recording`."""

    line_ts: NDArray[np.int64]
    periods: NDArray[np.float64]
    counts: NDArray[np.int64]
    azimuth: NDArray[np.float64]
    range_m: NDArray[np.float64]
    valid: NDArray[np.bool_]
    offsets: list[Buffer | None]
    intensity: list[Buffer | None]
    intensity_dtype: np.dtype[np.generic]
