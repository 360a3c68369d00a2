"""``calstation import rosbag|csv``: recordings made elsewhere, as calstation recordings.

Thin: parse the options, call :mod:`calstation.recordings.rosbag` or
:mod:`calstation.recordings.linelog`, write with
:func:`calstation.recordings.imported.write_imported` (whole or not at all) and say what was
imported and what had to be decided.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import typer

if TYPE_CHECKING:
    from calstation.recordings.imported import ImportedScan

ANGLE_HELP = ("Unit of the angle as stored: deg, rad or counts (encoder counts: give "
              "--counts-per-rev).")
CPR_HELP = ("Counts per turn: of an angle in counts (required), or the grid a deg/rad angle is "
            "stored on (default 2^32 per turn; give the encoder's own to keep its counts).")
BITS_HELP = ("The angle in counts is a raw counter of this many bits (8, 16, 24, 32 or 64, "
             "signed or not) that wraps at 2^bits: it is unwrapped. Without it, a counter's "
             "wrap is refused.")
DIRECTION_HELP = ("+1 or -1: the platter angle φ (right-handed about the rotation axis X_P) is "
                  "direction × the imported angle.")
KIND_HELP = "The recording's kind: spin, static or cube."


def register(app: typer.Typer) -> None:
    """Add the ``import`` group: ``rosbag`` and ``csv``."""
    from calstation.cli import command_group

    group = command_group(app, "import", "Import lidar lines and a mount angle recorded "
                          "elsewhere (ROS bags, CSV line logs) as calstation recordings.")

    @group.command("rosbag")
    def rosbag_cmd(
        bags: list[Path] = typer.Argument(..., help="A ROS 1 .bag, or a ROS 2 bag (folder, "
                                          ".db3 or .mcap); several: the parts of one split "
                                          "recording.", metavar="BAG...", show_default=False),
        scan: str = typer.Option(..., "--scan", help="TOPIC[:FIELD] of the sensor_msgs/"
                                 "LaserScan (FIELD: a dotted path into a custom message, e.g. "
                                 "/slice:laserScan).", show_default=False),
        angle: str = typer.Option(..., "--angle", help="TOPIC[:FIELD] of the mount angle: in "
                                  "the scan's message (held for its line, e.g. "
                                  "/slice:tiltAngle) or on its own topic (interpolated to each "
                                  "point's time, e.g. /joint_states:position[tilt]).",
                                  show_default=False),
        angle_unit: str = typer.Option("rad", "--angle-unit", help=ANGLE_HELP),
        counts_per_rev: int | None = typer.Option(None, "--counts-per-rev", help=CPR_HELP,
                                                  show_default=False),
        counts_bits: int | None = typer.Option(None, "--counts-bits", help=BITS_HELP,
                                               show_default=False),
        direction: int = typer.Option(1, "--direction", help=DIRECTION_HELP),
        kind: str = typer.Option("spin", "--kind", help=KIND_HELP),
        stamps: str = typer.Option("auto", "--stamps", help="Message times: header (the "
                                   "header stamps), bag (the receive times), auto (header "
                                   "stamps when every message has one on the bag's clock)."),
        station: str = typer.Option("", "--station", help="Station id to store."),
        out: Path = typer.Option(..., "--out", "-o", help="The recording to write (.mcap).",
                                 show_default=False),
    ) -> None:
        """Import a ROS bag's LaserScans and mount angle as a calstation recording.

        Bearings map to calstation azimuths by REP-103 (α = −θ, docs/frames.md), point times
        come from time_increment, and inf, nan or out-of-range returns are kept as invalid.
        """
        from calstation.atomic import check_output
        from calstation.recordings.rosbag import TopicSpec, read_rosbag

        check_output(out, "recording")  # refused before the bag is read
        scan_spec = TopicSpec.parse(scan, "--scan")
        angle_spec = TopicSpec.parse(angle, "--angle")
        with _progress(f"reading {', '.join(map(str, bags))}") as step:
            imported = read_rosbag(bags, scan_spec, angle_spec, angle_unit=angle_unit,
                                   stamps=stamps, progress=step)
        _write(imported, out, kind, counts_per_rev, direction, station, counts_bits)

    @group.command("csv")
    def csv_cmd(
        log: Path = typer.Argument(..., help="A text line log: one row per lidar line.",
                                   show_default=False),
        time_col: str = typer.Option(..., "--time", help="Column of each line's time (of its "
                                     "first point).", show_default=False),
        time_unit: str = typer.Option("s", "--time-unit", help="Unit of --time: s, ms, us or "
                                      "ns (since the Unix epoch, or any origin)."),
        angle: str = typer.Option(..., "--angle", help="Column of the mount angle at the "
                                  "line's time.", show_default=False),
        ranges: str = typer.Option(..., "--ranges", help="The range columns, in point order: "
                                   "a pattern (r*, range_[0-9]*) or one column holding the "
                                   "ranges separated by spaces or semicolons.",
                                   show_default=False),
        range_unit: str = typer.Option("m", "--range-unit", help="Unit of the ranges: m or mm."),
        azimuths: str = typer.Option(..., "--azimuths", help="FIRST:STEP, degrees: calstation "
                                     "azimuth α of the first point and the step to the next "
                                     "(α = 0 the boresight +Y_L, positive toward +X_L).",
                                     show_default=False),
        point_period: float = typer.Option(0.0, "--point-period", help="Seconds between two "
                                           "points of a line (0: all at the line's time)."),
        range_min: float = typer.Option(0.0, "--range-min", help="Shorter ranges are invalid "
                                        "(m)."),
        range_max: float = typer.Option(float("inf"), "--range-max", help="Longer ranges are "
                                        "invalid (m)."),
        hold: bool = typer.Option(False, "--hold", help="The angle holds for its whole line "
                                  "(stop-and-go acquisition) instead of being interpolated "
                                  "between the lines' times."),
        angle_unit: str = typer.Option("rad", "--angle-unit", help=ANGLE_HELP),
        counts_per_rev: int | None = typer.Option(None, "--counts-per-rev", help=CPR_HELP,
                                                  show_default=False),
        counts_bits: int | None = typer.Option(None, "--counts-bits", help=BITS_HELP,
                                               show_default=False),
        direction: int = typer.Option(1, "--direction", help=DIRECTION_HELP),
        kind: str = typer.Option("spin", "--kind", help=KIND_HELP),
        station: str = typer.Option("", "--station", help="Station id to store."),
        out: Path = typer.Option(..., "--out", "-o", help="The recording to write (.mcap).",
                                 show_default=False),
    ) -> None:
        """Import a CSV (or other delimited text) line log as a calstation recording.

        Empty or non-numeric range cells, and ranges outside --range-min..--range-max, are
        kept as invalid returns.
        """
        from calstation.atomic import check_output
        from calstation.recordings.linelog import LineLogColumns, read_line_log

        check_output(out, "recording")  # refused before the log is read
        columns = LineLogColumns(
            time=time_col, time_unit=time_unit, angle=angle, ranges=ranges,
            range_unit=range_unit, azimuths=azimuths, point_period_s=point_period,
            range_min_m=range_min, range_max_m=range_max, hold=hold,
        )
        with _progress(f"reading {log}") as step:
            imported = read_line_log(log, columns, angle_unit=angle_unit, progress=step)
        _write(imported, out, kind, counts_per_rev, direction, station, counts_bits)


def _write(imported: ImportedScan, out: Path, kind: str, counts_per_rev: int | None, direction: int,
           station: str, counts_bits: int | None) -> None:
    from rich.console import Console

    from calstation.recordings.imported import write_imported

    with _progress(f"writing {out}") as step:
        result = write_imported(imported, out, kind=kind, counts_per_revolution=counts_per_rev,
                                direction=direction, station_id=station, progress=step,
                                counts_bits=counts_bits)
    err = Console(stderr=True)
    for note in result.notes:
        err.print(f"note: {note}", highlight=False, markup=False)
    typer.echo(
        f"wrote {result.path}: {result.lines:,} lines, {result.points:,} points "
        f"({result.valid:,} valid), {result.angle_samples:,} angle samples "
        f"({result.counts_per_revolution:,} counts per turn)"
    )


class _progress:
    """A progress bar on stderr whose ``step(done, total)`` moves it."""

    def __init__(self, title: str) -> None:
        from rich.console import Console
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        self._bar = Progress(TextColumn("{task.description}"), BarColumn(),
                             TextColumn("{task.completed}/{task.total}"),
                             TimeElapsedColumn(), console=Console(stderr=True), transient=True)
        self._task = self._bar.add_task(title, total=None)

    def __enter__(self) -> Callable[[int, int], None]:
        self._bar.start()

        def step(done: int, total: int) -> None:
            if done == total or done % 200 == 0:
                self._bar.update(self._task, completed=done, total=total)

        return step

    def __exit__(self, *exc: object) -> None:
        self._bar.stop()
