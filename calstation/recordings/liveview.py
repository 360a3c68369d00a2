"""The live view: every scan streamed over the Foxglove WebSocket protocol while it is taken.

:func:`start_live_view` starts a WebSocket server bound to 127.0.0.1 and makes it the process's
live sink: from then on every :class:`~calstation.recordings.writer.RecordingWriter` of the
process also publishes each message it writes — the same channels, schemas, bytes and times as
the recording (``/lidar/scan``, ``/tf``, ``/tf_static``, ``/platter/cloud``, …). Foxglove
(*Open connection* → *Foxglove WebSocket* → ``ws://127.0.0.1:PORT``) then shows the scan in 3D
as it arrives.

The server is ``foxglove-sdk``'s, which speaks the protocol under its current subprotocol name,
``foxglove.sdk.v1``, and answers HTTP 400 to a client that offers only the older name,
``foxglove.websocket.v1`` (Foxglove Studio before the SDK, Lichtblick before its sdk.v1
support). The two are the same protocol (Foxglove's stated position; the SDK's own ROS bridge
made the same rename). So the port a client connects to is a small bridge
(:class:`_SubprotocolBridge`): it reads the WebSocket handshake, and when the client offers
``foxglove.websocket.v1`` but not ``foxglove.sdk.v1``, asks the SDK's server for
``foxglove.sdk.v1`` and answers the client with the name it asked for; after the handshake it
passes the bytes through untouched. Clients offering either name, or both, are served.

The server only sends what a client subscribed to, so an idle live view costs next to nothing.
The calibration (``/tf_static``) is sent once per scan; so that a client that connects later
still gets its transform tree, the newest calibration is sent again with the platter angle,
at most once a second.
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time
import warnings
from typing import TYPE_CHECKING

from calstation.errors import CalstationError
from calstation.recordings.messages import SchemaData

if TYPE_CHECKING:
    import foxglove

DEFAULT_PORT = 8765
"""The Foxglove WebSocket port Foxglove's own tools default to."""

LATCHED_TOPICS = ("/tf_static",)
REPEAT_LATCHED_S = 1.0
SUBPROTOCOL = "foxglove.sdk.v1"
"""The WebSocket subprotocol of ``foxglove-sdk``'s server."""
LEGACY_SUBPROTOCOL = "foxglove.websocket.v1"
"""The same protocol's earlier name, which older clients offer alone."""
_MAX_HANDSHAKE = 64 * 1024
_HANDSHAKE_TIMEOUT_S = 10.0


class LiveViewError(CalstationError):
    """The live view could not start (port in use, …)."""


class LiveView:
    """A running Foxglove WebSocket server fed by the recording writers. Close it when done.

    Use :func:`start_live_view`; ``port`` is the port actually bound (useful with port 0).
    """

    def __init__(self, port: int = DEFAULT_PORT, host: str = "127.0.0.1") -> None:
        import foxglove

        self._foxglove = foxglove
        self._context = foxglove.Context()
        try:
            self._bridge = _SubprotocolBridge(host, port)
        except OSError as exc:
            raise LiveViewError(f"cannot start the live view on {host}:{port}: {exc}") from exc
        try:  # the SDK's server, reached only through the bridge
            self._server = foxglove.start_server(
                name="calstation", host="127.0.0.1", port=0, context=self._context
            )
        except Exception as exc:  # the SDK raises its own error types
            self._bridge.close()
            raise LiveViewError(
                f"cannot start the live view on {host}:{port}: {exc}"
            ) from exc
        self._bridge.start(int(self._server.port))
        self.host = host
        self._lock = threading.Lock()
        self._channels: dict[str, foxglove.Channel] = {}
        self._latched: dict[str, tuple[SchemaData, bytes]] = {}
        self._last_repeat = 0.0
        self._closed = False
        self._failed = False
        from calstation.recordings.channels import CHANNELS, channel_schema

        for topic in CHANNELS:  # advertised at once, so a client can subscribe before a scan
            self._channel(topic, channel_schema(topic))

    @property
    def port(self) -> int:
        """The TCP port the server listens on."""
        return self._bridge.port

    @property
    def url(self) -> str:
        """The address to open in Foxglove."""
        return f"ws://{self.host}:{self.port}"

    def publish(self, topic: str, schema: SchemaData, data: bytes, log_time_ns: int) -> None:
        """Send one encoded message (what a :class:`RecordingWriter` writes) to the clients."""
        with self._lock:
            if self._closed:
                return
            try:
                self._log(topic, schema, data, log_time_ns)
                if topic in LATCHED_TOPICS:
                    self._latched[topic] = (schema, data)
                    self._last_repeat = time.monotonic()
                elif self._latched and time.monotonic() - self._last_repeat >= REPEAT_LATCHED_S:
                    self._last_repeat = time.monotonic()
                    for latched, (s, d) in self._latched.items():
                        self._log(latched, s, d, log_time_ns)
            except Exception as exc:  # the view must never cost the recording its data
                if not self._failed:
                    self._failed = True
                    warnings.warn(f"live view: cannot publish on {topic}: {exc}", stacklevel=2)

    def close(self) -> None:
        """Stop the server (idempotent); writers then no longer publish to it."""
        from calstation.recordings import writer

        with self._lock:
            if self._closed:
                return
            self._closed = True
        if writer.live_sink() is self:
            writer.set_live_sink(None)
        self._bridge.close()
        self._server.stop()

    def __enter__(self) -> LiveView:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _channel(self, topic: str, schema: SchemaData) -> foxglove.Channel:
        channel = self._channels.get(topic)
        if channel is None:
            fg = self._foxglove
            channel = fg.Channel(
                topic,
                schema=fg.Schema(name=schema.name, encoding=schema.encoding, data=schema.data),
                message_encoding="json" if schema.encoding == "jsonschema" else schema.encoding,
                context=self._context,
            )
            self._channels[topic] = channel
        return channel

    def _log(self, topic: str, schema: SchemaData, data: bytes, log_time_ns: int) -> None:
        self._channel(topic, schema).log(data, log_time=int(log_time_ns))


class _SubprotocolBridge:
    """A TCP port in front of the SDK's WebSocket server that also admits clients offering only
    :data:`LEGACY_SUBPROTOCOL` (see the module's docstring). One thread accepts; each
    connection gets two threads pumping bytes, one per direction."""

    def __init__(self, host: str, port: int) -> None:
        self._listener = socket.create_server((host, port))
        self._listener.settimeout(0.2)
        self.port = int(self._listener.getsockname()[1])
        self._upstream_port = 0
        self._closed = threading.Event()
        self._lock = threading.Lock()
        self._sockets: set[socket.socket] = set()
        self._accepting = threading.Thread(target=self._accept, name="live-view", daemon=True)

    def start(self, upstream_port: int) -> None:
        """Forward every connection to ``127.0.0.1:upstream_port`` from now on."""
        self._upstream_port = upstream_port
        self._accepting.start()

    def close(self) -> None:
        """Stop accepting and close every open connection (idempotent)."""
        self._closed.set()
        if self._accepting.is_alive():
            self._accepting.join(2.0)
        with self._lock:
            sockets, self._sockets = set(self._sockets), set()
        for sock in (self._listener, *sockets):
            with contextlib.suppress(OSError):
                sock.close()

    def _accept(self) -> None:
        while not self._closed.is_set():
            try:
                client, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            threading.Thread(target=self._serve, args=(client,), daemon=True).start()

    def _serve(self, client: socket.socket) -> None:
        upstream = None
        try:
            self._track(client)
            client.settimeout(_HANDSHAKE_TIMEOUT_S)
            head, rest = _read_head(client)
            request, legacy = rename_subprotocol(head)
            upstream = socket.create_connection(("127.0.0.1", self._upstream_port), timeout=5.0)
            self._track(upstream)
            upstream.sendall(request + rest)
            reply, rest = _read_head(upstream)
            if legacy:
                reply = reply.replace(SUBPROTOCOL.encode(), LEGACY_SUBPROTOCOL.encode())
            client.sendall(reply + rest)
            client.settimeout(None)
            upstream.settimeout(None)
        except OSError:
            for sock in (client, upstream):
                if sock is not None:
                    self._drop(sock)
            return
        threading.Thread(target=self._pump, args=(upstream, client), daemon=True).start()
        self._pump(client, upstream)

    def _pump(self, src: socket.socket, dst: socket.socket) -> None:
        try:
            while data := src.recv(65536):
                dst.sendall(data)
        except OSError:
            pass
        finally:
            self._drop(src)
            self._drop(dst)

    def _track(self, sock: socket.socket) -> None:
        with self._lock:
            self._sockets.add(sock)
        if self._closed.is_set():
            self._drop(sock)
            raise OSError("the live view is closed")

    def _drop(self, sock: socket.socket) -> None:
        with self._lock:
            self._sockets.discard(sock)
        with contextlib.suppress(OSError):
            sock.shutdown(socket.SHUT_RDWR)
        with contextlib.suppress(OSError):
            sock.close()


def _read_head(sock: socket.socket) -> tuple[bytes, bytes]:
    """An HTTP message's head (up to and including the blank line) and whatever followed it."""
    data = b""
    while (end := data.find(b"\r\n\r\n")) < 0:
        if len(data) > _MAX_HANDSHAKE:
            raise OSError("handshake too long")
        chunk = sock.recv(4096)
        if not chunk:
            raise OSError("connection closed during the handshake")
        data += chunk
    return data[: end + 4], data[end + 4 :]


def rename_subprotocol(head: bytes) -> tuple[bytes, bool]:
    """A client's WebSocket handshake as the SDK's server accepts it: if it offers
    :data:`LEGACY_SUBPROTOCOL` and not :data:`SUBPROTOCOL`, the offer becomes
    :data:`SUBPROTOCOL` (returns the new head and True); otherwise it is unchanged (False)."""
    lines = head.split(b"\r\n")
    for i, line in enumerate(lines):
        name, sep, value = line.partition(b":")
        if not sep or name.strip().lower() != b"sec-websocket-protocol":
            continue
        offered = [p.strip() for p in value.decode("latin-1").split(",")]
        if SUBPROTOCOL not in offered and LEGACY_SUBPROTOCOL in offered:
            lines[i] = b"Sec-WebSocket-Protocol: " + SUBPROTOCOL.encode()
            return b"\r\n".join(lines), True
    return head, False


def start_live_view(port: int = DEFAULT_PORT, host: str = "127.0.0.1") -> LiveView:
    """Start the live view on ``host:port`` (port 0: any free port) and make it the process's
    live sink, so every recording written from now on is streamed too."""
    from calstation.recordings import writer

    view = LiveView(port, host)
    writer.set_live_sink(view)
    return view
