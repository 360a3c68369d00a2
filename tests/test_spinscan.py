"""A spin scan prepared as its lines arrive equals the one prepared from its recording."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np

from calstation.drivers import EncoderSample
from calstation.engine.spinscan import SpinScanBuilder, from_recording, remember
from calstation.recordings.reader import read_recording


def _builder_fed_from(path: Path) -> SpinScanBuilder:
    rec = read_recording(path)
    builder = SpinScanBuilder(
        rec.counts_per_revolution, rec.encoder_direction, rec.encoder_latency_s
    )
    samples = [
        EncoderSample(int(t), int(c))
        for t, c in zip(rec.encoder_t_ns, rec.encoder_count, strict=True)
    ]
    # encoder batches interleaved with the lines, as a station delivers them
    step = max(1, len(samples) // 50)
    lines = list(rec.lines())
    per_batch = max(1, len(lines) // 50)
    for k in range(0, max(len(lines), len(samples)), 1):
        if k * step < len(samples):
            builder.write_encoder(samples[k * step : (k + 1) * step])
        for line in lines[k * per_batch : (k + 1) * per_batch]:
            builder.write_line(line)
    return builder


def test_prepared_while_scanning_equals_prepared_from_the_file(sim_run) -> None:
    spin = sim_run()["spin"]
    live = _builder_fed_from(spin).finish()
    # not remembered: the recording is prepared from its points
    read = from_recording(read_recording(spin))
    assert live.n_points == read.n_points > 100_000
    assert np.allclose(live.p_L, read.p_L, atol=1e-12)
    assert np.allclose(live.phi, read.phi, atol=1e-12)
    assert np.array_equal(live.static, read.static)
    assert math.isclose(live.noise, read.noise, rel_tol=1e-9)
    assert live.timings["during_scan"] > 0


def test_a_remembered_scan_is_used_only_while_its_file_is_unchanged(sim_run, tmp_path) -> None:
    path = tmp_path / "spin.mcap"
    shutil.copy(sim_run()["spin"], path)
    builder = _builder_fed_from(path)
    remember(path, builder)
    assert from_recording(read_recording(path)) is builder.finish()
    # the file is replaced (a new attempt written to the same name): read it again
    data = path.read_bytes()
    path.unlink()
    path.write_bytes(data + b"\0")
    assert from_recording(read_recording(path)) is not builder.finish()


def test_several_fine_tunings_of_one_recording_prepare_it_once(sim_run) -> None:
    rec = read_recording(sim_run()["spin"])
    first = from_recording(rec)
    assert from_recording(rec) is first
    # another reading of the file is prepared on its own
    assert from_recording(read_recording(sim_run()["spin"])) is not first
