"""A spin scan prepared as its lines arrive equals the one prepared from its recording; the
static test against its definition."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from calstation.drivers import EncoderSample
from calstation.engine import spinscan
from calstation.engine.spinscan import SpinScanBuilder, from_recording, static_of_cells
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
    read = from_recording(read_recording(spin))
    assert live.n_points == read.n_points > 100_000
    assert np.allclose(live.p_L, read.p_L, atol=1e-12)
    assert np.allclose(live.phi, read.phi, atol=1e-12)
    assert np.array_equal(live.static, read.static)
    assert math.isclose(live.noise, read.noise, rel_tol=1e-9)
    assert live.timings["during_scan"] > 0


def _interleaved(builder: SpinScanBuilder, samples: list[EncoderSample], lines: list,
                 batches: int = 50, hold_back_every: int = 0) -> list[int]:
    """Feed ``batches`` encoder batches interleaved with the lines; with ``hold_back_every``,
    every so many batches hand their first reading over with the next batch, after newer ones
    (as a driver's queue can). Returns :meth:`SpinScanBuilder.lines_ready` after each batch."""
    step = max(1, len(samples) // batches)
    per_batch = max(1, len(lines) // batches)
    held: list[EncoderSample] = []
    ready = []
    for k in range(max(batches, len(samples) // step + 1)):
        batch = samples[k * step : (k + 1) * step]
        if hold_back_every and k % hold_back_every == 1 and len(batch) > 2:
            batch, late = batch[1:], batch[:1]
        else:
            late = []
        builder.write_encoder(batch + held)
        held = late
        for line in lines[k * per_batch : (k + 1) * per_batch]:
            builder.write_line(line)
        ready.append(builder.lines_ready)
    builder.write_encoder(held)
    return ready


def _unfed(rec: Any) -> tuple[list[EncoderSample], list[Any], SpinScanBuilder]:
    """A recording's encoder readings and lines, and a builder for it that has been fed none."""
    samples = [EncoderSample(int(t), int(c))
               for t, c in zip(rec.encoder_t_ns, rec.encoder_count, strict=True)]
    builder = SpinScanBuilder(rec.counts_per_revolution, rec.encoder_direction,
                              rec.encoder_latency_s)
    return samples, list(rec.lines()), builder


def test_readings_handed_over_late_are_put_in_their_place(sim_run) -> None:
    rec = read_recording(sim_run()["spin"])
    samples, lines, builder = _unfed(rec)
    ready = _interleaved(builder, samples[: len(samples) // 2], lines[: len(lines) // 2],
                         hold_back_every=3)
    # the scan so far goes on growing through the late readings (it once stopped for good)
    assert ready[-1] > ready[len(ready) // 2] > 0
    half = builder.so_far()
    assert half is not None and half.n_points > 10_000 and np.isfinite(half.phi).all()
    first_phi = half.phi.copy()
    _interleaved(builder, samples[len(samples) // 2 :], lines[len(lines) // 2 :],
                 hold_back_every=3)
    live = builder.finish()
    read = from_recording(rec)
    assert live.n_points == read.n_points
    assert np.allclose(live.phi, read.phi, atol=1e-12)
    assert np.allclose(live.p_L, read.p_L, atol=1e-12)
    # a fit handed the first half keeps its arrays: the angles found again went to new ones
    assert np.array_equal(half.phi, first_phi)


def _readings_from_the_third_line(rec: Any, lines: list[Any]) -> list[EncoderSample]:
    """The recording's encoder readings from just after the third line began (on the lidar's
    clock): the first lands inside that line."""
    start = int(lines[2].timestamp_ns) + 1
    return [EncoderSample(int(t), int(c))
            for t, c in zip(rec.encoder_t_ns, rec.encoder_count, strict=True)
            if t - rec.encoder_latency_s * 1e9 >= start]


def test_lines_that_begin_before_the_first_reading_do_not_hold_the_scan_back(sim_run) -> None:
    rec = read_recording(sim_run()["spin"])
    lines = list(rec.lines())
    # the encoder's first reading lands inside the third line: the returns before it have no
    # angle, and the lines after it are prepared as their readings arrive
    samples = _readings_from_the_third_line(rec, lines)
    builder = SpinScanBuilder(rec.counts_per_revolution, rec.encoder_direction,
                              rec.encoder_latency_s)
    ready = _interleaved(builder, samples[: len(samples) // 2], lines[: len(lines) // 2])
    assert ready[-1] > len(lines) // 4
    so_far = builder.so_far()
    assert so_far is not None and np.isfinite(so_far.phi).all()
    # the returns of the first two lines have no angle: none of them is in the scan
    first_two = int(np.sum(lines[0].valid)) + int(np.sum(lines[1].valid))
    assert so_far.n_points < int(sum(np.sum(ln.valid) for ln in lines[:ready[-1]])) - first_two + 1


def test_lines_wait_for_the_platter_to_move_before_their_angles_are_found(sim_run) -> None:
    """The first readings of a slow platter can hold one count: an angle found from them alone
    would be that count's for every time, even outside their span, where the whole recording
    gives none (the returns before the first reading) — the scan prepared as it arrives must
    equal the one prepared with every reading."""
    rec = read_recording(sim_run()["spin"])
    lines = list(rec.lines())
    samples = _readings_from_the_third_line(rec, lines)
    # the first three readings hold the first one's count (the platter had not moved a count)
    samples[1:3] = [EncoderSample(s.timestamp_ns, samples[0].count) for s in samples[1:3]]

    def builder() -> SpinScanBuilder:
        return SpinScanBuilder(rec.counts_per_revolution, rec.encoder_direction,
                               rec.encoder_latency_s)

    live = builder()
    live.write_encoder(samples[:3])
    for line in lines[:20]:
        live.write_line(line)
    _interleaved(live, samples[3:], lines[20:])
    everything = builder()
    everything.write_encoder(samples)
    for line in lines:
        everything.write_line(line)
    a, b = live.finish(), everything.finish()
    assert a.n_points == b.n_points
    assert np.array_equal(a.phi, b.phi)


def test_the_first_lines_of_a_scan_are_the_scan_handed_out_at_those_lines(sim_run) -> None:
    """What a fit made while scanning kept with the scan it was handed (its ``memo``) reaches
    the step after the scan, which takes the same lines: the same object, until a late reading
    finds their angles again."""
    rec = read_recording(sim_run()["spin"])
    samples, lines, builder = _unfed(rec)
    builder.write_encoder(samples[: len(samples) // 2])
    for line in lines[: len(lines) // 3]:
        builder.write_line(line)
    handed = builder.so_far()
    assert handed is not None
    ready = builder.lines_ready
    handed.memo["kept"] = True
    builder.write_encoder(samples[len(samples) // 2 :])
    for line in lines[len(lines) // 3 :]:
        builder.write_line(line)
    assert builder.first_lines(ready) is handed
    assert builder.first_lines(ready).memo["kept"] is True
    again = from_recording(rec.first_lines(ready))
    assert np.array_equal(handed.phi, again.phi) and np.array_equal(handed.p_L, again.p_L)

    late = _unfed(rec)[2]
    late.write_encoder(samples[: len(samples) // 2 : 2])
    for line in lines[: len(lines) // 3]:
        late.write_line(line)
    first = late.so_far()
    assert first is not None
    at = late.lines_ready
    late.write_encoder(samples[1 : len(samples) // 2 : 2])  # late: between those handed over
    late.write_encoder(samples[len(samples) // 2 :])
    for line in lines[len(lines) // 3 :]:
        late.write_line(line)
    assert late.first_lines(at) is not first


@pytest.mark.parametrize("dense", [True, False])
def test_the_static_test_counts_each_returns_bin_and_window(
    dense: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Against the definition, return by return: static when at least 60 % of its azimuth
    bin's returns lie within two range cells of its own; the dense count and the sparse one
    (a grid past DENSE_LIMIT) alike, on bins and cells that do not start at 0."""
    rng = np.random.default_rng(3)
    n = 4000
    b = rng.integers(-7, 5, n).astype(np.int32)
    c = np.where(rng.random(n) < 0.7, 500 + rng.integers(-2, 2, n),
                 rng.integers(300, 900, n)).astype(np.int32)
    c[b == 4] = rng.integers(300, 900, int((b == 4).sum()))  # a bin with nothing static
    if not dense:
        monkeypatch.setattr(spinscan, "DENSE_LIMIT", 0)
    got = static_of_cells(b, c)
    same_bin = b[:, None] == b[None, :]
    near = (same_bin & (np.abs(c[:, None] - c[None, :]) <= 2)).sum(axis=1)
    want = near >= 0.6 * same_bin.sum(axis=1)
    assert 0.3 < want.mean() < 0.9 and not want[b == 4].any()
    assert np.array_equal(got, want)
