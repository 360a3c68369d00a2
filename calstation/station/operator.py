"""The operator's side of a run: the one interface between the station and its front ends.

The station (:mod:`calstation.station.machine`) talks to whoever runs it only through an
:class:`Operator`: it asks (``confirm_fixture``, ``on_failure``), reports (``info``, ``warn``,
``progress``, ``summary``) and publishes :class:`StationEvent` s (step started and finished, a
preview of the lidar line being recorded) through :func:`publish`. Everything it sends is plain
text and plain data: no markup, numbers in words made by :mod:`calstation.display`; each front
end renders it its own way. Two front ends implement it: the terminal's
(:mod:`calstation.cli._operator`, ``calstation run``) and the web station's
(:mod:`calstation.web.live`, ``calstation serve``). The state machine, the database writes and
resume stay in the station.
"""

from __future__ import annotations

import getpass
import math
import os
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol, runtime_checkable

from calstation import display
from calstation.display import fixture_name

ProgressCallback = Callable[[str, float], None]
"""``progress(phase, fraction)``: a step reports what it does and how far it is (0..1)."""

Decision = Literal["retry", "abort"]

def placement_prompt(fixture: str, geometry: object) -> str:
    """What the operator is asked at a placement, in words, from the recipe's ``geometry`` of
    ``fixture`` (a ``fixtures`` key): where its centre goes and how it is turned, as the
    placement drawing shows it."""
    name = fixture_name(fixture)
    if fixture == "static_target":
        return ("Place the L-shaped static target on the platter: base plate toward the lidar, "
                "the corner of base and wall over the platter centre. Keep the platter still.")
    if geometry is None:
        return "Clear the platter." if fixture == "none" else f"Place the {name} on the platter."
    offset = getattr(geometry, "offset", None)
    if offset is None or math.hypot(*offset) < 1e-4:
        where = "its centre on the axis"
    else:
        where = (f"its centre {display.number('distance', math.hypot(*offset))} from the axis "
                 f"(y {display.number('distance', offset[0], signed=True)}, z "
                 f"{display.number('distance', offset[1], signed=True)})")
    yaw = float(getattr(geometry, "yaw_deg", 0.0) or 0.0)
    turned = f", turned {yaw:g}°" if yaw else ""
    stand = ", standing on one face" if fixture == "qa_cube" else ""
    return f"Place the {name} on the platter{stand}, {where}{turned}, as the drawing shows."


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
    data: dict[str, Any] = field(default_factory=dict)  # Any: each kind's fields, listed above


def publish(ui: Operator, kind: str, /, **data: object) -> None:
    """Give ``ui`` the event ``kind`` if it listens (an ``event(StationEvent)`` method).

    Listening is optional so that a minimal operator (a script, a test) needs only the
    :class:`Operator` methods. An exception from the listener propagates: that is how a front
    end aborts a run mid-step (it raises ``AbortRun``).
    """
    if isinstance(ui, ListensToEvents):
        ui.event(StationEvent(kind, data))


class Operator(Protocol):
    """What the station needs from whoever runs it."""

    unattended: bool

    def info(self, message: str) -> None:
        """Show a line of information (plain text)."""
        ...

    def warn(self, message: str) -> None:
        """Show a warning (plain text)."""
        ...

    def confirm_fixture(self, fixture: str, description: str) -> bool:
        """Ask the operator to place ``fixture`` as ``description`` says (plain text, from the
        recipe: :func:`placement_prompt`); False means the operator aborts the run. Nothing
        may move before it returns True."""
        ...

    def on_failure(self, step: str, error: str, attempt: int) -> Decision:
        """A step failed: retry it, or abort the run."""
        ...

    def progress(self, title: str) -> AbstractContextManager[ProgressCallback]:
        """A context manager yielding a :data:`ProgressCallback` for one long step."""
        ...

    def summary(self, summary: dict[str, Any]) -> None:  # Any: storage's run mapping
        """Show the run's final PASS/FAIL summary (``summary`` as from ``report.run_summary``)."""
        ...

    # Optional: :class:`ListensToEvents` and :class:`WantsPreviews`.


@runtime_checkable
class ListensToEvents(Protocol):
    """An operator that listens to the run's events: ``event`` receives every
    :class:`StationEvent` (see :func:`publish`)."""

    def event(self, event: StationEvent) -> None:
        """One event of the run."""
        ...


@runtime_checkable
class WantsPreviews(Protocol):
    """An operator whose ``previews`` is True asks for the ``outline`` and ``cloud`` events
    too."""

    previews: bool


def default_operator() -> str:
    """Who runs the station when nobody says: ``$CALSTATION_OPERATOR``, else the login name."""
    try:
        return os.environ.get("CALSTATION_OPERATOR") or getpass.getuser()
    except Exception:  # no login name in a container, say
        return "unknown"
