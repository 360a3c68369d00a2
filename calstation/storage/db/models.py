"""The run database's tables: the database's identity, station, run, step, calibration, cube
check, artifact, and the re-processing campaigns (campaign, campaign run).

SQLAlchemy 2 typed models. Only portable column types are used (the same schema runs on SQLite and
PostgreSQL). Lengths are metres and angles radians, as everywhere in storage; times are UTC.
Constraints are named through :data:`NAMING_CONVENTION` so SQLite batch migrations can alter them.
"""

from __future__ import annotations

import datetime as dt
from enum import StrEnum
from typing import TYPE_CHECKING, Any

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Integer,
    MetaData,
    String,
    Text,
    UniqueConstraint,
    true,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship, validates

from calstation.jsonvalue import JSONObject

if TYPE_CHECKING:
    from calstation.engine.result import CalibrationResult

NAMING_CONVENTION: dict[str, str] = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}
"""Constraint names (Alembic's recommended convention)."""

MAX_ROW_ID = 2**63 - 1
"""The largest id a row can have (a signed 64-bit integer): a larger one names no row."""

PARAMS: tuple[str, ...] = ("tx", "ty", "tz", "rx", "ry", "rz")
"""The calibration parameters, in storage order (tx, ty, tz metres; rx, ry, rz radians)."""


def utcnow() -> dt.datetime:
    """The current time, timezone-aware UTC."""
    return dt.datetime.now(dt.UTC)


class Base(DeclarativeBase):
    """Declarative base with the naming convention."""

    metadata = MetaData(naming_convention=NAMING_CONVENTION)


class RunStatus(StrEnum):
    """A run's ``status``: running, or how it ended (stored as its value)."""

    RUNNING = "running"
    PASSED = "passed"
    FAILED = "failed"
    ABORTED = "aborted"
    INTERRUPTED = "interrupted"
    """its process ended, or lost the database, before the run finished: it is resumed"""


class StepStatus(StrEnum):
    """A step attempt's ``status`` (stored as its value)."""

    RUNNING = "running"
    """started; left so by a crash"""
    PASSED = "passed"
    FAILED = "failed"
    ABORTED = "aborted"
    INTERRUPTED = "interrupted"
    """found running by a resume"""


class DatabaseIdentity(Base):
    """This database's identity: a random ``uid`` given when its tables were created (or when a
    database made before identities was migrated to them). Run folders and the runs' shared
    copies are named with it (``runs/<uid>/<run id>``), so that two databases sharing one
    ``CALSTATION_HOME`` or one shared store never write into each other's runs. One row."""

    __tablename__ = "database_identity"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    uid: Mapped[str] = mapped_column(String(32), unique=True)
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class Station(Base):
    """A calibration station, known by the ``station.id`` of its recipes."""

    __tablename__ = "station"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(100), unique=True)
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)

    runs: Mapped[list[Run]] = relationship(back_populates="station")


class Run(Base):
    """One run of a recipe on a station.

    ``status`` is a :class:`RunStatus`: ``"running"``, ``"passed"``, ``"failed"``, ``"aborted"``
    or ``"interrupted"`` (its process ended, or lost the database, before the run finished);
    ``calstation resume`` continues a run that did not pass. ``host`` and ``pid`` name the
    process executing it (so a second process cannot drive the same run). ``motor_stop`` says
    how the turntable was stopped when the run's drivers closed: ``{"how": "stop" |
    "emergency_stop" | ..., "reason", "ok", "at"}``.
    ``unit_serial`` is the serial number of the calibrated unit: given by the operator
    (``calstation run --serial``), else the lidar driver's ``info().serial`` at preflight.
    """

    __tablename__ = "run"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    station_id: Mapped[int] = mapped_column(ForeignKey("station.id"), index=True)
    recipe_name: Mapped[str] = mapped_column(String(200))
    recipe_path: Mapped[str | None] = mapped_column(String(1000))
    recipe_text: Mapped[str] = mapped_column(Text)
    recipe_sha256: Mapped[str] = mapped_column(String(64))
    operator: Mapped[str] = mapped_column(String(100))
    unattended: Mapped[bool] = mapped_column(Boolean, default=False)
    data_dir: Mapped[str] = mapped_column(String(1000))
    started_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    finished_at: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))
    status: Mapped[str] = mapped_column(String(16), default=RunStatus.RUNNING.value, index=True)
    error: Mapped[str | None] = mapped_column(Text)
    host: Mapped[str | None] = mapped_column(String(255))
    pid: Mapped[int | None] = mapped_column(Integer)
    unit_serial: Mapped[str | None] = mapped_column(String(100), index=True)
    motor_stop: Mapped[JSONObject | None] = mapped_column(JSON)

    station: Mapped[Station] = relationship(back_populates="runs")
    steps: Mapped[list[Step]] = relationship(
        back_populates="run", order_by="Step.id", cascade="all, delete-orphan"
    )
    calibrations: Mapped[list[Calibration]] = relationship(
        back_populates="run", order_by="Calibration.id", cascade="all, delete-orphan"
    )
    cube_checks: Mapped[list[CubeCheckRecord]] = relationship(
        back_populates="run", order_by="CubeCheckRecord.id", cascade="all, delete-orphan"
    )
    artifacts: Mapped[list[Artifact]] = relationship(
        back_populates="run", order_by="Artifact.id", cascade="all, delete-orphan"
    )

    @validates("status")
    def _known_status(self, key: str, value: str) -> str:
        """A :class:`RunStatus`, kept as its plain value (ValueError for another)."""
        return str(RunStatus(value))


class Step(Base):
    """One attempt at one step of a run.

    ``status`` is a :class:`StepStatus`: ``"running"`` (started; left so by a crash),
    ``"passed"``, ``"failed"``, ``"interrupted"`` (found running by ``resume``) or ``"aborted"``.
    ``result`` is the step's JSON result mapping.
    """

    __tablename__ = "step"
    __table_args__ = (UniqueConstraint("run_id", "name", "attempt"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("run.id", ondelete="CASCADE"), index=True)
    name: Mapped[str] = mapped_column(String(50))
    attempt: Mapped[int] = mapped_column(Integer, default=1)
    status: Mapped[str] = mapped_column(String(16), default=StepStatus.RUNNING.value)
    started_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    finished_at: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))
    result: Mapped[dict[str, Any] | None] = mapped_column(JSON)  # Any: JSON, read by key
    error: Mapped[str | None] = mapped_column(Text)

    @validates("status")
    def _known_status(self, key: str, value: str) -> str:
        """A :class:`StepStatus`, kept as its plain value (ValueError for another)."""
        return str(StepStatus(value))

    run: Mapped[Run] = relationship(back_populates="steps")
    artifacts: Mapped[list[Artifact]] = relationship(back_populates="step")


class Calibration(Base):
    """A calibration H produced by a run (initial or fine-tuned).

    tx, ty, tz in metres and rx, ry, rz in radians (DESIGN §2); ``sigma_*`` their 1σ (None when
    not estimated). ``encoder_latency_s``: the estimated lidar–encoder time offset (encoder time
    minus lidar time, s) when the spin scan had a second pass, else None.
    ``predicted_error_m``: the reconstruction error the calibration predicts over the recipe's
    work volume (m, at the budget's level; ``diagnostics["predicted_error"]`` has the details),
    None when it was not predicted. ``range_offset`` (m), ``range_scale``, ``incidence_bias``
    (m at 60°) and their ``sigma_*``: the lidar's range model estimated with H (DESIGN §9), None
    when not estimated. ``accepted`` marks the run's final calibration when the run passed.
    """

    __tablename__ = "calibration"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("run.id", ondelete="CASCADE"), index=True)
    step_id: Mapped[int | None] = mapped_column(ForeignKey("step.id", ondelete="SET NULL"))
    stage: Mapped[str] = mapped_column(String(20))
    strategy: Mapped[str] = mapped_column(String(50))
    tx: Mapped[float] = mapped_column(Float)
    ty: Mapped[float] = mapped_column(Float)
    tz: Mapped[float] = mapped_column(Float)
    rx: Mapped[float] = mapped_column(Float)
    ry: Mapped[float] = mapped_column(Float)
    rz: Mapped[float] = mapped_column(Float)
    sigma_tx: Mapped[float | None] = mapped_column(Float)
    sigma_ty: Mapped[float | None] = mapped_column(Float)
    sigma_tz: Mapped[float | None] = mapped_column(Float)
    sigma_rx: Mapped[float | None] = mapped_column(Float)
    sigma_ry: Mapped[float | None] = mapped_column(Float)
    sigma_rz: Mapped[float | None] = mapped_column(Float)
    encoder_latency_s: Mapped[float | None] = mapped_column(Float)
    sigma_encoder_latency_s: Mapped[float | None] = mapped_column(Float)
    predicted_error_m: Mapped[float | None] = mapped_column(Float)
    range_offset: Mapped[float | None] = mapped_column(Float)
    sigma_range_offset: Mapped[float | None] = mapped_column(Float)
    range_scale: Mapped[float | None] = mapped_column(Float)
    sigma_range_scale: Mapped[float | None] = mapped_column(Float)
    incidence_bias: Mapped[float | None] = mapped_column(Float)
    sigma_incidence_bias: Mapped[float | None] = mapped_column(Float)
    cost: Mapped[float | None] = mapped_column(Float)
    iterations: Mapped[int | None] = mapped_column(Integer)
    accepted: Mapped[bool] = mapped_column(Boolean, default=False, index=True)
    diagnostics: Mapped[dict[str, Any] | None] = mapped_column(JSON)  # Any: JSON, read by key
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)

    run: Mapped[Run] = relationship(back_populates="calibrations")

    def params(self) -> dict[str, float]:
        """tx, ty, tz (m) and rx, ry, rz (rad)."""
        return {p: float(getattr(self, p)) for p in PARAMS}

    def sigmas(self) -> dict[str, float | None]:
        """1σ of each parameter (m / rad), None when not estimated."""
        return {p: getattr(self, f"sigma_{p}") for p in PARAMS}

    def result(self) -> CalibrationResult:
        """The calibration as the engine's result, as it was stored (the inverse of
        :func:`calstation.station.persist.calibration_row`): H, σ (NaN where not estimated),
        cost, iterations, strategy, the timings and the other diagnostics, the time offset.
        The one place a row becomes a result again."""
        import math

        from calstation.engine.frames import Extrinsics
        from calstation.engine.result import CalibrationResult

        diagnostics = dict(self.diagnostics or {})
        timings = diagnostics.pop("timings", None) or {}
        return CalibrationResult(
            H=Extrinsics.from_dict(self.params()),
            sigma={p: math.nan if v is None else float(v) for p, v in self.sigmas().items()},
            cost=math.nan if self.cost is None else float(self.cost),
            iterations=int(self.iterations or 0),
            strategy=self.strategy,
            timings={str(k): float(v) for k, v in timings.items() if v is not None},
            diagnostics=diagnostics,
            encoder_latency_s=self.encoder_latency_s,
            sigma_encoder_latency_s=self.sigma_encoder_latency_s,
        ).with_range(self.range_fields())

    def range_fields(self) -> dict[str, float | None]:
        """The range model as stored (DESIGN §9; None where not estimated)."""
        from calstation.engine.result import RANGE_FIELDS

        return {name: getattr(self, name) for name in RANGE_FIELDS}


class CubeCheckRecord(Base):
    """The QA cube check of a run (lengths in metres, perpendicularity in degrees; NULL: a
    measure the check could not make, e.g. no two adjacent side faces seen)."""

    __tablename__ = "cube_check"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("run.id", ondelete="CASCADE"), index=True)
    step_id: Mapped[int | None] = mapped_column(ForeignKey("step.id", ondelete="SET NULL"))
    calibration_id: Mapped[int | None] = mapped_column(
        ForeignKey("calibration.id", ondelete="SET NULL")
    )
    obb_edges: Mapped[list[float]] = mapped_column(JSON)
    obb_error: Mapped[float | None] = mapped_column(Float)
    face_edges: Mapped[list[float]] = mapped_column(JSON)
    edge_error: Mapped[float | None] = mapped_column(Float)
    height_judged: Mapped[bool] = mapped_column(Boolean, default=True, server_default=true())
    """whether ``edge_error`` counts the height (``face_edges[0]``): only for a cube of the
    platter's finish (``fixtures.qa_cube.same_finish_as_platter``), the height being measured
    from the platter"""
    flatness_rms: Mapped[float | None] = mapped_column(Float)
    perpendicularity_deg: Mapped[float | None] = mapped_column(Float)
    twist_deg: Mapped[float | None] = mapped_column(Float)
    """the ry correction the side faces ask for (degrees; NULL before it was measured)"""
    twist_sigma_deg: Mapped[float | None] = mapped_column(Float)
    flatness_excess: Mapped[float | None] = mapped_column(Float)
    """the worst face's RMS beyond the range noise (m; what ``qa.flatness_rms`` limits; NULL
    before it was measured, when the limit judged ``flatness_rms``)"""
    range_noise: Mapped[float | None] = mapped_column(Float)
    """the range noise measured on the faces (m, 1σ along the rays)"""
    passed: Mapped[bool] = mapped_column(Boolean)
    failures: Mapped[list[str]] = mapped_column(JSON)
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)

    run: Mapped[Run] = relationship(back_populates="cube_checks")


class Artifact(Base):
    """A file a run produced (a recording, a report): path, size in bytes and sha256.

    ``status`` is ``"complete"``, or ``"partial"`` for a recording cut short by a fault or an
    abort (kept for diagnosis, never re-used by ``resume``).
    """

    __tablename__ = "artifact"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("run.id", ondelete="CASCADE"), index=True)
    step_id: Mapped[int | None] = mapped_column(ForeignKey("step.id", ondelete="SET NULL"))
    kind: Mapped[str] = mapped_column(String(50))
    path: Mapped[str] = mapped_column(String(1000))
    size_bytes: Mapped[int] = mapped_column(BigInteger)
    sha256: Mapped[str] = mapped_column(String(64))
    status: Mapped[str] = mapped_column(String(16), default="complete", server_default="complete")
    location: Mapped[str | None] = mapped_column(String(1000))
    """Where the file's shared copy is (an fsspec URL: ``s3://…``, ``file://…``), once uploaded
    and verified against ``sha256``; None while only the local ``path`` holds it."""
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)

    run: Mapped[Run] = relationship(back_populates="artifacts")
    step: Mapped[Step | None] = relationship(back_populates="artifacts")


class Campaign(Base):
    """A re-processing campaign: stored runs calibrated again with today's engine
    (``calstation reprocess``).

    ``key`` identifies what is computed (the selection of runs and the strategy): the same
    command finds the campaign again and continues it. ``selection`` holds the filters as given,
    ``tolerance`` what a change is flagged above (:mod:`calstation.fleet.tolerance`),
    ``selected`` how many runs the last invocation selected, ``engine`` the calstation version.
    ``finished_at`` is set when every selected run has a row.
    """

    __tablename__ = "campaign"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    key: Mapped[str] = mapped_column(String(64), index=True)
    selection: Mapped[dict[str, object]] = mapped_column(JSON)
    strategy: Mapped[str | None] = mapped_column(String(50))
    tolerance: Mapped[dict[str, object]] = mapped_column(JSON)
    engine: Mapped[str] = mapped_column(String(100))
    host: Mapped[str | None] = mapped_column(String(255))
    selected: Mapped[int] = mapped_column(Integer, default=0)
    started_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    finished_at: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))

    runs: Mapped[list[CampaignRun]] = relationship(
        back_populates="campaign", order_by="CampaignRun.run_id", cascade="all, delete-orphan"
    )


class CampaignRun(Base):
    """One run of a campaign: its re-processing and how it compares with the stored H.

    ``outcome`` is ``"reprocessed"`` (``calibration_id`` is the stored re-processing, stage
    ``reprocess``, never accepted), ``"skipped"`` (its recordings are missing or changed:
    ``error`` says which) or ``"failed"`` (the engine failed: ``error``). ``comparison`` holds
    the stored H against the new one (:func:`calstation.fleet.compare.compare`); ``flagged``
    marks a change above the campaign's tolerance, ``refused`` a result today's engine refuses.
    ``seconds`` is the re-processing's own time, ``worker`` where it ran. One row per run and
    campaign: a resumed campaign never computes a run twice.
    """

    __tablename__ = "campaign_run"
    __table_args__ = (UniqueConstraint("campaign_id", "run_id"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    campaign_id: Mapped[int] = mapped_column(
        ForeignKey("campaign.id", ondelete="CASCADE"), index=True
    )
    run_id: Mapped[int] = mapped_column(ForeignKey("run.id", ondelete="CASCADE"), index=True)
    calibration_id: Mapped[int | None] = mapped_column(
        ForeignKey("calibration.id", ondelete="SET NULL")
    )
    outcome: Mapped[str] = mapped_column(String(16))
    flagged: Mapped[bool] = mapped_column(Boolean, default=False, index=True)
    refused: Mapped[bool] = mapped_column(Boolean, default=False)
    comparison: Mapped[dict[str, object] | None] = mapped_column(JSON)
    error: Mapped[str | None] = mapped_column(Text)
    seconds: Mapped[float | None] = mapped_column(Float)
    worker: Mapped[str | None] = mapped_column(String(255))
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)

    campaign: Mapped[Campaign] = relationship(back_populates="runs")


class StationLock(Base):
    """Who holds a station: at most one row per station, while a run drives its turntable.

    Taken by whatever starts or resumes a run (``calstation run``, ``resume``, any web station)
    before it creates the run, released when the run's drivers are closed
    (:mod:`calstation.station.lock`). ``token`` identifies one taking of the lock; ``front_end``
    says from where it was taken (``calstation run`` in a terminal, the web station at its
    address); ``host``, ``pid`` and ``process_started`` (the process's start time as the kernel
    counts it, so that a re-used process id is not taken for the holder) tell a lock left by a
    process that died; ``heartbeat_at`` is renewed while the holder lives, which tells it for a
    holder on another host.
    """

    __tablename__ = "station_lock"

    station_id: Mapped[int] = mapped_column(
        ForeignKey("station.id", ondelete="CASCADE"), primary_key=True
    )
    token: Mapped[str] = mapped_column(String(64))
    run_id: Mapped[int | None] = mapped_column(ForeignKey("run.id", ondelete="SET NULL"))
    operator: Mapped[str] = mapped_column(String(100))
    front_end: Mapped[str] = mapped_column(String(300))
    host: Mapped[str] = mapped_column(String(255))
    pid: Mapped[int] = mapped_column(Integer)
    process_started: Mapped[str | None] = mapped_column(String(64))
    acquired_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    heartbeat_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
