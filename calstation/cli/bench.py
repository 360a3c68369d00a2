"""``calstation bench paper``: reproduce the source paper's experiments on the simulated station."""

from __future__ import annotations

import shlex
import sys
from pathlib import Path

import typer


def _parse_deadline(text: str) -> float:
    """``HH:MM`` (UTC, today) → Unix time."""
    import datetime as dt

    from calstation.bench import BenchError

    try:
        hh, mm = (int(x) for x in text.split(":"))
        now = dt.datetime.now(dt.UTC)
        return now.replace(hour=hh, minute=mm, second=0, microsecond=0).timestamp()
    except ValueError:
        raise BenchError(f"--deadline {text!r}: expected HH:MM (UTC)") from None


def _command_line() -> str:
    """This command as typed (quoted for a shell), for the reports' provenance."""
    return "calstation " + " ".join(shlex.quote(a) for a in sys.argv[1:])


def _strategies(recipe: Path, methods: str) -> list[str]:
    """The strategies named in ``methods`` (comma-separated), after checking that the recipe
    exists and each strategy is installed."""
    from calstation import plugins
    from calstation.bench import BenchError

    if not recipe.is_file():
        raise BenchError(f"{recipe}: recipe not found (give --recipe)")
    chosen = [m.strip() for m in methods.split(",") if m.strip()]
    unknown = [m for m in chosen if m not in plugins.strategies()]
    if unknown or not chosen:
        raise BenchError(f"--methods {methods!r}: unknown strategy {', '.join(unknown)}; "
                         f"installed: {', '.join(sorted(plugins.strategies()))}")
    return chosen


def register(app: typer.Typer) -> None:
    """Add the ``bench`` command group."""
    bench = typer.Typer(
        help="Benchmarks against the source paper on the simulated station.",
        no_args_is_help=True,
    )
    app.add_typer(bench, name="bench")

    @bench.command("paper")
    def paper(
        quick: bool = typer.Option(
            False, "--quick", help="a small subset (one scenario, one start per set)"
        ),
        workers: int = typer.Option(2, "--workers", min=1, help="worker processes"),
        out: Path = typer.Option(
            Path("out/bench"), "--out", help="folder for recordings, records and the report"
        ),
        recipe: Path = typer.Option(
            Path("recipes/sim-periodicity.yaml"), "--recipe", help="simulated-station recipe"
        ),
        report_dir: Path | None = typer.Option(
            None, "--report-dir",
            help="where results.md and results/*.png go (default: the --out folder)",
        ),
        scenarios: str | None = typer.Option(
            None, "--scenarios", help="comma-separated subset, e.g. D5,D6 (default: all nine)"
        ),
        starts: int | None = typer.Option(
            None, "--starts", min=0, help="perturbed starts per set (default 50; quick 1)"
        ),
        landscape_grid: int | None = typer.Option(
            None, "--landscape-grid", min=0, help="landscape grid size per axis (0: skip)"
        ),
        ablation_starts: int | None = typer.Option(
            None, "--ablation-starts", min=0, help="set-B starts per ablation scenario"
        ),
        resume: bool = typer.Option(
            False, "--resume", help="keep records.jsonl in --out and run only missing tasks"
        ),
        deadline: str | None = typer.Option(
            None, "--deadline",
            help="UTC time HH:MM (today): run only the perturbed starts that will end before it",
        ),
        round_starts: int = typer.Option(
            50, "--round-starts", min=1,
            help="set-A and set-B starts added per round; each round reads every scenario "
            "again, and a run stopped between rounds has every scenario at the same starts",
        ),
        label: str | None = typer.Option(
            None, "--label", help="a note printed at the top of results.md (e.g. a reduced run)"
        ),
    ) -> None:
        """Nine scenarios × {initial, shape, periodicity} × {initial start, 50 set-A, 50 set-B
        starts}, measured against the true H; writes results.md with tables and figures."""
        from dataclasses import replace

        from rich.console import Console

        from calstation.bench import BenchError
        from calstation.bench.report import write_report
        from calstation.bench.runner import run_bench
        from calstation.bench.scenarios import select_scenarios
        from calstation.bench.tasks import BenchConfig

        if not recipe.is_file():
            raise BenchError(f"{recipe}: recipe not found (give --recipe)")
        command = _command_line()
        make = BenchConfig.quick_config if quick else BenchConfig.full
        config = make(recipe, out, workers=workers, command=command)
        if scenarios:
            chosen = tuple(select_scenarios(scenarios.split(",")))
            config = replace(config, scenarios=chosen)
            names = {s.name for s in chosen}
            if config.landscape_scenario not in names:
                config = replace(config, landscape_scenario=chosen[-1].name)
            if not names & set(config.ablation_scenarios):
                config = replace(config, ablation_scenarios=(chosen[0].name,))
        if starts is not None:
            config = replace(config, starts_per_set=starts)
        if landscape_grid is not None:
            config = replace(
                config,
                landscape_grid=landscape_grid,
                landscape_scenario=config.landscape_scenario if landscape_grid else None,
            )
        if ablation_starts is not None:
            config = replace(config, ablation_starts=ablation_starts)
        config = replace(config, round_starts=round_starts)
        if deadline is not None:
            config = replace(config, deadline=_parse_deadline(deadline))
        console = Console(stderr=True)
        console.print(
            f"bench: {len(config.scenarios)} scenario(s), {config.starts_per_set} start(s) per "
            f"set, {config.workers} worker(s), output in {out}"
        )
        meta = run_bench(config, console, resume=resume)
        path = write_report(out, report_dir or out, meta, label)
        console.print(f"bench finished in {meta['wall_s'] / 60.0:.1f} min; report: {path}")

    @bench.command("basin")
    def basin(
        out: Path = typer.Option(
            Path("out/bench-basin"), "--out", help="folder for the recordings and records"
        ),
        report_dir: Path | None = typer.Option(
            None, "--report-dir",
            help="where basin.md and results/basin.png go (default: --out); `bench report` "
            "adds basin.md found there to results.md",
        ),
        recipe: Path = typer.Option(
            Path("recipes/sim-periodicity.yaml"), "--recipe", help="simulated-station recipe"
        ),
        scenario: str = typer.Option("D5", "--scenario", help="one of the paper's D1–D9"),
        methods: str = typer.Option(
            "periodicity,shape", "--methods", help="comma-separated fine-tuning strategies"
        ),
        starts: int = typer.Option(4, "--starts", min=1, help="starts per parameter and level"),
        workers: int = typer.Option(2, "--workers", min=1, help="worker processes"),
    ) -> None:
        """The basin of convergence: the fraction of starts that converge against the start's
        distance from the true H, per parameter and jointly, out to ±500 mm and ±10°."""
        from rich.console import Console

        from calstation.bench.basin import run_basin

        chosen = _strategies(recipe, methods)
        command = _command_line()
        console = Console(stderr=True)
        path = run_basin(recipe, out, report_dir or out, scenario, chosen, starts, workers,
                         command, console)
        console.print(f"basin of convergence: {path}")

    @bench.command("speed")
    def speed(
        out: Path = typer.Option(
            Path("out/bench-speed"), "--out", help="folder for the recordings and records"
        ),
        report_dir: Path | None = typer.Option(
            None, "--report-dir",
            help="where speed.md and results/speed.png go (default: --out); `bench report` "
            "adds speed.md found there to results.md",
        ),
        recipe: Path = typer.Option(
            Path("recipes/sim-periodicity.yaml"), "--recipe", help="simulated-station recipe"
        ),
        scenario: str = typer.Option("D5", "--scenario", help="one of the paper's D1–D9"),
        methods: str = typer.Option(
            "periodicity,shape", "--methods", help="comma-separated fine-tuning strategies"
        ),
        speeds: str = typer.Option(
            "1,2,5,10,20", "--rpm", help="comma-separated platter speeds (rpm)"
        ),
    ) -> None:
        """Accuracy against platter speed at the sensor's line rate: each speed simulated,
        calibrated and measured against the true H (a slow turn is held to the simulator's 25 M
        returns per scan)."""
        from rich.console import Console

        from calstation.bench import BenchError
        from calstation.bench.speed import run_speed

        try:
            rpms = [float(x) for x in speeds.split(",") if x.strip()]
        except ValueError:
            raise BenchError(f"--rpm {speeds!r}: expected numbers such as 1,2,5") from None
        if not rpms or any(not 0.1 <= r <= 120 for r in rpms):
            raise BenchError(f"--rpm {speeds!r}: each speed must lie within 0.1–120 rpm")
        chosen = _strategies(recipe, methods)
        command = _command_line()
        console = Console(stderr=True)
        path = run_speed(recipe, out, report_dir or out, scenario, chosen, rpms, command,
                         console)
        console.print(f"accuracy against platter speed: {path}")

    @bench.command("targetless")
    def targetless(
        out: Path = typer.Option(
            Path("out/bench-targetless"), "--out", help="folder for the records"
        ),
        report_dir: Path | None = typer.Option(
            None, "--report-dir",
            help="where targetless.md and results/targetless.png go (default: --out); `bench "
            "report` adds targetless.md found there to results.md",
        ),
        recipe: Path = typer.Option(
            Path("recipes/sim-periodicity.yaml"), "--recipe",
            help="simulated-station recipe (with the L-target, to compare both starts)",
        ),
        method: str = typer.Option("periodicity", "--method", help="fine-tuning strategy"),
        seeds: int = typer.Option(5, "--seeds", min=1, max=50, help="stations per scenario"),
        scenarios: str | None = typer.Option(
            None, "--scenarios", help="comma-separated D1–D9, E1–E3 (default: all twelve)"
        ),
        geometry: bool = typer.Option(
            True, "--geometry/--no-geometry",
            help="also the stations of D5 with tz (±25–100 mm) or ry (±1–2°) far from what the "
            "start assumes",
        ),
    ) -> None:
        """The targetless start on the paper's nine scenarios and three more, several seeds
        each: converged fraction from the platter's chord, beside the L-target's start; then
        its basin: stations whose tz or ry break the start's assumptions."""
        from rich.console import Console

        from calstation.bench import BenchError
        from calstation.bench.targetless import run_targetless, targetless_scenarios

        (chosen,) = _strategies(recipe, method)
        names = [n.strip().upper() for n in scenarios.split(",")] if scenarios else None
        known = {s.name for s in targetless_scenarios()}
        if names and not set(names) <= known:
            raise BenchError(f"--scenarios {scenarios!r}: expected some of "
                             f"{', '.join(sorted(known))}")
        command = _command_line()
        console = Console(stderr=True)
        path = run_targetless(recipe, out, report_dir or out, chosen, seeds, names, command,
                              console, geometry)
        console.print(f"targetless start: {path}")

    @bench.command("report")
    def report(
        out: Path = typer.Option(
            Path("out/bench"), "--out", help="the folder of a `bench paper` run"
        ),
        report_dir: Path | None = typer.Option(
            None, "--report-dir", help="where results.md and results/*.png go (default: --out)"
        ),
        label: str | None = typer.Option(None, "--label", help="a note at the top"),
    ) -> None:
        """Rewrite results.md and its figures from the records of an earlier (or still running)
        `bench paper` run."""
        from rich.console import Console

        from calstation.bench.report import write_report

        path = write_report(out, report_dir or out, None, label)
        Console(stderr=True).print(f"report: {path}")
