"""The sim drivers: protocols, registration through the plugin hooks, clock, commands, CLI."""

from __future__ import annotations

import itertools
import math
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from calstation_sim import SimEncoder, SimLidar, SimTurntable, SimulatedStation

from calstation import plugins
from calstation.clock import HostClock, SimClock
from calstation.drivers import DriverContext, Encoder, Lidar, Turntable, TurntableState
from calstation.errors import DriverError
from calstation.recipes import LoadedRecipe
from calstation.recordings.reader import read_recording


def _drivers(
    recipe: LoadedRecipe, **settings: object
) -> tuple[object, object, object, DriverContext]:
    context = DriverContext(clock=SimClock(), recipe=recipe)
    lidar = plugins.driver_factory("lidar", "sim")(settings, context)
    turntable = plugins.driver_factory("turntable", "sim")({}, context)
    encoder = plugins.driver_factory("encoder", "sim")({}, context)
    return lidar, turntable, encoder, context


def test_registered_drivers_satisfy_the_protocols_and_share_one_station(
    make_recipe: Callable[..., LoadedRecipe],
) -> None:
    lidar, turntable, encoder, context = _drivers(make_recipe(), seed=7)
    assert isinstance(lidar, Lidar) and isinstance(lidar, SimLidar)
    assert isinstance(turntable, Turntable) and isinstance(turntable, SimTurntable)
    assert isinstance(encoder, Encoder) and isinstance(encoder, SimEncoder)
    station = context.shared["sim"]
    assert isinstance(station, SimulatedStation) and station.seed == 7
    assert lidar.station is turntable.station is encoder.station is station
    assert lidar.clock is turntable.clock is encoder.clock is context.clock
    assert encoder.counts_per_revolution == 4096
    plugins.fixture_placed(context, "qa_cube", station.recipe.recipe.fixtures.qa_cube)
    assert station.current_fixture == "qa_cube"
    plugins.fixture_placed(context, "none", None)
    assert station.current_fixture == "none"


def test_unknown_driver_setting_is_an_error(make_recipe: Callable[..., LoadedRecipe]) -> None:
    with pytest.raises(DriverError, match=r"unknown setting.*speed"):
        _drivers(make_recipe(), speed=3)


def test_real_time_runs_the_station_on_the_host_clock(
    make_recipe: Callable[..., LoadedRecipe],
) -> None:
    """With ``real_time`` the lines come at the lidar's line rate and the platter turns in wall
    time, as at a real station."""
    lidar, turntable, encoder, _ = _drivers(make_recipe(), real_time=True)
    assert isinstance(lidar, SimLidar) and isinstance(turntable, SimTurntable)
    assert isinstance(encoder, SimEncoder)
    assert isinstance(lidar.clock, HostClock) and lidar.clock is turntable.clock is encoder.clock
    period_s = 1.0 / lidar.info().line_rate_hz
    start = time.monotonic()
    lidar.start()
    stamps = []
    for line in lidar.lines():
        stamps.append(line.timestamp_ns)
        if len(stamps) == 100:
            lidar.stop()
    assert time.monotonic() - start >= 99 * period_s
    assert np.allclose(np.diff(stamps), period_s * 1e9)
    turntable.enable()
    turntable.spin(60.0)
    first = encoder.read()
    time.sleep(0.4)
    last = encoder.read()
    turntable.stop()
    assert last.timestamp_ns - first.timestamp_ns >= 0.4e9
    assert last.count != first.count


def test_a_real_time_lidar_hands_over_late_lines_rather_than_drop_them(
    make_recipe: Callable[..., LoadedRecipe],
) -> None:
    """A consumer that falls behind on the host's clock (a loaded host) still gets every line,
    in order, as from a device's buffer: a scan with holes lost a station its QA cube."""
    lidar, _, _, _ = _drivers(make_recipe(), real_time=True)
    period_ns = 1e9 / lidar.info().line_rate_hz
    lidar.start()
    stamps = []
    for line in lidar.lines():
        stamps.append(line.timestamp_ns)
        if len(stamps) == 100:  # the end of a batch: the next starts while 0.3 s behind
            time.sleep(0.3)
        if len(stamps) == 250:
            lidar.stop()
    assert np.allclose(np.diff(stamps), period_ns)


def test_lidar_streams_on_a_grid_and_advances_the_clock(
    make_recipe: Callable[..., LoadedRecipe],
) -> None:
    station = SimulatedStation(make_recipe())
    lidar = SimLidar(station)
    with pytest.raises(DriverError, match="before start"):
        next(lidar.lines())
    t0 = station.clock.now_ns()
    lidar.start()
    stamps = []
    for line in lidar.lines():
        stamps.append(line.timestamp_ns)
        assert station.clock.now_ns() == line.timestamp_ns + 1_000_000  # end of the line
        if len(stamps) == 250:  # crosses a batch boundary
            lidar.stop()
    assert stamps == [t0 + k * 1_000_000 for k in range(250)]
    # time that passes between reads skips lines, as a device without a buffer would
    lidar.start()
    lines = lidar.lines()
    start = next(lines).timestamp_ns
    station.clock.sleep(0.0105)
    assert next(lines).timestamp_ns == start + 12_000_000  # first grid line not in the past


def test_a_turntable_command_mid_batch_takes_effect_at_once(
    make_recipe: Callable[..., LoadedRecipe],
) -> None:
    station = SimulatedStation(make_recipe({}, ideal=True))
    station.place("qa_cube")
    lidar, turntable = SimLidar(station), SimTurntable(station)
    turntable.enable()
    lidar.start()
    lines = lidar.lines()
    for _ in range(5):
        next(lines)  # the batch of 100 lines was cast with the platter at rest
    turntable.spin(30.0)
    station.clock.sleep(0.5)
    line = next(lines)
    fresh = station.scan_line(line.timestamp_ns)  # noise-free station: same rays, same ranges
    assert np.array_equal(line.range_m, fresh.range_m)
    assert station.platter_angle(line.timestamp_ns) > 0.0


def test_encoder_stream_is_monotonic_and_complete(make_recipe: Callable[..., LoadedRecipe]) -> None:
    station = SimulatedStation(make_recipe())
    encoder, turntable = SimEncoder(station), SimTurntable(station)
    turntable.enable()
    turntable.spin(20.0)
    station.clock.sleep(0.0105)
    a = encoder.samples()
    assert [s.timestamp_ns - station.time_origin_ns for s in a] == [
        k * 1_000_000 for k in range(11)
    ]
    now = encoder.read()
    station.clock.sleep(0.003)
    b = encoder.samples()
    t = [s.timestamp_ns for s in [*a, now, *b]]
    assert all(x < y for x, y in itertools.pairwise(t))
    assert len(b) == 3
    assert all(s.count == station.encoder_count(s.timestamp_ns) for s in [*a, now, *b])


def test_turntable_commands_and_states(make_recipe: Callable[..., LoadedRecipe]) -> None:
    station = SimulatedStation(make_recipe({"simulation.turntable.speed_ripple": 0.0}))
    tt = SimTurntable(station)
    assert tt.status().state == TurntableState.DISABLED
    with pytest.raises(DriverError, match="disabled"):
        tt.spin(10.0)
    tt.enable()
    assert tt.status().state == TurntableState.ENABLED
    tt.move_to(1.0)
    assert station.platter_angle(station.clock.now_ns()) == pytest.approx(1.0, abs=1e-6)
    assert tt.status().speed_rpm == 0.0
    tt.move_to(-3.0)  # the short way round: 1.0 → −3.0 + 2π
    assert station.platter_angle(station.clock.now_ns()) == pytest.approx(
        2 * math.pi - 3.0, abs=1e-6
    )
    tt.spin(-20.0)
    station.clock.sleep(1.0)
    status = tt.status()
    assert status.state == TurntableState.MOVING and status.speed_rpm == pytest.approx(-20.0)
    tt.stop()
    assert tt.status().speed_rpm == 0.0
    tt.spin(20.0)
    station.clock.sleep(1.0)
    tt.emergency_stop()
    assert tt.status().state == TurntableState.EMERGENCY_STOP
    assert tt.status().speed_rpm == 0.0
    with pytest.raises(DriverError, match="emergency stop"):
        tt.spin(5.0)
    tt.enable()
    tt.close()
    assert tt.status().state == TurntableState.DISABLED


def _calstation(*args: str) -> subprocess.CompletedProcess[str]:
    exe = Path(sys.executable).with_name("calstation")
    return subprocess.run([str(exe), *args], capture_output=True, text=True, timeout=300)


def test_cli_simulate_writes_a_run(
    tmp_path: Path, make_recipe: Callable[..., LoadedRecipe]
) -> None:
    recipe = make_recipe(
        {
            "simulation.lidar.points_per_line": 100,
            "steps.static_scan.lines": 10,
            "steps.spin_scan.rpm": 60,
            "steps.cube_scan.rpm": 60,
        }
    )
    out = tmp_path / "run"
    done = _calstation(
        "simulate",
        str(recipe.path),
        "--out",
        str(out),
        "--seed",
        "2",
        "--range",
        "1.0",
        "--pitch",
        "30",
        "--quiet",
    )
    assert done.returncode == 0, done.stderr
    for name in ("static.mcap", "spin.mcap", "cube.mcap", "truth.json"):
        assert (out / name).is_file()
    rec = read_recording(out / "cube.mcap")
    assert rec.truth is not None and rec.truth.ty == 1.0
    assert rec.truth.rz == pytest.approx(math.radians(-30), abs=math.radians(0.5))
    assert rec.metadata["truth"]["scenario"] == {"range_m": 1.0, "pitch_deg": 30.0}


def test_cli_simulate_reports_a_bad_recipe_cleanly(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        "name: x\nstation:\n  id: s\n  lidar: {driver: sim}\nsimulation:\n  lidar: {fov_deg: -3}\n"
    )
    done = _calstation("simulate", str(bad), "--out", str(tmp_path / "o"))
    assert done.returncode == 2
    assert "Traceback" not in done.stderr
    assert "bad.yaml" in done.stderr and "fov_deg" in done.stderr
