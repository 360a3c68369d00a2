"""Aggregate the bench's records into the paper's tables, our ground-truth tables and
``results.md`` (with its PNG figures in ``results/``); the tables themselves are
:mod:`calstation.bench.tables`."""

from __future__ import annotations

import json
import math
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from calstation.atomic import write_atomic
from calstation.bench import BenchError
from calstation.bench.figures import (
    ablation_figure,
    cube_boxplots,
    landscape_figure,
    param_boxplots,
)
from calstation.bench.records import CONVERGENCE, BenchRecord, LandscapeGrid
from calstation.bench.scenarios import PERTURBATION_SEED, SCENARIO_SEED_BASE
from calstation.bench.tables import (
    DEG,
    MM,
    SET_LABELS,
    _ablation_offsets,
    _fmt,
    summary_against_paper,
    table_ablation,
    table_from_initial,
    table_ground_truth,
    table_per_scenario,
    table_sets,
    table_spread,
    table_timing,
)
from calstation.bench.tasks import ABLATION_VARIANTS, ABLATIONS, FINE_TUNING_METHODS, RunMeta


def load_records(out: Path) -> list[BenchRecord]:
    """Every record in ``out/records.jsonl`` (torn last lines skipped)."""
    path = out / "records.jsonl"
    if not path.is_file():
        raise BenchError(f"{path}: no bench records (run `calstation bench paper` first)")
    recs = []
    for line in path.read_text().splitlines():
        try:
            recs.append(json.loads(line))
        except ValueError:
            continue
    return recs


def _load_note(meta: RunMeta) -> str:
    """What the machine's load was during the run, as far as the metadata says."""
    start, end = meta.get("load_start"), meta.get("load_end")
    if start is None or end is None:
        return "the machine's load was not recorded; times depend on it"
    return (f"load average {start:.1f} at the start and {end:.1f} at the end; times on a busier "
            "machine are longer")


def main_records(records: Sequence[BenchRecord], starts: int) -> list[BenchRecord]:
    """The records of the main protocol: everything except ablation variants, and set-A/B
    starts numbered ``starts`` or more (rounds the run did not complete for every scenario)."""
    out = []
    for r in records:
        if r.get("variant", "default") != "default":
            continue
        if r["kind"] == "finetune" and r["set"] in ("A", "B") and r["index"] >= starts:
            continue
        out.append(r)
    return out


def _criterion_text() -> str:
    p, s, i = CONVERGENCE["periodicity"], CONVERGENCE["shape"], CONVERGENCE["initial"]
    return (
        f"- periodicity: axis offset ≤ {p['axis_offset_m'] * MM:g} mm, axis direction ≤ "
        f"{p['axis_angle_rad'] * DEG:g}°, |rz error| ≤ {p['rz_rad'] * DEG:g}°;\n"
        f"- shape: axis offset ≤ {s['axis_offset_m'] * MM:g} mm, axis direction ≤ "
        f"{s['axis_angle_rad'] * DEG:g}°;\n"
        f"- initial: every parameter inside the paper's set-A box around the truth "
        f"(|tx|, |ty|, |tz| ≤ {i['tx_m'] * MM:g} mm, |ry|, |rz| ≤ {i['ry_rad'] * DEG:g}°).\n"
        "A run that raised an error counts as not converged."
    )


def _landscape_grids(records: Sequence[BenchRecord]) -> dict[str, dict[str, LandscapeGrid]]:
    """pair name → method → {"u", "v", "cost", "truth", "scenario"} from landscape rows."""
    rows = [r for r in records if r["kind"] == "landscape" and r.get("status") == "ok"]
    out: dict[str, dict[str, LandscapeGrid]] = {}
    for r in rows:
        ls = r["landscape"]
        g = out.setdefault(ls["pair_name"], {}).setdefault(
            ls["method"],
            {"u": ls["u"], "v": ls["v"], "cost": [[math.nan] * len(ls["v"])
                                                   for _ in ls["u"]],
             "truth": ls.get("truth"), "scenario": r["scenario"], "pair": ls["pair"],
             "source": ls.get("source", "")},
        )
        g["cost"][ls["row"]] = [math.nan if c is None else c for c in ls["costs"]]
    return out


def write_report(
    out: Path,
    report_dir: Path,
    meta: RunMeta | None = None,
    label: str | None = None,
) -> Path:
    """Write ``report_dir/results.md`` and ``report_dir/results/*.png`` from the records in
    ``out``; returns the path of results.md."""
    every = load_records(out)
    if meta is None:
        meta_path = out / "run.json"
        meta = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
    cfg = meta.get("config", {})
    records = main_records(every, int(meta.get("starts_completed", cfg.get("starts_per_set", 0))))
    methods = [m for m in cfg.get("methods", FINE_TUNING_METHODS)]
    fig_dir = report_dir / "results"
    fig_dir.mkdir(parents=True, exist_ok=True)

    _spread_figures(records, methods, fig_dir)
    landscape_md = _landscape_figures(records, methods, fig_dir)
    abl_sc = [s for s in cfg.get("ablation_scenarios", []) if
              any(r["scenario"] == s for r in every)]
    _ablation_figures(every, abl_sc, int(cfg.get("ablation_starts", 0)), fig_dir)

    text = _compose(records, every, meta, methods, abl_sc, landscape_md, label)
    text += variants_section(report_dir)
    # sections of their own commands (calstation.bench.basin, .speed, .targetless)
    for name in ("basin.md", "speed.md", "targetless.md"):
        if (report_dir / name).is_file():
            text += "\n" + (report_dir / name).read_text()
    path = report_dir / "results.md"
    write_atomic(path, text, "bench report")
    return path


def _spread_figures(records: Sequence[BenchRecord], methods: Sequence[str],
                    fig_dir: Path) -> None:
    """The parameters' box plots (all methods, and periodicity alone) and the cube errors'."""
    param_boxplots(records, fig_dir / "param_spread.png", methods)
    if "periodicity" in methods:
        param_boxplots(records, fig_dir / "param_spread_periodicity.png", ["periodicity"], False)
    cube_boxplots(records, fig_dir / "cube_error.png", methods)


def _landscape_figures(records: Sequence[BenchRecord], methods: Sequence[str],
                       fig_dir: Path) -> list[str]:
    """A figure per sampled landscape (translation, rotation); the lines of results.md that
    show them and name the cost functions (none without a landscape)."""
    grids = _landscape_grids(records)
    landscape_md: list[str] = []
    sources: dict[str, str] = {}
    for pair_name, title in (("translation", "translation"), ("rotation", "rotation")):
        if pair_name in grids:
            g = grids[pair_name]
            any_g = next(iter(g.values()))
            pair = tuple(any_g["pair"])
            fname = f"landscape_{pair_name}.png"
            landscape_figure(
                {m: g[m] for m in methods if m in g}, fig_dir / fname, (pair[0], pair[1]),
                f"Cost landscape over {pair[0]} × {pair[1]}, scenario {any_g['scenario']} "
                "(axes: deviation from each method's converged value)",
            )
            landscape_md += [f"![{title} landscape](results/{fname})", ""]
            sources = {m: g[m].get("source", "") for m in g}
    if grids:
        landscape_md += [
            "Cost functions: " + "; ".join(f"{m}: {src}" for m, src in sources.items()) + ".",
            "",
            "calstation.engine.periodicity has no public function that evaluates the whole cost "
            "at a given H (only the optimiser's private residuals), so that landscape is assembled "
            "from its public building blocks as listed; the shape landscape uses the engine's "
            "public `ShapeCost`. Each grid point re-segments (shape) or re-matches "
            "(periodicity) at its own H, as the optimiser's outer loop does.",
        ]
    return landscape_md


def _ablation_figures(every: Sequence[BenchRecord], abl_sc: Sequence[str], n_abl: int,
                      fig_dir: Path) -> None:
    """The axis offsets of each ablation variant: periodicity's, and shape's when it has
    variants besides the default."""
    lim = CONVERGENCE["periodicity"]["axis_offset_m"] * MM
    ablation_figure(_ablation_offsets(every, abl_sc, n_abl), fig_dir / "ablation.png", lim,
                    f"Periodicity ablation, scenarios {', '.join(abl_sc)} (init + set B)")
    shape_offsets = _ablation_offsets(every, abl_sc, n_abl, "shape")
    if len(shape_offsets) > 1:
        ablation_figure(shape_offsets, fig_dir / "ablation_shape.png",
                        CONVERGENCE["shape"]["axis_offset_m"] * MM,
                        f"Shape ablation, scenarios {', '.join(abl_sc)} (init + set B)")


def variants_section(report_dir: Path) -> str:
    """"Harder stations": the ground-truth table of each variant report found in
    ``report_dir/bench-variants/<name>/results.md`` (``benchmarks/paper_variants.py``), with a
    link to it; empty when there is none."""
    root = report_dir / "bench-variants"
    found = sorted(d for d in root.iterdir() if (d / "results.md").is_file()) \
        if root.is_dir() else []
    parts = []
    for d in found:
        lines = (d / "results.md").read_text().splitlines()
        if "## Against the true H" not in lines:
            continue
        rest = lines[lines.index("## Against the true H") + 1:]
        start = next((i for i, line in enumerate(rest) if line.startswith("|")), len(rest))
        table = []
        for line in rest[start:]:
            if not line.startswith("|"):
                break
            table.append(line)
        parts += [f"### {d.name}: [its report](bench-variants/{d.name}/results.md)", "", *table,
                  ""]
    if not parts:
        return ""
    head = ["", "## Harder stations", "",
            "The same bench on recipes the default simulator does not produce "
            "(`benchmarks/paper_variants.py`: 2 mm of range noise, no background), each with its "
            "own report, figures and provenance; their ground-truth tables, columns as above "
            "(estimates without the observability gate or the cube's ry):", ""]
    return "\n".join(head + parts)


def _compose(
    records: Sequence[BenchRecord],
    every: Sequence[BenchRecord],
    meta: RunMeta,
    methods: Sequence[str],
    abl_sc: Sequence[str],
    landscape_md: Sequence[str],
    label: str | None,
) -> str:
    """The text of results.md, section by section: ``records`` the main protocol's,
    ``every`` all of them (ablation variants and failures included)."""
    parts = _title(every, meta, methods, label)
    parts += _provenance(records, every, meta)
    parts += _against_the_paper(records, methods)
    parts += _against_the_truth(records, methods)
    parts += ["## Cost landscapes", ""]
    parts += list(landscape_md) or ["(no landscape was sampled in this run)"]
    parts += [""]
    parts += _ablation(every, meta, abl_sc)
    parts += [
        "## Time per stage",
        "",
        "Measured inside the worker processes (one thread each).",
        "",
        table_timing(records, methods, meta),
        "",
    ]
    parts += _failures([r for r in every if r.get("status") != "ok"])
    return "\n".join(parts)


def _starts(meta: RunMeta) -> int | str:
    """Perturbed starts per set the run completed (its configuration's, or "?")."""
    return meta.get("starts_completed", meta.get("config", {}).get("starts_per_set", "?"))


def _title(
    every: Sequence[BenchRecord],
    meta: RunMeta,
    methods: Sequence[str],
    label: str | None,
) -> list[str]:
    """The heading, the run's ``label`` and, for a run smaller than the paper's protocol, what
    was left out and what the whole protocol would take."""
    cfg = meta.get("config", {})
    scen = cfg.get("scenarios", [])
    n_starts = _starts(meta)
    parts = [
        "# Results: the paper's experiments on the simulated station",
        "",
        "Generated by `calstation bench paper` (calstation/bench/). Every number below comes from "
        "the run described in *Provenance*; the simulator knows the true H, so beside the paper's "
        "indirect cube metric we report the errors against the truth (DESIGN §8).",
        "",
    ]
    reduced = []
    if len(scen) < 9:
        reduced.append(f"{len(scen)} of the 9 scenarios")
    if isinstance(n_starts, int) and n_starts < 50:
        reduced.append(f"{n_starts} instead of 50 perturbed starts per set")
    if meta.get("cut_by_deadline"):
        reduced.append("stopped at its deadline")
    if label:
        parts += [f"> **{label}**", ""]
    if reduced:
        fine = [r for r in every if r["kind"] == "finetune"]
        per_task = float(np.mean([r["wall_s"] for r in fine])) if fine else float("nan")
        full_h = per_task * 9 * len(methods) * 101 / max(1, int(cfg.get("workers", 1))) / 3600
        parts += [
            "> **Reduced run** (the paper's protocol is 9 scenarios × 50 + 50 starts): "
            + "; ".join(reduced) + f". At this run's mean of {_fmt(per_task, 1)} s per "
            f"fine-tuning task (calibration, cube check and distortion, measured on a shared "
            f"machine) the full protocol would need ~{_fmt(full_h, 1)} h with "
            f"{cfg.get('workers', '?')} workers, beyond the time available; the perturbed "
            "starts run in rounds (start i of sets A and B, every scenario and method) and the "
            "run stopped after the last round that fitted, so every scenario has the same "
            "starts. The seeds make any larger run extend this one (`--resume`).",
            "",
        ]
    return parts


def _provenance(
    records: Sequence[BenchRecord], every: Sequence[BenchRecord], meta: RunMeta
) -> list[str]:
    """How the run was made: command, commit, times, machine, recipe, scenarios, seeds, starts."""
    cfg = meta.get("config", {})
    scen = cfg.get("scenarios", [])
    n_starts = _starts(meta)
    wall = meta.get("wall_s_total", meta.get("wall_s"))
    phases = meta.get("phases_s", {})
    failed = [r for r in every if r.get("status") != "ok"]
    n_fine = sum(
        1 for r in records if r["kind"] == "finetune" and r.get("variant", "default") == "default"
    )
    return [
        "## Provenance",
        "",
        f"- Command: `{meta.get('command', '?')}`",
        f"- Git commit: `{meta.get('git_commit', '?')}`",
        f"- Started {meta.get('started_utc', '?')}, finished {meta.get('finished_utc', '?')}; "
        f"wall time {_fmt((wall or float('nan')) / 60.0, 1)} min on {meta.get('cpu_count', '?')} "
        f"cores with {cfg.get('workers', '?')} workers ({_load_note(meta)}).",
        "- Phases (s): " + ", ".join(f"{k} {v:.0f}" for k, v in phases.items()),
        f"- Recipe: `{cfg.get('recipe', '?')}`; scenarios "
        + ", ".join(f"{s['name']} ({s['range_m']:.2f} m, {s['pitch_deg']:.0f}°, seed {s['seed']})"
                    for s in scen),
        f"- Seeds: scenario D*i* is simulated with seed {SCENARIO_SEED_BASE} + *i*; the "
        f"perturbed starts use numpy `SeedSequence([{cfg.get('seed', PERTURBATION_SEED)}, "
        "scenario index 0–8, set index (A=0, B=1)])`, drawn uniformly in ±100 mm / ±1° (set A) "
        "and ±200 mm / ±2° (set B) on tx, tz, ry, rz around the initial calibration; ty is fixed "
        "and rx = 0. The same starts are used by both methods.",
        f"- Starts: the initial calibration plus {n_starts} set-A and {n_starts} set-B starts per "
        f"scenario and method ({n_fine} "
        f"fine-tunings); {len(failed)} task(s) raised an error (counted as not converged).",
        "",
    ]


def _against_the_paper(records: Sequence[BenchRecord], methods: Sequence[str]) -> list[str]:
    """The summary against the paper and its two cube-error tables (paper Tables II, III)."""
    return [
        "## Against the paper, in short",
        "",
        summary_against_paper(records, methods),
        "",
        "## Median cube edge error, fine-tuning from the initial calibration (paper Table II)",
        "",
        "The paper's metric: e = max_i(ŝ_i − s), edges ŝ_i of a minimum-volume oriented bounding "
        "box of the unsmoothed 10 cm cube cloud "
        "(`calstation.engine.cube.check_cube(...).obb_error`), "
        "median over the scenarios. The face-fit column is calstation's robust dimensioning "
        "(distance between opposite fitted face planes).",
        "",
        table_from_initial(records, methods),
        "",
        "## Median cube edge error over perturbed starts (paper Table III)",
        "",
        "The initial calibration is not perturbed, so its row repeats the table above.",
        "",
        table_sets(records, methods),
        "",
        "![cube edge error](results/cube_error.png)",
        "",
    ]


def _against_the_truth(records: Sequence[BenchRecord], methods: Sequence[str]) -> list[str]:
    """The errors against the true H, the spread over the perturbed starts (the paper's box
    plots) and the table per scenario."""
    return [
        "## Against the true H",
        "",
        "Axis offset: distance between the estimated and the true rotation axis, perpendicular "
        "to the true axis at the platter centre; axis direction: angle between them "
        "(`calstation.engine.metrics.axis_errors`). Per-parameter columns: median of |estimate − "
        "truth|; "
        "the periodicity gauge (the origin along the axis) comes from the engine's configured "
        "gauge, so the tx and ty errors include the gauge choice, which the axis metrics do not. "
        "Cube "
        "distortion: the QA-cube scan reconstructed with the estimated and with the true H, RMS "
        "and maximum point displacement after the best rigid alignment "
        "(`calstation.engine.metrics.reconstruction_distortion`).",
        "",
        "Converged means within the engine issue's thresholds:",
        "",
        _criterion_text(),
        "",
        table_ground_truth(records, methods),
        "",
        "## Spread over perturbed starts (the paper's box plots)",
        "",
        "Deviation of each estimate from the mean of its scenario and set, pooled over the "
        "scenarios (as the paper's Fig. 8, N = scenarios × starts). IQR / largest |deviation|; "
        "the paper prints no numbers, only what it says about tx.",
        "",
        table_spread(records, methods),
        "",
        "![parameter spread](results/param_spread.png)",
        "",
        "The periodicity boxes on their own, linear axes:",
        "",
        "![periodicity parameter spread](results/param_spread_periodicity.png)",
        "",
        "## Per scenario",
        "",
        table_per_scenario(records, methods),
        "",
    ]


def _ablation(
    every: Sequence[BenchRecord], meta: RunMeta, abl_sc: Sequence[str]
) -> list[str]:
    """The ablation of calstation's robustness features: periodicity's variants, and shape's
    when the run had any besides the default."""
    cfg = meta.get("config", {})
    parts = [
        "## Ablation of calstation's robustness features",
        "",
        "### Periodicity",
        "",
        f"Scenarios {', '.join(abl_sc) or '–'}; the initial calibration and the first "
        f"{cfg.get('ablation_starts', '?')} set-B starts of each. Recipe overrides per variant: "
        + "; ".join(
            f"{k}: `{json.dumps(ABLATION_VARIANTS[k])}`"
            for k in cfg.get("ablation_variants", list(ABLATION_VARIANTS))
            if k in ABLATION_VARIANTS
        ) + ".",
        "",
        table_ablation(every, abl_sc, int(cfg.get("ablation_starts", 0))),
        "",
        "![ablation](results/ablation.png)",
        "",
    ]
    shape_variants = [k for k in cfg.get("shape_ablation_variants", []) if k != "default"]
    if shape_variants:
        parts += [
            "### Shape",
            "",
            "The same subset with the shape strategy's additions switched off. Recipe overrides "
            "per variant: "
            + "; ".join(
                f"{k}: `{json.dumps(ABLATIONS['shape'][k])}`"
                for k in shape_variants
                if k in ABLATIONS["shape"]
            ) + ".",
            "",
            table_ablation(every, abl_sc, int(cfg.get("ablation_starts", 0)), "shape"),
            "",
            "![shape ablation](results/ablation_shape.png)",
            "",
        ]
    return parts


def _failures(failed: Sequence[BenchRecord]) -> list[str]:
    """The runs that raised an error, grouped by message (digits and file paths removed);
    nothing when there are none."""
    if not failed:
        return []
    parts = [
        "## Failures",
        "",
        "Runs that raised an error instead of returning an estimate (the engine's own "
        "message, file path removed), by method, start set and variant:",
        "",
    ]
    seen: dict[tuple[str, str], list[str]] = {}
    for r in failed:
        msg = str(r.get("error_message", "?")).splitlines()[0]
        msg = re.sub(r"\S*/scenarios/D\d/\w+\.mcap: ", "", msg)
        msg = re.sub(r"\d+", "#", msg)[:220]
        where = f"{r['method']}, {SET_LABELS.get(r['set'], r['set'])}"
        if r.get("variant", "default") != "default":
            where += f", {r['variant']}"
        seen.setdefault((where, msg), []).append(r["scenario"])
    for (where, msg), scen in sorted(seen.items(), key=lambda kv: (kv[0][0], -len(kv[1]))):
        names = ", ".join(sorted(set(scen), key=lambda n: int(n[1:])))
        parts.append(f"- {len(scen)} × [{where}] {msg} ({names})")
    parts.append("")
    return parts
