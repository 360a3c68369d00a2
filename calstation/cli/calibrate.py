"""``calstation calibrate`` and ``calstation verify``: offline calibration from recordings."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import typer


def _progress_bar(console: Any) -> Any:
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
        recipe: Path = typer.Argument(..., help="Recipe YAML.", show_default=False),
        static: Path = typer.Option(
            ..., "--static", help="Static scan of the L-target (MCAP).", show_default=False
        ),
        spin: Path = typer.Option(
            ...,
            "--spin",
            help="Spin scan for the fine-tuning: the spin target for periodicity, the QA cube "
            "for shape (MCAP).",
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
        out: Path | None = typer.Option(
            None,
            "--out",
            "-o",
            help="Write the calibration (YAML or JSON by suffix).",
            show_default=False,
        ),
        as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
    ) -> None:
        """Initial calibration from --static, then fine-tuning from --spin.

        Prints H (mm, degrees) with a 1σ per parameter; --json prints tx, ty, tz (m), rx, ry,
        rz (rad), sigma_* for each, strategy and cost on stdout.
        """
        from rich.console import Console

        from .. import plugins
        from ..errors import CalibrationError
        from ..initial import initial_calibration
        from ..quiet import stdout_to_stderr
        from ..recipe import load_recipe
        from ..recording import read_recording

        console = Console(stderr=True)
        loaded = load_recipe(recipe)
        rc = loaded.recipe
        name = strategy or rc.calibration.strategy
        strat = plugins.strategy(name)
        with console.status(f"reading {static}"):
            st = read_recording(static)
        if st.kind in ("spin", "cube"):
            raise CalibrationError(
                f"{static}: this is a {st.kind!r} recording, not the static scan of the L-target "
                "(recording kind 'static', static.mcap of a run)"
            )
        with console.status(f"reading {spin}"):
            sp = read_recording(spin)
        if sp.kind == "static":
            raise CalibrationError(
                f"{spin}: this is a 'static' recording; fine-tuning needs a spin scan "
                f"({'spin' if strat.fixture == 'spin_target' else 'cube'}.mcap of a run)"
            )
        with console.status("initial calibration"), stdout_to_stderr():
            initial = initial_calibration(st, rc.fixtures.static_target, rc.calibration.initial)
        with _progress_bar(console) as bar, stdout_to_stderr():
            task = bar.add_task(f"{name} fine-tuning", total=1.0)

            def progress(message: str, fraction: float) -> None:
                bar.update(task, description=message, completed=max(0.0, min(1.0, fraction)))

            result = strat.run(sp, initial.H, rc, progress)
            bar.update(task, completed=1.0)
        diagnostics = dict(result.diagnostics)
        diagnostics["initial"] = {
            "H": initial.H.as_dict(),
            "timings": dict(initial.timings),
        }
        diagnostics["recordings"] = {"static": str(static), "spin": str(spin)}
        diagnostics["recipe"] = {"name": rc.name, "sha256": loaded.sha256}
        from dataclasses import replace

        result = replace(result, diagnostics=diagnostics)
        if out is not None:
            result.save(out)
        if as_json:
            summary = result.summary()
            summary["initial"] = initial.H.as_dict()
            typer.echo(json.dumps(summary, indent=2))
            return
        from rich.table import Table

        table = Table(
            title=f"calibration ({result.strategy}, gauge {diagnostics.get('gauge', '—')})"
        )
        table.add_column("parameter")
        table.add_column("initial", justify="right")
        table.add_column("fine-tuned", justify="right")
        table.add_column("1σ", justify="right")
        for n in ("tx", "ty", "tz"):
            table.add_row(
                f"{n} (mm)",
                _mm(getattr(initial.H, n)),
                _mm(getattr(result.H, n)),
                _mm(result.sigma.get(n, math.nan)),
            )
        for n in ("rx", "ry", "rz"):
            table.add_row(
                f"{n} (°)",
                _deg(getattr(initial.H, n)),
                _deg(getattr(result.H, n)),
                _deg(result.sigma.get(n, math.nan)),
            )
        Console().print(table)
        typer.echo(
            f"cost {result.cost:.4g}, {result.iterations} iterations, "
            f"{result.timings.get('total', float('nan')):.2f} s"
            + (f"; written to {out}" if out is not None else "")
        )

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

        from ..cube import check_cube
        from ..errors import VerificationError
        from ..quiet import stdout_to_stderr
        from ..recipe import load_recipe
        from ..recording import read_recording
        from ..result import CalibrationResult

        console = Console(stderr=True)
        rc = load_recipe(recipe).recipe
        calib = CalibrationResult.load(calibration)
        with console.status(f"reading {cube}"):
            rec = read_recording(cube)
        if rec.kind != "cube":
            raise VerificationError(
                f"{cube}: this is a {rec.kind!r} recording, not a scan of the QA cube; verify "
                "needs the cube's spin scan (recording kind 'cube', cube.mcap of a run)"
            )
        with console.status("measuring the QA cube"), stdout_to_stderr():
            check = check_cube(
                rec,
                calib.H,
                rc.fixtures.qa_cube,
                rc.qa,
                platter_radius=rc.fixtures.platter.radius,
            )
        if as_json:
            typer.echo(json.dumps(check.to_dict(), indent=2))
        else:
            s = check.edge
            typer.echo(
                f"face-fit edges {', '.join(f'{v * 1e3:.2f}' for v in check.face_edges)} mm "
                f"(error {check.edge_error * 1e3:.2f} mm, limit {rc.qa.edge_error * 1e3:.2f})"
            )
            typer.echo(
                f"OBB edges {', '.join(f'{v * 1e3:.2f}' for v in check.obb_edges)} mm "
                f"(paper metric e = {check.obb_error * 1e3:.2f} mm for s = {s * 1e3:.0f} mm)"
            )
            typer.echo(
                f"flatness {check.flatness_rms * 1e3:.2f} mm RMS, perpendicularity "
                f"{check.perpendicularity_deg:.3f}°"
            )
            verdict = "[bold green]PASS[/]" if check.passed else "[bold red]FAIL[/]"
            Console().print(verdict + ("" if check.passed else ": " + "; ".join(check.failures)))
        if not check.passed:
            raise typer.Exit(1)
