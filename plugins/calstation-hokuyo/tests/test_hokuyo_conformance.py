"""The Hokuyo driver against calstation's driver conformance kit, over the SCIP emulator."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from calstation_hokuyo import HokuyoLidar, ScipSensor, TcpServer, WallScene

from calstation.testing.conformance import DriverConformance


class TestHokuyoConformance(DriverConformance):
    @pytest.fixture(autouse=True)
    def _server(self) -> Iterator[None]:
        with TcpServer(ScipSensor(WallScene(2.0))) as server:
            self.url = server.url
            yield

    def make_lidar(self) -> HokuyoLidar:
        return HokuyoLidar({"port": self.url, "timeout_s": 0.5})
