"""Aggregate the bench's records into the paper's tables, our ground-truth tables and
``results.md`` (with its PNG figures in ``results/``)."""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from calstation.bench import BenchError
from calstation.bench.figures import (
    METHOD_LABELS,
    ablation_figure,
    cube_boxplots,
    cube_error_values,
    deviations_from_mean,
    landscape_figure,
    param_boxplots,
)
from calstation.bench.runner import ABLATION_VARIANTS, ABLATIONS, CONVERGENCE, FINE_TUNING_METHODS
from calstation.bench.scenarios import PERTURBATION_SEED, SCENARIO_SEED_BASE, paper_scenarios

PAPER_TABLE_I = {"initial": 5.1, "shape": 3.2, "periodicity": 2.7}
"""Paper Table II (first): median cube edge error (mm), fine-tuning from the initial calibration."""
PAPER_TABLE_II = {
    "initial": {"A": 5.1, "B": 5.1},
    "shape": {"A": 3.0, "B": 4.0},
    "periodicity": {"A": 2.7, "B": 2.8},
}
"""Paper Table III: median cube edge error (mm) over the perturbed starts of sets A and B."""
PAPER_SPREAD = {
    ("periodicity", "A", "tx"): "sub-mm",
    ("periodicity", "B", "tx"): "≤ 1 mm for most",
    ("shape", "A", "tx"): "up to 12 mm (excl. outliers)",
}
"""What the paper says about the tx spread in its box plots (no numbers are printed)."""

SET_LABELS = {"init": "from initial", "A": "set A", "B": "set B"}
MM, DEG = 1e3, 180.0 / math.pi


def load_records(out: Path) -> list[dict[str, Any]]:
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


# --- selection and statistics --------------------------------------------------------------
def _select(
    records: Sequence[dict[str, Any]],
    method: str,
    start_set: str,
    variant: str = "default",
    ok_only: bool = True,
) -> list[dict[str, Any]]:
    out = []
    for r in records:
        if r.get("variant", "default") != variant:
            continue
        if method == "initial":
            if r["kind"] != "initial":
                continue
        elif not (r["kind"] == "finetune" and r["method"] == method and r["set"] == start_set):
            continue
        if ok_only and r.get("status") != "ok":
            continue
        out.append(r)
    return out


def _median(values: Sequence[float] | np.ndarray) -> float:
    arr = np.asarray(values, dtype=float)
    arr = arr[np.isfinite(arr)]
    return float(np.median(arr)) if arr.size else float("nan")


def _pct(values: Sequence[float] | np.ndarray, q: float) -> float:
    arr = np.asarray(values, dtype=float)
    arr = arr[np.isfinite(arr)]
    return float(np.percentile(arr, q)) if arr.size else float("nan")


def _fmt(x: float, digits: int = 2) -> str:
    if x is None or not math.isfinite(x):
        return "–"
    return f"{x:.{digits}f}"


def _values(recs: Sequence[dict[str, Any]], getter: Callable[[dict[str, Any]], Any]) -> np.ndarray:
    vals = []
    for r in recs:
        try:
            v = getter(r)
        except (KeyError, TypeError):
            continue
        if isinstance(v, int | float) and v is not None:
            vals.append(float(v))
    return np.asarray(vals, dtype=float)


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


# --- tables --------------------------------------------------------------------------------------
def _e_cell(e: np.ndarray, digits: int = 1) -> str:
    """Median (mm) with failures counted as +inf, and how many could not be measured."""
    if e.size == 0:
        return "–"
    med = float(np.median(e))
    lost = int(np.sum(~np.isfinite(e)))
    text = _fmt(med, digits) if math.isfinite(med) else "not measurable"
    return text + (f" ({lost}/{e.size} n/m)" if lost else "")


def table_from_initial(records: Sequence[dict[str, Any]], methods: Sequence[str]) -> str:
    """Paper Table II: median OBB cube edge error, fine-tuning from the initial calibration; the
    true H's row is the metric's floor on this simulated sensor."""
    rows = []
    for m in ["initial", *methods, "truth"]:
        e = cube_error_values(records, m, "init", "obb_error_m")
        ff = cube_error_values(records, m, "init", "edge_error_m")
        label = (
            "true H (metric floor, not in the paper)" if m == "truth" else METHOD_LABELS.get(m, m)
        )
        rows.append(
            [
                label,
                _e_cell(e),
                _fmt(PAPER_TABLE_I.get(m, float("nan")), 1),
                _e_cell(ff, 2),
                str(len(e)),
            ]
        )
    return _table(
        ["method", "calstation: median e (mm)", "paper (mm)", "calstation: face-fit (mm)", "N"],
        rows,
    )


def table_sets(records: Sequence[dict[str, Any]], methods: Sequence[str]) -> str:
    """Paper Table III: median OBB cube edge error over the perturbed starts of sets A and B
    (a run whose cube could not be measured counts as +inf: "n/m")."""
    rows = []
    for m in ["initial", *methods]:
        row = [METHOD_LABELS.get(m, m)]
        for s in ("A", "B"):
            e = cube_error_values(records, m, s, "obb_error_m")
            row += [_e_cell(e), _fmt(PAPER_TABLE_II.get(m, {}).get(s, float("nan")), 1)]
        rows.append(row)
    return _table(
        ["method", "set A: calstation (mm)", "set A: paper", "set B: calstation (mm)",
         "set B: paper"],
        rows,
    )


def table_ground_truth(records: Sequence[dict[str, Any]], methods: Sequence[str]) -> str:
    """Per method and start set: convergence, axis errors, per-parameter errors, distortion."""
    rows = []
    combos = [("initial", "init")] + [(m, s) for m in methods for s in ("init", "A", "B")]
    for m, s in combos:
        every = _select(records, m, s, ok_only=False)
        ok = [r for r in every if r.get("status") == "ok"]
        n_conv = sum(1 for r in every if r.get("converged"))
        off = _values(ok, lambda r: r["axis"]["axis_offset_m"]) * MM
        ang = _values(ok, lambda r: r["axis"]["axis_angle_rad"]) * DEG
        row = [
            METHOD_LABELS.get(m, m),
            SET_LABELS[s],
            f"{len(every)}",
            f"{len(every) - len(ok)}",
            f"{n_conv}/{len(every)} ({100.0 * n_conv / max(1, len(every)):.0f}%)",
            f"{_fmt(_median(off))} / {_fmt(_pct(off, 95))}",
            f"{_fmt(_median(ang), 3)} / {_fmt(_pct(ang, 95), 3)}",
        ]
        for p, scale, d in (("tx", MM, 2), ("ty", MM, 2), ("tz", MM, 2), ("ry", DEG, 3),
                            ("rz", DEG, 3)):
            err = _values(ok, lambda r, p=p: r["error"][p])  # type: ignore[misc]
            row.append(_fmt(_median(np.abs(err)) * scale, d))
        rms = _values(ok, lambda r: r["distortion"]["rms_m"]) * MM
        mx = _values(ok, lambda r: r["distortion"]["max_m"]) * MM
        row.append(f"{_fmt(_median(rms))} / {_fmt(_median(mx))}")
        rows.append(row)
    return _table(
        ["method", "start", "N", "failed", "converged", "axis offset mm (median / p95)",
         "axis direction ° (median / p95)", "tx err mm", "ty err mm", "tz err mm", "ry err °",
         "rz err °",
         "cube distortion mm (RMS / max, median)"],
        rows,
    )


def table_spread(records: Sequence[dict[str, Any]], methods: Sequence[str]) -> str:
    """The paper's box-plot statistics: deviation of tx, tz, ry, rz from their per-scenario mean
    over the perturbed starts; IQR and the largest |deviation| per method and set."""
    rows = []
    for m in methods:
        for s in ("A", "B"):
            row = [METHOD_LABELS.get(m, m), f"set {s}"]
            for p, scale, d in (("tx", MM, 3), ("tz", MM, 3), ("ry", DEG, 4), ("rz", DEG, 4)):
                dev = deviations_from_mean(records, m, s, p) * scale
                if dev.size:
                    iqr = float(np.percentile(dev, 75) - np.percentile(dev, 25))
                    row.append(f"{_fmt(iqr, d)} / {_fmt(float(np.max(np.abs(dev))), d)}")
                else:
                    row.append("–")
            tx = deviations_from_mean(records, m, s, "tx") * MM
            within = 100.0 * float(np.mean(np.abs(tx) <= 1.0)) if tx.size else float("nan")
            row.append(_fmt(within, 0) + "%")
            row.append(PAPER_SPREAD.get((m, s, "tx"), "–"))
            rows.append(row)
    return _table(
        ["method", "set", "tx mm (IQR / max)", "tz mm (IQR / max)", "ry ° (IQR / max)",
         "rz ° (IQR / max)", "tx within ±1 mm of mean", "paper on tx"],
        rows,
    )


def table_per_scenario(records: Sequence[dict[str, Any]], methods: Sequence[str]) -> str:
    """Per scenario: the OBB cube error of each method from the initial calibration, the
    periodicity axis offset from it, and each method's convergence rate over every start."""
    names = sorted({r["scenario"] for r in records if r["kind"] == "initial"},
                   key=lambda n: int(n[1:]))
    labels = {s.name: s.label for s in paper_scenarios()}
    rows = []
    for name in names:
        sub = [r for r in records if r["scenario"] == name]
        row = [labels.get(name, name)]
        for m in ["initial", *methods]:
            row.append(_e_cell(cube_error_values(sub, m, "init")))
        for m in methods:
            init = _select(sub, m, "init")
            off = _values(init, lambda r: r["axis"]["axis_offset_m"]) * MM
            row.append(_fmt(_median(off), 2))
        for m in methods:
            every = [r for s in ("init", "A", "B") for r in _select(sub, m, s, ok_only=False)]
            conv = sum(1 for r in every if r.get("converged"))
            row.append(f"{conv}/{len(every)}")
        rows.append(row)
    header = ["scenario"]
    header += [f"e {METHOD_LABELS.get(m, m)} (mm)" for m in ["initial", *methods]]
    header += [f"axis offset {METHOD_LABELS.get(m, m)} (mm)" for m in methods]
    header += [f"converged {METHOD_LABELS.get(m, m)}" for m in methods]
    return _table(header, rows)


def table_timing(records: Sequence[dict[str, Any]], methods: Sequence[str],
                 meta: dict[str, Any]) -> str:
    """Seconds per stage (median / p90 / max) as measured inside the workers."""
    rows = []
    sims = [r for r in records if r["kind"] == "simulate" and r.get("status") == "ok"]
    stages: list[tuple[str, np.ndarray]] = [
        ("simulate one scenario (3 scans)", _values(sims, lambda r: r["wall_s"])),
        ("initial calibration", _values(_select(records, "initial", "init"),
                                        lambda r: r["stage_s"])),
    ]
    for m in methods:
        recs = [r for s in ("init", "A", "B") for r in _select(records, m, s)]
        stages.append((f"{METHOD_LABELS.get(m, m)} fine-tuning",
                       _values(recs, lambda r: r["stage_s"])))
    evals = [r for r in records if r["kind"] in ("initial", "finetune") and r.get("status") == "ok"]
    stages.append(("cube check", _values(evals, lambda r: r["eval_timings"]["cube_check_s"])))
    stages.append(("reconstruction distortion",
                   _values(evals, lambda r: r["eval_timings"]["distortion_s"])))
    rows_ls = [r for r in records if r["kind"] == "landscape" and r.get("status") == "ok"]
    stages.append(("one cost evaluation (landscape)", _values(
        rows_ls, lambda r: r["stage_s"] / max(1, len(r["landscape"]["costs"])))))
    for name, v in stages:
        rows.append([name, str(v.size), _fmt(_median(v)), _fmt(_pct(v, 90)),
                     _fmt(float(np.max(v)) if v.size else float("nan"))])
    return _table(["stage", "N", "median (s)", "p90 (s)", "max (s)"], rows)


def _ablation_records(
    records: Sequence[dict[str, Any]], variant: str, scenarios: Sequence[str], n_starts: int,
    method: str = "periodicity",
) -> list[dict[str, Any]]:
    return [
        r for s in ("init", "B") for r in _select(records, method, s, variant, False)
        if r["scenario"] in scenarios and (s == "init" or r["index"] < n_starts)
    ]


def table_ablation(records: Sequence[dict[str, Any]], scenarios: Sequence[str],
                   n_starts: int, method: str = "periodicity") -> str:
    """``method`` with each robustness feature off, on the ablation subset (init + the first
    ``n_starts`` set-B starts)."""
    rows = []
    for variant in ABLATIONS[method]:
        every = _ablation_records(records, variant, scenarios, n_starts, method)
        if not every:
            continue
        ok = [r for r in every if r.get("status") == "ok"]
        conv = sum(1 for r in every if r.get("converged"))
        off = _values(ok, lambda r: r["axis"]["axis_offset_m"]) * MM
        ang = _values(ok, lambda r: r["axis"]["axis_angle_rad"]) * DEG
        ty = np.abs(_values(ok, lambda r: r["error"]["ty"])) * MM
        t = _values(ok, lambda r: r["stage_s"])
        rows.append([
            variant, str(len(every)), str(len(every) - len(ok)),
            f"{conv}/{len(every)} ({100.0 * conv / max(1, len(every)):.0f}%)",
            f"{_fmt(_median(off))} / {_fmt(_pct(off, 95))}",
            f"{_fmt(_median(ang), 3)} / {_fmt(_pct(ang, 95), 3)}",
            _fmt(_median(ty)),
            _fmt(_median(t), 1),
        ])
    return _table(
        [f"{method} variant", "N", "failed", "converged", "axis offset mm (median / p95)",
         "axis direction ° (median / p95)", "ty err mm (median)", "time s (median)"],
        rows,
    )


def _ablation_offsets(records: Sequence[dict[str, Any]], scenarios: Sequence[str],
                      n_starts: int, method: str = "periodicity") -> dict[str, np.ndarray]:
    out = {}
    for variant in ABLATIONS[method]:
        recs = [r for r in _ablation_records(records, variant, scenarios, n_starts, method)
                if r.get("status") == "ok"]
        if recs:
            out[variant] = _values(recs, lambda r: r["axis"]["axis_offset_m"]) * MM
    return out


def _load_note(meta: dict[str, Any]) -> str:
    """What the machine's load was during the run, as far as the metadata says."""
    start, end = meta.get("load_start"), meta.get("load_end")
    if start is None or end is None:
        return "the machine's load was not recorded; times depend on it"
    return (f"load average {start:.1f} at the start and {end:.1f} at the end; times on a busier "
            "machine are longer")


def main_records(records: Sequence[dict[str, Any]], starts: int) -> list[dict[str, Any]]:
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


def _landscape_grids(records: Sequence[dict[str, Any]]) -> dict[str, dict[str, dict[str, Any]]]:
    """pair name → method → {"u", "v", "cost", "truth", "scenario"} from landscape rows."""
    rows = [r for r in records if r["kind"] == "landscape" and r.get("status") == "ok"]
    out: dict[str, dict[str, dict[str, Any]]] = {}
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
    meta: dict[str, Any] | None = None,
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
    n_abl = int(cfg.get("ablation_starts", 0))
    methods = [m for m in cfg.get("methods", FINE_TUNING_METHODS)]
    fig_dir = report_dir / "results"
    fig_dir.mkdir(parents=True, exist_ok=True)

    param_boxplots(records, fig_dir / "param_spread.png", methods)
    if "periodicity" in methods:
        param_boxplots(records, fig_dir / "param_spread_periodicity.png", ["periodicity"], False)
    cube_boxplots(records, fig_dir / "cube_error.png", methods)
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
    abl_sc = [s for s in cfg.get("ablation_scenarios", []) if
              any(r["scenario"] == s for r in every)]
    lim = CONVERGENCE["periodicity"]["axis_offset_m"] * MM
    ablation_figure(_ablation_offsets(every, abl_sc, n_abl), fig_dir / "ablation.png", lim,
                    f"Periodicity ablation, scenarios {', '.join(abl_sc)} (init + set B)")
    shape_offsets = _ablation_offsets(every, abl_sc, n_abl, "shape")
    if len(shape_offsets) > 1:
        ablation_figure(shape_offsets, fig_dir / "ablation_shape.png",
                        CONVERGENCE["shape"]["axis_offset_m"] * MM,
                        f"Shape ablation, scenarios {', '.join(abl_sc)} (init + set B)")

    text = _compose(records, every, meta, methods, abl_sc, landscape_md, label)
    text += variants_section(report_dir)
    # sections of their own commands (calstation.bench.basin, .speed, .targetless)
    for name in ("basin.md", "speed.md", "targetless.md"):
        if (report_dir / name).is_file():
            text += "\n" + (report_dir / name).read_text()
    path = report_dir / "results.md"
    path.write_text(text)
    return path


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


def summary_against_paper(records: Sequence[dict[str, Any]], methods: Sequence[str]) -> str:
    """Bullet points: where calstation beats or trails each number the paper prints, computed
    from the records (median cube error e, its sets A/B, the tx spread for set A), with the
    ground truth the paper could not measure."""
    out = []

    def verdict(ours: float, paper: float) -> str:
        if not math.isfinite(ours):
            return "not measurable"
        return "beats" if ours < paper else ("ties" if ours == paper else "trails")

    for m in ["initial", *methods]:
        e = cube_error_values(records, m, "init", "obb_error_m")
        if e.size:
            med = float(np.median(e))
            out.append(
                f"- {METHOD_LABELS.get(m, m)}, from the initial calibration: median e "
                f"{_e_cell(e)} mm vs the paper's {PAPER_TABLE_I[m]:.1f} mm "
                f"({verdict(med, PAPER_TABLE_I[m])})."
            )
    floor = cube_error_values(records, "truth", "init", "obb_error_m")
    if floor.size:
        out.append(
            f"- The same metric with the *true* H gives a median e of "
            f"{_fmt(float(np.median(floor)), 1)} mm on this simulated sensor (range noise, mixed "
            "pixels at the cube's edges): the unsmoothed-OBB metric cannot go below that, so "
            "compare the methods with each other and with the ground-truth table rather than "
            "with the paper's absolute values."
        )
    for m in methods:
        for s in ("A", "B"):
            e = cube_error_values(records, m, s, "obb_error_m")
            if e.size:
                med = float(np.median(e))
                paper = PAPER_TABLE_II[m][s]
                every = _select(records, m, s, ok_only=False)
                ok = [r for r in every if r.get("status") == "ok"]
                conv = sum(1 for r in every if r.get("converged"))
                out.append(
                    f"- {METHOD_LABELS.get(m, m)}, set {s}: median e {_e_cell(e)} mm vs "
                    f"{paper:.1f} mm ({verdict(med, paper)}); converged {conv}/{len(every)} "
                    f"({len(every) - len(ok)} stopped with an error; {conv} of the {len(ok)} "
                    "estimates returned are within the thresholds)."
                )
    for m in methods:
        for s in ("A", "B"):
            tx = deviations_from_mean(records, m, s, "tx") * MM
            if tx.size:
                iqr = float(np.percentile(tx, 75) - np.percentile(tx, 25))
                within = 100.0 * float(np.mean(np.abs(tx) <= 1.0))
                out.append(
                    f"- tx spread, {METHOD_LABELS.get(m, m)}, set {s}: IQR {_fmt(iqr, 3)} mm, "
                    f"{within:.0f}% within ±1 mm of the mean, largest "
                    f"{_fmt(float(np.max(np.abs(tx))), 3)} mm (paper: "
                    f"{PAPER_SPREAD.get((m, s, 'tx'), 'no statement')})."
                )
    return "\n".join(out) if out else "(no results)"


def _compose(
    records: Sequence[dict[str, Any]],
    every: Sequence[dict[str, Any]],
    meta: dict[str, Any],
    methods: Sequence[str],
    abl_sc: Sequence[str],
    landscape_md: Sequence[str],
    label: str | None,
) -> str:
    cfg = meta.get("config", {})
    scen = cfg.get("scenarios", [])
    n_starts = meta.get("starts_completed", cfg.get("starts_per_set", "?"))
    wall = meta.get("wall_s_total", meta.get("wall_s"))
    phases = meta.get("phases_s", {})
    failed = [r for r in every if r.get("status") != "ok"]
    n_fine = sum(
        1 for r in records if r["kind"] == "finetune" and r.get("variant", "default") == "default"
    )
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
    parts += [
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
        "## Cost landscapes",
        "",
    ]
    parts += list(landscape_md) or ["(no landscape was sampled in this run)"]
    parts += [
        "",
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
    parts += [
        "## Time per stage",
        "",
        "Measured inside the worker processes (one thread each).",
        "",
        table_timing(records, methods, meta),
        "",
    ]
    if failed:
        parts += [
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
    return "\n".join(parts)
