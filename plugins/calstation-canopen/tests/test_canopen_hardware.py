"""A real CiA 402 drive and CiA 406 encoder: set CALSTATION_CAN_CHANNEL (and optionally
CALSTATION_CAN_INTERFACE, default socketcan; CALSTATION_CAN_DRIVE_NODE, default 1;
CALSTATION_CAN_ENCODER_NODE, default 2), make sure the platter is clear, and run
``pytest -m hardware plugins/calstation-canopen``. The platter turns slowly (2 rpm) for 3 s."""

from __future__ import annotations

import os
import time

import pytest
from calstation_canopen import Cia402Turntable, Cia406Encoder

from calstation.clock import HostClock
from calstation.drivers import DriverContext, TurntableState

CHANNEL = os.environ.get("CALSTATION_CAN_CHANNEL")
pytestmark = [
    pytest.mark.hardware,
    pytest.mark.skipif(not CHANNEL, reason="set CALSTATION_CAN_CHANNEL to test real devices"),
]


def test_spin_and_count() -> None:
    ctx = DriverContext(clock=HostClock())
    bus = {"interface": os.environ.get("CALSTATION_CAN_INTERFACE", "socketcan"),
           "channel": CHANNEL}
    tt = Cia402Turntable({**bus, "node_id": int(os.environ.get("CALSTATION_CAN_DRIVE_NODE", 1))},
                         ctx)
    enc = None
    try:
        enc = Cia406Encoder(
            {**bus, "node_id": int(os.environ.get("CALSTATION_CAN_ENCODER_NODE", 2))}, ctx)
        tt.enable()
        tt.spin(2.0)
        time.sleep(3.0)
        assert tt.status().state is TurntableState.MOVING
        tt.stop()
        samples = enc.samples()
        assert len(samples) > 10
        assert samples[-1].count != samples[0].count
    finally:
        tt.close()  # stops the motor and disables the drive on any exit
        if enc is not None:
            enc.close()
