"""Imports of data other tools recorded, holding what no scan can: NaN or infinite bearings and
times in a LaserScan, and raw counters that wrap. Each is refused in one sentence naming the
message or sample (or, for a counter whose width is given, unwrapped), and no file is left."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from calstation.cli import main
from calstation.recordings.reader import read_recording
from tests.support.clirun import cli_fails
from tests.support.rosbag import Bag


@pytest.fixture
def bag_with(tmp_path: Path, spin: dict[str, Path]) -> Callable[..., Path]:
    """A ROS 1 bag of five of the simulator's lines, one LaserScan field set to ``value``."""
    lines = list(read_recording(spin["spin"]).lines())[:5]

    def make(field: str, value: float) -> Path:
        path = tmp_path / f"{field}.bag"
        with Bag(path, "ros1") as bag:
            for i, ln in enumerate(lines):
                msg = bag.laser_scan(ln, 0.05, 30.0)
                if i == 2:
                    setattr(msg, field, np.float32(value))
                bag.write("/scan", "sensor_msgs/msg/LaserScan", ln.timestamp_ns, msg)
                bag.write("/angle", "std_msgs/msg/Float64", ln.timestamp_ns,
                          bag.t("std_msgs/msg/Float64")(data=0.1 * i))
        return path

    return make


@pytest.mark.parametrize(("field", "value"), [("angle_min", math.nan), ("angle_max", math.nan),
                                              ("angle_min", math.inf),
                                              ("time_increment", math.nan),
                                              ("range_min", math.nan), ("range_max", math.nan)])
def test_a_laserscan_without_numbers_for_its_geometry_is_refused(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, bag_with: Callable[..., Path],
    field: str, value: float
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    err = cli_fails(capsys, out, "import", "rosbag", bag_with(field, value), "--scan", "/scan",
                 "--angle", "/angle", "--out", out / "x.mcap")
    assert f"message 2: {field} is {value}, not a number" in err, err


@pytest.mark.parametrize("value", [1e6, -1e6, 3e38])
def test_a_time_increment_no_scanner_has_is_refused(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, bag_with: Callable[..., Path],
    value: float
) -> None:
    """A finite time_increment of days would give the points times past the nanosecond range:
    refused naming the message and the field, not written as a silently wrong line."""
    out = tmp_path / "out"
    out.mkdir()
    err = cli_fails(capsys, out, "import", "rosbag", bag_with("time_increment", value), "--scan",
                 "/scan", "--angle", "/angle", "--out", out / "x.mcap")
    assert "message 2: time_increment is" in err and "longer than any line scanner" in err, err


def test_an_infinite_range_max_is_no_upper_limit(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, bag_with: Callable[..., Path]
) -> None:
    out = tmp_path / "x.mcap"
    main_ok(["import", "rosbag", str(bag_with("range_max", math.inf)), "--scan", "/scan",
             "--angle", "/angle", "--out", str(out)], capsys)
    assert read_recording(out).n_lines == 5


def main_ok(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit) as exc:
        main(argv)
        raise SystemExit(0)
    out, err = capsys.readouterr()
    assert exc.value.code in (0, None), err
    return out


def _counter_log(path: Path, counts: list[int]) -> Path:
    """A line log whose angle column is a raw counter's reading at each line."""
    rows = ["t,c," + ",".join(f"r{i}" for i in range(5))]
    rows += [f"{0.01 * k:.2f},{c}," + ",".join(["1.5"] * 5) for k, c in enumerate(counts)]
    path.write_text("\n".join(rows) + "\n")
    return path


INT32_WRAP = [((2**31 - 60 + 5 * k) + 2**31) % 2**32 - 2**31 for k in range(25)]
"""25 readings of a signed 32-bit counter 3600 counts per turn, turning 5 counts per line,
through its wrap from 2^31 − 1 to −2^31."""


def _import_counter(tmp_path: Path, *extra: Any) -> list[Any]:
    log = _counter_log(tmp_path / "counter.csv", INT32_WRAP)
    return ["import", "csv", str(log), "--time", "t", "--angle", "c", "--angle-unit", "counts",
            "--counts-per-rev", "3600", "--ranges", "r*", "--azimuths", "-10:5", *extra]


def test_a_raw_counter_that_wraps_is_refused_without_its_width(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    err = cli_fails(capsys, out, *_import_counter(tmp_path, "--out", out / "x.mcap"))
    first = next(k for k, c in enumerate(INT32_WRAP) if c < 0)
    assert f"angle sample {first} is" in err and "give --counts-bits N" in err, err


def test_a_raw_counter_that_wraps_is_unwrapped_with_its_width(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    out = tmp_path / "x.mcap"
    main_ok(_import_counter(tmp_path, "--counts-bits", "32", "--out", str(out)), capsys)
    rec = read_recording(out)
    steps = np.diff(rec.encoder_count)
    assert len(rec.encoder_count) == 25 and np.all(steps == 5), steps  # 0.5° per line, no jump


def test_counts_bits_needs_an_angle_in_counts(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    argv = _import_counter(tmp_path, "--counts-bits", "12", "--out", out / "x.mcap")
    assert "one of 8, 16, 24, 32, 64" in cli_fails(capsys, out, *argv)
    argv[argv.index("counts")] = "deg"
    assert "needs --angle-unit counts" in cli_fails(capsys, out, *argv)
