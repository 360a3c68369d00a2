"""The web station's limits, in one place (``calstation serve`` sets a few from its options;
tests shorten the times)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

from calstation.storage.db.models import MAX_ROW_ID

MAX_ID = MAX_ROW_ID
"""The largest id a database row can have (a signed 64-bit integer); larger ids are refused."""


@dataclass(frozen=True)
class WebLimits:
    """Sizes, counts and times that bound what a client can make the server do."""

    max_body_bytes: int = 64 * 1024
    """A request body larger than this is refused (413) before it is read."""

    max_streams: int = 1000
    """Event streams open at once, from all clients; more are refused (503)."""

    max_streams_per_client: int = 8
    """Event streams open at once from one remote address (429 beyond). Clients on this
    computer (loopback) share one address and are bounded by ``max_streams`` only."""

    event_keepalive_s: float = 15.0
    """An idle stream gets a comment this often (and its session is checked again)."""

    event_min_period_s: float = 0.5
    """A stream sends at most one state per this period (bursts are coalesced): two frames a
    second are what a person follows, and what a page draws without slowing the run."""

    session_idle_s: float = 4 * 3600.0
    """A logged-in session unused this long ends."""

    session_max_s: float = 12 * 3600.0
    """A logged-in session ends this long after the login, used or not (one shift)."""

    max_sessions: int = 256
    """Logged-in sessions kept at once; the oldest ends first."""

    login_free_failures: int = 5
    """Wrong tokens a client may give before the back-off starts."""

    login_max_lock_s: float = 300.0
    """The longest a client is locked out (the back-off doubles up to this)."""

    login_window_s: float = 900.0
    """A client's wrong tokens are forgotten after this long without one."""

    clock: Callable[[], float] = field(default=time.monotonic, compare=False)
    """The clock of sessions and the throttle (tests move it)."""
