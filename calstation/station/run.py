"""The station state machine: one guided run of a recipe, step by step, into the database.

The workflow (DESIGN §1)::

    preflight → place_static_target → static_scan (+ initial calibration)
              → place_spin_target → spin_scan → fine_tune
              → place_qa_cube → cube_scan (+ cube check) → report

plus the ``failed`` state (a failed step; the operator retries it or gives up), ``aborted``
(the operator or a signal stopped the run) and ``done``. The states and transitions are a
``transitions`` machine; :meth:`Station.run` walks it top-down.

Every step attempt gets a ``step`` row when it starts (status ``running``) and is committed the
moment it ends, together with its recordings (``artifact``: path, size, sha256) and results
(``calibration``, ``cube_check``), in one transaction. A process killed mid-step therefore leaves
every earlier step intact, and :func:`resume_run` continues at the first step without a passed
attempt, re-using the recordings already taken. Recordings are written while scanning into the
run's folder ``<data dir>/runs/<run id>/`` (``static.mcap``, ``spin.mcap``, ``cube.mcap``), with
``report.json`` and ``calibration.yaml`` at the end.

The turntable is always stopped when the run ends, however it ends: ``stop()``, and
``emergency_stop()`` if that fails or the run was aborted.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import math
import os
import signal
import socket
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from rich.markup import escape
from sqlalchemy import select
from sqlalchemy.orm import Session
from transitions import Machine

from calstation import plugins
from calstation.clock import Clock, HostClock
from calstation.drivers import DriverContext
from calstation.engine.observability import check_sigma
from calstation.engine.result import CalibrationResult
from calstation.engine.spinscan import SpinScanBuilder, remember as remember_spin_scan
from calstation.errors import (
    CalstationError,
    DatabaseError,
    DriverError,
    ObservabilityError,
    StationError,
)
from calstation.plugins.recipe_checks import check_plugins
from calstation.recipes import LoadedRecipe, parse_recipe
from calstation.recordings.runfolder import RECORDING_OF, second_pass
from calstation.station.operator import Operator, publish
from calstation.storage.db import (
    Artifact,
    Calibration,
    CubeCheckRecord,
    Database,
    Run,
    Step,
    calstation_home,
    get_or_create_station,
    journal,
    utcnow,
)
from calstation.storage.report import previous_accepted, run_brief, run_summary

if TYPE_CHECKING:
    from calstation.engine.frames import Extrinsics

STEPS: tuple[str, ...] = (
    "preflight",
    "place_static_target",
    "static_scan",
    "place_spin_target",
    "spin_scan",
    "fine_tune",
    "place_qa_cube",
    "cube_scan",
    "report",
)
"""The steps of a run, in order (each is a state of the machine)."""

STATES: tuple[str, ...] = ("idle", *STEPS, "failed", "aborted", "done")

TARGETLESS_DROPS = ("place_static_target", "static_scan")
"""The steps a run without the L-target leaves out (``calibration.start: platter``)."""


def run_steps(recipe: Any) -> tuple[str, ...]:
    """The steps a run of ``recipe`` takes, in order: :data:`STEPS`, without the L-target's
    placement and static scan when the fine-tuning starts from the platter."""
    if recipe.calibration.start == "platter":
        return tuple(s for s in STEPS if s not in TARGETLESS_DROPS)
    return STEPS

SCAN_PLACEMENT: dict[str, str] = {
    "static_scan": "place_static_target",
    "spin_scan": "place_spin_target",
    "cube_scan": "place_qa_cube",
}
"""The placement step each scan needs (re-confirmed when a run resumes at the scan)."""

RETRY_FROM: dict[str, str] = {"fine_tune": "place_spin_target"}
"""Where a retry of a failed step starts: a fine-tuning refused for what its scan could see
is retried by re-placing the spin target and scanning again, not by re-reading the same scan."""

SECOND_PASS = second_pass("spin")
"""File stem and artifact kind of the spin scan's second pass (``second_pass_rpm``)."""
CUBE_SECOND_PASS = second_pass("cube")
"""… and of the cube scan's, measured together with the first (the time offset's check)."""

PREFLIGHT_LINES = 10
PREFLIGHT_SPIN_S = 0.5
PREFLIGHT_RAMP_S = 1.5


class AbortRun(CalstationError):
    """The operator (or a signal) aborted the run."""


@dataclass
class Drivers:
    """The run's three drivers and their context."""

    lidar: Any
    turntable: Any
    encoder: Any
    context: DriverContext

    @property
    def clock(self) -> Clock:
        """The clock the station waits on: the lidar's own (the simulator's), else the host's."""
        clock = getattr(self.lidar, "clock", None)
        return clock if clock is not None else self.context.clock


def file_sha256(path: Path) -> str:
    """sha256 (hex) of a file's bytes."""
    h = hashlib.sha256()
    with path.open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def checked_recording(
    art: Artifact | None, run_id: int, kind: str, error: type[CalstationError]
) -> Path:
    """The path of a stored ``kind`` recording of run ``run_id`` after checking that the file
    is there and unchanged (its stored sha256); ``error`` names what is wrong."""
    if art is None:
        raise error(f"run {run_id} has no {kind} recording stored")
    path = Path(art.path)
    if not path.is_file():
        raise error(f"the {kind} recording of run {run_id} is missing: {path}")
    digest = file_sha256(path)
    if digest != art.sha256:
        raise error(
            f"the {kind} recording {path} of run {run_id} changed since it was stored "
            f"(sha256 {digest[:12]}… now, {art.sha256[:12]}… stored)"
        )
    return path


def plain(value: Any) -> Any:
    """JSON-ready copy: numpy → Python, NaN/inf → None, tuples → lists, keys → str."""
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        f = float(value)
        return f if math.isfinite(f) else None
    if isinstance(value, Path):
        return str(value)
    return value


def _open_drivers(loaded: LoadedRecipe) -> Drivers:
    """Build the recipe's drivers through the plugin registry (``factory(settings, context)``)."""
    context = DriverContext(clock=HostClock(), recipe=loaded)
    st = loaded.recipe.station
    made: dict[str, Any] = {}
    try:
        for kind in ("lidar", "turntable", "encoder"):
            cfg = getattr(st, kind)
            made[kind] = plugins.driver_factory(kind, cfg.driver)(dict(cfg.settings), context)
    except BaseException:
        for driver in made.values():
            _quietly(driver.close)
        raise
    return Drivers(made["lidar"], made["turntable"], made["encoder"], context)


def _quietly(fn: Callable[[], Any]) -> None:
    with suppress(Exception):
        fn()


def _scene_truth(context: DriverContext) -> dict[str, Any] | None:
    """Ground truth of a simulated scene (an object in ``context.shared`` with ``truth_dict``)."""
    for obj in context.shared.values():
        truth_dict = getattr(obj, "truth_dict", None)
        if callable(truth_dict):
            truth: dict[str, Any] = plain(truth_dict())
            return truth
    return None


class Station:
    """Runs (or resumes) one run of a recipe on the station's drivers.

    ``run_id`` must exist in ``db``; ``loaded`` is its recipe; ``ui`` the operator. Call
    :meth:`run`, which returns the run's final status (``"passed"``, ``"failed"``,
    ``"aborted"``).
    """

    state: str
    trigger: Callable[..., bool]

    def __init__(self, db: Database, run_id: int, loaded: LoadedRecipe, ui: Operator) -> None:
        self.db = db
        self.run_id = run_id
        self.loaded = loaded
        self.recipe = loaded.recipe
        self.ui = ui
        self.failed_step: str | None = None
        self.drivers: Drivers | None = None
        with db.session() as s:
            run = s.get(Run, run_id)
            if run is None:
                raise StationError(f"no run {run_id} in the database")
            self.run_dir = Path(run.data_dir)
        db.log_path = self.run_dir / "database.log"  # SQL of database faults, never the console
        db.on_wait = lambda message: ui.warn(escape(message))
        self._partial: list[tuple[str, Path]] = []
        self._finished: list[tuple[str, Path]] = []  # a step's complete recordings so far
        self._scan_ended: float | None = None
        """when this process's last spin scan ended (monotonic s)"""
        self.steps = run_steps(self.recipe)
        self.machine = Machine(
            model=self, states=list(STATES), initial="idle", auto_transitions=False
        )
        self.machine.add_ordered_transitions(
            states=[*self.steps, "done"], trigger="advance", loop=False
        )
        for step in self.steps:
            self.machine.add_transition("begin", "idle", step, conditions=[self._is_first(step)])
            self.machine.add_transition(
                "retry", "failed", step, conditions=[self._is_failed(step)]
            )
        self.machine.add_transition("fail", list(self.steps), "failed")
        # a QA verdict (failed cube check) the operator does not retry still gets its report
        self.machine.add_transition("conclude", "failed", "report")
        self.machine.add_transition("abort", "*", "aborted")
        self._plan: list[str] = []

    # --- machine conditions --------------------------------------------------------------
    def _is_first(self, step: str) -> Callable[[], bool]:
        return lambda: bool(self._plan) and self._plan[0] == step

    def _is_failed(self, step: str) -> Callable[[], bool]:
        return lambda: self.failed_step == step

    # --- the run -----------------------------------------------------------------------------
    def run(self) -> str:
        """Execute the remaining steps; returns the final status. The motor is always stopped."""
        aborted = False
        self._final = "interrupted"
        try:
            self._plan = self._remaining_steps()
            self._mark_running()
            preload_engine()
            self._notify("run_started", run=self._brief())
            self.drivers = _open_drivers(self.loaded)
            self.trigger("begin")
            while True:
                step = self.state
                if not self._attempt(step):
                    if self.ui.on_failure(step, self._last_error, self._attempts(step)) == "retry":
                        self._restart_from(RETRY_FROM.get(step, step))
                        continue
                    if not self._verdict_failure:
                        return self._finish("failed", f"step {step} failed: {self._last_error}")
                    self._plan = ["report"]
                    self.trigger("conclude")
                    continue
                self._plan.pop(0)
                if not self._plan:
                    break
                # plans are suffixes of the run's steps
                if self._plan[0] != self._next_in_order(step, self.steps):
                    raise StationError(f"cannot go from {step} to {self._plan[0]}")
                self.trigger("advance")
            verdict = self._verdict()
            return self._finish(verdict, None if verdict == "passed" else self._failure_reason())
        except (AbortRun, KeyboardInterrupt) as exc:
            aborted = True
            self.trigger("abort")
            return self._finish("aborted", str(exc) or "aborted by the operator")
        except DatabaseError as exc:
            # the database failed (a lock outlasted the wait, or it went away): what could not be
            # stored is journalled; the run stops as interrupted, to be resumed
            aborted = True
            self.ui.warn(escape(str(exc)))
            return self._finish("interrupted", str(exc))
        except BaseException as exc:
            # an unexpected error (not a step failure): the run is failed, never left running
            self._finish("failed", f"{type(exc).__name__}: {exc}")
            raise
        finally:
            self._record_motor_stop(self._stop_hardware(emergency=aborted))

    def _restart_from(self, step: str) -> None:
        """Leave the failed state for ``step`` (the failed step or an earlier one) and plan
        every step from there again."""
        self.failed_step = step
        self._plan = list(self.steps[self.steps.index(step) :])
        self.trigger("retry")

    @staticmethod
    def _next_in_order(step: str, steps: tuple[str, ...] = STEPS) -> str:
        i = steps.index(step)
        return steps[i + 1] if i + 1 < len(steps) else "done"

    def _remaining_steps(self) -> list[str]:
        """Steps still to do: from the first without a passed attempt; a scan's placement first."""
        with self.db.session() as s:
            passed = set(
                s.scalars(
                    select(Step.name).where(Step.run_id == self.run_id, Step.status == "passed")
                )
            )
        todo = [step for step in self.steps if step not in passed]
        if not todo:
            return ["report"]
        first = self.steps.index(todo[0])
        plan = list(self.steps[first:])
        placement = SCAN_PLACEMENT.get(plan[0])
        if placement is not None and placement in passed:
            plan.insert(0, placement)
        return plan

    def _attempt(self, step: str) -> bool:
        """One attempt at ``step``: row, work, commit. False (with ``_last_error``) on failure.

        A step whose outcome is a failed QA verdict (``outcome.failure``) keeps its recordings and
        results and fails like any step, so the operator may retry it.
        """
        step_id, attempt = self._begin_step(step)
        self._verdict_failure = False
        self._partial = []
        self._finished = []
        try:
            publish(self.ui, "step_started", step=step, attempt=attempt)
            handler = getattr(self, f"_step_{step}")
            outcome: StepOutcome = handler(step_id)
        except (AbortRun, KeyboardInterrupt) as exc:
            with suppress(DatabaseError):  # journalled if not stored; the abort goes on
                self._end_step(step_id, "aborted", {}, str(exc) or "aborted by the operator",
                               StepOutcome({}))
            raise
        except DatabaseError:
            raise
        except Exception as exc:  # a step failure, whatever raised it, is the operator's call
            message = str(exc) if isinstance(exc, CalstationError) else (
                f"{type(exc).__name__}: {exc}"
            )
            self._last_error = message
            failed = {"error": message, **plain(getattr(exc, "details", {}))}
            self._end_step(step_id, "failed", failed, message, StepOutcome({}))
            publish(self.ui, "step_finished", step=step, attempt=attempt, status="failed",
                    result={"error": message}, error=message)
            self._notify("step_finished", run=self._brief(), step=step, status="failed",
                         result={"error": message})
            self.failed_step = step
            self.trigger("fail")
            return False
        if outcome.failure is not None:
            self._last_error = outcome.failure
            self._verdict_failure = True
            self._end_step(step_id, "failed", outcome.result, outcome.failure, outcome)
            self._notify("step_finished", run=self._brief(), step=step, status="failed",
                         result=outcome.result)
            self.failed_step = step
            self.trigger("fail")
            return False
        self._end_step(step_id, "passed", outcome.result, None, outcome)
        publish(self.ui, "step_finished", step=step, attempt=attempt, status="passed",
                result=plain(outcome.result), error=None)
        self._notify("step_finished", run=self._brief(), step=step, status="passed",
                     result=outcome.result)
        return True

    _last_error: str = ""
    _verdict_failure: bool = False
    _drift_failure: str | None = None

    # --- the steps ---------------------------------------------------------------------------
    def _step_preflight(self, step_id: int) -> StepOutcome:
        """The lidar returns data, the platter turns, the encoder counts in the configured
        direction."""
        d = self._drivers()
        info = d.lidar.info()
        lines = valid = points = 0
        with self.ui.progress("preflight: lidar") as progress:
            d.lidar.start()
            try:
                for line in d.lidar.lines():
                    lines += 1
                    points += len(line)
                    valid += int(np.count_nonzero(line.valid))
                    progress("reading lines", lines / PREFLIGHT_LINES)
                    if lines >= PREFLIGHT_LINES:
                        break
            finally:
                d.lidar.stop()
        if lines < PREFLIGHT_LINES or valid == 0:
            raise DriverError(
                f"preflight: the lidar returned {lines} lines with {valid} valid points; "
                f"expected {PREFLIGHT_LINES} lines with returns"
            )
        rpm = self.recipe.steps.spin_scan.rpm
        enc = self.recipe.station.encoder
        clock = d.clock
        with self.ui.progress("preflight: turntable and encoder") as progress:
            d.turntable.enable()
            try:
                d.turntable.spin(rpm)
                clock.sleep(PREFLIGHT_RAMP_S)
                progress("spinning up", 0.5)
                first = d.encoder.read()
                clock.sleep(PREFLIGHT_SPIN_S)
                last = d.encoder.read()
                status = d.turntable.status()
            finally:
                d.turntable.stop()
            progress("stopped", 1.0)
        if status.faults:
            raise DriverError(f"preflight: turntable faults: {', '.join(status.faults)}")
        counts = last.count - first.count
        cpr = d.encoder.counts_per_revolution
        dt_s = (last.timestamp_ns - first.timestamp_ns) * 1e-9
        expected = rpm / 60.0 * dt_s * cpr * enc.direction
        if counts == 0:
            raise DriverError(
                f"preflight: the encoder did not count while the platter was commanded to "
                f"{rpm:g} rpm for {dt_s:.2f} s (expected about {abs(expected):.0f} counts): is the "
                "platter turning and the encoder connected?"
            )
        if np.sign(counts) != np.sign(expected):
            raise DriverError(
                f"preflight: the encoder counted {counts} while the platter turned at {rpm:g} rpm; "
                f"with station.encoder.direction = {enc.direction} the counts should have the "
                f"opposite sign: fix the direction in the recipe (or the encoder wiring)"
            )
        if abs(counts) < 0.5 * abs(expected):
            raise DriverError(
                f"preflight: the encoder counted {counts} in {dt_s:.2f} s, expected about "
                f"{expected:.0f} at {rpm:g} rpm: check counts per revolution (ppr) and the drive"
            )
        return StepOutcome(
            {
                "lidar": plain(info.as_dict()),
                "unit_serial": self._record_serial(str(info.serial or "")),
                "lines": lines,
                "valid_fraction": valid / max(points, 1),
                "encoder_counts": int(counts),
                "expected_counts": float(expected),
                "counts_per_revolution": int(cpr),
                "rpm": rpm,
            }
        )

    def _record_serial(self, reported: str) -> str | None:
        """The run's unit serial: the operator's, else the lidar's (stored with the run)."""
        with self.db.session() as s:
            run = s.get(Run, self.run_id)
            assert run is not None
            if run.unit_serial and reported and reported != run.unit_serial:
                self.ui.warn(f"the lidar reports serial {reported!r}, the operator gave "
                             f"{run.unit_serial!r}; the operator's is kept")
            elif not run.unit_serial and reported:
                run.unit_serial = reported
            return run.unit_serial

    def _place(self, fixture: str) -> StepOutcome:
        geometry = getattr(self.recipe.fixtures, fixture)
        description = f"{geometry.kind}"
        offset = getattr(geometry, "offset", None)
        if offset is not None:
            description += (
                f", centre {math.hypot(*offset) * 1e3:.0f} mm from the axis "
                f"(offset y {offset[0] * 1e3:+.0f} mm, z {offset[1] * 1e3:+.0f} mm)"
            )
        if not self.ui.confirm_fixture(fixture, description):
            raise AbortRun(f"aborted by the operator while placing the {fixture}")
        plugins.fixture_placed(self._drivers().context, fixture, geometry)
        return StepOutcome({"fixture": fixture, "kind": geometry.kind,
                            "unattended": self.ui.unattended})

    def _step_place_static_target(self, step_id: int) -> StepOutcome:
        return self._place("static_target")

    def _step_place_spin_target(self, step_id: int) -> StepOutcome:
        return self._place(self._strategy().fixture)

    def _step_place_qa_cube(self, step_id: int) -> StepOutcome:
        return self._place("qa_cube")

    def _step_static_scan(self, step_id: int) -> StepOutcome:
        from calstation.engine.initial import initial_calibration
        from calstation.recordings.reader import read_recording

        d = self._drivers()
        lines = self.recipe.steps.static_scan.lines
        path = self._record("static_scan", step_id, lambda w, p: _acquire_static(d, w, lines, p))
        recording = read_recording(path)
        with self.ui.progress("initial calibration") as progress:
            progress("fitting the L-target", 0.1)
            result = initial_calibration(
                recording, self.recipe.fixtures.static_target, self.recipe.calibration.initial
            )
        self.ui.info(f"  initial: {_fmt_h(result.H.as_dict())}")
        return StepOutcome(
            {"recording": str(path), "lines": lines, "H": result.H.as_dict()},
            artifacts=[("static", path)],
            calibration=("initial", result),
        )

    def _step_spin_scan(self, step_id: int) -> StepOutcome:
        d = self._drivers()
        cfg = self.recipe.steps.spin_scan
        path = self._record("spin_scan", step_id, lambda w, p: _acquire_spin(d, w, cfg, p))
        result: dict[str, Any] = {"recording": str(path), "rpm": cfg.rpm,
                                  "revolutions": cfg.revolutions,
                                  "fixture": self._strategy().fixture}
        artifacts = [("spin", path)]
        # the same turns again at another speed: the fine-tune estimates the lidar–encoder time
        # offset from the two
        path2 = self._second_pass("spin_scan", step_id, path, SECOND_PASS)
        if path2 is not None:
            result.update(second_pass={"recording": str(path2), "rpm": cfg.second_pass_rpm})
            artifacts.append((SECOND_PASS, path2))
        return StepOutcome(result, artifacts=artifacts)

    def _second_pass(self, step: str, step_id: int, first: Path, stem: str) -> Path | None:
        """The scan step's second pass (``second_pass_rpm``) recorded as ``stem``; None when
        the recipe asks for none. A fault in it keeps the ``first`` pass (``_finished``)."""
        second = getattr(self.recipe.steps, step).second_pass()
        if second is None:
            return None
        d = self._drivers()
        self._finished.append((RECORDING_OF[step], first))
        return self._record(step, step_id, lambda w, p: _acquire_spin(d, w, second, p), stem)

    def _step_fine_tune(self, step_id: int) -> StepOutcome:
        from calstation.engine.frames import Extrinsics
        from calstation.recordings.reader import read_recording

        strategy = self._strategy()
        recording = read_recording(self._artifact_path("spin"))
        from calstation.plugins.cost_strategies import run_strategy

        with self.ui.progress(f"fine-tuning ({strategy.name})") as progress:
            if self.recipe.calibration.start == "platter":
                from calstation.plugins.cost_strategies import fine_tune_targetless

                result, warnings, first = fine_tune_targetless(
                    strategy, recording, self.recipe, progress)
                self.ui.info(f"  start from the platter: {_fmt_h(first.H.as_dict())} "
                             f"(chord {first.diagnostics['chord']})")
            else:
                start = self._stored_calibration("initial")
                result, warnings = run_strategy(
                    strategy, recording, Extrinsics.from_dict(start.params()), self.recipe,
                    progress
                )
            if self.recipe.steps.spin_scan.second_pass_rpm is not None:
                result = self._time_offset(result, recording, progress, "")
        for warning in warnings:
            self.ui.warn(warning)
        self.ui.info(f"  {strategy.name}: {_fmt_h(result.H.as_dict())}")
        after_scan = None
        if self._scan_ended is not None:
            # the spin scan was taken by this process: how long the operator waited for H
            after_scan = time.monotonic() - self._scan_ended
            self.ui.info(f"  result ready {after_scan:.1f} s after the scan ended")
        # a spin-target strategy's ry is gated after the cube scan has added its faces to it
        later = ("ry",) if strategy.fixture == "spin_target" else ()
        try:
            check_sigma(result, self.recipe.calibration.max_sigma, strategy.fixture, later)
        except ObservabilityError as exc:
            # the refused estimate is kept with the failed step: nothing computed is lost
            exc.details = {"refused": {"H": result.H.as_dict(), "sigma": result.sigma}}
            raise
        return StepOutcome(
            {"strategy": strategy.name, "H": result.H.as_dict(), "cost": plain(result.cost),
             "iterations": result.iterations, "after_scan_s": after_scan,
             "prepared_while_scanning": "scan_during_scan" in result.timings},
            calibration=("fine", result),
        )

    def _step_cube_scan(self, step_id: int) -> StepOutcome:
        from calstation.recordings.reader import read_recording

        d = self._drivers()
        cfg = self.recipe.steps.cube_scan
        if self.failed_step == "cube_scan":  # the operator's retry: re-seat the cube, rescan
            self._place("qa_cube")
        path = self._record("cube_scan", step_id, lambda w, p: _acquire_spin(d, w, cfg, p))
        artifacts = [("cube", path)]
        path2 = self._second_pass("cube_scan", step_id, path, CUBE_SECOND_PASS)
        if path2 is not None:
            artifacts.append((CUBE_SECOND_PASS, path2))
        fine = self._stored_calibration("fine")
        recording = read_recording(path)
        with self.ui.progress("cube check") as progress:
            progress("measuring the cube", 0.1)
            check, joint, ry_failure = self._check_cube_joint(recording, fine, progress)
            if path2 is not None:
                progress("measuring the cube from both passes", 0.8)
                check = self._check_cube_passes(recording, read_recording(path2), joint, fine)
        cube = plain(
            {
                "obb_edges": check.obb_edges,
                "obb_error": check.obb_error,
                "face_edges": check.face_edges,
                "edge_error": check.edge_error,
                "flatness_rms": check.flatness_rms,
                "perpendicularity_deg": check.perpendicularity_deg,
                "twist_deg": check.twist_deg,
                "twist_sigma_deg": check.twist_sigma_deg,
                "passed": check.passed,
                "failures": check.failures,
            }
        )
        self.ui.info(
            f"  cube: edge error {check.edge_error * 1000:.2f} mm, OBB error "
            f"{check.obb_error * 1000:.2f} mm, side-face twist {check.twist_deg:+.3f}° "
            f"(±{check.twist_sigma_deg:.3f}°) → {'pass' if check.passed else 'FAIL'}"
        )
        failures = list(check.failures) + ([ry_failure] if ry_failure else [])
        if ry_failure:
            cube["passed"] = False
            cube["failures"] = failures
        return StepOutcome(
            {"recording": str(path), "passed": not failures,
             "edge_error": cube["edge_error"], "obb_error": cube["obb_error"],
             "points": int(getattr(check, "points", 0)),
             "joint_ry": None if joint is None else plain(joint.diagnostics["joint"])},
            artifacts=artifacts,
            calibration=None if joint is None else ("fine", joint),
            cube=(None if joint is not None else fine.id, cube),
            failure=None if not failures else "cube check failed: " + "; ".join(failures),
        )

    def _check_cube_passes(
        self, first: Any, second: Any, joint: CalibrationResult | None, fine: Calibration
    ) -> Any:
        """The cube check on both cube passes together, under the final H and the estimated
        lidar–encoder time offset (the configured latency when none was estimated)."""
        from calstation.engine.cube import check_cube_passes
        from calstation.engine.frames import Extrinsics

        H = joint.H if joint is not None else Extrinsics.from_dict(fine.params())
        latency = joint.encoder_latency_s if joint is not None else fine.encoder_latency_s
        self.ui.info(
            "  cube measured from both passes, "
            + ("with the configured encoder latency" if latency is None
               else f"with the estimated encoder latency {latency * 1e3:.3f} ms")
        )
        return check_cube_passes(
            [first, second], H, self.recipe.fixtures.qa_cube, self.recipe.qa,
            encoder_latency_s=latency, platter_radius=self.recipe.fixtures.platter.radius,
        )

    def _check_cube_joint(
        self, recording: Any, fine: Calibration, progress: Any
    ) -> tuple[Any, CalibrationResult | None, str | None]:
        """The cube check, with ry combined from the spin target and the cube's side faces.

        The twist of the side faces under the fine-tuned H measures ry; when the fine-tuning
        came from the spin target the two are combined (:mod:`calstation.engine.joint`) and the cube
        is
        measured again with the combined H. Returns (the check, the combined calibration or
        None, a failure when ry stays undetermined or the two disagree).
        """
        from calstation.engine.cube import check_cube
        from calstation.engine.frames import Extrinsics
        from calstation.engine.joint import joint_summary
        from calstation.plugins.cost_strategies import fine_tune_with_cube

        H = Extrinsics.from_dict(fine.params())
        if self._strategy().fixture != "spin_target":
            check = check_cube(recording, H, self.recipe.fixtures.qa_cube, self.recipe.qa,
                               platter_radius=self.recipe.fixtures.platter.radius)
            return check, None, None
        diagnostics = fine.diagnostics or {}
        stored = CalibrationResult(
            H=H,
            sigma={p: math.nan if v is None else float(v) for p, v in fine.sigmas().items()},
            cost=float(fine.cost) if fine.cost is not None else math.nan,
            iterations=int(fine.iterations or 0),
            strategy=fine.strategy,
            timings={},
            diagnostics={"gauge": diagnostics.get("gauge"),
                         "covariance": diagnostics.get("covariance"),
                         **({"time_offset": diagnostics["time_offset"]}
                            if "time_offset" in diagnostics else {})},
            encoder_latency_s=fine.encoder_latency_s,
            sigma_encoder_latency_s=fine.sigma_encoder_latency_s,
        )
        result, check, failure = fine_tune_with_cube(stored, recording, self.recipe, progress)
        if result is stored:
            return check, None, failure
        result.diagnostics["from_calibration"] = fine.id
        self.ui.info(f"  {joint_summary(result)}")
        if result.encoder_latency_s is not None:
            # estimated again under the H whose ry the cube changed: the estimate moves a
            # little with ry (~0.08 ms per 0.1°, docs/algorithms.md)
            from calstation.recordings.reader import read_recording

            result = self._time_offset(result, read_recording(self._artifact_path("spin")),
                                       progress, " under the combined H")
        return check, result, failure

    def _time_offset(
        self, result: CalibrationResult, first: Any, progress: Any, under: str
    ) -> CalibrationResult:
        """``result`` with the lidar–encoder time offset from the spin scan's ``first`` pass and
        its stored second pass; ``under`` says which H, for the operator."""
        from calstation.engine.timeoffset import with_time_offset
        from calstation.recordings.reader import read_recording

        out = with_time_offset(
            result, first, read_recording(self._artifact_path(SECOND_PASS)),
            self.recipe.fixtures.platter.radius, progress,
        )
        self.ui.info(
            f"  lidar–encoder time offset{under}: {(out.encoder_latency_s or 0.0) * 1e3:.3f} ± "
            f"{(out.sigma_encoder_latency_s or math.nan) * 1e3:.3f} ms"
        )
        return out

    def _step_report(self, step_id: int) -> StepOutcome:
        """report.json and calibration.yaml, carrying the verdict the database will hold.

        The verdict, the accepted calibration and both files are stored in the step's one
        transaction; the files are written under temporary names and moved into place only once
        that transaction is committed, so report.json never claims a verdict the database does
        not hold."""
        from calstation.storage.report import export_calibration

        verdict = self._verdict_from_db()
        with self.db.session("preparing the report") as s:
            run = s.get(Run, self.run_id)
            assert run is not None
            fine = [c for c in run.calibrations if c.stage == "fine"]
            prev = previous_accepted(s, run) if fine else None
            drift = _drift(fine[-1], prev, self.recipe.qa) if prev is not None else None
            if drift is not None and drift["flagged"] and self.recipe.qa.drift_fails \
                    and verdict == "passed":
                verdict = "failed"
                self._drift_failure = (
                    f"calibration drifted beyond the recipe's limits since run "
                    f"{drift['previous_run']}: {', '.join(drift['flagged'])} "
                    "(qa.drift_fails is set)"
                )
            accept = fine[-1].id if fine and verdict == "passed" else None
            run.status = verdict  # as the step's transaction will store it; not committed here
            for c in run.calibrations:
                c.accepted = c.id == accept
            summary = run_summary(run)
            text = export_calibration(run, "yaml") if fine else None
            s.rollback()
        staged: list[tuple[str, Path, Path]] = []
        report = self.run_dir / "report.json"
        staged.append(("report", _write_staged(report, json.dumps(summary, indent=2) + "\n"),
                       report))
        if text is not None:
            calib = self.run_dir / "calibration.yaml"
            staged.append(("calibration", _write_staged(calib, text), calib))
        result: dict[str, Any] = {"verdict": verdict, "report": str(report)}
        if drift is not None:
            result["drift"] = drift
            if drift["flagged"]:
                self.ui.warn(
                    "calibration drifted beyond the recipe's limits since run "
                    f"{drift['previous_run']}: {', '.join(drift['flagged'])}"
                )
        return StepOutcome(result, staged=staged, run_status=verdict, accept_calibration=accept)

    # --- helpers -------------------------------------------------------------------------
    def _drivers(self) -> Drivers:
        if self.drivers is None:
            raise StationError("the drivers are not open")
        return self.drivers

    def _strategy(self) -> Any:
        return plugins.strategy(self.recipe.calibration.strategy)

    def _record(
        self,
        step: str,
        step_id: int,
        acquire: Callable[[Any, Callable[[str, float], None]], None],
        stem: str | None = None,
    ) -> Path:
        """Write the step's recording while acquiring; returns its path. ``stem`` names the file
        (and the artifact) when a step takes a second recording, default the recording's kind."""
        from calstation.recordings.writer import RecordingWriter

        d = self._drivers()
        kind = RECORDING_OF[step]
        stem = stem or kind
        path = self.run_dir / f"{stem}.mcap"
        if path.exists():  # a previous attempt's file (failed or killed): keep it aside
            n = 1
            while (aside := path.with_name(f"{stem}.attempt{n}.mcap")).exists():
                n += 1
            path.rename(aside)
            with self.db.session("moving a partial recording aside") as s:
                for art in s.scalars(select(Artifact).where(
                        Artifact.run_id == self.run_id, Artifact.path == str(path))):
                    art.path = str(aside)
        enc = self.recipe.station.encoder
        metadata: dict[str, dict[str, Any]] = {
            "run": {"id": self.run_id, "step": step, "step_id": step_id}
        }
        truth = _scene_truth(d.context)
        if truth is not None:
            metadata["truth"] = truth
        calibration, source = self._latest_calibration()
        self._partial = [(stem, path)]  # until the recording is complete
        with (
            RecordingWriter(
                path,
                kind=kind,
                lidar_info=d.lidar.info(),
                counts_per_revolution=d.encoder.counts_per_revolution,
                encoder_direction=enc.direction,
                encoder_latency_s=enc.latency_s,
                station_id=self.recipe.station.id,
                recipe=self.loaded,
                metadata=metadata,
                calibration=calibration,
                calibration_source=source,
                clock=d.clock,  # the drivers' time base: one clock in the file
            ) as writer,
            self.ui.progress(f"{stem} scan") as progress,
        ):
            # a spin scan's per-line work for the fine-tuning and the cube check is done as
            # the lines arrive
            builder = (
                SpinScanBuilder(
                    d.encoder.counts_per_revolution, enc.direction, enc.latency_s
                )
                if kind in ("spin", "cube") and stem == kind
                else None
            )
            acquire(_PublishingWriter(writer, self.ui, kind, builder), progress)
        self._partial = []
        if kind == "spin":
            self._scan_ended = time.monotonic()
        if builder is not None:
            remember_spin_scan(path, builder)
        return path

    def _attempts(self, step: str) -> int:
        with self.db.session() as s:
            return len(
                s.scalars(select(Step.id).where(Step.run_id == self.run_id, Step.name == step))
                .all()
            )

    def _begin_step(self, step: str) -> tuple[int, int]:
        with self.db.session() as s:
            attempt = self._attempts(step) + 1
            row = Step(run_id=self.run_id, name=step, attempt=attempt, status="running")
            s.add(row)
            s.flush()
            return row.id, attempt

    def _end_step(
        self,
        step_id: int,
        status: str,
        result: dict[str, Any],
        error: str | None,
        outcome: StepOutcome,
    ) -> None:
        """Commit the step's end, its artifacts and results in one transaction.

        Recordings cut short (``_partial``) are stored with the status ``partial``, those a step
        finished before it failed (``_finished``) as ``complete``. If the
        database fails, the change is journalled in the run folder and ResultJournalled raised
        (:func:`calstation.storage.db.journal.store`)."""
        files = [(kind, path, path, "complete") for kind, path in outcome.artifacts]
        files += [(kind, final, tmp, "complete") for kind, tmp, final in outcome.staged]
        files += [(kind, path, path, "partial") for kind, path in self._partial if path.exists()]
        files += [(kind, path, path, "complete") for kind, path in self._finished
                  if (kind, path) not in outcome.artifacts and path.exists()]
        self._partial = []
        self._finished = []
        artifacts = [
            {"kind": kind, "path": str(final), "size_bytes": source.stat().st_size,
             "sha256": file_sha256(source), "status": state}
            for kind, final, source, state in files
        ]
        calibration = cube = None
        if outcome.calibration is not None:
            stage, res = outcome.calibration
            calibration = journal.columns(_calibration_row(self.run_id, step_id, stage, res))
        if outcome.cube is not None:
            cal_id, check = outcome.cube
            cube = journal.columns(_cube_row(self.run_id, step_id, cal_id, check))
        change = journal.step_end(
            self.run_id, step_id, status, plain(result), error, artifacts=artifacts,
            calibration=calibration, cube=cube, run_status=outcome.run_status,
            accept_calibration=outcome.accept_calibration,
            staged=[(tmp, final) for _, tmp, final in outcome.staged],
        )
        journal.store(self.db, self.run_dir, change, f"the end of step {step_id}")

    def _mark_running(self) -> None:
        with self.db.session() as s:
            for row in s.scalars(
                select(Step).where(Step.run_id == self.run_id, Step.status == "running")
            ):
                row.status = "interrupted"
                row.error = "the process ended during this step"
                row.finished_at = row.finished_at or utcnow()
            run = s.get(Run, self.run_id)
            assert run is not None
            run.status = "running"
            run.finished_at = None
            run.error = None
            run.host = socket.gethostname()
            run.pid = os.getpid()

    def _latest_calibration(self) -> tuple[Extrinsics | None, str]:
        """The run's newest calibration (fine before initial) and its stage, for a recording's
        static transform and cloud; (None, "") before the first one."""
        from calstation.engine.frames import Extrinsics

        for stage in ("fine", "initial"):
            with suppress(StationError):
                cal = self._stored_calibration(stage)
                return Extrinsics.from_dict(cal.params()), stage
        return None, ""

    def _stored_calibration(self, stage: str) -> Calibration:
        with self.db.session() as s:
            cal = s.scalars(
                select(Calibration)
                .where(Calibration.run_id == self.run_id, Calibration.stage == stage)
                .order_by(Calibration.id.desc())
            ).first()
        if cal is None:
            raise StationError(f"run {self.run_id} has no {stage} calibration stored")
        return cal

    def _artifact_path(self, kind: str) -> Path:
        with self.db.session() as s:
            art = s.scalars(
                select(Artifact)
                .where(Artifact.run_id == self.run_id, Artifact.kind == kind,
                       Artifact.status == "complete")
                .order_by(Artifact.id.desc())
            ).first()
        return checked_recording(art, self.run_id, kind, StationError)

    def _verdict_from_db(self) -> str:
        with self.db.session() as s:
            check = s.scalars(
                select(CubeCheckRecord)
                .where(CubeCheckRecord.run_id == self.run_id)
                .order_by(CubeCheckRecord.id.desc())
            ).first()
        return "passed" if check is not None and check.passed else "failed"

    def _verdict(self) -> str:
        return "failed" if self._drift_failure else self._verdict_from_db()

    def _failure_reason(self) -> str | None:
        """Why a run that went through every step failed: drift, else the cube check."""
        if self._drift_failure:
            return self._drift_failure
        with self.db.session() as s:
            check = s.scalars(
                select(CubeCheckRecord)
                .where(CubeCheckRecord.run_id == self.run_id)
                .order_by(CubeCheckRecord.id.desc())
            ).first()
            if check is None or check.passed:
                return None
            return "cube check failed: " + "; ".join(str(f) for f in check.failures)

    def _brief(self) -> dict[str, Any]:
        with self.db.session() as s:
            run = s.get(Run, self.run_id)
            assert run is not None
            return run_brief(run)

    def _finish(self, status: str, error: str | None) -> str:
        """Store the run's end (journalled if the database fails: never raises for that)."""
        self._final = status
        try:
            journal.store(self.db, self.run_dir, journal.run_end(self.run_id, status, error),
                          f"the end of run {self.run_id}")
            with self.db.session("reading the run", read_only=True) as s:
                run = s.get(Run, self.run_id)
                assert run is not None
                summary = run_summary(run)
        except DatabaseError as exc:
            self.ui.warn(escape(str(exc)))
            return status
        self._write_report_html()
        self._notify("run_finished", run=run_brief_from(summary), status=status, summary=summary)
        self.ui.summary(summary)
        return status

    def _write_report_html(self) -> None:
        """``report.html`` in the run folder, whatever the outcome; a failure is a warning."""
        from calstation.storage.report_html import write_run_report

        try:
            write_run_report(self.db, self.run_id)
        except Exception as exc:
            self.ui.warn(f"could not write report.html: {type(exc).__name__}: {exc}")

    def _notify(self, hook: str, **kwargs: Any) -> None:
        """Call an observer hook; an observer's exception is a warning, never a failed run."""
        try:
            getattr(plugins, hook)(**kwargs)
        except Exception as exc:
            self.ui.warn(f"a plugin's {hook} observer failed: {type(exc).__name__}: {exc}")

    def _stop_hardware(self, emergency: bool) -> dict[str, Any] | None:
        """Stop the turntable (emergency stop first after an abort or fault; emergency stop if
        ``stop()`` fails), close the drivers; how it went, or None if no driver was open."""
        d = self.drivers
        if d is None:
            return None
        done: list[str] = []
        errors: list[str] = []

        def attempt(name: str) -> bool:
            try:
                getattr(d.turntable, name)()
            except Exception as exc:
                errors.append(f"{name} failed: {type(exc).__name__}: {exc}")
                return False
            done.append(name)
            return True

        if emergency:
            attempt("emergency_stop")
        if not attempt("stop") and "emergency_stop" not in done:
            attempt("emergency_stop")
        for driver in (d.lidar, d.turntable, d.encoder):
            _quietly(driver.close)
        self.drivers = None
        return {"how": " then ".join(done) or "not stopped", "ok": bool(done),
                "reason": self._final, "errors": errors, "at": utcnow().isoformat()}

    def _record_motor_stop(self, record: dict[str, Any] | None) -> None:
        """Say on the console and in the database (``run.motor_stop``) how the motor stopped."""
        if record is None:
            return
        text = f"motor stopped by {record['how']} (run {record['reason']})"
        if record["ok"]:
            self.ui.info(text)
        else:
            self.ui.warn(f"the motor could not be stopped: {'; '.join(record['errors'])}")
        with suppress(DatabaseError):  # journalled when the database is unavailable
            journal.store(self.db, self.run_dir, journal.motor_stop(self.run_id, record),
                          "how the motor stopped")


class _PublishingWriter:
    """A recording writer that also publishes each lidar line to the operator (live preview)
    and, for a spin scan, hands it to the fine-tuning's preparation (``builder``)."""

    def __init__(self, inner: Any, ui: Operator, kind: str, builder: Any = None) -> None:
        self._inner, self._ui, self._kind, self._builder = inner, ui, kind, builder

    def write_line(self, line: Any) -> None:
        self._inner.write_line(line)
        if self._builder is not None:
            self._builder.write_line(line)
        publish(self._ui, "lidar_line", kind=self._kind, line=line)

    def write_encoder(self, samples: Any) -> None:
        batch = list(samples)
        self._inner.write_encoder(batch)
        if self._builder is not None:
            self._builder.write_encoder(batch)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)


@dataclass
class StepOutcome:
    """What a step produced: its JSON result, files, and database results to store with it."""

    result: dict[str, Any]
    artifacts: list[tuple[str, Path]] = field(default_factory=list)
    calibration: tuple[str, Any] | None = None
    cube: tuple[int | None, dict[str, Any]] | None = None
    """(calibration id, check); None as the id: the calibration this step stores"""
    failure: str | None = None
    """A failed QA verdict: the step fails (the operator may retry) but keeps what it stored."""
    staged: list[tuple[str, Path, Path]] = field(default_factory=list)
    """(kind, temporary file, final path): moved into place once the step is stored."""
    run_status: str | None = None
    """The run's verdict, stored with the step (the report step)."""
    accept_calibration: int | None = None
    """The calibration the verdict accepts (the report step of a passed run)."""


def _write_staged(final: Path, text: str) -> Path:
    """Write ``text`` beside ``final`` under a temporary name (flushed to disk); its path."""
    tmp = final.with_name(final.name + ".pending")
    with tmp.open("w", encoding="utf-8") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    return tmp


def run_brief_from(summary: dict[str, Any]) -> dict[str, Any]:
    """The brief part of a summary (without steps and results)."""
    return {k: v for k, v in summary.items()
            if k not in ("steps", "calibrations", "cube_check", "artifacts")}


def _acquire_static(d: Drivers, writer: Any, lines: int, progress: Any) -> None:
    from calstation.station.acquisition import acquire_static

    acquire_static(d.lidar, d.encoder, writer, lines=lines, progress=progress)


def _acquire_spin(d: Drivers, writer: Any, cfg: Any, progress: Any) -> None:
    from calstation.station.acquisition import acquire_spin

    acquire_spin(
        d.lidar, d.turntable, d.encoder, writer, rpm=cfg.rpm, revolutions=cfg.revolutions,
        settle_s=cfg.settle_s, clock=d.clock, progress=progress,
    )


def _calibration_row(run_id: int, step_id: int | None, stage: str, res: Any) -> Calibration:
    H = res.H.as_dict()
    sigma = {k: plain(float(v)) for k, v in res.sigma.items()}
    diagnostics = plain(dict(res.diagnostics))
    if res.timings:
        diagnostics["timings"] = plain(dict(res.timings))
    return Calibration(
        run_id=run_id,
        step_id=step_id,
        stage=stage,
        strategy=res.strategy,
        **H,
        **{f"sigma_{p}": sigma.get(p) for p in H},
        cost=plain(float(res.cost)),
        iterations=int(res.iterations),
        encoder_latency_s=plain(getattr(res, "encoder_latency_s", None)),
        sigma_encoder_latency_s=plain(getattr(res, "sigma_encoder_latency_s", None)),
        accepted=False,
        diagnostics=diagnostics,
    )


def _cube_row(
    run_id: int, step_id: int, cal_id: int | None, c: dict[str, Any]
) -> CubeCheckRecord:
    def number(key: str) -> float:
        v = c.get(key)
        return float("nan") if v is None else float(v)

    return CubeCheckRecord(
        run_id=run_id,
        step_id=step_id,
        calibration_id=cal_id,
        obb_edges=list(c.get("obb_edges") or []),
        obb_error=number("obb_error"),
        face_edges=list(c.get("face_edges") or []),
        edge_error=number("edge_error"),
        flatness_rms=number("flatness_rms"),
        perpendicularity_deg=number("perpendicularity_deg"),
        twist_deg=number("twist_deg"),
        twist_sigma_deg=number("twist_sigma_deg"),
        passed=bool(c.get("passed")),
        failures=[str(f) for f in c.get("failures") or []],
    )


def _drift(current: Calibration, previous: Calibration, qa: Any) -> dict[str, Any]:
    """Differences to the previous accepted calibration and which exceed the recipe's limits."""
    deltas = {p: current.params()[p] - previous.params()[p] for p in current.params()}
    flagged = [
        p for p, d in deltas.items()
        if (p.startswith("t") and abs(d) > qa.drift_translation)
        or (p.startswith("r") and abs(math.degrees(d)) > qa.drift_rotation_deg)
    ]
    return {"previous_run": previous.run_id, "delta": deltas, "flagged": flagged}


def _fmt_h(H: Mapping[str, float]) -> str:
    parts = [
        f"{k}={v * 1000:.2f} mm" if k.startswith("t") else f"{k}={math.degrees(v):.3f}°"
        for k, v in H.items()
    ]
    return ", ".join(parts)


# --- entry points ----------------------------------------------------------------------------
def data_dir_default() -> Path:
    """Where run folders go: ``$CALSTATION_HOME`` (see
    :func:`calstation.storage.db.calstation_home`)."""
    return calstation_home()


_ENGINE_MODULES = (
    "calstation.engine.periodicity",
    "calstation.engine.shape",
    "calstation.engine.cube",
    "open3d",
)


def preload_engine() -> threading.Thread:
    """Import the engine (fine-tuning, cube check, Open3D) on a background thread while the
    operator places the targets and the scans run, so that no step after a scan waits for an
    import (~1.5 s together, Open3D ~0.8 s of it). A module that fails to import is left to
    fail with a clear error in the step that needs it."""

    def load() -> None:
        for name in _ENGINE_MODULES:
            with suppress(Exception):
                importlib.import_module(name)

    thread = threading.Thread(target=load, name="calstation-preload", daemon=True)
    thread.start()
    return thread


def start_run(
    loaded: LoadedRecipe,
    db: Database,
    ui: Operator,
    *,
    operator: str,
    data_dir: Path | None = None,
    serial: str | None = None,
) -> tuple[int, str]:
    """Create a run of ``loaded`` and execute it; returns (run id, final status).

    The recipe is validated against the installed plugins first. The run folder is
    ``<data_dir>/runs/<run id>/``. ``serial`` is the unit's serial number when the operator
    gives it (else the lidar's, read at preflight).
    """
    run_id = create_run(loaded, db, operator=operator, unattended=ui.unattended,
                        data_dir=data_dir, serial=serial)
    ui.info(f"run [bold]{run_id}[/] of recipe {escape(loaded.recipe.name)} on station "
            f"{loaded.recipe.station.id}; recordings in {escape(str(_run_dir(db, run_id)))}")
    with _signals_abort():
        return run_id, Station(db, run_id, loaded, ui).run()


def _run_dir(db: Database, run_id: int) -> Path:
    with db.session("reading the run", read_only=True) as s:
        run = s.get(Run, run_id)
        assert run is not None
        return Path(run.data_dir)


def create_run(
    loaded: LoadedRecipe,
    db: Database,
    *,
    operator: str,
    unattended: bool,
    data_dir: Path | None = None,
    serial: str | None = None,
) -> int:
    """Create (and commit) a ``running`` run of ``loaded`` and its folder; returns its id.

    ``serial`` is the unit's serial number when the operator gives it.

    The recipe is validated against the installed plugins first. Execute it with
    ``Station(db, run_id, loaded, ui).run()``.
    """
    check_plugins(loaded)
    base = (data_dir or data_dir_default()).expanduser().resolve()
    station_id = get_or_create_station(db, loaded.recipe.station.id)
    with db.session("creating the run") as s:
        run = Run(
            station_id=station_id,
            recipe_name=loaded.recipe.name,
            recipe_path=str(loaded.path.resolve()) if loaded.path else None,
            recipe_text=loaded.text,
            recipe_sha256=loaded.sha256,
            operator=operator,
            unit_serial=serial or None,
            unattended=unattended,
            data_dir="",
            status="running",
        )
        s.add(run)
        s.flush()
        run_dir = base / "runs" / str(run.id)
        run.data_dir = str(run_dir)
        run_id = run.id
    run_dir.mkdir(parents=True, exist_ok=True)
    return run_id


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def resumable_run(session: Session, run_id: int, force: bool) -> Run:
    """Run ``run_id`` from ``session`` if it may be resumed: :class:`StationError` when there
    is none, it already passed, or another live process executes it (unless ``force``)."""
    run = session.get(Run, run_id)
    if run is None:
        raise StationError(f"no run {run_id} in the database")
    if run.status == "passed":
        raise StationError(f"run {run_id} already passed; nothing to resume")
    _check_not_running_elsewhere(run, force)
    return run


def _check_not_running_elsewhere(run: Run, force: bool) -> None:
    """Refuse to resume a run another live process is executing (two processes, one motor)."""
    if run.status != "running" or force or run.pid is None:
        return
    if run.host == socket.gethostname():
        if run.pid != os.getpid() and _process_alive(run.pid):
            raise StationError(
                f"run {run.id} is being executed by process {run.pid} on this host; stop it "
                "first (or pass --force if that process id now belongs to something else)"
            )
        return
    raise StationError(
        f"run {run.id} was last executed on host {run.host!r} (process {run.pid}); resume it "
        "there, or pass --force if that process is gone"
    )


def resume_run(run_id: int, db: Database, ui: Operator, *, force: bool = False) -> str:
    """Continue run ``run_id`` at its first unfinished step; returns the final status.

    The recipe is the one stored with the run (not the file, which may have changed since).
    Recordings of finished steps are re-used after their sha256 is checked. A run still being
    executed by a live process is refused unless ``force``.
    """
    for note in journal.recover(db):  # results journalled by an earlier process, first
        ui.info(escape(note))
    with db.session() as s:
        run = resumable_run(s, run_id, force)
        text, path = run.recipe_text, run.recipe_path
        run_dir = Path(run.data_dir)
    source = f"recipe of run {run_id}"
    base_dir = Path(path).parent if path else None
    loaded = LoadedRecipe(parse_recipe(text, source, base_dir), Path(path) if path else None, text)
    check_plugins(loaded)
    run_dir.mkdir(parents=True, exist_ok=True)
    ui.info(f"resuming run [bold]{run_id}[/]; recordings in {escape(str(run_dir))}")
    with _signals_abort():
        return Station(db, run_id, loaded, ui).run()


@contextmanager
def _signals_abort() -> Iterator[None]:
    """SIGTERM aborts the run like Ctrl-C (so the motor is stopped and the run recorded)."""

    def handler(signum: int, frame: Any) -> None:
        raise AbortRun(f"aborted by signal {signal.Signals(signum).name}")

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def wait_for_step(
    db: Database, run_id: int, step: str, timeout_s: float = 60.0, status: str = "running"
) -> bool:
    """Poll until ``step`` of ``run_id`` has an attempt with ``status`` (for tests and tools)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with db.session("reading the steps", read_only=True) as s:
            found = s.scalars(
                select(Step.id).where(
                    Step.run_id == run_id, Step.name == step, Step.status == status
                )
            ).first()
        if found is not None:
            return True
        time.sleep(0.05)
    return False

