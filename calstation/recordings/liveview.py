"""The live view: every scan streamed over the Foxglove WebSocket protocol while it is taken.

:func:`start_live_view` starts a WebSocket server (``foxglove-sdk``'s, protocol
``foxglove.websocket.v1``) bound to 127.0.0.1 and makes it the process's live sink: from then on
every :class:`~calstation.recordings.writer.RecordingWriter` of the process also publishes each
message it writes — the same channels, schemas and bytes as the recording (``/lidar/scan``, ``/tf``,
``/tf_static``, ``/platter/cloud``, …). Foxglove (*Open connection* → *Foxglove WebSocket* →
``ws://127.0.0.1:PORT``) then shows the scan in 3D as it arrives.

The server only sends what a client subscribed to, so an idle live view costs next to nothing.
The calibration (``/tf_static``) is sent once per scan; so that a client that connects later
still gets its transform tree, the newest calibration is sent again with the platter angle,
at most once a second.
"""

from __future__ import annotations

import threading
import time
import warnings
from typing import Any

from calstation.errors import CalstationError
from calstation.recordings.messages import SchemaData

DEFAULT_PORT = 8765
"""The Foxglove WebSocket port Foxglove's own tools default to."""

LATCHED_TOPICS = ("/tf_static",)
REPEAT_LATCHED_S = 1.0


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
            self._server = foxglove.start_server(
                name="calstation", host=host, port=port, context=self._context
            )
        except Exception as exc:  # the SDK raises its own error types
            raise LiveViewError(
                f"cannot start the live view on {host}:{port}: {exc}"
            ) from exc
        self.host = host
        self._lock = threading.Lock()
        self._channels: dict[str, Any] = {}
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
        return int(self._server.port)

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
        self._server.stop()

    def __enter__(self) -> LiveView:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _channel(self, topic: str, schema: SchemaData) -> Any:
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


def start_live_view(port: int = DEFAULT_PORT, host: str = "127.0.0.1") -> LiveView:
    """Start the live view on ``host:port`` (port 0: any free port) and make it the process's
    live sink, so every recording written from now on is streamed too."""
    from calstation.recordings import writer

    view = LiveView(port, host)
    writer.set_live_sink(view)
    return view
