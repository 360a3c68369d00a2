"""Recordings written line by line with made-up, deterministic lines (the writer's tests, and the
process that is killed while it writes one), and a recording fed to a scan builder as a station
feeds it."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from calstation.drivers import LidarInfo, LidarLine
from calstation.recordings.writer import RecordingWriter

if TYPE_CHECKING:
    from calstation.engine.spinscan import SpinScanBuilder
    from calstation.recordings.recorded import Recording

T0 = 1_767_225_600_000_000_000


INFO = LidarInfo("acme", "line-1", "SN42", np.deg2rad(72.0), 100, 1000.0, 0.2, 10.0, {"fw": "1.2"})


def make_line(i: int, n: int = 100, *, offsets: bool = False, intensity: bool = False) -> LidarLine:
    """A deterministic line: values depend on the line index so a prefix can be checked."""
    rng = np.random.default_rng(i)
    return LidarLine(
        timestamp_ns=T0 + i * 1_000_000,
        azimuth_rad=np.linspace(-0.6, 0.6, n) + 1e-12 * i,
        range_m=1.0 + 0.01 * rng.standard_normal(n),
        valid=rng.random(n) > 0.05,
        point_period_ns=1000.0 / 3.0,
        time_offset_ns=np.arange(n, dtype=np.int64) * 7 if offsets else None,
        intensity=rng.random(n) * 100 if intensity else None,
    )


def writer(path: Path, **kw: object) -> RecordingWriter:
    """A spin-scan writer for the lines of :func:`make_line`; ``kw`` overrides its arguments."""
    args: dict[str, object] = {
        "kind": "spin",
        "lidar_info": INFO,
        "counts_per_revolution": 4096,
        "encoder_direction": 1,
    }
    args.update(kw)
    return RecordingWriter(path, **args)  # type: ignore[arg-type]


def fed_builder(rec: Recording) -> SpinScanBuilder:
    """A :class:`SpinScanBuilder` fed a recording's encoder readings and then every line, as a
    station feeds one while it scans."""
    from calstation.drivers import EncoderSample
    from calstation.engine.spinscan import SpinScanBuilder

    builder = SpinScanBuilder(rec.counts_per_revolution, rec.encoder_direction,
                              rec.encoder_latency_s)
    builder.write_encoder(EncoderSample(int(t), int(c))
                          for t, c in zip(rec.encoder_t_ns, rec.encoder_count, strict=True))
    for line in rec.lines():
        builder.write_line(line)
    return builder
