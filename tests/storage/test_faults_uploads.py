"""Uploads to stores that do not keep what they are given, or never answer: refused, or ended
with a sentence naming the endpoint; a location is stored only once a new connection has read
the copy back, so the verified location of an earlier upload is never replaced by a lost one."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from calstation.recipes import load_recipe
from calstation.recordings.runfolder import file_sha256
from calstation.station.runs import create_run
from calstation.storage.db import Artifact, Database, Run, open_database
from tests.support.clirun import run_cli
from tests.support.station import StationTestPlugin, toy_recipe


def _run_with_a_file(tmp_path: Path) -> tuple[str, int]:
    """A database holding one run with one recording in its folder: (URL, run id)."""
    url = f"sqlite:///{tmp_path / 'st.db'}"
    db = open_database(url)
    run = create_run(load_recipe(toy_recipe(tmp_path)), db, operator="ann", unattended=True,
                     data_dir=tmp_path / "data")
    with db.session() as s:
        row = s.get(Run, run)
        assert row is not None
        path = Path(row.data_dir) / "static.mcap"
        path.write_bytes(os.urandom(50_000))
        s.add(Artifact(run_id=run, kind="static", path=str(path),
                       size_bytes=path.stat().st_size, sha256=file_sha256(path)))
    db.dispose()
    return url, run


def _locations(url: str) -> list[str | None]:
    db = Database(url)
    with db.session("reading", read_only=True) as s:
        found = [a.location for a in s.query(Artifact).order_by(Artifact.id)]
    db.dispose()
    return found


def test_stores_that_do_not_keep_their_copies_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], station_plugin: StationTestPlugin,
    monkeypatch: pytest.MonkeyPatch
) -> None:
    url, run = _run_with_a_file(tmp_path)
    shared = f"file://{tmp_path / 'shared'}"
    code, _, err = run_cli(["upload", str(run), "--to", shared, "--db", url], capsys)
    assert code == 0, err
    verified = _locations(url)
    assert verified[0] is not None and verified[0].startswith(shared)
    with db_session_file_moved(url, tmp_path):  # the next upload must send it again
        monkeypatch.chdir(tmp_path)
        for store, said in (("memory://x", "vanish when calstation ends"),
                            ("s3:/", "looks like a URL without its '//'"),
                            ("s3:bucket", "looks like a URL without its '//'"),
                            ("relative/store", "must be an absolute path"),
                            ("http://host/x", "is not a store calstation keeps copies on")):
            code, _, err = run_cli(["upload", str(run), "--to", store, "--db", url], capsys)
            assert code == 2 and said in err and "Traceback" not in err, (store, err)
    assert _locations(url) == verified  # the verified shared copy is still the one recorded
    assert not (tmp_path / "s3:").exists() and not (tmp_path / "relative").exists()


class db_session_file_moved:
    """The run's recorded location is cleared for the block, as for a run not uploaded yet,
    and put back after."""

    def __init__(self, url: str, tmp_path: Path) -> None:
        self.url = url

    def __enter__(self) -> None:
        db = Database(self.url)
        with db.session() as s:
            art = s.query(Artifact).one()
            self.location, art.location = art.location, None
        db.dispose()

    def __exit__(self, *exc: object) -> None:
        db = Database(self.url)
        with db.session() as s:
            art = s.query(Artifact).one()
            assert art.location is None, "a refused upload stored a location"
            art.location = self.location
        db.dispose()


@pytest.fixture
def black_hole() -> Iterator[str]:
    """An endpoint that accepts connections and never answers: its URL."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(64)
    held: list[socket.socket] = []
    stop = threading.Event()

    def accept() -> None:
        server.settimeout(0.2)
        while not stop.is_set():
            try:
                held.append(server.accept()[0])
            except OSError:
                continue

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.getsockname()[1]}"
    finally:
        stop.set()
        thread.join()
        for conn in held:
            conn.close()
        server.close()


def test_an_endpoint_that_never_answers_ends_the_upload_with_a_sentence(
    tmp_path: Path, black_hole: str, station_plugin: StationTestPlugin
) -> None:
    pytest.importorskip("s3fs")
    url, run = _run_with_a_file(tmp_path)
    env = {**os.environ, "AWS_ACCESS_KEY_ID": "calstation", "AWS_SECRET_ACCESS_KEY": "secret",
           "AWS_DEFAULT_REGION": "us-east-1", "AWS_ENDPOINT_URL": black_hole,
           "CALSTATION_UPLOAD_TIMEOUT": "1"}
    try:  # the guard only catches a hang; the upload ends on its own time-out
        proc = subprocess.run([sys.executable, "-m", "calstation", "upload", str(run), "--to",
                               "s3://bucket/stations", "--db", url], env=env,
                              capture_output=True, text=True, timeout=120)
    except subprocess.TimeoutExpired:
        pytest.fail("calstation upload hung on an endpoint that never answers")
    said = " ".join((proc.stdout + proc.stderr).split())
    assert proc.returncode == 1, said
    assert f"the S3 endpoint {black_hole} (bucket bucket) did not answer within 1 s" in said
    assert "CALSTATION_UPLOAD_TIMEOUT" in said and "Traceback" not in said
    assert _locations(url) == [None]


def test_a_copy_is_read_back_through_a_new_connection_before_it_counts(tmp_path: Path) -> None:
    """A store whose copies only the connection that wrote them sees (as memory:// in one
    process, or a cache in front of a store that lost the write): the upload fails, naming it."""
    from fsspec.implementations.memory import MemoryFileSystem
    from fsspec.registry import register_implementation

    from calstation.recordings.shared import SharedStorageError, upload

    class PerConnection(MemoryFileSystem):
        protocol = "perconnection"

        def __init__(self, *args: object, **kwargs: object) -> None:
            super().__init__(*args, **kwargs)
            self.store: dict[str, object] = {}
            self.pseudo_dirs = [""]

    register_implementation("perconnection", PerConnection, clobber=True)
    src = tmp_path / "scan.mcap"
    src.write_bytes(os.urandom(100_000))
    with pytest.raises(SharedStorageError, match="reads back from a new connection"):
        upload(src, "perconnection://store/line-1/scan.mcap", file_sha256(src))
