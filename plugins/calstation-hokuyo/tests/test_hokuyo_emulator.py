"""The driver against the SCIP 2.0 emulator over TCP and a pty: streaming, time, faults."""

from __future__ import annotations

import itertools
import math
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
from calstation_hokuyo import (
    ClockSync,
    HokuyoError,
    HokuyoLidar,
    PtyServer,
    ScipChecksumError,
    ScipParameters,
    ScipSensor,
    ScipTimeout,
    TcpServer,
    WallScene,
    scip,
)

from calstation.drivers import LidarLine


def take(lidar: HokuyoLidar, n: int) -> list[LidarLine]:
    """Stream ``n`` lines, then stop."""
    lidar.start()
    try:
        return list(itertools.islice(lidar.lines(), n))
    finally:
        lidar.stop()


def assert_on_the_scan_grid(stamps: np.ndarray, period_ns: float = 10e6) -> None:
    """Consecutive stamps whole scan periods apart (within 0.2 ms), in order: one period, or
    several where the emulator skipped scans (owed for longer than its CATCH_UP_S)."""
    periods = np.diff(stamps) / period_ns
    np.testing.assert_allclose(periods, np.round(periods), atol=0.2e6 / period_ns)
    assert (np.round(periods) >= 1).all(), periods


@pytest.fixture
def sensor() -> ScipSensor:
    return ScipSensor(WallScene(2.0))


@pytest.fixture
def server(sensor: ScipSensor) -> Iterator[TcpServer]:
    with TcpServer(sensor) as srv:
        yield srv


@pytest.fixture
def lidar(server: TcpServer) -> Iterator[HokuyoLidar]:
    drv = HokuyoLidar({"port": server.url, "timeout_s": 0.5})
    yield drv
    drv.close()


def test_gd_example_bytes_from_the_emulator() -> None:
    """PROTOCOLS.md's GD0384038500 reply, produced by the emulator with UTM-30LX parameters."""
    boot = 1_700_000_000_000_000_000
    params = ScipParameters(ares=1024, amin=44, amax=725, afrt=384, scan_rpm=600,
                            dmax_mm=5600, sensor_clock_start_ms=16_000_000 + 200)

    def scene(t_ns: int) -> LidarLine:
        az = params.step_azimuths(384, 385)
        return LidarLine(t_ns, az, np.array([5.432, 1.234]), np.array([True, True]))

    sensor = ScipSensor(scene, params, now_ns=lambda: boot)
    sensor.laser_on = True
    # the reply carries the last complete scan, which started 2 periods (200 ms) before "now"
    assert sensor.receive(b"GD0384038500\n") == b"GD0384038500\n00P\nm2@0?\n1Dh0CBB\n\n"
    assert sensor.receive(b"QT\n") == b"QT\n00P\n\n"
    assert sensor.receive(b"GD0384038500\n") == b"GD0384038500\n10Q\n\n"  # laser off
    assert sensor.receive(b"XX\n") == b"XX\n0Dd\n\n"  # undefined command


def test_pp_of_the_emulator(lidar: HokuyoLidar) -> None:
    p = lidar.parameters()
    assert (p.ares, p.amin, p.amax, p.afrt, p.scan_rpm) == (5000, 2000, 3000, 2500, 6000)
    info = lidar.info()
    assert info.points_per_line == 1001
    assert math.degrees(info.fov_rad) == pytest.approx(72.0)
    assert info.line_rate_hz == pytest.approx(100.0)


def test_streamed_lines_see_the_wall_at_the_right_azimuths_and_times(
    lidar: HokuyoLidar, sensor: ScipSensor
) -> None:
    lines = take(lidar, 20)
    assert len(lines) == 20
    for line in lines:
        assert line.valid.all()
        np.testing.assert_allclose(line.range_m, 2.0 / np.cos(line.azimuth_rad), atol=0.0011)
    first = lines[0].azimuth_rad
    assert math.degrees(first[0]) == pytest.approx(36.0)  # AMIN is +36° with azimuth_sign −1
    assert math.degrees(first[-1]) == pytest.approx(-36.0)
    stamps = np.array([line.timestamp_ns for line in lines])
    assert_on_the_scan_grid(stamps)
    # the emulator's scans start on a 10 ms grid from its power-on; the driver's stamps land on
    # it within the clock sync error
    phase = (stamps - sensor._boot_ns) % 10_000_000
    phase = np.minimum(phase, 10_000_000 - phase)
    assert phase.max() < 1.0e6
    assert lines[0].point_period_ns == pytest.approx(2000.0)


def test_ms_encoding_and_clusters(server: TcpServer) -> None:
    drv = HokuyoLidar({"port": server.url, "encoding": "S", "cluster": 4,
                       "start_step": 2400, "end_step": 2600})
    try:
        lines = take(drv, 3)
    finally:
        drv.close()
    assert len(lines[0]) == math.ceil(201 / 4)
    # a cluster reports its nearest return; 2-character values are whole millimetres ≤ 4095
    np.testing.assert_allclose(lines[0].range_m, 2.0 / np.cos(lines[0].azimuth_rad), atol=0.004)


def test_over_a_pty(sensor: ScipSensor) -> None:
    with PtyServer(sensor) as pty:
        drv = HokuyoLidar({"port": pty.url, "timeout_s": 0.5})
        try:
            assert drv.version()["PROT"] == "SCIP 2.0"
            lines = take(drv, 5)
        finally:
            drv.close()
    assert len(lines) == 5 and all(line.valid.all() for line in lines)


def _streamed_scans(reply: bytes) -> list[int]:
    """The sensor timestamps (ms) of the streamed scans in ``reply``, in order."""
    stamps = []
    for block in reply.split(b"\n\n"):
        lines = block.split(b"\n")
        if len(lines) > 3 and lines[1].startswith(b"99"):
            stamps.append(scip.decode_value(lines[2][:4]))
    return stamps


@pytest.mark.parametrize("skip", [0, 2])
def test_scans_the_emulator_computed_late_are_sent_in_order(skip: int) -> None:
    """An emulator starved for 0.3 s (30 scans) by a loaded host owes those scans: the sensor
    measured them on time, so they come late and in order, on the request's grid; only scans
    owed for longer than CATCH_UP_S are skipped."""
    from calstation_hokuyo import emulator

    now = [1_000_000_000_000]
    sensor = ScipSensor(WallScene(2.0), now_ns=lambda: now[0])
    assert sensor.receive(f"MD2000300000{skip}00\n".encode()).endswith(b"00P\n\n")
    now[0] += 300_000_000
    sent = b"".join(iter(sensor.poll, b""))
    stamps = np.diff(_streamed_scans(sent))
    assert len(stamps) >= 28 // (skip + 1) - 1
    assert (stamps == 10 * (skip + 1)).all(), stamps
    # a stall longer than the catch-up window: the scans older than it are skipped
    now[0] += round((emulator.CATCH_UP_S + 1.0) * 1e9)
    late = _streamed_scans(b"".join(iter(sensor.poll, b"")))
    assert len(late) == pytest.approx(emulator.CATCH_UP_S * 100 / (skip + 1), abs=2)
    assert (np.diff(late) == 10 * (skip + 1)).all()
    assert (late[0] - _streamed_scans(sent)[-1]) % (10 * (skip + 1)) == 0


def test_timestamps_across_the_24_bit_wrap() -> None:
    params = ScipParameters(sensor_clock_start_ms=scip.TIMESTAMP_WRAP_MS - 1000)
    sensor = ScipSensor(WallScene(), params)
    wrap_ns = sensor._boot_ns + 1_000_000_000  # the host time at which the sensor's clock wraps
    with TcpServer(sensor) as srv:
        drv = HokuyoLidar({"port": srv.url})
        lines = []
        try:
            drv.start()
            for line in drv.lines():  # until 100 ms past the wrap
                lines.append(line)
                if line.timestamp_ns > wrap_ns + 100_000_000:
                    break
        finally:
            drv.stop()
            drv.close()
    stamps = np.array([line.timestamp_ns for line in lines])
    assert stamps[0] < wrap_ns, "the stream began after the wrap: nothing crossed it"
    assert_on_the_scan_grid(stamps)


def test_clock_sync_estimates_drift_and_unwraps() -> None:
    sync = ClockSync(min_drift_baseline_s=1.0)
    host0 = 1_000_000_000_000
    for k, host in enumerate((host0, host0 + 10_000_000_000)):
        sensor_ms = (scip.TIMESTAMP_WRAP_MS - 3000 + round(k * 10_000 * 1.0002)) % (
            scip.TIMESTAMP_WRAP_MS)
        sync.add(host - 200_000, host + 200_000, sensor_ms)
        sync.add(host - 900_000, host + 900_000, sensor_ms)  # a slower round trip: not used
        sync.commit()
    assert sync.drift_ppm == pytest.approx(200, abs=1)
    # a sensor time after the wrap maps forward in host time
    later = sync.unwrap(20_000)  # the second anchor read 7002 ms, after the wrap
    expected = host0 + 10_000_000_000 + (20_000 - 7002 - 0.5) / 1.0002 * 1e6
    assert sync.to_host_ns(later) == pytest.approx(expected, abs=1e3)


def test_bad_sum_while_streaming_is_a_clear_error(lidar: HokuyoLidar, sensor: ScipSensor) -> None:
    lidar.start()
    try:
        sensor.faults.corrupt_next_reply = True
        with pytest.raises(ScipChecksumError, match="bad sum"):
            for _ in itertools.islice(lidar.lines(), 50):
                pass
    finally:
        lidar.stop()


def test_laser_malfunction(lidar: HokuyoLidar, sensor: ScipSensor) -> None:
    sensor.faults.laser_malfunction = True
    with pytest.raises(HokuyoError, match="laser malfunction"):
        lidar.start()


def test_reconnects_after_a_timeout(server: TcpServer, sensor: ScipSensor) -> None:
    drv = HokuyoLidar({"port": server.url, "timeout_s": 0.3, "reconnect_attempts": 10})
    done = threading.Event()

    def wake() -> None:
        # the sensor hangs until the driver has given up on its connection and opened another
        while drv.reconnects == 0 or server.connections < 2:
            if done.wait(0.01):
                return
        sensor.faults.silent = False

    waker = threading.Thread(target=wake, daemon=True)
    after = 0
    try:
        drv.start()
        for got, _ in enumerate(drv.lines(), start=1):
            if got == 5:
                sensor.faults.silent = True
                waker.start()
            if drv.reconnects >= 1:  # lines queued before the silence do not count
                after += 1
            if after >= 10:
                break
        drv.stop()
    finally:
        done.set()
        drv.close()
    assert drv.reconnects >= 1
    assert server.connections >= 2
    assert after == 10


def test_times_out_when_the_sensor_stays_silent(lidar: HokuyoLidar, sensor: ScipSensor) -> None:
    lidar.settings["reconnect_attempts"] = 1
    lidar.start()
    sensor.faults.silent = True
    t0 = time.monotonic()
    with pytest.raises(ScipTimeout, match="no scan"):
        for _ in lidar.lines():
            pass
    # a hang guard, not a timing: the 0.5 s time-out once, then the one reconnect's
    assert time.monotonic() - t0 < 120.0
