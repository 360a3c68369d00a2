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
    browser: bool = False
    """the tests drive chromium (run with ``-m browser``)"""


PAGES = "tests/web/test_page_defects.py"
VOCABULARY = "tests/system/test_one_vocabulary.py"
PROMPTS = "tests/cli/test_terminal_prompts.py"
LIVE_PAGE = "tests/web/test_live_page_browser.py"

MUTATIONS = (
    Mutation(
        "sigma",
        "periodicity σ of tx, tz and rz × 1e-3",
        "calstation/engine/periodicity/solve.py",
        "sigma = sigma_from_covariance(reported_cov, problem.free)",
        "sigma = {k: v * (1e-3 if k in ('tx', 'tz', 'rz') else 1.0)"
        " for k, v in sigma_from_covariance(reported_cov, problem.free).items()}",
        ("tests/engine/test_trust.py", "tests/engine/test_periodicity.py"),
    ),
    Mutation(
        "sigma-scale",
        "the periodicity σ factor 1.3 → 0.3",
        "calstation/engine/periodicity/covariance.py",
        "SIGMA_SCALE = 1.3",
        "SIGMA_SCALE = 0.3",
        ("tests/engine/test_trust.py", "tests/engine/test_periodicity.py"),
    ),
    Mutation(
        "tz-bias",
        "a 0.4 mm bias in the periodicity tz",
        "calstation/engine/periodicity/solve.py",
        "H=Extrinsics.from_vector(x6[:6]),",
        "H=Extrinsics.from_vector(x6[:6] + [0, 0, 0.0004, 0, 0, 0]),",
        ("tests/engine/test_trust.py", "tests/engine/test_periodicity.py"),
    ),
    Mutation(
        "mutual-swapped",
        "mutual neighbours: the reverse query in the wrong tree",
        "calstation/engine/neighbours.py",
        "_, back = ta.query(b[cand], distance_upper_bound=radius, workers=WORKERS)",
        "_, back = tb.query(b[cand], distance_upper_bound=radius, workers=WORKERS)",
        ("tests/engine/test_neighbours.py",),
    ),
    Mutation(
        "mutual-first",
        "mutual neighbours: only the first pair returned",
        "calstation/engine/neighbours.py",
        "return i[mutual].astype(np.int64), j[mutual].astype(np.int64)",
        "return i[mutual][:1].astype(np.int64), j[mutual][:1].astype(np.int64)",
        ("tests/engine/test_neighbours.py",),
    ),
    Mutation(
        "twist-bias",
        "the cube's twist σ without its jackknife (the bias term alone)",
        "calstation/engine/twist.py",
        "return twist, float(math.hypot(spread, range_twist_bias(noise)))",
        "return twist, float(range_twist_bias(noise))",
        ("tests/engine/test_trust.py", "tests/cli/test_calibrate_cli.py"),
    ),
    Mutation(
        "twist-sign",
        "the cube's twist with its sign flipped",
        "calstation/engine/twist.py",
        "    twist = float(res.x[0])\n",
        "    twist = -float(res.x[0])\n",
        ("tests/engine/test_trust.py",),
    ),
    Mutation(
        "cube-edge",
        "the known-size cube fit with a cube 0.4 mm smaller than the recipe's",
        "calstation/engine/cubefit.py",
        "half = 0.5 * (self.edge if edge is None else edge)",
        "half = 0.5 * ((self.edge if edge is None else edge) - 0.0004)",
        ("tests/engine/test_cubefit.py", "tests/engine/test_shape.py"),
    ),
    Mutation(
        "cube-tolerance",
        "the known-size cube fit's σ without the edge tolerance",
        "calstation/engine/cubefit.py",
        "    if tolerance <= 0:\n",
        "    if True:\n",
        ("tests/engine/test_cubefit.py",),
    ),
    Mutation(
        "reconstruct-latency",
        "reconstruct ignores the calibration's encoder latency",
        "calstation/engine/reconstruct.py",
        "        recording = recording.with_encoder_latency(encoder_latency_s)\n",
        "        pass\n",
        ("tests/recordings/test_reconstruct.py",),
    ),
    Mutation(
        "csv-sigma-swap",
        "the CSV export with the σ_ry and σ_rz columns swapped",
        "calstation/storage/report.py",
        'row += ["" if s is None else repr(s) for s in cal.sigmas().values()]',
        'row += ["" if s is None else repr(s) for s in (lambda v: [*v[:4], v[5], v[4]])('
        "list(cal.sigmas().values()))]",
        ("tests/cli/test_cli_qa.py",),
    ),
    Mutation(
        "journal-fsync",
        "the journal's entries not flushed to the disk (its os.fsync deleted)",
        "calstation/storage/db/journal.py",
        "        os.fsync(f.fileno())\n",
        "",
        ("tests/storage/test_faults_db.py::test_a_journalled_result_is_on_the_disk_before_the_run_goes_on",),
    ),
    Mutation(
        "half-turn-shift",
        "the periodicity's second half-turn with its platter angles 1 mrad off",
        "calstation/engine/periodicity/cells.py",
        "    halves = [half(first & moving), half(~first & moving)]\n",
        "    halves = [half(first & moving), half(~first & moving)]\n"
        "    halves[1].phi = halves[1].phi + 1e-3\n",
        ("tests/engine/test_periodicity.py",),
    ),
    Mutation(
        "targetless-sign",
        "the targetless start tries +|tz| twice instead of ±|tz|",
        "calstation/engine/targetless.py",
        "candidates = [0.0, tz, -tz] if tz >= TZ_SIGN_MIN_M else [0.0]",
        "candidates = [0.0, tz, tz] if tz >= TZ_SIGN_MIN_M else [0.0]",
        ("tests/engine/test_targetless.py",),
    ),
    Mutation(
        "static-lines-bound",
        "steps.static_scan.lines without its ge=1 bound",
        "calstation/recipes/steps.py",
        "lines: int = Field(100, ge=1, le=10_000)",
        "lines: int = Field(100, le=10_000)",
        ("tests/recipes/test_faults_recipes.py",),
    ),
    Mutation(
        "range-model-ignored",
        "the reconstruction reads the ranges as measured, the estimated range model ignored",
        "calstation/engine/reconstruct.py",
        "return lidar_points_to_dynamic(range_model.points(p_L), phi, H)",
        "return lidar_points_to_dynamic(p_L, phi, H)",
        ("tests/engine/test_rangemodel.py",),
    ),
    Mutation(
        "encoder-ignored",
        "the encoder's stated accuracy not carried through the spin target and cube's combination",
        "calstation/engine/fusion.py",
        "        return replace(self, consider=columns(directions, self.names, sigma))",
        "        return self",
        ("tests/engine/test_encoder.py",),
    ),
    Mutation(
        "encoder-harmonic-wrong",
        "the spin target's encoder response taken at the first half-turn's angles for both",
        "calstation/engine/periodicity/problem.py",
        "harmonics = basis(c, s)",
        "harmonics = basis(m.ca, m.sa)",
        ("tests/engine/test_encoder.py",),
    ),
    Mutation(
        "range-sigma-dropped",
        "the range terms' σ left out of the predicted error",
        "calstation/engine/accuracy.py",
        "out[:, :, k] = -lidar_to_dynamic(along, phi, H.with_(tx=0.0, ty=0.0, tz=0.0))",
        "out[:, :, k] = 0.0",
        ("tests/engine/test_rangemodel.py",),
    ),
    Mutation(
        "certificate-unweighed",
        "the lidar's range offset certificate combined as if exact, whatever its σ",
        "calstation/engine/certificate.py",
        "gain = C[:, i] / (C[i, i] + certificate.sigma**2)",
        "gain = C[:, i] / C[i, i]",
        ("tests/engine/test_certificate.py",),
    ),
    Mutation(
        "certificate-disagreement-ignored",
        "a certificate far from the station's measured range offset combined all the same",
        "calstation/engine/certificate.py",
        "if float(chdtrc(1, apart**2)) < CONSISTENCY_P:",
        "if False:",
        ("tests/engine/test_certificate.py",),
    ),
    # the operator's and the QA engineer's pages, the terminal's prompts
    Mutation(
        "prompt-any-answer",
        "the terminal's placement prompt takes an unlisted answer (x, exit) as continue",
        "calstation/cli/_operator.py",
        '            shown = f"“{escape(typed.strip()[:40])}”" if typed.strip() else '
        '"An empty line"\n',
        "            return go\n",
        (f"{PROMPTS}::test_a_placement_prompt_moves_nothing_until_continue",),
    ),
    Mutation(
        "prompt-eof-goes-on",
        "the end of the input at a placement prompt taken as continue",
        "calstation/cli/_operator.py",
        '            except EOFError:\n                return "abort"\n',
        "            except EOFError:\n                return go\n",
        (f"{PROMPTS}::test_end_of_input_at_a_prompt_aborts",),
    ),
    Mutation(
        "progress-clock-stops",
        "a step's progress bar completed by its first phase (its clock stops at 0:00:00)",
        "calstation/cli/_operator.py",
        "completed=max(0.0, min(UNFINISHED, float(fraction))),",
        "completed=max(0.0, min(1.0, float(fraction))),",
        (f"{PROMPTS}::test_a_steps_progress_bar_counts_its_time_through_all_its_phases",),
    ),
    Mutation(
        "trends-unit",
        "/trends.json labels its values (metres) with the unit shown (mm)",
        "calstation/storage/qa.py",
        'return {"station": station, "param": param, "unit": display.quantity(param).stored,',
        'return {"station": station, "param": param, "unit": display.quantity(param).unit,',
        (f"{VOCABULARY}::test_one_parameter_of_one_run_is_one_value_in_one_unit_everywhere",),
    ),
    Mutation(
        "compare-held",
        "/compare computes a difference for a parameter one run did not estimate",
        "calstation/storage/qa.py",
        "diff = None if va is None or vb is None or held_a or held_b else vb - va",
        "diff = None if va is None or vb is None else vb - va",
        (f"{VOCABULARY}::test_a_parameter_not_estimated_reads_so_everywhere_and_is_never_flagged",),
    ),
    Mutation(
        "compare-noise",
        "/compare flags a difference within the two runs' 3σ",
        "calstation/storage/qa.py",
        "and abs(diff) > max(limit, noise)})",
        "and abs(diff) > limit})",
        (f"{VOCABULARY}::test_a_parameter_not_estimated_reads_so_everywhere_and_is_never_flagged",),
    ),
    Mutation(
        "not-estimated",
        "a held parameter (no σ, zero) read as estimated: 0.0000 instead of not estimated",
        "calstation/display.py",
        "return no_sigma and (value is None or value == 0.0)",
        "return False",
        (f"{VOCABULARY}::test_a_parameter_not_estimated_reads_so_everywhere_and_is_never_flagged",
         f"{PAGES}::test_the_terminal_summary_says_1_turn_and_not_estimated"),
    ),
    Mutation(
        "duration-raw",
        "durations of a minute or more shown as raw seconds (130.72)",
        "calstation/display.py",
        'return f"{whole // 60} min {whole % 60:02d} s"',
        'return f"{s:.2f}"',
        (f"{VOCABULARY}::test_the_formatter",
         f"{PAGES}::test_the_run_page_names_steps_in_words_and_times_for_people"),
    ),
    Mutation(
        "count-plural",
        "counts always plural (1 turns)",
        "calstation/display.py",
        'word = noun if n == 1 else (plural or f"{noun}s")',
        'word = plural or f"{noun}s"',
        (f"{PAGES}::test_the_terminal_summary_says_1_turn_and_not_estimated",),
    ),
    Mutation(
        "placement-60mm",
        "the spin target's placement prompt says 60 mm whatever the recipe says",
        "calstation/station/operator.py",
        "where = (f\"its centre {display.number('distance', math.hypot(*offset))} from the axis \"",
        "where = (f\"its centre about 60 mm from the axis \"",
        (f"{VOCABULARY}::test_the_placement_prompts_say_what_the_recipe_and_its_drawing_say",),
    ),
    Mutation(
        "pareto-abort-red",
        "an operator's abort drawn as a failure in the Pareto",
        "calstation/storage/dashboard_figures.py",
        '"marker": {"color": [ABORTED if r["status"] == RunStatus.ABORTED else FLAG\n',
        '"marker": {"color": [FLAG  # every bar a failure\n',
        (f"{PAGES}::test_an_abort_is_not_a_failure_in_the_pareto_and_its_ticks_are_round",),
    ),
    Mutation(
        "chart-drift-scale",
        "a control chart scaled to the drift limit (its points collapse into one line)",
        "calstation/storage/dashboard_figures.py",
        "    window = (lo - pad, hi + pad)\n",
        '    window = (min(lo, (lim["centre"] - (lim["limit"] or 0.0)) * k) - pad,\n'
        '              max(hi, (lim["centre"] + (lim["limit"] or 0.0)) * k) + pad)\n',
        (f"{PAGES}::test_a_control_chart_is_scaled_to_its_points_not_to_the_drift_limit",),
    ),
    Mutation(
        "live-times",
        "the live header and steps keep their own clock at the run's end, not the database's",
        "calstation/web/live.py",
        "                _times_as_stored(st, result)\n",
        "                pass\n",
        (f"{PAGES}::test_the_live_header_steps_and_end_screen_agree_on_the_times",),
    ),
    Mutation(
        "log-raw-step",
        "the page log names a step by its key (place_qa_cube)",
        "calstation/web/live.py",
        "self.live.add_log(\"info\", f\"▶ {step_title(d['step'])}\"",
        "self.live.add_log(\"info\", f\"▶ {d['step']}\"",
        (f"{PAGES}::test_the_page_log_names_steps_in_words",),
    ),
    Mutation(
        "end-screen-no-limit",
        "the end screen writes ≤ — for a cube figure without a limit",
        "calstation/web/templates/result.html",
        "{% if c.limit is not none %}",
        "{% if true %}",
        (f"{PAGES}::test_the_end_screen_shows_no_limit_where_there_is_none_and_no_red_on_a_pass",),
    ),
    Mutation(
        "stream-no-tick",
        "the event stream reads the station locks only in a quiet moment (never during a scan)",
        "calstation/web/events.py",
        "                await hub.tick()\n                # coalesce bursts",
        "                # coalesce bursts",
        ("tests/web/test_live_stream.py",),
    ),
    Mutation(
        "status-stale-at-end",
        "the end screen shows the station still held by the run that just gave it back",
        "calstation/web/app.py",
        "    runner.released = status.refresh\n",
        "",
        ("tests/web/test_web_browser.py::test_a_full_simulated_run_by_clicking_with_a_reload",),
        browser=True,
    ),
    Mutation(
        "page-clock-cached",
        "the operator page counts its clocks from a cached state's time, not the server's now",
        "calstation/web/static/station.js",
        "skew = Number(ev.data) - Date.now() / 1000;",
        "skew = state.now - Date.now() / 1000;",
        (f"{LIVE_PAGE}::test_a_page_opened_long_after_the_state_last_changed_counts_from_the_"
         "servers_clock",),
        browser=True,
    ),
    Mutation(
        "start-while-held",
        "Start offered while another run holds the chosen recipe's station",
        "calstation/web/static/station.js",
        "button.disabled = !option || !!held;",
        "button.disabled = !option;",
        (f"{LIVE_PAGE}::test_every_page_shows_who_holds_the_station",),
        browser=True,
    ),
    Mutation(
        "hidden-page-draws",
        "the operator page draws its plots while it cannot be seen",
        "calstation/web/static/station.js",
        'function shown(el) { return !document.hidden && el.getAttribute("data-in-view") !== '
        '"no"; }',
        "function shown(el) { return true; }",
        (f"{LIVE_PAGE}::test_a_hidden_page_draws_nothing_and_catches_up_when_shown",),
        browser=True,
    ),
    Mutation(
        "range-fit-in-corrected-units",
        "the cube's range fit on corrected returns, whose noise shrinks as k grows",
        "calstation/engine/cubefit.py",
        "            out *= 1.0 + float(v[SCALE])\n",
        "",
        ("tests/engine/test_rangemodel.py",),
    ),
    Mutation(
        "unmeasured-scale-ignored",
        "the stated uncertainty of a scale error the recipe does not measure left out",
        "calstation/pipeline/judgement.py",
        "    result = with_scale_uncertainty(result, recipe)\n    predicted = predict(",
        "    predicted = predict(",
        ("tests/engine/test_rangemodel.py",),
    ),
    Mutation(
        "unmeasured-scale-uncorrelated",
        "the scale's correlation with the translation it moved dropped",
        "calstation/engine/rangemodel.py",
        "out[n, i] = out[i, n] = -s2 * float(t[axis])",
        "out[n, i] = out[i, n] = 0.0",
        ("tests/engine/test_rangemodel.py",),
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


def _run_tests(root: Path, tests: tuple[str, ...], browser: bool = False
               ) -> tuple[bool, float, str]:
    plugins = sorted(str(p.parent) for p in (root / "plugins").glob("*/pyproject.toml"))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), *plugins]),
           "OMP_NUM_THREADS": "1"}
    t0 = time.perf_counter()
    marker = ["-m", "browser"] if browser else []
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider",
                           *marker, *tests], cwd=root, env=env, capture_output=True, text=True)
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
        for browser in (False, True):
            tests = tuple(sorted({t for m in chosen if m.browser == browser for t in m.tests}))
            if not tests:
                continue
            passed, seconds, said = _run_tests(clean, tests, browser)
            print(f"unmutated tree: {'browser ' if browser else ''}tests "
                  f"{'pass' if passed else 'FAIL'} ({seconds:.0f} s)")
            if not passed:
                print(said)
                print("the unmutated tree must pass first")
                return 1
        for m in chosen:
            root = Path(tmp) / m.name
            _tree(root)
            _apply(root, m)
            passed, seconds, _ = _run_tests(root, m.tests, m.browser)
            missed += passed
            print(f"{'MISSED' if passed else 'caught'}  {m.name:15} {m.what} "
                  f"({', '.join(m.tests)}; {seconds:.0f} s)", flush=True)
    print(f"{len(chosen) - missed} of {len(chosen)} mutations caught")
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
