"""Scripted exchanges: the driver must send exactly these bytes and understand exactly these
replies (PyMeasure's ``expected_protocol`` style, over a real TCP socket)."""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager

import pytest
from calstation_hokuyo import HokuyoError, HokuyoLidar, ScipChecksumError, ScipStatusError

from calstation.clock import SimClock
from calstation.testing.transports import ScriptedDevice, TcpServer

PP = (
    b"PP\n",
    b"PP\n00P\nMODL:UTM-30LX;@\nDMIN:20;4\nDMAX:5600;_\nARES:1024;\\\nAMIN:44;7\n"
    b"AMAX:725;o\nAFRT:384;6\nSCAN:600;e\n\n",
)
TM = [
    (b"TM0\n", b"TM0\n00P\n\n"),
    (b"TM1\n", b"TM1\n00P\nm2?f4\n\n"),  # sensor time 15 999 990 ms
    (b"TM2\n", b"TM2\n00P\n\n"),
]
BM = (b"BM\n", b"BM\n00P\n\n")
GD = (b"GD0384038500\n", b"GD0384038500\n00P\nm2@0?\n1Dh0CBB\n\n")

SETTINGS = {"start_step": 384, "end_step": 385, "sync_round_trips": 1, "timeout_s": 1.0}


@contextmanager
def expected_protocol(
    exchanges: list[tuple[bytes, bytes]], **settings: object
) -> Iterator[HokuyoLidar]:
    """A driver connected to a scripted device; the script must be followed to its end."""
    device = ScriptedDevice(exchanges)
    with TcpServer(device) as server:
        lidar = HokuyoLidar({**SETTINGS, **settings, "port": server.url}, clock=SimClock())
        try:
            yield lidar
        finally:
            lidar._close_port()
    device.check()


def test_version_and_parameters() -> None:
    vv = (
        b"VV\n",
        b"VV\n00P\nVEND:Hokuyo Automatic Co., Ltd.;;\nPROD:UTM-30LX;I\n"
        b"FIRM:1.1.0;F\nPROT:SCIP 2.0;N\nSERI:H0000001;6\n\n",
    )
    with expected_protocol([vv, PP]) as lidar:
        fields = lidar.version()
        params = lidar.parameters()
    assert fields["PROT"] == "SCIP 2.0"
    assert (params.ares, params.amin, params.amax, params.afrt, params.scan_rpm) == (
        1024, 44, 725, 384, 600,
    )
    assert (params.dmin_mm, params.dmax_mm) == (20, 5600)


def test_gd_single_scan_from_the_protocol_example() -> None:
    with expected_protocol([PP, *TM, BM, GD]) as lidar:
        line = lidar.single_scan()
        clock_ns = lidar.clock.now_ns()
    assert line.range_m.tolist() == [5.432, 1.234]
    assert line.valid.tolist() == [True, True]
    # step 384 is AFRT (the boresight); step 385 is one step counter-clockwise: toward −X_L
    assert line.azimuth_rad.tolist() == pytest.approx([0.0, -2 * math.pi / 1024])
    # 16 000 000 ms is 10 ms after the TM1 reading (+0.5 ms: TM1 truncates), and step 384 comes
    # 340 steps after AMIN at 0.1 s / 1024 steps
    expected = clock_ns + round((10 - 0.5) * 1e6) + round(340 * 0.1 / 1024 * 1e9)
    assert abs(line.timestamp_ns - expected) <= 1
    assert line.point_period_ns == pytest.approx(0.1 / 1024 * 1e9)


def test_azimuth_sign_and_boresight_are_configurable() -> None:
    with expected_protocol([PP, *TM, BM, GD], azimuth_sign=1, boresight_step=385) as lidar:
        line = lidar.single_scan()
    assert line.azimuth_rad.tolist() == pytest.approx([-2 * math.pi / 1024, 0.0])


def test_bad_sum_in_a_scan_is_a_clear_error() -> None:
    bad = (b"GD0384038500\n", b"GD0384038500\n00P\nm2@0?\n1Dh0CBC\n\n")
    with expected_protocol([PP, *TM, BM, bad]) as lidar, pytest.raises(
        ScipChecksumError, match="bad sum"
    ):
        lidar.single_scan()


def test_laser_off_status_10_is_a_clear_error() -> None:
    off = (b"GD0384038500\n", b"GD0384038500\n10Q\n\n")
    with expected_protocol([PP, *TM, BM, off]) as lidar, pytest.raises(
        HokuyoError, match="laser is off"
    ):
        lidar.single_scan()


def test_laser_malfunction_on_bm() -> None:
    bm_fail = (b"BM\n", b"BM\n01Q\n\n")
    with expected_protocol([PP, *TM, bm_fail]) as lidar, pytest.raises(
        HokuyoError, match="laser malfunction"
    ):
        lidar.single_scan()


def test_stream_request_and_stop() -> None:
    md_scan = b"MD0384038500000\n99b\nm2@0?\n1Dh0CBB\n\n"
    exchanges = [
        PP,
        (b"QT\n", b"QT\n00P\n\n"),
        *TM,
        BM,
        (b"MD0384038500000\n", b"MD0384038500000\n00P\n\n" + md_scan),
        (b"QT\n", b"QT\n00P\n\n"),
    ]
    with expected_protocol(exchanges) as lidar:
        lidar.parameters()
        lidar.start()
        line = next(iter(lidar.lines()))
        lidar.stop()
    assert line.range_m.tolist() == [5.432, 1.234]


def test_error_status_on_a_command() -> None:
    with expected_protocol([(b"PP\n", b"PP\n0Dd\n\n")]) as lidar, pytest.raises(
        ScipStatusError, match="status 0D"
    ):
        lidar.parameters()


def test_unknown_setting_is_rejected() -> None:
    with pytest.raises(HokuyoError, match="unknown setting"):
        HokuyoLidar({"port": "loop://", "azimuth": 1})
    with pytest.raises(HokuyoError, match="port is required"):
        HokuyoLidar({})
