"""Hostile recordings: decompression bombs, damage in a finished file, impossible timing.

A bomb is refused before it is decompressed (or as soon as it inflates past what a scan does),
in a process whose peak memory stays at a few hundred MB; damage in a file that ends with its
footer is an error naming the file and the place, never half of the scan; a truncated write is
still read up to its last complete chunk; line times that go backwards and an encoder that jumps
faster than a turntable turns are refused naming the line or the reading.
"""

from __future__ import annotations

import json
import struct
import subprocess
import sys
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from calstation.drivers import EncoderSample, LidarInfo, LidarLine
from calstation.errors import RecordingError
from calstation.recordings.reader import RecordingTruncatedWarning, read_recording
from calstation.recordings.writer import RecordingWriter

MAGIC = b"\x89MCAP0\r\n"
MiB = 1 << 20
T0 = 1_767_225_600_000_000_000
INFO = LidarInfo("acme", "line-1", "SN1", 1.2566, 200, 100.0, 0.2, 10.0)


def recording(path: Path, lines: int = 120, encoder: Callable[[int], int] | None = None,
              line_time: Callable[[int], int] | None = None) -> Path:
    """A small spin recording: ``lines`` lines of 200 points, 1 kHz encoder readings turning
    at 30 rpm (``encoder(k)`` gives reading k's count instead, ``line_time(i)`` line i's time)."""
    rng = np.random.default_rng(5)
    count = encoder or (lambda k: round(4096 * 0.5 * k / 1000))
    stamp = line_time or (lambda i: T0 + 50_000_000 + i * 10_000_000)
    with RecordingWriter(path, kind="spin", lidar_info=INFO, counts_per_revolution=4096,
                         encoder_direction=1) as w:
        w.write_encoder(EncoderSample(T0 + k * 1_000_000, count(k)) for k in range(1400))
        for i in range(lines):
            w.write_line(LidarLine(timestamp_ns=stamp(i), azimuth_rad=np.linspace(-0.6, 0.6, 200),
                                   range_m=1.1 + 0.3 * rng.random(200),
                                   valid=np.ones(200, bool), point_period_ns=40_000.0))
    return path


# --- decompression bombs -------------------------------------------------------------------
def bomb(path: Path, compression: str, inflated: int, declared: int | None = None,
         chunks: int = 1) -> Path:
    from calstation.testing.hostile import decompression_bomb

    return decompression_bomb(path, compression, inflated, declared=declared, chunks=chunks)


READ = """
import json, sys, time
from calstation.errors import RecordingError
from calstation.recordings.reader import read_recording
t0 = time.process_time()
try:
    read_recording(sys.argv[1]); said = None
except RecordingError as exc:
    said = str(exc)
# VmHWM: this program's own peak (ru_maxrss would keep the forking parent's)
hwm = next(ln for ln in open("/proc/self/status") if ln.startswith("VmHWM:"))
print(json.dumps({"error": said, "cpu_s": time.process_time() - t0,
                  "peak_mb": int(hwm.split()[1]) / 1024}))
"""


def read_in_a_process(path: Path, **env: str) -> dict[str, object]:
    """``read_recording(path)`` in a process of its own: the error, its CPU time and its peak
    memory (its own, not the test's)."""
    import os

    proc = subprocess.run([sys.executable, "-c", READ, str(path)], capture_output=True,
                          text=True, timeout=600, env={**os.environ, **env})
    assert proc.returncode == 0, proc.stderr[-3000:]
    return dict(json.loads(proc.stdout.strip().splitlines()[-1]))


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_a_chunk_declaring_a_gigabyte_is_refused_before_it_is_decompressed(
    tmp_path: Path, compression: str
) -> None:
    path = bomb(tmp_path / f"bomb-{compression}.mcap", compression, 1024 * MiB)
    assert path.stat().st_size < 5 * MiB
    got = read_in_a_process(path)
    assert got["error"] is not None and str(path) in str(got["error"])
    assert "declares 1,073,741,824 bytes" in str(got["error"]) and "refused" in str(got["error"])
    assert float(got["peak_mb"]) < 300, got  # a 1 GiB inflation would show


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_a_chunk_that_lies_about_its_size_is_never_decompressed_past_it(
    tmp_path: Path, compression: str
) -> None:
    """The chunk declares 1 MiB; its compressed stream (whose own header says 1 GiB for zstd)
    inflates to a gigabyte: decompression stops past the declared size."""
    path = bomb(tmp_path / f"liar-{compression}.mcap", compression, 1024 * MiB, declared=MiB)
    got = read_in_a_process(path)
    assert got["error"] is not None and str(path) in str(got["error"])
    assert "inflates past the 1048576 bytes its header declares" in str(got["error"])
    assert float(got["peak_mb"]) < 300, got


def test_many_chunks_inflating_like_no_scan_are_refused(tmp_path: Path) -> None:
    path = bomb(tmp_path / "chunks.mcap", "zstd", 16 * MiB, chunks=40)  # 640 MiB in all
    got = read_in_a_process(path)
    assert "inflate" in str(got["error"]) and "a decompression bomb?" in str(got["error"])
    assert float(got["peak_mb"]) < 400, got


def test_a_file_of_more_records_than_the_setting_is_refused(tmp_path: Path) -> None:
    path = recording(tmp_path / "r.mcap", lines=600)  # 1,200 messages and more
    got = read_in_a_process(path, CALSTATION_MCAP_MAX_RECORDS="1000")
    assert "more than 1,000 records" in str(got["error"]), got
    assert read_in_a_process(path)["error"] is None  # the default reads it
    bad = read_in_a_process(path, CALSTATION_MCAP_MAX_CHUNK_MB="none")
    assert "CALSTATION_MCAP_MAX_CHUNK_MB='none'" in str(bad["error"])


# --- damage in a finished file -------------------------------------------------------------
def _same(a: object, b: object) -> bool:
    return all(np.array_equal(getattr(a, k), getattr(b, k), equal_nan=True)
               for k in ("line_timestamp_ns", "azimuth_rad", "range_m", "valid",
                         "encoder_t_ns", "encoder_count"))


def test_a_flipped_byte_in_a_finished_file_is_damage_never_half_a_scan(tmp_path: Path) -> None:
    """A byte flipped in turn at 150 places spread over the file: each read is an error naming
    the file, or the whole scan as written (a flip in a part of the summary the reader skips);
    never a partial read taken for a killed writer's file."""
    path = recording(tmp_path / "r.mcap", lines=600)
    data = path.read_bytes()
    whole = read_recording(path)
    damaged = 0
    places = range(len(MAGIC), len(data) - len(MAGIC), len(data) // 150 + 1)
    for at in places:
        flipped = bytearray(data)
        flipped[at] ^= 0x40
        bad = tmp_path / "bad.mcap"
        bad.write_bytes(bytes(flipped))
        try:
            with _no_truncation():
                got = read_recording(bad)
        except RecordingError as exc:
            assert str(bad) in str(exc), exc
            damaged += 1
            continue
        assert not got.truncated and _same(got, whole), f"byte {at}: a different scan was read"
    assert damaged > 0.8 * len(places)


class _no_truncation:
    """No RecordingTruncatedWarning inside the block (a finished file is never 'truncated')."""

    def __enter__(self) -> None:
        import warnings

        self._catch = warnings.catch_warnings(record=True)
        self._seen = self._catch.__enter__()
        warnings.simplefilter("always")

    def __exit__(self, *exc: object) -> None:
        self._catch.__exit__(*exc)
        cut = [w for w in self._seen if issubclass(w.category, RecordingTruncatedWarning)]
        assert not cut, cut[0].message


def test_a_crc_mismatch_is_damage_and_a_cut_file_is_a_killed_writer(tmp_path: Path) -> None:
    path = recording(tmp_path / "r.mcap", lines=1200)  # several chunks
    data = bytearray(path.read_bytes())
    chunk = data.index(b"zstd") + 4 + 8 + 200  # inside the first chunk's compressed records
    data[chunk] ^= 0x01
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match=r"damaged\.mcap is damaged: damaged record at byte "
                                             r"\d+: .*writer finished it"):
        read_recording(damaged)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: len(data) * 2 // 3])
    with pytest.warns(RecordingTruncatedWarning, match="writer killed"):
        rec = read_recording(cut)
    assert rec.truncated and 0 < rec.n_lines < 1200


def test_a_changed_byte_outside_the_chunks_fails_the_data_sections_crc(tmp_path: Path) -> None:
    """A metadata record lies outside the chunks: a byte changed in it leaves the record
    readable, and only the data section's CRC (computed beside the chunks) can tell."""
    path = recording(tmp_path / "r.mcap", lines=1200)  # several chunks: the CRC on a worker
    data = bytearray(path.read_bytes())
    at = data.index(b"counts_per_revolution")
    assert at < data.index(b"zstd")  # the metadata is written ahead of the first chunk
    data[at] ^= 0x20  # c -> C: still a valid record, of other text
    changed = tmp_path / "changed.mcap"
    changed.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match=r"changed\.mcap is damaged: .*the data section's "
                                             r"CRC does not match its bytes"):
        read_recording(changed)


# --- timing --------------------------------------------------------------------------------
def test_line_times_that_go_backwards_are_refused_naming_the_line(tmp_path: Path) -> None:
    path = recording(tmp_path / "back.mcap",
                     line_time=lambda i: T0 + 50_000_000 + (i if i != 60 else 30) * 10_000_000)
    with pytest.raises(RecordingError, match=r"back\.mcap: lidar line 60 is stamped 290\.000 ms "
                                             r"before line 59: the line times go backwards"):
        read_recording(path)


def test_an_encoder_count_that_wrapped_at_32_bits_is_refused_naming_the_reading(
    tmp_path: Path
) -> None:
    """A driver that handed over its raw int32 counter: 2^31 − 1 wraps to −2^31."""
    start = 2**31 - 500

    def wrapped(k: int) -> int:
        c = start + round(4096 * 0.5 * k / 1000)
        return (c + 2**31) % 2**32 - 2**31

    path = recording(tmp_path / "wrap.mcap", encoder=wrapped)
    first = next(k for k in range(1400) if wrapped(k) < 0)
    with pytest.raises(RecordingError, match=rf"wrap\.mcap: encoder reading {first} is "
                                             r"4,294,967,29\d counts .* faster than any "
                                             r"turntable turns"):
        read_recording(path)


def test_an_error_inside_a_recording_names_its_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A line timing whose offsets do not fit its points (as another tool could write it):
    the error names the file."""
    from calstation.recordings import messages as pb

    path = recording(tmp_path / "r.mcap", lines=3)
    original = pb.line_timing_parts

    def other_tool(data: object) -> tuple[object, ...]:
        parts = list(original(data))  # type: ignore[arg-type]
        parts[5] = b"\x00" * 8  # one time offset for 200 points
        return tuple(parts)

    monkeypatch.setattr(pb, "line_timing_parts", other_tool)
    with pytest.raises(RecordingError, match=r"r\.mcap.*1 time offsets for 200 points"):
        read_recording(path)


def test_the_data_section_crc_is_written_and_checked(tmp_path: Path) -> None:
    path = recording(tmp_path / "r.mcap", lines=3)
    data = path.read_bytes()
    end = data.rindex(b"\x0f" + struct.pack("<Q", 4))
    (crc,) = struct.unpack_from("<I", data, end + 9)
    assert crc == zlib.crc32(data[:end]) != 0
