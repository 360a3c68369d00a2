"""Commands given what a plant gives them: a mistyped --db, a read-only copy of the database, run
ids past what a row can hold, and operator names and serials holding control characters. Each
gets one clear sentence (exit 2) and changes nothing it was not asked to change."""

from __future__ import annotations

import datetime as dt
import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from calstation.storage.db import Run, open_database
from tests.support.clirun import run_cli
from tests.support.qa import H1, add_run

ESC = "\x1b"


def _files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


@pytest.mark.parametrize("argv", [["history"], ["show", "1"], ["export", "1"],
                                  ["trend", "--station", "st-1", "--param", "tx"],
                                  ["db", "info"]])
def test_a_mistyped_db_makes_no_folder_and_no_database(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch,
    argv: list[str]
) -> None:
    monkeypatch.setenv("CALSTATION_HOME", str(tmp_path / "home"))
    monkeypatch.chdir(tmp_path)
    typo = tmp_path / "statoin" / "calstation.db"
    code, _, err = run_cli([*argv, "--db", f"sqlite:///{typo}"], capsys)
    assert code == 2 and "there is no database at" in err and "mistyped" in err, err
    assert _files(tmp_path) == []  # no folder, no database, no log, no plot


@pytest.fixture
def read_only_db(tmp_path: Path) -> Iterator[str]:
    """A database with one run, on a read-only file system (a tmpfs remounted read-only, as
    root; a read-only file in a read-only folder otherwise): its URL."""
    made = tmp_path / "made.db"
    db = open_database(f"sqlite:///{made}")
    add_run(db, "st-1", "passed", H1, dt.datetime(2026, 3, 1, tzinfo=dt.UTC))
    db.dispose()
    ro = tmp_path / "ro"
    ro.mkdir()
    if os.geteuid() == 0:
        mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(ro)],
                                 capture_output=True)
        if mounted.returncode != 0:
            pytest.skip("cannot mount a read-only file system here")
        shutil.copy(made, ro / "copy.db")
        subprocess.run(["mount", "-o", "remount,ro", str(ro)], check=True)
    else:
        shutil.copy(made, ro / "copy.db")
        (ro / "copy.db").chmod(0o444)
        ro.chmod(0o555)
    try:
        yield f"sqlite:///{ro / 'copy.db'}"
    finally:
        if os.geteuid() == 0:
            subprocess.run(["umount", "-l", str(ro)], check=False)
        else:
            ro.chmod(0o755)


def test_a_read_only_copy_of_the_database_is_read(
    read_only_db: str, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, err = run_cli(["history", "--json", "--db", read_only_db], capsys)
    assert code == 0, err
    assert '"station": "st-1"' in out
    code, out, err = run_cli(["export", "1", "-f", "json", "--db", read_only_db], capsys)
    assert code == 0 and str(H1["tx"]) in out, err
    # a command that writes says it cannot, in one sentence
    code, _, err = run_cli(["upload", "1", "--to", "/srv/none", "--db", read_only_db], capsys)
    assert code == 2 and "Traceback" not in err, err


@pytest.mark.parametrize("run_id", [str(2**63), str(2**64 + 5), "9" * 30])
def test_run_ids_past_a_64_bit_integer_are_no_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], run_id: str
) -> None:
    url = f"sqlite:///{tmp_path / 'qa.db'}"
    db = open_database(url)
    add_run(db, "st-1", "passed", H1, dt.datetime(2026, 3, 1, tzinfo=dt.UTC))
    db.dispose()
    for argv in (["show", run_id], ["export", run_id], ["upload", run_id, "--to",
                                                          str(tmp_path / "store")],
                 ["resume", run_id]):
        code, _, err = run_cli([*argv, "--db", url], capsys)
        assert code == 2 and "no run" in err and "Traceback" not in err, (argv, err)


# --- operator and serial text: one check for every front end -----------------------------------
BAD_TEXT = [
    ("operator", f"ann{ESC}[2J", "U+001B"),
    ("operator", "ann\nbob", "U+000A"),
    ("operator", "a" * 10_000, "10000 characters long; at most 100"),
    ("serial", f"SN{ESC}]0;pwned\a", "U+001B"),
    ("serial", "S" * 10_000, "10000 characters long; at most 100"),
]


@pytest.mark.parametrize(("field", "value", "said"), BAD_TEXT)
def test_the_cli_refuses_the_text_the_web_refuses(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch,
    field: str, value: str, said: str
) -> None:
    from calstation_sim import plugin as sim_plugin

    from calstation import plugins
    from tests.support.station import toy_recipe

    url = f"sqlite:///{tmp_path / 'st.db'}"
    option = {"operator": ["--operator", value], "serial": ["--operator", "ann", "--serial",
                                                             value]}[field]
    with plugins.isolated(sim_plugin):
        code, _, err = run_cli(["run", str(toy_recipe(tmp_path)), "--yes", "--db", url,
                                "--data-dir", str(tmp_path / "data"), *option], capsys)
    assert code == 2 and said in err and "Traceback" not in err, err
    db = open_database(url)
    with db.session("reading", read_only=True) as s:
        assert s.query(Run).count() == 0  # nothing stored
    db.dispose()


@pytest.mark.parametrize(("field", "value", "said"), BAD_TEXT)
def test_the_web_refuses_the_same_text_with_the_same_words(
    field: str, value: str, said: str
) -> None:
    from pydantic import ValidationError

    from calstation.web.payloads import StartRequest

    body = {"recipe": "sim.yaml", "operator": "ann", field: value}
    with pytest.raises(ValidationError) as info:
        StartRequest.model_validate(body)
    if "characters long" not in said:  # pydantic words its own length check
        assert said in str(info.value)


def test_history_shows_stored_control_characters_as_escapes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A database written before the check (or by another tool) may hold them: the terminal
    that lists them is never repainted."""
    url = f"sqlite:///{tmp_path / 'qa.db'}"
    db = open_database(url)
    add_run(db, "st-1", "failed", H1, dt.datetime(2026, 3, 1, tzinfo=dt.UTC),
             operator=f"mallory{ESC}[2J{ESC}[H", serial=f"SN{ESC}]0;title\a",
             error=f"boom{ESC}[31m")
    db.dispose()
    for argv in (["history"], ["show", "1"]):
        code, out, err = run_cli([*argv, "--db", url], capsys)
        assert code == 0, err
        assert ESC not in out and "\a" not in out, (argv, out)
        assert "mallory\\x1b" in out and "boom\\x1b[31m" in out, out
