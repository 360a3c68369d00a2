"""The operator page's live updates: server-sent events over async waits.

An open stream costs a coroutine and a socket, never a thread: :class:`EventHub` hears every
change of the run's :class:`~calstation.web.live.LiveState` (from whichever thread made it) and
wakes the streams waiting on each event loop at once. The state is serialised once per change,
whatever the number of streams, and a stream sends at most one state per
``event_min_period_s`` (a scan changes the state hundreds of times a second).

:class:`StreamSlots` bounds the streams open at once, in total and per remote address. A stream
ends when its client goes away (it is noticed at once, not at the next write), and, on a
station with a token, when its session ends.
"""

from __future__ import annotations

import asyncio
import json
import threading
import time
from collections import Counter
from collections.abc import Callable

import anyio
from starlette.responses import Response
from starlette.types import Receive, Scope, Send

from calstation.web.hosts import is_local_host
from calstation.web.live import LiveState
from calstation.web.security import AccessError
from calstation.web.settings import WebLimits

TICK_S = 2.0
"""How often the state's tick runs (the station's holders read again) while streams wait."""


class EventHub:
    """Fans the live state's changes out to the event streams (see the module docstring)."""

    def __init__(self, live: LiveState, tick: Callable[[], object] | None = None) -> None:
        self.live = live
        self._tick = tick
        """called (in a thread) every :data:`TICK_S` while a stream waits, by one of them: it
        may change the state (the station's holders, read again), which the streams send"""
        self._ticked = -TICK_S
        self._ticking = False
        self._lock = threading.Lock()
        self._waiters: dict[asyncio.AbstractEventLoop, asyncio.Event] = {}
        self._cache_lock = threading.Lock()
        self._cache: tuple[int, bytes] = (-1, b"")
        live.add_listener(self._changed)

    def _changed(self) -> None:
        """Called by the live state (any thread, under its lock): never blocks."""
        with self._lock:
            loops = list(self._waiters)
        for loop in loops:
            try:
                loop.call_soon_threadsafe(self._wake, loop)
            except RuntimeError:  # that loop is closed
                with self._lock:
                    self._waiters.pop(loop, None)

    def _wake(self, loop: asyncio.AbstractEventLoop) -> None:
        with self._lock:
            event = self._waiters.pop(loop, None)
        if event is not None:
            event.set()

    async def tick(self) -> None:
        """Run the tick, if one is given and due and none runs (however many streams ask)."""
        now = time.monotonic()
        if self._tick is None or self._ticking or now - self._ticked < TICK_S:
            return
        self._ticking, self._ticked = True, now
        try:
            await asyncio.to_thread(self._tick)
        finally:
            self._ticking = False

    def next_change(self) -> asyncio.Event:
        """An event set at the next change of the state (on the running loop). Take it
        *before* reading the state's version, so that no change can fall in between."""
        loop = asyncio.get_running_loop()
        with self._lock:
            event = self._waiters.get(loop)
            if event is None:
                event = self._waiters[loop] = asyncio.Event()
            return event

    def message(self) -> tuple[int, bytes]:
        """The current state as a server-sent event (version, bytes), serialised once."""
        version = self.live.version
        with self._cache_lock:
            if self._cache[0] == version:
                return self._cache
        snapshot = self.live.snapshot()
        data = json.dumps(snapshot, separators=(",", ":"))
        entry = (int(snapshot["version"]), f"event: state\ndata: {data}\n\n".encode())
        with self._cache_lock:
            if entry[0] >= self._cache[0]:
                self._cache = entry
        return entry


class StreamSlots:
    """Counts the open streams; refuses one past the total or past a remote client's share."""

    def __init__(self, limits: WebLimits) -> None:
        self.total, self.per_client = limits.max_streams, limits.max_streams_per_client
        self._lock = threading.Lock()
        self._open: Counter[str] = Counter()
        self._count = 0

    def take(self, client: str) -> None:
        """Take a slot for ``client``; AccessError (503 or 429) when there is none."""
        with self._lock:
            if self._count >= self.total:
                raise AccessError(503, f"{self.total} event streams are open, the most this "
                                       "station serves: try again later", {"Retry-After": "10"})
            if not is_local_host(client) and self._open[client] >= self.per_client:
                raise AccessError(429, f"{client} has {self.per_client} event streams open, "
                                       "the most one client may", {"Retry-After": "10"})
            self._open[client] += 1
            self._count += 1

    def give_back(self, client: str) -> None:
        """Release a slot taken by ``client``."""
        with self._lock:
            self._count -= 1
            self._open[client] -= 1
            if self._open[client] <= 0:
                del self._open[client]

    @property
    def count(self) -> int:
        """Streams open now."""
        return self._count


class EventStream(Response):
    """The ``text/event-stream`` response of one client (holds one of :class:`StreamSlots`
    until it ends). ``still_allowed`` is asked at each keep-alive; False ends the stream."""

    media_type = "text/event-stream"

    def __init__(self, hub: EventHub, slots: StreamSlots, client: str, limits: WebLimits,
                 still_allowed: Callable[[], bool]) -> None:
        # no body and no length: Response.__init__ would announce an empty one
        self.status_code = 200
        self.background = None
        self.init_headers({"Content-Type": "text/event-stream; charset=utf-8",
                           "Cache-Control": "no-store", "X-Accel-Buffering": "no"})
        self.hub, self.slots, self.client, self.limits = hub, slots, client, limits
        self.still_allowed = still_allowed

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            await send({"type": "http.response.start", "status": 200,
                        "headers": self.raw_headers})
            async with anyio.create_task_group() as group:
                async def watch_disconnect() -> None:
                    while (await receive())["type"] != "http.disconnect":
                        pass
                    group.cancel_scope.cancel()

                group.start_soon(watch_disconnect)
                try:
                    await self._stream(send)
                finally:
                    group.cancel_scope.cancel()
        except OSError:  # the client went away mid-write
            pass
        finally:
            self.slots.give_back(self.client)

    async def _stream(self, send: Send) -> None:
        limits, hub = self.limits, self.hub
        sent = -1
        quiet_since = time.monotonic()

        async def chunk(body: bytes) -> None:
            await send({"type": "http.response.body", "body": body, "more_body": True})

        while True:
            changed = hub.next_change()
            if hub.live.version != sent:
                sent, body = hub.message()
                # and the server's clock now, not the one cached with the state: the page's
                # clocks (elapsed, since when) count from it
                await chunk(body)
                await chunk(clock_event())
                quiet_since = time.monotonic()
                # the station's holders, read again while the run keeps the stream busy too
                await hub.tick()
                # coalesce bursts (progress, lidar lines): a page needs a few frames a second
                await asyncio.sleep(limits.event_min_period_s)
                continue
            try:
                async with asyncio.timeout(min(limits.event_keepalive_s, TICK_S)):
                    await changed.wait()
            except TimeoutError:
                await hub.tick()
                if time.monotonic() - quiet_since < limits.event_keepalive_s:
                    continue
                if not self.still_allowed():
                    await chunk(b"event: end\ndata: \"session ended: log in again\"\n\n")
                    await send({"type": "http.response.body", "body": b"", "more_body": False})
                    return
                await chunk(b": keep-alive\n\n" + clock_event())
                quiet_since = time.monotonic()



def clock_event() -> bytes:
    """A ``clock`` event: the server's time now, seconds since the epoch."""
    return f"event: clock\ndata: {time.time():.3f}\n\n".encode()
