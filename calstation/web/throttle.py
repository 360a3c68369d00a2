"""Back-off of wrong station tokens, per client address.

A client (an IP address) may give a wrong token a few times (:attr:`free`); after that each
further wrong token locks it out for twice as long as the one before (1 s, 2 s, 4 s, … up to
:attr:`max_lock_s`). While locked out, every token it sends, right or wrong, is refused with
HTTP 429 and ``Retry-After`` without being compared, so guessing cannot go faster than the
back-off allows. A client's count is forgotten after :attr:`window_s` without a wrong token,
and after a right one. The table is bounded: the least recently seen clients are dropped first.
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass


@dataclass
class _Client:
    failures: int = 0
    last_failure: float = 0.0
    locked_until: float = 0.0


class LoginThrottle:
    """Counts wrong tokens per client and says how long a client must wait."""

    def __init__(self, *, free: int = 5, max_lock_s: float = 300.0, window_s: float = 900.0,
                 capacity: int = 10_000, clock: Callable[[], float] = time.monotonic) -> None:
        self.free, self.max_lock_s, self.window_s = free, max_lock_s, window_s
        self.capacity = capacity
        self.clock = clock
        self._lock = threading.Lock()
        self._clients: OrderedDict[str, _Client] = OrderedDict()

    def wait_s(self, client: str) -> float:
        """Seconds ``client`` must still wait before a token of its is compared (0: none)."""
        now = self.clock()
        with self._lock:
            c = self._clients.get(client)
            return 0.0 if c is None else max(0.0, c.locked_until - now)

    def failed(self, client: str) -> float:
        """``client`` gave a wrong token; returns the lock-out it now has (seconds, 0: none)."""
        now = self.clock()
        with self._lock:
            c = self._clients.pop(client, None) or _Client()
            if now - c.last_failure > self.window_s:
                c.failures = 0
            c.failures += 1
            c.last_failure = now
            if c.failures > self.free:
                lock = min(self.max_lock_s, 2.0 ** (c.failures - self.free - 1))
                c.locked_until = now + lock
            self._clients[client] = c
            while len(self._clients) > self.capacity:
                self._clients.popitem(last=False)
            return max(0.0, c.locked_until - now)

    def succeeded(self, client: str) -> None:
        """``client`` gave the right token: its count starts again."""
        with self._lock:
            self._clients.pop(client, None)


def retry_after(seconds: float) -> str:
    """A ``Retry-After`` header value (whole seconds, at least 1)."""
    return str(max(1, math.ceil(seconds)))
