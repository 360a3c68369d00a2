"""Run folders and shared copies of their own: two databases that share one CALSTATION_HOME (the
damaged one moved aside, any --db) or one shared store never write into each other's runs."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from calstation.recipes import load_recipe
from calstation.recordings.runfolder import file_sha256
from calstation.station.runs import create_run, start_run
from calstation.storage.db import Artifact, Database, Run, open_database
from calstation.storage.db.database import SCHEMA_HEAD
from tests.support.station import ScriptedOperator, StationTestPlugin, toy_recipe


def _artifacts(db: Database, run_id: int) -> dict[str, tuple[str, str]]:
    with db.session("reading", read_only=True) as s:
        return {a.kind: (a.path, a.sha256) for a in s.query(Artifact).filter_by(run_id=run_id)}


def _folder(db: Database, run_id: int) -> Path:
    with db.session("reading", read_only=True) as s:
        run = s.get(Run, run_id)
        assert run is not None
        return Path(run.data_dir)


def test_a_second_database_in_the_same_home_leaves_the_first_ones_runs_alone(
    tmp_path: Path, station_plugin: StationTestPlugin
) -> None:
    home = tmp_path / "home"
    recipe = load_recipe(toy_recipe(tmp_path))
    first = open_database(f"sqlite:///{home / 'calstation.db'}")
    run_a, _ = start_run(recipe, first, ScriptedOperator(place=lambda f: f != "qa_cube"),
                         operator="ann", data_dir=home)
    kept = _artifacts(first, run_a)
    assert set(kept) == {"static", "spin"}
    # the damaged-database advice: move it aside; calstation makes a new one where it was
    shutil.move(home / "calstation.db", home / "calstation.db.damaged")
    for suffix in ("-wal", "-shm"):
        if (home / f"calstation.db{suffix}").exists():
            shutil.move(home / f"calstation.db{suffix}", home / f"calstation.db.damaged{suffix}")
    first.dispose()
    second = open_database(f"sqlite:///{home / 'calstation.db'}")
    run_b, _ = start_run(recipe, second, ScriptedOperator(place=lambda f: f != "qa_cube"),
                         operator="bob", data_dir=home)
    assert run_a == run_b == 1  # the same run id in both databases
    assert _folder(second, run_b) != Path(kept["spin"][0]).parent
    for path, digest in kept.values():  # every file of the first run as it was stored
        assert file_sha256(Path(path)) == digest
    assert not list(home.rglob("*.attempt*"))
    moved = open_database(f"sqlite:///{home / 'calstation.db.damaged'}")
    assert _artifacts(moved, run_a) == kept
    moved.dispose()
    second.dispose()


def test_a_copy_of_a_database_numbering_runs_in_the_same_place_gets_new_folders(
    tmp_path: Path, station_plugin: StationTestPlugin
) -> None:
    recipe = load_recipe(toy_recipe(tmp_path))
    a = open_database(f"sqlite:///{tmp_path / 'a.db'}")
    create_run(recipe, a, operator="ann", unattended=True, data_dir=tmp_path)
    a.dispose()
    shutil.copy(tmp_path / "a.db", tmp_path / "copy.db")  # the same identity, the same ids
    a = open_database(f"sqlite:///{tmp_path / 'a.db'}")
    copy = open_database(f"sqlite:///{tmp_path / 'copy.db'}")
    assert a.identity == copy.identity
    run = create_run(recipe, a, operator="ann", unattended=True, data_dir=tmp_path)
    (_folder(a, run) / "spin.mcap").write_bytes(b"the first database's recording")
    same = create_run(recipe, copy, operator="bob", unattended=True, data_dir=tmp_path)
    assert same == run
    assert _folder(copy, same) == _folder(a, run).with_name(f"{run}-2")
    assert (_folder(a, run) / "spin.mcap").read_bytes() == b"the first database's recording"
    a.dispose()
    copy.dispose()


def test_a_database_made_before_identities_keeps_its_folders_and_gets_one(
    tmp_path: Path, station_plugin: StationTestPlugin
) -> None:
    from sqlalchemy import text

    url = f"sqlite:///{tmp_path / 'old.db'}"
    old = Database(url)
    old.upgrade("0010_station_lock")
    with old.engine.begin() as conn:
        conn.execute(text("INSERT INTO station (id, name, created_at) VALUES (1, 'sim-test', "
                          "'2026-01-01 00:00:00')"))
        conn.execute(text(
            "INSERT INTO run (id, station_id, recipe_name, recipe_text, recipe_sha256, operator, "
            "unattended, data_dir, started_at, status) VALUES (1, 1, 'r', 'x', 'ab', 'ann', 0, "
            f"'{tmp_path / 'runs' / '1'}', '2026-01-01 00:00:00', 'passed')"))
    assert old.upgrade() == ("0010_station_lock", SCHEMA_HEAD)
    old.dispose()
    from calstation.storage.db.models import DatabaseIdentity

    db = open_database(url)
    with db.session("reading", read_only=True) as s:
        assert s.query(DatabaseIdentity).count() == 1
    assert _folder(db, 1) == tmp_path / "runs" / "1"  # the run stored before: where it was
    new = create_run(load_recipe(toy_recipe(tmp_path)), db, operator="ann", unattended=True,
                     data_dir=tmp_path)
    assert _folder(db, new) == tmp_path / "runs" / db.identity / str(new)
    assert db.downgrade("0010_station_lock")[1] == "0010_station_lock"
    db.dispose()


def test_two_databases_upload_their_run_1_to_one_store_without_meeting(
    tmp_path: Path, station_plugin: StationTestPlugin
) -> None:
    from calstation.recordings.shared import SharedStorageError, upload
    from calstation.storage.uploads import upload_run

    store = f"file://{tmp_path / 'store'}"
    recipe = load_recipe(toy_recipe(tmp_path))
    copies = []
    for name in ("a", "b"):
        db = open_database(f"sqlite:///{tmp_path / name}.db")
        run = create_run(recipe, db, operator="ann", unattended=True, data_dir=tmp_path / name)
        path = _folder(db, run) / "static.mcap"
        path.write_bytes(f"the recording of database {name}".encode())
        with db.session() as s:
            s.add(Artifact(run_id=run, kind="static", path=str(path),
                           size_bytes=path.stat().st_size, sha256=file_sha256(path)))
        done = upload_run(db, run, store)
        assert done.ok and len(done.sent) == 1, done
        copies.append((done.sent[0], file_sha256(path)))
        db.dispose()
    assert copies[0][0] != copies[1][0]
    for location, digest in copies:
        assert file_sha256(Path(location.removeprefix("file://"))) == digest
    # an object already at a location is never replaced by another file
    other = tmp_path / "other.mcap"
    other.write_bytes(b"different bytes")
    with pytest.raises(SharedStorageError, match="holds another file already"):
        upload(other, copies[0][0], file_sha256(other))
    assert file_sha256(Path(copies[0][0].removeprefix("file://"))) == copies[0][1]
