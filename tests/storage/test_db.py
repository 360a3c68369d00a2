"""The run database: migrations match the models, WAL mode, round trips, PostgreSQL."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import pytest
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import inspect, select, text

from calstation.errors import DatabaseError
from calstation.storage.db import (
    SCHEMA_HEAD,
    Artifact,
    Base,
    Calibration,
    CubeCheckRecord,
    Database,
    Run,
    Station,
    Step,
    alembic_config,
    default_database_url,
    head_revision,
    open_database,
)


def test_revision_chain_is_linear() -> None:
    script = ScriptDirectory.from_config(alembic_config())
    heads = script.get_heads()
    assert len(heads) == 1, f"several heads: {heads}"
    bases = script.get_bases()
    assert len(bases) == 1, f"several bases: {bases}"
    seen = []
    for rev in script.walk_revisions():
        assert not rev.is_merge_point, f"{rev.revision} merges branches"
        assert not rev.is_branch_point, f"{rev.revision} branches"
        seen.append(rev.revision)
    assert seen[0] == heads[0] and seen[-1] == bases[0]


def _assert_matches_models(db: Database) -> None:
    with db.engine.connect() as conn:
        diff = compare_metadata(
            MigrationContext.configure(conn, opts={"compare_type": True}), Base.metadata
        )
    assert diff == [], f"migrations and models differ: {diff}"


def test_the_schema_head_constant_is_the_newest_migration() -> None:
    assert head_revision() == SCHEMA_HEAD


def test_a_database_at_another_revision_is_not_taken_for_current(tmp_path: Path) -> None:
    db = Database(f"sqlite:///{tmp_path / 'old.db'}")
    db.upgrade("0002")
    with pytest.raises(DatabaseError, match="needs " + SCHEMA_HEAD):
        db.ensure_schema()


def test_upgrade_to_head_matches_models(tmp_path: Path) -> None:
    db = Database(f"sqlite:///{tmp_path / 'c.db'}")
    before, after = db.upgrade()
    assert before is None and after == head_revision()
    _assert_matches_models(db)
    # idempotent
    assert db.upgrade() == (after, after)
    db.dispose()


def test_env_uses_the_given_connection(tmp_path: Path) -> None:
    from alembic import command

    db = Database(f"sqlite:///{tmp_path / 'conn.db'}")
    with db.engine.begin() as conn:
        command.upgrade(alembic_config(conn), "head")
    assert db.current_revision() == head_revision()
    with db.engine.begin() as conn:
        command.downgrade(alembic_config(conn), "base")
    with db.engine.connect() as conn:
        assert set(inspect(conn).get_table_names()) <= {"alembic_version"}
    db.dispose()


def test_sqlite_is_in_wal_mode_with_foreign_keys(tmp_path: Path) -> None:
    db = open_database(f"sqlite:///{tmp_path / 'sub' / 'w.db'}")
    with db.engine.connect() as conn:
        assert conn.execute(text("PRAGMA journal_mode")).scalar() == "wal"
        assert conn.execute(text("PRAGMA foreign_keys")).scalar() == 1
    db.dispose()


def test_a_read_only_session_refuses_to_write(tmp_path: Path) -> None:
    """Its transaction holds no lock to write with: a change is refused and nothing is written."""
    db = open_database(f"sqlite:///{tmp_path / 'r.db'}")
    with (pytest.raises(DatabaseError, match="read-only database session"),
          db.session("reading", read_only=True) as s):
        s.add(Station(name="never"))
    with db.session("reading", read_only=True) as s:
        assert s.query(Station).count() == 0
    db.dispose()


def test_default_location_follows_calstation_home(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("CALSTATION_DB_URL", raising=False)
    monkeypatch.setenv("CALSTATION_HOME", str(tmp_path / "home"))
    assert default_database_url() == f"sqlite:///{tmp_path / 'home' / 'calstation.db'}"
    monkeypatch.setenv("CALSTATION_DB_URL", "sqlite:////elsewhere.db")
    assert default_database_url() == "sqlite:////elsewhere.db"


def test_outdated_database_is_refused(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'old.db'}"
    db = Database(url)
    db.upgrade("0002")
    with pytest.raises(DatabaseError, match=r"at revision 0002, .*run `calstation db upgrade`"):
        db.ensure_schema()
    db.dispose()


def test_unknown_revision_says_what_it_is(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'new.db'}"
    db = Database(url)
    db.upgrade()
    with db.engine.begin() as conn:
        conn.execute(text("UPDATE alembic_version SET version_num = 'from_the_future'"))
    with pytest.raises(DatabaseError, match=r"at revision 'from_the_future', which this calstation "
                                            "does not know .* newer calstation"):
        db.ensure_schema()
    with pytest.raises(DatabaseError, match="does not know"):
        db.upgrade()
    from typer.testing import CliRunner

    from calstation.cli import _build, app

    _build()
    shown = CliRunner().invoke(app, ["db", "info", "--db", url])
    assert "revision: from_the_future" in shown.output
    assert "unknown to this calstation: migrated by a newer version" in shown.output
    db.dispose()


def test_bad_url_is_a_clear_error() -> None:
    with pytest.raises(DatabaseError, match="cannot use database URL"):
        Database("nosuchdialect://x/y")


def _fill(db: Database) -> int:
    with db.session() as s:
        station = Station(name="st-1")
        run = Run(
            station=station,
            recipe_name="r",
            recipe_path="/r.yaml",
            recipe_text="name: r\n",
            recipe_sha256="0" * 64,
            operator="ann",
            data_dir="/tmp/runs/1",
        )
        step = Step(run=run, name="static_scan", status="passed", result={"lines": 100})
        cal = Calibration(
            run=run, stage="initial", strategy="initial", tx=0.001, ty=1.0, tz=-0.002,
            rx=0.0, ry=0.003, rz=-0.785, sigma_tx=None, cost=1.5, iterations=3,
            diagnostics={"segments": [1, 2]},
        )
        cube = CubeCheckRecord(
            run=run, obb_edges=[0.1, 0.1, 0.1], obb_error=0.001, face_edges=[0.1, 0.1, 0.1],
            edge_error=0.0002, flatness_rms=0.0009, perpendicularity_deg=0.1, passed=True,
            failures=[],
        )
        art = Artifact(run=run, step=step, kind="static", path="/tmp/runs/1/static.mcap",
                       size_bytes=5_000_000_000, sha256="a" * 64)
        s.add_all([station, run, step, cal, cube, art])
        s.flush()
        return run.id


def _check_roundtrip(db: Database, run_id: int) -> None:
    with db.session() as s:
        run = s.get(Run, run_id)
        assert run is not None
        assert run.station.name == "st-1"
        assert run.steps[0].result == {"lines": 100}
        cal = run.calibrations[0]
        assert cal.params() == {"tx": 0.001, "ty": 1.0, "tz": -0.002, "rx": 0.0, "ry": 0.003,
                                "rz": -0.785}
        assert cal.sigma_tx is None and cal.diagnostics == {"segments": [1, 2]}
        assert run.cube_checks[0].face_edges == [0.1, 0.1, 0.1]
        assert run.artifacts[0].size_bytes == 5_000_000_000
        assert run.artifacts[0].step is not None
        assert isinstance(run.started_at, dt.datetime)
        assert s.scalars(select(Step).where(Step.run_id == run_id)).one().name == "static_scan"


def test_models_round_trip_on_sqlite(tmp_path: Path) -> None:
    db = open_database(f"sqlite:///{tmp_path / 'rt.db'}")
    _check_roundtrip(db, _fill(db))
    db.dispose()


# --- PostgreSQL: a throw-away server (tests/conftest.py), skipped when none can be started ------
def test_postgresql_upgrade_matches_models_and_round_trips(postgres_url: str) -> None:
    db = Database(postgres_url)
    db.upgrade()
    _assert_matches_models(db)
    _check_roundtrip(db, _fill(db))
    db.dispose()


def test_unit_serial_migration_fills_and_downgrades_losslessly(tmp_path: Path) -> None:
    """0003 fills unit_serial from what the steps recorded; its downgrade keeps every serial in
    a step result, so upgrading again restores it."""

    db = Database(f"sqlite:///{tmp_path / 'serial.db'}")
    db.upgrade("0002")
    with db.engine.begin() as conn:
        conn.execute(text(
            "INSERT INTO station (id, name, created_at) VALUES (1, 'st', '2026-01-01')"))
        for run_id in (1, 2, 3):
            conn.execute(text(
                "INSERT INTO run (id, station_id, recipe_name, recipe_text, recipe_sha256, "
                "operator, unattended, data_dir, started_at, status) VALUES "
                f"({run_id}, 1, 'r', 'name: r', 'ab', 'ann', 0, '/d', '2026-01-01', 'passed')"))
        conn.execute(text(
            "INSERT INTO step (run_id, name, attempt, status, started_at, result) VALUES "
            "(1, 'preflight', 1, 'passed', '2026-01-01', "
            "'{\"lidar\": {\"serial\": \"H-0042\"}, \"lines\": 10}')"))
        conn.execute(text(
            "INSERT INTO step (run_id, name, attempt, status, started_at, result) VALUES "
            "(2, 'preflight', 1, 'passed', '2026-01-01', '{\"lidar\": {\"serial\": \"H-7\"}}')"))
    db.upgrade()
    with db.session() as s:
        assert [r.unit_serial for r in s.scalars(select(Run).order_by(Run.id))] == [
            "H-0042", "H-7", None]
        s.get(Run, 2).unit_serial = "OPERATOR-9"  # given by the operator, not the lidar's
    db.downgrade("0002")
    with db.engine.connect() as conn:
        assert "unit_serial" not in {c["name"] for c in inspect(conn).get_columns("run")}
        assert conn.execute(text("SELECT count(*) FROM step")).scalar() == 2  # nothing lost
    db.upgrade()
    with db.session() as s:
        assert [r.unit_serial for r in s.scalars(select(Run).order_by(Run.id))] == [
            "H-0042", "OPERATOR-9", None]
        s.get(Run, 3).unit_serial = "NO-STEPS"
    with pytest.raises(Exception, match="would lose it"):
        db.downgrade("0002")
    db.dispose()
