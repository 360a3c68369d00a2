"""What a step works with: :class:`RunContext`, the run's database, folder, recipe, operator and
drivers, passed to each step instead of the whole station; and :class:`ScanFiles`, the recordings
of the step under way, which the station stores with the step however it ends."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

from calstation import plugins
from calstation.errors import StationError
from calstation.recipes import LoadedRecipe, Recipe
from calstation.station import stored
from calstation.station.hardware import Drivers
from calstation.station.operator import Operator
from calstation.station.prepared import PreparedScan
from calstation.storage.db import Calibration, Database

if TYPE_CHECKING:
    from calstation.engine.result import CalibrationResult
    from calstation.plugins.cost_strategies import Strategy


@dataclass
class ScanFiles:
    """The recordings of the step under way, as (kind, path), for the step's end to store even
    when the step fails or is aborted."""

    partial: list[tuple[str, Path]] = field(default_factory=list)
    """The recording being written, until it is complete (stored as ``partial``)."""
    finished: list[tuple[str, Path]] = field(default_factory=list)
    """Recordings a step completed before a later one (a second pass) began: a fault in the
    later one keeps them as ``complete``."""
    scan_ended: float | None = None
    """When this process's last spin scan ended (monotonic s): how long the operator waited
    for H after it is the fine-tuning's ``after_scan_s``."""

    def take(self) -> tuple[list[tuple[str, Path]], list[tuple[str, Path]]]:
        """(partial, finished) of the step under way, forgotten here: the step is ending."""
        taken = (self.partial, self.finished)
        self.partial, self.finished = [], []
        return taken


@dataclass
class RunContext:
    """The run a step works on: database, folder, recipe, operator, drivers, recordings.

    ``drivers`` is set while the station has them open; ``retrying`` is set by the station
    before each attempt: True when it follows a failed attempt of the same step (the cube scan
    then asks for the cube to be re-seated). ``prepared``: what a scan step prepared while its
    lines arrived, by the recording's path (:mod:`calstation.station.prepared`), for the steps
    after it.
    """

    db: Database
    run_id: int
    run_dir: Path
    loaded: LoadedRecipe
    ui: Operator
    drivers: Drivers | None = None
    retrying: bool = False
    scans: ScanFiles = field(default_factory=ScanFiles)
    prepared: dict[Path, PreparedScan] = field(default_factory=dict)

    def keep_prepared(self, scan: PreparedScan) -> None:
        """Keep what was prepared while ``scan.path`` was taken; a preparation of the returns
        (a few hundred MB for a long scan) is kept for the newest scan alone."""
        if scan.builder is not None:
            self.prepared = {p: replace(k, builder=None) for p, k in self.prepared.items()}
        self.prepared[scan.path] = scan

    @property
    def recipe(self) -> Recipe:
        """The run's recipe (the model, without its file)."""
        return self.loaded.recipe

    def hardware(self) -> Drivers:
        """The open drivers; :class:`StationError` when they are not open."""
        if self.drivers is None:
            raise StationError("the drivers are not open")
        return self.drivers

    def strategy(self) -> Strategy:
        """The recipe's fine-tuning strategy (the plugin registry's)."""
        return plugins.strategy(self.recipe.calibration.strategy)

    def stored_calibration(self, stage: str) -> Calibration:
        """The run's newest ``stage`` calibration (:func:`stored.stored_calibration`)."""
        return stored.stored_calibration(self.db, self.run_id, stage)

    def stored_result(self, stage: str) -> CalibrationResult:
        """The run's newest ``stage`` calibration as the engine's result
        (:meth:`~calstation.storage.db.Calibration.result`)."""
        return self.stored_calibration(stage).result()

    def artifact_path(self, kind: str) -> Path:
        """The run's newest complete ``kind`` recording, checked
        (:func:`stored.artifact_path`)."""
        return stored.artifact_path(self.db, self.run_id, kind)
