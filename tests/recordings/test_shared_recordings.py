"""Recordings on shared storage: verified, resumable uploads that never lose the local copy,
read back through fsspec URLs, against a real S3 server (moto's, speaking the S3 HTTP protocol
on 127.0.0.1) and fsspec's local and memory file systems."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy import select

from calstation.errors import RecordingError
from calstation.recipes import load_recipe
from calstation.recordings.runfolder import file_sha256
from calstation.recordings.shared import (
    SharedStorageError,
    StoredFile,
    filesystem,
    local_copy,
    upload,
)
from calstation.station.runs import start_run
from calstation.storage.db import Artifact, Database, open_database
from calstation.testing.fleet import FleetRecordings, SeededRun, seed_runs
from tests.support.clirun import run_cli
from tests.support.station import ScriptedOperator, StationTestPlugin, toy_recipe

MB = 1 << 20


def _bytes(tmp_path: Path, size: int = 3 * MB) -> tuple[Path, str]:
    data = os.urandom(size)
    path = tmp_path / "scan.mcap"
    path.write_bytes(data)
    return path, hashlib.sha256(data).hexdigest()


@pytest.mark.parametrize("store", ["file", "memory"])
def test_an_interrupted_upload_is_continued_and_checked(tmp_path: Path, store: str) -> None:
    src, digest = _bytes(tmp_path)
    base = f"file://{tmp_path}/store" if store == "file" else f"memory://{tmp_path.name}"
    url = f"{base}/line-1/runs/7/scan.mcap"
    fs, path = filesystem(url)
    fs.makedirs(path.rsplit("/", 1)[0], exist_ok=True)
    with fs.open(path + ".partial", "wb") as f:  # an earlier copy cut after 1 MB
        f.write(src.read_bytes()[:MB])
    done = upload(src, url, digest)
    assert (done.resumed_from, done.sent) == (MB, 2 * MB)
    assert fs.cat(path) == src.read_bytes() and not fs.exists(path + ".partial")
    assert upload(src, url, digest).sent == 0  # there already, checked: nothing sent
    # a partial copy of other bytes is not continued
    with fs.open(path + ".partial", "wb") as f:
        f.write(b"x" * MB)
    fs.rm(path)
    again = upload(src, url, digest)
    assert (again.resumed_from, again.sent) == (0, 3 * MB) and fs.cat(path) == src.read_bytes()


def test_a_failed_upload_keeps_the_local_copy(tmp_path: Path) -> None:
    src, digest = _bytes(tmp_path, MB)
    (tmp_path / "blocker").write_text("a file where the store's folder should be")
    with pytest.raises(SharedStorageError, match="could not copy"):
        upload(src, f"file://{tmp_path}/blocker/runs/1/scan.mcap", digest)
    with pytest.raises(SharedStorageError, match="reads back with sha256"):
        upload(src, f"file://{tmp_path}/store/scan.mcap", "0" * 64)  # not the bytes stored
    assert file_sha256(src) == digest
    assert not list((tmp_path / "store").glob("*"))  # nothing half-written left


def test_a_recording_is_read_from_its_shared_copy_when_the_run_folder_lost_it(
    tmp_path: Path
) -> None:
    src, digest = _bytes(tmp_path, MB)
    url = f"memory://{tmp_path.name}/shared/scan.mcap"
    upload(src, url, digest)
    stored = StoredFile(str(src), digest, MB, url)
    assert local_copy(stored, tmp_path / "cache") == src  # the run folder's file, unchanged
    src.write_bytes(b"changed" + src.read_bytes()[7:])
    fetched = local_copy(stored, tmp_path / "cache")
    assert fetched.parent.parent == tmp_path / "cache" / "recordings"
    assert file_sha256(fetched) == digest
    src.unlink()
    assert local_copy(stored, tmp_path / "cache") == fetched  # fetched once
    fs, path = filesystem(url)
    fs.pipe(path, b"other bytes")
    with pytest.raises(SharedStorageError, match=r"is missing.*holds other bytes"):
        local_copy(stored, tmp_path / "cache")


# --- a real S3 server --------------------------------------------------------------------------
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def s3_server() -> Iterator[str]:
    """moto's S3 server on 127.0.0.1 (``moto[server]``); skipped when it is not installed."""
    pytest.importorskip("s3fs")
    pytest.importorskip("moto.server")
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p",
                             str(port)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", port)) == 0:
                    break
            time.sleep(0.1)
        else:
            pytest.fail("moto's S3 server did not start within 30 s")
        yield f"http://127.0.0.1:{port}"
    finally:
        proc.terminate()
        proc.wait(timeout=30)


@pytest.fixture
def s3_env(s3_server: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> str:
    """Credentials and the endpoint in the environment (as every AWS tool reads them; the Dask
    workers inherit them), a bucket, and a cache of our own; the bucket's URL."""
    for key, value in {"AWS_ACCESS_KEY_ID": "calstation", "AWS_SECRET_ACCESS_KEY": "secret",
                       "AWS_DEFAULT_REGION": "us-east-1", "AWS_ENDPOINT_URL": s3_server,
                       "CALSTATION_CACHE": str(tmp_path / "cache")}.items():
        monkeypatch.setenv(key, value)
    bucket = f"fleet-{tmp_path.name.lower().replace('_', '-')[-40:]}"
    fs, _ = filesystem(f"s3://{bucket}")
    fs.mkdir(bucket)
    fs.invalidate_cache()
    return f"s3://{bucket}"


def _runs_in_own_folders(db: Database, fleet: FleetRecordings, tmp_path: Path) -> list[int]:
    """Two runs on copies of the simulated recordings (so that they can be deleted)."""
    copies = []
    for k, files in enumerate(fleet.recordings):
        folder = tmp_path / f"run-folder-{k}"
        folder.mkdir()
        copies.append({kind: Path(shutil.copy(files[kind], folder)) for kind in
                       ("static", "spin", "cube")})
    return seed_runs(db, fleet.recipe, copies, fleet.today,
                     [SeededRun("line-1", "SN-1", 0), SeededRun("line-2", "SN-2", 1)])


def test_runs_on_s3_are_reprocessed_by_dask_workers_from_their_shared_copies(
    fleet_sim: FleetRecordings, s3_env: str, tmp_path: Path,
    capsys: pytest.CaptureFixture[str]
) -> None:
    url = f"sqlite:///{tmp_path / 'fleet.db'}"
    db = open_database(url)
    ids = _runs_in_own_folders(db, fleet_sim, tmp_path)
    store = f"{s3_env}/stations"
    # no such bucket: nothing sent, nothing lost
    code, out, _ = run_cli(["upload", "--pending", "--to", "s3://no-such-bucket-here", "--db",
                            url], capsys)
    assert code == 1 and "3 not sent" in out
    code, out, err = run_cli(["upload", "--pending", "--to", store, "--db", url], capsys)
    assert code == 0, err
    with db.session() as s:
        arts = s.scalars(select(Artifact).order_by(Artifact.id)).all()
        assert [a.location for a in arts] == [
            f"{store}/line-{k + 1}/runs/{db.identity}/{run}/{kind}.mcap"
            for k, run in enumerate(ids) for kind in ("static", "spin", "cube")]
        local = [Path(a.path) for a in arts]
    for path in local:  # the run folders are gone: only the shared copies are left
        path.unlink()
    code, out, err = run_cli(["reprocess", "--db", url, "--workers", "1", "--json"], capsys)
    assert code == 0, err
    data = json.loads(out)
    assert [r["outcome"] for r in data["runs"]] == ["reprocessed", "reprocessed"], data["runs"]
    assert data["runs"][0]["difference"]["tx"] == 0.0
    # another object now under that name: the run is reported and skipped, never used
    fs, path = filesystem(f"{store}/line-1/runs/{db.identity}/{ids[0]}/spin.mcap")
    fs.pipe(path, b"not the recording")
    code, _, err = run_cli(["calibrate", "--run", str(ids[0]), "--db", url], capsys)
    assert code == 2 and "holds other bytes than stored" in " ".join(err.split())
    code, out, err = run_cli(["reprocess", "--db", url, "--workers", "1", "--new", "--json"],
                             capsys)
    runs = json.loads(out)["runs"]
    assert [r["outcome"] for r in runs] == ["skipped", "reprocessed"]
    assert "holds other bytes" in runs[0]["error"]
    db.dispose()


def test_a_station_uploads_its_run_after_it_ends(
    tmp_path: Path, station_plugin: StationTestPlugin, monkeypatch: pytest.MonkeyPatch
) -> None:
    store = tmp_path / "shared"
    monkeypatch.setenv("CALSTATION_RECORDINGS_URL", f"file://{store}")
    db = open_database(f"sqlite:///{tmp_path / 'st.db'}")
    ui = ScriptedOperator()
    run_id, status = start_run(load_recipe(toy_recipe(tmp_path)), db, ui, operator="ann",
                               data_dir=tmp_path)
    assert status == "passed"
    with db.session() as s:
        arts = s.scalars(select(Artifact).where(Artifact.run_id == run_id)).all()
        assert {a.kind for a in arts} >= {"static", "spin", "cube", "report"}
        for a in arts:
            assert a.location == (f"file://{store}/sim-test/runs/{db.identity}/{run_id}/"
                                  f"{Path(a.path).name}")
            assert file_sha256(Path(a.location.removeprefix("file://"))) == a.sha256
            assert Path(a.path).is_file()  # the local copy stays
    # unreachable store: a warning, the run keeps its files, `calstation upload` sends later
    monkeypatch.setenv("CALSTATION_RECORDINGS_URL", f"file://{tmp_path}/st.db/not-a-folder")
    run2, status = start_run(load_recipe(toy_recipe(tmp_path)), db, ui, operator="ann",
                             data_dir=tmp_path)
    assert status == "passed"
    assert any("were not all copied" in w and f"calstation upload {run2}" in w
               for w in ui.messages)
    with db.session() as s:
        assert all(a.location is None for a in
                   s.scalars(select(Artifact).where(Artifact.run_id == run2)))
    db.dispose()


def test_a_recording_lost_everywhere_names_both_places(tmp_path: Path) -> None:
    from calstation.station.stored import checked_recording

    stored = StoredFile(str(tmp_path / "spin.mcap"), "a" * 64, 1, f"file://{tmp_path}/s.mcap")
    with pytest.raises(RecordingError, match=r"spin recording of run 4: .*spin\.mcap is missing; "
                                             r"file://.*s\.mcap is missing"):
        checked_recording(stored, 4, "spin", RecordingError)
