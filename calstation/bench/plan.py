"""``calstation plan``: what a station design can reach, before any hardware exists.

The recipe's simulation section describes the station to be built (the lidar's pose, range
noise, line rate and points per line; the turntable; the fixtures). :func:`plan` simulates it
— a static scan, a spin scan of a few turns and a cube scan, for a few seeds — and fine-tunes
exactly as the station would, on the first turn and on all of them. It reports per parameter
the σ the strategy states, the predicted reconstruction error over the recipe's work volume
(with the cube's faces added to ry, for a spin-target strategy), how it falls with the turns,
and the turns the budget needs: the random part of the error falls as 1/√turns, which the
measured 1 → N turns checks. It also tries the spin target's placement and height where they
matter (centred against 60 mm off-centre, and 1.5 times taller), a QA cube three times larger
where the lidar's range offset is measured on it, and recommends.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, TypedDict, TypeVar

from calstation.bench import BenchError
from calstation.errors import CalstationError
from calstation.jsonvalue import JSONObject

if TYPE_CHECKING:
    from calstation.engine.result import CalibrationResult
    from calstation.pipeline import Calibrated
    from calstation.recipes import LoadedRecipe, Recipe
    from calstation.recordings.recorded import Recording

PARAMS = ("tx", "tz", "ry", "rz")
OFF_CENTRE_M = 0.06
"""Where the spin target stands off the axis in the placement the plan tries."""
TALLER = 1.5
"""How much taller the spin target the plan tries is."""
LARGER_CUBE = 3.0
"""How much larger the QA cube the plan tries is, with the lidar's range model (centred)."""

CERTIFICATE_M = 5e-5
"""The σ of the lidar's range offset certificate the plan tries (m): a range bench's."""

Progress = Callable[[str, float], None]
_T = TypeVar("_T")


class RangeTerms(TypedDict):
    """The σ of the range terms a fit estimated (SI), and why they were not measured."""

    range_sigma: dict[str, float]
    range_problem: str | None
    axis_sigma_m: float
    """the σ of where the axis lies, across it (:func:`calstation.engine.accuracy.
    axis_offset_sigma`; NaN without a range model, whose ty is the gauge)"""
    certified_m: float
    """the predicted error with a certificate of the lidar's range offset of σ
    :data:`CERTIFICATE_M` combined (NaN: the recipe has one, or the offset was not measured)"""
    certified_axis_sigma_m: float
    """the axis's σ with that certificate (NaN likewise)"""


class Fit(TypedDict):
    """One fine-tuning of a simulated run on its first ``turns`` turns (:func:`_fit`)."""

    turns: int
    sigma: dict[str, float]
    predicted_error_m: float
    with_cube_m: float
    range_sigma: dict[str, float]
    range_problem: str | None
    axis_sigma_m: float
    certified_m: float
    certified_axis_sigma_m: float
    seconds: float


class ByTurns(TypedDict):
    """A design's fits on one number of turns, the median over the seeds."""

    turns: int
    sigma: dict[str, float]
    predicted_error_m: float
    with_cube_m: float
    range_sigma: dict[str, float]
    range_problem: str | None
    axis_sigma_m: float
    certified_m: float
    certified_axis_sigma_m: float


class Design(TypedDict):
    """One design of the plan: its fits by turns, the turns the budget needs, or its error."""

    name: str
    change: str
    by_turns: list[ByTurns]
    turns_needed: int | None
    error: str | None


class WorkVolume(TypedDict):
    radius_m: float
    height_m: float


class Plan(TypedDict):
    """The plan as plain data (:func:`plan`)."""

    recipe: str
    budget_m: float
    axis_sigma_limit_m: float | None
    work_volume: WorkVolume
    level: float
    strategy: str
    seeds: int
    turns_simulated: int
    designs: list[Design]
    recommendations: list[str]
    seconds: float


Made = tuple["Recipe", dict[str, Path]]
"""A simulated run: the recipe as simulated and its recordings by name."""


@dataclass
class Trial:
    """One simulated design: what the fine-tuning gave after each number of turns."""

    name: str
    change: str
    turns: list[Fit] = field(default_factory=list)
    """per number of turns: ``turns``, ``sigma`` (m, rad), ``predicted_error_m``,
    ``with_cube_m`` (the predicted error with the cube's faces added to ry and the lidar's
    range model), ``range_sigma`` (the σ of each range term estimated, SI), ``range_problem``
    (why the range model was not measured, or None), ``seconds``"""
    error: str | None = None
    """why the design could not be simulated (an alternative the geometry does not allow)"""


def plan(
    loaded: LoadedRecipe,
    *,
    seeds: int = 1,
    turns: int = 2,
    alternatives: bool = True,
    progress: Progress | None = None,
    out_dir: Path | None = None,
    cache: Path | None = None,
) -> Plan:
    """Simulate the recipe ``loaded`` (:class:`~calstation.recipes.LoadedRecipe`, with a
    ``simulation`` section) and return the plan as plain data (see the module docstring).

    ``progress(message, fraction)`` is called as each simulation and each fine-tuning starts
    and when the plan is done (fraction 0 … 1 of the work, by its expected time). ``cache``: a
    folder that keeps the simulated runs by the hash of the recipe as simulated
    (:func:`simulated`; :func:`cache_folder` is the command's), so that a plan of the same
    station again, or with another budget or strategy option, fits without simulating."""
    recipe = loaded.recipe
    if recipe.simulation is None:
        raise BenchError(
            f"recipe {recipe.name!r} has no simulation section: calstation plan simulates the "
            "station it describes (the lidar's pose, range noise, line rate, the fixtures); add "
            "one (recipes/sim-periodicity.yaml is an example) or use --set simulation.…"
        )
    if turns < 1 or seeds < 1:
        raise BenchError("--turns and --seeds must be at least 1")
    say = progress or (lambda message, fraction: None)
    with tempfile.TemporaryDirectory(prefix="calstation-plan-") as scratch:
        work = Path(out_dir or scratch)
        return _plan(loaded, seeds, turns, alternatives, say, work, cache)


PLAN_WORKERS = 2
"""Processes the plan simulates and fine-tunes in at once (a station computer's two cores)."""


@dataclass(frozen=True)
class _Run:
    """One simulated run of the plan: a design and a seed."""

    name: str
    change: str
    patch: JSONObject
    seed: int
    turns: int
    scans: tuple[str, ...] = ()
    """the scans an alternative changes, simulated for it (the others are the design's)"""


def _plan(
    loaded: LoadedRecipe, seeds: int, turns: int, alternatives: bool, say: Progress, work: Path,
    cache: Path | None,
) -> Plan:
    """:func:`plan` with its folder for the simulated recordings: every run simulated, then
    every fit, each on :data:`PLAN_WORKERS` processes."""
    recipe = loaded.recipe
    designs: list[Alternative] = [("as designed", "the recipe", {}, ())]
    if alternatives:
        designs += _alternatives(recipe)
    t0 = time.perf_counter()
    runs = [_Run(name, change, patch, seed, turns if not patch else 1, scans)
            for name, change, patch, scans in designs
            for seed in range(1, (seeds if not patch else 1) + 1)]
    trials = {r.name: Trial(r.name, r.change) for r in runs}
    # the work in turns of scan: each run's simulation (an alternative's spin scan alone), then
    # each fine-tuning on 1 … turns turns with the cube
    work_share = _Shares(say, sum(r.turns + (2 if not r.patch else 0) for r in runs)
                         + sum(n + 1 for r in runs for n in range(1, r.turns + 1)))
    made: dict[int, Made] = {}
    try:
        with _pool() as pool:
            made = _simulate_all(pool, loaded, runs, work, cache, trials, work_share)
            _fit_all(pool, runs, made, trials, work_share)
    finally:
        if cache is None:
            for _, files in made.values():
                for path in files.values():
                    path.unlink(missing_ok=True)
    say("done", 1.0)
    return _summary(recipe, trials, turns, seeds, time.perf_counter() - t0)


class _Shares:
    """Progress by the share of the plan's work done: ``say(message, done ÷ total)``."""

    def __init__(self, say: Progress, total: float) -> None:
        self.say, self.total, self.done = say, total, 0.0

    def __call__(self, message: str, work: float = 0.0) -> None:
        self.done += work
        self.say(message, min(1.0, self.done / self.total))


def _pool() -> ProcessPoolExecutor:
    """The plan's worker processes (spawned: the plan may run on a web server's thread)."""
    import multiprocessing

    return ProcessPoolExecutor(max_workers=max(1, min(PLAN_WORKERS, os.cpu_count() or 1)),
                               mp_context=multiprocessing.get_context("spawn"))


def _simulate_all(
    pool: ProcessPoolExecutor, loaded: LoadedRecipe, runs: list[_Run], work: Path,
    cache: Path | None, trials: dict[str, Trial], share: _Shares,
) -> dict[int, Made]:
    """Every run simulated (or taken from ``cache``) at once: {run's index: (the recipe as
    simulated, its recordings)}. An alternative changes one fixture (:func:`_alternatives`):
    the scan of it is simulated and the other scans are the design's (seed 1), which show the
    same station with the same truth — else the whole run is simulated. An alternative the
    recipe's geometry does not allow gets its error."""
    share("simulating the scans")
    futures = {pool.submit(_simulate_job, loaded, r.patch, r.seed, r.turns, work / f"{k}",
                           cache, r.scans if r.patch else None): k
               for k, r in enumerate(runs)}
    made: dict[int, Made] = {}
    for future in _as_completed(futures):
        k = futures[future]
        run = runs[k]
        try:
            made[k] = future.result()
        except CalstationError as exc:
            if not run.patch:
                raise
            trials[run.name].error = str(exc)  # an alternative the geometry does not allow
        share(f"simulated {run.name}, seed {run.seed}",
              run.turns + (2 if not run.patch else 0))
    designed = made[0][1]
    for k, run in enumerate(runs):
        if not run.patch or k not in made:
            continue
        recipe, own = made[k]
        if _truth(designed) != _truth(own):
            made[k] = _simulate_job(loaded, run.patch, run.seed, run.turns, work / f"{k}",
                                    cache, None)
        else:
            shared: dict[str, Path] = {name: designed[name] for name in ("static", "spin", "cube")
                                       if name in designed and name not in run.scans}
            made[k] = (recipe, {**shared, **{name: own[name] for name in run.scans},
                                "truth": own["truth"]})
    return made


def _fit_all(
    pool: ProcessPoolExecutor, runs: list[_Run], made: dict[int, Made],
    trials: dict[str, Trial], share: _Shares,
) -> None:
    """Every run's fine-tunings on 1 … its turns at once, into ``trials`` (an alternative's
    failure is its error; the design's is raised)."""
    share("fine-tuning")
    futures = {pool.submit(_fit_job, made[k][0], made[k][1], n): (k, n)
               for k in made for n in range(1, runs[k].turns + 1)}
    found: dict[tuple[int, int], Fit] = {}
    for future in _as_completed(futures):
        k, n = futures[future]
        run = runs[k]
        try:
            found[k, n] = future.result()
        except CalstationError as exc:
            if not run.patch:
                raise
            trials[run.name].error = str(exc)
        share(f"fine-tuned {run.name}, seed {run.seed}, on {n} turn{'s' if n > 1 else ''}",
              n + 1)
    for (k, _), row in sorted(found.items()):
        trials[runs[k].name].turns.append(row)


def _as_completed(futures: Iterable[Future[_T]]) -> Iterator[Future[_T]]:
    from concurrent.futures import as_completed

    return as_completed(futures)


def _truth(files: dict[str, Path]) -> list[object]:
    """The true H of a simulated run (its ``truth.json``)."""
    truth = json.loads(files["truth"].read_text())
    return [truth.get(k) for k in PARAMETERS]


def _simulate_job(
    loaded: LoadedRecipe, patch: Mapping[str, object], seed: int, turns: int, out: Path,
    cache: Path | None, only: tuple[str, ...] | None,
) -> Made:
    """In a worker: the (patched) recipe as simulated and its run's recordings (``only``: the
    scans to simulate)."""
    recipe = _patched(loaded, patch, seed, turns)
    return recipe, simulated(recipe, out, cache, only=only)


def _fit_job(recipe: Recipe, files: dict[str, Path], turns: int) -> Fit:
    """In a worker: :func:`_fit` on the recordings ``files``."""
    from calstation.recordings.reader import read_recording

    return _fit(recipe, {k: read_recording(v) for k, v in files.items() if k != "truth"},
                turns)


Alternative = tuple[str, str, JSONObject, tuple[str, ...]]
"""A design the plan tries: its name, the change in words, the recipe's patch and the scans
the change is seen in (simulated for it; the others are the design's)."""


def _alternatives(recipe: Recipe) -> list[Alternative]:
    """The spin target's placement and height, tried where the strategy scans it, and, where the
    lidar's range offset is measured on the QA cube, a larger cube (:func:`_larger_cube`)."""
    from calstation import plugins

    out: list[Alternative] = []
    if plugins.strategy(recipe.calibration.strategy).fixture == "spin_target":
        out += _spin_target_alternatives(recipe)
    if recipe.calibration.range_model != "none":
        out += _larger_cube(recipe)
    return out


def _spin_target_alternatives(recipe: Recipe) -> list[Alternative]:
    """The spin target centred (or off-centre) and 1.5 times taller."""
    target = recipe.fixtures.spin_target
    offset = tuple(getattr(target, "offset", (0.0, 0.0)))
    out: list[Alternative] = []
    if math.hypot(*offset) < 0.03:
        out.append(("off-centre", f"spin target {OFF_CENTRE_M * 1e3:.0f} mm off the axis",
                    {"fixtures": {"spin_target": {"offset": [OFF_CENTRE_M, 0.0]}}}, ("spin",)))
    else:
        out.append(("centred", "spin target on the axis",
                    {"fixtures": {"spin_target": {"offset": [0.0, 0.0]}}}, ("spin",)))
    height = getattr(target, "height", None)
    if height is not None:
        out.append(("taller", f"spin target {TALLER:g} × taller ({height * TALLER * 1e3:.0f} mm)",
                    {"fixtures": {"spin_target": {"height": height * TALLER}}}, ("spin",)))
    return out


def _larger_cube(recipe: Recipe) -> list[Alternative]:
    """A QA cube :data:`LARGER_CUBE` times the recipe's edge, centred on the platter, where it
    fits (its footprint's diagonal within the platter): the range offset is told from where the
    lidar stands only by how the rays' directions spread over the cube (docs/algorithms.md,
    *The lidar's certificate*), so a wider cube measures it, and the axis with it, better."""
    edge = recipe.fixtures.qa_cube.edge * LARGER_CUBE
    if edge * math.sqrt(2.0) > 2.0 * recipe.fixtures.platter.radius - 0.02:
        return []
    return [("larger cube", f"a QA cube of {edge * 1e3:.0f} mm, centred",
             {"fixtures": {"qa_cube": {"edge": edge, "offset": [0.0, 0.0]}}}, ("cube",))]


def _patched(loaded: LoadedRecipe, patch: Mapping[str, object], seed: int = 1,
             turns: int = 1) -> Recipe:
    """The recipe as the plan simulates it: ``patch`` applied, ``turns`` turns of the
    strategy's own scan (the cube's for shape) and one of the other, no second passes, the
    simulation's ``seed``."""
    from calstation import plugins
    from calstation.bench.records import scan_of
    from calstation.bench.worker import apply_overrides

    long = {"revolutions": turns + 0.05, "max_revolutions": turns + 0.05,
            "second_pass_rpm": None}
    one = {**long, "revolutions": 1.05, "max_revolutions": 1.05}
    on_cube = scan_of(plugins.strategy(loaded.recipe.calibration.strategy)) == "cube"
    return apply_overrides(loaded.recipe, {
        **patch, "steps": {"spin_scan": one if on_cube else long,
                           "cube_scan": long if on_cube else one},
        "simulation": {"seed": seed},
    })


PARAMETERS = ("tx", "ty", "tz", "rx", "ry", "rz")
"""The true H's parameters in a simulated run's ``truth.json``."""


CACHE_ENTRIES = 8
"""Simulated runs the plan's cache keeps, the most recently used (one of two turns at 1000
lines/s is ~90 MB)."""


def simulated(
    recipe: Recipe, out: Path, cache: Path | None, only: tuple[str, ...] | None = None
) -> dict[str, Path]:
    """The recordings of one simulated run of ``recipe`` (``{"static", "spin", "cube",
    "truth"}`` → paths): from ``cache`` (a folder per simulated run, named by the hash of the
    recipe as simulated and of the simulator's version and source), else simulated into ``out``
    or, with a cache, into the cache (a folder of its own, renamed into place when complete, so
    that an interrupted plan leaves no half run to be read). ``only``: the scans to simulate
    (:class:`calstation.plugins.simulation.Simulator`'s)."""
    import yaml

    from calstation import plugins
    from calstation.recipes import LoadedRecipe

    simulator = plugins.simulator()
    text = yaml.safe_dump(recipe.model_dump(mode="json"), sort_keys=False)
    loaded = LoadedRecipe(recipe, None, text)
    if cache is None:
        return {k: Path(v) for k, v in simulator.simulate_run(loaded, out, progress=False,
                                                              only=only).items()}
    folder = cache / _cache_key(text + f"\nonly: {only}", simulator)
    index = folder / "files.json"
    if index.is_file():
        try:
            files = {k: folder / v for k, v in json.loads(index.read_text()).items()}
        except (OSError, ValueError, AttributeError):
            files = {}
        if files and all(p.is_file() for p in files.values()):
            os.utime(index)  # most recently used
            return files
    cache.mkdir(parents=True, exist_ok=True)
    partial = Path(tempfile.mkdtemp(prefix=".partial-", dir=cache))
    try:
        made = simulator.simulate_run(loaded, partial, progress=False, only=only)
        (partial / "files.json").write_text(json.dumps({k: Path(v).name
                                                        for k, v in made.items()}))
        shutil.rmtree(folder, ignore_errors=True)
        partial.rename(folder)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    _prune(cache)
    return {k: folder / Path(v).name for k, v in made.items()}


def _cache_key(text: str, simulator: object) -> str:
    """The cache's name for a simulated run of the recipe ``text``: its hash with calstation's
    version and the source files of ``simulator``'s package (their names, sizes and times), so
    that a changed simulator simulates again."""
    from calstation import __version__

    digest = hashlib.sha256(text.encode())
    digest.update(f"calstation {__version__}".encode())
    module = sys.modules[type(simulator).__module__]
    for path in sorted(Path(str(module.__file__)).parent.glob("*.py")):
        stat = path.stat()
        digest.update(f"{path.name} {stat.st_size} {stat.st_mtime_ns}".encode())
    return digest.hexdigest()[:32]


def _prune(cache: Path) -> None:
    """Keep the :data:`CACHE_ENTRIES` most recently used simulated runs in ``cache``."""
    entries = sorted((p for p in cache.iterdir() if (p / "files.json").is_file()),
                     key=lambda p: (p / "files.json").stat().st_mtime, reverse=True)
    for old in entries[CACHE_ENTRIES:]:
        shutil.rmtree(old, ignore_errors=True)
    day_ago = time.time() - 86_400
    for left in cache.glob(".partial-*"):  # a plan killed while it simulated
        if left.stat().st_mtime < day_ago:
            shutil.rmtree(left, ignore_errors=True)


def cache_folder() -> Path:
    """Where the plan keeps its simulated runs: ``$CALSTATION_HOME/plan-cache``."""
    from calstation.storage.db.database import calstation_home

    return calstation_home() / "plan-cache"


def _fit(recipe: Recipe, recordings: dict[str, Recording], turns: int) -> Fit:
    """The station's calibration (:func:`calstation.pipeline.calibrate`) on the first
    ``turns`` turns of the strategy's scan (``recordings``: the simulated run's, read once for
    all its fits): σ and the predicted error of the fine-tuning, and (for a spin-target
    strategy) the predicted error once the cube's faces join ry."""
    from calstation import plugins
    from calstation.bench.records import scan_of
    from calstation.pipeline import Scans, calibrate, turned
    from calstation.pipeline.judgement import with_prediction

    t0 = time.perf_counter()
    strategy = plugins.strategy(recipe.calibration.strategy)
    static = (None if recipe.calibration.start == "platter" or "static" not in recordings
              else recordings["static"])
    scan = recordings[scan_of(strategy)].first_turns(turns)
    on_target = strategy.fixture == "spin_target"
    done = calibrate(recipe, Scans(
        spin=turned(scan), static=static,
        cube=turned(recordings["cube"]) if on_target else None), strategy)
    result = done.fine_tuned
    predicted = with_prediction(result, recipe, turns=turns)[1]
    with_cube = with_prediction(done.result, recipe)[1].max_m if on_target else predicted.max_m
    return {"turns": turns, "sigma": {p: result.sigma.get(p, math.nan) for p in PARAMS},
            "predicted_error_m": predicted.max_m, "with_cube_m": with_cube,
            **_range_terms(recipe, done), "seconds": time.perf_counter() - t0}


def _range_terms(recipe: Recipe, done: Calibrated) -> RangeTerms:
    """The σ of the lidar's range terms the calibration estimated (``range_sigma``, SI; empty
    without a range model), and why they were not measured (``range_problem``, or None)."""
    from calstation.engine.accuracy import axis_offset_sigma
    from calstation.engine.rangemodel import RANGE_NAMES
    from calstation.pipeline.judgement import range_model_unset

    if recipe.calibration.range_model == "none":
        return {"range_sigma": {}, "range_problem": None, "axis_sigma_m": math.nan,
                "certified_m": math.nan, "certified_axis_sigma_m": math.nan}
    fields = done.result.range_fields()
    sigma = {n: _or_nan(fields.get(f"sigma_{n}")) for n in RANGE_NAMES
             if fields.get(n) is not None}
    # not measured: held at the start (no cube scan, or the cube's fit could not be combined,
    # whose reason the cube stage gives)
    unset = range_model_unset(done.result)
    problem = (done.ry_failure or unset) if unset else None
    axis = axis_offset_sigma(done.result.H, done.result.diagnostics.get("covariance"))
    certified, certified_axis = _certified(recipe, done.result)
    return {"range_sigma": sigma, "range_problem": problem, "axis_sigma_m": axis,
            "certified_m": certified, "certified_axis_sigma_m": certified_axis}


def _certified(recipe: Recipe, result: CalibrationResult) -> tuple[float, float]:
    """The predicted error and the axis's σ of ``result`` with a certificate of the lidar's
    range offset of σ :data:`CERTIFICATE_M` combined (:mod:`calstation.engine.certificate`; its
    value the measured one, so only the σ narrow); NaN when the recipe states one already or the
    offset was not measured."""
    from calstation.engine.accuracy import axis_offset_sigma
    from calstation.engine.certificate import Certificate, with_certificate
    from calstation.pipeline.judgement import with_prediction

    none = (math.nan, math.nan)
    if recipe.calibration.range_offset_certificate is not None or result.range_offset is None:
        return none
    certified, _ = with_certificate(result, Certificate(result.range_offset, CERTIFICATE_M))
    if "certificate" not in certified.diagnostics:
        return none
    return (with_prediction(certified, recipe)[1].max_m,
            axis_offset_sigma(certified.H, certified.diagnostics.get("covariance")))


def _or_nan(value: float | None) -> float:
    return math.nan if value is None else float(value)


def _summary(
    recipe: Recipe, trials: dict[str, Trial], turns: int, seeds: int, seconds: float
) -> Plan:
    """The plan as plain data, with the turns the budget needs and what to change."""
    budget = recipe.calibration.accuracy.max_error
    designs: list[Design] = []
    for trial in trials.values():
        rows: list[ByTurns] = []
        for k in sorted({r["turns"] for r in trial.turns}):
            at = [r for r in trial.turns if r["turns"] == k]
            rows.append({
                "turns": k,
                "sigma": {p: _median([r["sigma"][p] for r in at]) for p in PARAMS},
                "predicted_error_m": _median([r["predicted_error_m"] for r in at]),
                "with_cube_m": _median([r["with_cube_m"] for r in at]),
                "range_sigma": {n: _median([r["range_sigma"].get(n, math.nan) for r in at])
                                for n in at[0]["range_sigma"]},
                "range_problem": next((r["range_problem"] for r in at if r["range_problem"]),
                                      None),
                "axis_sigma_m": _median([r["axis_sigma_m"] for r in at]),
                "certified_m": _median([r["certified_m"] for r in at]),
                "certified_axis_sigma_m": _median([r["certified_axis_sigma_m"] for r in at]),
            })
        designs.append({"name": trial.name, "change": trial.change, "by_turns": rows,
                        "turns_needed": _turns_needed(rows, budget) if rows else None,
                        "error": trial.error})
    return {
        "recipe": recipe.name,
        "budget_m": budget,
        "axis_sigma_limit_m": recipe.calibration.accuracy.axis_sigma,
        "work_volume": {"radius_m": recipe.calibration.accuracy.work_radius(
            recipe.fixtures.platter), "height_m": recipe.calibration.accuracy.height},
        "level": recipe.calibration.accuracy.level,
        "strategy": recipe.calibration.strategy,
        "seeds": seeds,
        "turns_simulated": turns,
        "designs": designs,
        "recommendations": _recommend(designs, budget),
        "seconds": seconds,
    }


def _median(values: list[float]) -> float:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return statistics.median(finite) if finite else math.nan


def _turns_needed(rows: list[ByTurns], budget: float) -> int | None:
    """The turns that bring the predicted error (with the cube) within ``budget``: the first
    simulated number of turns that does, else the last one's error extrapolated as 1/√turns."""
    for row in rows:
        if row["with_cube_m"] <= budget:
            return int(row["turns"])
    last = rows[-1]
    if not math.isfinite(last["with_cube_m"]):
        return None
    needed: int = math.ceil(float(last["turns"]) * (float(last["with_cube_m"]) / budget) ** 2)
    return needed


def _recommend(designs: list[Design], budget: float) -> list[str]:
    """What the designer should do, from the trials: the recipe as it is, or a change that
    brings the budget within fewer turns."""
    base = designs[0]
    out = []
    need = base["turns_needed"]
    first = base["by_turns"][0]
    if need is not None and need <= 1:
        out.append(f"as designed, one turn meets the budget of {budget * 1e3:.3f} mm "
                   f"(predicted {first['with_cube_m'] * 1e3:.3f} mm)")
    elif need is not None:
        out.append(f"as designed, about {need} turns meet the budget of {budget * 1e3:.3f} mm: "
                   f"set steps.spin_scan.max_revolutions to at least {need}")
    certified, axis = first["certified_axis_sigma_m"], first["axis_sigma_m"]
    if math.isfinite(certified) and certified < 0.8 * axis:
        out.append(f"the lidar's range offset from a certificate of ±{CERTIFICATE_M * 1e3:.2f} "
                   "mm (calibration.range_offset_certificate): the axis placed to σ "
                   f"{certified * 1e3:.3f} mm instead of {axis * 1e3:.3f} mm after one turn, "
                   f"predicted {first['certified_m'] * 1e3:.3f} mm instead of "
                   f"{first['with_cube_m'] * 1e3:.3f} mm (the cube measures the offset only as "
                   "far as its size tells it from where the lidar stands)")
    for alt in designs[1:]:
        if not alt["by_turns"]:
            continue
        row = alt["by_turns"][0]
        e = row["with_cube_m"]
        if math.isfinite(e) and e < 0.8 * first["with_cube_m"]:
            out.append(f"{alt['change']}: predicted {e * 1e3:.3f} mm after one turn instead of "
                       f"{first['with_cube_m'] * 1e3:.3f} mm")
        elif math.isfinite(row["axis_sigma_m"]) and row["axis_sigma_m"] < 0.8 * axis:
            b, b_first = (r["range_sigma"].get("range_offset", math.nan) for r in (row, first))
            out.append(f"{alt['change']}: the axis placed to σ {row['axis_sigma_m'] * 1e3:.3f} "
                       f"mm instead of {axis * 1e3:.3f} mm after one turn (the lidar's range "
                       f"offset to ±{b * 1e3:.3f} mm instead of ±{b_first * 1e3:.3f} mm), "
                       f"predicted {e * 1e3:.3f} mm instead of {first['with_cube_m'] * 1e3:.3f} mm")
    return out
