"""The CiA 402 turntable and CiA 406 encoder drivers against calstation's conformance kit, each
talking to its emulator on a virtual CAN channel of its own."""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator

import pytest
from calstation_canopen import (
    Cia402Turntable,
    Cia406Encoder,
    DriveEmulator,
    EncoderEmulator,
    RampPlatter,
)

from calstation.clock import HostClock
from calstation.drivers import DriverContext, Encoder
from calstation.testing.conformance import DriverConformance

_channels = itertools.count()


class TestCanopenConformance(DriverConformance):
    turntable_rpm = 30.0

    @pytest.fixture(autouse=True)
    def _bus(self) -> Iterator[None]:
        self.channel = f"calstation-conformance-{next(_channels)}"
        self.clock = HostClock()
        self.platter = RampPlatter(acceleration_rpm_s=600.0, clock=self.clock)
        drive = DriveEmulator(self.platter, node_id=5, channel=self.channel, clock=self.clock,
                              heartbeat_ms=50)
        encoder = EncoderEmulator(
            lambda t: math.floor(self.platter.platter_angle(t) / (2 * math.pi) * 4096), 4096,
            node_id=3, channel=self.channel, clock=self.clock, total_range=4096 * 4,
        )
        try:
            yield
        finally:
            encoder.close()
            drive.close()

    def make_turntable(self) -> Cia402Turntable:
        return Cia402Turntable(
            {"interface": "virtual", "channel": self.channel, "node_id": 5,
             "heartbeat_timeout_s": 0.3},
            DriverContext(clock=self.clock),
        )

    def make_encoder(self) -> Cia406Encoder:
        return Cia406Encoder({"interface": "virtual", "channel": self.channel, "node_id": 3,
                              "sync_period_s": 0.005}, DriverContext(clock=self.clock))

    def turn_encoder(self, encoder: Encoder) -> None:
        self.platter.set_speed(60.0, self.clock.now_ns())
        self.clock.sleep(0.3)
        self.platter.set_speed(0.0, self.clock.now_ns())
