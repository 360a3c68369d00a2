"""CiA 402 / CiA 406 drivers against their emulators on python-can's virtual bus: pinned frames,
the drive state machine, PDOs, faults and heartbeat loss."""

from __future__ import annotations

import itertools
import json
import math
import struct
import time
from collections.abc import Callable, Iterator
from typing import Any

import can
import numpy as np
import pytest
from calstation_canopen import (
    CanopenError,
    Cia402Turntable,
    Cia406Encoder,
    DriveEmulator,
    EncoderEmulator,
    RampPlatter,
    Unwrapper,
)

from calstation.clock import HostClock, SimClock
from calstation.drivers import DriverContext, TurntableState

_channels = itertools.count()


@pytest.fixture
def channel() -> str:
    """A fresh virtual channel per test, so tests never hear each other."""
    return f"calstation-test-{next(_channels)}"


@pytest.fixture
def sniffer(channel: str) -> Iterator[can.BusABC]:
    """A bus on the same channel that records every frame the others send."""
    bus = can.Bus(interface="virtual", channel=channel)
    yield bus
    bus.shutdown()


def frames(bus: can.BusABC, duration_s: float = 0.05) -> list[str]:
    """Frames received so far, as ``IDX#HEXDATA`` (candump's short form)."""
    out = []
    deadline = time.monotonic() + duration_s
    while (msg := bus.recv(max(0.0, deadline - time.monotonic()))) is not None:
        out.append(f"{msg.arbitration_id:03X}#{bytes(msg.data).hex().upper()}")
    return out


@pytest.fixture
def clock() -> HostClock:
    return HostClock()


@pytest.fixture
def platter(clock: HostClock) -> RampPlatter:
    return RampPlatter(acceleration_rpm_s=600.0, clock=clock)


@pytest.fixture
def drive(platter: RampPlatter, channel: str, clock: HostClock) -> Iterator[DriveEmulator]:
    emu = DriveEmulator(platter, node_id=5, channel=channel, clock=clock, heartbeat_ms=50)
    yield emu
    emu.close()


@pytest.fixture
def turntable(drive: DriveEmulator, channel: str, clock: HostClock) -> Iterator[Cia402Turntable]:
    tt = Cia402Turntable(
        {"interface": "virtual", "channel": channel, "node_id": 5, "heartbeat_timeout_s": 0.3},
        DriverContext(clock=clock),
    )
    yield tt
    tt.close()


def test_sdo_write_and_rpdo_frames_are_the_documented_bytes(
    drive: DriveEmulator, turntable: Cia402Turntable, sniffer: can.BusABC
) -> None:
    frames(sniffer)  # boot-up and heartbeats so far
    turntable.sdo_write(0x6060, 0, "<b", 3)
    seen = [f for f in frames(sniffer) if not f.startswith("705")]
    assert seen == ["605#2F60600003000000", "585#6060600000000000"]
    turntable.send_rpdo(0x000F, 1000)
    assert "205#0F00E8030000" in frames(sniffer)


HANG_S = 600.0
"""A hang guard: a wait below ends when its condition holds, however busy the machine."""


def eventually(condition: Callable[[], object], what: str) -> None:
    """Wait until ``condition()`` holds (the emulators answer on their own threads)."""
    deadline = time.monotonic() + HANG_S
    while not condition():
        assert time.monotonic() < deadline, f"{what}: not after {HANG_S:g} s"
        time.sleep(0.01)


def test_tpdo_frame_is_decoded(
    channel: str, sniffer: can.BusABC, clock: HostClock, drive: DriveEmulator,
    turntable: Cia402Turntable,
) -> None:
    turntable._subscribe(0x185, turntable._on_tpdo1)
    sniffer.send(can.Message(arbitration_id=0x185, data=bytes.fromhex("3702FD010000"),
                             is_extended_id=False))
    eventually(lambda: turntable._statusword == 0x0237, "the TPDO decoded")
    assert turntable.position_rad() == pytest.approx(2 * math.pi * 509 / 10_000)


def _at_speed(platter: RampPlatter, clock: HostClock, rpm: float,
              turntable: Cia402Turntable | None = None) -> None:
    """Wait until the emulated platter turns at ``rpm`` (its ramp is 0.25 s at 30 rpm; a busy
    host can take longer to deliver the command), and the drive's TPDOs report it."""
    eventually(lambda: platter.platter_speed_rpm(clock.now_ns()) == pytest.approx(rpm),
               f"the platter at {rpm} rpm")
    if turntable is not None:
        eventually(lambda: turntable.status().speed_rpm == pytest.approx(rpm),
                   f"the drive reporting {rpm} rpm")


def test_enable_sequence_then_spin_turns_the_platter(
    drive: DriveEmulator, turntable: Cia402Turntable, platter: RampPlatter,
    sniffer: can.BusABC, clock: HostClock,
) -> None:
    frames(sniffer)
    turntable.enable()
    sent = frames(sniffer)
    assert "000#0105" in sent  # NMT start node 5
    controlwords = [int(f[4:8][2:] + f[4:8][:2], 16) for f in sent if f.startswith("205#")]
    assert controlwords == [0x06, 0x07, 0x0F]
    assert turntable.status().state is TurntableState.ENABLED
    turntable.spin(30.0)
    _at_speed(platter, clock, 30.0, turntable)
    status = turntable.status()
    assert status.state is TurntableState.MOVING
    assert status.speed_rpm == pytest.approx(30.0)
    assert status.position_rad == pytest.approx(platter.platter_angle(status.timestamp_ns),
                                                abs=2e-3)
    # TPDO1 on SYNC: statusword (operation enabled, remote, voltage) + position, little-endian
    tpdo = [f for f in frames(sniffer) if f.startswith("185#")]
    assert tpdo and all(len(f) == 4 + 12 for f in tpdo)
    sw = struct.unpack("<H", bytes.fromhex(tpdo[-1][4:8]))[0]
    assert sw & 0x6F == 0x27 and sw & 0x0210 == 0x0210
    turntable.stop()
    assert abs(platter.platter_speed_rpm(clock.now_ns())) < 0.05


def test_a_second_pass_turns_the_other_way(
    drive: DriveEmulator, turntable: Cia402Turntable, platter: RampPlatter, clock: HostClock,
) -> None:
    """A spin scan's second pass (steps.spin_scan.second_pass_rpm < 0): after a stop, a negative
    speed turns the platter backwards, and the drive reports the signed speed."""
    turntable.enable()
    turntable.spin(20.0)
    _at_speed(platter, clock, 20.0)
    turntable.stop()
    turntable.spin(-20.0)
    _at_speed(platter, clock, -20.0, turntable)
    before = turntable.status()
    time.sleep(0.2)
    after = turntable.status()
    assert platter.platter_speed_rpm(clock.now_ns()) == pytest.approx(-20.0)
    assert after.state is TurntableState.MOVING and after.speed_rpm == pytest.approx(-20.0)
    turned = after.position_rad - before.position_rad
    seconds = (after.timestamp_ns - before.timestamp_ns) * 1e-9
    assert turned == pytest.approx(-20.0 / 60.0 * 2 * math.pi * seconds, abs=0.05)
    turntable.stop()


def test_drive_fault_is_reported_and_reset(
    drive: DriveEmulator, turntable: Cia402Turntable, platter: RampPlatter, clock: HostClock
) -> None:
    turntable.enable()
    turntable.spin(20.0)
    drive.inject_fault(0x2310)
    eventually(lambda: turntable.status().state is TurntableState.FAULT, "the fault reported")
    status = turntable.status()
    assert any("0x2310" in f for f in status.faults)
    assert drive.commanded_rpm == 0.0  # the drive let go of the motor
    with pytest.raises(CanopenError, match="FAULT"):
        turntable.spin(5.0)
    turntable.enable()  # fault reset, then the enable sequence again
    assert turntable.status().state is TurntableState.ENABLED
    assert turntable.status().faults == ()


def test_quick_stop(drive: DriveEmulator, turntable: Cia402Turntable) -> None:
    turntable.enable()
    turntable.spin(10.0)
    turntable.emergency_stop()
    eventually(lambda: turntable.status().state is TurntableState.EMERGENCY_STOP,
               "the quick stop reported")
    assert drive.commanded_rpm == 0.0


def test_lost_drive_heartbeat_stops_and_refuses_to_spin(
    drive: DriveEmulator, turntable: Cia402Turntable, sniffer: can.BusABC
) -> None:
    turntable.enable()
    turntable.spin(10.0)
    frames(sniffer)
    drive.node.nmt.stop_heartbeat()  # the drive goes silent
    eventually(lambda: "heartbeat lost" in turntable.status().faults, "the lost heartbeat")
    status = turntable.status()
    assert status.state is TurntableState.FAULT
    assert "heartbeat lost" in status.faults
    assert any(f.startswith("205#0200") for f in frames(sniffer))  # quick stop was sent
    with pytest.raises(CanopenError, match="heartbeat"):
        turntable.spin(10.0)


def test_lost_master_heartbeat_stops_the_drive(
    drive: DriveEmulator, turntable: Cia402Turntable, platter: RampPlatter, clock: HostClock
) -> None:
    turntable.enable()
    turntable.spin(10.0)
    turntable.bus.stop_heartbeat()  # the host process hangs
    eventually(lambda: drive.state.name == "FAULT", "the drive's fault")
    assert 0x8130 in drive.faults
    assert drive.commanded_rpm == 0.0


@pytest.fixture
def encoder_emulator(
    platter: RampPlatter, channel: str, clock: HostClock
) -> Iterator[EncoderEmulator]:
    emu = EncoderEmulator(
        lambda t: math.floor(platter.platter_angle(t) / (2 * math.pi) * 4096), 4096,
        node_id=3, channel=channel, clock=clock, total_range=4096 * 4,
    )
    yield emu
    emu.close()


def test_encoder_on_sync_is_stamped_with_the_sync_time(
    encoder_emulator: EncoderEmulator, platter: RampPlatter, channel: str, clock: HostClock,
    sniffer: can.BusABC,
) -> None:
    ctx = DriverContext(clock=clock)
    enc = Cia406Encoder({"interface": "virtual", "channel": channel, "node_id": 3,
                         "sync_period_s": 0.005}, ctx)
    try:
        assert enc.counts_per_revolution == 4096
        platter.set_speed(-60.0, clock.now_ns())  # one turn a second, backwards
        time.sleep(1.2)  # past the 4-turn range of the raw position: must unwrap
        samples = enc.samples()
        assert len(samples) > 100
        times = [s.timestamp_ns for s in samples]
        assert all(b > a for a, b in itertools.pairwise(times))
        for s in samples[-20:]:
            expected = platter.platter_angle(s.timestamp_ns) / (2 * math.pi) * 4096
            assert abs(s.count - expected) < 8  # within ~1 ms of the SYNC at 4096 counts/s
        assert samples[-1].count < -4096  # signed and unwrapped
        tpdo = [f for f in frames(sniffer) if f.startswith("183#")]
        assert tpdo and all(len(f) == 4 + 8 for f in tpdo)  # 0x6004 as 4 bytes
    finally:
        enc.close()


class _StallingClock(SimClock):
    """A SimClock that moves 3 ms on while a frame is sent when ``stall`` is set (a busy
    host holding the SYNC producer's thread)."""

    stall = False

    def now_ns(self) -> int:
        t = super().now_ns()
        if self.stall:
            self.stall = False
            self.advance_to(t + 3_000_000)
        return t


def test_a_sync_whose_sending_stalled_gives_no_sample(channel: str) -> None:
    """A SYNC that took longer than SYNC_SEND_S to reach the bus has an uncertain time: what the
    encoder latched at it is dropped, not stamped up to the stall too early."""
    from calstation_canopen.bus import SharedBus

    clock = _StallingClock(0)
    bus = SharedBus("virtual", channel, clock=clock)
    try:
        clock.advance_to(2_000_000)
        steady = bus.send_sync()
        clock.advance_to(4_000_000)
        clock.stall = True
        stalled = bus.send_sync()
        assert bus.sync_time_certain(steady) and not bus.sync_time_certain(stalled)
    finally:
        bus.close()


class _LateWakingClock(HostClock):
    """The host's clock, 19.5 ms further on once the SYNC producer has sent three SYNCs (its
    thread woke that late: a busy host)."""

    def __init__(self) -> None:
        super().__init__()
        self.offset = 0
        self.bus: Any = None

    def now_ns(self) -> int:
        if self.bus is not None and self.offset == 0 and len(self.bus._sync_times) >= 3:
            self.offset = 19_500_000
        return super().now_ns() + self.offset


def test_a_sync_producer_that_falls_behind_sends_no_burst(channel: str) -> None:
    """SYNCs every 10 ms, the producer waking 19.5 ms late once: it sends at once, then keeps
    the next SYNC at least half a period away. Two SYNCs 0.5 ms apart (it once sent the next
    on the old grid) cannot be told apart by their answers' time on the wire."""
    from calstation_canopen.bus import SharedBus

    clock = _LateWakingClock()
    bus = SharedBus("virtual", channel, clock=clock)
    clock.bus = bus
    try:
        bus.start_sync(0.01)
        deadline = time.monotonic() + 10.0
        while len(bus._sync_times) < 8 and time.monotonic() < deadline:
            time.sleep(0.005)
        bus.stop_sync()
        times = list(bus._sync_times)
        assert len(times) >= 8 and clock.offset
        assert min(np.diff(times)) >= 5_000_000, np.diff(times)
    finally:
        bus.close()


def test_encoder_cyclic_mode(
    encoder_emulator: EncoderEmulator, channel: str, clock: HostClock
) -> None:
    enc = Cia406Encoder({"interface": "virtual", "channel": channel, "node_id": 3,
                         "mode": "cyclic", "cyclic_ms": 5}, DriverContext(clock=clock))
    try:
        time.sleep(0.3)
        n = len(enc.samples())
        assert 20 <= n <= 80  # 60 nominal; generous for a busy machine
        assert encoder_emulator.value(0x6200) == 5
        assert encoder_emulator.value(0x1800, 2) == 0xFE
    finally:
        enc.close()


def test_unwrapper_handles_both_directions() -> None:
    u = Unwrapper(1000)
    assert [u(r) for r in (990, 995, 5, 10, 995, 900)] == [-10, -5, 5, 10, -5, -100]


def test_settings_are_checked(channel: str) -> None:
    with pytest.raises(CanopenError, match="unknown setting"):
        Cia402Turntable({"interface": "virtual", "channel": channel, "nodeid": 3})
    with pytest.raises(CanopenError, match="channel is required"):
        Cia406Encoder({"interface": "virtual"})


def test_missing_drive_times_out(channel: str, clock: HostClock) -> None:
    tt = Cia402Turntable({"interface": "virtual", "channel": channel, "node_id": 9,
                          "sdo_timeout_s": 0.1}, DriverContext(clock=clock))
    try:
        with pytest.raises(CanopenError, match="no SDO answer"):
            tt.enable()
    finally:
        tt.close()


def test_probe_turntable_and_encoder(
    drive: DriveEmulator, encoder_emulator: EncoderEmulator, channel: str,
    capsys: pytest.CaptureFixture[str],
) -> None:
    from calstation.cli import main

    for kind, driver, node in (("turntable", "canopen402", 5), ("encoder", "canopen406", 3)):
        with pytest.raises(SystemExit) as exit_info:
            main(["probe", kind, "--driver", driver, "--interface", "virtual", "--channel",
                  channel, "--node-id", str(node), "--json"])
        assert exit_info.value.code in (0, None)
        out = json.loads(capsys.readouterr().out)
        assert out["info"]["node_id"] == node
        if kind == "turntable":
            assert out["info"]["device_type"] == "0x00020192"
            assert out["status"]["state"] == "disabled"
        else:
            assert out["info"]["counts_per_revolution"] == 4096
            assert isinstance(out["sample"]["count"], int)
    assert drive.commanded_rpm == 0.0  # a probe never moves the motor


EMULATOR_PROCESS = """
import sys, time
from calstation_canopen import DriveEmulator, RampPlatter
emu = DriveEmulator(RampPlatter(), node_id=4, interface="udp_multicast", channel=sys.argv[1])
print("ready", flush=True)
sys.stdin.read()  # until the test closes our stdin
emu.close()
"""


def test_drive_emulator_in_another_process_over_udp_multicast() -> None:
    import subprocess
    import sys

    pytest.importorskip("msgpack")
    group = "239.74.163.7"
    proc = subprocess.Popen([sys.executable, "-c", EMULATOR_PROCESS, group],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
        tt = Cia402Turntable({"interface": "udp_multicast", "channel": group, "node_id": 4})
        try:
            tt.enable()
            tt.spin(30.0)
            eventually(lambda: tt.status().speed_rpm == pytest.approx(30.0), "30 rpm reported")
            tt.stop()
        finally:
            tt.close()
    finally:
        assert proc.stdin is not None
        proc.stdin.close()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()


def test_a_tpdo_is_paired_with_the_sync_before_it_on_the_wire_however_late_it_is_handled(
    channel: str,
) -> None:
    """A busy host handles a TPDO hundreds of milliseconds late, or loses the answer to one
    SYNC: the frame's time on the wire still names the SYNC it answers (the order and the
    lateness do not)."""
    from calstation_canopen.bus import SharedBus

    from calstation.clock import SimClock

    clock = SimClock(0)
    bus = SharedBus("virtual", channel, clock=clock)
    try:
        syncs = []
        for t in (0, 2_000_000, 4_000_000, 6_000_000):
            clock.advance_to(t)
            syncs.append(bus.send_sync())
        late = 300_000_000
        # the answer to the 2 ms SYNC, handled 298 ms later
        assert bus.pair_sync(syncs[0], late, 2_200_000) == syncs[1]
        # the answer to the 2 ms SYNC was lost: the next one answers the 4 ms SYNC
        assert bus.pair_sync(syncs[0], late, 4_200_000) == syncs[2]
        # without the wire's time, in order when on time
        assert bus.pair_sync(syncs[0], 3_000_000) == syncs[1]
        # a frame on the wire before any SYNC after the last pairing answers none: not the
        # next SYNC, sent after it (that once shifted every answer after a burst of SYNCs)
        assert bus.pair_sync(syncs[1], late, 2_200_000) is None
        assert bus.pair_sync(syncs[1], late, 3_900_000) is None
        # a frame's time on the wire, from python-can's wall-clock stamp
        now = 10_000_000_000
        assert bus.wire_ns(time.time() - 0.25, now) == pytest.approx(now - 250_000_000,
                                                                     abs=50_000_000)
        assert bus.wire_ns(0.0, now) is None  # an interface without timestamps
        assert bus.wire_ns(time.time() - 3600.0, now) is None  # not on the wall clock
        bus.interface = "kvaser"  # an adapter's stamps, on a clock of its own
        assert bus.wire_ns(time.time() - 0.25, now) is None
    finally:
        bus.close()
