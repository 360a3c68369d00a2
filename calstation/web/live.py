"""The web front end of a run: an :class:`~calstation.station.operator.Operator` that keeps the
run's live state for the pages and takes the operator's answers from them, and the runner that
executes one run at a time in a background thread of the server process.

The station (:mod:`calstation.station.machine`) is the same one the console drives:
:class:`WebOperator` only records what it is told (steps, progress, prompts, lidar lines, the
verdict) into a :class:`LiveState`, and blocks the run's thread at a prompt until a page answers.
Abort from a page raises :class:`~calstation.errors.AbortRun` inside the run at its next progress
report or lidar line (or answers the pending prompt with abort), which is what Ctrl-C does on the
console: the station closes the step as aborted and stops the motor (``emergency_stop`` then
``stop``).

Because the state lives in the server, a page that is closed or reloaded mid-run finds the same
step and the same pending prompt.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, TypedDict

import numpy as np
from numpy.typing import ArrayLike

from calstation import display
from calstation.display import fixture_name, step_title
from calstation.errors import AbortRun, CalstationError, StationError
from calstation.station.operator import (
    STEP_HINTS,
    Decision,
    StationEvent,
)
from calstation.station.runs import PreparedRun, prepare_resume, prepare_run, resumable_run
from calstation.station.steps import STEPS, run_steps
from calstation.storage.db import Database, RunStatus, StepStatus

if TYPE_CHECKING:
    from calstation.drivers import LidarLine
    from calstation.recipes import Recipe
    from calstation.web.endscreen import EndScreen
    from calstation.web.status import StationEntry

LINE_PREVIEW_PERIOD_S = 0.5
"""At most this often the live lidar line is refreshed (the lidar gives ~1000 lines/s): as
often as the event stream sends a state."""

LINE_PREVIEW_POINTS = 240
"""Points of the live lidar line (a subsample of the line's valid returns: the plot is a
third of the screen wide)."""

PROGRESS_STEP = 0.01
"""Progress is published when its fraction moved by this much (or its phase changed)."""

LOG_LINES = 60

MAX_RETRIES = 3
"""A failed step can be retried this many times from the page, then only aborted."""


class Busy(CalstationError):
    """A run is already in progress on this station (HTTP 409)."""


class NoSuchPrompt(CalstationError):
    """An answer to a prompt that is not (or no longer) pending (HTTP 409)."""


class StepState(TypedDict):
    """A step as the operator page shows it."""

    name: str
    title: str
    status: str
    attempt: int
    error: str | None
    started_at: float | None
    seconds: float | None


class CloudState(TypedDict):
    """The scan's cloud so far: one ``id`` per scan, its points in mm (frame D)."""

    id: int
    scan: str
    source: str
    x: list[float]
    y: list[float]
    z: list[float]


class LiveSnapshot(TypedDict):
    """The operator page's state as JSON-ready data (:meth:`LiveState.snapshot`)."""

    version: int
    busy: bool
    run_id: int | None
    station: str | None
    recipe: str | None
    operator: str | None
    serial: str | None
    started_at: float | None
    finished_at: float | None
    now: float
    status: str
    step: str | None
    attempt: int
    steps: list[StepState]
    progress: dict[str, object] | None
    prompt: dict[str, object] | None
    line: dict[str, object] | None
    outline: dict[str, object] | None
    cloud: dict[str, object] | None
    accuracy: list[dict[str, object]]
    log: list[dict[str, str]]
    result: EndScreen | None
    error: str | None
    abort_requested: str | None
    stations: list[StationEntry]


@dataclass
class _Shown:
    """The progress a page was last sent."""

    phase: str | None = None
    fraction: float = -1.0
    at: float = 0.0


def zoom_window(x_mm: ArrayLike, y_mm: ArrayLike, platter_m: float
                ) -> dict[str, list[float]] | None:
    """The part of a lidar line that matters: the nearest returns (the platter and what stands
    on it, in front of the floor and walls), within one platter diameter plus 10 cm in range of
    the nearest, with a margin; ``{"x": [lo, hi], "y": [lo, hi]}`` in mm, None without returns."""
    x, y = np.asarray(x_mm, dtype=float), np.asarray(y_mm, dtype=float)
    if x.size == 0:
        return None
    rng = np.hypot(x, y)
    near = rng <= np.percentile(rng, 2) + 1000.0 * (platter_m + 0.1)
    xs, ys = x[near], y[near]
    pad = max(50.0, 0.1 * max(float(np.ptp(xs)), float(np.ptp(ys))))
    return {"x": [float(xs.min() - pad), float(xs.max() + pad)],
            "y": [float(ys.min() - pad), float(ys.max() + pad)]}


def _outline_mm(event: StationEvent) -> dict[str, object]:
    """An ``outline`` event as the live line plot draws it: each polyline as x and y lists in
    mm."""
    d = event.data
    lines = [{"x": [round(1000.0 * p[0], 1) for p in line],
              "y": [round(1000.0 * p[1], 1) for p in line]} for line in d["lines"]]
    return {"scan": d["scan"], "fixture": d["fixture"], "source": d["source"],
            "known": bool(d["known"]), "platter_angle_deg": round(d["platter_angle_deg"], 1),
            "lines": lines}


_cloud_ids = itertools.count(1)


def _add_cloud(st: LiveState, event: StationEvent) -> None:
    """Append a ``cloud`` event's new points (a new scan's first starts a new cloud)."""
    d = event.data
    c = st.cloud
    if c is None or d["start"] == 0 or c["scan"] != d["scan"] or len(c["x"]) != d["start"]:
        c = st.cloud = {"id": next(_cloud_ids), "scan": d["scan"], "source": d["source"],
                        "x": [], "y": [], "z": []}
    for axis, values in enumerate((c["x"], c["y"], c["z"])):
        values.extend(round(1000.0 * p[axis], 1) for p in d["points"])


def _epoch(iso: object) -> float | None:
    import datetime as dt

    if not iso:
        return None
    t = dt.datetime.fromisoformat(str(iso))
    return (t if t.tzinfo else t.replace(tzinfo=dt.UTC)).timestamp()


def _times_as_stored(st: LiveState, result: EndScreen) -> None:
    """The run's and its steps' times as the database has them, so that the page's header, its
    steps and its end screen show one elapsed time each (the live clock started a little
    after the run's row, and stopped after its report)."""
    started, finished = _epoch(result["started_at"]), _epoch(result["finished_at"])
    if started is not None and finished is not None:
        st.started_at, st.finished_at = started, finished
    last = {s["name"]: s for s in result["steps"]}
    for name, step in st.steps.items():
        stored = last.get(name)
        if stored is not None and stored["seconds"] is not None:
            step["seconds"] = stored["seconds"]
            step["status"] = stored["status"]
            step["attempt"] = stored["attempt"]


class LiveState:
    """What the operator page shows, kept by the server; thread-safe.

    :meth:`snapshot` is the page's JSON twin (``/state.json``); ``version`` grows with every
    change, so the event stream sends a snapshot only when something changed.
    """

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._ids = itertools.count(1)
        self._listeners: list[Callable[[], None]] = []
        self.version = 0
        self.stations: list[StationEntry] = []
        """who holds each station of the server (:mod:`calstation.web.status`), kept across
        runs"""
        self._reset()

    def _reset(self) -> None:
        self.run_id: int | None = None
        self.station: str | None = None
        self.recipe: str | None = None
        self.operator: str | None = None
        self.serial: str | None = None
        self.started_at: float | None = None
        """when the run (or its resumption) started, seconds since the epoch"""
        self.finished_at: float | None = None
        self.outline: dict[str, object] | None = None
        """where the platter and the fixture being scanned should appear in the live line plot
        (the ``outline`` event, in mm)"""
        self.cloud: CloudState | None = None
        """the scan's cloud so far (the ``cloud`` events): ``id`` (one per scan), ``scan``,
        ``source`` and the points' ``x``, ``y``, ``z`` lists (mm, frame D)"""
        self.status = "idle"
        self.step: str | None = None
        self.attempt = 0
        self.steps: dict[str, StepState] = {
            s: {"name": s, "title": step_title(s), "status": "pending", "attempt": 0,
                "error": None, "started_at": None, "seconds": None} for s in STEPS
        }
        self.progress: dict[str, object] | None = None
        self.prompt: dict[str, object] | None = None
        self.line: dict[str, object] | None = None
        self.accuracy: list[dict[str, object]] = []
        """the predicted error after each turn of the scan under way (the ``accuracy`` event)"""
        self.log: list[dict[str, str]] = []
        self.result: EndScreen | None = None
        self.error: str | None = None
        self.abort_requested: str | None = None
        self._answer: tuple[int, str] | None = None

    # --- changes ---------------------------------------------------------------------------
    def _changed(self) -> None:
        self.version += 1
        self._cond.notify_all()
        for listener in self._listeners:
            with contextlib.suppress(Exception):  # a page's stream must never stop the run
                listener()

    def add_listener(self, listener: Callable[[], None]) -> None:
        """Call ``listener()`` after every change (from the changing thread, under the state's
        lock: it must return at once and not read the state)."""
        with self._cond:
            self._listeners.append(listener)

    def begin(
        self, run_id: int, recipe: str, operator: str, serial: str | None,
        steps: tuple[str, ...] = STEPS, station: str | None = None,
    ) -> None:
        """A new (or resumed) run starts; ``steps`` are the ones it takes (a run without the
        L-target leaves two out)."""
        with self._cond:
            self._reset()
            self.steps = {k: v for k, v in self.steps.items() if k in steps}
            self.run_id, self.recipe, self.operator, self.serial = run_id, recipe, operator, serial
            self.station = station
            self.started_at = time.time()
            self.status = RunStatus.RUNNING
            self._changed()

    def set_stations(self, stations: list[StationEntry]) -> None:
        """Who holds each station now (published when it changed)."""
        def put(st: LiveState) -> None:
            st.stations = stations
        self.update(put)

    def update(self, fn: Callable[[LiveState], None]) -> None:
        """Apply ``fn`` to the state under its lock and publish the change."""
        with self._cond:
            fn(self)
            self._changed()

    def add_log(self, level: str, message: str) -> None:
        """Append a line to the page's log."""
        def add(st: LiveState) -> None:
            st.log = [*st.log[-(LOG_LINES - 1):], {"level": level, "text": message}]
        self.update(add)

    def finish(self, status: str, result: EndScreen | None, error: str | None) -> None:
        """The run ended (``result`` is the end screen's data: verdict, values and limits)."""
        def end(st: LiveState) -> None:
            st.status, st.result, st.error = status, result, error
            st.prompt = st.progress = None
            st.finished_at = time.time()
            for step in st.steps.values():
                if step["status"] == StepStatus.RUNNING:  # the step it was aborted (or died) in
                    step["status"] = (StepStatus.ABORTED if status == RunStatus.ABORTED
                                      else StepStatus.FAILED)
                    if step["started_at"] is not None:
                        step["seconds"] = st.finished_at - step["started_at"]
            if result is not None:
                _times_as_stored(st, result)
        self.update(end)

    # --- prompts ---------------------------------------------------------------------------
    def ask(self, prompt: dict[str, object], allowed: tuple[str, ...]) -> str:
        """Show ``prompt`` and block until a page answers one of ``allowed`` (or abort)."""
        with self._cond:
            pid = next(self._ids)
            self.prompt = {**prompt, "id": pid, "answers": list(allowed)}
            self._answer = None
            self._changed()
            while True:
                if self.abort_requested:
                    answer = "abort"
                    break
                if self._answer is not None and self._answer[0] == pid:
                    answer = self._answer[1]
                    break
                self._cond.wait(timeout=0.5)
            self.prompt = None
            self._answer = None
            self._changed()
            return answer

    def answer(self, prompt_id: int, answer: str) -> None:
        """Answer the pending prompt; :class:`NoSuchPrompt` if it is not pending or the answer
        is not one it offers."""
        with self._cond:
            p = self.prompt
            answers = p["answers"] if p is not None else None
            if p is None or p["id"] != prompt_id or not isinstance(answers, list):
                raise NoSuchPrompt(
                    f"prompt {prompt_id} is not pending (it was answered, or the run moved on); "
                    "reload the page"
                )
            if answer not in answers:
                raise NoSuchPrompt(
                    f"{answer!r} is not an answer to this prompt; use one of "
                    f"{', '.join(str(a) for a in answers)}"
                )
            self._answer = (prompt_id, answer)
            # answered: no longer pending for any page, before the run's thread wakes to it
            self.prompt = None
            self._changed()

    def request_abort(self, reason: str) -> bool:
        """Ask the running run to abort; False if no run is running."""
        with self._cond:
            if self.status != RunStatus.RUNNING:
                return False
            self.abort_requested = reason
            self._changed()
            return True

    # --- reading ---------------------------------------------------------------------------
    def cloud_since(self, cloud_id: int, start: int) -> dict[str, object]:
        """The points of cloud ``cloud_id`` from the ``start``-th on (all of the current cloud
        when ``cloud_id`` is not it: the page then starts again)."""
        with self._cond:
            c = self.cloud
            if c is None:
                return {"id": None, "start": 0, "x": [], "y": [], "z": []}
            first = max(0, start) if c["id"] == cloud_id else 0
            return {"id": c["id"], "scan": c["scan"], "source": c["source"], "start": first,
                    "x": c["x"][first:], "y": c["y"][first:], "z": c["z"][first:]}

    def snapshot(self) -> LiveSnapshot:
        """The state as JSON-ready data (the operator page's JSON twin)."""
        with self._cond:
            return {
                "version": self.version,
                "busy": self.status == RunStatus.RUNNING,
                "run_id": self.run_id,
                "station": self.station,
                "recipe": self.recipe,
                "operator": self.operator,
                "serial": self.serial,
                "started_at": self.started_at,
                "finished_at": self.finished_at,
                "now": time.time(),
                "status": self.status,
                "step": self.step,
                "attempt": self.attempt,
                "steps": [s.copy() for s in self.steps.values()],
                "progress": None if self.progress is None else dict(self.progress),
                "prompt": None if self.prompt is None else dict(self.prompt),
                "line": self.line,
                "outline": self.outline,
                # the points are fetched apart, only the new ones (cloud_since)
                "cloud": None if self.cloud is None else {
                    "id": self.cloud["id"], "scan": self.cloud["scan"],
                    "source": self.cloud["source"], "count": len(self.cloud["x"])},
                "accuracy": [dict(a) for a in self.accuracy],
                "log": list(self.log),
                "result": self.result,
                "error": self.error,
                "abort_requested": self.abort_requested,
                "stations": self.stations,
            }


class WebOperator:
    """The station's operator for the web pages (see the module docstring)."""

    unattended = False
    previews = True
    """the station publishes the fixture's expected outline and the scan's cloud"""

    def __init__(self, live: LiveState, recipe: Recipe) -> None:
        self.live = live
        self.recipe = recipe
        self._last_line = 0.0
        self._lines = 0
        self._with_outline = False
        """outlines arrive: a line is shown with each (else every LINE_PREVIEW_PERIOD_S)"""
        self._line_due = False

    # --- the Operator protocol -------------------------------------------------------------
    def info(self, message: str) -> None:
        """A line for the page's log."""
        self.live.add_log("info", message)

    def warn(self, message: str) -> None:
        """A warning for the page's log."""
        self.live.add_log("warning", message)

    def confirm_fixture(self, fixture: str, description: str) -> bool:
        """Show the placement picture with Continue and Abort; wait for the answer."""
        from calstation.web.placement import placement_svg

        self._check_abort()
        geometry = getattr(self.recipe.fixtures, fixture, None)
        svg = None
        if geometry is not None:
            svg = placement_svg(self.recipe.fixtures.platter.radius, geometry,
                                f"place the {fixture_name(fixture)}")
        answer = self.live.ask(
            {"kind": "fixture", "fixture": fixture, "step": self.live.step,
             "title": f"Place the {fixture_name(fixture)}", "text": description, "svg": svg},
            ("continue", "abort"),
        )
        return answer == "continue"

    def on_failure(self, step: str, error: str, attempt: int) -> Decision:
        """Show the step's error with Retry and Abort; wait for the answer."""
        allowed: tuple[str, ...] = ("retry", "abort") if attempt <= MAX_RETRIES else ("abort",)
        answer = self.live.ask(
            {"kind": "failure", "step": step, "error": error, "attempt": attempt,
             "title": f"{step_title(step).capitalize()} failed",
             "text": f"The step {step_title(step)} failed (attempt {attempt}). "
                     + STEP_HINTS.get(step, "Fix the cause shown below, then retry the step.")
                     + (" Or abort the run." if "retry" in allowed
                        else f" {MAX_RETRIES} retries are used up: abort the run.")},
            allowed,
        )
        return "retry" if answer == "retry" else "abort"

    @contextmanager
    def progress(self, title: str) -> Iterator[Callable[[str, float], None]]:
        """Progress of one long step, in words and a fraction; checks for an abort."""
        shown = _Shown()

        def update(phase: str, fraction: float) -> None:
            self._check_abort()
            frac = max(0.0, min(1.0, float(fraction))) if math.isfinite(fraction) else 0.0
            now = time.monotonic()
            # steps report progress per line: publish only what a person can see change
            if (phase == shown.phase and abs(frac - shown.fraction) < PROGRESS_STEP
                    and now - shown.at < LINE_PREVIEW_PERIOD_S):
                return
            shown.phase, shown.fraction, shown.at = phase, frac, now
            self.live.update(lambda st: setattr(
                st, "progress", {"title": title, "phase": phase, "fraction": frac}))

        update("", 0.0)
        yield update
        self.live.update(lambda st: setattr(
            st, "progress", {"title": title, "phase": "done", "fraction": 1.0}))

    def summary(self, summary: Mapping[str, object]) -> None:
        """The run's final summary; the runner builds the end screen from the database."""
        self.live.add_log("info", f"run {summary['id']} {summary['status']}")

    def event(self, event: StationEvent) -> None:
        """Steps started and finished, and the live lidar line; checks for an abort."""
        d = event.data
        if event.kind == "step_started":
            def started(st: LiveState) -> None:
                st.step, st.attempt = d["step"], d["attempt"]
                step = st.steps[d["step"]]
                step["status"], step["attempt"], step["error"] = (StepStatus.RUNNING,
                                                                  d["attempt"], None)
                step["started_at"], step["seconds"] = time.time(), None
                st.progress = None
                if d["step"] not in ("static_scan", "spin_scan", "cube_scan"):
                    st.line = st.outline = None
                if d["step"] != "fine_tune":  # the fine-tuning is of the spin scan just shown
                    st.cloud = None
            self._with_outline = False
            self.live.update(started)
            self.live.add_log("info", f"▶ {step_title(d['step'])}"
                              + (f" (attempt {d['attempt']})" if d["attempt"] > 1 else ""))
        elif event.kind == "step_finished":
            def finished(st: LiveState) -> None:
                step = st.steps[d["step"]]
                step["status"], step["attempt"], step["error"] = (d["status"], d["attempt"],
                                                                  d.get("error"))
                step["seconds"] = (None if step["started_at"] is None
                                   else time.time() - step["started_at"])
                st.progress = None
                if d["step"] == "preflight" and not st.serial:
                    # the lidar's serial, when the operator gave none
                    st.serial = (d.get("result") or {}).get("unit_serial") or None
            self.live.update(finished)
        elif event.kind == "outline":
            # the next line is shown with it: the line and the outline at one platter angle
            self._with_outline = True
            self._line_due = True
            self.live.update(lambda st: setattr(st, "outline", _outline_mm(event)))
        elif event.kind == "cloud":
            self.live.update(lambda st: _add_cloud(st, event))
        elif event.kind == "lidar_line":
            self._preview(d["kind"], d["line"])
        elif event.kind == "accuracy":
            error, budget = float(d["predicted_error_m"]), float(d["budget_m"])
            point = {"scan": d["scan"], "turns": d["turns"], "predicted_error_m": error,
                     "budget_m": budget, "within": error <= budget and not d.get("more"),
                     "budget_text": display.number("predicted_error", budget),
                     "text": f"{display.count(d['turns'], 'turn')}: "
                             f"{display.number('predicted_error', error)}"
                             + ("" if not d.get("more") else f" (turning on: {d['more']})")}

            def predicted(st: LiveState) -> None:
                st.accuracy = [a for a in st.accuracy if a["scan"] == point["scan"]] + [point]
            self.live.update(predicted)
        self._check_abort()

    # --- helpers ---------------------------------------------------------------------------
    def _check_abort(self) -> None:
        reason = self.live.abort_requested
        if reason:
            raise AbortRun(reason)

    def _preview(self, kind: str, line: LidarLine) -> None:
        now = time.monotonic()
        if self._with_outline and not self._line_due and now - self._last_line < 1.0:
            return
        if not self._with_outline and now - self._last_line < LINE_PREVIEW_PERIOD_S:
            return
        self._last_line, self._line_due = now, False
        self._lines += 1
        seq = self._lines
        valid = np.asarray(line.valid, dtype=bool)
        rho = np.asarray(line.range_m)[valid]
        alpha = np.asarray(line.azimuth_rad)[valid]
        if rho.size > LINE_PREVIEW_POINTS:
            pick = np.linspace(0, rho.size - 1, LINE_PREVIEW_POINTS).astype(int)
            rho, alpha = rho[pick], alpha[pick]
        # frame L (DESIGN §2): x = ρ·sin α, y = ρ·cos α; in millimetres for the plot
        x = np.round(rho * np.sin(alpha) * 1000.0, 1).tolist()
        y = np.round(rho * np.cos(alpha) * 1000.0, 1).tolist()
        window = zoom_window(np.asarray(x), np.asarray(y),
                             2.0 * float(self.recipe.fixtures.platter.radius))
        self.live.update(lambda st: setattr(
            st, "line", {"seq": seq, "kind": kind, "x_mm": x, "y_mm": y,
                         "points": int(valid.sum()), "window": window}))


class Runner:
    """Executes one run at a time in a background thread and keeps its :class:`LiveState`.

    ``start`` and ``resume`` raise :class:`Busy` while a run is in progress: of two concurrent
    starts exactly one runs (the lock is taken without waiting).
    """

    def __init__(self, db: Database, data_dir: Path, recipes_dir: Path) -> None:
        self.db = db
        self.data_dir = data_dir
        self.recipes_dir = recipes_dir
        self.live = LiveState()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self.released: Callable[[], None] | None = None
        """called when a run has given its station back, before its end is published (the
        server reads the station locks again, so the end screen offers Start at once)"""

    # --- recipes ---------------------------------------------------------------------------
    def recipes(self) -> list[str]:
        """The recipe files offered on the operator page (names in the recipes folder)."""
        if not self.recipes_dir.is_dir():
            return []
        return sorted(p.name for p in self.recipes_dir.glob("*.yaml"))

    def recipe_path(self, name: str) -> Path:
        """The recipe file ``name`` of the recipes folder (never a path outside it)."""
        if name not in self.recipes():
            raise StationError(
                f"no recipe {name!r} in {self.recipes_dir}; choose one of "
                f"{', '.join(self.recipes()) or '(none)'}"
            )
        return self.recipes_dir / name

    # --- runs ------------------------------------------------------------------------------
    def start(self, recipe: str, operator: str, serial: str | None, where: str | None = None
              ) -> int:
        """Create a run of the recipe file ``recipe`` and execute it in the background, through
        the station's own :func:`~calstation.station.runs.prepare_run`. ``where`` is the
        station's address as the browser used it (named to whoever is refused the station
        meanwhile). :class:`~calstation.station.lock.StationBusy` when another run, from any
        front end, holds the station."""
        from calstation.recipes import load_recipe
        from calstation.storage.db.fields import operator_name, unit_serial
        from calstation.web.offer import refuse_unrunnable

        operator, serial = operator_name(operator), unit_serial(serial)
        self._take()
        try:
            refuse_unrunnable(self.recipe_path(recipe))
            loaded = load_recipe(self.recipe_path(recipe))
            serial = (serial or "").strip() or None
            ui = WebOperator(self.live, loaded.recipe)
            prepared = prepare_run(loaded, self.db, ui, operator=operator.strip(),
                                   front_end=self._front_end(where), data_dir=self.data_dir,
                                   serial=serial)
        except BaseException:
            self._lock.release()
            raise
        self.live.begin(prepared.run_id, loaded.recipe.name, operator.strip(), serial,
                        run_steps(loaded.recipe), station=loaded.recipe.station.id)
        self._launch(prepared)
        return prepared.run_id

    def resume(self, run_id: int, force: bool = False, where: str | None = None) -> int:
        """Continue run ``run_id`` at its first unfinished step (as ``calstation resume``),
        through the station's own :func:`~calstation.station.runs.prepare_resume`."""
        from calstation.recipes import parse_recipe

        self._take()
        try:
            with self.db.session() as s:
                # refused here, with its reason, rather than in the run's thread
                run = resumable_run(s, run_id, force)
                recipe = parse_recipe(run.recipe_text, f"recipe of run {run_id}")
                operator, serial = run.operator, run.unit_serial
            ui = WebOperator(self.live, recipe)
            prepared = prepare_resume(run_id, self.db, ui, front_end=self._front_end(where),
                                      force=force)
        except BaseException:
            self._lock.release()
            raise
        self.live.begin(run_id, recipe.name, operator, serial, run_steps(recipe),
                        station=recipe.station.id)
        self._launch(prepared)
        return run_id

    @staticmethod
    def _front_end(where: str | None) -> str:
        return f"the web station at {where}" if where else "a web station"

    def abort(self, reason: str) -> bool:
        """Abort the running run (the motor is stopped by the station); False if none runs."""
        return self.live.request_abort(reason)

    def join(self, timeout: float | None = None) -> bool:
        """Wait for the background run to end; True if none is running any more."""
        t = self._thread
        if t is not None:
            t.join(timeout)
            return not t.is_alive()
        return True

    @property
    def busy(self) -> bool:
        """A run is in progress."""
        return self._lock.locked()

    def _take(self) -> None:
        if not self._lock.acquire(blocking=False):
            snap = self.live.snapshot()
            raise Busy(
                f"run {snap['run_id']} ({snap['recipe']}, operator {snap['operator']}) is in "
                f"progress on this station, at step {snap['step'] or 'start-up'}; finish or "
                "abort it first"
            )

    def _launch(self, prepared: PreparedRun) -> None:
        run_id = prepared.run_id

        def main() -> None:
            status: str = RunStatus.FAILED
            error: str | None = None
            try:
                status = prepared.execute()  # gives the station back, however it ends
            except CalstationError as exc:
                error = str(exc)
                self.live.add_log("error", error)
            except BaseException as exc:
                error = f"{type(exc).__name__}: {exc}"
                self.live.add_log("error", error)
            finally:
                prepared.release()
                if self.released is not None:
                    with contextlib.suppress(Exception):  # the status line must not stop the end
                        self.released()
                self.live.finish(status, self._end_screen(run_id), error)
                self._lock.release()

        try:
            self._thread = threading.Thread(target=main, name=f"calstation-run-{run_id}",
                                            daemon=True)
            self._thread.start()
        except BaseException:
            prepared.release()
            self._lock.release()
            raise

    def _end_screen(self, run_id: int) -> EndScreen | None:
        from calstation.storage.report_html import report_data

        try:
            data = report_data(self.db, run_id, views=False)
        except Exception as exc:
            self.live.add_log("error", f"could not read run {run_id}: {exc}")
            return None
        from calstation.web.endscreen import end_screen

        return end_screen(data)

