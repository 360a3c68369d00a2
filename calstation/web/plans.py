"""The station designer's page (``/plan``): ``calstation plan`` of a recipe of the station's
recipes folder, run in the background of the server, one at a time, and its result.

A plan simulates the recipe's station for a minute or so (:mod:`calstation.bench.plan`); it
moves nothing, but it takes the processor, so it is refused while a run is in progress, and a
run may start while a plan computes. Starting one is a state-changing request like any other
(the session, CSRF and origin checks of :mod:`calstation.web.security`).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, TypedDict

from calstation.errors import CalstationError
from calstation.web.live import Busy, Runner

if TYPE_CHECKING:
    from calstation.bench.plan import Plan


class PlanState(TypedDict, total=False):
    """A plan's state for the page (:meth:`Planner.snapshot`)."""

    status: str
    recipe: str
    seeds: int
    turns: int
    progress: str
    fraction: float
    started: float
    finished: float
    elapsed_s: float
    left_s: float | None
    progress_text: str
    plan: Plan
    error: str


class Planner:
    """One plan at a time, in a background thread; its state for the page."""

    def __init__(self, runner: Runner) -> None:
        self.runner = runner
        self._lock = threading.Lock()
        self._state: PlanState = {"status": "idle"}

    def snapshot(self) -> PlanState:
        """The page's JSON twin: ``status`` (idle, running, done, failed), the recipe, the
        progress (while running: ``elapsed_s``, the estimated ``left_s``, None before the first
        stage is done, and ``progress_text`` in words), the plan
        (:func:`calstation.bench.plan.plan`) or the error."""
        with self._lock:
            state = self._state.copy()
        if state["status"] == "running":
            from calstation import display

            elapsed = time.time() - state["started"]
            state["elapsed_s"] = elapsed
            state["left_s"] = display.time_left(elapsed, state["fraction"])
            state["progress_text"] = display.progress_text(state["progress"],
                                                           state["fraction"], elapsed)
        return state

    def start(self, recipe: str, seeds: int, turns: int) -> None:
        """Plan ``recipe`` (a file of the recipes folder) in the background; :class:`Busy`
        while another plan computes or a run is in progress."""
        path = self.runner.recipe_path(recipe)
        with self._lock:
            if self._state["status"] == "running":
                raise Busy(f"a plan of {self._state['recipe']} is being computed; wait for it")
            if self.runner.busy:
                raise Busy("a run is in progress on this station: plan when it has ended")
            self._state = {"status": "running", "recipe": recipe, "seeds": seeds, "turns": turns,
                           "progress": "starting", "fraction": 0.0, "started": time.time()}
        threading.Thread(target=self._plan, args=(path, seeds, turns), daemon=True,
                         name="calstation-plan").start()

    def _plan(self, path: Path, seeds: int, turns: int) -> None:
        from calstation.bench.plan import plan
        from calstation.recipes import load_recipe

        def progress(message: str, fraction: float) -> None:
            with self._lock:
                self._state["progress"], self._state["fraction"] = message, fraction

        try:
            result = plan(load_recipe(path), seeds=seeds, turns=turns, progress=progress)
        except CalstationError as exc:
            update: PlanState = {"status": "failed", "error": str(exc)}
        except Exception as exc:  # a fault in the plan must not take the server down
            update = {"status": "failed", "error": f"{type(exc).__name__}: {exc}"}
        else:
            update = {"status": "done", "plan": result}
        with self._lock:
            self._state.update(update)
            self._state["finished"] = time.time()
