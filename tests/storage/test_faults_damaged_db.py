"""A database file that is not one (random bytes, a text file) or whose content is damaged: every
command that opens it says so in one sentence naming the file and what to do, never a traceback.

The damaged schema reproduces the fault suite's find: SQLite's message about it holds the damaged
bytes, which Python could not decode (a ``UnicodeDecodeError`` from ``PRAGMA journal_mode=WAL``).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from calstation.storage.db import open_database
from tests.support.clirun import run_cli

REPO = Path(__file__).resolve().parents[2]
RECIPE = REPO / "recipes" / "sim-periodicity.yaml"


def _random_bytes(path: Path) -> Path:
    path.write_bytes(os.urandom(20_000))
    return path


def _text(path: Path) -> Path:
    path.write_text("station: bench-1\nthis is a text file, not a database\n")
    return path


def _damaged_schema(path: Path) -> Path:
    """A real calstation database whose schema text has a byte that is not UTF-8."""
    open_database(f"sqlite:///{path}").dispose()
    data = bytearray(path.read_bytes())
    at = data.index(b"tablestation_lockstation_lock")  # sqlite_master's row: type, name, …
    data[at + 7] = 0xD5  # in its name, which SQLite's message quotes
    at = data.index(b"CREATE TABLE station_lock")
    data[at + 3] = 0xD5  # and in its SQL, which then cannot be read
    path.write_bytes(bytes(data))
    for side in ("-wal", "-shm"):
        Path(f"{path}{side}").unlink(missing_ok=True)
    return path


COMMANDS = [
    ["history"], ["show", "1"], ["trend", "--station", "sim-01", "--param", "tx"],
    ["export", "1", "--format", "yaml"], ["resume", "1"], ["db", "upgrade"],
    ["calibrate", "--run", "1"], ["run", str(RECIPE), "--yes"],
]


@pytest.mark.parametrize("make", [_random_bytes, _text, _damaged_schema],
                         ids=["random-bytes", "text-file", "damaged-schema"])
def test_every_command_says_in_one_sentence_the_file_is_not_a_usable_database(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], make: object,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("CALSTATION_HOME", str(tmp_path / "home"))
    path = make(tmp_path / "runs.db")  # type: ignore[operator]
    before = path.read_bytes()
    url = f"sqlite:///{path}"
    for argv in COMMANDS:
        code, out, err = run_cli([*argv, "--db", url], capsys)
        said = " ".join(err.split())
        assert code == 2, (argv, out, err)
        assert "Traceback" not in out + err and "UnicodeDecodeError" not in out + err, argv
        assert said.startswith(f"error: the database file {path} ")
        assert ("is not a database" in said) == (make is not _damaged_schema), said
        assert ("is damaged" in said) == (make is _damaged_schema), said
        assert "give calstation the right file (--db or $CALSTATION_DB_URL)" in said
        assert "restore it from a backup" in said
        assert said.count(". ") == 0, said  # one sentence
    assert path.read_bytes() == before  # the file was left as it was
