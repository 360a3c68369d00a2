"""Hostile files, made on purpose: what the reliability tests and ``benchmarks/hostile_inputs.py``
feed calstation to check that it refuses them within bounds (docs/reliability.md).

- :func:`decompression_bomb`: a finished MCAP file whose chunks inflate far past their size
  (zstd or lz4), declaring their true size or lying about it.
- :func:`flip_byte`: a file with one bit of one byte changed, as a bad disk or copy leaves it.
"""

from __future__ import annotations

import io
import struct
from collections.abc import Iterator
from pathlib import Path

MAGIC = b"\x89MCAP0\r\n"
MiB = 1 << 20


def _record(op: int, body: bytes) -> bytes:
    return struct.pack("<BQ", op, len(body)) + body


def _string(text: str) -> bytes:
    return struct.pack("<I", len(text)) + text.encode()


def _zeros(total: int) -> Iterator[bytes]:
    """``total`` bytes of records: one message, on a channel nobody registered, of zeros."""
    yield struct.pack("<BQ", 0x05, total - 9)
    left = total - 9
    block = bytes(8 * MiB)
    while left > 0:
        part = min(left, len(block))
        yield block[:part]
        left -= part


def _compressed(compression: str, total: int) -> bytes:
    if compression == "zstd":
        import zstandard

        out = io.BytesIO()
        writer = zstandard.ZstdCompressor().stream_writer(out, size=total, closefd=False)
        for part in _zeros(total):
            writer.write(part)
        writer.close()  # type: ignore[no-untyped-call]
        return out.getvalue()
    if compression == "lz4":
        import lz4.frame

        comp = lz4.frame.LZ4FrameCompressor()
        return b"".join([comp.begin(), *(comp.compress(p) for p in _zeros(total)), comp.flush()])
    raise ValueError(f"compression must be zstd or lz4, not {compression!r}")


def decompression_bomb(path: Path, compression: str, inflated: int, *,
                       declared: int | None = None, chunks: int = 1) -> Path:
    """Write a finished MCAP file (header, ``chunks`` chunks, data end, footer) to ``path``:
    each chunk's ``compression`` stream inflates to ``inflated`` bytes and its header declares
    ``declared`` (default: the truth). Returns ``path``."""
    body = _compressed(compression, inflated)
    size = inflated if declared is None else declared
    chunk = _record(0x06, struct.pack("<QQQI", 0, 0, size, 0) + _string(compression)
                    + struct.pack("<Q", len(body)) + body)
    data = MAGIC + _record(0x01, _string("") + _string("calstation.testing.hostile"))
    data += chunk * chunks + _record(0x0F, struct.pack("<I", 0))
    data += _record(0x02, struct.pack("<QQI", 0, 0, 0)) + MAGIC
    path.write_bytes(data)
    return path


def flip_byte(source: Path, target: Path, at: int, bit: int = 6) -> Path:
    """``source`` copied to ``target`` with bit ``bit`` of byte ``at`` flipped."""
    data = bytearray(source.read_bytes())
    data[at] ^= 1 << bit
    target.write_bytes(bytes(data))
    return target
