"""The bench's figures (matplotlib, Agg backend, PNG), after the paper's box plots and cost
landscapes. Each function takes plain records (see :mod:`.records`) and writes one PNG."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from calstation.bench.records import BenchRecord, LandscapeGrid

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

METHOD_LABELS = {
    "initial": "initial",
    "shape": "shape-constrained",
    "periodicity": "periodicity-constrained",
}
METHOD_COLOURS = {"initial": "#9e9e9e", "shape": "#e07b39", "periodicity": "#3a7dc9"}

PARAMS_BOX: tuple[tuple[str, str, float, float], ...] = (
    # name, unit, scale from SI, symlog linear threshold (display units)
    ("tx", "mm", 1e3, 1.0),
    ("tz", "mm", 1e3, 1.0),
    ("ry", "°", 180.0 / math.pi, 0.05),
    ("rz", "°", 180.0 / math.pi, 0.05),
)



def save_figure(fig: Figure, path: Path, dpi: int = 110) -> None:
    """Write the matplotlib figure ``fig`` to ``path`` (its format from the suffix), whole or not
    at all (:func:`calstation.atomic.atomic_output`; a missing folder is made)."""
    from calstation.atomic import atomic_output

    with atomic_output(path, "figure", make_parents=True) as tmp:
        fig.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".") or "png")

def _agg() -> None:
    """Draw without a display (matplotlib's Agg backend), before pyplot is used."""
    import matplotlib

    matplotlib.use("Agg")


def deviations_from_mean(
    records: Sequence[BenchRecord], method: str, start_set: str, param: str
) -> np.ndarray:
    """Deviation of the estimated ``param`` (SI units) from its mean over the starts of
    ``start_set``, the mean taken per scenario (as the paper's box plots), pooled over scenarios.
    Only successful runs count. Shape (N,)."""
    by_scenario: dict[str, list[float]] = {}
    for r in records:
        if (
            r["kind"] == "finetune"
            and r["method"] == method
            and r["set"] == start_set
            and r.get("variant", "default") == "default"
            and r.get("status") == "ok"
        ):
            by_scenario.setdefault(r["scenario"], []).append(float(r["H"][param]))
    parts = [np.asarray(v) - np.mean(v) for v in by_scenario.values() if v]
    return np.concatenate(parts) if parts else np.zeros(0)


def param_boxplots(
    records: Sequence[BenchRecord], path: Path, methods: Sequence[str], log: bool = True
) -> None:
    """Box plots of the deviation from the mean of tx, tz (mm), ry, rz (°) per method, for set A
    (left) and set B (right). ``log``: symmetric-log y axes so sub-millimetre spreads and far
    outliers both show; otherwise linear (for one method's own scale)."""
    _agg()
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(4, 2, figsize=(8.5, 11), constrained_layout=True)
    for row, (param, unit, scale, linthresh) in enumerate(PARAMS_BOX):
        for col, start_set in enumerate(("A", "B")):
            ax = axes[row][col]
            data = [deviations_from_mean(records, m, start_set, param) * scale for m in methods]
            _boxes(ax, data, methods)
            if log:
                ax.set_yscale("symlog", linthresh=linthresh)
            ax.axhline(0.0, color="k", lw=0.5)
            ax.set_title(f"{param} deviation from mean, set {start_set}", fontsize=10)
            ax.set_ylabel(f"{param} − mean ({unit})")
            ax.grid(True, axis="y", alpha=0.3)
    which = " and ".join(METHOD_LABELS.get(m, m) for m in methods)
    fig.suptitle(f"Spread of the fine-tuned parameters over perturbed starts: {which}")
    save_figure(fig, path)
    plt.close(fig)


def _boxes(ax: Axes, data: Sequence[np.ndarray], methods: Sequence[str]) -> None:
    positions = list(range(1, len(methods) + 1))
    nonempty = [d if len(d) else np.array([np.nan]) for d in data]
    bp = ax.boxplot(
        nonempty,
        positions=positions,
        widths=0.6,
        patch_artist=True,
        showfliers=True,
        flierprops={"markersize": 3, "alpha": 0.6},
        medianprops={"color": "k"},
    )
    for patch, m in zip(bp["boxes"], methods, strict=True):
        patch.set_facecolor(METHOD_COLOURS.get(m, "#cccccc"))
        patch.set_alpha(0.8)
    ax.set_xticks(positions)
    ax.set_xticklabels(
        [f"{METHOD_LABELS.get(m, m)}\nN={len(d)}" for m, d in zip(methods, data, strict=True)],
        fontsize=8,
    )


def cube_error_values(
    records: Sequence[BenchRecord], method: str, start_set: str, key: str = "obb_error_m"
) -> np.ndarray:
    """The cube edge error ``key`` (mm) of every record of ``method`` and ``start_set``
    (``"init"`` for the initial calibration itself; method ``"truth"``: the cube checked with
    the true H, the metric's floor). A calibration or cube check that failed gives +inf: the
    cube could not be measured. Shape (N,)."""
    vals = []
    for r in records:
        if r.get("variant", "default") != "default":
            continue
        if method in ("initial", "truth"):
            ok = r["kind"] == "initial"
        else:
            ok = r["kind"] == "finetune" and r["method"] == method and r["set"] == start_set
        if not ok:
            continue
        cube = r.get("truth_cube", {}) if method == "truth" else r.get("cube", {})
        v = cube.get(key) if r.get("status") == "ok" or method == "truth" else None
        vals.append(float(v) * 1e3 if isinstance(v, int | float) else math.inf)
    return np.asarray(vals, dtype=float)


def cube_boxplots(records: Sequence[BenchRecord], path: Path, methods: Sequence[str]) -> None:
    """Box plots of the paper's cube edge error e = max_i(ŝ_i − s) (OBB of the unsmoothed
    cloud, mm) for the initial calibration and each method, for sets A and B; the face-fit edge
    error below."""
    _agg()
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(9, 7), constrained_layout=True)
    all_methods = ["initial", *methods]
    panels = (
        ("obb_error_m", "OBB edge error e (paper metric)"),
        ("edge_error_m", "face-fit edge error"),
    )
    for row, (key, title) in enumerate(panels):
        for col, start_set in enumerate(("A", "B")):
            ax = axes[row][col]
            data = [cube_error_values(records, m, start_set, key) for m in all_methods]
            lost = sum(int(np.sum(~np.isfinite(d))) for d in data)
            finite = [d[np.isfinite(d)] for d in data]
            _boxes(ax, finite, all_methods)
            ax.set_yscale("symlog", linthresh=1.0)
            low = min((float(d.min()) for d in finite if d.size), default=0.0)
            ax.set_ylim(bottom=min(0.0, low))
            note = f" ({lost} n/m)" if lost else ""
            ax.set_title(f"{title}, set {start_set}{note}", fontsize=9)
            ax.set_ylabel("mm")
            ax.grid(True, axis="y", alpha=0.3)
    fig.suptitle(
        "10 cm QA-cube edge error (initial: one value per scenario; n/m: cube not measurable)"
    )
    save_figure(fig, path)
    plt.close(fig)


def landscape_figure(
    grids: dict[str, LandscapeGrid], path: Path, pair: tuple[str, str], title: str
) -> None:
    """Filled contours of each method's cost over ``pair`` (deviation from its converged value,
    mm or °), one panel per method in ``grids`` (method → {"u", "v", "cost", "truth"}). Costs are
    shown as log10 of cost/min so the basin's shape is visible across decades."""
    _agg()
    import matplotlib.pyplot as plt

    methods = list(grids)
    fig, axes = plt.subplots(
        1, max(1, len(methods)), figsize=(5.2 * max(1, len(methods)), 4.6),
        constrained_layout=True, squeeze=False,
    )
    units = {p: ("mm" if p.startswith("t") else "°") for p in pair}
    for ax, m in zip(axes[0], methods, strict=False):
        g = grids[m]
        u, v, cost = np.asarray(g["u"]), np.asarray(g["v"]), np.asarray(g["cost"], dtype=float)
        finite = np.isfinite(cost) & (cost > 0)
        if finite.any():
            floor = np.nanmin(cost[finite])
            z = np.where(finite, np.log10(np.where(finite, cost, floor) / floor), np.nan)
            cs = ax.contourf(u, v, z.T, levels=20, cmap="viridis")
            ax.contour(u, v, z.T, levels=10, colors="w", linewidths=0.4, alpha=0.6)
            fig.colorbar(cs, ax=ax, label="log10(cost / min cost)")
        ax.plot([0], [0], "r+", ms=12, mew=2, label="converged")
        truth = g["truth"]
        if truth is not None:
            ax.plot([truth[0]], [truth[1]], "wx", ms=9, mew=2, label="true H")
        ax.set_xlabel(f"Δ{pair[0]} ({units[pair[0]]})")
        ax.set_ylabel(f"Δ{pair[1]} ({units[pair[1]]})")
        ax.set_title(f"{METHOD_LABELS.get(m, m)} cost", fontsize=10)
        ax.legend(loc="upper right", fontsize=7)
    fig.suptitle(title)
    save_figure(fig, path)
    plt.close(fig)


def ablation_figure(
    data: dict[str, np.ndarray], path: Path, limit_mm: float, title: str
) -> None:
    """Box plots of the axis offset (mm) per ablation variant, with the convergence limit."""
    _agg()
    import matplotlib.pyplot as plt

    names = list(data)
    fig, ax = plt.subplots(figsize=(max(6.0, 1.9 * len(names)), 4.2), constrained_layout=True)
    vals = [data[n] if len(data[n]) else np.array([np.nan]) for n in names]
    ax.boxplot(vals, widths=0.6, showfliers=True, flierprops={"markersize": 3})
    ax.set_xticks(range(1, len(names) + 1))
    ax.set_xticklabels(names, fontsize=8)
    ax.set_yscale("log")
    ax.axhline(limit_mm, color="r", lw=0.8, ls="--", label=f"limit {limit_mm} mm")
    ax.set_ylabel("axis offset (mm)")
    ax.legend(fontsize=8)
    ax.grid(True, axis="y", alpha=0.3)
    ax.set_title(title, fontsize=10)
    save_figure(fig, path)
    plt.close(fig)
