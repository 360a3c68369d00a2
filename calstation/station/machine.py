"""The station state machine: one guided run of a recipe, step by step, into the database.

The states are the steps of :mod:`calstation.station.steps`, in order, plus ``failed`` (a step
failed; the operator retries it or gives up), ``refused`` (a step's QA verdict failed: the
operator retries it, or the run goes on to its report), ``aborted`` (the operator or a signal
stopped the run), ``interrupted`` (the database went away: the run is resumed later) and
``done``; a ``transitions`` machine, and the only record of where the run is: which step runs,
which is retried, whether a failure may still be reported are its states and transitions, never
flags kept beside it. :class:`Station` only sequences the steps, persists each outcome and
decides retry and abort; each step's work is its own class.

**Where a step's retry is decided:** here, and only here, in :meth:`Station._after_failure`. The
operator answers retry or abort (``Operator.on_failure``); a retry starts at the step
:data:`RETRY_FROM` names (the failed step itself by default); a QA verdict the operator does not
retry (a failed cube check) still goes through ``report``; anything else fails the run. A step
learns that it is retried only from ``RunContext.retrying`` (the cube scan then asks for the
cube to be re-seated).

Every step attempt gets a ``step`` row when it starts (status ``running``) and is committed the
moment it ends, together with its recordings (``artifact``: path, size, sha256) and results
(``calibration``, ``cube_check``), in one transaction (:mod:`calstation.station.persist`). A
process killed mid-step therefore leaves every earlier step intact, and a resumed run
(:func:`calstation.station.runs.resume_run`) continues at the first step without a passed
attempt, re-using the recordings already taken. Recordings are written while scanning into the
run's folder ``<data dir>/runs/<run id>/`` (``static.mcap``, ``spin.mcap``, ``cube.mcap``), with
``report.json`` and ``calibration.yaml`` at the end. Once the run's end is stored, its observers
(:mod:`calstation.station.observers`: ``report.html``, the plugins' hook, the operator's summary,
the upload) are told.

The turntable is always stopped when the run ends, however it ends: ``stop()``, and
``emergency_stop()`` if that fails or the run was aborted or interrupted.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from contextlib import suppress
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from transitions import Machine

from calstation import plugins
from calstation.errors import AbortRun, CalstationError, DatabaseError, StationError
from calstation.recipes import LoadedRecipe
from calstation.station import persist, stored
from calstation.station.context import RunContext
from calstation.station.hardware import open_drivers, stop_and_close
from calstation.station.observers import (
    EndObserver,
    RunEnded,
    default_observers,
    notify,
    tell_observers,
)
from calstation.station.operator import Operator, publish
from calstation.station.outcome import StepOutcome, plain
from calstation.station.preload import import_open3d_first, preload_engine
from calstation.station.steps import REGISTRY, STEPS, run_steps
from calstation.storage.db import Database, Run, RunStatus, StepStatus

STATES: tuple[str, ...] = ("idle", *STEPS, "failed", "refused", "aborted", "interrupted", "done")

SCAN_PLACEMENT: dict[str, str] = {
    "static_scan": "place_static_target",
    "spin_scan": "place_spin_target",
    "cube_scan": "place_qa_cube",
}
"""The placement step each scan needs (re-confirmed when a run resumes at the scan)."""

WITHOUT_ENGINE = frozenset({"preflight", *SCAN_PLACEMENT.values()})
"""The steps that run beside the engine's import in the background (:func:`preload_engine`):
every other step waits for it to end first. Two threads importing one module (scipy's, say)
can take its import locks in opposite orders, and Python then fails one of the imports with a
deadlock error: a loaded machine's run failed its spin scan so while the import still ran."""

RETRY_FROM: dict[str, str] = {"fine_tune": "place_spin_target"}
"""Where a retry of a failed step starts: a fine-tuning refused for what its scan could see
is retried by re-placing the spin target and scanning again, not by re-reading the same scan."""

__all__ = ["RETRY_FROM", "SCAN_PLACEMENT", "STATES", "Station", "next_in_order"]


def next_in_order(step: str, steps: tuple[str, ...] = STEPS) -> str:
    """The step after ``step`` in ``steps``; ``done`` after the last."""
    i = steps.index(step)
    return steps[i + 1] if i + 1 < len(steps) else "done"


@dataclass(frozen=True)
class _Attempt:
    """How one attempt at a step ended: its ``outcome`` when it passed, else the ``error`` the
    operator reads."""

    outcome: StepOutcome | None = None
    error: str = ""


@dataclass(frozen=True)
class _End:
    """How the run ends: its final status, and why it did not pass."""

    status: RunStatus
    error: str | None = None


class Station:
    """Runs (or resumes) one run of a recipe on the station's drivers.

    ``run_id`` must exist in ``db``; ``loaded`` is its recipe; ``ui`` the operator;
    ``observers`` what happens once the run's end is stored (default:
    :func:`~calstation.station.observers.default_observers`). Call :meth:`run`, which returns
    the run's final status (``passed``, ``failed``, ``aborted``, ``interrupted``).
    """

    state: str
    trigger: Callable[..., bool]

    def __init__(
        self, db: Database, run_id: int, loaded: LoadedRecipe, ui: Operator,
        observers: Sequence[EndObserver] | None = None,
    ) -> None:
        with db.session() as s:
            run = s.get(Run, run_id)
            if run is None:
                raise StationError(f"no run {run_id} in the database")
            run_dir = Path(run.data_dir)
        self.ctx = RunContext(db, run_id, run_dir, loaded, ui)
        self.db, self.run_id, self.ui = db, run_id, ui
        self.observers = default_observers(db, ui) if observers is None else observers
        self.steps = run_steps(loaded.recipe)
        self.machine = self._build_machine()
        self._preload: threading.Thread | None = None

    def _build_machine(self) -> Machine:
        """The states and transitions: ``begin`` at a step, ``advance`` through the run's steps
        in order to ``done``, ``fail`` and ``refuse`` out of a step, ``retry`` into one,
        ``conclude`` from a refused verdict to the report, ``abort`` and ``interrupt``."""
        machine = Machine(model=self, states=list(STATES), initial="idle", auto_transitions=False)
        machine.add_ordered_transitions(
            states=[*self.steps, "done"], trigger="advance", loop=False
        )
        for step in self.steps:
            machine.add_transition("begin", "idle", step, conditions=[_at(step)])
            machine.add_transition("retry", ["failed", "refused"], step, conditions=[_at(step)])
        machine.add_transition("fail", list(self.steps), "failed")
        # a QA verdict (failed cube check) the operator does not retry still gets its report
        machine.add_transition("refuse", list(self.steps), "refused")
        machine.add_transition("conclude", "refused", "report")
        machine.add_transition("abort", "*", "aborted")
        machine.add_transition("interrupt", "*", "interrupted")
        return machine

    # --- the run -----------------------------------------------------------------------------
    def run(self) -> RunStatus:
        """Execute the remaining steps; returns the final status. The motor is always stopped."""
        end = _End(RunStatus.INTERRUPTED, "the run was stopped")
        try:
            try:
                self._start()
                end = self._walk()
            except (AbortRun, KeyboardInterrupt) as exc:
                self.trigger("abort")
                end = _End(RunStatus.ABORTED, str(exc) or "aborted by the operator")
            except DatabaseError as exc:
                # the database failed (a lock outlasted the wait, or it went away): what could
                # not be stored is journalled; the run stops as interrupted, to be resumed
                self.trigger("interrupt")
                self.ui.warn(str(exc))
                end = _End(RunStatus.INTERRUPTED, str(exc))
            except BaseException as exc:
                # an unexpected error (not a step failure): the run is failed, never left running
                end = _End(RunStatus.FAILED, f"{type(exc).__name__}: {exc}")
                self._end(end)
                raise
            self._end(end)
            return end.status
        finally:
            self._stop_hardware(end.status)

    def _start(self) -> None:
        """Claim the run, open the drivers, enter the first step still to do."""
        first = self._first_step()
        persist.mark_running(self.db, self.run_id)
        notify(self.ui, "run_started",
               partial(plugins.run_started, stored.brief(self.db, self.run_id)))
        # Open3D first, one thread at a time: a driver's module may import it
        import_open3d_first()
        self.ctx.drivers = open_drivers(self.ctx.loaded)
        # after the drivers' own imports; the operator's placements overlap it
        self._preload = preload_engine()
        self.trigger("begin", first)

    def _walk(self) -> _End:
        """Attempt the steps in order, from where the machine is, until it is done; the run's
        end (its verdict is the report step's)."""
        retrying = False
        report: StepOutcome | None = None
        while self.state != "done":
            step = self.state
            attempt = self._attempt(step, retrying)
            if attempt.outcome is not None:
                report = attempt.outcome
                self.trigger("advance")
                retrying = False
                continue
            decided = self._after_failure(step, attempt.error)
            if isinstance(decided, _End):
                return decided
            retrying = decided == "retry"
        return self._verdict(report)

    def _after_failure(self, step: str, error: str) -> _End | str:
        """The retry decision for a failed ``step``: the operator's retry restarts at
        :data:`RETRY_FROM` (the step itself by default); giving up on a QA verdict still reports;
        giving up otherwise fails the run. The trigger pulled (``retry``, ``conclude``), or the
        run's end when it ends here."""
        attempts = stored.attempts(self.db, self.run_id, step)
        if self.ui.on_failure(step, error, attempts) == "retry":
            self.trigger("retry", RETRY_FROM.get(step, step))
            return "retry"
        if self.state == "refused":
            self.trigger("conclude")
            return "conclude"
        return _End(RunStatus.FAILED, f"step {step} failed: {error}")

    def _first_step(self) -> str:
        """The first step still to do: the first without a passed attempt, or its scan's
        placement when the run resumes at a scan; the report when every step passed."""
        passed = stored.passed_steps(self.db, self.run_id)
        todo = [step for step in self.steps if step not in passed]
        if not todo:
            return "report"
        placement = SCAN_PLACEMENT.get(todo[0])
        return placement if placement is not None and placement in passed else todo[0]

    # --- one attempt -------------------------------------------------------------------------
    def _attempt(self, step: str, retrying: bool) -> _Attempt:
        """One attempt at ``step``: row, work, commit; the machine leaves the step by ``fail``
        or ``refuse`` when it does not pass. ``retrying``: the attempt follows a failed one (of
        this step, or of a later one that :data:`RETRY_FROM` restarts here).

        A step whose outcome is a failed QA verdict (``outcome.failure``) keeps its recordings and
        results and fails like any step, so the operator may retry it.
        """
        if step not in WITHOUT_ENGINE and self._preload is not None:
            self._preload.join()  # no import of this thread's beside the preload's
        step_id, attempt = persist.begin_step(self.db, self.run_id, step)
        self.ctx.scans.take()
        self.ctx.retrying = retrying
        try:
            publish(self.ui, "step_started", step=step, attempt=attempt)
            outcome = REGISTRY[step].run(self.ctx, step_id)
        except (AbortRun, KeyboardInterrupt) as exc:
            with suppress(DatabaseError):  # journalled if not stored; the abort goes on
                persist.end_step(self.ctx, step_id, StepStatus.ABORTED, {},
                                 str(exc) or "aborted by the operator", StepOutcome({}))
            raise
        except DatabaseError:
            raise
        except Exception as exc:  # a step failure, whatever raised it, is the operator's call
            return _Attempt(error=self._step_raised(step, step_id, attempt, exc))
        if outcome.failure is not None:
            self._step_refused(step, step_id, outcome)
            return _Attempt(error=outcome.failure)
        self._step_passed(step, step_id, attempt, outcome)
        return _Attempt(outcome=outcome)

    def _step_raised(self, step: str, step_id: int, attempt: int, exc: Exception) -> str:
        """Store and announce a step that raised; the machine goes to ``failed``. Its error."""
        message = str(exc) if isinstance(exc, CalstationError) else (
            f"{type(exc).__name__}: {exc}"
        )
        failed = {"error": message, **plain(getattr(exc, "details", {}))}
        persist.end_step(self.ctx, step_id, StepStatus.FAILED, failed, message, StepOutcome({}))
        publish(self.ui, "step_finished", step=step, attempt=attempt, status=StepStatus.FAILED,
                result={"error": message}, error=message)
        notify(self.ui, "step_finished", partial(
            plugins.step_finished, stored.brief(self.db, self.run_id), step, StepStatus.FAILED,
            {"error": message}))
        self.trigger("fail")
        return message

    def _step_refused(self, step: str, step_id: int, outcome: StepOutcome) -> None:
        """Store a step whose QA verdict failed, with what it measured; the machine goes to
        ``refused``."""
        assert outcome.failure is not None
        persist.end_step(self.ctx, step_id, StepStatus.FAILED, outcome.result, outcome.failure,
                         outcome)
        notify(self.ui, "step_finished", partial(
            plugins.step_finished, stored.brief(self.db, self.run_id), step, StepStatus.FAILED,
            outcome.result))
        self.trigger("refuse")

    def _step_passed(self, step: str, step_id: int, attempt: int, outcome: StepOutcome) -> None:
        """Store and announce a passed step."""
        persist.end_step(self.ctx, step_id, StepStatus.PASSED, outcome.result, None, outcome)
        publish(self.ui, "step_finished", step=step, attempt=attempt, status=StepStatus.PASSED,
                result=plain(outcome.result), error=None)
        notify(self.ui, "step_finished", partial(
            plugins.step_finished, stored.brief(self.db, self.run_id), step, StepStatus.PASSED,
            outcome.result))

    # --- the end -----------------------------------------------------------------------------
    def _verdict(self, report: StepOutcome | None) -> _End:
        """The run's end after its last step: the report step's verdict, and why it failed
        (drift beyond the recipe's limits, else the cube check)."""
        status = RunStatus(report.run_status) if report is not None and report.run_status \
            else RunStatus(stored.cube_verdict(self.db, self.run_id))
        if status == RunStatus.PASSED:
            return _End(status)
        drift = report.drift_failure if report is not None else None
        return _End(status, drift or stored.cube_failure(self.db, self.run_id))

    def _end(self, end: _End) -> None:
        """Store the run's end (journalled if the database fails: never raises for that), then
        tell the observers (:mod:`calstation.station.observers`)."""
        try:
            summary = persist.end_run(self.ctx, end.status, end.error)
        except DatabaseError as exc:
            self.ui.warn(str(exc))
            return
        tell_observers(self.observers, RunEnded(self.run_id, end.status, end.error, summary),
                       self.ui)

    def _stop_hardware(self, status: RunStatus) -> None:
        """Stop the turntable and close the drivers, if open (an emergency stop too when the run
        was aborted or interrupted); say how on the console and store it in the run
        (``run.motor_stop``)."""
        d = self.ctx.drivers
        if d is None:
            return
        record = stop_and_close(d, self.state in ("aborted", "interrupted"), str(status))
        self.ctx.drivers = None
        text = f"motor stopped by {record['how']} (run {record['reason']})"
        if record["ok"]:
            self.ui.info(text)
        else:
            self.ui.warn(f"the motor could not be stopped: {'; '.join(record['errors'])}")
        with suppress(DatabaseError):  # journalled when the database is unavailable
            persist.store_motor_stop(self.ctx, record)


def _at(step: str) -> Callable[[str], bool]:
    """The condition of a transition into ``step``: the trigger names it."""
    return lambda at: at == step
