"""The MCAP record walker: chunks decompressed ahead of the walk, damage met where it is."""

from __future__ import annotations

import io
import struct

import pytest
from mcap.writer import CompressionType, Writer

from calstation.recordings import mcapscan


def _file(n_messages: int = 400, chunk_size: int = 2000) -> bytes:
    out = io.BytesIO()
    w = Writer(out, chunk_size=chunk_size, compression=CompressionType.ZSTD)
    w.start()
    schema = w.register_schema("s", "jsonschema", b"{}")
    channel = w.register_channel("/t", "json", schema)
    for i in range(n_messages):
        data = b'{"i": %d, "pad": "%s"}' % (i, b"x" * 40)
        w.add_message(channel, log_time=i, publish_time=i, data=data)
    w.finish()
    return out.getvalue()


def _walk(data: bytes) -> tuple[list[bytes], mcapscan.ScanResult]:
    seen: list[bytes] = []
    handlers = mcapscan.Handlers(
        channel=lambda *_: None,
        message=lambda _c, d: seen.append(bytes(d)),
        metadata=lambda *_: None,
        attachment=lambda *_: None,
    )
    return seen, mcapscan.scan(data, handlers)


def _chunk_bodies(data: bytes) -> list[tuple[int, int]]:
    spans, pos = [], len(mcapscan.MAGIC)
    while pos + 9 <= len(data):
        op, length = struct.unpack_from("<BQ", data, pos)
        if op == mcapscan.OP_CHUNK:
            spans.append((pos + 9, pos + 9 + length))
        if op == mcapscan.OP_FOOTER:
            break
        pos += 9 + length
    return spans


def test_every_message_in_order_across_many_chunks() -> None:
    data = _file()
    assert len(_chunk_bodies(data)) > 2 * mcapscan.AHEAD
    seen, result = _walk(data)
    assert result.clean
    assert [int(s.split(b",")[0].split(b":")[1]) for s in seen] == list(range(400))


@pytest.mark.parametrize("which", [0, 1, 4, -1])
def test_a_damaged_chunk_ends_the_walk_after_the_chunks_before_it(which: int) -> None:
    data = bytearray(_file())
    spans = _chunk_bodies(bytes(data))
    start, end = spans[which]
    data[end - 20] ^= 0xFF  # inside the compressed records
    seen, result = _walk(bytes(data))
    assert not result.clean and "damaged record" in result.problem
    # the messages delivered are those of the chunks before the damaged one
    assert seen == _walk(bytes(data[: start - 9]))[0]
    assert len(seen) < 400
