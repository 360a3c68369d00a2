"""A fast, crash-tolerant, bounded reader of the records of an MCAP file, for reading recordings.

The ``mcap`` package parses every record field by field through small Python reads; a spin scan
has tens of thousands of records, and that alone would cap reading far below the sensor's
point rate. This module walks the file held in memory with ``struct.unpack_from`` and hands out
messages as ``memoryview`` slices of their decompressed chunk (no copies), so the bulk arrays go
straight to ``numpy.frombuffer``.

It reads a file front to back, never trusting the summary, so a file whose writer was killed is
read up to its last complete record: :func:`scan` stops at the first incomplete or damaged
record and says why. A file that ends with its footer was closed by its writer: damage met in it
(a CRC that does not match, a record that runs past its end) is damage done since, and
:class:`ScanResult` says so (``complete``), for the reader to refuse the file rather than read
half of it. Only the records a recording reader needs are decoded (channels, messages, metadata,
attachments, the footer); the others are skipped by length.

What a file can make the reader do is bounded (:class:`ReadLimits`, from the environment): a
chunk that declares more than ``max_chunk_bytes`` is refused before it is decompressed, a chunk
is never decompressed past what it declares, a file whose chunks inflate more than
``max_inflation`` times their compressed size (past a first ``INFLATION_GRACE`` bytes) is
refused, and so is one of more than ``max_records`` records: a decompression bomb is refused
within a fraction of a second and a few hundred MB (:class:`Refused`).
"""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Callable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

MAGIC = b"\x89MCAP0\r\n"

OP_FOOTER = 0x02
OP_CHANNEL = 0x04
OP_DATA_END = 0x0F
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


class Refused(Exception):
    """The file asks for more than :class:`ReadLimits` allow (a decompression bomb, or records
    past counting): it is not read at all."""


MB = 1 << 20

INFLATION_GRACE = 128 * MB
"""Bytes a file's chunks may inflate to before their ratio to the compressed bytes is checked
(small files of very regular data compress far better than a scan's)."""


def _env_number(name: str, default: float, low: float, high: float) -> float:
    text = os.environ.get(name)
    if not text:
        return default
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not low <= value <= high:
        raise Refused(f"{name}={text!r}: expected a number from {low:g} to {high:g}")
    return value


@dataclass(frozen=True)
class ReadLimits:
    """How much one file may make the reader hold and do."""

    max_chunk_bytes: int = 32 * MB
    """Largest decompressed chunk read (calstation's writer closes chunks at ~1 MiB)."""
    max_records: int = 5_000_000
    """Most records read from one file (a spin scan of an hour has under 400 000)."""
    max_inflation: float = 100.0
    """Largest ratio of a file's decompressed chunks to their compressed bytes, past
    :data:`INFLATION_GRACE` (a scan's chunks inflate about 4 times)."""

    @classmethod
    def from_environment(cls) -> ReadLimits:
        """The limits, from ``CALSTATION_MCAP_MAX_CHUNK_MB``, ``CALSTATION_MCAP_MAX_RECORDS``
        and ``CALSTATION_MCAP_MAX_INFLATION`` where set (:class:`Refused` for a value that is
        not a number in range)."""
        d = cls()
        return cls(
            max_chunk_bytes=int(_env_number("CALSTATION_MCAP_MAX_CHUNK_MB",
                                            d.max_chunk_bytes / MB, 1, 4096) * MB),
            max_records=int(_env_number("CALSTATION_MCAP_MAX_RECORDS", d.max_records, 1e3,
                                        1e10)),
            max_inflation=_env_number("CALSTATION_MCAP_MAX_INFLATION", d.max_inflation, 2,
                                      1e6),
        )


@dataclass
class _Budget:
    """What the walk has used so far of its :class:`ReadLimits`."""

    limits: ReadLimits
    records: int = 0
    compressed: int = 0
    inflated: int = 0

    def record(self) -> None:
        self.records += 1
        if self.records > self.limits.max_records:
            raise Refused(
                f"it holds more than {self.limits.max_records:,} records, more than calstation "
                "reads from one file (CALSTATION_MCAP_MAX_RECORDS)"
            )

    def chunk(self, compressed: int, inflated: int) -> None:
        self.compressed += compressed
        self.inflated += inflated
        ratio = self.inflated / max(self.compressed, 1)
        if self.inflated > INFLATION_GRACE and ratio > self.limits.max_inflation:
            raise Refused(
                f"its chunks inflate {ratio:,.0f} times their compressed size (to "
                f"{self.inflated / MB:,.0f} MB so far), more than the "
                f"{self.limits.max_inflation:g} times calstation reads "
                "(CALSTATION_MCAP_MAX_INFLATION): a decompression bomb?"
            )


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
    routes: Mapping[int, Callable[[memoryview], None]] | None = None
    """Where given, a message goes to ``routes[channel_id](data)`` (nowhere for a channel it
    does not hold) instead of ``message``: one call less per message, and none for a channel
    the reader skips."""

    def route(self, channel_id: int, data: memoryview) -> None:
        """Hand a message to its route, or to ``message``."""
        if self.routes is None:
            self.message(channel_id, data)
        elif (read := self.routes.get(channel_id)) is not None:
            read(data)


@dataclass(frozen=True)
class ScanResult:
    """How the scan ended: ``clean`` when the footer was read, else ``problem`` says why not;
    ``complete`` when the file ends with its footer (its writer finished it) — a walk that is
    not clean in a complete file met damage done since."""

    clean: bool
    problem: str = ""
    complete: bool = False


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
    """The chunk's records, never more than ``size`` + 1 bytes of them (whatever the compressed
    stream's own header claims)."""
    if compression == "":
        return bytes(data)
    if compression == "zstd":
        import zstandard

        reader = zstandard.ZstdDecompressor().stream_reader(data)
        parts, got = [], 0
        while got <= size:
            part = reader.read(size + 1 - got)
            if not part:
                break
            parts.append(part)
            got += len(part)
        return b"".join(parts)
    if compression == "lz4":
        try:
            import lz4.frame
        except ImportError:
            raise Damaged("an lz4 chunk, and the lz4 package is not installed") from None
        return bytes(lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=size + 1))
    raise Damaged(f"unknown chunk compression {compression!r}")


def _chunk_body(buf: memoryview, pos: int, end: int) -> tuple[str, memoryview, int, int]:
    """(compression, compressed records, uncompressed size, CRC) of a chunk record's body."""
    if pos + _CHUNK.size > end:
        raise Damaged("a chunk header runs past its record")
    _, _, size, crc = _CHUNK.unpack_from(buf, pos)
    compression, pos = _string(buf, pos + _CHUNK.size, end)
    if pos + 8 > end:
        raise Damaged("a chunk header runs past its record")
    (n,) = _U64.unpack_from(buf, pos)
    pos += 8
    if pos + n > end:
        raise Damaged("chunk records run past the chunk")
    return compression, buf[pos : pos + n], size, crc


def _inflate(buf: memoryview, pos: int, end: int, limits: ReadLimits) -> bytes:
    """A chunk's records, decompressed and checked against its size and CRC; a chunk that
    declares more than ``limits`` allow is :class:`Refused` before it is decompressed."""
    compression, data, size, crc = _chunk_body(buf, pos, end)
    if size > limits.max_chunk_bytes:
        raise Refused(
            f"a chunk of {len(data):,} compressed bytes declares {size:,} bytes of records, more "
            f"than the {limits.max_chunk_bytes / MB:g} MB calstation decompresses "
            "(CALSTATION_MCAP_MAX_CHUNK_MB; calstation's own chunks hold about 1 MB)"
        )
    try:
        raw = _decompress(compression, data, size)
    except Damaged:
        raise
    except Exception as exc:  # zstd and lz4 raise their own error types
        raise Damaged(f"cannot decompress: {exc}") from exc
    if len(raw) > size:
        raise Damaged(f"chunk inflates past the {size} bytes its header declares")
    if len(raw) != size:
        raise Damaged(f"chunk holds {len(raw)} bytes, its header says {size}")
    if crc and zlib.crc32(raw) != crc:
        raise Damaged("chunk CRC mismatch")
    return raw


AHEAD = 3
"""Chunks decompressed ahead, on worker threads, while the current one's records are read
(decompression and the CRC release the GIL; the records are read in Python)."""

WORKERS = 2
"""Worker threads: the chunks ahead, and the data section's CRC beside them."""

_WORKER: ThreadPoolExecutor | None = None


class _ChunksAhead:
    """The file's chunks decompressed in order, up to :data:`AHEAD` ahead of the reader.

    The chunk records are found by their headers alone, up to the first record that runs past
    the end of the file; the reader still walks every record itself and meets any damage where
    it is. Where that finds the data-end record, the CRC of every byte before it is computed
    beside the chunks (:meth:`data_crc`), for the walk to compare when it gets there.
    """

    def __init__(self, buf: memoryview, pos: int, budget: _Budget) -> None:
        global _WORKER
        self.buf = buf
        self.budget = budget
        self.spans: list[tuple[int, int]] = []
        data_end = -1
        total = len(buf)
        while pos + _RECORD.size <= total:
            op, length = _RECORD.unpack_from(buf, pos)
            start = pos + _RECORD.size
            if start + length > total or op == OP_FOOTER:
                break
            if op == OP_CHUNK:
                self.spans.append((start, start + length))
            elif op == OP_DATA_END:
                data_end = pos
                break
            pos = start + length
        self.pending: dict[int, Future[bytes]] = {}
        self.next = 0
        self._crc: tuple[int, Future[int]] | None = None
        if len(self.spans) > 1:
            if _WORKER is None:
                _WORKER = ThreadPoolExecutor(max_workers=WORKERS,
                                             thread_name_prefix="calstation-mcap")
            self._top_up()
            if data_end >= 0:
                self._crc = (data_end, _WORKER.submit(zlib.crc32, buf[:data_end]))

    def _top_up(self) -> None:
        assert _WORKER is not None
        while self.next < len(self.spans) and len(self.pending) < AHEAD:
            start, end = self.spans[self.next]
            self.pending[start] = _WORKER.submit(_inflate, self.buf, start, end,
                                                 self.budget.limits)
            self.next += 1

    def records(self, start: int, end: int) -> bytes:
        """The decompressed records of the chunk record whose body is ``buf[start:end]``."""
        future = self.pending.pop(start, None)
        if future is None:
            raw = _inflate(self.buf, start, end, self.budget.limits)
        else:
            self._top_up()
            raw = future.result()
        self.budget.chunk(end - start, len(raw))
        return raw

    def data_crc(self, pos: int) -> int:
        """The CRC of ``buf[:pos]``: computed beside the chunks where ``pos`` is the data-end
        record the headers led to, else here."""
        if self._crc is not None and self._crc[0] == pos:
            return self._crc[1].result()
        return zlib.crc32(self.buf[:pos])

    def cancel(self) -> None:
        for future in self.pending.values():
            future.cancel()
        self.pending.clear()
        if self._crc is not None:
            self._crc[1].cancel()


@dataclass
class _Walk:
    """Where the top-level walk is, for messages that name the damaged record's place."""

    pos: int = 0
    data_crc_checked: bool = False


def _records(
    buf: memoryview, pos: int, on: Handlers, *, chunks: _ChunksAhead, walk: _Walk
) -> ScanResult:
    """Walk the file's top-level records from ``pos`` (each chunk's by :func:`_chunk_records`).
    ``chunks`` decompresses the chunks (ahead of the walk) and counts what the file uses of its
    budget."""
    total = len(buf)
    budget = chunks.budget
    while True:
        walk.pos = pos
        if pos == total:
            return ScanResult(
                False, "the file ends after a complete record, without the MCAP footer"
            )
        if pos + _RECORD.size > total:
            return ScanResult(False, "the file ends inside a record, which was dropped")
        op, length = _RECORD.unpack_from(buf, pos)
        start = pos + _RECORD.size
        end = start + length
        if end > total:
            return ScanResult(False, "the file ends inside a record, which was dropped")
        budget.record()
        if op == OP_MESSAGE:
            if length < _MESSAGE.size:
                raise Damaged("a message record is too short")
            (channel_id,) = _U16.unpack_from(buf, start)
            on.route(channel_id, buf[start + _MESSAGE.size : end])
        elif op == OP_CHANNEL:
            _channel(buf, start, end, on)
        elif op == OP_CHUNK:
            _chunk_records(memoryview(chunks.records(start, end)), on, budget)
        elif op == OP_METADATA:
            name, p = _string(buf, start, end)
            values, _ = _string_map(buf, p, end)
            on.metadata(name, values)
        elif op == OP_ATTACHMENT:
            _attachment(buf, start, end, on)
        elif op == OP_DATA_END:
            _check_data_crc(buf, pos, start, end, walk, chunks)
        elif op == OP_FOOTER:
            return ScanResult(True)
        pos = end


def _channel(buf: memoryview, start: int, end: int, on: Handlers) -> None:
    if end - start < 4:
        raise Damaged("a channel record is too short")
    (channel_id,) = _U16.unpack_from(buf, start)
    topic, p = _string(buf, start + 4, end)
    encoding, _ = _string(buf, p, end)
    on.channel(channel_id, topic, encoding)


def _chunk_records(buf: memoryview, on: Handlers, budget: _Budget) -> None:
    """Walk the records of a decompressed chunk: messages (nearly all of a file's records) and
    channels; any incomplete record is damage. :func:`_records`' walk, the handlers and the
    record count kept in locals (a chunk holds thousands of messages)."""
    total = len(buf)
    unpack = _RECORD.unpack_from
    message = on.message
    get = on.routes.get if on.routes is not None else None  # Handlers.route, inlined
    count, most = budget.records, budget.limits.max_records
    pos = 0
    try:
        while pos < total:
            if pos + _RECORD.size > total:
                raise Damaged("a record header runs past the chunk")
            op, length = unpack(buf, pos)
            start = pos + _RECORD.size
            pos = start + length
            if pos > total:
                raise Damaged("a record runs past the chunk")
            count += 1
            if count > most:
                budget.records = count - 1
                budget.record()  # raises Refused
            if op == OP_MESSAGE:
                if length < _MESSAGE.size:
                    raise Damaged("a message record is too short")
                channel_id = buf[start] | buf[start + 1] << 8
                if get is None:
                    message(channel_id, buf[start + _MESSAGE.size : pos])
                elif (read := get(channel_id)) is not None:
                    read(buf[start + _MESSAGE.size : pos])
            elif op == OP_CHANNEL:
                _channel(buf, start, pos, on)
    finally:
        budget.records = count


def _attachment(buf: memoryview, start: int, end: int, on: Handlers) -> None:
    if start + 16 > end:
        raise Damaged("an attachment record is too short")
    name, p = _string(buf, start + 16, end)
    _, p = _string(buf, p, end)
    if p + 8 > end:
        raise Damaged("attachment data runs past its record")
    (n,) = _U64.unpack_from(buf, p)
    if p + 8 + n > end:
        raise Damaged("attachment data runs past its record")
    data = bytes(buf[p + 8 : p + 8 + n])
    if p + 8 + n + 4 <= end:  # the CRC of every field before it (0: none)
        (crc,) = _U32.unpack_from(buf, p + 8 + n)
        if crc and zlib.crc32(buf[start : p + 8 + n]) != crc:
            raise Damaged(f"attachment {name!r} CRC mismatch")
    on.attachment(name, data)


def _check_data_crc(
    buf: memoryview, pos: int, start: int, end: int, walk: _Walk, chunks: _ChunksAhead
) -> None:
    """The data section's CRC (every byte before the data-end record), when the writer
    computed one (0: none)."""
    if end - start < 4:
        raise Damaged("the data-end record is too short")
    (crc,) = _U32.unpack_from(buf, start)
    if crc:
        walk.data_crc_checked = True
        if chunks.data_crc(pos) != crc:
            raise Damaged("the data section's CRC does not match its bytes")


_FOOTER_AT_END = _RECORD.size + 20 + len(MAGIC)
"""Bytes from a footer record's opcode to the end of a complete file."""


def is_complete(data: bytes | memoryview) -> bool:
    """Whether the file ends as a writer that finished it ends it: the footer record, then the
    magic bytes."""
    if len(data) < len(MAGIC) + _FOOTER_AT_END or bytes(data[-len(MAGIC):]) != MAGIC:
        return False
    op, length = _RECORD.unpack_from(data, len(data) - _FOOTER_AT_END)
    return bool(op == OP_FOOTER and length == 20)


def scan(data: bytes, on: Handlers, limits: ReadLimits | None = None) -> ScanResult:
    """Walk the records of the MCAP file ``data`` (starting with the magic bytes), calling
    ``on``'s handlers. Stops at the footer (clean) or at the first incomplete or damaged
    record (``problem`` says which, and where; ``complete`` says whether the file ends with its
    footer all the same). :class:`Refused` when the file asks for more than ``limits``
    (default :meth:`ReadLimits.from_environment`); the handlers' own exceptions propagate."""
    buf = memoryview(data)
    budget = _Budget(limits or ReadLimits.from_environment())
    chunks = _ChunksAhead(buf, len(MAGIC), budget)
    walk = _Walk(len(MAGIC))
    complete = is_complete(buf)
    try:
        result = _records(buf, len(MAGIC), on, chunks=chunks, walk=walk)
    except (Damaged, struct.error, UnicodeDecodeError) as exc:
        return ScanResult(False, f"damaged record at byte {walk.pos}: {exc}", complete)
    finally:
        chunks.cancel()
    return ScanResult(result.clean, result.problem, complete)
