"""``calstation import rosbag`` and ``import csv``: bags written here with ``rosbags``' writer
from the simulator's data (ROS 1 ``.bag``, ROS 2 ``.db3`` and ``.mcap``; a LaserScan with a
JointState, a custom message with the angle inside, an encoder count) import to recordings that
``calstation reconstruct`` turns into the simulator's own cloud of the same scan within 1e-6 m;
bad input gets a one-sentence error and leaves no file behind."""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from calstation.cli import _build, app
from calstation.recordings.files import read_ply
from calstation.recordings.reader import read_recording
from tests.support.clirun import cli_fails
from tests.support.rosbag import CUSTOM, Bag

DATA = Path(__file__).resolve().parents[1] / "data" / "v1"
STOP_AND_GO_STEPS = 12


@pytest.fixture(scope="module")
def cli() -> CliRunner:
    _build()
    return CliRunner()


def _run(cli: CliRunner, *args: str) -> str:
    res = cli.invoke(app, [str(a) for a in args])
    assert res.exit_code == 0, res.output + repr(res.exception)
    return res.output


def _cloud(cli: CliRunner, recording: Path, truth: Path, out: Path) -> np.ndarray:
    _run(cli, "reconstruct", recording, "--truth", truth, "--out", out)
    return read_ply(out)


def _suffix(flavour: str) -> str:
    return {"ros1": "sim.bag", "db3": "sim_db3", "mcap": "sim_mcap"}[flavour]


# --- the simulator's own recordings -------------------------------------------------------------
@pytest.fixture(scope="module")
def stop_and_go(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The simulator taking a stop-and-go scan (turn a step, stop, take one line: as a tilting
    or nodding mount does), written as its own recording, with the line angles."""
    from calstation_sim.station import SimulatedStation

    from calstation.drivers import EncoderSample
    from calstation.recipes import load_recipe
    from calstation.recordings.writer import RecordingWriter

    out = tmp_path_factory.mktemp("stopgo")
    station = SimulatedStation(load_recipe(DATA / "recipe.yaml"))
    station.place("spin_target")
    t = station.clock.now_ns() + 10_000_000
    lines, angles = [], []
    for _ in range(STOP_AND_GO_STEPS):
        moving = station.set_speed(20.0, t)
        t = station.set_speed(0.0, moving + 20_000_000) + 30_000_000  # at rest again
        line = station.scan_line(t)
        lines.append(line)
        count = station.encoder_count(t + station.encoder_latency_ns)
        angles.append(station.encoder_direction * 360.0 * count / station.counts_per_revolution)
        t = int(line.point_times_ns()[-1]) + 30_000_000
    enc_t = np.arange(station.clock.now_ns(), t, 5_000_000, dtype=np.int64)
    enc_c = station.encoder_counts(enc_t)
    path = out / "stopgo.mcap"
    with RecordingWriter(path, kind="spin", lidar_info=station.lidar_info,
                         counts_per_revolution=station.counts_per_revolution,
                         encoder_direction=station.encoder_direction,
                         encoder_latency_s=station.encoder_latency_ns * 1e-9,
                         clock=station.clock) as w:
        k = 0
        for line in lines:
            j = int(np.searchsorted(enc_t, line.point_times_ns()[-1], "right")) + 1
            w.write_encoder(EncoderSample(int(a), int(b)) for a, b in zip(enc_t[k:j], enc_c[k:j],
                                                                        strict=True))
            k = j
            w.write_line(line)
        w.write_encoder(EncoderSample(int(a), int(b)) for a, b in zip(enc_t[k:], enc_c[k:],
                                                                    strict=True))
    truth = out / "truth.json"
    truth.write_text(json.dumps(station.truth_dict()))
    assert len(set(angles)) > STOP_AND_GO_STEPS // 2  # it did turn
    return {"recording": path, "truth": truth, "lines": lines, "angles": angles,
            "info": station.lidar_info}


def _write_jointstate_bag(rec: Any, bag: Bag, second: Bag | None = None,
                          other_joints: bool = False) -> None:
    """LaserScans on /scan, the platter angle as a JointState on /joint_states (at the encoder's
    readings, on the lines' clock), and the raw count as std_msgs/Int64 on /encoder. With
    ``second``, the recording's second half goes there (a split bag); with ``other_joints``,
    another publisher's JointStates (an arm's) share /joint_states."""
    info = rec.lidar_info
    first = bag
    latency = round(rec.encoder_latency_s * 1e9)
    phi = rec.encoder_direction * 2 * math.pi * rec.encoder_count / rec.counts_per_revolution
    lines = list(rec.lines())
    events = [(ln.timestamp_ns, 0, i) for i, ln in enumerate(lines)]
    events += [(int(t) - latency, 1, i) for i, t in enumerate(rec.encoder_t_ns)]
    middle = int(np.median([t for t, _, _ in events]))
    for t, what, i in sorted(events):
        bag = second if second is not None and t >= middle else first
        if what == 0:
            bag.write("/scan", "sensor_msgs/msg/LaserScan", t + 1_000_000,
                      bag.laser_scan(lines[i], info.range_min_m, info.range_max_m))
        else:
            js = bag.t("sensor_msgs/msg/JointState")(
                header=bag.header(t, "base"), name=["platter"],
                position=np.array([phi[i]]), velocity=np.zeros(0), effort=np.zeros(0))
            bag.write("/joint_states", "sensor_msgs/msg/JointState", t + 200_000, js)
            count = bag.t("std_msgs/msg/Int64")(data=int(rec.encoder_count[i]))
            bag.write("/encoder", "std_msgs/msg/Int64", t, count)
            if other_joints:
                arm = bag.t("sensor_msgs/msg/JointState")(
                    header=bag.header(t + 100_000, "base"), name=["shoulder", "elbow"],
                    position=np.array([1.0, 2.0]), velocity=np.zeros(0), effort=np.zeros(0))
                bag.write("/joint_states", "sensor_msgs/msg/JointState", t + 300_000, arm)


@pytest.mark.parametrize("flavour", ["ros1", "db3", "mcap"])
def test_a_laserscan_and_jointstate_bag_reconstructs_as_the_simulator(
    cli: CliRunner, spin: dict[str, Path], tmp_path: Path, flavour: str
) -> None:
    rec = read_recording(spin["spin"])
    path = tmp_path / _suffix(flavour)
    with Bag(path, flavour) as bag:
        _write_jointstate_bag(rec, bag)
    if flavour != "ros1":  # a ROS 2 bag is read from its folder or from its storage file
        path = next(path.glob("*.db3" if flavour == "db3" else "*.mcap"))
    out = tmp_path / "imported.mcap"
    said = _run(cli, "import", "rosbag", path, "--scan", "/scan",
                "--angle", "/joint_states:position[platter]", "--out", out)
    assert f"wrote {out}" in said
    want = _cloud(cli, spin["spin"], spin["truth"], tmp_path / "sim.ply")
    got = _cloud(cli, out, spin["truth"], tmp_path / "imported.ply")
    assert got.shape == want.shape
    assert np.max(np.linalg.norm(got - want, axis=1)) < 1e-6
    imported = read_recording(out)
    assert imported.n_lines == rec.n_lines and imported.n_points == rec.n_points
    np.testing.assert_array_equal(imported.valid, rec.valid)  # invalid kept, as invalid
    np.testing.assert_array_equal(imported.t_ns, rec.t_ns)  # per-point times, to the ns
    meta = imported.metadata["import"]
    assert meta["scan"] == "/scan" and meta["angle"] == "/joint_states:position[platter]"
    assert meta["stamps"] == "header" and meta["bag"]["files"][0]["sha256"]
    # the same angle as raw encoder counts, with the encoder's counts per turn: exact counts
    out2 = tmp_path / "counts.mcap"
    _run(cli, "import", "rosbag", path, "--scan", "/scan", "--angle", "/encoder",
         "--angle-unit", "counts", "--counts-per-rev", str(rec.counts_per_revolution),
         "--direction", str(rec.encoder_direction), "--stamps", "bag", "--out", out2)
    last = np.r_[rec.encoder_t_ns[1:] != rec.encoder_t_ns[:-1], True]  # one reading per time
    np.testing.assert_array_equal(read_recording(out2).encoder_count, rec.encoder_count[last])


@pytest.mark.parametrize("flavour", ["ros1", "mcap"])
def test_a_custom_message_with_the_angle_inside_reconstructs_as_the_simulator(
    cli: CliRunner, stop_and_go: dict[str, Any], tmp_path: Path, flavour: str
) -> None:
    """A stop-and-go scan: one custom message per line, bundling the LaserScan and the angle
    it was taken at (in degrees), held for the whole line."""
    info = stop_and_go["info"]
    path = tmp_path / _suffix(flavour)
    with Bag(path, flavour) as bag:
        for line, angle in zip(stop_and_go["lines"], stop_and_go["angles"], strict=True):
            msg = bag.t(CUSTOM)(scan=bag.laser_scan(line, info.range_min_m, info.range_max_m),
                                angle_deg=angle)
            bag.write("/slice", CUSTOM, line.timestamp_ns + 7_000_000, msg)
    out = tmp_path / "imported.mcap"
    _run(cli, "import", "rosbag", path, "--scan", "/slice:scan", "--angle", "/slice:angle_deg",
         "--angle-unit", "deg", "--counts-per-rev", "4096", "--out", out)
    want = _cloud(cli, stop_and_go["recording"], stop_and_go["truth"], tmp_path / "sim.ply")
    got = _cloud(cli, out, stop_and_go["truth"], tmp_path / "imported.ply")
    assert got.shape == want.shape and len(got) > 1000
    assert np.max(np.linalg.norm(got - want, axis=1)) < 1e-6
    # without FIELDs: the one LaserScan field and the one other number of the message
    _run(cli, "import", "rosbag", path, "--scan", "/slice", "--angle", "/slice",
         "--angle-unit", "deg", "--out", tmp_path / "auto.mcap")
    auto = _cloud(cli, tmp_path / "auto.mcap", stop_and_go["truth"], tmp_path / "auto.ply")
    assert np.max(np.linalg.norm(auto - want, axis=1)) < 1e-6


def test_a_split_bag_and_a_shared_joint_states_topic(
    cli: CliRunner, spin: dict[str, Path], tmp_path: Path
) -> None:
    """The two files of a split recording import as one; JointStates of other joints on the
    same topic are left out (with a note), the named joint's are used."""
    rec = read_recording(spin["spin"])
    a, b = tmp_path / "part_0.bag", tmp_path / "part_1.bag"
    with Bag(a, "ros1") as first, Bag(b, "ros1") as second:
        _write_jointstate_bag(rec, first, second, other_joints=True)
    out = tmp_path / "imported.mcap"
    res = cli.invoke(app, ["import", "rosbag", str(a), str(b), "--scan", "/scan",
                           "--angle", "/joint_states:position[platter]", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "without 'position[platter]' (other joints) left out" in " ".join(res.output.split())
    want = _cloud(cli, spin["spin"], spin["truth"], tmp_path / "sim.ply")
    got = _cloud(cli, out, spin["truth"], tmp_path / "imported.ply")
    assert got.shape == want.shape and np.max(np.linalg.norm(got - want, axis=1)) < 1e-6
    assert len(read_recording(out).metadata["import"]["bag"]) == 2


def test_an_imported_scan_is_a_recording_like_any_other(
    cli: CliRunner, spin: dict[str, Path], tmp_path: Path
) -> None:
    """It passes the one-clock check of the station's own recordings, and its metadata says
    where it came from."""
    from tests.support.one_clock import check_one_clock

    rec = read_recording(spin["spin"])
    path = tmp_path / "sim.bag"
    with Bag(path, "ros1") as bag:
        _write_jointstate_bag(rec, bag)
    out = tmp_path / "imported.mcap"
    _run(cli, "import", "rosbag", path, "--scan", "/scan", "--angle", "/joint_states",
         "--kind", "spin", "--station", "bench-7", "--out", out)
    check_one_clock(out)
    imported = read_recording(out)
    assert imported.metadata["calstation"]["kind"] == "spin"
    assert imported.metadata["calstation"]["station_id"] == "bench-7"
    assert imported.metadata["import"]["tool"] == "calstation import rosbag"
    assert imported.lidar_info.points_per_line == rec.lidar_info.points_per_line


# --- errors ---------------------------------------------------------------------------------
@pytest.fixture
def small_bag(tmp_path: Path, spin: dict[str, Path]) -> Iterator[Callable[..., Path]]:
    rec = read_recording(spin["spin"])
    lines = list(rec.lines())[:5]

    def make(name: str = "small.bag", *, scans: bool = True, angle: bool = True,
             intensities: int | None = None) -> Path:
        path = tmp_path / name
        with Bag(path, "ros1") as bag:
            if not angle:  # the topic is there, its messages are not
                bag.connections["/angle"] = bag.writer.add_connection(
                    "/angle", "std_msgs/msg/Float64", typestore=bag.store)
            for ln in lines if scans else []:
                inten = None if intensities is None else np.ones(intensities)
                bag.write("/scan", "sensor_msgs/msg/LaserScan", ln.timestamp_ns,
                          bag.laser_scan(ln, 0.05, 30.0, inten))
            for ln in lines if angle else []:
                bag.write("/angle", "std_msgs/msg/Float64", ln.timestamp_ns,
                          bag.t("std_msgs/msg/Float64")(data=0.1))
        return path

    yield make


def test_import_errors_are_one_sentence_and_leave_nothing(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, small_bag: Callable[..., Path]
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    target = out / "x.mcap"
    common = ("--out", target)
    bag = small_bag()
    err = cli_fails(capsys, out, "import", "rosbag", bag, "--scan", "/scan", "--angle", "/tilt",
                 *common)
    assert "--angle /tilt" in err and "no topic /tilt" in err and "/scan (sensor_msgs" in err
    err = cli_fails(capsys, out, "import", "rosbag", small_bag("noangle.bag", angle=False),
                 "--scan", "/scan", "--angle", "/angle", *common)
    assert "--angle /angle: topic /angle has no messages" in err and "angle is missing" in err
    err = cli_fails(capsys, out, "import", "rosbag", bag, "--scan", "/scan",
                 "--angle", "/angle:value", *common)
    assert "topic /angle (std_msgs/msg/Float64)" in err and "no field 'value'" in err
    assert "fields data" in err
    err = cli_fails(capsys, out, "import", "rosbag", small_bag("mismatch.bag", intensities=3),
                 "--scan", "/scan", "--angle", "/angle", *common)
    assert "mismatched lengths" in err and "3 intensities" in err and "/scan" in err
    err = cli_fails(capsys, out, "import", "rosbag", small_bag("empty.bag", scans=False,
                                                             angle=False),
                 "--scan", "/scan", "--angle", "/angle", *common)
    assert "is empty" in err
    err = cli_fails(capsys, out, "import", "rosbag", bag, "--scan", "/angle", "--angle", "/angle",
                 *common)
    assert "not a sensor_msgs/msg/LaserScan" in err and "/angle" in err
    err = cli_fails(capsys, out, "import", "rosbag", bag, "--scan", "/scan", "--angle", "/angle",
                 "--angle-unit", "counts", *common)
    assert "--counts-per-rev" in err
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"not a bag")
    err = cli_fails(capsys, out, "import", "rosbag", junk, "--scan", "/scan", "--angle", "/a",
                 *common)
    assert "junk.bag" in err and "cannot read" in err


def test_an_unknown_type_is_a_clear_error(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """A ROS 2 bag (format 8) does not carry its custom types' definitions."""
    from rosbags.rosbag2 import Writer as W2
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg("float64 tilt\n", "acme_msgs/msg/Tilt"))
    path = tmp_path / "old_bag"
    with W2(path, version=8) as w:
        c = w.add_connection("/tilt", "acme_msgs/msg/Tilt", typestore=store)
        w.write(c, 1, store.serialize_cdr(store.types["acme_msgs/msg/Tilt"](tilt=0.5),
                                          "acme_msgs/msg/Tilt"))
    out = tmp_path / "out"
    out.mkdir()
    err = cli_fails(capsys, out, "import", "rosbag", path, "--scan", "/tilt", "--angle", "/tilt",
                 "--out", out / "x.mcap")
    assert "acme_msgs/msg/Tilt" in err


def test_a_failure_while_writing_keeps_the_previous_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, small_bag: Callable[..., Path]
) -> None:
    """The recording is written under a temporary name and renamed at the end: a failure half
    way leaves the previous file as it was and nothing else."""
    from calstation.recordings import imported
    from calstation.recordings.rosbag import TopicSpec, read_rosbag

    scan = read_rosbag(small_bag(), TopicSpec("/scan", ""), TopicSpec("/angle", ""))
    out = tmp_path / "out"
    out.mkdir()
    target = out / "x.mcap"
    target.write_bytes(b"previous")

    def boom(done: int, total: int) -> None:
        if done == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        imported.write_imported(scan, target, progress=boom)
    assert target.read_bytes() == b"previous" and sorted(out.iterdir()) == [target]


# --- csv ------------------------------------------------------------------------------------
def test_a_csv_line_log_reconstructs_as_the_simulator(
    cli: CliRunner, stop_and_go: dict[str, Any], tmp_path: Path
) -> None:
    lines, info = stop_and_go["lines"], stop_and_go["info"]
    n = len(lines[0])
    az = np.degrees(lines[0].azimuth_rad)
    rows = ["t_s;tilt_deg;" + ";".join(f"r{i}" for i in range(n))]
    for line, angle in zip(lines, stop_and_go["angles"], strict=True):
        sec, nsec = divmod(line.timestamp_ns, 1_000_000_000)
        cells = [repr(float(r)) if v else "" for r, v in zip(line.range_m * 1000, line.valid,
                                                               strict=True)]
        rows.append(f"{sec}.{nsec:09d};{angle!r};" + ";".join(cells))
    log = tmp_path / "lines.csv"
    log.write_text("\n".join(rows) + "\n")
    out = tmp_path / "csv.mcap"
    _run(cli, "import", "csv", log, "--time", "t_s", "--angle", "tilt_deg", "--angle-unit",
         "deg", "--counts-per-rev", "4096", "--ranges", "r*", "--range-unit", "mm",
         "--azimuths", f"{float(az[0])!r}:{float(az[1] - az[0])!r}", "--point-period",
         repr(lines[0].point_period_ns * 1e-9), "--range-min", str(info.range_min_m),
         "--hold", "--out", out)
    want = _cloud(cli, stop_and_go["recording"], stop_and_go["truth"], tmp_path / "sim.ply")
    got = _cloud(cli, out, stop_and_go["truth"], tmp_path / "csv.ply")
    assert got.shape == want.shape
    assert np.max(np.linalg.norm(got - want, axis=1)) < 1e-6
    assert read_recording(out).metadata["import"]["tool"] == "calstation import csv"


def test_csv_errors_name_the_row_and_column(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    log = tmp_path / "l.csv"
    args = ("--time", "t", "--angle", "a", "--ranges", "r*", "--azimuths", "-10:1",
            "--out", out / "x.mcap")
    log.write_text("t,a,r0,r1\n1.0,0.1,1.0,1.1\n1.1,,1.0,1.2\n")
    err = cli_fails(capsys, out, "import", "csv", log, *args)
    assert "row 3" in err and "column 'a'" in err and "angle is missing" in err
    log.write_text("t,a,r0,r1\n1.0,0.1,1.0,1.1\n")
    err = cli_fails(capsys, out, "import", "csv", log, *args[:-2], "--time", "time",
                 "--out", out / "x.mcap")
    assert "--time 'time'" in err and "columns: t, a, r0, r1" in err
    log.write_text("t;a;r\n1.0;0.1;1.0 1.1 1.2\n1.1;0.2;1.0 1.1\n")
    err = cli_fails(capsys, out, "import", "csv", log, "--time", "t", "--angle", "a", "--ranges",
                 "r", "--azimuths", "-10:1", "--out", out / "x.mcap")
    assert "row 3" in err and "mismatched lengths" in err
    log.write_text("t,a,r0\n")
    err = cli_fails(capsys, out, "import", "csv", log, *args)
    assert "no lines" in err
