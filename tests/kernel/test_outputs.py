"""Outputs are written whole or not at all, and never replace what the user did not name: the one
atomic writer (calstation/atomic.py) and the commands that write through it (export, import,
reconstruct, the run folder's report), tried on a full disk, devices, FIFOs and folders."""

from __future__ import annotations

import errno
import io
import json
import os
import stat
from pathlib import Path
from typing import Any

import pytest

from tests.support.clirun import run_cli

DATA = Path(__file__).resolve().parents[1] / "data" / "v1"


def _device(folder: Path) -> Path:
    """A character device of our own (a copy of /dev/null's node, made as root; skipped
    otherwise): a test of a refusal must never risk the machine's /dev/null."""
    if os.geteuid() != 0:
        pytest.skip("making a device node needs root")
    node = folder / "null"
    os.mknod(node, stat.S_IFCHR | 0o666, os.makedev(1, 3))
    return node


def _special(kind: str, folder: Path) -> Path:
    """A folder, a FIFO or a character device in ``folder``, named as an output."""
    if kind == "device":
        return _device(folder)
    target = folder / ("out" if kind == "folder" else "pipe")
    target.mkdir() if kind == "folder" else os.mkfifo(target)
    return target


def _full_disk(monkeypatch: pytest.MonkeyPatch, folder: Path, after: int = 4096) -> None:
    """Writes to files in ``folder`` fail with ENOSPC once ``after`` bytes went to one file, as
    on a full disk (the error the file system gives, raised where it raises it: the write)."""
    real_fdopen = os.fdopen

    class Filling(io.FileIO):
        written = 0

        def write(self, data: Any) -> int:
            self.written += len(data)
            if self.written > after:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return super().write(data)

    def fdopen(fd: int, *args: Any, **kwargs: Any) -> Any:
        if Path(os.readlink(f"/proc/self/fd/{fd}")).parent == folder:
            return Filling(fd, "wb")
        return real_fdopen(fd, *args, **kwargs)

    monkeypatch.setattr(os, "fdopen", fdopen)


def test_a_full_disk_leaves_the_previous_file_intact(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from calstation.atomic import write_atomic
    from calstation.errors import OutputError
    target = tmp_path / "calibration.json"
    target.write_text('{"H": "the previous calibration"}')
    _full_disk(monkeypatch, tmp_path)
    with pytest.raises(OutputError, match=r"No space left on device.*calibration.json is as it "
                                          "was"):
        write_atomic(target, "x" * 100_000, "export")
    assert target.read_text() == '{"H": "the previous calibration"}'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration.json"]


@pytest.mark.parametrize("kind", ["folder", "fifo", "device"])
def test_a_folder_fifo_or_device_named_as_the_output_is_refused(tmp_path: Path,
                                                                 kind: str) -> None:
    from calstation.atomic import atomic_output, stage, write_atomic
    from calstation.errors import OutputError
    target = _special(kind, tmp_path)
    before = os.stat(target)
    for write in (lambda: write_atomic(target, b"data"),
                  lambda: atomic_output(target).__enter__(),
                  lambda: stage(target, b"data")):
        with pytest.raises(OutputError, match="never replaces a"):
            write()
    after = os.stat(target)
    assert (after.st_mode, after.st_ino) == (before.st_mode, before.st_ino)
    assert sorted(p.name for p in tmp_path.iterdir()) == [target.name]


def test_a_missing_folder_is_a_sentence_unless_the_caller_makes_it(tmp_path: Path) -> None:
    from calstation.atomic import check_output, write_atomic
    from calstation.errors import OutputError
    with pytest.raises(OutputError, match=r"the folder .*nowhere does not exist"):
        check_output(tmp_path / "nowhere" / "x.json", "export")
    assert not (tmp_path / "nowhere").exists()
    write_atomic(tmp_path / "made" / "x.json", "{}", make_parents=True)
    assert (tmp_path / "made" / "x.json").read_text() == "{}"


def test_a_failure_inside_the_block_leaves_nothing_and_keeps_the_target(tmp_path: Path) -> None:
    from calstation.atomic import atomic_output
    target = tmp_path / "cloud.ply"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic_output(target) as tmp:
        tmp.write_bytes(b"half of the new")
        raise RuntimeError("the writer died")
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cloud.ply"]


def test_the_new_file_is_flushed_before_it_replaces_the_target(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from calstation import atomic
    from calstation.atomic import atomic_output, write_atomic
    """fsync of the file before the rename, and of its folder after: otherwise a power cut
    can leave the renamed file empty."""
    order: list[str] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd: int) -> None:
        order.append("fsync-folder" if stat.S_ISDIR(os.fstat(fd).st_mode) else "fsync-file")
        real_fsync(fd)

    def replace(a: str | Path, b: str | Path) -> None:
        order.append("rename")
        real_replace(a, b)

    monkeypatch.setattr(atomic.os, "fsync", fsync)
    monkeypatch.setattr(atomic.os, "replace", replace)
    write_atomic(tmp_path / "a.txt", "text")
    assert order == ["fsync-file", "rename", "fsync-folder"]
    order.clear()
    with atomic_output(tmp_path / "b.txt") as tmp:
        tmp.write_text("text")
    assert order == ["fsync-file", "rename", "fsync-folder"]


def test_a_staged_file_waits_for_its_commit_and_keeps_the_mode(tmp_path: Path) -> None:
    from calstation.atomic import commit, stage
    from calstation.errors import OutputError
    target = tmp_path / "report.json"
    target.write_text("old")
    target.chmod(0o640)
    tmp = stage(target, "new")
    assert target.read_text() == "old" and tmp.parent == tmp_path
    commit(tmp, target)
    assert target.read_text() == "new" and stat.S_IMODE(target.stat().st_mode) == 0o640
    # the target became a folder meanwhile: refused, the staged file removed
    other = stage(tmp_path / "later.json", "x")
    (tmp_path / "later.json").mkdir()
    with pytest.raises(OutputError, match="is a folder"):
        commit(other, tmp_path / "later.json")
    assert not other.exists()


def test_a_link_named_as_the_output_is_written_through(tmp_path: Path) -> None:
    from calstation.atomic import write_atomic
    real = tmp_path / "real.yaml"
    real.write_text("old")
    link = tmp_path / "link.yaml"
    link.symlink_to(real)
    write_atomic(link, "new")
    assert link.is_symlink() and real.read_text() == "new"


# --- the commands ------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["fifo", "device", "folder"])
def test_import_out_onto_a_device_fifo_or_folder_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], kind: str
) -> None:
    log = tmp_path / "log.csv"
    log.write_text("t,a,r0,r1\n" + "".join(f"{i / 10},{i / 10},1.5,1.6\n" for i in range(20)))
    out = _special(kind, tmp_path)
    before = os.stat(out)
    code, _, err = run_cli(["import", "csv", str(log), "--time", "t", "--angle", "a",
                            "--ranges", "r*", "--azimuths", "0:1", "-o", str(out)], capsys)
    assert code == 2 and "never replaces a" in err and "Traceback" not in err, err
    after = os.stat(out)
    assert (after.st_mode, after.st_ino) == (before.st_mode, before.st_ino)


@pytest.mark.parametrize("kind", ["fifo", "device"])
def test_reconstruct_onto_a_device_or_fifo_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], kind: str
) -> None:
    calib = tmp_path / "c.json"
    calib.write_text(json.dumps({"H": {"tx": 0.0, "ty": 1.2, "tz": 0.0, "rx": 0.0, "ry": 0.0,
                                       "rz": -0.785}}))
    out = _special(kind, tmp_path)
    before = os.stat(out)
    code, _, err = run_cli(["reconstruct", str(DATA / "spin.mcap"), "-c", str(calib), "-o",
                            str(out)], capsys)
    assert code == 2 and "never replaces a" in err and "Traceback" not in err, err
    after = os.stat(out)
    assert (after.st_mode, after.st_ino) == (before.st_mode, before.st_ino)


def _exported_run(tmp_path: Path) -> str:
    """A database holding one passed run with a final calibration; its URL."""
    import datetime as dt

    from calstation.storage.db import open_database
    from tests.support.qa import H1, add_run

    url = f"sqlite:///{tmp_path / 'qa.db'}"
    db = open_database(url)
    add_run(db, "st-1", "passed", H1, dt.datetime(2026, 3, 1, tzinfo=dt.UTC))
    db.dispose()
    return url


def test_export_into_a_missing_folder_or_onto_a_folder_is_a_sentence(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    url = _exported_run(tmp_path)
    for out, said in ((tmp_path / "missing" / "c.yaml", "does not exist"),
                      (tmp_path, "is a folder")):
        code, _, err = run_cli(["export", "1", "--db", url, "-o", str(out)], capsys)
        assert code == 2 and said in err and "Traceback" not in err, err
    assert not (tmp_path / "missing").exists()


def test_export_on_a_full_disk_keeps_the_previous_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    url = _exported_run(tmp_path)
    out = tmp_path / "exports" / "calibration.json"
    out.parent.mkdir()
    out.write_text('{"H": "the previous export"}\n')
    _full_disk(monkeypatch, out.parent, after=100)
    code, _, err = run_cli(["export", "1", "--db", url, "-f", "json", "-o", str(out)], capsys)
    assert code == 2 and "No space left on device" in err and "is as it was" in err, err
    assert out.read_text() == '{"H": "the previous export"}\n'
    assert [p.name for p in out.parent.iterdir()] == ["calibration.json"]


@pytest.mark.parametrize("kind", ["full disk", "fifo"])
def test_a_calibration_result_saved_is_written_whole_or_not_at_all(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, kind: str
) -> None:
    """CalibrationResult.save (the library's writer of calibration files) goes through the one
    atomic writer: a full disk keeps the previous file, a FIFO is refused without blocking."""
    from calstation.engine.frames import Extrinsics
    from calstation.engine.result import CalibrationResult
    from calstation.errors import OutputError

    result = CalibrationResult(Extrinsics(0.1, 0.0, 0.2, 0.0, 0.01, 0.0), {}, 0.0, 1, "manual",
                               diagnostics={"residuals": list(range(2000))})
    if kind == "fifo":
        target = _special("fifo", tmp_path)
        with pytest.raises(OutputError, match="never replaces a named pipe"):
            result.save(target)
        assert stat.S_ISFIFO(os.stat(target).st_mode)
        return
    target = tmp_path / "calibration.json"
    target.write_text('{"H": "the previous calibration"}')
    _full_disk(monkeypatch, tmp_path)
    with pytest.raises(OutputError, match=r"No space left on device.*is as it was"):
        result.save(target)
    assert target.read_text() == '{"H": "the previous calibration"}'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration.json"]


def test_a_bench_resumed_on_a_full_disk_keeps_every_finished_record(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """--resume rewrites records.jsonl without the line a kill cut short: whole or not at all,
    so a failure meanwhile keeps every record finished before."""
    from calstation.bench.execute import RecordStore
    from calstation.errors import OutputError

    path = tmp_path / "records.jsonl"
    finished = "".join(json.dumps({"id": f"t{k}", "data": "x" * 200}) + "\n" for k in range(40))
    path.write_text(finished + '{"id": "cut sho')
    _full_disk(monkeypatch, tmp_path)
    with pytest.raises(OutputError, match="No space left on device"):
        RecordStore(path, resume=True)
    assert path.read_text() == finished + '{"id": "cut sho'
    monkeypatch.undo()
    assert list(RecordStore(path, resume=True).records) == [f"t{k}" for k in range(40)]
    assert path.read_text() == finished


def test_simulate_onto_a_fifo_among_its_outputs_is_refused(tmp_path: Path) -> None:
    """`calstation simulate --out DIR` writes each recording whole or not at all: a FIFO where a
    recording goes is refused in a sentence and stays a FIFO (opening it for writing blocked)."""
    import subprocess
    import sys

    from calstation.testing import lean_recipe

    out = tmp_path / "sim"
    out.mkdir()
    os.mkfifo(out / "static.mcap")
    proc = subprocess.run([sys.executable, "-m", "calstation", "simulate",
                           str(lean_recipe(tmp_path)), "--out", str(out)],
                          capture_output=True, text=True, timeout=300)  # a hang guard
    assert proc.returncode == 2, proc.stderr
    assert "static.mcap is a named pipe (FIFO)" in proc.stderr and "Traceback" not in proc.stderr
    assert stat.S_ISFIFO(os.stat(out / "static.mcap").st_mode)
    assert sorted(p.name for p in out.iterdir()) == ["static.mcap"]
