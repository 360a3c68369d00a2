"""Recording a scan into the run's folder while it is taken.

:func:`record_scan` writes ``<run dir>/<stem>.mcap`` (``static``, ``spin``, ``cube``, a second
pass ``spin-pass2`` …, :mod:`calstation.recordings.runfolder`) as the acquisition runs, with the
run, the recipe, the newest calibration and (simulator) the scene's truth in its metadata. Every
lidar line also goes to the operator (live preview) and, for a spin or cube scan, to the
fine-tuning's preparation (:class:`~calstation.engine.spinscan.SpinScanBuilder`), so no step
after the scan re-reads what it could prepare while scanning. The files of the step under way are
tracked in the context's :class:`~calstation.station.context.ScanFiles`, for the step's end to
store them whatever happens.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
from sqlalchemy import select

from calstation.drivers import DriverContext, EncoderSample, LidarLine, TurntableStatus
from calstation.engine.spinscan import SpinScanBuilder
from calstation.jsonvalue import JSONObject
from calstation.recordings.runfolder import RECORDING_OF
from calstation.station.acquisition import (
    LineGaps,
    MoreTurns,
    Writer,
    acquire_spin,
    acquire_static,
    lost_lines_warning,
)
from calstation.station.context import RunContext
from calstation.station.hardware import Drivers
from calstation.station.operator import Operator, ProgressCallback, publish
from calstation.station.outcome import plain
from calstation.station.prepared import PreparedScan
from calstation.station.preview import ScanPreview, wants_previews
from calstation.station.stored import latest_calibration
from calstation.station.turns import TurnByTurn
from calstation.storage.db import Artifact

if TYPE_CHECKING:
    from calstation.recipes import SpinScanStep

Acquire = Callable[[Writer, ProgressCallback, "MoreTurns | None"], None]
"""``acquire(writer, progress, more)``: takes a scan into ``writer``, reporting its progress,
turning on while ``more`` asks (a spin scan)."""

MoreTurnsOf = Callable[[SpinScanBuilder], "TurnByTurn | None"]
"""What decides, from the scan prepared so far, whether a spin scan goes on (None: it does
not)."""


def static_acquisition(d: Drivers, lines: int) -> Acquire:
    """A static scan of ``lines`` lines on the drivers ``d``."""

    def acquire(writer: Writer, progress: ProgressCallback, more: MoreTurns | None) -> None:
        acquire_static(d.lidar, d.encoder, writer, lines=lines, progress=progress)

    return acquire


def spin_acquisition(d: Drivers, cfg: SpinScanStep) -> Acquire:
    """A spin scan at ``cfg.rpm`` for ``cfg.revolutions`` turns on the drivers ``d``, and on
    while ``more`` asks (:class:`~calstation.station.turns.TurnByTurn`)."""

    def acquire(writer: Writer, progress: ProgressCallback, more: MoreTurns | None) -> None:
        acquire_spin(
            d.lidar, d.turntable, d.encoder, writer, rpm=cfg.rpm, revolutions=cfg.revolutions,
            settle_s=cfg.settle_s, clock=d.clock, progress=progress, more=more,
        )

    return acquire


def record_scan(
    ctx: RunContext, step: str, step_id: int, acquire: Acquire, stem: str | None = None,
    more_turns: MoreTurnsOf | None = None,
) -> Path:
    """Write the step's recording while acquiring; returns its path. ``stem`` names the file
    (and the artifact) when a step takes a second recording, default the recording's kind.
    ``more_turns`` makes a spin scan go on until its accuracy budget holds. What the scan
    prepared while its lines arrived — its returns, and what it did turn by turn — is kept in
    ``ctx.prepared`` (:class:`~calstation.station.prepared.PreparedScan`) for the steps after
    it."""
    from calstation.recordings.writer import RecordingWriter

    d = ctx.hardware()
    kind = RECORDING_OF[step]
    stem = stem or kind
    path = ctx.run_dir / f"{stem}.mcap"
    if path.exists():
        _set_aside(ctx, path, stem)
    enc = ctx.recipe.station.encoder
    metadata = _metadata(ctx, step, step_id, d.context)
    calibration, source = latest_calibration(ctx.db, ctx.run_id)
    ctx.scans.partial = [(stem, path)]  # until the recording is complete
    with (
        RecordingWriter(
            path,
            kind=kind,
            lidar_info=d.lidar.info(),
            counts_per_revolution=d.encoder.counts_per_revolution,
            encoder_direction=enc.direction,
            encoder_latency_s=enc.latency_s,
            station_id=ctx.recipe.station.id,
            recipe=ctx.loaded,
            metadata=metadata,
            calibration=calibration,
            calibration_source=source,
            clock=d.clock,  # the drivers' time base: one clock in the file
        ) as writer,
        ctx.ui.progress(f"{stem} scan") as progress,
    ):
        # a spin scan's per-line work for the fine-tuning and the cube check is done as
        # the lines arrive
        builder = (
            SpinScanBuilder(d.encoder.counts_per_revolution, enc.direction, enc.latency_s)
            if kind in ("spin", "cube") and stem == kind
            else None
        )
        more = None if more_turns is None or builder is None else more_turns(builder)
        preview = (ScanPreview(ctx, kind, builder,
                               getattr(getattr(ctx.recipe.steps, step), "revolutions", 1.0))
                   if wants_previews(ctx.ui) else None)
        publishing = PublishingWriter(writer, ctx.ui, kind, builder, preview)
        try:
            acquire(publishing, progress, more)
            if preview is not None:
                preview.line(final=True)
        finally:
            turns = None if more is None else more.close(_whole_turns(builder))
            delivered, lost, longest_s = publishing.gaps.lost()
            if (warning := lost_lines_warning(stem, delivered, lost, longest_s)) is not None:
                ctx.ui.warn(warning)
    ctx.scans.partial = []
    if kind == "spin":
        ctx.scans.scan_ended = time.monotonic()
    if builder is not None or turns is not None:
        ctx.keep_prepared(PreparedScan(path, builder, turns, lost))
    return path


def _whole_turns(builder: SpinScanBuilder | None) -> int:
    """Whole revolutions in the scan prepared so far (as the fine-tuning counts them)."""
    scan = None if builder is None else builder.so_far()
    if scan is None or scan.n_points == 0:
        return 0
    span = float(np.nanmax(scan.phi) - np.nanmin(scan.phi))
    return max(0, math.floor(span / (2 * math.pi) + 0.02))


def record_second_pass(ctx: RunContext, step: str, step_id: int, first: Path,
                       stem: str) -> Path | None:
    """The scan step's second pass (``second_pass_rpm``) recorded as ``stem``; None when
    the recipe asks for none. A fault in it keeps the ``first`` pass (``ScanFiles.finished``)."""
    second = getattr(ctx.recipe.steps, step).second_pass()
    if second is None:
        return None
    prepared = ctx.prepared.get(first)
    turned = None if prepared is None else prepared.turns
    if turned is not None:  # the first pass went on for accuracy: the same turns again
        whole = int(turned.summary.get("whole_turns", 0))
        second = second.model_copy(update={"revolutions": max(second.revolutions, whole + 0.05)})
    d = ctx.hardware()
    ctx.scans.finished.append((RECORDING_OF[step], first))
    return record_scan(ctx, step, step_id, spin_acquisition(d, second), stem)


def _set_aside(ctx: RunContext, path: Path, stem: str) -> None:
    """Keep a previous attempt's file (failed or killed) aside as ``<stem>.attempt<n>.mcap``,
    and its artifact row pointing at it."""
    n = 1
    while (aside := path.with_name(f"{stem}.attempt{n}.mcap")).exists():
        n += 1
    path.rename(aside)
    with ctx.db.session("moving a partial recording aside") as s:
        for art in s.scalars(select(Artifact).where(
                Artifact.run_id == ctx.run_id, Artifact.path == str(path))):
            art.path = str(aside)


def _metadata(
    ctx: RunContext, step: str, step_id: int, context: DriverContext
) -> dict[str, JSONObject]:
    """A recording's run metadata, and the simulated scene's truth when there is one."""
    metadata: dict[str, JSONObject] = {
        "run": {"id": ctx.run_id, "step": step, "step_id": step_id}
    }
    truth = scene_truth(context)
    if truth is not None:
        metadata["truth"] = truth
    return metadata


@runtime_checkable
class HasTruth(Protocol):
    """A simulated scene that knows its ground truth (``truth_dict``)."""

    def truth_dict(self) -> Mapping[str, object]:
        """The scene's truth, as ``truth.json`` holds it."""
        ...


def scene_truth(context: DriverContext) -> JSONObject | None:
    """Ground truth of a simulated scene (an object in ``context.shared`` with ``truth_dict``)."""
    for obj in context.shared.values():
        if isinstance(obj, HasTruth):
            return plain(obj.truth_dict())
    return None


class PublishingWriter:
    """A recording writer that also publishes each lidar line to the operator (live preview)
    and, for a spin scan, hands it to the fine-tuning's preparation (``builder``); ``preview``
    publishes the fixture's expected outline and the cloud so far."""

    def __init__(self, inner: Writer, ui: Operator, kind: str,
                 builder: SpinScanBuilder | None = None,
                 preview: ScanPreview | None = None) -> None:
        self._inner, self._ui, self._kind, self._builder = inner, ui, kind, builder
        self._preview = preview
        self.gaps = LineGaps()
        """The lines the lidar's stream lost, from the gaps in those recorded."""

    def write_line(self, line: LidarLine) -> None:
        """Record ``line``, prepare it (spin scans) and publish it (``lidar_line``)."""
        self._inner.write_line(line)
        self.gaps.add(line.timestamp_ns)
        if self._builder is not None:
            self._builder.write_line(line)
        publish(self._ui, "lidar_line", kind=self._kind, line=line)
        if self._preview is not None:
            self._preview.line()

    def write_encoder(self, samples: Iterable[EncoderSample]) -> None:
        """Record encoder ``samples`` and hand them to the preparation (spin scans)."""
        batch = list(samples)
        self._inner.write_encoder(batch)
        if self._builder is not None:
            self._builder.write_encoder(batch)

    def write_turntable(self, status: TurntableStatus) -> None:
        """Record a turntable status."""
        self._inner.write_turntable(status)

    def __getattr__(self, name: str) -> object:
        return getattr(self._inner, name)
