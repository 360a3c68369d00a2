"""MCAP recordings: round trip, crash recovery, bad files, platter angle."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest

from calstation.drivers import (
    EncoderSample,
    TurntableState,
    TurntableStatus,
)
from calstation.engine.frames import Extrinsics, polar_to_lidar
from calstation.errors import RecordingError
from calstation.recipes import LoadedRecipe, parse_recipe
from calstation.recordings.channels import FORMAT_VERSION
from calstation.recordings.reader import RecordingTruncatedWarning, read_recording
from tests.support.paths import REPO
from tests.support.recordings import INFO, T0, make_line, writer

RECIPE_TEXT = textwrap.dedent(
    """\
    name: test-recipe
    station:
      id: st-7
      lidar: {driver: replay}
      turntable: {driver: replay}
      encoder: {driver: replay, ppr: 1024}
    """
)


def test_round_trip(tmp_path: Path) -> None:
    recipe = LoadedRecipe(parse_recipe(RECIPE_TEXT), None, RECIPE_TEXT)
    lines = [make_line(i, offsets=(i % 3 == 1), intensity=(i % 2 == 0)) for i in range(40)]
    enc = [EncoderSample(T0 + k * 500_000, 3 * k - 5) for k in range(90)]
    status = TurntableStatus(T0 + 5, TurntableState.MOVING, 20.0, 1.25, ("warn",))
    truth = {"tx": 0.01, "ty": 1.2, "tz": -0.003, "rx": 0.0, "ry": 0.002, "rz": -0.78,
             "fixtures": {"qa_cube": {"y": 0.08, "z": 0.05, "yaw_rad": np.float64(0.3)}},
             "seed": np.int64(7), "scenario": {"range_m": 1.25, "pitch_deg": 45.0}}
    path = tmp_path / "r.mcap"
    with writer(path, station_id="st-7", recipe=recipe, encoder_latency_s=0.002,
                encoder_direction=-1, metadata={"truth": truth}) as w:
        w.write_turntable(status)
        for i, line in enumerate(lines):
            w.write_line(line)
            w.write_encoder(enc[2 * i : 2 * i + 2])
        w.write_encoder(enc[80:])
        w.add_metadata("notes", {"operator": "ann", "values": [1, 2, 3]})

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rec = read_recording(path)
    assert not rec.truncated
    assert rec.kind == "spin"
    assert rec.lidar_info == INFO
    assert (rec.counts_per_revolution, rec.encoder_direction) == (4096, -1)
    assert rec.encoder_latency_s == pytest.approx(0.002)
    cal = rec.metadata["calstation"]
    assert cal["format_version"] == FORMAT_VERSION
    assert cal["station_id"] == "st-7"
    assert cal["recipe_name"] == "test-recipe"
    assert cal["recipe_sha256"] == recipe.sha256
    assert rec.recipe_text == RECIPE_TEXT
    assert rec.metadata["notes"] == {"operator": "ann", "values": [1, 2, 3]}
    assert rec.metadata["truth"]["fixtures"]["qa_cube"]["yaw_rad"] == 0.3
    assert rec.truth == Extrinsics(0.01, 1.2, -0.003, 0.0, 0.002, -0.78)
    assert rec.turntable == [status]

    assert rec.n_lines == 40 and rec.n_points == 4000
    np.testing.assert_array_equal(rec.line_timestamp_ns, [ln.timestamp_ns for ln in lines])
    np.testing.assert_array_equal(rec.line_index, np.repeat(np.arange(40), 100))
    np.testing.assert_array_equal(rec.azimuth_rad, np.concatenate([ln.azimuth_rad for ln in lines]))
    np.testing.assert_allclose(
        rec.range_m, np.concatenate([ln.range_m for ln in lines]), rtol=1e-7
    )  # stored as float32
    np.testing.assert_array_equal(rec.valid, np.concatenate([ln.valid for ln in lines]))
    np.testing.assert_array_equal(rec.t_ns, np.concatenate([ln.point_times_ns() for ln in lines]))
    assert rec.intensity is not None
    for i, line in enumerate(lines):
        got = rec.intensity[i * 100 : (i + 1) * 100]
        if line.intensity is None:
            assert np.isnan(got).all()
        else:
            np.testing.assert_allclose(got, line.intensity, rtol=1e-6)
    np.testing.assert_array_equal(rec.encoder_t_ns, [s.timestamp_ns for s in enc])
    np.testing.assert_array_equal(rec.encoder_count, [s.count for s in enc])
    assert rec.encoder_samples() == enc

    back = list(rec.lines())
    assert len(back) == 40
    for orig, got in zip(lines, back, strict=True):
        assert got.timestamp_ns == orig.timestamp_ns
        assert got.point_period_ns == orig.point_period_ns
        assert (got.time_offset_ns is None) == (orig.time_offset_ns is None)
        np.testing.assert_array_equal(got.point_times_ns(), orig.point_times_ns())
        np.testing.assert_array_equal(got.valid, orig.valid)


def test_the_writer_takes_any_recipe_with_a_name_a_text_and_a_sha256(tmp_path: Path) -> None:
    """The writer knows no recipe model: it stores the ``name``, ``sha256`` and ``text`` of what
    it is given (a LoadedRecipe, or this plain record)."""

    class Plain(NamedTuple):
        name: str
        text: str
        sha256: str

    plain = Plain("plain", "name: plain\n", "ab" * 32)
    path = tmp_path / "r.mcap"
    with writer(path, recipe=plain) as w:
        w.write_line(make_line(0))
    rec = read_recording(path)
    cal = rec.metadata["calstation"]
    assert (cal["recipe_name"], cal["recipe_sha256"]) == ("plain", "ab" * 32)
    assert rec.recipe_text == "name: plain\n"


def test_file_is_plain_mcap_in_well_known_schemas(tmp_path: Path) -> None:
    """Any MCAP reader sees the foxglove schemas, and a standard protobuf decoder decodes every
    message to the values written (LaserScan bearings π/2 − α, NaN for invalid returns)."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    path = tmp_path / "r.mcap"
    line = make_line(0, intensity=True)
    H = Extrinsics(0.01, 1.2, -0.003, 0.0, 0.002, -0.78)
    with writer(path, calibration=H, calibration_source="fine") as w:
        w.write_line(line)
        w.write_encoder([EncoderSample(T0, 0), EncoderSample(T0 + 200_000_000, 1024)])
        w.write_turntable(TurntableStatus(T0, TurntableState.MOVING, 20.0, None, ()))
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None
        schemas = {s.name: s.encoding for s in summary.schemas.values()}
        assert {"foxglove.LaserScan", "foxglove.FrameTransform", "foxglove.PointCloud",
                "calstation.LidarLineTiming", "calstation.EncoderSamples"} <= set(schemas)
        assert schemas["foxglove.LaserScan"] == "protobuf"
        topics = {c.topic: c.message_encoding for c in summary.channels.values()}
        assert topics["/lidar/scan"] == "protobuf" and topics["/turntable/status"] == "json"
        decoded: dict[str, list[object]] = {}
        for _, channel, _, proto in reader.iter_decoded_messages(
            topics=["/lidar/scan", "/lidar/line", "/encoder/count", "/tf", "/tf_static",
                    "/platter/cloud"]
        ):
            decoded.setdefault(channel.topic, []).append(proto)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    scan = decoded["/lidar/scan"][0]
    assert scan.frame_id == "lidar"
    assert scan.timestamp.ToNanoseconds() == T0
    assert scan.start_angle == pytest.approx(np.pi / 2 - line.azimuth_rad[0])
    assert scan.end_angle == pytest.approx(np.pi / 2 - line.azimuth_rad[-1])
    ranges = np.array(scan.ranges)
    np.testing.assert_array_equal(ranges[line.valid], line.range_m[line.valid])
    assert np.isnan(ranges[~line.valid]).all()
    np.testing.assert_array_equal(scan.intensities, line.intensity)
    timing = decoded["/lidar/line"][0]
    np.testing.assert_array_equal(timing.azimuth_rad, line.azimuth_rad)
    np.testing.assert_array_equal(timing.valid, line.valid)
    np.testing.assert_array_equal(timing.invalid_range_m, line.range_m[~line.valid])
    assert timing.point_period_ns == line.point_period_ns
    enc = decoded["/encoder/count"][0]
    assert list(enc.count) == [0, 1024]
    tf = decoded["/tf"][0]  # a quarter turn: 1024 of 4096 counts
    assert (tf.parent_frame_id, tf.child_frame_id) == ("platform", "platter")
    q = tf.rotation
    np.testing.assert_allclose([q.x, q.y, q.z, q.w], [np.sin(np.pi / 4), 0, 0, np.cos(np.pi / 4)])
    static = decoded["/tf_static"][0]
    assert (static.parent_frame_id, static.child_frame_id) == ("lidar", "platform")
    tr, q = static.translation, static.rotation
    np.testing.assert_allclose([tr.x, tr.y, tr.z], H.t)
    np.testing.assert_allclose([q.x, q.y, q.z, q.w], H.as_quaternion())
    cloud = decoded["/platter/cloud"][0]
    assert cloud.frame_id == "platter" and cloud.point_stride == 12
    assert [f.name for f in cloud.fields] == ["x", "y", "z"]
    assert len(cloud.data) == 12 * int(line.valid.sum())
    assert json.loads(meta["encoder"]["counts_per_revolution"]) == 4096
    assert json.loads(meta["calstation"]["format_version"]) == 2
    assert json.loads(meta["calibration"]["source"]) == "fine"
    assert read_recording(path).calibration == H


def test_chunks_are_on_disk_while_writing(tmp_path: Path) -> None:
    path = tmp_path / "live.mcap"
    w = writer(path, chunk_size=20_000)
    size0 = path.stat().st_size
    for i in range(30):
        w.write_line(make_line(i))
    assert path.stat().st_size > size0 + 10_000  # several chunks flushed, writer still open
    w.close()


_KILL_CHILD = textwrap.dedent(
    """
    import sys
    sys.path.insert(0, {repo!r})
    from calstation.drivers import EncoderSample
    from tests.support.recordings import make_line, writer, T0
    from pathlib import Path
    w = writer(Path({path!r}), chunk_size=30_000)
    i = 0
    while True:
        w.write_line(make_line(i))
        w.write_encoder([EncoderSample(T0 + i * 1_000_000, i)])
        i += 1
        if i % 25 == 0:
            w.flush()
            print(i, flush=True)
    """
)


def test_writer_killed_mid_scan_is_readable(tmp_path: Path) -> None:
    """A real SIGKILL: the data of every complete chunk is read back, with a warning."""
    path = tmp_path / "killed.mcap"
    code = _KILL_CHILD.format(repo=str(REPO), path=str(path))
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        flushed = 0
        deadline = time.monotonic() + 60
        while flushed < 100 and time.monotonic() < deadline:
            line = proc.stdout.readline()
            assert line, "writer process died early"
            flushed = int(line)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == -signal.SIGKILL
    assert flushed >= 100

    with pytest.warns(RecordingTruncatedWarning, match=r"not closed cleanly \(writer killed\?\)"
                      r": read \d+ lines / \d+ encoder samples up to t=") as record:
        rec = read_recording(path)
    assert str(path) in str(record[0].message)
    assert rec.truncated
    # everything flushed before the kill was seen is there, and it is an exact prefix
    assert rec.n_lines >= flushed
    for i, got in enumerate(rec.lines()):
        want = make_line(i)
        assert got.timestamp_ns == want.timestamp_ns
        np.testing.assert_array_equal(got.azimuth_rad, want.azimuth_rad)
        np.testing.assert_allclose(got.range_m, want.range_m, rtol=1e-7)
        np.testing.assert_array_equal(got.valid, want.valid)
    np.testing.assert_array_equal(rec.encoder_count, np.arange(len(rec.encoder_count)))
    assert len(rec.encoder_count) >= flushed


def test_truncated_at_any_byte_never_crashes(tmp_path: Path) -> None:
    path = tmp_path / "full.mcap"
    with writer(path, chunk_size=5_000) as w:
        for i in range(30):
            w.write_line(make_line(i))
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    seen = []
    for n in range(0, len(data), max(1, len(data) // 97)):
        cut.write_bytes(data[:n])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RecordingTruncatedWarning)
            try:
                rec = read_recording(cut)
            except RecordingError as exc:
                assert str(cut) in str(exc)
                continue
        assert rec.truncated
        seen.append(rec.n_lines)
    assert seen == sorted(seen) and seen[-1] == 30 and seen[0] < 30


def test_bad_files(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="does not exist"):
        read_recording(tmp_path / "missing.mcap")
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(RecordingError, match=r"empty\.mcap is empty"):
        read_recording(empty)
    text = tmp_path / "notes.mcap"
    text.write_text("just some text, not a recording\n")
    with pytest.raises(RecordingError, match=r"notes\.mcap is not an MCAP file"):
        read_recording(text)
    with pytest.raises(RecordingError, match="is not a file"):
        read_recording(tmp_path)

    from mcap.writer import Writer

    foreign = tmp_path / "foreign.mcap"
    with open(foreign, "wb") as f:
        mw = Writer(f)
        mw.start()
        mw.add_metadata("something", {"a": "b"})
        mw.finish()
    with pytest.raises(RecordingError, match=r"foreign\.mcap has no 'calstation' metadata"):
        read_recording(foreign)

    no_lines = tmp_path / "nolines.mcap"
    with writer(no_lines) as w:
        w.write_encoder([EncoderSample(T0, 0)])
    with pytest.raises(RecordingError, match=r"nolines\.mcap contains no lidar lines"):
        read_recording(no_lines)


def test_writer_rejects_bad_input(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="reserved"):
        writer(tmp_path / "a.mcap", metadata={"lidar": {}})
    with pytest.raises(RecordingError, match="direction"):
        writer(tmp_path / "b.mcap", encoder_direction=2)
    with writer(tmp_path / "c.mcap") as w:
        with pytest.raises(RecordingError, match="negative timestamp"):
            w.write_encoder([EncoderSample(-5, 0)])
        with pytest.raises(RecordingError, match="cannot be stored as JSON"):
            w.add_metadata("truth", {"x": object()})
    with pytest.raises(RecordingError, match="already closed"):
        w.write_line(make_line(0))


def _encoder_recording(
    tmp_path: Path, *, direction: int = 1, latency_s: float = 0.0, counts: list[int] | None = None
) -> Path:
    path = tmp_path / f"enc{direction}_{latency_s}.mcap"
    with writer(path, encoder_direction=direction, encoder_latency_s=latency_s) as w:
        w.write_line(make_line(0))
        # 1 kHz samples, 4 counts per ms = 4000 counts/s
        cs = counts if counts is not None else [4 * k for k in range(101)]
        w.write_encoder([EncoderSample(T0 + k * 1_000_000, c) for k, c in enumerate(cs)])
    return path


def test_platter_angle_interpolates_in_time(tmp_path: Path) -> None:
    rec = read_recording(_encoder_recording(tmp_path))
    t = np.array([T0, T0 + 250_000, T0 + 50_500_000, T0 + 100_000_000])
    expected = 2 * np.pi * np.array([0.0, 1.0, 202.0, 400.0]) / 4096
    np.testing.assert_allclose(rec.platter_angle(t), expected, rtol=0, atol=1e-12)
    outside = rec.platter_angle([T0 - 1, T0 + 100_000_001])
    assert np.isnan(outside).all()


def test_platter_angle_direction_and_latency(tmp_path: Path) -> None:
    rec = read_recording(_encoder_recording(tmp_path, direction=-1))
    assert rec.platter_angle(T0 + 10_000_000) == pytest.approx(-2 * np.pi * 40 / 4096)
    # the encoder stamps each reading 3 ms late: the count stamped T0+13 ms was at lidar T0+10 ms
    rec = read_recording(_encoder_recording(tmp_path, latency_s=0.003))
    assert rec.platter_angle(T0 + 10_000_000) == pytest.approx(2 * np.pi * 52 / 4096)
    assert np.isnan(rec.platter_angle(T0 + 99_000_000))  # past the last reading once shifted


def test_platter_at_rest_holds_everywhere(tmp_path: Path) -> None:
    rec = read_recording(_encoder_recording(tmp_path, counts=[1024, 1024]))
    np.testing.assert_allclose(rec.platter_angle([T0 - 10**9, T0 + 10**10]), np.pi / 2)


def test_no_encoder_is_an_error(tmp_path: Path) -> None:
    path = tmp_path / "noenc.mcap"
    with writer(path) as w:
        w.write_line(make_line(0))
    rec = read_recording(path)
    with pytest.raises(RecordingError, match="no encoder readings"):
        rec.platter_angle(T0)


def test_points_lidar(tmp_path: Path) -> None:
    path = _encoder_recording(tmp_path)
    rec = read_recording(path)
    p_L, phi = rec.points_lidar()
    line = make_line(0)
    v = line.valid
    np.testing.assert_allclose(p_L, polar_to_lidar(rec.range_m[v], line.azimuth_rad[v]))
    np.testing.assert_allclose(phi, rec.platter_angle(line.point_times_ns()[v]))
    assert len(phi) == v.sum()


def test_failed_scan_is_closed_with_the_reason(tmp_path: Path) -> None:
    path = tmp_path / "failed.mcap"
    with pytest.raises(RuntimeError, match="turntable fault"), writer(path) as w:
        for i in range(5):
            w.write_line(make_line(i))
        raise RuntimeError("turntable fault: overcurrent")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rec = read_recording(path)
    assert not rec.truncated and rec.n_lines == 5
    assert rec.metadata["aborted"] == {"error": "RuntimeError: turntable fault: overcurrent"}


def test_bad_metadata_leaves_no_file(tmp_path: Path) -> None:
    path = tmp_path / "never.mcap"
    with pytest.raises(RecordingError, match=r"metadata 'truth' key 'x' cannot be stored"):
        writer(path, metadata={"truth": {"x": object()}})
    assert not path.exists()


def test_cloud_only_for_a_completed_scan_with_a_calibration(tmp_path: Path) -> None:
    """The reconstructed cloud is written at the end of a scan that completed, decimated to
    ``cloud_points``; a failed scan gets its ``aborted`` record and no cloud."""
    from mcap.reader import make_reader

    H = Extrinsics(0.01, 1.2, -0.003, 0.0, 0.002, -0.78)

    def scan(path: Path, fail: bool) -> dict[str, int]:
        try:
            with writer(path, calibration=H, calibration_source="initial", cloud_points=500) as w:
                w.write_encoder([EncoderSample(T0 - 1_000_000, 0)])
                for i in range(20):
                    w.write_line(make_line(i))
                    w.write_encoder([EncoderSample(T0 + (i + 1) * 1_000_000, 10 * (i + 1))])
                if fail:
                    raise RuntimeError("lidar unplugged")
        except RuntimeError:
            pass
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
        assert summary is not None and summary.statistics is not None
        return {summary.channels[c].topic: n
                for c, n in summary.statistics.channel_message_counts.items()}

    done = scan(tmp_path / "done.mcap", fail=False)
    assert done["/platter/cloud"] == 1 and done["/tf_static"] == 1 and done["/lidar/scan"] == 20
    rec = read_recording(tmp_path / "done.mcap")
    assert rec.calibration == H and rec.metadata["calibration"]["source"] == "initial"
    with open(tmp_path / "done.mcap", "rb") as f:
        (msg,) = [m for _, _, m in make_reader(f).iter_messages(topics=["/platter/cloud"])]
    from calstation.engine.reconstruct import reconstruct
    from calstation.recordings.messages import point_cloud

    # every k-th point (valid or not) of the scan, k = ceil(2000 / 500), reconstructed
    points = reconstruct(rec, H)
    every_4th = np.zeros(rec.n_points, bool)
    every_4th[::4] = True
    want = points[every_4th[rec.valid]]
    assert 0 < len(want) <= 500
    assert msg.data == point_cloud(int(rec.t_ns[-1]), "platter", want)
    failed = scan(tmp_path / "failed.mcap", fail=True)
    assert "/platter/cloud" not in failed and failed["/lidar/scan"] == 20
    assert read_recording(tmp_path / "failed.mcap").metadata["aborted"] == {
        "error": "RuntimeError: lidar unplugged"}
