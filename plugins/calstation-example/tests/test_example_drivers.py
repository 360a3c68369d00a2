"""The example drivers against calstation's conformance kit (no other plugin needed)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from calstation_example import drivers, plugin as example

from calstation import plugins
from calstation.clock import HostClock
from calstation.drivers import DriverContext, Encoder, Lidar, LidarInfo, LidarLine, Turntable
from calstation.testing.conformance import (
    ConformanceError,
    DriverConformance,
    check_lidar,
    check_turntable,
)


class TestExampleDrivers(DriverConformance):
    """Every rule of the Lidar, Turntable and Encoder protocols, on the example drivers, each
    built through the plugin registry exactly as a recipe would."""

    def setup_method(self) -> None:
        self.context = DriverContext(clock=HostClock())

    def make_lidar(self) -> Lidar:
        with plugins.isolated(example, builtins=False):
            return plugins.driver_factory("lidar", "example")({"line_rate_hz": 100}, self.context)

    def make_turntable(self) -> Turntable:
        with plugins.isolated(example, builtins=False):
            return plugins.driver_factory("turntable", "example")({}, self.context)

    def make_encoder(self) -> Encoder:
        with plugins.isolated(example, builtins=False):
            return plugins.driver_factory("encoder", "example")(
                {"counts_per_revolution": 4096}, self.context)

    def turn_encoder(self, encoder: Encoder) -> None:
        table = self.make_turntable()
        table.enable()
        table.spin(30.0)
        self.context.clock.sleep(0.3)
        table.stop()


def test_the_kit_catches_a_broken_lidar() -> None:
    """A lidar whose timestamps go backwards, or whose line azimuths leave the field of view,
    fails with a message naming the rule."""

    class Backwards(drivers.ExampleLidar):
        def lines(self) -> Iterator[LidarLine]:
            for i, line in enumerate(super().lines()):
                yield type(line)(line.timestamp_ns - i * 10**9, line.azimuth_rad, line.range_m,
                                 line.valid, line.point_period_ns)

    def make() -> drivers.ExampleLidar:
        return Backwards(HostClock(), {"line_rate_hz": 200})

    with pytest.raises(ConformanceError, match="line timestamps strictly increase"):
        check_lidar(make)

    class Wide(drivers.ExampleLidar):
        def info(self) -> LidarInfo:
            from dataclasses import replace

            return replace(super().info(), fov_rad=self.fov / 2)

    with pytest.raises(ConformanceError, match="inside the field of view"):
        check_lidar(lambda: Wide(HostClock(), {"line_rate_hz": 200}))


def test_the_kit_catches_a_turntable_that_does_not_stop() -> None:
    class NeverStops(drivers.ExampleTurntable):
        def stop(self) -> None:
            pass

    def make() -> drivers.ExampleTurntable:
        return NeverStops(drivers.Motion(HostClock()))

    with pytest.raises(ConformanceError, match="stop\\(\\) stands the platter"):
        check_turntable(make, spin_s=0.3)
