"""A real Hokuyo sensor: set CALSTATION_HOKUYO_URL (e.g. /dev/ttyACM0 or
socket://192.168.0.10:10940) and run ``pytest -m hardware plugins/calstation-hokuyo``."""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterator

import numpy as np
import pytest
from calstation_hokuyo import HokuyoLidar

URL = os.environ.get("CALSTATION_HOKUYO_URL")
pytestmark = [
    pytest.mark.hardware,
    pytest.mark.skipif(not URL, reason="set CALSTATION_HOKUYO_URL to test a real sensor"),
]


@pytest.fixture
def lidar() -> Iterator[HokuyoLidar]:
    drv = HokuyoLidar({"port": URL})
    yield drv
    drv.close()  # laser off, port released, whatever happened


def test_identity(lidar: HokuyoLidar) -> None:
    assert lidar.version()["PROT"].startswith("SCIP 2")
    p = lidar.parameters()
    assert p.amin <= p.afrt <= p.amax < p.ares


def test_single_scan_and_stream(lidar: HokuyoLidar) -> None:
    line = lidar.single_scan()
    assert line.valid.any()
    lidar.start()
    try:
        lines = list(itertools.islice(lidar.lines(), 20))
    finally:
        lidar.stop()
    period_ns = 60e9 / lidar.parameters().scan_rpm
    np.testing.assert_allclose(np.diff([ln.timestamp_ns for ln in lines]), period_ns,
                               rtol=0.05)
    assert abs(lidar.sync.drift_ppm) < 1000
