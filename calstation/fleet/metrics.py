"""The station's Prometheus metrics (``/metrics`` of ``calstation serve``), read from the run
database at each scrape, so they cover every run of the station — from the web station or the
console — and survive a restart of the server.

- ``calstation_runs{station, status}``: runs by status;
- ``calstation_step_duration_seconds{station, step}``: a histogram of every finished attempt of a
  step; ``calstation_cycle_time_seconds{station, status}``: of every run that passed, failed or
  was aborted, start to end;
- ``calstation_accepted_translation_metres`` / ``…_rotation_radians{station, param}``: the latest
  accepted H; ``calstation_accepted_sigma_metres`` / ``…_sigma_radians``: its 1σ;
- ``calstation_predicted_error_metres{station, param}``: its predicted reconstruction error (95 %
  over the work volume), ``all`` from its covariance and each parameter from its σ alone;
- ``calstation_accepted_run`` / ``calstation_accepted_timestamp_seconds{station}``: its run and
  when that run ended;
- ``calstation_drift{station, param}``: 1 when the latest report flagged the parameter's drift;
- ``calstation_busy``: 1 while this server runs a run.

The histograms are built incrementally: each station's finished steps and runs are read once,
in id order, up to the first one still running (which is read again at the next scrape).
Lengths are metres and angles radians (Prometheus' base units).
"""

from __future__ import annotations

import datetime as dt
import math
import threading
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from calstation.storage.db import (
    PARAMS,
    Calibration,
    Database,
    Run,
    RunStatus,
    Station,
    Step,
    StepStatus,
)

if TYPE_CHECKING:
    from prometheus_client.core import GaugeMetricFamily
    from prometheus_client.metrics_core import Metric
    from sqlalchemy import Row

    # (id, label, status, started, finished) of a step or a run
    StatusRow = Row[int, str, str, dt.datetime, dt.datetime | None]

STEP_BUCKETS = (0.5, 1, 2, 5, 10, 20, 30, 60, 120, 300, 600, 1800)
"""Upper bounds of the step-duration histogram (s)."""

CYCLE_BUCKETS = (30, 60, 120, 180, 300, 450, 600, 900, 1200, 1800, 3600)
"""Upper bounds of the cycle-time histogram (s)."""

FINISHED = (RunStatus.PASSED, RunStatus.FAILED, RunStatus.ABORTED)
"""The statuses of a finished step or run (``interrupted`` ones may still be resumed)."""


@dataclass
class _Histogram:
    """One label set's cumulative histogram."""

    bounds: tuple[float, ...]
    counts: list[int] = field(default_factory=list)
    total: float = 0.0
    n: int = 0

    def observe(self, value: float) -> None:
        if not self.counts:
            self.counts = [0] * len(self.bounds)
        for k, bound in enumerate(self.bounds):
            if value <= bound:
                self.counts[k] += 1
        self.total += value
        self.n += 1

    def buckets(self) -> list[tuple[str, float]]:
        counts = self.counts or [0] * len(self.bounds)
        return [*((f"{b:g}", float(c)) for b, c in zip(self.bounds, counts, strict=True)),
                ("+Inf", float(self.n))]


class _Accumulator:
    """Histograms fed with the rows of one query, each station read up to its first row still
    running (its watermark: the highest id folded in)."""

    def __init__(self, bounds: tuple[float, ...]) -> None:
        self.bounds = bounds
        self.watermark: dict[str, int] = {}
        self.histograms: dict[tuple[str, str], _Histogram] = {}

    def fold(self, station: str, rows: Iterable[StatusRow]) -> None:
        """``rows`` (id, label, status, started, finished) of ``station`` above its watermark,
        in id order."""
        for row_id, label, status, started, finished in rows:
            if status == RunStatus.RUNNING:  # a step's RUNNING is the same word
                break
            self.watermark[station] = row_id
            if status in FINISHED and started is not None and finished is not None:
                seconds = (finished - started).total_seconds()
                key = (station, label)
                self.histograms.setdefault(key, _Histogram(self.bounds)).observe(max(seconds, 0))


class StationMetrics:
    """The metrics of the stations ``stations()`` names (all in the database when it names
    none) over ``db``; ``busy()`` tells whether this server runs a run. :meth:`render` gives the
    text exposition."""

    def __init__(self, db: Database, stations: Callable[[], list[str]],
                 busy: Callable[[], bool]) -> None:
        self.db, self.stations, self.busy = db, stations, busy
        self.steps = _Accumulator(STEP_BUCKETS)
        self.cycles = _Accumulator(CYCLE_BUCKETS)
        self._predicted: dict[int, dict[str, float]] = {}
        self._lock = threading.Lock()

    def render(self) -> bytes:
        """The metrics in Prometheus' text format."""
        from prometheus_client import CollectorRegistry, generate_latest

        registry = CollectorRegistry(auto_describe=False)
        registry.register(_Collector(self))
        with self._lock:
            return bytes(generate_latest(registry))

    # --- the reads, at each scrape -----------------------------------------------------------
    def _names(self, s: Session) -> list[str]:
        wanted = self.stations()
        known = list(s.scalars(select(Station.name).order_by(Station.name)))
        return [n for n in known if n in wanted] if wanted else known

    def families(self) -> Iterator[Metric]:
        """Every metric family (see the module docstring)."""
        from prometheus_client.core import GaugeMetricFamily

        with self.db.session("reading the metrics", read_only=True) as s:
            names = self._names(s)
            yield self._runs(s, names)
            self._fold(s, names)
            yield from self._histograms()
            yield from self._accepted(s, names)
            yield self._drift(s, names)
        busy = GaugeMetricFamily("calstation_busy", "1 while this server runs a run")
        busy.add_metric([], 1.0 if self.busy() else 0.0)
        yield busy

    def _runs(self, s: Session, names: list[str]) -> Metric:
        from prometheus_client.core import GaugeMetricFamily

        family = GaugeMetricFamily("calstation_runs", "Runs by status", labels=["station",
                                                                                "status"])
        rows = s.execute(select(Station.name, Run.status, func.count())
                         .join(Run, Run.station_id == Station.id)
                         .where(Station.name.in_(names)).group_by(Station.name, Run.status))
        for station, status, n in rows:
            family.add_metric([station, status], float(n))
        return family

    def _fold(self, s: Session, names: list[str]) -> None:
        for station in names:
            steps = (select(Step.id, Step.name, Step.status, Step.started_at, Step.finished_at)
                     .join(Run, Step.run_id == Run.id).join(Station, Run.station_id == Station.id)
                     .where(Station.name == station,
                            Step.id > self.steps.watermark.get(station, 0))
                     .order_by(Step.id))
            self.steps.fold(station, s.execute(steps).all())
            runs = (select(Run.id, Run.status, Run.status, Run.started_at, Run.finished_at)
                    .join(Station, Run.station_id == Station.id)
                    .where(Station.name == station,
                           Run.id > self.cycles.watermark.get(station, 0))
                    .order_by(Run.id))
            self.cycles.fold(station, s.execute(runs).all())

    def _histograms(self) -> Iterator[Metric]:
        from prometheus_client.core import HistogramMetricFamily

        for name, label, acc, text in (
            ("calstation_step_duration_seconds", "step", self.steps,
             "Duration of each finished attempt of a step"),
            ("calstation_cycle_time_seconds", "status", self.cycles,
             "Start to end of each run that passed, failed or was aborted"),
        ):
            family = HistogramMetricFamily(name, text, labels=["station", label])
            for (station, value), h in sorted(acc.histograms.items()):
                family.add_metric([station, value], h.buckets(), sum_value=h.total)
            yield family

    def _accepted(self, s: Session, names: list[str]) -> Iterator[Metric]:
        from prometheus_client.core import GaugeMetricFamily

        def gauge(name: str, text: str, labels: tuple[str, ...] = ("station", "param")
                  ) -> GaugeMetricFamily:
            return GaugeMetricFamily(name, text, labels=list(labels))

        t, r = (gauge("calstation_accepted_translation_metres", "Latest accepted tx, ty, tz"),
                gauge("calstation_accepted_rotation_radians", "Latest accepted rx, ry, rz"))
        st, sr = (gauge("calstation_accepted_sigma_metres", "1 sigma of the latest accepted "
                        "translation"),
                  gauge("calstation_accepted_sigma_radians", "1 sigma of the latest accepted "
                        "rotation"))
        pe = gauge("calstation_predicted_error_metres", "Predicted reconstruction error (95 %) "
                   "of the latest accepted calibration over the work volume: all parameters, "
                   "and each one's sigma alone")
        run = gauge("calstation_accepted_run", "Run of the latest accepted calibration",
                    ("station",))
        when = gauge("calstation_accepted_timestamp_seconds", "When that run ended (Unix time)",
                     ("station",))
        for station in names:
            found = s.execute(select(Calibration, Run).join(Run, Calibration.run_id == Run.id)
                              .join(Station, Run.station_id == Station.id)
                              .where(Station.name == station, Calibration.accepted)
                              .order_by(Run.id.desc(), Calibration.id.desc()).limit(1)).first()
            if found is None:
                continue
            cal, done = found
            for p, v in cal.params().items():
                (t if p.startswith("t") else r).add_metric([station, p], v)
            for p, sigma in cal.sigmas().items():
                if sigma is not None and math.isfinite(sigma):
                    (st if p.startswith("t") else sr).add_metric([station, p], sigma)
            for p, v in self._predicted_of(cal, done).items():
                pe.add_metric([station, p], v)
            run.add_metric([station], float(done.id))
            end = done.finished_at or done.started_at
            if end is not None:  # SQLite gives naive UTC
                when.add_metric([station], (end if end.tzinfo else end.replace(tzinfo=dt.UTC))
                                .timestamp())
        yield from (t, r, st, sr, pe, run, when)

    def _predicted_of(self, cal: Calibration, run: Run) -> dict[str, float]:
        """The predicted error of ``cal`` (cached by its id): ``all`` and each parameter's."""
        if cal.id not in self._predicted:
            self._predicted[cal.id] = predicted_errors(cal, run)
        return self._predicted[cal.id]

    def _drift(self, s: Session, names: list[str]) -> Metric:
        from prometheus_client.core import GaugeMetricFamily

        family = GaugeMetricFamily("calstation_drift", "1 when the latest report flagged the "
                                   "parameter's drift beyond the recipe's limits",
                                   labels=["station", "param"])
        for station in names:
            step = s.scalars(select(Step).join(Run, Step.run_id == Run.id)
                             .join(Station, Run.station_id == Station.id)
                             .where(Station.name == station, Step.name == "report",
                                    Step.status == StepStatus.PASSED)
                             .order_by(Step.id.desc()).limit(1)).first()
            drift = ((step.result or {}).get("drift") if step is not None else None) or {}
            if step is None:
                continue
            flagged = set(drift.get("flagged") or [])
            for p in PARAMS:
                family.add_metric([station, p], 1.0 if p in flagged else 0.0)
        return family


def predicted_errors(cal: Calibration, run: Run) -> dict[str, float]:
    """The predicted reconstruction error (m) of a stored calibration over its recipe's work
    volume, at the accuracy budget's level: ``all`` as the station predicts it (covariance, σ,
    bias bound: :func:`calstation.fleet.compare.predicted`), and each parameter's uncertainty
    alone (:func:`calstation.engine.accuracy.contributions`); none when its recipe no longer
    loads."""
    from calstation.engine.accuracy import contributions
    from calstation.engine.frames import Extrinsics
    from calstation.errors import CalstationError
    from calstation.fleet.compare import predicted, work_volume
    from calstation.station.reprocess import run_recipe

    try:
        recipe = run_recipe(run).recipe
    except CalstationError:
        return {}
    diagnostics = cal.diagnostics or {}
    radius, height = work_volume(recipe)
    out = {"all": predicted(cal.result(), recipe)}
    sigma = {p: math.nan if v is None else float(v) for p, v in cal.sigmas().items()}
    out.update(contributions(Extrinsics.from_dict(cal.params()), sigma,
                             diagnostics.get("covariance"), radius=radius, height=height,
                             level=recipe.calibration.accuracy.level))
    return {k: float(v) for k, v in out.items() if v is not None and math.isfinite(v)}


class _Collector:
    """The prometheus_client collector of a :class:`StationMetrics`."""

    def __init__(self, metrics: StationMetrics) -> None:
        self.metrics = metrics

    def collect(self) -> Iterator[Metric]:
        return self.metrics.families()
