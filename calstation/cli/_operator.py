"""The terminal's operator (``calstation run``, ``calstation resume``) and the run summary
``calstation show`` prints: the console front end of :mod:`calstation.station.operator`.

The station sends plain text and plain data; this module renders them (rich): messages escaped,
numbers through :mod:`calstation.display`. A prompt takes only the words it lists
(:data:`PLACEMENT_ANSWERS`, :data:`FAILURE_ANSWERS`) and asks again otherwise, so nothing moves
without an explicit ``continue`` or ``retry``. With ``unattended=True`` (``--yes``) it never
asks: fixtures are placed by the ``calstation_fixture_placed`` hook (the simulator puts them into
its scene) and a failed step fails the run.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from rich.console import Console
from rich.markup import escape
from rich.panel import Panel
from rich.progress import (
    BarColumn,
    Progress,
    SpinnerColumn,
    TaskProgressColumn,
    TextColumn,
    TimeElapsedColumn,
)
from rich.table import Table

from calstation import display
from calstation.station.operator import (
    STEP_HINTS,
    Decision,
    ProgressCallback,
    StationEvent,
)
from calstation.storage.db.models import RunStatus

# Any: the run summary as the station's Operator protocol passes it (storage's run mapping),
# and its parts (calibrations, cube check, QA limits) read from it
Stored = dict[str, Any]

PLACEMENT_ANSWERS: dict[str, tuple[str, ...]] = {"continue": ("continue", "c"),
                                                 "abort": ("abort", "a")}
"""What the terminal's placement prompt accepts: the scan starts on ``continue`` only."""

FAILURE_ANSWERS: dict[str, tuple[str, ...]] = {"retry": ("retry", "r"), "abort": ("abort", "a")}
"""What the terminal's failed-step prompt accepts: the step runs again on ``retry`` only."""


UNFINISHED = 0.999
"""The most a step's bar shows before the step ends (it reads 100 % already)."""


class ConsoleOperator:
    """The terminal operator UI (rich). ``unattended`` answers every question itself."""

    def __init__(
        self, unattended: bool = False, console: Console | None = None, max_retries: int = 3
    ) -> None:
        self.unattended = unattended
        self.console = console or Console()
        self.max_retries = max_retries

    def info(self, message: str) -> None:
        """Print a line (the station's plain text, as it is)."""
        self.console.print(escape(message), highlight=False)

    def event(self, event: StationEvent) -> None:
        """Print the start of each step (the console shows no live lidar lines)."""
        if event.kind == "step_started":
            attempt = event.data["attempt"]
            self.console.print(
                f"[bold]▶ {escape(display.step_title(event.data['step']))}[/]"
                + (f" (attempt {attempt})" if attempt > 1 else ""), highlight=False)

    def warn(self, message: str) -> None:
        """Print a warning."""
        self.console.print(f"[yellow]warning:[/] {escape(message)}", highlight=False)

    def confirm_fixture(self, fixture: str, description: str) -> bool:
        """Prompt "place …", then wait for ``continue`` or ``abort`` (unattended: announce and
        go on)."""
        name = display.fixture_name(fixture)
        if self.unattended:
            self.console.print(f"[cyan]→ {escape(name)}[/]: placed automatically (--yes)")
            return True
        self.console.print(Panel(escape(description), title=f"place the {escape(name)}",
                                 border_style="cyan"))
        return self._ask(PLACEMENT_ANSWERS, "when it is placed") == "continue"

    def on_failure(self, step: str, error: str, attempt: int) -> Decision:
        """Show the error; ask retry/abort (unattended: abort)."""
        hint = STEP_HINTS.get(step)
        self.console.print(
            Panel(
                escape(error) + (f"\n[dim]{escape(hint)}[/]" if hint else ""),
                title=f"{escape(display.step_title(step))} failed (attempt {attempt})",
                border_style="red",
            )
        )
        if self.unattended or attempt > self.max_retries:
            return "abort"
        return "retry" if self._ask(FAILURE_ANSWERS, "to run the step again") == "retry" \
            else "abort"

    def _ask(self, answers: dict[str, tuple[str, ...]], why: str) -> str:
        """Ask until the operator types one of ``answers``' words; the answer's key. Anything
        else (an empty line, ``x``, ``exit``) asks again: only a listed word moves the run on.
        The end of the input (Ctrl-D, a closed pipe) aborts."""
        go, *_ = answers
        words = "; ".join(f"[bold]{w[0]}[/] ({w[1]}) {why if key == go else 'to abort the run'}"
                          for key, w in answers.items())
        question = f"Type {words}: "
        while True:
            try:
                typed = self.console.input(question)
            except EOFError:
                return "abort"
            said = typed.strip().lower()
            for key, accepted in answers.items():
                if said in accepted:
                    return key
            shown = f"“{escape(typed.strip()[:40])}”" if typed.strip() else "An empty line"
            listed = ", ".join(w for a in answers.values() for w in a)
            self.console.print(f"[yellow]{shown} is not an answer here[/]: nothing moves until "
                               f"you type one of {listed}", highlight=False)

    @contextmanager
    def progress(self, title: str) -> Iterator[ProgressCallback]:
        """A progress bar for one step; the callback sets its phase and fraction."""
        with Progress(
            SpinnerColumn(),
            TextColumn("{task.description}"),
            BarColumn(),
            TaskProgressColumn(),
            TimeElapsedColumn(),
            console=self.console,
            transient=False,
        ) as bar:
            task = bar.add_task(title, total=1.0)

            def update(phase: str, fraction: float) -> None:
                # a phase's 1.0 is not the step's end: a bar that reached its total stops its
                # clock for good, and the next phase would count from 0:00:00 again
                bar.update(
                    task,
                    description=f"{title}: {phase}" if phase else title,
                    completed=max(0.0, min(UNFINISHED, float(fraction))),
                )

            yield update
            bar.update(task, completed=1.0, description=title)

    def summary(self, summary: Stored) -> None:
        """The final verdict: PASS/FAIL banner, calibration (mm, deg) and cube check."""
        render_summary(self.console, summary)


def _print_predicted_error(console: Console, calibrations: list[Stored]) -> None:
    """The predicted reconstruction error of the final calibration beside its budget."""
    final = next((c for c in calibrations if c["accepted"]), None) or next(
        (c for c in reversed(calibrations) if c.get("predicted_error_m") is not None), None)
    if final is None or final.get("predicted_error_m") is None:
        return
    error, budget = final["predicted_error_m"], final.get("budget_m")
    record = (final.get("diagnostics") or {}).get("predicted_error") or {}
    volume = record.get("work_volume") or {}
    where = (f" over the work volume r {display.number('distance', volume['radius_m'])} × h "
             f"{display.number('distance', volume['height_m'])}" if volume else "")
    level = display.percent(record.get("level", 0.95), 0)
    if budget is None:
        verdict = ""
    elif error <= budget:
        verdict = f" ≤ budget {display.number('predicted_error', budget)} [green]✔[/]"
    else:
        verdict = f" > budget {display.number('predicted_error', budget)} [red]✘[/]"
    turns = record.get("turns")
    after = f", after {display.count(turns, 'turn')}" if isinstance(turns, int | float) else ""
    console.print(f"predicted reconstruction error ({final['stage']}, {level}{where}{after}): "
                  f"{display.number('predicted_error', error)}{verdict}", highlight=False)


def _print_range_model(console: Console, calibrations: list[Stored]) -> None:
    """The lidar's range model of the final calibration, when it has one."""
    from calstation.engine.rangemodel import describe

    final = next((c for c in calibrations if c["accepted"]), None) or (
        calibrations[-1] if calibrations else None)
    text = None if final is None else describe(
        final, (final.get("diagnostics") or {}).get("certificate"))
    if final is not None and text:
        console.print(f"lidar range model ({final['stage']}): {text}; every range is corrected "
                      "by it", highlight=False)


_BANNER: dict[str, tuple[str, str]] = {
    RunStatus.PASSED: ("PASS", "bold white on green"),
    RunStatus.FAILED: ("FAIL", "bold white on red"),
}
"""The verdict's banner and its style by the run's status (any other: its name, yellow)."""


def render_summary(console: Console, s: Stored) -> None:
    """Print a run summary in display units (mm, deg) with a PASS/FAIL banner."""
    status = s["status"]
    verdict, style = _BANNER.get(status, (status.upper(), "bold black on yellow"))
    _calibration_table(console, s)
    _print_predicted_error(console, s["calibrations"])
    _print_range_model(console, s["calibrations"])
    for c in s["calibrations"]:
        if c.get("refused"):
            console.print(f"[red]✘[/] calibration {c.get('id', '—')} ({c['stage']}, "
                          f"{c['strategy']}) refused: {escape('; '.join(c['refused']))}",
                          highlight=False)
    cube = s.get("cube_check")
    if cube:
        _print_cube(console, cube)
    limits = s.get("qa_limits")
    if limits:
        _print_limits(console, limits)
    if s.get("error"):
        console.print(f"[red]{escape(s['error'])}[/]")
    console.print(Panel(f"{verdict}", style=style, expand=False))


def _calibration_table(console: Console, s: Stored) -> None:
    """The run's calibrations, each with its ±1σ row; "not estimated" for a held parameter.
    Nothing when the run stored none (aborted before its first scan)."""
    if not s["calibrations"]:
        console.print("no calibration was stored in this run", highlight=False)
        return
    table = Table(
        title=f"run {s['id']} — station {s['station']} — recipe {s['recipe_name']}",
        caption="✔ accepted; ✘ refused (stored, never accepted); ±1σ below each value",
    )
    table.add_column("")
    for p in display.H_PARAMS:
        table.add_column(display.quantity(p).heading, justify="right")
    table.add_column("strategy")
    for c in s["calibrations"]:
        held = set(c.get("not_estimated") or [p for p in c["H"] if display.not_estimated(
            c["H"][p], c["sigma"].get(p))])
        label = c["stage"] + (" ✔" if c["accepted"] else "") + (" ✘ refused" if c.get("refused")
                                                               else "")
        table.add_row(label, *(display.NOT_ESTIMATED if p in held
                               else display.number(p, v, unit=False)
                               for p, v in c["H"].items()), c["strategy"])
        sig = c["sigma"]
        if any(v is not None for v in sig.values()):
            table.add_row("  ±1σ", *("" if p in held else display.number(p, v, unit=False)
                                     for p, v in sig.items()), "", style="dim")
    console.print(table)


def _print_cube(console: Console, cube: Stored) -> None:
    edges = ", ".join(display.number("edge", e, unit=False) for e in cube["face_edges"])
    if cube.get("height_judged") is False:
        edges += " (the height from a platter of another finish: not judged)"
    excess = cube.get("flatness_excess")
    beyond = ("" if excess is None or excess != excess
              else f" ({display.number('flatness_excess', excess)} beyond the range noise)")
    twist = cube.get("twist_deg")
    twist_text = (display.MISSING if twist is None or twist != twist else
                  f"{display.number('twist_deg', twist, signed=True)} "
                  f"({display.sigma_text('twist_deg', cube.get('twist_sigma_deg'))})")
    console.print(
        f"QA cube: face-fit edges [{edges}] mm, edge error "
        f"{display.number('edge_error', cube['edge_error'])}, OBB error "
        f"{display.number('obb_error', cube['obb_error'])}, flatness RMS "
        f"{display.number('flatness_rms', cube['flatness_rms'])}{beyond}, perpendicularity "
        f"{display.number('perpendicularity_deg', cube['perpendicularity_deg'])}, side-face "
        f"twist {twist_text} → {'pass' if cube['passed'] else 'FAIL'}",
        highlight=False,
    )
    for f in cube.get("failures") or []:
        console.print(f"  [red]✘[/] {escape(str(f))}")


def _print_limits(console: Console, limits: Stored) -> None:
    twist = (f", side-face twist ≤ {display.number('twist_deg', limits['twist_deg'])}"
             if "twist_deg" in limits else "")
    console.print(
        f"limits: edge error ≤ {display.number('edge_error', limits['edge_error'])}, OBB error "
        f"≤ {display.number('obb_error', limits['obb_edge_error'])}, flatness beyond the range "
        f"noise ≤ {display.number('flatness_rms', limits['flatness_rms'])}, perpendicularity ≤ "
        f"{display.number('perpendicularity_deg', limits['perpendicularity_deg'])}{twist}; "
        f"drift ≤ {display.number('tx', limits['drift_translation'])} / "
        f"{display.number('rz', math.radians(limits['drift_rotation_deg']))}"
        + (" (fails the run)" if limits.get("drift_fails") else " (warns)"),
        highlight=False,
    )
