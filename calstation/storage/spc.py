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

import math
import statistics
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

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
    ranges = [abs(b - a) for a, b in zip(base, base[1:], strict=False)]
    sigma = statistics.fmean(ranges) / D2 if ranges else 0.0
    return ControlLimits(centre=centre, sigma=sigma, baseline=k)


def western_electric(values: Sequence[float], limits: ControlLimits) -> list[list[int]]:
    """For each value, the Western Electric rules (1–4) it is flagged by (empty: in control).

    A rule over a window flags the point that completes it. With σ = 0 (a constant
    baseline) only a value off the centre line breaks rule 1."""
    c, s = limits.centre, limits.sigma
    flags: list[list[int]] = [[] for _ in values]
    z = [((v - c) / s if s > 0 else (0.0 if v == c else math.copysign(math.inf, v - c)))
         if math.isfinite(v) else 0.0 for v in values]
    for i, zi in enumerate(z):
        if abs(zi) > 3.0:
            flags[i].append(1)
        if s <= 0:
            continue
        for rule, window, need, level in ((2, 3, 2, 2.0), (3, 5, 4, 1.0)):
            if i + 1 < window or abs(zi) <= level:
                continue
            side = math.copysign(1.0, zi)
            recent = z[i + 1 - window:i + 1]
            if sum(1 for x in recent if x * side > level) >= need:
                flags[i].append(rule)
        if i >= 7 and zi != 0:
            side = math.copysign(1.0, zi)
            if all(x * side > 0 for x in z[i - 7:i + 1]):
                flags[i].append(4)
    return flags


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
        if status in ("passed", "failed", "aborted"):
            self.finished += 1
        if status == "passed":
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
