"""Recipes: shipped files validate; each kind of invalid recipe names its field and YAML line."""

from __future__ import annotations

import re
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from calstation import hookimpl, plugins
from calstation.cli import main
from calstation.errors import RecipeError
from calstation.plugins.recipe_checks import check_plugins
from calstation.recipes import load_recipe

RECIPES = Path(__file__).resolve().parents[2] / "recipes"

BASE = """\
name: test
station:
  id: st-1
  lidar:
    driver: fake
  turntable:
    driver: fake
  encoder:
    driver: fake
    ppr: 1024
    direction: 1
fixtures:
  spin_target:
    kind: frustum
    slope_deg: 20
  qa_cube:
    kind: cube
    edge: 0.1
    offset: [0.08, 0.05]
simulation:
  truth:
    pitch_deg: 45
  lidar:
    points_per_line: 1000
    line_rate_hz: 1000
steps:
  static_scan:
    lines: 100
calibration:
  strategy: fake-strategy
"""


class FakePlugin:
    """Registers a driver of each kind and one strategy, all named fake."""

    __name__ = "fake-recipe-plugin"

    @hookimpl
    def calstation_register_drivers(self, register: Any) -> None:
        for kind in ("lidar", "turntable", "encoder"):
            register(kind, "fake", lambda settings, context: None)

    @hookimpl
    def calstation_register_cost_strategies(self, register: Any) -> None:
        register(SimpleNamespace(name="fake-strategy", fixture="spin_target"))


@pytest.fixture
def fake_plugins() -> Any:
    with plugins.isolated(FakePlugin(), builtins=False) as pm:
        yield pm


def _write(tmp_path: Path, text: str, name: str = "r.yaml") -> Path:
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


def test_base_recipe_is_valid(tmp_path: Path, fake_plugins: Any) -> None:
    loaded = load_recipe(_write(tmp_path, BASE))
    check_plugins(loaded)
    assert loaded.recipe.station.id == "st-1"


@pytest.mark.parametrize("path", sorted(RECIPES.glob("*.yaml")), ids=lambda p: p.name)
def test_shipped_recipes_load(path: Path) -> None:
    loaded = load_recipe(path)
    assert loaded.recipe.name == path.stem


# (description, edit of BASE, field named, text on the YAML line the error must point at)
INVALID: list[tuple[str, tuple[str, str], str, str]] = [
    ("unknown top-level key", ("calibration:", "calibratoin:"), "calibratoin", "calibratoin:"),
    ("unknown nested key", ("    edge: 0.1", "    edg: 0.1"), "fixtures.qa_cube.edg", "edg:"),
    ("wrong type", ("    lines: 100", "    lines: many"), "steps.static_scan.lines", "lines:"),
    ("negative length", ("    edge: 0.1", "    edge: -0.1"), "fixtures.qa_cube.edge", "edge:"),
    ("missing driver", ("  lidar:\n    driver: fake\n", "  lidar: {}\n"),
     "station.lidar.driver", "lidar: {}"),
    ("bad encoder direction", ("    direction: 1", "    direction: 2"),
     "station.encoder.direction", "direction:"),
    ("unknown fixture kind", ("    kind: frustum", "    kind: sphere"),
     "fixtures.spin_target", "spin_target:"),
    ("lidar faster than its point budget", ("    line_rate_hz: 1000", "    line_rate_hz: 5000"),
     "simulation.lidar", "  lidar:\n    points"),
    ("station id not a name", ("  id: st-1", "  id: st 1/2"), "station.id", "id:"),
    ("cube off the platter", ("    offset: [0.08, 0.05]", "    offset: [0.30, 0.05]"),
     "fixtures.qa_cube.offset", "offset:"),
    ("facets steeper than the lidar pitch", ("    slope_deg: 20", "    slope_deg: 60"),
     "fixtures.spin_target.slope_deg", "slope_deg:"),
    ("mesh file missing", ("    kind: cube\n", "    kind: cube\n    mesh: cube.stl\n"),
     "fixtures.qa_cube.mesh", "mesh:"),
    ("L-target heights not linear",
     ("fixtures:\n", "fixtures:\n  static_target:\n    h_tall: 0.2\n    h_mid: 0.1\n"
      "    h_short: 0.05\n"), "fixtures.static_target", "static_target:"),
    ("shape option not a boolean",
     ("  strategy: fake-strategy\n", "  strategy: fake-strategy\n  options:\n    shape:\n"
      "      coarse: maybe\n"), "calibration.options.shape.coarse", "coarse:"),
    ("unknown shape box", ("  strategy: fake-strategy\n", "  strategy: fake-strategy\n"
                           "  options:\n    shape:\n      box: round\n"),
     "calibration.options.shape.box", "box:"),
    ("a certificate without a range model",
     ("  strategy: fake-strategy\n", "  strategy: fake-strategy\n  range_model: none\n"
      "  range_offset_certificate: {offset: 0.001, sigma: 0.0001}\n"),
     "calibration.range_offset_certificate", "range_offset_certificate:"),
    ("a certificate without its sigma",
     ("  strategy: fake-strategy\n", "  strategy: fake-strategy\n"
      "  range_offset_certificate:\n    offset: 0.001\n"),
     "calibration.range_offset_certificate.sigma", "range_offset_certificate:"),
    ("the scale error without a cube of the platter's finish",
     ("  strategy: fake-strategy\n", "  strategy: fake-strategy\n  range_model: offset+scale\n"),
     "calibration.range_model", "range_model:"),
    ("revolutions below one turn", ("    lines: 100", "    lines: 100\n  spin_scan:\n"
                                     "    revolutions: 0.5"), "steps.spin_scan.revolutions",
     "revolutions:"),
]


def _line_with(text: str, marker: str) -> int:
    """1-based line where ``marker`` starts in ``text``."""
    return text[: text.index(marker)].count("\n") + 1


@pytest.mark.parametrize("desc,edit,field,marker", INVALID, ids=[i[0] for i in INVALID])
def test_invalid_recipe_names_field_and_line(
    tmp_path: Path, desc: str, edit: tuple[str, str], field: str, marker: str
) -> None:
    old, new = edit
    assert old in BASE, desc
    text = BASE.replace(old, new, 1)
    path = _write(tmp_path, text)
    with pytest.raises(RecipeError) as info:
        load_recipe(path)
    message = str(info.value)
    line = _line_with(text, marker)
    assert f"{path}:{line}: {field}: " in message, message


@pytest.mark.parametrize(
    "edit,field,line",
    [
        (("  lidar:\n    driver: fake", "  lidar:\n    driver: nosuch"), "station.lidar.driver", 5),
        (("  strategy: fake-strategy", "  strategy: nosuch"), "calibration.strategy", 30),
    ],
    ids=["unknown driver", "unknown strategy"],
)
def test_unregistered_plugin_names_field_and_line(
    tmp_path: Path, fake_plugins: Any, edit: tuple[str, str], field: str, line: int
) -> None:
    path = _write(tmp_path, BASE.replace(*edit))
    loaded = load_recipe(path)
    with pytest.raises(RecipeError) as info:
        check_plugins(loaded)
    assert f"{path}:{line}: {field}: no " in str(info.value)
    assert "installed: fake" in str(info.value)


def test_not_yaml_names_the_line(tmp_path: Path) -> None:
    path = _write(tmp_path, BASE.replace("    ppr: 1024", "    ppr: [1024"))
    with pytest.raises(RecipeError, match=re.escape(f"{path}:1") + r"\d: not valid YAML"):
        load_recipe(path)


def test_not_a_mapping_and_missing_file(tmp_path: Path) -> None:
    with pytest.raises(RecipeError, match="must be a YAML mapping"):
        load_recipe(_write(tmp_path, "- a\n- b\n"))
    with pytest.raises(RecipeError, match="recipe file not found"):
        load_recipe(tmp_path / "nope.yaml")


def test_several_problems_are_all_reported(tmp_path: Path) -> None:
    text = BASE.replace("    edge: 0.1", "    edge: -0.1").replace("    lines: 100", "    lines: x")
    with pytest.raises(RecipeError) as info:
        load_recipe(_write(tmp_path, text))
    assert "fixtures.qa_cube.edge" in str(info.value)
    assert "steps.static_scan.lines" in str(info.value)


def test_cli_validate_and_list(
    tmp_path: Path, fake_plugins: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    good = _write(tmp_path, BASE, "good.yaml")
    bad = _write(tmp_path, BASE.replace("    edge: 0.1", "    edge: -0.1"), "bad.yaml")
    with pytest.raises(SystemExit) as exit_info:
        main(["recipes", "validate", str(good)])
    assert exit_info.value.code in (0, None)
    assert "good.yaml: OK" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exit_info:
        main(["recipes", "validate", str(bad)])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "fixtures.qa_cube.edge" in err and "bad.yaml:18" in err
    with pytest.raises(SystemExit) as exit_info:
        main(["recipes", "list", str(tmp_path)])
    assert exit_info.value.code in (0, None)
    out = capsys.readouterr().out
    assert "good.yaml" in out and "bad.yaml" in out and "invalid" in out


def test_the_shipped_recipes_come_from_the_package_listed_and_copied(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """An installed calstation lists and copies the recipes it ships without its checkout:
    they are the package's own files (a wheel carries them: pyproject's package-data)."""
    import calstation
    from calstation.recipes import SHIPPED_DIR, shipped_recipes

    assert SHIPPED_DIR.is_relative_to(Path(calstation.__file__).resolve().parent)
    assert "sim-periodicity.yaml" in [p.name for p in shipped_recipes()]
    monkeypatch.chdir(tmp_path)  # no ./recipes here
    monkeypatch.setenv("CALSTATION_HOME", str(tmp_path / "home"))
    monkeypatch.delenv("CALSTATION_RECIPES", raising=False)

    def cli(*argv: str) -> tuple[int, str, str]:
        try:
            main(list(argv))
        except SystemExit as exc:
            out, err = capsys.readouterr()
            return int(exc.code or 0), out, err
        out, err = capsys.readouterr()
        return 0, out, err

    code, out, _ = cli("recipes", "list")
    assert code == 0 and "sim-periodicity.yaml" in out and "shipped" in out
    mine = tmp_path / "mine.yaml"
    code, out, _ = cli("recipes", "copy", "sim-periodicity", str(mine))
    assert code == 0 and str(mine) in out
    assert mine.read_bytes() == (SHIPPED_DIR / "sim-periodicity.yaml").read_bytes()
    # a file there already is replaced only when named and --force is given
    mine.write_text("name: edited\n")
    code, _, err = cli("recipes", "copy", "sim-periodicity.yaml", str(mine))
    assert code == 2 and "exists; give --force" in err and mine.read_text() == "name: edited\n"
    code, _, _ = cli("recipes", "copy", "sim-periodicity", str(mine), "--force")
    assert code == 0 and mine.read_bytes() == (SHIPPED_DIR / "sim-periodicity.yaml").read_bytes()
    # a folder gets NAME.yaml, never over a file it holds
    code, _, _ = cli("recipes", "copy", "sim-shape", str(tmp_path))
    assert code == 0 and (tmp_path / "sim-shape.yaml").is_file()
    code, _, err = cli("recipes", "copy", "sim-shape", str(tmp_path), "--force")
    assert code == 2 and "name the file to write" in err
    for name, target, says in (("nope", mine, "no shipped recipe named 'nope'"),
                               ("../sim-shape", mine, "no shipped recipe"),
                               ("sim-shape", tmp_path / "none" / "x.yaml", "does not exist")):
        code, _, err = cli("recipes", "copy", name, str(target))
        assert code == 2 and says in " ".join(err.split()) and "Traceback" not in err
    assert not list(tmp_path.glob(".*.part"))


def test_the_scale_error_with_a_cube_of_the_platters_finish(tmp_path: Path) -> None:
    """offset+scale reads the scale error from the cube's height above the platter: valid once
    the recipe states that the two are of one finish, and the refusal says what to do."""
    text = BASE.replace("  strategy: fake-strategy\n",
                        "  strategy: fake-strategy\n  range_model: offset+scale\n", 1)
    with pytest.raises(RecipeError) as info:
        load_recipe(_write(tmp_path, text))
    assert "same_finish_as_platter: true" in str(info.value)
    assert "range_model: offset" in str(info.value)
    stated = text.replace("  qa_cube:\n", "  qa_cube:\n    same_finish_as_platter: true\n", 1)
    recipe = load_recipe(_write(tmp_path, stated)).recipe
    assert recipe.calibration.range_model == "offset+scale"
    assert recipe.fixtures.qa_cube.same_finish_as_platter
