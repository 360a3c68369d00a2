"""The station state machine: one guided run of a recipe, step by step, into the database.

The states are the steps of :mod:`calstation.station.steps`, in order, plus ``failed`` (a failed
step; the operator retries it or gives up), ``aborted`` (the operator or a signal stopped the
run) and ``done``; a ``transitions`` machine. :class:`Station` only sequences the steps, persists
each outcome and decides retry and abort; each step's work is its own class.

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
``report.json`` and ``calibration.yaml`` at the end.

The turntable is always stopped when the run ends, however it ends: ``stop()``, and
``emergency_stop()`` if that fails or the run was aborted.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import suppress
from pathlib import Path
from typing import Any

from rich.markup import escape
from transitions import Machine

from calstation import plugins
from calstation.errors import AbortRun, CalstationError, DatabaseError, StationError
from calstation.recipes import LoadedRecipe
from calstation.station import persist, stored
from calstation.station.context import RunContext
from calstation.station.hardware import open_drivers, stop_and_close
from calstation.station.operator import Operator, publish
from calstation.station.outcome import StepOutcome, plain
from calstation.station.preload import preload_engine
from calstation.station.steps import REGISTRY, STEPS, run_steps
from calstation.storage.db import Database, Run

STATES: tuple[str, ...] = ("idle", *STEPS, "failed", "aborted", "done")

SCAN_PLACEMENT: dict[str, str] = {
    "static_scan": "place_static_target",
    "spin_scan": "place_spin_target",
    "cube_scan": "place_qa_cube",
}
"""The placement step each scan needs (re-confirmed when a run resumes at the scan)."""

RETRY_FROM: dict[str, str] = {"fine_tune": "place_spin_target"}
"""Where a retry of a failed step starts: a fine-tuning refused for what its scan could see
is retried by re-placing the spin target and scanning again, not by re-reading the same scan."""


def next_in_order(step: str, steps: tuple[str, ...] = STEPS) -> str:
    """The step after ``step`` in ``steps``; ``done`` after the last."""
    i = steps.index(step)
    return steps[i + 1] if i + 1 < len(steps) else "done"


def run_brief_from(summary: dict[str, Any]) -> dict[str, Any]:
    """The brief part of a summary (without steps and results)."""
    return {k: v for k, v in summary.items()
            if k not in ("steps", "calibrations", "cube_check", "artifacts")}


class Station:
    """Runs (or resumes) one run of a recipe on the station's drivers.

    ``run_id`` must exist in ``db``; ``loaded`` is its recipe; ``ui`` the operator. Call
    :meth:`run`, which returns the run's final status (``"passed"``, ``"failed"``,
    ``"aborted"``).
    """

    state: str
    trigger: Callable[..., bool]

    def __init__(self, db: Database, run_id: int, loaded: LoadedRecipe, ui: Operator) -> None:
        with db.session() as s:
            run = s.get(Run, run_id)
            if run is None:
                raise StationError(f"no run {run_id} in the database")
            run_dir = Path(run.data_dir)
        db.log_path = run_dir / "database.log"  # SQL of database faults, never the console
        db.on_wait = lambda message: ui.warn(escape(message))
        self.ctx = RunContext(db, run_id, run_dir, loaded, ui)
        self.db, self.run_id, self.ui = db, run_id, ui
        self.failed_step: str | None = None
        self.steps = run_steps(loaded.recipe)
        self.machine = self._build_machine()
        self._plan: list[str] = []
        self._final = "interrupted"
        self._last_error = ""
        self._verdict_failure = False
        self._drift_failure: str | None = None

    def _build_machine(self) -> Machine:
        """The states and transitions: ``advance`` through the run's steps in order, ``begin``
        at the plan's first, ``fail``/``retry``/``conclude`` around ``failed``, ``abort``."""
        machine = Machine(model=self, states=list(STATES), initial="idle", auto_transitions=False)
        machine.add_ordered_transitions(
            states=[*self.steps, "done"], trigger="advance", loop=False
        )
        for step in self.steps:
            machine.add_transition("begin", "idle", step, conditions=[self._is_first(step)])
            machine.add_transition("retry", "failed", step, conditions=[self._is_failed(step)])
        machine.add_transition("fail", list(self.steps), "failed")
        # a QA verdict (failed cube check) the operator does not retry still gets its report
        machine.add_transition("conclude", "failed", "report")
        machine.add_transition("abort", "*", "aborted")
        return machine

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
            self._start()
            return self._walk()
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
            self._stop_hardware(emergency=aborted)

    def _start(self) -> None:
        """Plan the steps still to do, claim the run, open the drivers, enter the first step."""
        self._plan = self._remaining_steps()
        persist.mark_running(self.db, self.run_id)
        preload_engine()
        self._notify("run_started", run=stored.brief(self.db, self.run_id))
        self.ctx.drivers = open_drivers(self.ctx.loaded)
        self.trigger("begin")

    def _walk(self) -> str:
        """Attempt the planned steps in order until none is left; the run's final status."""
        while True:
            step = self.state
            if not self._attempt(step):
                final = self._after_failure(step)
                if final is not None:
                    return final
                continue
            self._plan.pop(0)
            if not self._plan:
                break
            # plans are suffixes of the run's steps
            if self._plan[0] != next_in_order(step, self.steps):
                raise StationError(f"cannot go from {step} to {self._plan[0]}")
            self.trigger("advance")
        verdict = self._verdict()
        return self._finish(verdict, None if verdict == "passed" else self._failure_reason())

    def _after_failure(self, step: str) -> str | None:
        """The retry decision for a failed ``step``: the operator's retry restarts at
        :data:`RETRY_FROM` (the step itself by default); giving up on a QA verdict still reports;
        giving up otherwise fails the run. The final status when the run ends here, else None."""
        attempts = stored.attempts(self.db, self.run_id, step)
        if self.ui.on_failure(step, self._last_error, attempts) == "retry":
            self._restart_from(RETRY_FROM.get(step, step))
            return None
        if not self._verdict_failure:
            return self._finish("failed", f"step {step} failed: {self._last_error}")
        self._plan = ["report"]
        self.trigger("conclude")
        return None

    def _restart_from(self, step: str) -> None:
        """Leave the failed state for ``step`` (the failed step or an earlier one) and plan
        every step from there again."""
        self.failed_step = step
        self._plan = list(self.steps[self.steps.index(step) :])
        self.trigger("retry")

    def _remaining_steps(self) -> list[str]:
        """Steps still to do: from the first without a passed attempt; a scan's placement first."""
        passed = stored.passed_steps(self.db, self.run_id)
        todo = [step for step in self.steps if step not in passed]
        if not todo:
            return ["report"]
        first = self.steps.index(todo[0])
        plan = list(self.steps[first:])
        placement = SCAN_PLACEMENT.get(plan[0])
        if placement is not None and placement in passed:
            plan.insert(0, placement)
        return plan

    # --- one attempt -------------------------------------------------------------------------
    def _attempt(self, step: str) -> bool:
        """One attempt at ``step``: row, work, commit. False (with ``_last_error``) on failure.

        A step whose outcome is a failed QA verdict (``outcome.failure``) keeps its recordings and
        results and fails like any step, so the operator may retry it.
        """
        step_id, attempt = persist.begin_step(self.db, self.run_id, step)
        self._verdict_failure = False
        self.ctx.scans.take()
        self.ctx.retrying = self.failed_step == step
        try:
            publish(self.ui, "step_started", step=step, attempt=attempt)
            outcome = REGISTRY[step].run(self.ctx, step_id)
        except (AbortRun, KeyboardInterrupt) as exc:
            with suppress(DatabaseError):  # journalled if not stored; the abort goes on
                persist.end_step(self.ctx, step_id, "aborted", {},
                                 str(exc) or "aborted by the operator", StepOutcome({}))
            raise
        except DatabaseError:
            raise
        except Exception as exc:  # a step failure, whatever raised it, is the operator's call
            self._step_raised(step, step_id, attempt, exc)
            return False
        if outcome.failure is not None:
            self._step_refused(step, step_id, outcome)
            return False
        self._step_passed(step, step_id, attempt, outcome)
        return True

    def _step_raised(self, step: str, step_id: int, attempt: int, exc: Exception) -> None:
        """Store and announce a step that raised; the machine goes to ``failed``."""
        message = str(exc) if isinstance(exc, CalstationError) else (
            f"{type(exc).__name__}: {exc}"
        )
        self._last_error = message
        failed = {"error": message, **plain(getattr(exc, "details", {}))}
        persist.end_step(self.ctx, step_id, "failed", failed, message, StepOutcome({}))
        publish(self.ui, "step_finished", step=step, attempt=attempt, status="failed",
                result={"error": message}, error=message)
        self._notify("step_finished", run=stored.brief(self.db, self.run_id), step=step,
                     status="failed", result={"error": message})
        self.failed_step = step
        self.trigger("fail")

    def _step_refused(self, step: str, step_id: int, outcome: StepOutcome) -> None:
        """Store a step whose QA verdict failed, with what it measured; the machine goes to
        ``failed``."""
        assert outcome.failure is not None
        self._last_error = outcome.failure
        self._verdict_failure = True
        persist.end_step(self.ctx, step_id, "failed", outcome.result, outcome.failure, outcome)
        self._notify("step_finished", run=stored.brief(self.db, self.run_id), step=step,
                     status="failed", result=outcome.result)
        self.failed_step = step
        self.trigger("fail")

    def _step_passed(self, step: str, step_id: int, attempt: int, outcome: StepOutcome) -> None:
        """Store and announce a passed step."""
        persist.end_step(self.ctx, step_id, "passed", outcome.result, None, outcome)
        if outcome.drift_failure is not None:
            self._drift_failure = outcome.drift_failure
        publish(self.ui, "step_finished", step=step, attempt=attempt, status="passed",
                result=plain(outcome.result), error=None)
        self._notify("step_finished", run=stored.brief(self.db, self.run_id), step=step,
                     status="passed", result=outcome.result)

    # --- the end -----------------------------------------------------------------------------
    def _verdict(self) -> str:
        return "failed" if self._drift_failure else stored.cube_verdict(self.db, self.run_id)

    def _failure_reason(self) -> str | None:
        """Why a run that went through every step failed: drift, else the cube check."""
        if self._drift_failure:
            return self._drift_failure
        return stored.cube_failure(self.db, self.run_id)

    def _finish(self, status: str, error: str | None) -> str:
        """Store the run's end (journalled if the database fails: never raises for that)."""
        self._final = status
        try:
            summary = persist.end_run(self.ctx, status, error)
        except DatabaseError as exc:
            self.ui.warn(escape(str(exc)))
            return status
        self._write_report_html()
        self._notify("run_finished", run=run_brief_from(summary), status=status, summary=summary)
        self.ui.summary(summary)
        self._upload_files()
        return status

    def _write_report_html(self) -> None:
        """``report.html`` in the run folder, whatever the outcome; a failure is a warning."""
        from calstation.storage.report_html import write_run_report

        try:
            write_run_report(self.db, self.run_id)
        except Exception as exc:
            self.ui.warn(f"could not write report.html: {type(exc).__name__}: {exc}")

    def _upload_files(self) -> None:
        """Copy the run's files to the fleet's shared store when one is configured
        (``$CALSTATION_RECORDINGS_URL``, :mod:`calstation.storage.uploads`). A failure is a
        warning: the run folder keeps every file, and ``calstation upload`` sends them later."""
        from calstation.storage.uploads import recordings_store, upload_run

        store = recordings_store()
        if store is None:
            return
        try:
            done = upload_run(self.db, self.run_id, store)
        except CalstationError as exc:
            problem = str(exc)
        else:
            if done.ok:
                self.ui.info(f"files copied to {escape(store)}: {len(done.sent)} sent, "
                             f"{len(done.present)} there already")
                return
            problem = "; ".join(done.failed)
        self.ui.warn(f"the run's files were not all copied to {escape(store)}: "
                     f"{escape(problem)}; the run folder keeps them, and `calstation upload "
                     f"{self.run_id}` sends them later")

    def _notify(self, hook: str, **kwargs: Any) -> None:
        """Call an observer hook; an observer's exception is a warning, never a failed run."""
        try:
            getattr(plugins, hook)(**kwargs)
        except Exception as exc:
            self.ui.warn(f"a plugin's {hook} observer failed: {type(exc).__name__}: {exc}")

    def _stop_hardware(self, emergency: bool) -> None:
        """Stop the turntable and close the drivers, if open; say how on the console and store
        it in the run (``run.motor_stop``)."""
        d = self.ctx.drivers
        if d is None:
            return
        record = stop_and_close(d, emergency, self._final)
        self.ctx.drivers = None
        text = f"motor stopped by {record['how']} (run {record['reason']})"
        if record["ok"]:
            self.ui.info(text)
        else:
            self.ui.warn(f"the motor could not be stopped: {'; '.join(record['errors'])}")
        with suppress(DatabaseError):  # journalled when the database is unavailable
            persist.store_motor_stop(self.ctx, record)
