"""The test suite's teeth, measured: apply each mutation below to a copy of the committed tree,
run the tests that should catch it, and print whether they did.

    .venv/bin/python scripts/mutation_check.py            # every mutation (about 10 min)
    .venv/bin/python scripts/mutation_check.py --only sigma

Each mutation is a defect the suite must not let through: a σ that no longer covers the error,
a bias in the estimate, a matching that returns the wrong pairs. A mutation the tests do not
catch is printed as MISSED, and the script exits 1. The copy is ``git archive HEAD``, so
uncommitted changes are not checked.
"""

from __future__ import annotations

import argparse
import io
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Mutation:
    name: str
    what: str
    path: str
    old: str
    new: str
    tests: tuple[str, ...]


MUTATIONS = (
    Mutation(
        "sigma",
        "periodicity σ of tx, tz and rz × 1e-3",
        "calstation/engine/periodicity/solve.py",
        "sigma = sigma_from_covariance(reported_cov, problem.free)",
        "sigma = {k: v * (1e-3 if k in ('tx', 'tz', 'rz') else 1.0)"
        " for k, v in sigma_from_covariance(reported_cov, problem.free).items()}",
        ("tests/test_trust.py", "tests/test_periodicity.py"),
    ),
    Mutation(
        "sigma-scale",
        "the periodicity σ factor 1.3 → 0.3",
        "calstation/engine/periodicity/covariance.py",
        "SIGMA_SCALE = 1.3",
        "SIGMA_SCALE = 0.3",
        ("tests/test_trust.py", "tests/test_periodicity.py"),
    ),
    Mutation(
        "tz-bias",
        "a 0.4 mm bias in the periodicity tz",
        "calstation/engine/periodicity/solve.py",
        "H=Extrinsics.from_vector(x6),",
        "H=Extrinsics.from_vector(x6 + [0, 0, 0.0004, 0, 0, 0]),",
        ("tests/test_trust.py", "tests/test_periodicity.py"),
    ),
    Mutation(
        "mutual-swapped",
        "mutual neighbours: the reverse query in the wrong tree",
        "calstation/engine/neighbours.py",
        "_, back = ta.query(b[cand], distance_upper_bound=radius, workers=WORKERS)",
        "_, back = tb.query(b[cand], distance_upper_bound=radius, workers=WORKERS)",
        ("tests/test_neighbours.py",),
    ),
    Mutation(
        "mutual-first",
        "mutual neighbours: only the first pair returned",
        "calstation/engine/neighbours.py",
        "return i[mutual].astype(np.int64), j[mutual].astype(np.int64)",
        "return i[mutual][:1].astype(np.int64), j[mutual][:1].astype(np.int64)",
        ("tests/test_neighbours.py",),
    ),
    Mutation(
        "twist-bias",
        "the cube's twist σ without its jackknife (the bias term alone)",
        "calstation/engine/twist.py",
        "return twist, float(math.hypot(spread, range_twist_bias(noise)))",
        "return twist, float(range_twist_bias(noise))",
        ("tests/test_trust.py", "tests/test_calibrate_cli.py"),
    ),
    Mutation(
        "twist-sign",
        "the cube's twist with its sign flipped",
        "calstation/engine/twist.py",
        "    twist = float(res.x[0])\n",
        "    twist = -float(res.x[0])\n",
        ("tests/test_trust.py",),
    ),
    Mutation(
        "cube-edge",
        "the known-size cube fit with a cube 0.4 mm smaller than the recipe's",
        "calstation/engine/cubefit.py",
        "half = 0.5 * (self.edge if edge is None else edge)",
        "half = 0.5 * ((self.edge if edge is None else edge) - 0.0004)",
        ("tests/test_cubefit.py", "tests/test_shape.py"),
    ),
    Mutation(
        "cube-tolerance",
        "the known-size cube fit's σ without the edge tolerance",
        "calstation/engine/cubefit.py",
        "    if tolerance > 0:\n",
        "    if False:\n",
        ("tests/test_cubefit.py",),
    ),
    Mutation(
        "reconstruct-latency",
        "reconstruct ignores the calibration's encoder latency",
        "calstation/engine/reconstruct.py",
        "        recording = recording.with_encoder_latency(encoder_latency_s)\n",
        "        pass\n",
        ("tests/test_reconstruct.py",),
    ),
    Mutation(
        "csv-sigma-swap",
        "the CSV export with the σ_ry and σ_rz columns swapped",
        "calstation/storage/report.py",
        'row += ["" if s is None else repr(s) for s in cal.sigmas().values()]',
        'row += ["" if s is None else repr(s) for s in (lambda v: [*v[:4], v[5], v[4]])('
        "list(cal.sigmas().values()))]",
        ("tests/test_cli_qa.py",),
    ),
    Mutation(
        "journal-fsync",
        "the journal's entries not flushed to the disk (its os.fsync deleted)",
        "calstation/storage/db/journal.py",
        "        os.fsync(f.fileno())\n",
        "",
        ("tests/test_faults_db.py::test_a_journalled_result_is_on_the_disk_before_the_run_goes_on",),
    ),
    Mutation(
        "half-turn-shift",
        "the periodicity's second half-turn with its platter angles 1 mrad off",
        "calstation/engine/periodicity/cells.py",
        "    halves = [half(first & moving), half(~first & moving)]\n",
        "    halves = [half(first & moving), half(~first & moving)]\n"
        "    halves[1].phi = halves[1].phi + 1e-3\n",
        ("tests/test_periodicity.py",),
    ),
    Mutation(
        "targetless-sign",
        "the targetless start tries +|tz| twice instead of ±|tz|",
        "calstation/engine/targetless.py",
        "candidates = [0.0, tz, -tz] if tz >= TZ_SIGN_MIN_M else [0.0]",
        "candidates = [0.0, tz, tz] if tz >= TZ_SIGN_MIN_M else [0.0]",
        ("tests/test_targetless.py",),
    ),
    Mutation(
        "static-lines-bound",
        "steps.static_scan.lines without its ge=1 bound",
        "calstation/recipes/steps.py",
        "lines: int = Field(100, ge=1, le=10_000)",
        "lines: int = Field(100, le=10_000)",
        ("tests/test_faults_recipes.py",),
    ),
    Mutation(
        "range-model-ignored",
        "the reconstruction reads the ranges as measured, the estimated range model ignored",
        "calstation/engine/reconstruct.py",
        "return lidar_points_to_dynamic(range_model.points(p_L), phi, H)",
        "return lidar_points_to_dynamic(p_L, phi, H)",
        ("tests/test_rangemodel.py",),
    ),
    Mutation(
        "range-sigma-dropped",
        "the range terms' σ left out of the predicted error",
        "calstation/engine/accuracy.py",
        "out[:, :, k] = -lidar_to_dynamic(along, phi, H.with_(tx=0.0, ty=0.0, tz=0.0))",
        "out[:, :, k] = 0.0",
        ("tests/test_rangemodel.py",),
    ),
)


def _tree(into: Path) -> None:
    """The committed tree (HEAD) unpacked into ``into``."""
    data = subprocess.run(["git", "archive", "HEAD"], cwd=REPO, check=True,
                          capture_output=True).stdout
    with tarfile.open(fileobj=io.BytesIO(data)) as tar:
        tar.extractall(into, filter="data")


def _apply(root: Path, m: Mutation) -> None:
    path = root / m.path
    text = path.read_text()
    if text.count(m.old) != 1:
        raise SystemExit(f"mutation {m.name}: {m.path} holds {text.count(m.old)} copies of "
                         f"{m.old!r}, not one: update the mutation with the code")
    path.write_text(text.replace(m.old, m.new))


def _run_tests(root: Path, tests: tuple[str, ...]) -> tuple[bool, float, str]:
    plugins = sorted(str(p.parent) for p in (root / "plugins").glob("*/pyproject.toml"))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), *plugins]),
           "OMP_NUM_THREADS": "1"}
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider",
                           *tests], cwd=root, env=env, capture_output=True, text=True)
    return proc.returncode == 0, time.perf_counter() - t0, proc.stdout[-4000:]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", action="append", help="run only these mutations (by name)")
    args = ap.parse_args()
    chosen = [m for m in MUTATIONS if not args.only or m.name in args.only]
    missed = 0
    with tempfile.TemporaryDirectory(prefix="calstation-mutation-") as tmp:
        clean = Path(tmp) / "clean"
        _tree(clean)
        passed, seconds, said = _run_tests(clean,
                                           tuple(sorted({t for m in chosen for t in m.tests})))
        print(f"unmutated tree: tests {'pass' if passed else 'FAIL'} ({seconds:.0f} s)")
        if not passed:
            print(said)
            print("the unmutated tree must pass first")
            return 1
        for m in chosen:
            root = Path(tmp) / m.name
            _tree(root)
            _apply(root, m)
            passed, seconds, _ = _run_tests(root, m.tests)
            missed += passed
            print(f"{'MISSED' if passed else 'caught'}  {m.name:15} {m.what} "
                  f"({', '.join(m.tests)}; {seconds:.0f} s)", flush=True)
    print(f"{len(chosen) - missed} of {len(chosen)} mutations caught")
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
