"""The operator page's event stream while a run keeps it busy (a scan changes the state many
times a second): it still reads again who holds the station, so an open page's status line
follows a run started anywhere without waiting for a quiet moment."""

from __future__ import annotations

import asyncio
import threading

from calstation.web.events import EventHub, EventStream, StreamSlots
from calstation.web.live import LiveState
from calstation.web.settings import WebLimits

HANG_S = 60.0
"""A hang guard: the waits below end at their event long before."""


def test_a_busy_stream_reads_the_stations_holders_again() -> None:
    live = LiveState()
    ticks: list[int] = []
    twice = threading.Event()

    def tick() -> None:  # what the server's tick does: read the station locks again
        ticks.append(live.version)
        if len(ticks) >= 2:
            twice.set()

    hub = EventHub(live, tick=tick)
    limits = WebLimits(event_min_period_s=0.05)
    stop = threading.Event()

    def scan() -> None:  # a change far more often than the tick's period, as a scan makes
        while not stop.is_set():
            live.update(lambda st: setattr(st, "progress", {"fraction": st.version}))
            stop.wait(0.02)

    sent: list[bytes] = []

    async def send(message: dict[str, object]) -> None:
        body = message.get("body")
        if isinstance(body, bytes):
            sent.append(body)

    async def follow() -> None:
        stream = EventStream(hub, StreamSlots(limits), "127.0.0.1", limits, lambda: True)
        task = asyncio.create_task(stream._stream(send))
        try:
            await asyncio.to_thread(twice.wait, HANG_S)
        finally:
            task.cancel()

    changer = threading.Thread(target=scan, daemon=True)
    changer.start()
    try:
        asyncio.run(follow())
    finally:
        stop.set()
        changer.join()
    # read again (at most every events.TICK_S) while states kept being sent, not only when quiet
    assert twice.is_set(), f"the holders were read {len(ticks)} times in {HANG_S} s"
    assert ticks[1] - ticks[0] > 5  # the state changed all along in between
    assert sum(b.startswith(b"event: state") for b in sent) > 5
