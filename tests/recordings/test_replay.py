"""Replay drivers: a recording played back as if it were hardware."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from calstation import plugins
from calstation.clock import HostClock
from calstation.drivers import (
    DriverContext,
    Encoder,
    EncoderSample,
    Lidar,
    LidarInfo,
    LidarLine,
    Turntable,
    TurntableState,
    TurntableStatus,
)
from calstation.errors import DriverError
from calstation.plugins.builtin import replay
from calstation.recordings.reader import read_recording
from calstation.recordings.recorded import Recording
from calstation.recordings.writer import RecordingWriter
from calstation.station.acquisition import acquire_spin, acquire_static
from tests.support.paths import RECIPES

T0 = 1_767_225_600_000_000_000
MS = 1_000_000
CPR = 4096
INFO = LidarInfo("acme", "line-1", "SN1", 1.2566, 100, 1000.0, 0.2, 10.0)


def _factories() -> dict[tuple[str, str], Any]:
    found: dict[tuple[str, str], Any] = {}
    replay.calstation_register_drivers(register=lambda k, n, f: found.__setitem__((k, n), f))
    return found


def _drivers(path: Path, **settings: Any) -> tuple[Any, Any, Any, DriverContext]:
    f = _factories()
    ctx = DriverContext(clock=HostClock())
    s = {"path": str(path), **settings}
    return (
        f[("lidar", "replay")](s, ctx),
        f[("turntable", "replay")](s, ctx),
        f[("encoder", "replay")](s, ctx),
        ctx,
    )


def _line(t_ns: int, k: int) -> LidarLine:
    rng = np.random.default_rng(k)
    return LidarLine(
        timestamp_ns=t_ns,
        azimuth_rad=np.linspace(-0.6, 0.6, 100),
        range_m=1.0 + 0.01 * rng.random(100),
        valid=rng.random(100) > 0.1,
        point_period_ns=9000.0,
    )


def _writer(path: Path, kind: str) -> RecordingWriter:
    return RecordingWriter(
        path, kind=kind, lidar_info=INFO, counts_per_revolution=CPR, encoder_direction=1
    )


def _synthetic_spin(path: Path, rpm: float = 60.0) -> None:
    """Turntable ramping to ``rpm`` at 120 rpm/s, encoder at 1 kHz, lines from 0.6 s to 2.9 s."""

    def revs(t: float) -> float:
        ramp = rpm / 120.0
        if t < ramp:
            return 120.0 * t * t / 2 / 60.0
        return (120.0 * ramp * ramp / 2 + rpm * (t - ramp)) / 60.0

    with _writer(path, "spin") as w:
        for k in range(60):
            t = k * 0.05
            w.write_turntable(
                TurntableStatus(T0 + k * 50 * MS, TurntableState.MOVING, min(rpm, 120.0 * t))
            )
        w.write_encoder(
            EncoderSample(T0 + k * MS, round(revs(k / 1000) * CPR)) for k in range(3000)
        )
        for k in range(2300):
            w.write_line(_line(T0 + 600 * MS + k * MS, k))


def _assert_same_lines(a: Recording, b: Recording) -> None:
    assert a.n_lines == b.n_lines
    np.testing.assert_array_equal(a.line_timestamp_ns, b.line_timestamp_ns)
    np.testing.assert_array_equal(a.t_ns, b.t_ns)
    np.testing.assert_array_equal(a.azimuth_rad, b.azimuth_rad)
    np.testing.assert_array_equal(a.range_m, b.range_m)
    np.testing.assert_array_equal(a.valid, b.valid)


def test_registered_as_builtin_plugin() -> None:
    assert "calstation.plugins.builtin.replay" in plugins.DEFAULT_PLUGINS
    assert set(_factories()) == {("lidar", "replay"), ("turntable", "replay"),
                                 ("encoder", "replay")}


def test_replay_delivers_recorded_data(tmp_path: Path) -> None:
    path = tmp_path / "spin.mcap"
    _synthetic_spin(path)
    rec = read_recording(path)
    lidar, turntable, encoder, ctx = _drivers(path)
    assert isinstance(lidar, Lidar)
    assert isinstance(turntable, Turntable)
    assert isinstance(encoder, Encoder)
    assert lidar.info() == INFO and encoder.counts_per_revolution == CPR
    assert lidar.clock is turntable.clock is encoder.clock  # one session, one time base
    assert len(ctx.shared["replay"]) == 1

    lidar.start()
    got: list[LidarLine] = []
    samples: list[EncoderSample] = []
    for line in lidar.lines():
        got.append(line)
        new = encoder.samples()
        # readings up to the end of the line just delivered (one line period: 1 ms), not beyond
        end = line.timestamp_ns + MS
        assert all(s.timestamp_ns <= end for s in new)
        samples += new
        if len(got) == 10:
            assert samples[-1].timestamp_ns == T0 + 610 * MS
    samples += encoder.samples()
    lidar.stop()
    assert len(got) == rec.n_lines
    for a, b in zip(got, rec.lines(), strict=True):
        assert a.timestamp_ns == b.timestamp_ns and a.point_period_ns == b.point_period_ns
        np.testing.assert_array_equal(a.range_m, b.range_m)
        np.testing.assert_array_equal(a.point_times_ns(), b.point_times_ns())
    # after the last line the clock is at the recording's end: every reading was handed out
    assert samples == rec.encoder_samples()
    st = turntable.status()
    assert st.speed_rpm == 60.0 and st.state is TurntableState.MOVING


def test_acquisition_over_replay_reproduces_the_recording(tmp_path: Path) -> None:
    """The acquisition loop re-run on replayed hardware gives the same data, twice over."""
    source = tmp_path / "source.mcap"
    _synthetic_spin(source)
    outputs = []
    for gen, src in enumerate([source, tmp_path / "gen0.mcap"]):
        lidar, turntable, encoder, _ = _drivers(src)
        out = tmp_path / f"gen{gen}.mcap"
        with _writer(out, "spin") as w:
            acquire_spin(lidar, turntable, encoder, w, rpm=60.0, revolutions=1.05,
                         settle_s=0.1, clock=lidar.clock)
        outputs.append(read_recording(out))
    first, second = outputs
    _assert_same_lines(first, second)
    np.testing.assert_array_equal(first.encoder_t_ns, second.encoder_t_ns)
    np.testing.assert_array_equal(first.encoder_count, second.encoder_count)
    # the first generation is the source's scan, cut where 1.05 turns were covered
    original = read_recording(source)
    n = first.n_lines
    assert 1000 < n < original.n_lines
    np.testing.assert_array_equal(first.line_timestamp_ns, original.line_timestamp_ns[:n])
    np.testing.assert_array_equal(first.range_m, original.range_m[: n * 100])
    turns = (first.encoder_count[-1] - first.encoder_count[0]) / CPR
    assert turns >= 1.05
    # time-ordered; only the final reading may repeat (the acquisition's closing read())
    assert np.all(np.diff(first.encoder_t_ns[:-1]) > 0)
    assert first.encoder_t_ns[-1] >= first.encoder_t_ns[-2]


def test_static_replay_in_folder_follows_fixtures(tmp_path: Path) -> None:
    with _writer(tmp_path / "static.mcap", "static") as w:
        w.write_encoder([EncoderSample(T0 - 5 * MS, 77)])
        for k in range(30):
            w.write_line(_line(T0 + k * MS, 1000 + k))
    _synthetic_spin(tmp_path / "spin.mcap")
    lidar, turntable, encoder, ctx = _drivers(tmp_path)
    out = tmp_path / "out" / "static.mcap"
    with _writer(out, "static") as w:
        acquire_static(lidar, encoder, w, lines=30)
    _assert_same_lines(read_recording(out), read_recording(tmp_path / "static.mcap"))
    st = turntable.status()  # no recorded status: derived from the (still) encoder
    assert st.speed_rpm == 0.0 and st.position_rad == pytest.approx(2 * np.pi * 77 / CPR)

    replay.calstation_fixture_placed(context=ctx, fixture="spin_target", geometry=None)
    assert lidar.clock.now_ns() == T0  # the spin recording starts with its first status
    lidar.start()
    first = next(iter(lidar.lines()))
    assert first.timestamp_ns == T0 + 600 * MS
    with pytest.raises(DriverError, match=r"cube\.mcap is missing"):
        replay.calstation_fixture_placed(context=ctx, fixture="qa_cube", geometry=None)


def test_realtime_replay_takes_the_recorded_time(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "rt.mcap"
    with _writer(path, "static") as w:
        w.write_encoder([EncoderSample(T0, 0)])
        for k in range(40):
            w.write_line(_line(T0 + k * 2 * MS, k))  # 80 ms of lines
    lidar, _, _, _ = _drivers(path, realtime=True)
    lidar.start()
    t = time.monotonic()
    n = sum(1 for _ in lidar.lines())
    elapsed = time.monotonic() - t
    assert n == 40
    assert elapsed >= 0.075
    lidar2, _, _, _ = _drivers(path)
    lidar2.start()
    waited: list[float] = []
    monkeypatch.setattr(time, "sleep", waited.append)
    assert sum(1 for _ in lidar2.lines()) == 40  # as fast as it reads: it never waits
    assert waited == []


def test_bad_settings(tmp_path: Path) -> None:
    f = _factories()[("lidar", "replay")]
    ctx = DriverContext(clock=HostClock())
    with pytest.raises(DriverError, match="'path'"):
        f({}, ctx)
    with pytest.raises(DriverError, match="unknown setting"):
        f({"path": "x.mcap", "speed": 2}, ctx)
    with pytest.raises(DriverError, match="realtime"):
        f({"path": "x.mcap", "realtime": "yes"}, ctx)
    with pytest.raises(DriverError, match=r"missing\.mcap does not exist"):
        f({"path": str(tmp_path / "missing.mcap")}, ctx)
    bad = tmp_path / "bad.mcap"
    bad.write_text("not mcap")
    with pytest.raises(DriverError, match="not an MCAP file"):
        f({"path": str(bad)}, ctx)
    with pytest.raises(DriverError, match="holds none of"):
        f({"path": str(tmp_path)}, ctx)
    lidar_path = tmp_path / "ok.mcap"
    with _writer(lidar_path, "static") as w:
        w.write_line(_line(T0, 0))
    lidar = f({"path": str(lidar_path)}, ctx)
    with pytest.raises(DriverError, match="before start"):
        next(iter(lidar.lines()))


def test_simulated_run_replays_identically(
    sim_run: Any, tmp_path: Path
) -> None:
    """A simulated run's folder replayed through the acquisition loops gives the same scans."""
    from calstation.recipes import load_recipe

    paths = sim_run()
    steps = load_recipe(RECIPES / "sim-periodicity.yaml").recipe.steps
    lidar, turntable, encoder, ctx = _drivers(paths["spin"].parent)
    for fixture, name in [("static_target", "static"), ("spin_target", "spin")]:
        replay.calstation_fixture_placed(context=ctx, fixture=fixture, geometry=None)
        out = tmp_path / f"{name}.mcap"
        with RecordingWriter(out, kind=name, lidar_info=lidar.info(),
                             counts_per_revolution=encoder.counts_per_revolution,
                             encoder_direction=1) as w:
            if name == "static":
                acquire_static(lidar, encoder, w, lines=steps.static_scan.lines)
            else:
                scan = steps.spin_scan
                acquire_spin(lidar, turntable, encoder, w, rpm=scan.rpm,
                             revolutions=scan.revolutions, settle_s=scan.settle_s,
                             clock=lidar.clock)
        original, replayed = read_recording(paths[name]), read_recording(out)
        _assert_same_lines(original, replayed)
        k = len(original.encoder_t_ns)
        np.testing.assert_array_equal(replayed.encoder_t_ns[:k], original.encoder_t_ns)
        np.testing.assert_array_equal(replayed.encoder_count[:k], original.encoder_count)
        # at most the closing reading is repeated once more
        assert len(replayed.encoder_t_ns) - k <= 1
        assert replayed.turntable == original.turntable
