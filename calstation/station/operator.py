"""The operator's side of a run: the one interface between the station and its front ends.

The station (:mod:`calstation.station.machine`) talks to whoever runs it only through an
:class:`Operator`: it asks (``confirm_fixture``, ``on_failure``), reports (``info``, ``warn``,
``progress``, ``summary``) and publishes :class:`StationEvent` s (step started and finished, a
preview of the lidar line being recorded) through :func:`publish`. Two front ends implement it:
:class:`ConsoleOperator` here (``calstation run``, rich) and the web station's operator
(:mod:`calstation.web.live`, ``calstation serve``). The state machine, the database writes and
resume stay in the station.

:class:`ConsoleOperator` is the interactive terminal UI; with ``unattended=True`` (``--yes``) it
never asks: fixtures are placed by the ``calstation_fixture_placed`` hook (the simulator puts them
into its scene) and a failed step fails the run.
"""

from __future__ import annotations

import getpass
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

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

ProgressCallback = Callable[[str, float], None]
"""``progress(phase, fraction)``: a step reports what it does and how far it is (0..1)."""

Decision = Literal["retry", "abort"]

FIXTURE_PROMPTS: dict[str, str] = {
    "static_target": (
        "Place the L-shaped static target on the platter: base plate toward the lidar, the "
        "corner of base and wall over the platter centre. Keep the platter still."
    ),
    "spin_target": (
        "Place the heptagonal spin target off-centre, as the recipe's offset says (about 60 mm "
        "from the axis): a centred target cannot show the axis tilt out of the scan plane (ry), "
        "and the fine-tuning then refuses its result."
    ),
    "qa_cube": "Place the QA cube anywhere on the platter, standing on one face.",
    "none": "Clear the platter.",
}

PLACEMENT_ANSWERS: dict[str, tuple[str, ...]] = {"continue": ("continue", "c"),
                                                 "abort": ("abort", "a")}
"""What the terminal's placement prompt accepts: the scan starts on ``continue`` only."""

FAILURE_ANSWERS: dict[str, tuple[str, ...]] = {"retry": ("retry", "r"), "abort": ("abort", "a")}
"""What the terminal's failed-step prompt accepts: the step runs again on ``retry`` only."""


FIXTURE_NAMES: dict[str, str] = {
    "static_target": "L-shaped static target",
    "spin_target": "spin target",
    "qa_cube": "QA cube",
    "demo": "demonstration fixture",
}
"""What the operator calls each fixture of a recipe (messages never show the recipe's keys)."""

STEP_TITLES: dict[str, str] = {
    "preflight": "preflight check",
    "place_static_target": "place the L-shaped static target",
    "static_scan": "static scan and initial calibration",
    "place_spin_target": "place the spin target",
    "spin_scan": "spin scan",
    "fine_tune": "fine-tuning",
    "place_qa_cube": "place the QA cube",
    "cube_scan": "QA cube scan and check",
    "report": "report",
}
"""What the operator calls each step of a run."""


def fixture_name(fixture: str) -> str:
    """The operator's name of ``fixture`` (a ``fixtures`` key)."""
    return FIXTURE_NAMES.get(fixture, fixture.replace("_", " "))


def step_title(step: str) -> str:
    """The operator's name of ``step``."""
    return STEP_TITLES.get(step, step.replace("_", " "))


STEP_HINTS: dict[str, str] = {
    "preflight": "Check that the lidar is powered and connected, that the platter turns freely "
    "and that the encoder is connected, then retry.",
    "static_scan": "Check the L-target: base plate toward the lidar, the corner of base and wall "
    "over the platter centre, nothing between it and the lidar; then retry.",
    "spin_scan": "Check that the platter turns and nothing touches the spin target, then retry "
    "(the scan is taken again).",
    "fine_tune": "Check that the spin target stood on the platter, fully in view, during the "
    "spin scan; retry runs the fine-tuning again on the same recording.",
    "cube_scan": "Check that the QA cube stands on one face, fully in view, and nothing touches "
    "it; then retry (the scan is taken again).",
    "report": "Check the free disk space and the database connection, then retry.",
}
"""What the operator can do about a failed step (shown beside its error)."""

EVENT_KINDS: tuple[str, ...] = (
    "step_started", "step_finished", "lidar_line", "accuracy", "outline", "cloud")
"""What :class:`StationEvent` s a station publishes (prompts, progress and the final summary
are the :class:`Operator` methods of the same names)."""


@dataclass(frozen=True)
class StationEvent:
    """Something that happened in a run, for front ends to show.

    - ``step_started``: ``step``, ``attempt``.
    - ``step_finished``: ``step``, ``attempt``, ``status`` (``passed``/``failed``), ``result``
      (the step's JSON result as stored) and ``error``.
    - ``lidar_line``: ``kind`` (recording kind: static, spin, cube) and ``line`` (the
      :class:`~calstation.drivers.LidarLine` just written); published for every line, so a
      front end keeps only what it can show.
    - ``outline`` (to an operator with ``previews = True``, twice a second at most):
      ``scan``, ``fixture``, ``source`` (the calibration used, in words), ``known`` (False
      when no calibration is known yet), ``platter_angle_deg`` (turned since the fixture was
      placed) and ``lines``, closed polylines of [x_L, y_L] metres where the platter and the
      fixture should appear in the scan plane (:mod:`calstation.station.preview`).
    - ``cloud`` (likewise, spin and cube scans): ``scan``, ``source``, ``start`` (how many
      points this scan sent before) and ``points``, the new points [x, y, z] in D (m).
    """

    kind: str
    data: dict[str, Any] = field(default_factory=dict)


def publish(ui: Operator, kind: str, /, **data: Any) -> None:
    """Give ``ui`` the event ``kind`` if it listens (an ``event(StationEvent)`` method).

    Listening is optional so that a minimal operator (a script, a test) needs only the
    :class:`Operator` methods. An exception from the listener propagates: that is how a front
    end aborts a run mid-step (it raises ``AbortRun``).
    """
    listener = getattr(ui, "event", None)
    if listener is not None:
        listener(StationEvent(kind, data))


class Operator(Protocol):
    """What the station needs from whoever runs it."""

    unattended: bool

    def info(self, message: str) -> None:
        """Show a line of information."""
        ...

    def warn(self, message: str) -> None:
        """Show a warning."""
        ...

    def confirm_fixture(self, fixture: str, description: str) -> bool:
        """Ask the operator to place ``fixture``; False means the operator aborts the run."""
        ...

    def on_failure(self, step: str, error: str, attempt: int) -> Decision:
        """A step failed: retry it, or abort the run."""
        ...

    def progress(self, title: str) -> Any:
        """A context manager yielding a :data:`ProgressCallback` for one long step."""
        ...

    def summary(self, summary: dict[str, Any]) -> None:
        """Show the run's final PASS/FAIL summary (``summary`` as from ``report.run_summary``)."""
        ...

    # Optional: ``def event(self, event: StationEvent) -> None`` receives every
    # :class:`StationEvent` (see :func:`publish`); ``previews = True`` asks for the
    # ``outline`` and ``cloud`` events too.


class ConsoleOperator:
    """The terminal operator UI (rich). ``unattended`` answers every question itself."""

    def __init__(
        self, unattended: bool = False, console: Console | None = None, max_retries: int = 3
    ) -> None:
        self.unattended = unattended
        self.console = console or Console()
        self.max_retries = max_retries

    def info(self, message: str) -> None:
        """Print a line."""
        self.console.print(message, highlight=False)

    def event(self, event: StationEvent) -> None:
        """Print the start of each step (the console shows no live lidar lines)."""
        if event.kind == "step_started":
            self.console.print(
                f"[bold]▶ {event.data['step']}[/] (attempt {event.data['attempt']})",
                highlight=False,
            )

    def warn(self, message: str) -> None:
        """Print a warning."""
        self.console.print(f"[yellow]warning:[/] {escape(message)}", highlight=False)

    def confirm_fixture(self, fixture: str, description: str) -> bool:
        """Prompt "place …", then wait for ``continue`` or ``abort`` (unattended: announce and
        go on)."""
        text = FIXTURE_PROMPTS.get(fixture, f"Place the {fixture} on the platter.")
        if description:
            text += f"\n[dim]{escape(description)}[/]"
        if self.unattended:
            self.console.print(f"[cyan]→ {fixture}[/]: placed automatically (--yes)")
            return True
        self.console.print(Panel(text, title=f"operator: {fixture}", border_style="cyan"))
        return self._ask(PLACEMENT_ANSWERS, "when it is placed") == "continue"

    def on_failure(self, step: str, error: str, attempt: int) -> Decision:
        """Show the error; ask retry/abort (unattended: abort)."""
        hint = STEP_HINTS.get(step)
        self.console.print(
            Panel(
                escape(error) + (f"\n[dim]{escape(hint)}[/]" if hint else ""),
                title=f"step {step} failed (attempt {attempt})", border_style="red",
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
                bar.update(
                    task,
                    description=f"{title}: {phase}" if phase else title,
                    completed=max(0.0, min(1.0, float(fraction))),
                )

            yield update
            bar.update(task, completed=1.0, description=title)

    def summary(self, summary: dict[str, Any]) -> None:
        """The final verdict: PASS/FAIL banner, calibration (mm, deg) and cube check."""
        render_summary(self.console, summary)


def _print_predicted_error(console: Console, calibrations: list[dict[str, Any]]) -> None:
    """The predicted reconstruction error of the final calibration beside its budget."""
    final = next((c for c in calibrations if c["accepted"]), None) or next(
        (c for c in reversed(calibrations) if c.get("predicted_error_m") is not None), None)
    if final is None or final.get("predicted_error_m") is None:
        return
    error, budget = final["predicted_error_m"], final.get("budget_m")
    record = (final.get("diagnostics") or {}).get("predicted_error") or {}
    volume = record.get("work_volume") or {}
    where = (f" over the work volume r {volume['radius_m'] * 1e3:.0f} mm × h "
             f"{volume['height_m'] * 1e3:.0f} mm" if volume else "")
    level = record.get("level", 0.95)
    if budget is None:
        verdict = ""
    elif error <= budget:
        verdict = f" ≤ budget {budget * 1e3:.3f} mm [green]✔[/]"
    else:
        verdict = f" > budget {budget * 1e3:.3f} mm [red]✘[/]"
    turns = record.get("turns")
    after = f", after {turns:g} turns" if isinstance(turns, int | float) else ""
    console.print(f"predicted reconstruction error ({final['stage']}, {level:.0%}{where}{after}): "
                  f"{error * 1e3:.3f} mm{verdict}", highlight=False)


def _print_range_model(console: Console, calibrations: list[dict[str, Any]]) -> None:
    """The lidar's range model of the final calibration, when it has one."""
    from calstation.engine.rangemodel import describe

    final = next((c for c in calibrations if c["accepted"]), None) or (
        calibrations[-1] if calibrations else None)
    text = None if final is None else describe(final)
    if final is not None and text:
        console.print(f"lidar range model ({final['stage']}): {text}; every range is corrected "
                      "by it", highlight=False)


def render_summary(console: Console, s: dict[str, Any]) -> None:
    """Print a run summary in display units (mm, deg) with a PASS/FAIL banner."""
    import math

    status = s["status"]
    style = {"passed": "bold white on green", "failed": "bold white on red"}.get(
        status, "bold black on yellow"
    )
    verdict = {"passed": "PASS", "failed": "FAIL"}.get(status, status.upper())
    table = Table(
        title=f"run {s['id']} — station {s['station']} — recipe {s['recipe_name']}",
        caption="tx, ty, tz in mm; rx, ry, rz in degrees; ✔ accepted; ✘ refused (stored, "
        "never accepted)",
    )
    table.add_column("")
    for p in ("tx", "ty", "tz", "rx", "ry", "rz"):
        table.add_column(p, justify="right")
    table.add_column("strategy")
    def shown(p: str, v: float) -> str:
        return f"{v * 1000:.3f}" if p.startswith("t") else f"{math.degrees(v):.4f}"

    refused = []
    for c in s["calibrations"]:
        if c.get("refused"):
            refused.append(c)
        row = [c["stage"] + (" ✔" if c["accepted"] else "") + (" ✘ refused" if c.get("refused")
                                                             else "")]
        for p, v in c["H"].items():
            row.append(shown(p, v))
        row.append(c["strategy"])
        table.add_row(*row)
        sig = c["sigma"]
        if any(v is not None for v in sig.values()):
            srow = ["  ±1σ"]
            for p, v in sig.items():
                if v is None:
                    srow.append("—")
                else:
                    srow.append(shown(p, v))
            srow.append("")
            table.add_row(*srow, style="dim")
    console.print(table)
    _print_predicted_error(console, s["calibrations"])
    _print_range_model(console, s["calibrations"])
    for c in refused:
        console.print(f"[red]✘[/] calibration {c.get('id', '—')} ({c['stage']}, {c['strategy']}) "
                      f"refused: {escape('; '.join(c['refused']))}", highlight=False)
    cube = s.get("cube_check")
    if cube:
        edges = ", ".join(f"{e * 1000:.2f}" for e in cube["face_edges"])
        console.print(
            f"QA cube: face-fit edges [{edges}] mm, edge error {cube['edge_error'] * 1000:.2f} mm, "
            f"OBB error {cube['obb_error'] * 1000:.2f} mm, flatness RMS "
            f"{cube['flatness_rms'] * 1000:.2f} mm{_beyond_noise(cube)}, perpendicularity "
            f"{cube['perpendicularity_deg']:.3f}°, side-face twist "
            f"{_twist(cube)} → {'pass' if cube['passed'] else 'FAIL'}",
            highlight=False,
        )
        for f in cube.get("failures") or []:
            console.print(f"  [red]✘[/] {escape(str(f))}")
    limits = s.get("qa_limits")
    if limits:
        console.print(
            f"limits: edge error ≤ {limits['edge_error'] * 1000:.2f} mm, OBB error ≤ "
            f"{limits['obb_edge_error'] * 1000:.2f} mm, flatness beyond the range noise ≤ "
            f"{limits['flatness_rms'] * 1000:.2f} mm, perpendicularity ≤ "
            f"{limits['perpendicularity_deg']:.3f}°"
            + (f", side-face twist ≤ {limits['twist_deg']:.3f}°" if "twist_deg" in limits else "")
            + "; drift ≤ "
            f"{limits['drift_translation'] * 1000:.2f} mm / {limits['drift_rotation_deg']:.3f}°"
            + (" (fails the run)" if limits.get("drift_fails") else " (warns)"),
            highlight=False,
        )
    if s.get("error"):
        console.print(f"[red]{escape(s['error'])}[/]")
    console.print(Panel(f"{verdict}", style=style, expand=False))


def _beyond_noise(cube: dict[str, Any]) -> str:
    """`` (0.05 mm beyond the range noise)``, or nothing for checks stored without it."""
    excess = cube.get("flatness_excess")
    if excess is None or excess != excess:
        return ""
    return f" ({excess * 1000:.2f} mm beyond the range noise)"


def _twist(cube: dict[str, Any]) -> str:
    """The side faces' twist as ``+0.012° (±0.030°)``, or ``—`` for checks stored without it."""
    twist, sigma = cube.get("twist_deg"), cube.get("twist_sigma_deg")
    if twist is None or twist != twist:
        return "—"
    return f"{twist:+.3f}° (±{sigma if sigma is not None else float('nan'):.3f}°)"


def default_operator() -> str:
    """Who runs the station when nobody says: ``$CALSTATION_OPERATOR``, else the login name."""
    try:
        return os.environ.get("CALSTATION_OPERATOR") or getpass.getuser()
    except Exception:  # no login name in a container, say
        return "unknown"
