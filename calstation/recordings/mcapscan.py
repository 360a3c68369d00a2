"""A fast, crash-tolerant reader of the records of an MCAP file, for reading recordings.

The ``mcap`` package parses every record field by field through small Python reads; a spin scan
has tens of thousands of records, and that alone would cap reading far below the sensor's
point rate. This module walks the file held in memory with ``struct.unpack_from`` and hands out
messages as ``memoryview`` slices of their decompressed chunk (no copies), so the bulk arrays go
straight to ``numpy.frombuffer``.

It reads a file front to back, never trusting the summary, so a file whose writer was killed is
read up to its last complete record: :func:`scan` stops at the first incomplete or damaged
record and says why. Only the records a recording reader needs are decoded (channels, messages,
metadata, attachments, the footer); the others are skipped by length.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

MAGIC = b"\x89MCAP0\r\n"

OP_FOOTER = 0x02
OP_CHANNEL = 0x04
OP_MESSAGE = 0x05
OP_CHUNK = 0x06
OP_ATTACHMENT = 0x09
OP_METADATA = 0x0C

_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_RECORD = struct.Struct("<BQ")
_MESSAGE = struct.Struct("<HIQQ")
_CHUNK = struct.Struct("<QQQI")


class Damaged(Exception):
    """A record is malformed (a length past its end, a bad CRC, a decompression error)."""


@dataclass
class Handlers:
    """What :func:`scan` calls for each record of interest."""

    channel: Callable[[int, str, str], None]
    """``channel(id, topic, message_encoding)``."""
    message: Callable[[int, memoryview], None]
    """``message(channel_id, data)``."""
    metadata: Callable[[str, dict[str, str]], None]
    """``metadata(name, values)``."""
    attachment: Callable[[str, bytes], None]
    """``attachment(name, data)``."""


@dataclass(frozen=True)
class ScanResult:
    """How the scan ended: ``clean`` when the footer was read, else ``problem`` says why not."""

    clean: bool
    problem: str = ""


def _string(buf: memoryview, pos: int, end: int) -> tuple[str, int]:
    if pos + 4 > end:
        raise Damaged("a string runs past its record")
    (n,) = _U32.unpack_from(buf, pos)
    pos += 4
    if pos + n > end:
        raise Damaged("a string runs past its record")
    return bytes(buf[pos : pos + n]).decode("utf-8"), pos + n


def _string_map(buf: memoryview, pos: int, end: int) -> tuple[dict[str, str], int]:
    if pos + 4 > end:
        raise Damaged("a map runs past its record")
    (n,) = _U32.unpack_from(buf, pos)
    pos += 4
    stop = pos + n
    if stop > end:
        raise Damaged("a map runs past its record")
    out: dict[str, str] = {}
    while pos < stop:
        key, pos = _string(buf, pos, stop)
        value, pos = _string(buf, pos, stop)
        out[key] = value
    return out, stop


def _decompress(compression: str, data: memoryview, size: int) -> bytes:
    if compression == "":
        return bytes(data)
    if compression == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    if compression == "lz4":
        try:
            import lz4.frame
        except ImportError:
            raise Damaged("an lz4 chunk, and the lz4 package is not installed") from None
        return bytes(lz4.frame.decompress(data))
    raise Damaged(f"unknown chunk compression {compression!r}")


def _chunk_body(buf: memoryview, pos: int, end: int) -> tuple[str, memoryview, int, int]:
    """(compression, compressed records, uncompressed size, CRC) of a chunk record's body."""
    if pos + _CHUNK.size > end:
        raise Damaged("a chunk header runs past its record")
    _, _, size, crc = _CHUNK.unpack_from(buf, pos)
    compression, pos = _string(buf, pos + _CHUNK.size, end)
    (n,) = _U64.unpack_from(buf, pos)
    pos += 8
    if pos + n > end:
        raise Damaged("chunk records run past the chunk")
    return compression, buf[pos : pos + n], size, crc


def _inflate(buf: memoryview, pos: int, end: int) -> bytes:
    """A chunk's records, decompressed and checked against its size and CRC."""
    compression, data, size, crc = _chunk_body(buf, pos, end)
    try:
        raw = _decompress(compression, data, size)
    except Damaged:
        raise
    except Exception as exc:  # zstd raises its own error types
        raise Damaged(f"cannot decompress: {exc}") from exc
    if len(raw) != size:
        raise Damaged(f"chunk holds {len(raw)} bytes, its header says {size}")
    if crc and zlib.crc32(raw) != crc:
        raise Damaged("chunk CRC mismatch")
    return raw


AHEAD = 3
"""Chunks decompressed ahead, on a worker thread, while the current one's records are read
(decompression and the CRC release the GIL; the records are read in Python)."""

_WORKER: ThreadPoolExecutor | None = None


class _ChunksAhead:
    """The file's chunks decompressed in order, up to :data:`AHEAD` ahead of the reader.

    The chunk records are found by their headers alone, up to the first record that runs past
    the end of the file; the reader still walks every record itself and meets any damage where
    it is.
    """

    def __init__(self, buf: memoryview, pos: int) -> None:
        global _WORKER
        self.buf = buf
        self.spans: list[tuple[int, int]] = []
        total = len(buf)
        while pos + _RECORD.size <= total:
            op, length = _RECORD.unpack_from(buf, pos)
            start = pos + _RECORD.size
            if start + length > total or op == OP_FOOTER:
                break
            if op == OP_CHUNK:
                self.spans.append((start, start + length))
            pos = start + length
        self.pending: dict[int, Future[bytes]] = {}
        self.next = 0
        if len(self.spans) > 1:
            if _WORKER is None:
                _WORKER = ThreadPoolExecutor(max_workers=1, thread_name_prefix="calstation-mcap")
            self._top_up()

    def _top_up(self) -> None:
        assert _WORKER is not None
        while self.next < len(self.spans) and len(self.pending) < AHEAD:
            start, end = self.spans[self.next]
            self.pending[start] = _WORKER.submit(_inflate, self.buf, start, end)
            self.next += 1

    def records(self, start: int, end: int) -> bytes:
        """The decompressed records of the chunk record whose body is ``buf[start:end]``."""
        future = self.pending.pop(start, None)
        if future is None:
            return _inflate(self.buf, start, end)
        self._top_up()
        return future.result()

    def cancel(self) -> None:
        for future in self.pending.values():
            future.cancel()
        self.pending.clear()


def _records(
    buf: memoryview, pos: int, on: Handlers, *, inner: bool, chunks: _ChunksAhead | None = None
) -> ScanResult:
    """Walk records from ``pos``; in a chunk (``inner``) any incomplete record is damage.
    ``chunks`` decompresses the top level's chunks ahead of the walk."""
    total = len(buf)
    while True:
        if pos == total:
            if inner:
                return ScanResult(True)
            return ScanResult(
                False, "the file ends after a complete record, without the MCAP footer"
            )
        if pos + _RECORD.size > total:
            if inner:
                raise Damaged("a record header runs past the chunk")
            return ScanResult(False, "the file ends inside a record, which was dropped")
        op, length = _RECORD.unpack_from(buf, pos)
        start = pos + _RECORD.size
        end = start + length
        if end > total:
            if inner:
                raise Damaged("a record runs past the chunk")
            return ScanResult(False, "the file ends inside a record, which was dropped")
        if op == OP_MESSAGE:
            if length < _MESSAGE.size:
                raise Damaged("a message record is too short")
            (channel_id,) = _U16.unpack_from(buf, start)
            on.message(channel_id, buf[start + _MESSAGE.size : end])
        elif op == OP_CHANNEL:
            (channel_id,) = _U16.unpack_from(buf, start)
            topic, p = _string(buf, start + 4, end)
            encoding, _ = _string(buf, p, end)
            on.channel(channel_id, topic, encoding)
        elif op == OP_CHUNK and not inner:
            raw = _inflate(buf, start, end) if chunks is None else chunks.records(start, end)
            _records(memoryview(raw), 0, on, inner=True)
        elif op == OP_METADATA and not inner:
            name, p = _string(buf, start, end)
            values, _ = _string_map(buf, p, end)
            on.metadata(name, values)
        elif op == OP_ATTACHMENT and not inner:
            name, p = _string(buf, start + 16, end)
            _, p = _string(buf, p, end)
            (n,) = _U64.unpack_from(buf, p)
            if p + 8 + n > end:
                raise Damaged("attachment data runs past its record")
            on.attachment(name, bytes(buf[p + 8 : p + 8 + n]))
        elif op == OP_FOOTER and not inner:
            return ScanResult(True)
        pos = end


def scan(data: bytes, on: Handlers) -> ScanResult:
    """Walk the records of the MCAP file ``data`` (starting with the magic bytes), calling
    ``on``'s handlers. Stops at the footer (clean) or at the first incomplete or damaged record
    (``problem`` says which); the handlers' own exceptions propagate."""
    buf = memoryview(data)
    chunks = _ChunksAhead(buf, len(MAGIC))
    try:
        return _records(buf, len(MAGIC), on, inner=False, chunks=chunks)
    except (Damaged, struct.error, UnicodeDecodeError) as exc:
        return ScanResult(False, f"damaged record: {exc}")
    finally:
        chunks.cancel()
