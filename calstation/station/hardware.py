"""The run's drivers: opened from the recipe through the plugin registry, and stopped and closed
however the run ends — the turntable first (``stop()``, and ``emergency_stop()`` after an abort or
fault, or when ``stop()`` fails)."""

from __future__ import annotations

from collections.abc import Callable
from contextlib import suppress
from dataclasses import dataclass
from typing import Protocol, TypedDict, runtime_checkable

from calstation import plugins
from calstation.clock import Clock, HostClock
from calstation.drivers import DriverContext, Encoder, Lidar, Turntable
from calstation.recipes import LoadedRecipe
from calstation.storage.db import utcnow


@runtime_checkable
class HasClock(Protocol):
    """A driver on a time base of its own (the simulator's, which advances only as data is
    produced), exposed as its ``clock``."""

    clock: Clock | None


class MotorStop(TypedDict):
    """How the turntable was stopped at a run's end (``run.motor_stop``): the calls that
    succeeded (``how``), whether any did, the run's final status, the errors, when (UTC)."""

    how: str
    ok: bool
    reason: str
    errors: list[str]
    at: str


@dataclass
class Drivers:
    """The run's three drivers and their context."""

    lidar: Lidar
    turntable: Turntable
    encoder: Encoder
    context: DriverContext

    @property
    def clock(self) -> Clock:
        """The clock the station waits on: the lidar's own (the simulator's), else the host's."""
        clock = self.lidar.clock if isinstance(self.lidar, HasClock) else None
        return clock if clock is not None else self.context.clock


def open_drivers(loaded: LoadedRecipe) -> Drivers:
    """Build the recipe's drivers through the plugin registry (``factory(settings, context)``)."""
    context = DriverContext(clock=HostClock(), recipe=loaded)
    st = loaded.recipe.station
    made: list[Lidar | Turntable | Encoder] = []
    try:
        lidar = plugins.driver_factory("lidar", st.lidar.driver)(dict(st.lidar.settings), context)
        made.append(lidar)
        turntable = plugins.driver_factory("turntable", st.turntable.driver)(
            dict(st.turntable.settings), context)
        made.append(turntable)
        encoder = plugins.driver_factory("encoder", st.encoder.driver)(
            dict(st.encoder.settings), context)
    except BaseException:
        for driver in made:
            quietly(driver.close)
        raise
    return Drivers(lidar, turntable, encoder, context)


def quietly(fn: Callable[[], object]) -> None:
    """Call ``fn``, ignoring its exception: closing what is already failing must not hide why."""
    with suppress(Exception):
        fn()


def stop_and_close(d: Drivers, emergency: bool, reason: str) -> MotorStop:
    """Stop the turntable (emergency stop first when ``emergency``; emergency stop if ``stop()``
    fails), close the drivers; how it went (``how``, ``ok``, ``reason``, ``errors``, ``at``),
    ``reason`` being the run's final status, for ``run.motor_stop``."""
    done: list[str] = []
    errors: list[str] = []

    def attempt(name: str) -> bool:
        try:
            getattr(d.turntable, name)()
        except Exception as exc:
            errors.append(f"{name} failed: {type(exc).__name__}: {exc}")
            return False
        done.append(name)
        return True

    if emergency:
        attempt("emergency_stop")
    if not attempt("stop") and "emergency_stop" not in done:
        attempt("emergency_stop")
    for driver in (d.lidar, d.turntable, d.encoder):
        quietly(driver.close)
    return MotorStop(how=" then ".join(done) or "not stopped", ok=bool(done), reason=reason,
                     errors=errors, at=utcnow().isoformat())
