"""What a scan step prepared while its lines arrived, handed explicitly to the steps after it
through the run's context (:attr:`calstation.station.context.RunContext.prepared`).

A spin or cube scan's returns are prepared line by line as they arrive
(:class:`~calstation.engine.spinscan.SpinScanBuilder`), and a scan that turns until the accuracy
budget holds fine-tunes the turns so far while it goes on (:class:`ScanTurns`). The fine-tune
and cube steps take both from here instead of preparing or fitting the recording again; a run
resumed by another process finds nothing here and prepares its recordings from their files.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, NotRequired, TypedDict

from calstation.engine.accuracy import PredictedError
from calstation.engine.result import CalibrationResult
from calstation.engine.spinscan import SpinScanBuilder

if TYPE_CHECKING:
    from calstation.pipeline.stages import CubeChecked


@dataclass(frozen=True)
class TurnFit:
    """A fine-tuning on the first ``turns`` whole revolutions of a scan under way."""

    turns: int
    result: CalibrationResult
    predicted: PredictedError
    seconds: float
    """how long the fit took"""
    lines: int | None = None
    """the recording's first lines the fit saw (those prepared when its turn was complete)"""
    stage: CubeChecked | None = None
    """the pipeline's cube stage the fit made (the cube scan's, with the lidar's range model):
    the step after the scan takes it as it is"""


class FitRecord(TypedDict):
    """One fit of a scan under way, as its summary keeps it (m, s)."""

    turns: int
    predicted_error_m: float
    seconds: float
    lines: NotRequired[int | None]
    """absent from a summary stored before the fits kept their lines"""


class TurnsSummary(TypedDict):
    """What a scan that went on turn by turn did (:meth:`~calstation.station.turns.TurnByTurn.
    summary`), stored as the scan step's ``turn_by_turn``: why it stopped (``budget``,
    ``turns``, ``time``, ``fit``: a fit said more turns would not help), the budget (m), the
    most turns, each fit and each failed one, and the whole turns scanned once it ended."""

    stopped: str
    budget_m: float
    max_revolutions: float
    fits: list[FitRecord]
    failed_fits: list[str]
    whole_turns: NotRequired[int]
    met_turns: NotRequired[int]
    """the turns of the fit the scan stopped on (absent from a summary stored before it was
    kept: its fits end with that one)"""


@dataclass(frozen=True)
class ScanTurns:
    """What a scan that went on turn by turn did: the fit that met the budget (None when none
    did: the step after the scan fine-tunes the whole recording), and its
    :meth:`~calstation.station.turns.TurnByTurn.summary`."""

    fit: TurnFit | None
    summary: TurnsSummary


@dataclass(frozen=True)
class PreparedScan:
    """What was prepared while the recording at ``path`` was taken: its returns as they arrived
    (``builder``; None once a later scan needed the memory) and what it did turn by turn
    (``turns``; None when it took exactly its revolutions), and the lidar lines its stream lost
    (``lost_lines``, :class:`~calstation.station.acquisition.LineGaps`)."""

    path: Path
    builder: SpinScanBuilder | None = None
    turns: ScanTurns | None = None
    lost_lines: int = 0

    @property
    def met(self) -> TurnFit | None:
        """The fit within the budget the scan stopped on; None when it did not stop on one."""
        return None if self.turns is None else self.turns.fit

    def fitted(self) -> tuple[int, int | None] | None:
        """(whole turns, the recording's first lines) the fit that met the budget saw; None
        when the scan did not stop on one."""
        fit = self.met
        return None if fit is None else (fit.turns, fit.lines)
