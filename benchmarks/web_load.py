"""The web station under load: idle event streams and a huge request body.

Prints figures; the same measurements, with limits, are tests
(``tests/web/test_web_security_server.py``). Starts ``calstation serve`` on 127.0.0.1 (a free port,
a temporary database and home) and then:

1. opens ``--streams`` idle event streams (default 500), each read up to its first event, and
   keeps them open;
2. times, ``--repeat`` times, a new client's first event and a ``GET /state.json``;
3. posts a ``--body-mb`` body (default 200 MB) to ``/api/start``, once with its
   ``Content-Length`` and once chunked, and reads the server's peak memory (``VmHWM``) before
   and after.

Every request goes to 127.0.0.1; every loop is bounded in count and time.

    .venv/bin/python benchmarks/web_load.py [--streams 500] [--repeat 5] [--body-mb 200]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import socket
import ssl
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

HOST = "127.0.0.1"
IDLE_S = 2.0
"""Streams are measured this long after they opened, when they are idle."""


@dataclass
class Station:
    """A ``calstation serve`` process on 127.0.0.1 (its stderr in ``log``)."""

    process: subprocess.Popen[bytes]
    port: int
    scheme: str = "http"
    log: Path | None = None
    host: str = HOST

    @property
    def url(self) -> str:
        return f"{self.scheme}://{self.host}:{self.port}"


def free_port() -> int:
    with socket.socket() as s:
        s.bind((HOST, 0))
        return int(s.getsockname()[1])


@contextmanager
def serve(folder: Path, *args: str, env: dict[str, str] | None = None,
          host: str = HOST) -> Iterator[Station]:
    """``calstation serve ARGS`` on ``host`` (127.0.0.1) with a database and home in ``folder``
    (and ``env`` added to the environment); stopped (SIGINT, then killed after 30 s) at the
    end."""
    port = free_port()
    tls = "--tls-cert" in args
    (folder / "recipes").mkdir(parents=True, exist_ok=True)
    environment = {k: v for k, v in os.environ.items()
                   if k not in ("CALSTATION_TOKEN", "CALSTATION_TOKEN_FILE")}
    environment.update(CALSTATION_HOME=str(folder / "home"), **(env or {}))
    log = (folder / "serve.log").open("wb")  # the station's refusals, read by the tests
    process = subprocess.Popen(
        [sys.executable, "-c", "from calstation.cli import main; main()", "serve",
         "--host", host, "--port", str(port), "--recipes", str(folder / "recipes"),
         "--db", f"sqlite:///{folder / 'load.db'}", *args],
        env=environment, stdout=subprocess.DEVNULL, stderr=log)
    station = Station(process, port, "https" if tls else "http", folder / "serve.log", host)
    # only to see that it is up: the certificate is checked by whoever uses the station
    context = ssl.create_default_context()
    context.check_hostname, context.verify_mode = False, ssl.CERT_NONE
    try:
        deadline = time.monotonic() + 60
        while True:
            if process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("calstation serve did not start")
            try:
                with urllib.request.urlopen(station.url + "/state.json", timeout=2,
                                            context=context if tls else None):
                    break
            except OSError:
                time.sleep(0.1)
        yield station
    finally:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(10)
        log.close()


def memory_mib(pid: int) -> dict[str, float]:
    """The process's resident memory now (``VmRSS``) and at its peak (``VmHWM``), MiB."""
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            out[key] = int(value.split()[0]) / 1024
    return out


async def _first_event(port: int) -> tuple[asyncio.StreamWriter, float]:
    """Open ``GET /events`` and read up to the end of its first event; (the open connection,
    seconds from connecting to the first event)."""
    t0 = time.perf_counter()
    reader, writer = await asyncio.open_connection(HOST, port)
    writer.write(f"GET /events HTTP/1.1\r\nHost: {HOST}:{port}\r\n\r\n".encode())
    head = await reader.readuntil(b"\r\n\r\n")
    if not head.startswith(b"HTTP/1.1 200"):
        writer.close()
        raise RuntimeError(f"event stream refused: {head.splitlines()[0]!r}")
    data = b""
    # the state event read to its end (a blank line), whatever events follow it (the clock)
    while (start := data.find(b"event: state")) < 0 or data.find(b"\n\n", start) < 0:
        chunk = await reader.read(65536)
        if not chunk:
            raise RuntimeError("event stream closed before its first event")
        data += chunk
    return writer, time.perf_counter() - t0


async def open_streams(port: int, n: int, *, concurrency: int = 50,
                       timeout: float = 120.0) -> list[asyncio.StreamWriter]:
    """Open ``n`` event streams, each read up to its first event, and leave them idle."""
    gate = asyncio.Semaphore(concurrency)

    async def one() -> asyncio.StreamWriter:
        async with gate:
            writer, _ = await _first_event(port)
            return writer

    async with asyncio.timeout(timeout):
        return list(await asyncio.gather(*(one() for _ in range(n))))


async def first_event_s(port: int, timeout: float = 30.0) -> float:
    """Seconds a new client waits for its first event."""
    async with asyncio.timeout(timeout):
        writer, seconds = await _first_event(port)
    writer.close()
    return seconds


async def get_s(port: int, path: str, timeout: float = 30.0) -> tuple[int, float]:
    """(status, seconds) of a ``GET path`` on a new connection."""
    t0 = time.perf_counter()
    async with asyncio.timeout(timeout):
        reader, writer = await asyncio.open_connection(HOST, port)
        writer.write(f"GET {path} HTTP/1.1\r\nHost: {HOST}:{port}\r\nConnection: close\r\n\r\n"
                     .encode())
        data = await reader.read()
    writer.close()
    return int(data.split(b" ", 2)[1]), time.perf_counter() - t0


async def post_body(port: int, size: int, *, chunked: bool, timeout: float = 60.0
                    ) -> tuple[str, float]:
    """Post ``size`` bytes of a JSON-looking body to ``/api/start``; (the status line, or what
    happened to the connection, and seconds). 1 MiB is sent at a time."""
    t0 = time.perf_counter()
    block = b" " * (1 << 20)
    length = "Transfer-Encoding: chunked" if chunked else f"Content-Length: {size}"
    async with asyncio.timeout(timeout):
        reader, writer = await asyncio.open_connection(HOST, port)
        writer.write(f"POST /api/start HTTP/1.1\r\nHost: {HOST}:{port}\r\n"
                     f"Origin: http://{HOST}:{port}\r\nContent-Type: application/json\r\n"
                     f"{length}\r\n\r\n".encode())
        sent = 0
        try:
            while sent < size:
                piece = block[:min(len(block), size - sent)]
                writer.write(b"%x\r\n%s\r\n" % (len(piece), piece) if chunked else piece)
                await writer.drain()
                sent += len(piece)
            if chunked:
                writer.write(b"0\r\n\r\n")
                await writer.drain()
        except (ConnectionError, OSError) as exc:
            outcome = f"connection closed after {sent >> 20} MiB ({type(exc).__name__})"
        try:
            line = await asyncio.wait_for(reader.readline(), 10)
            outcome = line.decode("latin-1").strip() or locals().get("outcome", "no answer")
        except (ConnectionError, OSError, TimeoutError) as exc:
            outcome = locals().get("outcome", f"no answer ({type(exc).__name__})")
    writer.close()
    return outcome, time.perf_counter() - t0


async def _measure(station: Station, streams: int, repeat: int, body_mb: int) -> None:
    port = station.port
    pid = station.process.pid
    base = await first_event_s(port)
    print(f"first event, no other stream: {base * 1000:.1f} ms")
    t0 = time.perf_counter()
    writers = await open_streams(port, streams)
    print(f"{len(writers)} idle event streams opened in {time.perf_counter() - t0:.1f} s "
          f"(server: {memory_mib(pid)['VmRSS']:.0f} MiB resident)")
    await asyncio.sleep(IDLE_S)  # past their first event's coalescing: idle, waiting
    firsts = [await first_event_s(port) for _ in range(repeat)]
    gets = [(await get_s(port, "/state.json"))[1] for _ in range(repeat)]
    print(f"with {streams} idle streams: a new client's first event in "
          f"{statistics.median(firsts) * 1000:.1f} ms median, {max(firsts) * 1000:.1f} ms worst "
          f"of {repeat}; GET /state.json {statistics.median(gets) * 1000:.1f} ms median, "
          f"{max(gets) * 1000:.1f} ms worst")
    for w in writers:
        w.close()
    await asyncio.sleep(0.5)
    for chunked in (False, True):
        before = memory_mib(pid)
        outcome, seconds = await post_body(port, body_mb << 20, chunked=chunked)
        after = memory_mib(pid)
        status, took = await get_s(port, "/state.json")
        print(f"{body_mb} MiB body ({'chunked' if chunked else 'Content-Length'}): {outcome} "
              f"in {seconds:.2f} s; server peak memory {before['VmHWM']:.0f} → "
              f"{after['VmHWM']:.0f} MiB (+{after['VmHWM'] - before['VmHWM']:.1f}); then "
              f"GET /state.json {status} in {took * 1000:.1f} ms")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--streams", type=int, default=500)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--body-mb", type=int, default=200)
    args = ap.parse_args()
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    with tempfile.TemporaryDirectory() as tmp, serve(Path(tmp)) as station:
        asyncio.run(_measure(station, args.streams, args.repeat, args.body_mb))


if __name__ == "__main__":
    main()
