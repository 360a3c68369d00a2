"""``simulate_run``: the recordings of a whole simulated run, plus its ground truth."""

from __future__ import annotations

import json
from collections.abc import Callable, Collection, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

from calstation.atomic import atomic_output, write_atomic
from calstation.engine.frames import PARAMETER_NAMES, Extrinsics
from calstation.errors import SimulationError
from calstation.recipes import LoadedRecipe, SpinScanStep
from calstation.recordings.runfolder import second_pass
from calstation.station.acquisition import acquire_spin, acquire_static

from .drivers import SimEncoder, SimLidar, SimTurntable
from .station import SimulatedStation


def _scans(recipe: LoadedRecipe) -> list[tuple[str, str, str, SpinScanStep | None]]:
    """(file stem, recording kind, fixture, spin step or None for the static scan) in run order."""
    steps = recipe.recipe.steps
    out: list[tuple[str, str, str, SpinScanStep | None]] = []
    if recipe.recipe.calibration.start != "platter":  # a targetless run has no static scan
        out.append(("static", "static", "static_target", None))
    for kind, fixture, step in (("spin", "spin_target", steps.spin_scan),
                                ("cube", "qa_cube", steps.cube_scan)):
        out.append((kind, kind, fixture, step))
        second = step.second_pass()
        if second is not None:
            out.append((second_pass(kind), kind, fixture, second))
    return out


@contextmanager
def _progress_bars(enabled: bool) -> Iterator[Callable[[str, str], Callable[[str, float], None]]]:
    """Yields ``task(name, title) -> progress(phase, fraction)``; a rich progress display when
    ``enabled``, silent callbacks otherwise."""
    if not enabled:
        yield lambda name, title: lambda phase, fraction: None
        return
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    columns = (
        TextColumn("{task.description:<28}"),
        BarColumn(),
        TextColumn("{task.percentage:>5.1f}%"),
        TextColumn("{task.fields[phase]}"),
        TimeElapsedColumn(),
    )
    with Progress(*columns, transient=False) as bars:

        def task(name: str, title: str) -> Callable[[str, float], None]:
            tid = bars.add_task(title, total=1.0, phase="")

            def update(phase: str, fraction: float) -> None:
                bars.update(tid, completed=fraction, phase=phase)

            return update

        yield task


def simulate_run(
    recipe: LoadedRecipe,
    out_dir: Path,
    *,
    seed: int | None = None,
    range_m: float | None = None,
    pitch_deg: float | None = None,
    progress: bool = True,
    only: Collection[str] | None = None,
) -> dict[str, Path]:
    """Simulate a whole run of ``recipe`` and write its recordings into ``out_dir``.

    Writes ``static.mcap`` (the L-target at rest, ``steps.static_scan.lines`` lines; not for a
    recipe whose ``calibration.start`` is ``platter``),
    ``spin.mcap`` (the spin target, ``steps.spin_scan``), ``cube.mcap`` (the QA cube,
    ``steps.cube_scan``), each followed by ``spin-pass2.mcap`` / ``cube-pass2.mcap`` (the same
    turns again) when the step has a ``second_pass_rpm``, and ``truth.json``
    (:meth:`SimulatedStation.truth_dict`; also stored as the ``"truth"`` metadata of each
    recording). Returns ``{"static", "spin", "cube", "truth"}`` (plus the second passes) →
    paths. ``seed``, ``range_m`` (m) and ``pitch_deg`` override the
    recipe's simulation. ``only``: the stems of the scans to simulate (``{"spin"}``: the spin
    scan alone; the truth is the seed's either way, the placements' errors may differ).
    """
    from calstation.recordings.writer import RecordingWriter

    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SimulationError(f"cannot create output folder {out}: {exc}") from None
    station = SimulatedStation(recipe, seed=seed, range_m=range_m, pitch_deg=pitch_deg)
    lidar, turntable, encoder = SimLidar(station), SimTurntable(station), SimEncoder(station)
    r = recipe.recipe
    enc = r.station.encoder
    paths: dict[str, Path] = {}
    truth = station.truth_dict()
    truth_H = Extrinsics.from_dict({k: truth[k] for k in PARAMETER_NAMES})
    with _progress_bars(progress) as task:
        for stem, kind, fixture, step in _scans(recipe):
            if only is not None and stem not in only:
                continue
            if station.current_fixture != fixture:
                station.place(fixture)
            path = out / f"{stem}.mcap"
            update = task(stem, f"{stem} scan ({fixture})")
            # whole or not at all, beside the file it replaces (a device or FIFO is refused)
            with atomic_output(path, "recording", make_parents=True) as tmp, RecordingWriter(
                tmp,
                kind=kind,
                lidar_info=lidar.info(),
                counts_per_revolution=encoder.counts_per_revolution,
                encoder_direction=enc.direction,
                encoder_latency_s=enc.latency_s,
                station_id=r.station.id,
                recipe=recipe,
                metadata={"truth": station.truth_dict()},
                # the true H gives the file its transform tree and cloud in a viewer
                calibration=truth_H,
                calibration_source="truth",
                clock=station.clock,  # the simulated time the lines and readings carry
            ) as writer:
                if step is None:
                    acquire_static(
                        lidar, encoder, writer, lines=r.steps.static_scan.lines, progress=update
                    )
                else:
                    acquire_spin(
                        lidar,
                        turntable,
                        encoder,
                        writer,
                        rpm=step.rpm,
                        revolutions=step.revolutions,
                        settle_s=step.settle_s,
                        clock=station.clock,
                        progress=update,
                    )
            paths[stem] = path
    paths["truth"] = write_truth(out / "truth.json", station.truth_dict())
    return paths


def write_truth(path: Path, truth: Mapping[str, object]) -> Path:
    """Write ``truth`` as indented JSON, whole or not at all; returns ``path``."""
    return write_atomic(path, json.dumps(truth, indent=2, sort_keys=True) + "\n", "truth file")
