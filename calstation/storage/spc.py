"""Statistical process control for the QA dashboard: pure functions over plain numbers.

Control limits of an individuals chart, the Western Electric rules, yields, the failure Pareto
and the median cycle time. No database and no web here: :mod:`.dashboard` feeds these from
the stored runs, and the tests feed them by hand.

Conventions (Montgomery, *Introduction to Statistical Quality Control*, §6.4 and §5.3.6):

- the centre line is the mean of the station's baseline points (its first
  :data:`BASELINE_MIN` or quarter of its history, whichever is larger), and σ is estimated from
  their average moving range, ``σ = MR̄ / d2`` with ``d2 = 1.128`` (robust to a slow drift, unlike
  the standard deviation of all points);
- the Western Electric rules flag a point when
  1. it lies beyond 3σ from the centre line;
  2. it is the second of 2 of 3 successive points beyond 2σ on the same side;
  3. it is the fourth of 4 of 5 successive points beyond 1σ on the same side;
  4. it is the eighth of 8 successive points on the same side of the centre line.
"""

from __future__ import annotations

import itertools
import math
import statistics
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from calstation.storage.db.models import RunStatus

D2 = 1.128
"""Moving range of two points: E[|x_i − x_{i−1}|] = d2·σ for normal data."""

BASELINE_MIN = 20
"""Fewest points of the baseline the control limits come from (fewer: all the points)."""

RULES = {
    1: "beyond 3σ",
    2: "2 of 3 beyond 2σ on one side",
    3: "4 of 5 beyond 1σ on one side",
    4: "8 in a row on one side",
}
"""The Western Electric rules by number, as the dashboard names them."""


@dataclass(frozen=True)
class ControlLimits:
    """Centre line and σ of an individuals chart; the ±3σ limits follow."""

    centre: float
    sigma: float
    baseline: int
    """How many points (the first ones) the centre and σ come from."""

    @property
    def upper(self) -> float:
        return self.centre + 3.0 * self.sigma

    @property
    def lower(self) -> float:
        return self.centre - 3.0 * self.sigma


def baseline_size(n: int) -> int:
    """How many of ``n`` points form the baseline: a quarter, at least :data:`BASELINE_MIN`
    (all of them when there are fewer)."""
    return min(n, max(BASELINE_MIN, n // 4))


def control_limits(values: Sequence[float], baseline: int | None = None) -> ControlLimits:
    """Centre line and σ from the first ``baseline`` values (default :func:`baseline_size`):
    their mean, and their average moving range over ``d2``. ValueError for no value; σ is 0
    for a single value or a constant series."""
    finite = [float(v) for v in values if math.isfinite(v)]
    if not finite:
        raise ValueError("control limits need at least one finite value")
    k = baseline_size(len(finite)) if baseline is None else max(1, min(baseline, len(finite)))
    base = finite[:k]
    centre = statistics.fmean(base)
    ranges = [abs(b - a) for a, b in itertools.pairwise(base)]
    sigma = statistics.fmean(ranges) / D2 if ranges else 0.0
    return ControlLimits(centre=centre, sigma=sigma, baseline=k)


def rule_hits(values: Sequence[float], limits: ControlLimits) -> dict[int, NDArray[np.bool_]]:
    """For each Western Electric rule (1–4), which values break it.

    A rule over a window flags the point that completes it (and is itself on the rule's side).
    With σ = 0 (a constant baseline) only a value off the centre line breaks rule 1; a value
    that is not finite breaks none."""
    v = np.asarray(values, dtype=np.float64)
    ok = np.isfinite(v)
    dev = np.where(ok, v - limits.centre, 0.0)
    none = np.zeros(v.size, dtype=bool)
    if limits.sigma <= 0:
        return {1: dev != 0, 2: none, 3: none.copy(), 4: none.copy()}
    z = dev / limits.sigma
    hits = {1: np.abs(z) > 3.0, 2: none, 3: none.copy(), 4: none.copy()}
    for side in (1.0, -1.0):
        zs = z * side
        for rule, window, need, level in ((2, 3, 2, 2.0), (3, 5, 4, 1.0), (4, 8, 8, 0.0)):
            beyond = (zs > level) & ok
            hits[rule] = hits[rule] | (beyond & (_window_sums(beyond, window) >= need))
    return {rule: h & ok for rule, h in hits.items()}


def western_electric(values: Sequence[float], limits: ControlLimits) -> list[list[int]]:
    """For each value, the Western Electric rules (1–4) it breaks (empty: in control); see
    :func:`rule_hits`."""
    hits = rule_hits(values, limits)
    flags: list[list[int]] = [[] for _ in range(len(values))]
    for rule in (1, 2, 3, 4):
        for i in np.flatnonzero(hits[rule]):
            flags[i].append(rule)
    return flags


def out_of_control(values: Sequence[float], limits: ControlLimits) -> int:
    """How many values break at least one Western Electric rule."""
    hits = rule_hits(values, limits)
    return int(np.count_nonzero(hits[1] | hits[2] | hits[3] | hits[4]))


def _window_sums(mask: NDArray[np.bool_], window: int) -> NDArray[np.int64]:
    """For each index, how many of the ``window`` values ending there are True (0 where the
    window is not complete)."""
    c = np.concatenate(([0], np.cumsum(mask.astype(np.int64))))
    out = np.zeros(mask.size, dtype=np.int64)
    if mask.size >= window:
        out[window - 1:] = c[window:] - c[:-window]
    return out


@dataclass
class Yield:
    """Runs of a group (a station's day or week) and how many passed, and at the first pass."""

    runs: int = 0
    finished: int = 0
    passed: int = 0
    first_pass: int = 0
    cycle_times: list[float] = field(default_factory=list)

    def add(self, status: str, first_pass: bool, cycle_s: float | None) -> None:
        """Count one run: ``status`` as stored; ``first_pass`` when it passed with no step
        repeated on a unit never run before; ``cycle_s`` its duration when it finished."""
        self.runs += 1
        if status in (RunStatus.PASSED, RunStatus.FAILED, RunStatus.ABORTED):
            self.finished += 1
        if status == RunStatus.PASSED:
            self.passed += 1
            if first_pass:
                self.first_pass += 1
        if cycle_s is not None and math.isfinite(cycle_s) and cycle_s >= 0:
            self.cycle_times.append(cycle_s)

    @property
    def yield_(self) -> float | None:
        """Passed over finished runs (None: none finished)."""
        return self.passed / self.finished if self.finished else None

    @property
    def first_pass_yield(self) -> float | None:
        """First-pass runs over finished runs (None: none finished)."""
        return self.first_pass / self.finished if self.finished else None

    @property
    def median_cycle_s(self) -> float | None:
        return statistics.median(self.cycle_times) if self.cycle_times else None

    def as_dict(self) -> dict[str, float | int | None]:
        return {"runs": self.runs, "finished": self.finished, "passed": self.passed,
                "first_pass": self.first_pass, "yield": self.yield_,
                "first_pass_yield": self.first_pass_yield,
                "median_cycle_s": self.median_cycle_s}


def pareto(reasons: Iterable[str]) -> list[tuple[str, int, float]]:
    """Failure reasons by count, most frequent first (ties by name), each with the cumulative
    share of all failures (0–1)."""
    counts: dict[str, int] = {}
    for r in reasons:
        counts[r] = counts.get(r, 0) + 1
    total = sum(counts.values())
    out: list[tuple[str, int, float]] = []
    running = 0
    for reason, n in sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])):
        running += n
        out.append((reason, n, running / total))
    return out
