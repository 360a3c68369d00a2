"""The byte-stream emulator kit: serve an emulated device over TCP or a pseudo-terminal.

A device is anything with :class:`StreamDevice`'s three methods: it gets the bytes the host sent
(``receive``), is polled for bytes it wants to send on its own (``poll``, for streaming data),
and is told when the host went away (``disconnect``). :class:`TcpServer` and :class:`PtyServer`
run one background thread each and connect a device to a real transport, so the driver under test
opens an ordinary pyserial URL (``socket://127.0.0.1:PORT``) or a tty path (``/dev/pts/N``).
Reusing the kit for a new device means writing only the device class.
"""

from __future__ import annotations

import contextlib
import os
import select
import socket
import threading
import time
from collections.abc import Callable
from typing import Protocol

POLL_INTERVAL_S = 0.001
"""How often the transports poll a device for streamed data when the host is quiet."""


class StreamDevice(Protocol):
    """An emulated device behind a byte stream."""

    def receive(self, data: bytes) -> bytes:
        """Bytes from the host; returns the bytes to answer with at once (may be empty)."""
        ...

    def poll(self) -> bytes:
        """Bytes the device sends on its own now (streamed scans); empty when none are due."""
        ...

    def disconnect(self) -> None:
        """The host closed the connection: drop per-connection state (stop streaming)."""
        ...


class _Server:
    """Common thread handling of the transports."""

    def __init__(self) -> None:
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.connections = 0
        """How many host connections were accepted (tests check reconnects with it)."""

    def _start(self, target: Callable[[], None], name: str) -> None:
        self._thread = threading.Thread(target=target, name=name, daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop the server thread and release the transport. Idempotent."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5)
        self._thread = None

    def __enter__(self) -> _Server:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class TcpServer(_Server):
    """Serve ``device`` on a TCP port (one host at a time, like a real sensor's Ethernet port).

    ``port=0`` picks a free port; :attr:`port` and :attr:`url` tell which. The device object lives
    as long as the server, so its state (laser, clock) survives a host reconnecting.
    """

    def __init__(self, device: StreamDevice, host: str = "127.0.0.1", port: int = 0) -> None:
        super().__init__()
        self.device = device
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._sock.bind((host, port))
        self._sock.listen(1)
        self._sock.settimeout(0.1)
        self.host, self.port = self._sock.getsockname()[:2]
        self.drop_connection = threading.Event()
        """Set it to make the server close the current connection (a cable pulled)."""
        self._start(self._serve, f"tcp-emulator:{self.port}")

    @property
    def url(self) -> str:
        """The pyserial URL of this server."""
        return f"socket://{self.host}:{self.port}"

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except (TimeoutError, OSError):
                continue
            self.connections += 1
            with conn:
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                self._talk(conn)
            self.device.disconnect()
        self._sock.close()

    def _talk(self, conn: socket.socket) -> None:
        self.drop_connection.clear()
        while not self._stop.is_set() and not self.drop_connection.is_set():
            ready, _, _ = select.select([conn], [], [], POLL_INTERVAL_S)
            out = b""
            if ready:
                try:
                    data = conn.recv(65536)
                except OSError:
                    return
                if not data:
                    return
                out += self.device.receive(data)
            out += self.device.poll()
            if out:
                try:
                    conn.sendall(out)
                except OSError:
                    return


class PtyServer(_Server):
    """Serve ``device`` on a pseudo-terminal; the host opens :attr:`port` like a serial port."""

    def __init__(self, device: StreamDevice) -> None:
        import tty

        super().__init__()
        self.device = device
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no CR/LF translation: the bytes go through untouched
        self.port = os.ttyname(self._slave)
        self._start(self._serve, f"pty-emulator:{self.port}")

    @property
    def url(self) -> str:
        """The tty path (pyserial opens it like a serial port)."""
        return self.port

    def _serve(self) -> None:
        pending = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], POLL_INTERVAL_S)
            if ready:
                try:
                    data = os.read(self._master, 65536)
                except OSError:
                    data = b""
                if data:
                    pending += self.device.receive(data)
            pending += self.device.poll()
            while pending and not self._stop.is_set():
                _, writable, _ = select.select([], [self._master], [], 0.05)
                if not writable:
                    break
                try:
                    n = os.write(self._master, pending)
                except BlockingIOError:
                    break
                except OSError:
                    # nobody holds the slave open: drop output like a serial line does
                    pending = b""
                    time.sleep(POLL_INTERVAL_S)
                    break
                pending = pending[n:]
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)


class ScriptedDevice:
    """A device that expects exact request bytes and answers with scripted bytes.

    The scripted-exchange style of PyMeasure's ``expected_protocol``: ``exchanges`` is a list of
    ``(request, reply)`` pairs, each request the exact bytes the driver must send (terminator
    included), each reply the exact bytes to answer with (``b""`` for none). Anything else the
    driver sends is recorded in :attr:`errors`; :meth:`check` raises if the script was not
    followed to the end.
    """

    def __init__(self, exchanges: list[tuple[bytes, bytes]], terminator: bytes = b"\n") -> None:
        self.exchanges = list(exchanges)
        self.terminator = terminator
        self.errors: list[str] = []
        self.received: list[bytes] = []
        self._buffer = b""
        self._lock = threading.Lock()

    def receive(self, data: bytes) -> bytes:
        """Match complete requests against the script."""
        out = b""
        with self._lock:
            self._buffer += data
            while self.terminator in self._buffer:
                cut = self._buffer.index(self.terminator) + len(self.terminator)
                request, self._buffer = self._buffer[:cut], self._buffer[cut:]
                self.received.append(request)
                if not self.exchanges:
                    self.errors.append(f"unexpected request {request!r} after the script ended")
                    continue
                expected, answer = self.exchanges.pop(0)
                if request != expected:
                    self.errors.append(f"expected {expected!r}, got {request!r}")
                    continue
                out += answer
        return out

    def poll(self) -> bytes:
        """Scripted devices send nothing on their own."""
        return b""

    def disconnect(self) -> None:
        """Nothing to reset."""

    def check(self) -> None:
        """Raise AssertionError if a request differed or the script has requests left."""
        with self._lock:
            problems = list(self.errors)
            if self.exchanges:
                problems.append(f"{len(self.exchanges)} scripted request(s) never came, "
                                f"next {self.exchanges[0][0]!r}")
        if problems:
            raise AssertionError("; ".join(problems))
