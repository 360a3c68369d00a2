"""Fault injection, recipes: malformed recipes are refused before anything moves.

Every case edits the shipped ``recipes/sim-periodicity.yaml`` one way and expects
``calstation recipes validate`` to refuse it with ``FILE:LINE: field: message`` — never a
traceback, never a hang. The last tests run recipes at the edges of the accepted ranges on the
simulated station (slow) to check the rule: what validate accepts runs to its end.
"""

from __future__ import annotations

import os
import re
import threading
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from pydantic import BaseModel, ConfigDict, Field

from calstation import hookimpl, plugins
from calstation.cli import main
from calstation.errors import RecipeError
from calstation.plugins.recipe_checks import check_plugins
from calstation.recipes import load_recipe, parse_recipe

REPO = Path(__file__).resolve().parents[2]
BASE = (REPO / "recipes" / "sim-periodicity.yaml").read_text(encoding="utf-8")


def replace(old: str, new: str) -> Callable[[str], str]:
    """An edit replacing the first ``old`` (which must be in the base recipe) by ``new``."""

    def edit(text: str) -> str:
        assert old in text, old
        return text.replace(old, new, 1)

    return edit


def add_under(anchor: str, lines: str) -> Callable[[str], str]:
    """An edit inserting ``lines`` right after the line ``anchor``."""
    return replace(anchor + "\n", anchor + "\n" + lines.rstrip("\n") + "\n")


def under_strategy(lines: str) -> Callable[[str], str]:
    return add_under("  strategy: periodicity", lines)


def append(lines: str) -> Callable[[str], str]:
    return lambda text: text + lines


FRUSTUM = "  spin_target:\n    kind: frustum\n"


def polygon(points: str) -> Callable[[str], str]:
    return replace(FRUSTUM, FRUSTUM + f"    polygon: {points}\n")


# (id, edit, field path expected, marker: text at the start of the line the error must name)
CASES: list[tuple[str, Callable[[str], str], str, str]] = [
    # --- numbers that are not finite ---
    ("settle inf", add_under("    revolutions: 1.05", "    settle_s: .inf"),
     "steps.spin_scan.settle_s", "    settle_s: .inf"),
    ("range inf", replace("    range: 1.25", "    range: .inf"), "simulation.truth.range",
     "    range: .inf"),
    ("rpm nan", replace("    rpm: 20", "    rpm: .nan"), "steps.spin_scan.rpm", "    rpm: .nan"),
    ("noise nan", replace("    range_noise: 0.001", "    range_noise: .nan"),
     "simulation.lidar.range_noise", "    range_noise: .nan"),
    ("pitch -inf", replace("    pitch_deg: 45", "    pitch_deg: -.inf"),
     "simulation.truth.pitch_deg", "    pitch_deg: -.inf"),
    ("cube offset inf", replace("    offset: [0.08, 0.05]", "    offset: [.inf, 0.05]"),
     "fixtures.qa_cube.offset.0", "    offset: [.inf"),
    ("yaw nan", replace("    yaw_deg: 20", "    yaw_deg: .nan"), "fixtures.qa_cube.yaw_deg",
     "    yaw_deg: .nan"),
    ("latency inf", add_under("    direction: 1", "    latency_s: .inf"),
     "station.encoder.latency_s", "    latency_s: .inf"),
    ("true H nan", add_under("    pitch_deg: 45", "    H: {tx: .nan, ty: 1.0}"),
     "simulation.truth.H.tx", "    H: {tx"),
    ("qa limit inf", replace("  edge_error: 0.0010", "  edge_error: .inf"), "qa.edge_error",
     "  edge_error: .inf"),
    ("polygon vertex nan", polygon("[[0.1, 0.0], [.nan, 0.1], [-0.1, 0.0]]"),
     "fixtures.spin_target.polygon.1.0", "    polygon:"),
    # --- numbers out of their documented ranges ---
    ("revolutions 1e6", replace("    revolutions: 1.05", "    revolutions: 1.0e6"),
     "steps.spin_scan.revolutions", "    revolutions: 1.0e6"),
    ("lines 1e8", replace("    lines: 100", "    lines: 100000000"), "steps.static_scan.lines",
     "    lines: 100000000"),
    ("lines zero", replace("    lines: 100", "    lines: 0"), "steps.static_scan.lines",
     "    lines: 0"),
    ("lines too few for the initial calibration", replace("    lines: 100", "    lines: 5"),
     "steps.static_scan.lines", "    lines: 5"),
    ("rpm zero", replace("    rpm: 20", "    rpm: 0"), "steps.spin_scan.rpm", "    rpm: 0"),
    ("rpm 10000", replace("    rpm: 20", "    rpm: 10000"), "steps.spin_scan.rpm",
     "    rpm: 10000"),
    ("rpm negative", replace("    rpm: 20", "    rpm: -5"), "steps.spin_scan.rpm",
     "    rpm: -5"),
    ("settle one day", add_under("    revolutions: 1.05", "    settle_s: 86400"),
     "steps.spin_scan.settle_s", "    settle_s: 86400"),
    ("platter 1e300", replace("    diameter: 0.585", "    diameter: 1e300"),
     "fixtures.platter.diameter", "    diameter: 1e300"),
    ("platter tiny", replace("    diameter: 0.585", "    diameter: 0.001"),
     "fixtures.platter.diameter", "    diameter: 0.001"),
    ("noise one metre", replace("    range_noise: 0.001", "    range_noise: 1.0"),
     "simulation.lidar.range_noise", "    range_noise: 1.0"),
    ("noise negative", replace("    range_noise: 0.001", "    range_noise: -0.001"),
     "simulation.lidar.range_noise", "    range_noise: -0.001"),
    ("points per line huge", replace("    points_per_line: 1000", "    points_per_line: 10000000"),
     "simulation.lidar.points_per_line", "    points_per_line: 10000000"),
    ("fov zero", replace("    fov_deg: 72", "    fov_deg: 0"), "simulation.lidar.fov_deg",
     "    fov_deg: 0"),
    ("seed negative", replace("  seed: 0", "  seed: -1"), "simulation.seed", "  seed: -1"),
    ("seed 2^70", replace("  seed: 0", "  seed: 1180591620717411303424"), "simulation.seed",
     "  seed: 118"),
    ("ppr zero", replace("    ppr: 1024", "    ppr: 0"), "station.encoder.ppr", "    ppr: 0"),
    ("ppr too coarse", replace("    ppr: 1024", "    ppr: 8"), "station.encoder.ppr", "    ppr: 8"),
    ("ppr huge", replace("    ppr: 1024", "    ppr: 1000000000"), "station.encoder.ppr",
     "    ppr: 1000000000"),
    ("latency two seconds", add_under("    direction: 1", "    latency_s: 2.0"),
     "station.encoder.latency_s", "    latency_s: 2.0"),
    ("range below the minimum", replace("    range: 1.25", "    range: 0.05"),
     "simulation.truth.range", "    range: 0.05"),
    ("pitch 90", replace("    pitch_deg: 45", "    pitch_deg: 90"), "simulation.truth.pitch_deg",
     "    pitch_deg: 90"),
    ("cube edge 5 m", replace("    edge: 0.100", "    edge: 5.0"), "fixtures.qa_cube.edge",
     "    edge: 5.0"),
    ("L width zero", replace("    width: 0.20", "    width: 0"), "fixtures.static_target.width",
     "    width: 0"),
    ("slope 89.5", replace("    slope_deg: 20", "    slope_deg: 89.5"),
     "fixtures.spin_target.slope_deg", "    slope_deg: 89.5"),
    ("notch 0.95", replace("    notch_depth: 0.45", "    notch_depth: 0.95"),
     "fixtures.spin_target.notch_depth", "    notch_depth: 0.95"),
    ("dropout 1", add_under("    range_noise: 0.001", "    dropout: 1.0"),
     "simulation.lidar.dropout", "    dropout: 1.0"),
    ("placement sigma 1 m", add_under("  seed: 0", "  placement:\n    position_sigma: 1.0"),
     "simulation.placement.position_sigma", "    position_sigma: 1.0"),
    ("true rotation 10 rad", add_under("    pitch_deg: 45", "    H: {tx: 0, ty: 1.2, rz: 10}"),
     "simulation.truth.H.rz", "    H: {"),
    ("true H unknown key", add_under("    pitch_deg: 45", "    H: {tx: 0, ty: 1.2, qq: 1}"),
     "simulation.truth.H.qq", "    H: {"),
    ("optimiser bound 10 m", add_under(
         "  strategy: periodicity", "  periodicity:\n    translation_bound: 10"),
     "calibration.periodicity.translation_bound", "    translation_bound: 10"),
    ("max_outer 1e9", add_under(
         "  strategy: periodicity", "  periodicity:\n    max_outer: 1000000000"),
     "calibration.periodicity.max_outer", "    max_outer:"),
    ("version zero", replace("version: 1", "version: 0"), "version", "version: 0"),
    ("true H missing ty", add_under("    pitch_deg: 45", "    H: {tx: 0, tz: 0, ry: 0, rz: -0.7}"),
     "simulation.truth.H", "    H: {"),
    ("turntable too slow to spin up", add_under("  seed: 0", "  turntable:\n"
                                                "    acceleration_rpm_s: 2"),
     "simulation.turntable.acceleration_rpm_s", "    acceleration_rpm_s: 2"),
    ("normal neighbours 5000", under_strategy("  periodicity:\n    normal_neighbours: 5000"),
     "calibration.periodicity.normal_neighbours", "    normal_neighbours: 5000"),
    ("wrong type for rpm", replace("    rpm: 20", "    rpm: fast"), "steps.spin_scan.rpm",
     "    rpm: fast"),
    ("integer lines as float", replace("    lines: 100", "    lines: 100.5"),
     "steps.static_scan.lines", "    lines: 100.5"),
    ("too many simulated lines", replace("    points_per_line: 1000\n    line_rate_hz: 1000",
                                         "    points_per_line: 2\n    line_rate_hz: 100000"),
     "steps.spin_scan.revolutions", "    revolutions: 1.05"),
    ("slow spin at full lidar rate", replace("    rpm: 20", "    rpm: 0.5"),
     "steps.spin_scan.revolutions", "    revolutions: 1.05"),
    ("range window excludes the platter", replace("    range_noise: 0.001",
                                                  "    range_noise: 0.001\n    range_max: 1.0"),
     "simulation.truth.range", "    range: 1.25"),
    ("range window reversed", replace("    range_noise: 0.001",
                                      "    range_noise: 0.001\n    range_min: 3\n"
                                      "    range_max: 2"),
     "simulation.lidar.range_min", "    range_min: 3"),
    ("wall inside the platter", add_under("  seed: 0", "  background:\n    wall_distance: 0.2"),
     "simulation.background.wall_distance", "    wall_distance: 0.2"),
    # --- fixtures that do not fit or cannot be built ---
    ("L-target 2 m wide", replace("    width: 0.20", "    width: 1.5"),
     "fixtures.static_target.width", "    width: 1.5"),
    ("L-target base too long", replace("    base_length: 0.15", "    base_length: 0.40"),
     "fixtures.static_target.base_length", "    base_length: 0.40"),
    ("L-target off centre", add_under("    h_short: 0.05", "    offset: [0.0, 0.25]"),
     "fixtures.static_target.offset", "    offset: [0.0, 0.25]"),
    ("cube off the platter", replace("    offset: [0.08, 0.05]", "    offset: [0.25, 0.05]"),
     "fixtures.qa_cube.offset", "    offset: [0.25"),
    ("frustum too big", replace("    circumradius: 0.20", "    circumradius: 0.35"),
     "fixtures.spin_target.circumradius", "    circumradius: 0.35"),
    ("frustum too high for its slope", replace("    height: 0.055", "    height: 0.3"),
     "fixtures.spin_target.height", "    height: 0.3"),
    ("self-intersecting polygon", polygon("[[0.1, 0.1], [-0.1, -0.1], [0.1, -0.1], [-0.1, 0.1]]"),
     "fixtures.spin_target.polygon", "    polygon:"),
    ("collinear polygon", polygon("[[0.0, 0.0], [0.1, 0.0], [0.2, 0.0]]"),
     "fixtures.spin_target.polygon.0", "    polygon:"),
    ("collinear vertex", polygon("[[0.1, 0.0], [0.1, 0.1], [0.0, 0.1], [-0.1, 0.1], "
                                 "[-0.1, -0.1]]"),
     "fixtures.spin_target.polygon.2", "    polygon:"),
    ("duplicate polygon points", polygon("[[0.1, 0.0], [0.0, 0.1], [0.0, 0.1], [-0.1, 0.0]]"),
     "fixtures.spin_target.polygon.2", "    polygon:"),
    ("two-point polygon", polygon("[[0.1, 0.0], [0.0, 0.1]]"),
     "fixtures.spin_target.polygon", "    polygon:"),
    ("polygon not star-shaped", polygon("[[0.15, -0.15], [0.15, 0.15], [-0.15, 0.15], "
                                        "[-0.15, 0.10], [0.10, 0.10], [0.10, -0.10], "
                                        "[-0.15, -0.10], [-0.15, -0.15]]"),
     "fixtures.spin_target.polygon", "    polygon:"),
    ("polygon off the platter", polygon("[[0.4, 0.0], [0.0, 0.2], [-0.2, 0.0], [0.0, -0.2]]"),
     "fixtures.spin_target.polygon", "    polygon:"),
    ("mesh file missing", add_under("    kind: cube", "    mesh: nosuch.stl"),
     "fixtures.qa_cube.mesh", "    mesh: nosuch.stl"),
    ("mesh not a mesh format", add_under("    kind: cube", "    mesh: cube.txt"),
     "fixtures.qa_cube.mesh", "    mesh: cube.txt"),
    ("demo prism off the platter",
     add_under("    yaw_deg: 20", "  demo:\n    - kind: prism\n      offset: [0.25, 0.0]"),
     "fixtures.demo[0].offset", "      offset: [0.25"),
    # --- duplicate and unknown keys ---
    ("duplicate name", replace("version: 1", "version: 1\nname: other"), "name", "name: other"),
    ("duplicate rpm", replace("    rpm: 20\n", "    rpm: 20\n    rpm: 30\n"),
     "steps.spin_scan.rpm", "    rpm: 30"),
    ("duplicate qa section", append("qa:\n  edge_error: 0.5\n"), "qa", "qa:\n  edge_error: 0.5"),
    ("unknown top-level key", append("qaa:\n  edge_error: 0.5\n"), "qaa", "qaa:"),
    ("unknown periodicity option", under_strategy("  options:\n    periodicity:\n      speed: 3"),
     "calibration.options.periodicity.speed", "      speed: 3"),
    ("unknown shape option", under_strategy("  options:\n    shape:\n      boxx: upright"),
     "calibration.options.shape.boxx", "      boxx:"),
    ("shape option wrong value", under_strategy("  options:\n    shape:\n      box: round"),
     "calibration.options.shape.box", "      box: round"),
]


def _line_of(text: str, marker: str) -> int:
    return text[: text.index(marker)].count("\n") + 1


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_malformed_recipe_is_refused_with_file_line_and_field(
    tmp_path: Path, case: tuple[str, Callable[[str], str], str, str]
) -> None:
    _name, edit, field, marker = case
    text = edit(BASE)
    path = tmp_path / "r.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(RecipeError) as info:
        check_plugins(load_recipe(path))
    message = str(info.value)
    line = _line_of(text, marker)
    shown = field.replace(".0.", "[0].").replace(".1.", "[1].").replace(".2.", "[2].")
    shown = re.sub(r"\.(\d+)$", r"[\1]", shown)
    assert f"{path}:{line}: {shown}: " in message, message
    assert "Traceback" not in message


def test_at_least_sixty_malformed_recipes() -> None:
    assert len(CASES) + len(FILE_CASES) + len(SETTINGS_CASES) >= 60


def test_duplicate_key_names_both_lines(tmp_path: Path) -> None:
    text = BASE.replace("    rpm: 20\n", "    rpm: 20\n    rpm: 30\n", 1)
    first = _line_of(text, "    rpm: 20")
    with pytest.raises(RecipeError, match=f"first at line {first}, again at line {first + 1}"):
        parse_recipe(text, "r.yaml")


# --- the file itself -----------------------------------------------------------------------
def _nested(tmp_path: Path) -> Path:
    p = tmp_path / "nested.yaml"
    p.write_text("name: " + "[" * 20000 + "]" * 20000 + "\n", encoding="utf-8")
    return p


def _big(tmp_path: Path) -> Path:
    p = tmp_path / "big.yaml"
    with p.open("w", encoding="utf-8") as f:
        f.write(BASE)
        f.write("# " + "x" * 1000 + "\n" * 1)
        for _ in range(50_000):
            f.write("# " + "x" * 1000 + "\n")
    return p


def _fifo(tmp_path: Path) -> Path:
    p = tmp_path / "fifo.yaml"
    os.mkfifo(p)
    return p


def _folder(tmp_path: Path) -> Path:
    p = tmp_path / "folder.yaml"
    p.mkdir()
    return p


def _binary(tmp_path: Path) -> Path:
    p = tmp_path / "binary.yaml"
    p.write_bytes(BASE.encode() + b"\xff\xfe\x00garbage\n")
    return p


def _laughs(tmp_path: Path) -> Path:
    lines = ['a0: &a0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for i in range(1, 9):
        lines.append(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 9) + "]")
    p = tmp_path / "laughs.yaml"
    p.write_text(BASE + "\n".join(lines) + "\n", encoding="utf-8")
    return p


def _empty(tmp_path: Path) -> Path:
    p = tmp_path / "empty.yaml"
    p.write_text("", encoding="utf-8")
    return p


def _tabs(tmp_path: Path) -> Path:
    p = tmp_path / "tabs.yaml"
    p.write_text(BASE.replace("    rpm: 20", "\trpm: 20"), encoding="utf-8")
    return p


def _long_integer(tmp_path: Path) -> Path:
    p = tmp_path / "digits.yaml"
    p.write_text(BASE.replace("    rpm: 20\n", "    rpm: " + "9" * 5000 + "\n", 1),
                 encoding="utf-8")
    return p


def _many_keys(tmp_path: Path) -> Path:
    """Nearly 1 MB: the recipe and 60 000 keys more."""
    p = tmp_path / "keys.yaml"
    p.write_text(BASE + "".join(f"k{i:05d}: {i:05d}\n" for i in range(60_000)), encoding="utf-8")
    return p


FILE_CASES: list[tuple[str, Callable[[Path], Path], str]] = [
    ("20000 nested brackets", _nested, r"nested\.yaml:1: .*nested more than \d+ levels deep"),
    ("50 MB recipe", _big, r"big\.yaml: the recipe is \d+\.\d MB, more than"),
    ("fifo", _fifo, r"fifo\.yaml: the recipe is a named pipe \(FIFO\), not a regular file"),
    ("folder", _folder, r"folder\.yaml: the recipe is a folder, not a regular file"),
    ("not UTF-8", _binary, r"binary\.yaml: line \d+: the recipe is not UTF-8 text"),
    ("billion laughs", _laughs, r"laughs\.yaml:\d+: .*expands to more than"),
    ("empty file", _empty, r"empty\.yaml: a recipe must be a YAML mapping"),
    ("tab indentation", _tabs, r"tabs\.yaml:\d+: not valid YAML"),
    ("missing file", lambda tmp: tmp / "nope.yaml", r"nope\.yaml: recipe file not found"),
    ("5000-digit integer", _long_integer,
     r"digits\.yaml:\d+: steps\.spin_scan\.rpm: an integer of 5000 characters"),
    ("60 000 keys", _many_keys, r"keys\.yaml:\d+: holds more than 50000 values"),
]


@pytest.mark.parametrize("case", FILE_CASES, ids=[c[0] for c in FILE_CASES])
def test_bad_recipe_file_is_refused_quickly(
    tmp_path: Path, case: tuple[str, Callable[[Path], Path], str]
) -> None:
    _name, make, pattern = case
    path = make(tmp_path)
    outcome: dict[str, object] = {}

    def validate() -> None:
        try:
            load_recipe(path)
        except RecipeError as exc:
            outcome["error"] = str(exc)
        except BaseException as exc:  # the test reports what escaped
            outcome["escaped"] = exc

    worker = threading.Thread(target=validate, daemon=True)
    worker.start()
    worker.join(300.0)  # a hang guard: each is refused in well under a second of CPU
    assert not worker.is_alive(), f"validating {path.name} hung"
    assert "escaped" not in outcome, outcome.get("escaped")
    assert re.search(pattern, str(outcome.get("error"))), outcome


def test_a_recipe_of_too_many_values_is_refused_before_anything_is_built(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The count is taken on the parser's events: the node tree (PyYAML's pure-Python
    composer: seconds for a megabyte) is never made for such a file."""
    import yaml

    def never(self: Any) -> Any:
        raise AssertionError("the node tree was built")

    monkeypatch.setattr(yaml.SafeLoader, "get_single_node", never)
    with pytest.raises(RecipeError, match="holds more than 50000 values"):
        load_recipe(_many_keys(tmp_path))


def test_thousands_of_unknown_keys_are_counted_not_each_located(
    monkeypatch: pytest.MonkeyPatch
) -> None:
    from calstation.recipes import load as load_module

    located: list[object] = []
    real = load_module.line_of
    monkeypatch.setattr(load_module, "line_of",
                        lambda node, loc: located.append(loc) or real(node, loc))
    text = BASE.replace("qa:\n", "qa:\n" + "".join(f"  k{i}: {i}\n" for i in range(20_000)), 1)
    with pytest.raises(RecipeError) as info:
        parse_recipe(text, "r.yaml")
    lines = str(info.value).splitlines()
    assert lines[1].strip().endswith("qa.k0: unknown key")
    assert lines[-1].strip() == "… and 19980 more problems"
    assert len(located) == 20


def test_cli_validate_reports_without_traceback(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _nested(tmp_path)
    with pytest.raises(SystemExit) as info:
        main(["recipes", "validate", str(path)])
    assert info.value.code == 2
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err + captured.out
    assert "nested more than" in captured.err


def test_validate_refuses_a_static_scan_too_short_for_the_initial_calibration(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The fault suite's recipe: it validated, then failed at its static scan."""
    for lines, code in ((1, 2), (9, 2), (10, 0)):
        path = tmp_path / f"lines{lines}.yaml"
        path.write_text(replace("    lines: 100", f"    lines: {lines}")(BASE), encoding="utf-8")
        with pytest.raises(SystemExit) as info:
            main(["recipes", "validate", str(path)])
        err = " ".join(capsys.readouterr().err.split())
        assert info.value.code == code, err
        if code:
            assert "steps.static_scan.lines" in err and "too few for the initial calibration" in err
            assert "at least 10" in err and "Traceback" not in err
    # a targetless recipe has no static scan: its lines are not judged
    targetless = BASE.replace("calibration:\n", "calibration:\n  start: platter\n", 1)
    assert "start: platter" in targetless
    path = tmp_path / "targetless.yaml"
    path.write_text(replace("    lines: 100", "    lines: 1")(targetless), encoding="utf-8")
    with pytest.raises(SystemExit) as info:
        main(["recipes", "validate", str(path)])
    assert info.value.code == 0, capsys.readouterr().err


# --- driver settings, checked against the settings model each driver declares -------------
CANOPEN = (REPO / "recipes" / "hokuyo-canopen-emulated.yaml").read_text(encoding="utf-8")
SETTINGS_CASES: list[tuple[str, str, tuple[str, str], str]] = [
    ("node id zero", CANOPEN, ("      node_id: 1", "      node_id: 0"),
     "station.turntable.settings.node_id"),
    ("node id 200", CANOPEN, ("      node_id: 2", "      node_id: 200"),
     "station.encoder.settings.node_id"),
    ("sync period inf", CANOPEN, ("      sync_period_s: 0.002", "      sync_period_s: .inf"),
     "station.encoder.settings.sync_period_s"),
    ("unknown drive setting", CANOPEN, ("      node_id: 1", "      node_id: 1\n      nodeid: 1"),
     "station.turntable.settings.nodeid"),
    ("sim seed negative", BASE, ("  lidar:\n    driver: sim",
                                 "  lidar:\n    driver: sim\n    settings: {seed: -3}"),
     "station.lidar.settings.seed"),
    ("sim unknown setting", BASE, ("  turntable:\n    driver: sim",
                                   "  turntable:\n    driver: sim\n    settings: {rpm: 3}"),
     "station.turntable.settings.rpm"),
]


@pytest.mark.parametrize("case", SETTINGS_CASES, ids=[c[0] for c in SETTINGS_CASES])
def test_driver_settings_are_checked_before_the_run(
    tmp_path: Path, case: tuple[str, str, tuple[str, str], str]
) -> None:
    _name, base, (old, new), field = case
    assert old in base
    text = base.replace(old, new, 1)
    path = tmp_path / "r.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(RecipeError) as info:
        check_plugins(load_recipe(path))
    assert re.search(rf"{re.escape(str(path))}:\d+: {re.escape(field)}: ", str(info.value)), (
        str(info.value))


# --- a plugin strategy's options model --------------------------------------------------------
class _PluginOptions(BaseModel):
    model_config = ConfigDict(extra="forbid")

    iterations: int = Field(5, ge=1, le=50)


class _OptionsPlugin:
    __name__ = "options-plugin"

    @hookimpl
    def calstation_register_cost_strategies(self, register: Any) -> None:
        register(SimpleNamespace(name="planes", fixture="spin_target",
                                 options_model=_PluginOptions))


@pytest.mark.parametrize("options,field", [
    ("  options:\n    planes:\n      iteratons: 3\n", "calibration.options.planes.iteratons"),
    ("  options:\n    planes:\n      iterations: 500\n", "calibration.options.planes.iterations"),
], ids=["unknown key", "out of range"])
def test_a_plugin_strategy_options_model_is_enforced(
    tmp_path: Path, options: str, field: str
) -> None:
    from calstation_sim import plugin as sim_plugin

    text = BASE.replace("  strategy: periodicity\n", "  strategy: planes\n" + options)
    path = tmp_path / "r.yaml"
    path.write_text(text, encoding="utf-8")
    with plugins.isolated(sim_plugin, _OptionsPlugin()):
        with pytest.raises(RecipeError) as info:
            check_plugins(load_recipe(path))
        assert f"{path}:{_line_of(text, options.splitlines()[-1])}: {field}: " in str(info.value)
        good = tmp_path / "good.yaml"
        good.write_text(BASE.replace("  strategy: periodicity\n", "  strategy: planes\n"))
        check_plugins(load_recipe(good))  # defaults fit the model


def test_a_static_scan_of_no_lines_is_refused_even_where_no_static_scan_is_used(
    tmp_path: Path
) -> None:
    """The targetless recipe takes no static scan, so no cross-field check looks at its length:
    the field's own bound refuses 0 lines."""
    text = (REPO / "recipes" / "sim-targetless.yaml").read_text(encoding="utf-8")
    assert "    lines: 100\n" in text
    path = tmp_path / "targetless.yaml"
    path.write_text(text.replace("    lines: 100\n", "    lines: 0\n", 1), encoding="utf-8")
    with pytest.raises(RecipeError) as info:
        check_plugins(load_recipe(path))
    assert f"{path}:{_line_of(path.read_text(), '    lines: 0')}: steps.static_scan.lines: " \
           "Input should be greater than or equal to 1" in str(info.value)
