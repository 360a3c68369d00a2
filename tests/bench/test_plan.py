"""``calstation plan`` and the web station's /plan page: the station designer's figures from a
simulation of the recipe's station, against what the fine-tuning really does."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest
import yaml
from fastapi.testclient import TestClient

from calstation.testing import lean_recipe
from calstation.web.app import create_app
from tests.support.clirun import run_cli

pytest.importorskip("calstation_sim")

RECIPES = Path(__file__).resolve().parents[2] / "recipes"


def _quick(folder: Path, recipe: str = "sim-periodicity.yaml", **simulation: Any) -> Path:
    """The simulated station, quick to simulate: 500 points per line at 60 rpm."""
    data = yaml.safe_load((RECIPES / recipe).read_text())
    data["simulation"]["lidar"]["points_per_line"] = 500
    data["simulation"]["lidar"].update(simulation)
    data["steps"]["spin_scan"].update(rpm=60, settle_s=0.1)
    data["steps"]["cube_scan"].update(rpm=60, settle_s=0.1)
    data["steps"]["static_scan"]["lines"] = 40
    path = folder / "quick.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def test_plan_reports_sigma_predicted_error_and_turns(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, err = run_cli(["plan", str(_quick(tmp_path)), "--seeds", "1", "--turns", "2",
                              "--json"], capsys)
    assert code == 0, err
    plan = json.loads(out)
    assert plan["budget_m"] == 0.0003 and plan["strategy"] == "periodicity"
    base, *alternatives = plan["designs"]
    assert [r["turns"] for r in base["by_turns"]] == [1, 2]
    one, two = base["by_turns"]
    for row in (one, two):
        assert all(math.isfinite(row["sigma"][p]) and row["sigma"][p] > 0
                   for p in ("tx", "tz", "ry", "rz"))
        # the cube's scan adds the range offset's σ (below) and takes little from the rest:
        # within a tenth of the spin target's alone (2 turns: 0.231 against 0.212 mm; 0.218
        # with the platter taken for flat)
        assert 0 < row["with_cube_m"] <= row["predicted_error_m"] * 1.10
        # the lidar's range offset (the recipe's range model), measured by the QA cube: about
        # 0.5 mm on this sparse scan (500 points a line at 60 rpm; 0.49 mm with the platter
        # taken for flat, 0.52 mm with its dish and its height at the cube fitted)
        assert row["range_problem"] is None
        assert 0 < row["range_sigma"]["range_offset"] < 0.6e-3
        # and where that puts the axis, which the cube scan turns on for (axis_sigma)
        assert 0 < row["axis_sigma_m"] < 1e-3
        # a certificate of the offset would place it better, and the error with it is said
        assert 0 < row["certified_axis_sigma_m"] < row["axis_sigma_m"]
        assert 0 < row["certified_m"] <= row["with_cube_m"]
    assert plan["axis_sigma_limit_m"] == 0.0001
    assert any("calibration.range_offset_certificate" in r for r in plan["recommendations"])
    assert base["turns_needed"] >= 1
    # piped, the plan says what it does, how long it has taken and what is left
    lines = [line for line in err.splitlines() if line.startswith("planning: ")]
    assert lines[0].startswith("planning: starting — 0 %, ") and "so far" in lines[0], err
    assert any(line.startswith("planning: simulating the scans — 0 %") for line in lines)
    later = [line for line in lines if "centred" in line]
    assert later and "so far, about " in later[0] and later[0].endswith(" left"), err
    assert "planned in " in err
    # the recipe's target stands 60 mm off-centre: the plan tries it centred, and says why a
    # taller one does not fit this frustum
    names = {d["name"]: d for d in alternatives}
    assert "centred" in names and names["centred"]["by_turns"][0]["turns"] == 1
    assert "taller" in names and "inset" in names["taller"]["error"]
    # and, the range offset being measured on the cube, a cube three times larger, centred:
    # the rays spread wider over it, which tells the offset better from where the lidar stands
    # (the shipped recipe: ±0.080 mm against ±0.214 mm, the axis's σ 0.105 against 0.177 mm)
    larger = names["larger cube"]["by_turns"][0]
    assert names["larger cube"]["change"] == "a QA cube of 300 mm, centred"
    assert 0 < larger["range_sigma"]["range_offset"] < 0.7 * one["range_sigma"]["range_offset"]
    assert 0 < larger["axis_sigma_m"] < one["axis_sigma_m"]
    assert any(r.startswith("a QA cube of 300 mm, centred: ") for r in plan["recommendations"])
    assert plan["recommendations"]


def test_plan_of_a_shape_recipe_fits_the_cube_scan_over_its_turns(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The shape strategy fine-tunes on the cube's scan: the plan turns the cube, not the spin
    target (on the target's scan the shape fit found no cube: σ of tens of millimetres)."""
    code, out, err = run_cli(["plan", str(_quick(tmp_path, "sim-shape.yaml")), "--seeds", "1",
                              "--turns", "2", "--json"], capsys)
    assert code == 0, err
    plan = json.loads(out)
    assert plan["strategy"] == "shape"
    base = plan["designs"][0]
    assert [r["turns"] for r in base["by_turns"]] == [1, 2]
    for row in base["by_turns"]:
        assert 0 < row["sigma"]["tz"] < 0.3e-3 and 0 < row["sigma"]["ry"] < math.radians(0.1)
        assert 0 < row["predicted_error_m"] <= plan["budget_m"]
    assert base["turns_needed"] == 1


def test_plan_of_a_recipe_without_simulation_says_what_to_add(
    capsys: pytest.CaptureFixture[str]
) -> None:
    code, _, err = run_cli(["plan", str(RECIPES / "real-station-template.yaml")], capsys)
    assert code != 0 and "no simulation section" in err and "--set simulation" in err


def test_plan_set_changes_the_simulated_station(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, err = run_cli(["plan", str(_quick(tmp_path)), "--seeds", "1", "--turns", "1",
                              "--no-alternatives", "--json",
                              "--set", "simulation.lidar.range_noise=0.002"], capsys)
    assert code == 0, err
    noisy = json.loads(out)["designs"][0]["by_turns"][0]
    code, out, err = run_cli(["plan", str(_quick(tmp_path)), "--seeds", "1", "--turns", "1",
                              "--no-alternatives", "--json"], capsys)
    quiet = json.loads(out)["designs"][0]["by_turns"][0]
    # twice the range noise: a larger σ of ry and a larger predicted error
    assert noisy["sigma"]["ry"] > 1.3 * quiet["sigma"]["ry"]
    assert noisy["predicted_error_m"] > quiet["predicted_error_m"]
    code, _, err = run_cli(["plan", str(_quick(tmp_path)), "--set", "nonsense"], capsys)
    assert code != 0 and "KEY=VALUE" in err


def test_the_plan_page_plans_a_recipe_of_the_station(tmp_path: Path) -> None:
    import re
    import time

    from calstation.storage.db import open_database

    recipes = tmp_path / "recipes"
    recipes.mkdir()
    _quick(recipes)
    db = open_database(f"sqlite:///{tmp_path / 'web.db'}")
    app = create_app(db, data_dir=tmp_path / "data", recipes_dir=recipes)
    try:
        with TestClient(app, base_url="http://127.0.0.1:8470") as client:
            page = client.get("/plan")
            assert page.status_code == 200 and "quick.yaml" in page.text
            csrf = re.search(r'<meta name="csrf-token" content="([^"]+)">', page.text)
            assert csrf is not None
            headers = {"X-CSRF-Token": csrf.group(1), "Origin": "http://127.0.0.1:8470"}
            body = {"recipe": "quick.yaml", "seeds": 1, "turns": 1}
            assert client.post("/api/plan", json=body).status_code == 403  # no CSRF
            assert client.post("/api/plan", json={**body, "seeds": 9},
                               headers=headers).status_code == 422
            assert client.post("/api/plan", json={**body, "recipe": "../x.yaml"},
                               headers=headers).status_code == 422
            r = client.post("/api/plan", json=body, headers=headers)
            assert r.status_code == 202 and r.json()["status"] == "running"
            assert client.post("/api/plan", json=body, headers=headers).status_code == 409
            deadline = time.monotonic() + 240
            said = []
            while (now := client.get("/plan.json").json())["status"] == "running":
                assert time.monotonic() < deadline
                said.append(now["progress_text"])
                if now["left_s"] is not None:  # an estimate once a stage is done
                    assert now["progress_text"].endswith(" left")
                time.sleep(0.5)
            assert said and all(" so far" in text for text in said)
            state = client.get("/plan.json").json()
            assert state["status"] == "done", state
            assert state["plan"]["designs"][0]["by_turns"][0]["turns"] == 1
            page = client.get("/plan").text
            assert "Turns the budget needs" in page and 'id="plan-recommendations"' in page
    finally:
        db.dispose()


def test_a_plan_is_refused_while_a_run_is_on(tmp_path: Path) -> None:
    from calstation.web.live import Busy
    from calstation.web.plans import Planner

    class Running:
        busy = True

        def recipe_path(self, name: str) -> Path:
            return lean_recipe(tmp_path)

    with pytest.raises(Busy, match="a run is in progress"):
        Planner(Running()).start("lean.yaml", 1, 1)  # type: ignore[arg-type]


@pytest.fixture(autouse=True)
def _own_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The plan's cache of simulated scans in the test's own folder, not the user's."""
    monkeypatch.setenv("CALSTATION_HOME", str(tmp_path / "home"))


def test_a_plan_again_takes_its_simulated_scans_from_the_cache(tmp_path: Path) -> None:
    """The simulated scans are kept by the hash of the recipe as simulated: the same plan
    again simulates nothing and gives the same figures; another station simulates again. An
    alternative placement of the spin target simulates its spin scan alone (the static and cube
    scans are the design's), a larger cube its cube scan alone, and the progress runs from 0
    to 1."""
    from calstation.bench.plan import CACHE_ENTRIES, plan
    from calstation.recipes import load_recipe

    cache = tmp_path / "cache"

    def kept() -> dict[str, tuple[list[str], int]]:
        return {p.parent.name: (sorted(json.loads(p.read_text())), p.parent.stat().st_ino)
                for p in cache.glob("*/files.json")}

    loaded = load_recipe(_quick(tmp_path))
    said: list[float] = []
    first = plan(loaded, turns=1, cache=cache, progress=lambda m, f: said.append(f))
    runs = kept()
    # the design; the larger cube's cube scan; centred's spin scan
    assert sorted(files for files, _ in runs.values()) == [
        ["cube", "spin", "static", "truth"], ["cube", "truth"], ["spin", "truth"]]
    assert said == sorted(said) and said[0] == 0.0 and said[-1] == 1.0
    again = plan(loaded, turns=1, cache=cache)
    assert kept() == runs and again["designs"] == first["designs"]
    noisier = load_recipe(_quick(tmp_path, range_noise=0.002))
    plan(noisier, turns=1, cache=cache, alternatives=False)
    assert len(kept()) == len(runs) + 1 <= CACHE_ENTRIES
