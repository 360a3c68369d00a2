"""The preflight step: the lidar returns data, the platter turns, the encoder counts in the
configured direction — checked before the operator places anything."""

from __future__ import annotations

import numpy as np

from calstation.errors import DriverError
from calstation.recipes import PREFLIGHT_RAMP_S
from calstation.station.context import RunContext
from calstation.station.hardware import Drivers
from calstation.station.outcome import StepOutcome, plain
from calstation.storage.db import Run

PREFLIGHT_LINES = 10
"""Lidar lines the preflight reads; each must come, and some must have returns."""
PREFLIGHT_SPIN_S = 0.5
"""How long the preflight counts encoder ticks, once the platter is up to speed."""


class Preflight:
    """The lidar returns data, the platter turns, the encoder counts in the configured
    direction."""

    name = "preflight"

    def run(self, ctx: RunContext, step_id: int) -> StepOutcome:
        """Read the lidar, spin the platter and count; :class:`DriverError` names what is
        wrong."""
        d = ctx.hardware()
        info = d.lidar.info()
        lines, valid, points = _read_lidar(ctx, d)
        rpm = ctx.recipe.steps.spin_scan.rpm
        counts, expected, cpr = _count_turning(ctx, d, rpm)
        return StepOutcome(
            {
                "lidar": plain(info.as_dict()),
                "unit_serial": _record_serial(ctx, str(info.serial or "")),
                "lines": lines,
                "valid_fraction": valid / max(points, 1),
                "encoder_counts": int(counts),
                "expected_counts": float(expected),
                "counts_per_revolution": int(cpr),
                "rpm": rpm,
            }
        )


def _read_lidar(ctx: RunContext, d: Drivers) -> tuple[int, int, int]:
    """Read :data:`PREFLIGHT_LINES` lines; (lines, valid points, points)."""
    lines = valid = points = 0
    with ctx.ui.progress("preflight: lidar") as progress:
        d.lidar.start()
        try:
            for line in d.lidar.lines():
                lines += 1
                points += len(line)
                valid += int(np.count_nonzero(line.valid))
                progress("reading lines", lines / PREFLIGHT_LINES)
                if lines >= PREFLIGHT_LINES:
                    break
        finally:
            d.lidar.stop()
    if lines < PREFLIGHT_LINES or valid == 0:
        raise DriverError(
            f"preflight: the lidar returned {lines} lines with {valid} valid points; "
            f"expected {PREFLIGHT_LINES} lines with returns"
        )
    return lines, valid, points


def _count_turning(ctx: RunContext, d: Drivers, rpm: float) -> tuple[int, float, int]:
    """Spin the platter at ``rpm`` and count; (counts, counts expected, counts per
    revolution) once they are checked."""
    clock = d.clock
    with ctx.ui.progress("preflight: turntable and encoder") as progress:
        d.turntable.enable()
        try:
            d.turntable.spin(rpm)
            clock.sleep(PREFLIGHT_RAMP_S)
            progress("spinning up", 0.5)
            first = d.encoder.read()
            clock.sleep(PREFLIGHT_SPIN_S)
            last = d.encoder.read()
            status = d.turntable.status()
        finally:
            d.turntable.stop()
        progress("stopped", 1.0)
    if status.faults:
        raise DriverError(f"preflight: turntable faults: {', '.join(status.faults)}")
    counts = last.count - first.count
    cpr = d.encoder.counts_per_revolution
    dt_s = (last.timestamp_ns - first.timestamp_ns) * 1e-9
    expected = rpm / 60.0 * dt_s * cpr * ctx.recipe.station.encoder.direction
    _check_counts(ctx, counts, expected, rpm, dt_s)
    return counts, expected, cpr


def _check_counts(ctx: RunContext, counts: int, expected: float, rpm: float, dt_s: float) -> None:
    """The encoder counted, in the configured direction, about as many as the speed implies."""
    direction = ctx.recipe.station.encoder.direction
    if counts == 0:
        raise DriverError(
            f"preflight: the encoder did not count while the platter was commanded to "
            f"{rpm:g} rpm for {dt_s:.2f} s (expected about {abs(expected):.0f} counts): is the "
            "platter turning and the encoder connected?"
        )
    if np.sign(counts) != np.sign(expected):
        raise DriverError(
            f"preflight: the encoder counted {counts} while the platter turned at {rpm:g} rpm; "
            f"with station.encoder.direction = {direction} the counts should have the "
            f"opposite sign: fix the direction in the recipe (or the encoder wiring)"
        )
    if abs(counts) < 0.5 * abs(expected):
        raise DriverError(
            f"preflight: the encoder counted {counts} in {dt_s:.2f} s, expected about "
            f"{expected:.0f} at {rpm:g} rpm: check counts per revolution (ppr) and the drive"
        )


def _record_serial(ctx: RunContext, reported: str) -> str | None:
    """The run's unit serial: the operator's, else the lidar's (stored with the run)."""
    with ctx.db.session() as s:
        run = s.get(Run, ctx.run_id)
        assert run is not None
        simulated = ctx.recipe.station.lidar.driver == "sim"  # its serial names no unit
        if run.unit_serial and reported and reported != run.unit_serial and not simulated:
            ctx.ui.warn(f"the lidar reports serial {reported!r}, the operator gave "
                        f"{run.unit_serial!r}; the operator's is kept")
        elif not run.unit_serial and reported:
            run.unit_serial = reported
        return run.unit_serial
