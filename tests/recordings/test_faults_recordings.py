"""Fault injection, recordings and drivers: damaged files, wrong kinds, empty clouds, library
chatter on stdout, and drivers that disconnect mid-scan.

Every command is run through the real entry point; an outcome is either a result or one clear
error (exit code 2), never a traceback; a scan cut short stays on disk and in the database as a
``partial`` recording, and the run records how the motor was stopped.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from sqlalchemy import select

from calstation import hookimpl, plugins
from calstation.drivers import EncoderSample, LidarInfo, LidarLine
from calstation.engine.frames import Extrinsics
from calstation.errors import DriverError
from calstation.quiet import quiet_open3d, stdout_to_stderr
from calstation.recipes import load_recipe
from calstation.recordings.runfolder import file_sha256
from calstation.recordings.writer import RecordingWriter
from calstation.station.runs import resume_run, start_run
from calstation.storage.db import Artifact, Database, Run, Step
from tests.support.clirun import run_cli as _run

pytest.importorskip("calstation_sim")
from calstation_sim import drivers as sim_drivers, plugin as sim_plugin

from tests.support.station import ScriptedOperator, SpyTurntable, ToyStrategy, toy_recipe

REPO = Path(__file__).resolve().parents[2]
RECIPE = str(REPO / "recipes" / "sim-periodicity.yaml")
T0 = 1_767_225_600_000_000_000
INFO = LidarInfo("acme", "line-1", "SN1", 1.2566, 200, 100.0, 0.2, 10.0)
H = Extrinsics(tx=0.0, ty=1.25, tz=0.0, rx=0.0, ry=0.0, rz=-0.785)


def _recording(path: Path, kind: str = "spin", valid: float = 0.9, lines: int = 60) -> Path:
    rng = np.random.default_rng(3)
    with RecordingWriter(path, kind=kind, lidar_info=INFO, counts_per_revolution=4096,
                         encoder_direction=1) as w:
        w.write_encoder(EncoderSample(T0 + k * 1_000_000, round(2048 * k / 1000))
                        for k in range(800))
        for i in range(lines):
            w.write_line(LidarLine(
                timestamp_ns=T0 + 50_000_000 + i * 10_000_000,
                azimuth_rad=np.linspace(-0.6, 0.6, 200),
                range_m=1.1 + 0.3 * rng.random(200),
                valid=rng.random(200) < valid,
                point_period_ns=40_000.0,
            ))
    return path


@pytest.fixture
def calibration_file(tmp_path: Path) -> Path:
    path = tmp_path / "calibration.yaml"
    path.write_text("H: " + json.dumps(H.as_dict()) + "\n")
    return path


# --- damaged recordings --------------------------------------------------------------------
def _truncated(tmp: Path) -> Path:
    p = _recording(tmp / "t.mcap")
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    return p


def _garbage(tmp: Path) -> Path:
    p = tmp / "g.mcap"
    p.write_bytes(os.urandom(4096))
    return p


def _empty(tmp: Path) -> Path:
    p = tmp / "e.mcap"
    p.write_bytes(b"")
    return p


def _zeroed_middle(tmp: Path) -> Path:
    p = _recording(tmp / "z.mcap")
    data = bytearray(p.read_bytes())
    mid = len(data) // 2
    data[mid: mid + 2000] = bytes(2000)
    p.write_bytes(bytes(data))
    return p


def _header_only(tmp: Path) -> Path:
    p = _recording(tmp / "h.mcap")
    p.write_bytes(p.read_bytes()[:64])
    return p


def _folder(tmp: Path) -> Path:
    p = tmp / "folder.mcap"
    p.mkdir()
    return p


def _not_mcap(tmp: Path) -> Path:
    p = tmp / "r.mcap"
    p.write_text("name: a recipe, not a recording\n")
    return p


def _fifo(tmp: Path) -> Path:
    p = tmp / "fifo.mcap"
    os.mkfifo(p)
    return p


DAMAGED: list[tuple[str, Callable[[Path], Path]]] = [
    ("a named pipe", _fifo),
    ("truncated half", _truncated),
    ("random bytes", _garbage),
    ("empty file", _empty),
    ("zeroed middle", _zeroed_middle),
    ("header only", _header_only),
    ("a folder", _folder),
    ("a text file", _not_mcap),
]


@pytest.mark.parametrize("case", DAMAGED, ids=[c[0] for c in DAMAGED])
def test_damaged_recording_gives_a_result_or_one_clear_error(
    tmp_path: Path, calibration_file: Path, capsys: pytest.CaptureFixture[str],
    case: tuple[str, Callable[[Path], Path]],
) -> None:
    _name, make = case
    path = make(tmp_path)
    out = tmp_path / "out.ply"
    code, stdout, err = _run(["reconstruct", str(path), "-c", str(calibration_file),
                              "-o", str(out)], capsys)
    assert "Traceback" not in err + stdout
    if code == 0:  # read up to the last complete chunk: said so
        assert "wrote" in stdout and out.exists()
    else:
        assert code == 2 and err.startswith("error:") and path.name in err, err
        assert not out.exists()


def test_a_calibration_file_that_is_a_pipe_is_refused_not_waited_on(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rec = _recording(tmp_path / "spin.mcap")
    pipe = tmp_path / "calibration.yaml"
    os.mkfifo(pipe)
    code, _, err = _run(["reconstruct", str(rec), "-c", str(pipe), "-o",
                         str(tmp_path / "x.ply")], capsys)
    assert code == 2 and "named pipe (FIFO), not a regular file" in err
    code, _, err = _run(["verify", RECIPE, "--cube", str(rec), "-c", str(pipe)], capsys)
    assert code == 2 and "named pipe (FIFO), not a regular file" in err


def test_verify_refuses_a_recording_that_is_not_a_cube_scan(
    tmp_path: Path, calibration_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for kind in ("spin", "static"):
        rec = _recording(tmp_path / f"{kind}.mcap", kind=kind)
        code, out, err = _run(["verify", RECIPE, "--cube", str(rec), "-c",
                               str(calibration_file), "--json"], capsys)
        assert code == 2 and out == ""
        assert f"this is a '{kind}' recording, not a scan of the QA cube" in err


def test_calibrate_refuses_recordings_of_the_wrong_kind(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    spin = _recording(tmp_path / "spin.mcap", kind="spin")
    static = _recording(tmp_path / "static.mcap", kind="static")
    code, out, err = _run(["calibrate", RECIPE, "--static", str(spin), "--spin", str(spin),
                           "--json"], capsys)
    assert code == 2 and out == ""
    assert "this is a 'spin' recording, not the static scan of the L-target" in err
    code, out, err = _run(["calibrate", RECIPE, "--static", str(static), "--spin", str(static),
                           "--json"], capsys)
    assert code == 2 and out == "" and "this is a 'static' recording" in err


def test_reconstruct_refuses_to_write_an_empty_cloud(
    tmp_path: Path, calibration_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rec = _recording(tmp_path / "dark.mcap", valid=0.0)
    out = tmp_path / "dark.ply"
    code, _, err = _run(["reconstruct", str(rec), "-c", str(calibration_file), "-o", str(out)],
                        capsys)
    assert code == 2 and "none of its 60 lines holds a valid return" in err
    assert not out.exists()


def test_library_warnings_never_reach_stdout(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    with quiet_open3d() as o3d:
        o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Warning)
        o3d.io.read_triangle_mesh(str(tmp_path / "nosuch.ply"))  # Open3D warns on fd 1
    with stdout_to_stderr():
        os.write(1, b"C-level chatter\n")
    out, err = capfd.readouterr()
    assert out == ""
    assert "C-level chatter" in err


# --- drivers that disconnect -----------------------------------------------------------------
class FlakyLidar:
    """The sim lidar, disconnecting after ``limit`` lines (a cable pulled mid-scan)."""

    def __init__(self, inner: Any, limit: int) -> None:
        self.inner, self.limit, self.count = inner, limit, 0

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def lines(self) -> Iterator[Any]:
        for line in self.inner.lines():
            self.count += 1
            if self.count > self.limit:
                raise DriverError(f"lidar disconnected after {self.limit} lines")
            yield line


class FlakyTurntable(SpyTurntable):
    """The sim turntable whose drive faults when told to spin a second time, and whose
    ``stop`` then fails (the emergency stop must follow)."""

    def __init__(self, inner: Any, calls: list[str]) -> None:
        super().__init__(inner, calls)
        self.spins = 0

    def spin(self, rpm: float) -> None:
        self.spins += 1
        if self.spins == 3:  # preflight, spin scan, then the cube scan: the drive faults
            self.broken = True
            raise DriverError("drive fault: over-current (the drive stopped responding)")
        self.inner.spin(rpm)

    def stop(self) -> None:
        if getattr(self, "broken", False):
            self.calls.append("stop failed")
            raise DriverError("drive does not answer")
        super().stop()


class DisconnectPlugin:
    __name__ = "disconnect-plugin"

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.motor_calls: list[str] = []
        self.strategy = ToyStrategy()

    @hookimpl
    def calstation_register_drivers(self, register: Any) -> None:
        register("lidar", "spy", lambda s, c: FlakyLidar(sim_drivers.lidar_factory({}, c),
                                                         self.limit))
        register("turntable", "spy", lambda s, c: FlakyTurntable(
            sim_drivers.turntable_factory({}, c), self.motor_calls))
        register("encoder", "spy", lambda s, c: sim_drivers.encoder_factory({}, c))

    @hookimpl
    def calstation_register_cost_strategies(self, register: Any) -> None:
        register(self.strategy)


def test_lidar_disconnect_mid_scan_keeps_a_partial_recording_and_stops_the_motor(
    tmp_path: Path, db: Database, capsys: pytest.CaptureFixture[str]
) -> None:
    plugin = DisconnectPlugin(limit=10 + 40 + 300)  # preflight, static scan, then mid spin scan
    with plugins.isolated(sim_plugin, plugin):
        ui = ScriptedOperator()
        run_id, status = start_run(load_recipe(toy_recipe(tmp_path)), db, ui,
                                   operator="ann", data_dir=tmp_path)
    assert status == "failed"
    assert "lidar disconnected after 350 lines" in ui.failures[0][1]
    with db.session() as s:
        run = s.get(Run, run_id)
        assert run is not None and run.status == "failed"
        assert run.motor_stop is not None and run.motor_stop["how"] == "stop"
        spin = s.scalars(select(Artifact).where(Artifact.run_id == run_id,
                                                Artifact.kind == "spin")).one()
        step = s.get(Step, spin.step_id)
        assert step is not None and step.status == "failed"
    assert spin.status == "partial"
    assert Path(spin.path).exists() and file_sha256(Path(spin.path)) == spin.sha256
    assert any("motor stopped by stop" in m for m in ui.messages)
    # `show` tells the same
    shown = json.loads(_run(["show", str(run_id), "--json", "--db", db.url], capsys)[1])
    assert shown["motor_stop"]["how"] == "stop"
    assert {(a["kind"], a["status"]) for a in shown["artifacts"]} >= {("spin", "partial")}
    # resumed with the cable back: the scan is taken again, the partial one kept aside
    with plugins.isolated(sim_plugin, DisconnectPlugin(limit=10**9)):
        assert resume_run(run_id, db, ScriptedOperator()) in ("passed", "failed")
    with db.session() as s:
        spins = {a.status: a.path for a in s.scalars(select(Artifact).where(
            Artifact.run_id == run_id, Artifact.kind == "spin"))}
    assert set(spins) == {"partial", "complete"}
    assert spins["partial"].endswith("spin.attempt1.mcap") and Path(spins["partial"]).exists()
    assert spins["complete"].endswith("spin.mcap")


def test_drive_fault_then_failed_stop_ends_in_an_emergency_stop_that_is_recorded(
    tmp_path: Path, db: Database
) -> None:
    plugin = DisconnectPlugin(limit=10**9)
    with plugins.isolated(sim_plugin, plugin):
        ui = ScriptedOperator()
        run_id, status = start_run(load_recipe(toy_recipe(tmp_path)), db, ui,
                                   operator="ann", data_dir=tmp_path)
    assert status == "failed"
    assert "over-current" in ui.failures[0][1] and ui.failures[0][0] == "cube_scan"
    assert plugin.motor_calls[-2:] == ["stop failed", "emergency_stop"]
    with db.session() as s:
        run = s.get(Run, run_id)
        assert run is not None and run.motor_stop is not None
        assert run.motor_stop["how"] == "emergency_stop" and run.motor_stop["ok"]
        assert "stop failed: DriverError: drive does not answer" in run.motor_stop["errors"]
    assert any("motor stopped by emergency_stop" in m for m in ui.messages)
