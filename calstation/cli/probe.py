"""``calstation probe lidar|turntable|encoder``: the operator's manual preflight of one device.

Opens one driver through the plugin registry, prints its identity and one sample, and closes it
(the motor is never moved). ``--json`` prints one JSON object instead:

- lidar: ``{"info": {...}, "scan": {"timestamp_ns": int, "azimuth_rad": [...], "range_m": [...]}}``
  (ranges of invalid returns are ``null``);
- turntable: ``{"info": {...}, "status": {...}}``;
- encoder: ``{"info": {...}, "sample": {"timestamp_ns": int, "count": int}}``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypedDict

import typer

from calstation.errors import DriverError
from calstation.jsonvalue import JSONObject

if TYPE_CHECKING:
    from calstation.drivers import Lidar, LidarLine


class ProbeScan(TypedDict):
    timestamp_ns: int
    azimuth_rad: list[float]
    range_m: list[float | None]


class ProbeSample(TypedDict):
    timestamp_ns: int
    count: int


class ProbeResult(TypedDict, total=False):
    """What ``probe`` prints: the device's identity and one sample of its kind."""

    info: dict[str, object]
    scan: ProbeScan
    status: JSONObject
    sample: ProbeSample


def _parse_sets(items: list[str]) -> dict[str, object]:
    """``KEY=VALUE`` options; values are read as YAML scalars (numbers, true/false, text)."""
    import yaml

    out: dict[str, object] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise DriverError(f"--set {item!r}: expected KEY=VALUE")
        out[key.strip()] = yaml.safe_load(value)
    return out


def _settings(kind: str, port: str | None, channel: str | None, interface: str | None,
              node_id: int | None, sets: list[str]) -> dict[str, object]:
    settings: dict[str, object] = {}
    if port is not None:
        settings["port"] = port
    if channel is not None:
        settings["channel"] = channel
    if interface is not None:
        settings["interface"] = interface
    if node_id is not None:
        settings["node_id"] = node_id
    settings.update(_parse_sets(sets))
    return settings


def _info_of(driver: object) -> dict[str, object]:
    info = getattr(driver, "info", None)
    if info is None:
        return {}
    value = info()
    if hasattr(value, "as_dict"):
        return dict(value.as_dict())
    return dict(value)


def _first_line(driver: Lidar) -> LidarLine:
    driver.start()
    try:
        for line in driver.lines():
            return line
    finally:
        driver.stop()
    raise DriverError("probe: the lidar stopped before sending a line")


def probe(kind: str, driver_name: str, settings: dict[str, object],
          recipe: Path | None = None) -> ProbeResult:
    """Open driver ``driver_name`` of ``kind`` with ``settings``; return its identity and one
    sample as a JSON-ready mapping. The driver is always closed."""
    from calstation import plugins
    from calstation.clock import HostClock
    from calstation.drivers import DriverContext

    loaded = None
    if recipe is not None:
        from calstation.recipes import load_recipe

        loaded = load_recipe(recipe)
    context = DriverContext(clock=HostClock(), recipe=loaded)
    factory = plugins.driver_factory(kind, driver_name)
    driver: Any = factory(settings, context)  # Any: of the kind the command line names
    try:
        info = _info_of(driver)
        if kind == "lidar":
            line = _first_line(driver)
            return {
                "info": info,
                "scan": {
                    "timestamp_ns": int(line.timestamp_ns),
                    "azimuth_rad": [float(a) for a in line.azimuth_rad],
                    "range_m": [
                        float(r) if ok and math.isfinite(r) else None
                        for r, ok in zip(line.range_m, line.valid, strict=True)
                    ],
                },
            }
        if kind == "turntable":
            return {"info": info, "status": driver.status().as_dict()}
        sample = driver.read()
        info.setdefault("counts_per_revolution", driver.counts_per_revolution)
        return {"info": info,
                "sample": {"timestamp_ns": int(sample.timestamp_ns), "count": int(sample.count)}}
    finally:
        driver.close()


def _print_human(kind: str, result: ProbeResult) -> None:
    from rich.console import Console
    from rich.table import Table

    console = Console()
    table = Table(title=f"{kind} identity", show_header=False)
    for key, value in result["info"].items():
        table.add_row(str(key), json.dumps(value) if isinstance(value, dict) else str(value))
    console.print(table)
    if kind == "lidar":
        scan = result["scan"]
        ranges = [r for r in scan["range_m"] if r is not None]
        az = scan["azimuth_rad"]
        console.print(
            f"one line at {scan['timestamp_ns']} ns: {len(az)} points, {len(ranges)} valid, "
            f"azimuth {math.degrees(min(az)):.2f}° … {math.degrees(max(az)):.2f}°, "
            + (f"range {min(ranges):.3f} … {max(ranges):.3f} m" if ranges else "no returns")
        )
    elif kind == "turntable":
        st = result["status"]
        pos, speed, faults = st["position_rad"], st["speed_rpm"], st["faults"]
        # as TurntableStatus.as_dict writes them
        assert isinstance(speed, float | int) and isinstance(faults, list)
        assert pos is None or isinstance(pos, float | int)
        console.print(
            f"status: {st['state']}, {speed:.3f} rpm, position "
            + ("unknown" if pos is None else f"{math.degrees(pos):.3f}°")
            + (f", faults: {', '.join(str(f) for f in faults)}" if faults else ", no faults")
        )
    else:
        s = result["sample"]
        console.print(f"count {s['count']} at {s['timestamp_ns']} ns")


def register(app: typer.Typer) -> None:
    """Add the ``probe`` command."""

    @app.command("probe")
    def probe_cmd(
        kind: str = typer.Argument(..., help="lidar, turntable or encoder."),
        driver: str = typer.Option(..., "--driver", help="Registered driver name (hokuyo, ...)."),
        port: str | None = typer.Option(
            None, "--port", help="Serial port or URL (socket://HOST:PORT) of a lidar."),
        channel: str | None = typer.Option(None, "--channel", help="CAN channel (can0, ...)."),
        interface: str | None = typer.Option(
            None, "--interface", help="python-can interface (socketcan, virtual, ...)."),
        node_id: int | None = typer.Option(None, "--node-id", help="CANopen node id."),
        sets: list[str] = typer.Option(
            [], "--set", help="Extra driver setting KEY=VALUE (repeatable)."),
        recipe: Path | None = typer.Option(
            None, "--recipe", help="Recipe for drivers that need one (the simulator)."),
        as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
    ) -> None:
        """Print a device's identity and one sample (never moves the motor)."""
        if kind not in ("lidar", "turntable", "encoder"):
            raise DriverError(f"probe: unknown device kind {kind!r}; use lidar, turntable or "
                              "encoder")
        settings = _settings(kind, port, channel, interface, node_id, sets)
        result = probe(kind, driver, settings, recipe)
        if as_json:
            typer.echo(json.dumps(result))
        else:
            _print_human(kind, result)
