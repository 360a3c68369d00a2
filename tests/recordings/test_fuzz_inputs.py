"""Fuzzing what calstation reads from outside: recordings (version 2 and version 1), ROS bags and
recipes, changed at random by hypothesis. Whatever the change, the reader gives a result or its
own error (RecordingError, RecordingImportError, RecipeError): never another exception, never a
hang (each example is small and its reads are bounded).

The number of examples of each target is ``CALSTATION_FUZZ_EXAMPLES`` (default 40, what CI runs
with the derandomised ``ci`` profile of tests/conftest.py); a longer hunt:
``CALSTATION_FUZZ_EXAMPLES=5000 pytest tests/recordings/test_fuzz_inputs.py``.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from calstation.errors import RecipeError, RecordingError, RecordingImportError

REPO = Path(__file__).resolve().parents[2]
V1 = REPO / "tests" / "data" / "v1" / "static.mcap"
RECIPE = (REPO / "recipes" / "sim-periodicity.yaml").read_text(encoding="utf-8")
EXAMPLES = int(os.environ.get("CALSTATION_FUZZ_EXAMPLES", "40"))
FUZZ = settings(max_examples=EXAMPLES, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

# --- byte-level changes of a file -----------------------------------------------------------
EDITS = st.lists(
    st.tuples(st.sampled_from(["flip", "set", "insert", "delete", "truncate", "repeat"]),
              st.floats(0.0, 1.0), st.integers(0, 255), st.integers(1, 4096)),
    min_size=1, max_size=6,
)


def edited(data: bytes, edits: list[tuple[str, float, int, int]]) -> bytes:
    """``data`` with each edit applied at its relative position."""
    out = bytearray(data)
    for kind, where, value, size in edits:
        at = min(int(where * len(out)), max(len(out) - 1, 0))
        if kind == "flip" and out:
            out[at] ^= 1 << (value % 8)
        elif kind == "set" and out:
            out[at] = value
        elif kind == "insert":
            out[at:at] = bytes([value]) * (size % 64 + 1)
        elif kind == "delete":
            del out[at : at + size]
        elif kind == "truncate":
            del out[at:]
        elif kind == "repeat":
            out[at:at] = out[at : at + size]
    return bytes(out)


def _read(path: Path) -> Any:
    """read_recording, with its truncation warning allowed."""
    from calstation.recordings.reader import read_recording

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_recording(path)


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """A small version-2 recording: 40 lines of 60 points and the encoder between them."""
    from calstation.drivers import EncoderSample, LidarInfo, LidarLine
    from calstation.recordings.writer import RecordingWriter

    path = tmp_path_factory.mktemp("fuzz") / "seed.mcap"
    t0 = 1_767_225_600_000_000_000
    rng = np.random.default_rng(0)
    with RecordingWriter(path, kind="spin", lidar_info=LidarInfo("acme", "x", "1", 1.0, 60,
                                                                 100.0, 0.1, 10.0),
                         counts_per_revolution=4096, encoder_direction=1,
                         chunk_size=4096) as w:
        w.write_encoder(EncoderSample(t0 + k * 1_000_000, k) for k in range(500))
        for i in range(40):
            w.write_line(LidarLine(t0 + 10_000_000 + i * 10_000_000, np.linspace(-0.5, 0.5, 60),
                                   1.0 + rng.random(60), rng.random(60) > 0.2, 50_000.0))
    return path.read_bytes()


@FUZZ
@given(edits=EDITS)
def test_a_changed_recording_is_read_or_refused_in_one_error(
    recording: bytes, tmp_path_factory: pytest.TempPathFactory, edits: list[Any]
) -> None:
    path = tmp_path_factory.mktemp("mcap") / "changed.mcap"
    path.write_bytes(edited(recording, edits))
    try:
        rec = _read(path)
    except RecordingError as exc:
        assert str(path) in str(exc), exc
        return
    assert rec.n_lines <= 40 and len(rec.encoder_t_ns) <= 500


# --- version 1: JSON messages whose fields are changed --------------------------------------
JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.floats()
    | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner,
                                                                 max_size=4),
    max_leaves=10,
)


@pytest.fixture(scope="module")
def v1_messages() -> list[tuple[str, str, bytes, int]]:
    """The version-1 fixture's messages: (topic, encoding, data, log time)."""
    from mcap.reader import make_reader

    with V1.open("rb") as f:
        reader = make_reader(f)
        return [(ch.topic, ch.message_encoding, bytes(msg.data), msg.log_time)
                for _, ch, msg in reader.iter_messages()]


def _v1_file(path: Path, messages: list[tuple[str, str, bytes, int]]) -> None:
    """A version-1 recording of ``messages`` with the fixture's metadata."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    with V1.open("rb") as f:
        reader = make_reader(f)
        metadata = [(m.name, dict(m.metadata)) for m in reader.iter_metadata()]
    out = io.BytesIO()
    w = Writer(out, compression=CompressionType.NONE)
    w.start()
    schema = w.register_schema("calstation.v1", "jsonschema", b"{}")
    channels: dict[str, int] = {}
    for topic, encoding, data, t in messages:
        if topic not in channels:
            channels[topic] = w.register_channel(topic, encoding, schema)
        w.add_message(channels[topic], log_time=t, publish_time=t, data=data)
    for name, values in metadata:
        w.add_metadata(name, values)
    w.finish()
    path.write_bytes(out.getvalue())


@FUZZ
@given(which=st.floats(0.0, 1.0), key=st.sampled_from(
    ["timestamp_ns", "count", "point_period_ns", "azimuth_rad", "range_m", "valid",
     "time_offset_ns", "intensity", "state", "speed_rpm", "position_rad"]),
    value=JSON_VALUES | st.just("__delete__"))
def test_a_version_1_message_with_any_field_is_read_or_refused(
    v1_messages: list[tuple[str, str, bytes, int]], tmp_path_factory: pytest.TempPathFactory,
    which: float, key: str, value: Any,
) -> None:
    messages = list(v1_messages)
    i = min(int(which * len(messages)), len(messages) - 1)
    topic, encoding, data, t = messages[i]
    body = json.loads(data)
    if value == "__delete__":
        body.pop(key, None)
    else:
        body[key] = value
    messages[i] = (topic, encoding, json.dumps(body, allow_nan=True).encode(), t)
    path = tmp_path_factory.mktemp("v1") / "changed.mcap"
    _v1_file(path, messages)
    try:
        _read(path)
    except RecordingError as exc:
        assert str(path) in str(exc), exc


# --- ROS bags: a LaserScan of any numbers, and changed bytes --------------------------------
FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=32)


def _bag(path: Path, scan: dict[str, Any], ranges: list[float]) -> None:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    t = store.types
    with Writer(path) as w:
        cs = w.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=store)
        ca = w.add_connection("/angle", "std_msgs/msg/Float64", typestore=store)
        for k in range(4):
            stamp_ns = 1_767_225_600_000_000_000 + k * 25_000_000
            header = t["std_msgs/msg/Header"](
                seq=k, stamp=t["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9,
                                                               nanosec=stamp_ns % 10**9),
                frame_id="laser")
            msg = t["sensor_msgs/msg/LaserScan"](
                header=header, ranges=np.asarray(ranges, np.float32),
                intensities=np.zeros(0, np.float32),
                **{k2: np.float32(v) for k2, v in scan.items()})
            w.write(cs, stamp_ns, store.serialize_ros1(msg, "sensor_msgs/msg/LaserScan"))
            w.write(ca, stamp_ns, store.serialize_ros1(t["std_msgs/msg/Float64"](data=0.1 * k),
                                                       "std_msgs/msg/Float64"))


SCAN_FIELDS = st.fixed_dictionaries({
    name: FLOATS for name in ("angle_min", "angle_max", "angle_increment", "time_increment",
                              "scan_time", "range_min", "range_max")})


@pytest.mark.filterwarnings("error::RuntimeWarning")  # an overflow is a wrong line, not a pass
@FUZZ
@given(scan=SCAN_FIELDS, ranges=st.lists(FLOATS, max_size=40))
def test_a_laserscan_of_any_numbers_is_imported_or_refused(
    tmp_path_factory: pytest.TempPathFactory, scan: dict[str, float], ranges: list[float]
) -> None:
    from calstation.recordings.imported import write_imported
    from calstation.recordings.rosbag import TopicSpec, read_rosbag

    folder = tmp_path_factory.mktemp("bag")
    _bag(folder / "s.bag", scan, ranges)
    try:
        imported = read_rosbag(folder / "s.bag", TopicSpec("/scan", ""), TopicSpec("/angle", ""))
        write_imported(imported, folder / "out.mcap")
    except RecordingImportError:
        assert not (folder / "out.mcap").exists()
        return
    rec = _read(folder / "out.mcap")  # what was imported reads back
    assert np.all(np.isfinite(rec.azimuth_rad)) and np.all(np.isfinite(rec.t_ns))


@pytest.fixture(scope="module")
def bag_bytes(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    path = tmp_path_factory.mktemp("seed-bag") / "seed.bag"
    _bag(path, {"angle_min": -0.5, "angle_max": 0.5, "angle_increment": 1.0 / 19,
                "time_increment": 1e-4, "scan_time": 0.025, "range_min": 0.1,
                "range_max": 10.0}, [1.0 + 0.01 * i for i in range(20)])
    return path.read_bytes()


@FUZZ
@given(edits=EDITS)
def test_a_changed_bag_is_imported_or_refused_in_one_error(
    bag_bytes: bytes, tmp_path_factory: pytest.TempPathFactory, edits: list[Any]
) -> None:
    from calstation.recordings.rosbag import TopicSpec, read_rosbag

    path = tmp_path_factory.mktemp("bag") / "changed.bag"
    path.write_bytes(edited(bag_bytes, edits))
    with contextlib.suppress(RecordingImportError):  # its one error, or the scan
        read_rosbag(path, TopicSpec("/scan", ""), TopicSpec("/angle", ""))


# --- recipes --------------------------------------------------------------------------------
YAML_BITS = st.sampled_from([
    "", " ", "\n", "\t", ":", "- ", "[", "]", "{", "}", ",", "&a", "*a", "!!python/object ",
    "<<: *a", "'", '"', "#", "?", "|", ">", "~", "null", ".nan", ".inf", "-.inf", "1e400",
    "9" * 120, "0x1F", "0o17", "true", "2026-01-01", "\u202e", "\x1b", "\x00",
])


@FUZZ
@given(edits=st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(0, 40),
                                st.lists(YAML_BITS | st.text(max_size=6), max_size=4)),
                      min_size=1, max_size=5))
def test_a_changed_recipe_is_loaded_or_refused_in_one_error(
    tmp_path_factory: pytest.TempPathFactory, edits: list[tuple[float, int, list[str]]]
) -> None:
    from calstation.plugins.recipe_checks import check_plugins
    from calstation.recipes import load_recipe

    text = RECIPE
    for where, cut, bits in edits:
        at = int(where * len(text))
        text = text[:at] + "".join(bits) + text[at + cut :]
    path = tmp_path_factory.mktemp("recipe") / "r.yaml"
    path.write_bytes(text.encode("utf-8", "surrogatepass"))
    try:
        check_plugins(load_recipe(path))
    except RecipeError as exc:
        assert str(path) in str(exc), exc


@FUZZ
@given(value=JSON_VALUES, field=st.sampled_from([
    ("steps", "spin_scan", "rpm"), ("steps", "static_scan", "lines"),
    ("fixtures", "platter", "radius"), ("simulation", "lidar", "range_noise"),
    ("calibration", "strategy"), ("qa", "edge_error"), ("station", "id"), ("name",)]))
def test_a_recipe_field_of_any_value_is_loaded_or_refused(
    tmp_path_factory: pytest.TempPathFactory, value: Any, field: tuple[str, ...]
) -> None:
    import yaml

    from calstation.plugins.recipe_checks import check_plugins
    from calstation.recipes import load_recipe

    data = yaml.safe_load(RECIPE)
    node = data
    for key in field[:-1]:
        node = node[key]
    node[field[-1]] = value
    try:
        text = yaml.safe_dump(data)
    except (yaml.YAMLError, ValueError):
        return  # not a value YAML can hold
    path = tmp_path_factory.mktemp("recipe") / "fuzz.yaml"
    path.write_text(text, encoding="utf-8")
    try:
        loaded = load_recipe(path)
        check_plugins(loaded)
    except RecipeError as exc:
        assert str(path) in str(exc), exc
        return
    recipe = loaded.recipe
    assert all(math.isfinite(x) for x in (recipe.steps.spin_scan.rpm,
                                          recipe.fixtures.platter.radius))
