"""``calstation calibrate`` and ``calstation verify``: offline calibration from recordings."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING

import typer

if TYPE_CHECKING:
    from rich.console import Console
    from rich.progress import Progress

    from calstation.engine.frames import Extrinsics
    from calstation.engine.result import CalibrationResult
    from calstation.pipeline import Calibrated, Scans
    from calstation.plugins.cost_strategies import Strategy
    from calstation.recipes import LoadedRecipe
    from calstation.recordings.recorded import Recording
    from calstation.station.reprocess import Reprocessing


def _progress_bar(console: Console) -> Progress:
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(
        TextColumn("{task.description:<40}"),
        BarColumn(),
        TextColumn("{task.percentage:>5.1f}%"),
        TimeElapsedColumn(),
        console=console,
        transient=False,
    )


def _mm(v: float) -> str:
    return "—" if not math.isfinite(v) else f"{v * 1e3:.3f}"


def _deg(v: float) -> str:
    return "—" if not math.isfinite(v) else f"{math.degrees(v):.4f}"


def register(app: typer.Typer) -> None:
    """Add the ``calibrate`` and ``verify`` commands."""

    @app.command("calibrate")
    def calibrate_cmd(
        recipe: Path | None = typer.Argument(
            None, help="Recipe YAML (not with --run).", show_default=False
        ),
        static: Path | None = typer.Option(
            None, "--static", help="Static scan of the L-target (MCAP).", show_default=False
        ),
        spin: Path | None = typer.Option(
            None,
            "--spin",
            help="Spin scan for the fine-tuning: the spin target for periodicity, the QA cube "
            "for shape (MCAP).",
            show_default=False,
        ),
        spin_pass2: Path | None = typer.Option(
            None,
            "--spin-pass2",
            help="The spin scan's second pass at another speed or the other way (MCAP, "
            "spin-pass2.mcap of a run): the lidar–encoder time offset is estimated from the two.",
            show_default=False,
        ),
        cube: Path | None = typer.Option(
            None,
            "--cube",
            help="Spin scan of the QA cube (MCAP): with a spin-target strategy its side faces "
            "are combined into ry, as the station does.",
            show_default=False,
        ),
        run: int | None = typer.Option(
            None,
            "--run",
            help="Re-process stored run N: its recipe and recordings come from the database, "
            "and the result is stored with the run.",
            show_default=False,
        ),
        strategy: str | None = typer.Option(
            None,
            "--strategy",
            "-s",
            help="Fine-tuning strategy (periodicity, shape, or a plugin's); default: the "
            "recipe's calibration.strategy.",
            show_default=False,
        ),
        accept: bool = typer.Option(
            False, "--accept",
            help="With --run: make the re-processing the run's accepted calibration.",
        ),
        out: Path | None = typer.Option(
            None,
            "--out",
            "-o",
            help="Write the calibration (YAML or JSON by suffix).",
            show_default=False,
        ),
        as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
        db: str | None = typer.Option(
            None, "--db", help="Database URL for --run (default: $CALSTATION_DB_URL or SQLite).",
            show_default=False,
        ),
    ) -> None:
        """Initial calibration from --static, then fine-tuning from --spin; or re-process a run.

        Without --static the fine-tuning starts from the platter's chord in the spin scan (no
        L-target: docs/algorithms.md, targetless start).

        Prints H (mm, degrees) with a 1σ per parameter; --json prints tx, ty, tz (m), rx, ry,
        rz (rad), sigma_* for each, strategy and cost on stdout. With --run N the result is stored
        with run N as a re-processing (not accepted unless --accept) and compared with the run's
        accepted calibration. A recording whose encoder settings or recipe sha256 differ from the
        recipe's gives a warning naming both values. A result whose σ exceeds the
        recipe's calibration.max_sigma is printed (and written with --out) but refused: exit
        code 3, with what to do on stderr (``refused`` in the JSON). With --cube, the cube
        scan's side-face twist is combined into ry (strategy ``periodicity+cube``) and the ry
        limit applies to the combined σ; the cube check under the result is printed. With
        --spin-pass2 the lidar–encoder time offset is estimated too (encoder_latency_s and its σ,
        refused above calibration.max_sigma.encoder_latency_ms).
        """
        from calstation.errors import CalstationError

        if run is not None:
            given = (recipe, static, spin, spin_pass2, cube)
            if any(v is not None for v in given):
                raise CalstationError(
                    "--run takes the recipe and the recordings from the database: give either "
                    "--run N, or RECIPE --static FILE --spin FILE"
                )
            _reprocess(run, strategy, accept, out, as_json, db)
            return
        if recipe is None or spin is None:
            missing = [n for n, v in (("RECIPE", recipe), ("--spin", spin)) if v is None]
            raise CalstationError(
                f"missing {', '.join(missing)}: give RECIPE [--static FILE] --spin FILE, or "
                "--run N"
            )
        if accept:
            raise CalstationError("--accept applies to a stored run: use it with --run N")
        _calibrate_files(recipe, static, spin, strategy, out, as_json, cube, spin_pass2)

    @app.command("verify")
    def verify_cmd(
        recipe: Path = typer.Argument(..., help="Recipe YAML.", show_default=False),
        cube: Path = typer.Option(
            ..., "--cube", help="Spin scan of the QA cube (MCAP).", show_default=False
        ),
        calibration: Path = typer.Option(
            ..., "--calibration", "-c", help="Calibration file (YAML/JSON).", show_default=False
        ),
        as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
    ) -> None:
        """Dimension the QA cube with a calibration; exit code 1 when the check fails."""
        from rich.console import Console

        from calstation.engine.cube import check_cube
        from calstation.engine.result import CalibrationResult
        from calstation.errors import VerificationError
        from calstation.quiet import stdout_to_stderr
        from calstation.recipes import load_recipe

        console = Console(stderr=True)
        rc = load_recipe(recipe).recipe
        calib = CalibrationResult.load(calibration)
        rec = _read_cube(console, cube, VerificationError, "verify needs the cube's spin scan")
        with console.status("measuring the QA cube"), stdout_to_stderr():
            check = check_cube(
                rec,
                calib.H,
                rc.fixtures.qa_cube,
                rc.qa,
                platter_radius=rc.fixtures.platter.radius,
                range_model=calib.range_model,
            )
        if as_json:
            typer.echo(json.dumps(check.to_dict(), indent=2))
        else:
            s = check.edge
            height = ("" if check.height_judged
                      else "; the height, from a platter of another finish, not judged")
            typer.echo(
                f"face-fit edges {', '.join(f'{v * 1e3:.2f}' for v in check.face_edges)} mm "
                f"(error {check.edge_error * 1e3:.2f} mm, limit {rc.qa.edge_error * 1e3:.2f}"
                f"{height})"
            )
            typer.echo(
                f"OBB edges {', '.join(f'{v * 1e3:.2f}' for v in check.obb_edges)} mm "
                f"(paper metric e = {check.obb_error * 1e3:.2f} mm for s = {s * 1e3:.0f} mm)"
            )
            typer.echo(
                f"flatness {check.flatness_rms * 1e3:.2f} mm RMS "
                f"({check.flatness_excess * 1e3:.2f} mm beyond the range noise of "
                f"{check.range_noise * 1e3:.2f} mm), perpendicularity "
                f"{check.perpendicularity_deg:.3f}°, side-face twist {check.twist_deg:+.3f}° "
                f"(±{check.twist_sigma_deg:.3f}°, limit ±{rc.qa.twist_deg:.3f}°)"
            )
            verdict = "[bold green]PASS[/]" if check.passed else "[bold red]FAIL[/]"
            Console().print(verdict + ("" if check.passed else ": " + "; ".join(check.failures)))
        if not check.passed:
            raise typer.Exit(1)


def _warn(console: Console, warnings: list[str]) -> None:
    from rich.markup import escape

    for w in warnings:
        console.print(f"[yellow]warning:[/] {escape(w)}", highlight=False)


def _calibrate_files(
    recipe: Path, static: Path | None, spin: Path, strategy: str | None, out: Path | None,
    as_json: bool, cube: Path | None = None, spin_pass2: Path | None = None,
) -> None:
    """``calibrate RECIPE [--static] --spin``: the recordings read and checked, then the
    calibration pipeline (:func:`calstation.pipeline.calibrate`) whole; nothing is stored.
    Without ``static`` the start comes from the platter's chord in the spin scan."""
    from dataclasses import replace

    from rich.console import Console

    from calstation import plugins
    from calstation.errors import CalibrationError
    from calstation.pipeline import calibrate
    from calstation.quiet import stdout_to_stderr
    from calstation.recipes import load_recipe

    console = Console(stderr=True)
    loaded = load_recipe(recipe)
    rc = loaded.recipe
    name = strategy or rc.calibration.strategy
    strat = plugins.strategy(name)
    if cube is not None and strat.fixture != "spin_target":
        raise CalibrationError(
            f"--cube: the {name} strategy fine-tunes on the cube scan itself; give the cube "
            "scan as --spin (--cube adds the cube to a spin-target strategy's ry)"
        )
    files = {"static": static, "spin": spin, "spin_pass2": spin_pass2, "cube": cube}
    read, warnings = _read_files(console, files, strat, loaded)
    _warn(console, warnings)
    with _progress_bar(console) as bar, stdout_to_stderr():
        task = bar.add_task(f"{strat.name} fine-tuning", total=1.0)

        def progress(message: str, fraction: float) -> None:
            bar.update(task, description=message, completed=max(0.0, min(1.0, fraction)))

        done = calibrate(rc, _scans(read), strat, progress)
        bar.update(task, completed=1.0)
    _warn(console, done.warnings)
    if done.cube_check is not None:
        _print_cube(console, done)
    diagnostics = dict(done.result.diagnostics)
    diagnostics["initial"] = {"H": done.start.H.as_dict(), "timings": dict(done.start.timings),
                              "strategy": done.start.strategy}
    diagnostics["recordings"] = {k: str(v) for k, v in files.items() if v is not None}
    diagnostics["recipe"] = {"name": rc.name, "sha256": loaded.sha256}
    if warnings or done.warnings:
        diagnostics["warnings"] = warnings + done.warnings
    result = replace(done.result, diagnostics=diagnostics)
    if out is not None:
        from calstation.recordings.files import save_calibration

        save_calibration(result, out)
    if as_json:
        summary = result.summary()
        summary["initial"] = done.start.H.as_dict()
        summary["refused"] = done.refused
        typer.echo(json.dumps(summary, indent=2))
    else:
        _print_result(done.start.H, result)
        typer.echo(_timing_line(result) + (f"; written to {out}" if out is not None else ""))
    if done.refused:
        _refuse(done.refused)


def _read_files(
    console: Console, files: dict[str, Path | None], strat: Strategy, loaded: LoadedRecipe
) -> tuple[dict[str, Recording], list[str]]:
    """The recordings named on the command line, each checked to be the scan it is given as;
    (kind → recording, every disagreement between a recording and the recipe)."""
    from calstation.errors import CalibrationError
    from calstation.pipeline import recording_disagreements

    read: dict[str, Recording] = {}
    if files["static"] is not None:
        read["static"] = _read_any(console, files["static"])
        if read["static"].kind in ("spin", "cube"):
            raise CalibrationError(
                f"{files['static']}: this is a {read['static'].kind!r} recording, not the static "
                "scan of the L-target (recording kind 'static', static.mcap of a run)"
            )
    spin = files["spin"]
    assert spin is not None
    read["spin"] = _read_any(console, spin)
    if read["spin"].kind == "static":
        raise CalibrationError(
            f"{files['spin']}: this is a 'static' recording; fine-tuning needs a spin scan "
            f"({'spin' if strat.fixture == 'spin_target' else 'cube'}.mcap of a run)"
        )
    if files["spin_pass2"] is not None:
        read["spin_pass2"] = _read_kind(console, files["spin_pass2"], "spin", CalibrationError,
                                        "--spin-pass2 takes the spin scan's second pass",
                                        "spin-pass2.mcap")
    if files["cube"] is not None:
        read["cube"] = _read_cube(console, files["cube"], CalibrationError,
                                  "--cube needs the cube's spin scan")
    warnings = [w for rec in read.values() for w in recording_disagreements(rec, loaded)]
    return read, warnings


def _scans(read: dict[str, Recording]) -> Scans:
    """The recordings as the pipeline takes them (each spin scan's returns prepared once)."""
    from calstation.pipeline import Scans, turned

    return Scans(spin=turned(read["spin"]), static=read.get("static"),
                 spin_pass2=read.get("spin_pass2"),
                 cube=turned(read["cube"]) if "cube" in read else None)


def _print_cube(console: Console, done: Calibrated) -> None:
    """The cube's figures under the result (and the ry combination, when there was one)."""
    from rich.markup import escape

    from calstation.engine.joint import joint_summary

    check = done.cube_check
    if check is None:
        return
    line = (f"cube: side-face twist {check.twist_deg:+.3f}° ± {check.twist_sigma_deg:.3f}°, "
            f"edge error {check.edge_error * 1e3:.2f} mm")
    if "joint" in done.result.diagnostics:
        line += f"; {joint_summary(done.result)}"
    console.print(escape(line), highlight=False)


def _read_any(console: Console, path: Path) -> Recording:
    """The recording at ``path``."""
    from calstation.recordings.reader import read_recording

    with console.status(f"reading {path}"):
        return read_recording(path)


def _read_cube(console: Console, path: Path, error: type[Exception], need: str) -> Recording:
    """The recording at ``path``, which must be a scan of the QA cube (else ``error``)."""
    return _read_kind(console, path, "cube", error, need, "cube.mcap")


def _read_kind(
    console: Console, path: Path, kind: str, error: type[Exception], need: str, file: str
) -> Recording:
    """The recording at ``path``, which must be of ``kind`` (else ``error`` saying ``need`` and
    which ``file`` of a run that is)."""
    from calstation.recordings.reader import read_recording

    with console.status(f"reading {path}"):
        rec = read_recording(path)
    if rec.kind != kind:
        what = "a scan of the QA cube" if kind == "cube" else f"a {kind!r} recording"
        raise error(
            f"{path}: this is a {rec.kind!r} recording, not {what}; {need} "
            f"(recording kind {kind!r}, {file} of a run)"
        )
    return rec


def _refuse(refused: list[str]) -> None:
    """Say on stderr why the result is refused (a ``calibration.max_sigma`` limit, ry
    undetermined with the cube, the accuracy budget, each with what to do); exit 3."""
    from rich.console import Console
    from rich.markup import escape

    console = Console(stderr=True)
    for reason in refused:
        console.print(f"[bold red]refused[/]: {escape(reason)}", highlight=False)
    raise typer.Exit(3)


def _timing_line(result: CalibrationResult) -> str:
    total = result.timings.get("total")
    took = f"{total:.2f} s" if isinstance(total, float | int) and math.isfinite(total) else "—"
    return f"cost {result.cost:.4g}, {result.iterations} iterations, {took}"


def _print_result(initial: Extrinsics, result: CalibrationResult) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(
        title=f"calibration ({result.strategy}, gauge {result.diagnostics.get('gauge', '—')})"
    )
    table.add_column("parameter")
    table.add_column("initial", justify="right")
    table.add_column("fine-tuned", justify="right")
    table.add_column("1σ", justify="right")
    for n in ("tx", "ty", "tz"):
        table.add_row(f"{n} (mm)", _mm(getattr(initial, n)), _mm(getattr(result.H, n)),
                      _mm(result.sigma.get(n, math.nan)))
    for n in ("rx", "ry", "rz"):
        table.add_row(f"{n} (°)", _deg(getattr(initial, n)), _deg(getattr(result.H, n)),
                      _deg(result.sigma.get(n, math.nan)))
    if result.encoder_latency_s is not None:
        offset = result.diagnostics.get("time_offset", {})
        configured = offset.get("configured_s")
        sigma = result.sigma_encoder_latency_s
        table.add_row(
            "encoder latency (ms)",
            "—" if configured is None else f"{configured * 1e3:.3f}",
            f"{result.encoder_latency_s * 1e3:.3f}",
            "—" if sigma is None else f"{sigma * 1e3:.3f}",
        )
    Console().print(table)


def _reprocess(
    run_id: int, strategy: str | None, accept: bool, out: Path | None, as_json: bool,
    db: str | None,
) -> None:
    """``calibrate --run N``: re-process a stored run and store the result with it."""
    from rich.console import Console
    from rich.table import Table

    from calstation.station.reprocess import difference_rows, reprocess_run
    from calstation.storage.db import open_database

    console = Console(stderr=True)
    database = open_database(db)
    try:
        with _progress_bar(console) as bar:
            task = bar.add_task(f"re-processing run {run_id}", total=1.0)

            def progress(message: str, fraction: float) -> None:
                bar.update(task, description=message, completed=max(0.0, min(1.0, fraction)))

            def status(message: str) -> None:
                bar.update(task, description=message)

            done = reprocess_run(database, run_id, strategy, accept=accept, progress=progress,
                                 status=status)
            bar.update(task, completed=1.0)
    finally:
        database.dispose()
    _warn(console, done.warnings)
    result = done.result
    if out is not None:
        from calstation.recordings.files import save_calibration

        save_calibration(result, out)
    if as_json:
        summary = result.summary()
        summary["initial"] = done.initial.H.as_dict()
        summary["run_id"] = run_id
        summary["calibration_id"] = done.calibration_id
        summary["accepted"] = done.accepted_now
        summary["compared_to"] = done.accepted_id
        summary["difference"] = done.difference
        summary["warnings"] = done.warnings
        summary["refused"] = done.refused
        typer.echo(json.dumps(summary, indent=2))
        _refuse_reprocessing(console, done, accept)
        return
    _print_result(done.initial.H, result)
    typer.echo(
        _timing_line(result) + f"; stored with run {run_id} as calibration "
        f"{done.calibration_id} (re-processing, "
        f"{'accepted' if done.accepted_now else 'not accepted'})"
        + (f"; written to {out}" if out is not None else "")
    )
    if done.accepted is None:
        typer.echo(f"run {run_id} has no accepted calibration to compare with")
        _refuse_reprocessing(console, done, accept)
        return
    gauges = (done.accepted_gauge, result.diagnostics.get("gauge"))
    caption = None
    if gauges[0] != gauges[1]:
        caption = (f"gauges differ (accepted: {gauges[0] or '—'}, re-processed: "
                   f"{gauges[1] or '—'}): a shift of the origin along the rotation axis is a "
                   "gauge choice, not a calibration difference; it shows in tx and ty")
    table = Table(title=f"difference to the accepted calibration {done.accepted_id} of run "
                        f"{run_id} (mm, °)", caption=caption)
    for col in ("parameter", "accepted", "re-processed", "difference"):
        table.add_column(col, justify="right")
    for p, a, b, d in difference_rows(done.accepted, result.H):
        fmt = "{:.4f}" if p.startswith("r") else "{:.3f}"
        table.add_row(p, fmt.format(a), fmt.format(b), ("{:+" + fmt[2:]).format(d))
    Console().print(table)
    _refuse_reprocessing(console, done, accept)


def _refuse_reprocessing(console: Console, done: Reprocessing, accept: bool) -> None:
    """A re-processing over ``calibration.max_sigma``: say why (it is stored, not accepted)
    and exit 3."""
    from rich.markup import escape

    if not done.refused:
        return
    kept = (f"stored with run {done.run_id} as calibration {done.calibration_id}, "
            + ("not accepted although --accept was given" if accept else "not accepted"))
    console.print(f"[bold red]refused[/] ({kept}): {escape('; '.join(done.refused))}",
                  highlight=False)
    raise typer.Exit(3)
