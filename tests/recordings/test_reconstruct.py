"""Reconstruction to frame D, PLY output, calibration files and the reconstruct command."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from calstation.cli import reconstruct as reconstruct_cli
from calstation.drivers import EncoderSample, LidarInfo, LidarLine
from calstation.engine.frames import (
    Extrinsics,
    dynamic_to_lidar,
    lidar_to_dynamic,
    lidar_to_polar,
    polar_to_lidar,
)
from calstation.engine.reconstruct import reconstruct
from calstation.errors import RecordingError
from calstation.recordings.files import load_extrinsics, read_ply, write_ply
from calstation.recordings.reader import read_recording
from calstation.recordings.writer import RecordingWriter

T0 = 1_767_225_600_000_000_000
CPR = 4096
H = Extrinsics(tx=0.012, ty=1.25, tz=-0.004, rx=0.0, ry=0.003, rz=-0.785)
INFO = LidarInfo("acme", "line-1", "SN1", 1.2566, 200, 100.0, 0.2, 10.0)
RATE = 0.5  # platter turns per second


def _spin_recording(path: Path, n_lines: int = 50, n: int = 200) -> None:
    """Lines of 200 points spread over 8 ms each (the platter turns 1.44° during one line),
    encoder at 1 kHz turning at RATE rev/s, direction −1."""
    rng = np.random.default_rng(3)
    with RecordingWriter(
        path, kind="spin", lidar_info=INFO, counts_per_revolution=CPR, encoder_direction=-1
    ) as w:
        w.write_encoder(
            EncoderSample(T0 + k * 1_000_000, -round(RATE * CPR * k / 1000)) for k in range(700)
        )
        for i in range(n_lines):
            w.write_line(
                LidarLine(
                    timestamp_ns=T0 + 50_000_000 + i * 10_000_000,
                    azimuth_rad=np.linspace(-0.6, 0.6, n),
                    range_m=1.1 + 0.3 * rng.random(n),
                    valid=rng.random(n) > 0.1,
                    point_period_ns=40_000.0,
                )
            )


def test_reconstruct_matches_frames_with_per_point_angle(tmp_path: Path) -> None:
    path = tmp_path / "spin.mcap"
    _spin_recording(path)
    rec = read_recording(path)
    points = reconstruct(rec, H)
    v = rec.valid
    assert points.shape == (int(v.sum()), 3)
    # every point with its own φ (direction −1: counts fall while φ grows), exact encoder rate
    t_s = (rec.t_ns[v] - T0) * 1e-9
    phi = 2 * np.pi * RATE * t_s
    p_L = polar_to_lidar(rec.range_m[v], rec.azimuth_rad[v])
    expected = lidar_to_dynamic(p_L, phi, H)
    # the encoder counts are rounded: φ is off by ≤ half a count, points ≤ 1.5 m from the axis
    np.testing.assert_allclose(points, expected, rtol=0, atol=1.5 * 0.5 * 2 * np.pi / CPR)
    # going back with dynamic_to_lidar at the same φ gives the measured points in the scan plane
    np.testing.assert_allclose(dynamic_to_lidar(points, rec.points_lidar()[1], H), p_L, atol=1e-9)
    # one φ per line would be wrong by up to the platter's turn during a line (~1.44°, ~30 mm)
    line_phi = 2 * np.pi * RATE * (rec.line_timestamp_ns[rec.line_index[v]] - T0) * 1e-9
    per_line = lidar_to_dynamic(p_L, line_phi, H)
    assert np.abs(per_line - points).max() > 0.01


def test_a_calibrations_encoder_latency_replaces_the_recordings(tmp_path: Path) -> None:
    """The recording says 0; a calibration's 5 ms (encoder time minus lidar time) puts every
    reading 5 ms earlier on the lidar's clock, so each point sees the platter 5 ms further on:
    φ + 2π·RATE·5 ms (15.7 mrad, 19 mm at 1.2 m)."""
    path = tmp_path / "spin.mcap"
    _spin_recording(path)
    rec = read_recording(path)
    assert rec.encoder_latency_s == 0.0
    v = rec.valid
    p_L = polar_to_lidar(rec.range_m[v], rec.azimuth_rad[v])
    phi = 2 * np.pi * RATE * ((rec.t_ns[v] - T0) * 1e-9 + 0.005)
    expected = lidar_to_dynamic(p_L, phi, H)
    got = reconstruct(rec, H, encoder_latency_s=0.005)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1.5 * 0.5 * 2 * np.pi / CPR)
    assert np.abs(got - reconstruct(rec, H)).max() > 0.01


def test_known_point_reconstructs_back(tmp_path: Path) -> None:
    """A point of D seen at a known φ, put in a recording, comes back where it was in D."""
    t = T0 + 196_400_000  # the encoder turns one revolution in the second from T0
    phi = 2 * np.pi * 0.1964
    # pick a point in D that lies in the scan plane at φ: start in L, go to D with frames
    p_L0 = polar_to_lidar([1.3], [0.2])
    p_D = lidar_to_dynamic(p_L0, phi, H)
    p_L = dynamic_to_lidar(p_D, phi, H)
    assert abs(p_L[0, 2]) < 1e-12
    rho, alpha = lidar_to_polar(p_L)
    path = tmp_path / "one.mcap"
    with RecordingWriter(
        path, kind="static", lidar_info=INFO, counts_per_revolution=CPR, encoder_direction=1
    ) as w:
        w.write_encoder([EncoderSample(T0, 0), EncoderSample(T0 + 1_000_000_000, CPR)])
        w.write_line(LidarLine(t, alpha, rho, np.array([True])))
    rec = read_recording(path)
    assert rec.platter_angle(t) == pytest.approx(phi, abs=1e-9)
    got = reconstruct(rec, H)
    np.testing.assert_allclose(got, p_D, atol=1e-6)  # range stored as float32


def test_ply_is_readable_by_open3d(tmp_path: Path) -> None:
    o3d = pytest.importorskip("open3d")
    pts = np.random.default_rng(0).normal(size=(12345, 3)) * 0.2
    path = tmp_path / "cloud.ply"
    write_ply(path, pts)
    cloud = o3d.io.read_point_cloud(str(path))
    assert len(cloud.points) == 12345
    np.testing.assert_allclose(np.asarray(cloud.points), pts, atol=1e-7)
    np.testing.assert_allclose(read_ply(path), pts, atol=1e-7)
    assert not path.with_name("cloud.ply.part").exists()


def test_ply_rejects_bad_points(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match=r"shape \(N, 3\)"):
        write_ply(tmp_path / "a.ply", np.zeros((4, 2)))
    with pytest.raises(RecordingError, match="1 of 2 points are not finite"):
        write_ply(tmp_path / "b.ply", [[0, 0, 0], [np.nan, 0, 0]])
    assert not (tmp_path / "b.ply").exists()


def test_load_extrinsics(tmp_path: Path) -> None:
    h = H.as_dict()
    yml = tmp_path / "cal.yaml"
    yml.write_text("strategy: periodicity\nH:\n" + "".join(f"  {k}: {v!r}\n" for k, v in h.items()))
    assert load_extrinsics(yml) == H
    js = tmp_path / "cal.json"
    js.write_text(json.dumps({"H": h, "cost": 1.0}))
    assert load_extrinsics(js) == H
    truth = tmp_path / "truth.json"
    truth.write_text(json.dumps({**h, "fixtures": {}, "seed": 1}))
    assert load_extrinsics(truth, source="truth") == H

    with pytest.raises(RecordingError, match=r"calibration file .*truth\.json has no 'H'"):
        load_extrinsics(truth)
    no_tz = tmp_path / "no_tz.json"
    no_tz.write_text(json.dumps({"H": {k: v for k, v in h.items() if k != "tz"}}))
    with pytest.raises(RecordingError, match=r"no_tz\.json is missing field H\.tz"):
        load_extrinsics(no_tz)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({**h, "ry": "small"}))
    with pytest.raises(RecordingError, match=r"field ry must be a finite number, got 'small'"):
        load_extrinsics(bad, source="truth")
    broken = tmp_path / "broken.json"
    broken.write_text("{ not json")
    with pytest.raises(RecordingError, match=r"broken\.json is not valid JSON"):
        load_extrinsics(broken, source="truth")
    with pytest.raises(RecordingError, match="does not exist"):
        load_extrinsics(tmp_path / "nope.yaml")


def test_load_calibration_file_gives_the_encoder_latency_with_h(tmp_path: Path) -> None:
    from calstation.recordings.files import load_calibration_file

    h = H.as_dict()
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps({"H": h}))
    assert load_calibration_file(cal) == (H, None)  # no estimate: the recording's latency
    cal.write_text(json.dumps({"H": h, "encoder_latency_s": 0.0052}))
    assert load_calibration_file(cal) == (H, 0.0052)
    truth = tmp_path / "truth.json"
    truth.write_text(json.dumps({**h, "encoder": {"latency_s": 0.005}}))
    assert load_calibration_file(truth, source="truth") == (H, 0.005)
    cal.write_text(json.dumps({"H": h, "encoder_latency_s": "late"}))
    with pytest.raises(RecordingError, match=r"cal\.json: field encoder_latency_s must be a "
                                             r"finite number of seconds, got 'late'"):
        load_calibration_file(cal)


def _app() -> typer.Typer:
    app = typer.Typer()

    @app.callback()
    def _root() -> None:
        """Test root."""

    reconstruct_cli.register(app)
    return app


def test_cli_reconstruct(tmp_path: Path) -> None:
    o3d = pytest.importorskip("open3d")
    rec_path = tmp_path / "spin.mcap"
    _spin_recording(rec_path)
    truth = tmp_path / "truth.json"
    truth.write_text(json.dumps(H.as_dict()))
    out = tmp_path / "out" / "spin.ply"
    out.parent.mkdir()  # an output's folder is the user's to make (a typo makes none)
    result = CliRunner().invoke(
        _app(), ["reconstruct", str(rec_path), "--truth", str(truth), "--out", str(out)]
    )
    assert result.exit_code == 0, result.output
    expected = reconstruct(read_recording(rec_path), H)
    assert f"wrote {len(expected):,} points" in result.output and str(out) in result.output
    cloud = np.asarray(o3d.io.read_point_cloud(str(out)).points)
    np.testing.assert_allclose(cloud, expected, atol=1e-6)

    cal = tmp_path / "cal.yaml"
    cal.write_text("H: " + json.dumps(H.as_dict()))
    out2 = tmp_path / "cal.ply"
    result = CliRunner().invoke(
        _app(), ["reconstruct", str(rec_path), "--calibration", str(cal), "--out", str(out2)]
    )
    assert result.exit_code == 0, result.output
    np.testing.assert_allclose(read_ply(out2), read_ply(out))

    both = CliRunner().invoke(
        _app(),
        ["reconstruct", str(rec_path), "--calibration", str(cal), "--truth", str(truth),
         "--out", str(out2)],
    )
    assert both.exit_code == 2 and "exactly one of" in both.output


def test_cli_errors_are_clean(tmp_path: Path) -> None:
    """Through the real entry point: one clear message, exit code 2, no traceback."""
    truth = tmp_path / "truth.json"
    truth.write_text(json.dumps(H.as_dict()))
    missing = tmp_path / "missing.mcap"
    code = "import sys; from calstation.cli import main; main(sys.argv[1:])"
    proc = subprocess.run(
        [sys.executable, "-c", code, "reconstruct", str(missing), "--truth", str(truth),
         "--out", str(tmp_path / "x.ply")],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 2
    assert "missing.mcap does not exist" in proc.stderr
    assert "Traceback" not in proc.stderr
