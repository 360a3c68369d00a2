"""The host clock: one time base (integer nanoseconds) for every lidar line and encoder sample."""

from __future__ import annotations

import threading
import time
from typing import Protocol, runtime_checkable


@runtime_checkable
class Clock(Protocol):
    """A source of host-clock time in nanoseconds since the Unix epoch."""

    def now_ns(self) -> int:
        """The current time (ns since the Unix epoch)."""
        ...

    def sleep(self, seconds: float) -> None:
        """Wait ``seconds`` of this clock's time."""
        ...


class HostClock:
    """Wall-clock nanoseconds that never go backwards.

    Epoch-based (so recordings carry absolute times) but advanced by ``time.monotonic_ns`` so an NTP
    step during a scan cannot break the lidar/encoder time pairing.
    """

    def __init__(self) -> None:
        self._offset = time.time_ns() - time.monotonic_ns()

    def now_ns(self) -> int:
        """The current time (ns since the Unix epoch)."""
        return time.monotonic_ns() + self._offset

    def sleep(self, seconds: float) -> None:
        """Sleep in real time."""
        time.sleep(max(0.0, seconds))


class SimClock:
    """A simulated clock that only moves when told to; ``sleep`` returns at once.

    Simulated drivers share one ``SimClock`` so that lidar lines and encoder samples line up
    exactly, and a simulated run takes as long as the computation, not as long as the scan.
    """

    def __init__(self, start_ns: int = 1_767_225_600_000_000_000) -> None:  # 2026-01-01T00:00Z
        self._now = int(start_ns)
        self._lock = threading.Lock()

    def now_ns(self) -> int:
        """The simulated time (ns)."""
        with self._lock:
            return self._now

    def advance_to(self, t_ns: int) -> None:
        """Move time forward to ``t_ns`` (never backwards)."""
        with self._lock:
            self._now = max(self._now, int(t_ns))

    def sleep(self, seconds: float) -> None:
        """Advance the simulated time by ``seconds``."""
        with self._lock:
            self._now += round(max(0.0, seconds) * 1e9)
