"""Acquisition loops: a static scan and a spin scan, written to a recording while they run.

Generic over the driver protocols of :mod:`calstation.drivers`: the same loops drive the simulated
station and real hardware. The ``writer`` is a
:class:`calstation.recordings.writer.RecordingWriter` (or
anything with its ``write_line``/``write_encoder``/``write_turntable`` methods).

Progress is reported through ``progress(phase, fraction)``: ``phase`` a short text ("waiting for
speed", "scanning"), ``fraction`` in [0, 1] for that phase.
"""

from __future__ import annotations

import math
from array import array
from collections import deque
from collections.abc import Callable, Iterable
from contextlib import suppress
from itertools import pairwise
from typing import Protocol

from calstation.clock import Clock
from calstation.drivers import Encoder, EncoderSample, Lidar, LidarLine, Turntable, TurntableStatus
from calstation.errors import DriverError

Progress = Callable[[str, float], None]
"""``progress(phase, fraction)``: called as an acquisition advances."""

PRE_ROLL_S = 0.05
"""Encoder history (s) kept from just before the first line, so its first points interpolate."""

SPEED_TOLERANCE = 0.05
"""The turntable is at speed when within this fraction of the commanded rpm."""

SPEED_POLL_S = 0.05
STATUS_PERIOD_S = 0.1
"""Turntable status is recorded at about this period during a spin scan."""

LATE_LINES_FACTOR = 10
"""A spin scan's lines may reach the station this many times slower than they were scanned (a
loaded host works through the lidar's buffer) before the scan is stopped as stalled."""


LOST_LINES_WARN = 0.01
"""A scan whose lidar stream lost more than this fraction of its lines is named to the operator
(:class:`LineGaps`)."""


class LineGaps:
    """The lines a lidar's stream lost on the way to the station, counted from the gaps between
    the stamps of the lines it delivered: the line period is their median spacing, and a gap
    of k periods (beyond 1.5) lost k − 1 lines. A lidar whose lines do not reach the station
    (a network that drops packets, a host that cannot keep up with a sensor that then drops
    scans) leaves holes in the platter's turn that no fit can fill."""

    def __init__(self) -> None:
        self._stamps = array("q")  # 8 bytes a line: 4 MB for 8 minutes at 1000 lines/s

    def add(self, timestamp_ns: int) -> None:
        """Count a delivered line, stamped ``timestamp_ns``."""
        self._stamps.append(timestamp_ns)

    def lost(self) -> tuple[int, int, float]:
        """(lines delivered, lines lost, the longest gap between two delivered lines in s)."""
        stamps = self._stamps
        if len(stamps) < 10:
            return len(stamps), 0, 0.0
        gaps = [b - a for a, b in pairwise(stamps)]
        period = sorted(gaps)[len(gaps) // 2]
        if period <= 0:
            return len(stamps), 0, 0.0
        lost = sum(round(g / period) - 1 for g in gaps if g > 1.5 * period)
        return len(stamps), lost, max(gaps) * 1e-9


def lost_lines_warning(scan: str, delivered: int, lost: int, longest_s: float) -> str | None:
    """What to tell the operator about the lines the ``scan``'s lidar stream lost (the counts
    of :meth:`LineGaps.lost`), or None when it lost at most :data:`LOST_LINES_WARN` of them."""
    if lost <= LOST_LINES_WARN * (delivered + lost):
        return None
    return (
        f"the {scan} scan lost {lost} of its {delivered + lost} lidar lines "
        f"({100 * lost / (delivered + lost):.0f} %; the longest gap {longest_s:.2f} s): they "
        "did not reach the station, and the platter angles they would have covered are "
        "missing from the scan. Is the lidar's connection sound, and can this computer keep "
        "up with it?"
    )


class Writer(Protocol):
    """What the acquisition loops need of a recording writer."""

    def write_line(self, line: LidarLine) -> None:
        """Append one lidar line."""
        ...

    def write_encoder(self, samples: Iterable[EncoderSample]) -> None:
        """Append encoder samples (oldest first)."""
        ...

    def write_turntable(self, status: TurntableStatus) -> None:
        """Append one turntable status."""
        ...


def _pre_roll(samples: list[EncoderSample], now: EncoderSample) -> list[EncoderSample]:
    """The samples of the last ``PRE_ROLL_S`` before ``now`` (the rest is stale history)."""
    horizon = now.timestamp_ns - round(PRE_ROLL_S * 1e9)
    return [s for s in samples if horizon <= s.timestamp_ns < now.timestamp_ns]


def _start_encoder(encoder: Encoder, writer: Writer) -> EncoderSample:
    """Write a little encoder history plus a reading now; returns that reading."""
    history = encoder.samples()
    now = encoder.read()
    writer.write_encoder([*_pre_roll(history, now), now])
    return now


def _finish_encoder(encoder: Encoder, writer: Writer) -> None:
    """The stream's last samples plus a reading now, so the last points of the last line
    interpolate rather than extrapolate."""
    samples = encoder.samples()
    last = encoder.read()
    if not samples or last.timestamp_ns > samples[-1].timestamp_ns:
        samples.append(last)
    writer.write_encoder(samples)


def acquire_static(
    lidar: Lidar,
    encoder: Encoder,
    writer: Writer,
    *,
    lines: int,
    progress: Progress | None = None,
) -> None:
    """Record ``lines`` lidar lines with the platter at rest, plus the encoder stream.

    The lidar is started and always stopped again. Raises :class:`DriverError` if the lidar
    stops streaming before ``lines`` lines arrived.
    """
    if lines <= 0:
        raise DriverError(f"a static scan needs at least one line, got {lines}")
    _start_encoder(encoder, writer)
    n = 0
    lidar.start()
    try:
        for line in lidar.lines():
            writer.write_line(line)
            writer.write_encoder(encoder.samples())
            n += 1
            if progress is not None:
                progress("scanning", n / lines)
            if n >= lines:
                break
    finally:
        lidar.stop()
    _finish_encoder(encoder, writer)
    if n < lines:
        raise DriverError(f"the lidar stopped after {n} of {lines} lines")


class MoreTurns(Protocol):
    """Whether a spin scan should go on past its ``revolutions``: called after every line once
    they are done, with the turns covered and the seconds scanned; False ends the scan. It must
    answer at once (the lines keep arriving); ``max_revolutions`` bounds it whatever it says."""

    max_revolutions: float

    def __call__(self, turns: float, seconds: float) -> bool: ...


def acquire_spin(
    lidar: Lidar,
    turntable: Turntable,
    encoder: Encoder,
    writer: Writer,
    *,
    rpm: float,
    revolutions: float,
    settle_s: float,
    clock: Clock,
    progress: Progress | None = None,
    speed_timeout_s: float = 60.0,
    more: MoreTurns | None = None,
) -> None:
    """Spin the platter at ``rpm`` and record lines, encoder and turntable status until the
    encoder has covered ``revolutions`` turns since the first line — and on, while ``more``
    asks for more turns (see :class:`MoreTurns`).

    Sequence: enable, spin, wait (polling ``turntable.status()``, sleeping on ``clock``) until
    the speed is within :data:`SPEED_TOLERANCE` of ``rpm``, wait ``settle_s`` more, then scan.
    The turntable is stopped in every case (``emergency_stop`` if a normal stop fails), and the
    lidar stopped. Raises :class:`DriverError` if the speed is not reached within
    ``speed_timeout_s`` or the encoder does not advance as the commanded speed implies.
    """
    if rpm == 0 or not math.isfinite(rpm):
        raise DriverError(f"a spin scan needs a non-zero finite speed, got {rpm} rpm")
    if revolutions <= 0:
        raise DriverError(f"a spin scan needs a positive number of revolutions, got {revolutions}")
    turntable.enable()
    try:
        turntable.spin(rpm)
        _wait_for_speed(turntable, writer, rpm, clock, speed_timeout_s, progress)
        if settle_s > 0:
            clock.sleep(settle_s)
        _scan_turns(lidar, turntable, encoder, writer, rpm, revolutions, clock, progress, more)
    except BaseException as exc:
        _stop_after_fault(turntable, writer, exc)
        raise
    try:
        turntable.stop()
    except Exception:
        turntable.emergency_stop()
        raise
    finally:
        writer.write_turntable(turntable.status())


def _stop_after_fault(turntable: Turntable, writer: Writer, exc: BaseException) -> None:
    """Stop the platter after ``exc`` (emergency stop if ``stop`` fails) without hiding ``exc``:
    the fault that ended the scan is the one the operator must read."""
    try:
        turntable.stop()
    except Exception as stop_exc:
        exc.add_note(f"then the turntable's stop failed: {stop_exc}")
        with suppress(Exception):
            turntable.emergency_stop()
    with suppress(Exception):
        writer.write_turntable(turntable.status())


def _wait_for_speed(
    turntable: Turntable,
    writer: Writer,
    rpm: float,
    clock: Clock,
    timeout_s: float,
    progress: Progress | None,
) -> None:
    start = clock.now_ns()
    first: float | None = None
    while True:
        status = turntable.status()
        writer.write_turntable(status)
        if status.faults:
            raise DriverError(f"turntable fault while speeding up: {', '.join(status.faults)}")
        if first is None:
            first = status.speed_rpm
        if abs(status.speed_rpm - rpm) <= SPEED_TOLERANCE * abs(rpm):
            if progress is not None:
                progress("waiting for speed", 1.0)
            return
        if progress is not None and rpm != first:
            progress(
                "waiting for speed", min(1.0, max(0.0, (status.speed_rpm - first) / (rpm - first)))
            )
        if (clock.now_ns() - start) * 1e-9 > timeout_s:
            raise DriverError(
                f"turntable did not reach {rpm:g} rpm within {timeout_s:g} s "
                f"(last reported {status.speed_rpm:.3g} rpm)"
            )
        clock.sleep(SPEED_POLL_S)


class _CountAt:
    """The encoder count at a line's time, interpolated between the readings around it (the
    newest reading when none is later yet). Lines and readings come in time order; readings
    older than the line are dropped as they are passed."""

    def __init__(self, start: EncoderSample) -> None:
        self._before = start
        self._pending: deque[EncoderSample] = deque()

    def __call__(self, samples: Iterable[EncoderSample], t_ns: int) -> float:
        self._pending.extend(samples)
        while self._pending and self._pending[0].timestamp_ns <= t_ns:
            self._before = self._pending.popleft()
        before = self._before
        if not self._pending or before.timestamp_ns >= t_ns:
            return float(before.count)
        after = self._pending[0]
        f = (t_ns - before.timestamp_ns) / (after.timestamp_ns - before.timestamp_ns)
        return before.count + f * (after.count - before.count)


def _scan_turns(
    lidar: Lidar,
    turntable: Turntable,
    encoder: Encoder,
    writer: Writer,
    rpm: float,
    revolutions: float,
    clock: Clock,
    progress: Progress | None,
    more: MoreTurns | None = None,
) -> None:
    cpr = encoder.counts_per_revolution
    start = _start_encoder(encoder, writer)
    most = revolutions if more is None else max(revolutions, more.max_revolutions)
    # generous limits, so a stalled encoder cannot hang the scan: twice the nominal time plus
    # slack of lines scanned (a loaded host that receives the lines late is not a fault), and
    # ten times that on the clock (lines whose stamps do not advance are)
    scanned_ns = round((2.0 * most * 60.0 / abs(rpm) + 5.0) * 1e9)
    limit_ns = start.timestamp_ns + scanned_ns
    waited_ns = clock.now_ns() + LATE_LINES_FACTOR * scanned_ns
    next_status = clock.now_ns()
    turns = 0.0
    count_at = _CountAt(start)
    first: float | None = None
    lidar.start()
    try:
        for line in lidar.lines():
            writer.write_line(line)
            samples = encoder.samples()
            writer.write_encoder(samples)
            # the turns between the first line and this one, as the recording counts them
            # (not from the reading before the lidar started, nor to the newest reading: a
            # lidar that takes a while to start, or hands a line over after it was scanned,
            # would leave the recording short of the turns asked)
            count = count_at(samples, line.timestamp_ns)
            first = count if first is None else first
            turns = abs(count - first) / cpr
            now = clock.now_ns()
            if now >= next_status:
                writer.write_turntable(turntable.status())
                next_status = now + round(STATUS_PERIOD_S * 1e9)
            if progress is not None:
                progress("scanning", min(1.0, turns / revolutions))
            if turns >= revolutions and (
                more is None or turns >= most
                or not more(turns, (now - start.timestamp_ns) * 1e-9)
            ):
                break
            if line.timestamp_ns > limit_ns:
                raise DriverError(
                    f"the encoder covered only {turns:.3f} of {most:g} turns in "
                    f"{(line.timestamp_ns - start.timestamp_ns) * 1e-9:.1f} s of lines at "
                    f"{rpm:g} rpm: is the platter turning and the encoder connected?"
                )
            if now > waited_ns:
                raise DriverError(
                    f"the lidar's lines cover only {turns:.3f} of {most:g} turns after "
                    f"{(now - start.timestamp_ns) * 1e-9:.1f} s: its line stamps lag the "
                    f"station's clock by {(now - line.timestamp_ns) * 1e-9:.1f} s (are they "
                    f"advancing, and can this computer keep up with the lidar?)"
                )
    finally:
        lidar.stop()
    _finish_encoder(encoder, writer)
    if turns < revolutions:
        raise DriverError(f"the lidar stopped streaming after {turns:.3f} of {revolutions:g} turns")
