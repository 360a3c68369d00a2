"""The web station's HTTP API and pages through FastAPI's test client, on the simulated station.

The station is the real one (simulated drivers, wrapped to observe motor commands; the stand-in
fine-tuning strategy of tests/support/station.py), run by the web station's runner in its
background thread, exactly as ``calstation serve`` runs it.
"""

from __future__ import annotations

import re
import threading
from pathlib import Path
from typing import Any

import pytest

from calstation.errors import CalstationError
from calstation.storage.db import Database, Run
from calstation.storage.report import export_calibration, get_run
from calstation.web.placement import SIZE, placement_svg
from tests.support.station import StationTestPlugin, toy_recipe
from tests.support.webapi import ORIGIN, TOKEN, csrf_of, finish, make_client, wait_prompt
from tests.support.webstation import run_status, steps_of, wait_live, wait_until

calstation_sim = pytest.importorskip("calstation_sim")


def test_a_run_from_the_api_to_its_report(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    with make_client(tmp_path, db) as client:
        headers = csrf_of(client)
        r = client.post("/api/start", headers=headers,
                        json={"recipe": "lean.yaml", "operator": "ann", "serial": "SN-0042"})
        assert r.status_code == 201, r.text
        run_id = r.json()["run_id"]
        prompt = wait_prompt(client)
        assert prompt["fixture"] == "static_target" and prompt["answers"] == ["continue", "abort"]
        assert "<svg" in prompt["svg"] and "the scan line" in prompt["svg"]
        final = finish(client, headers)
        status = run_status(db, run_id)
        assert final["status"] == status and status in ("passed", "failed")
        # the verdict is the cube check's; every step itself passed
        assert [s[2] for s in steps_of(db, run_id)] == ["passed"] * 9
        # the end screen: every measured value beside its limit
        result = final["result"]
        assert result["verdict"] == {"passed": "PASS", "failed": "FAIL"}[status]
        names = [row["name"] for row in result["cube_rows"]]
        assert "side-face twist |δ| (ry check)" in names  # beside the other cube figures
        assert "face-fit edge error" in names and all(
            row["limit"] is not None for row in result["cube_rows"]
            if row["name"] != "face flatness (RMS, range noise included)")
        assert result["serial"] == "SN-0042"
        # every step's time and the run's, in the operator's words
        assert [r["title"] for r in result["steps"]][:3] == [
            "preflight check", "place the L-shaped static target",
            "static scan and initial calibration"]
        assert all(r["seconds"] is not None and r["seconds"] >= 0 for r in result["steps"])
        assert result["elapsed_s"] >= sum(r["seconds"] for r in result["steps"]) * 0.99
        # rx, the gauge, is said to be not estimated rather than shown as 0.000
        assert all("rx" in c["not_estimated"] for c in result["calibrations"])
        initial = next(c for c in result["calibrations"] if c["stage"] == "initial")
        assert "ry" in initial["not_estimated"] and initial["label"] == (
            "initial, from the L-target")
        page = client.get("/").text
        assert "not estimated" in page and 'id="step-times"' in page and "SN-0042" in page
        # every step went through the page's live state
        assert [s["status"] for s in final["steps"]] == ["passed"] * 9
        # report.html in the run folder, also served
        with db.session() as s:
            folder = Path(get_run(s, run_id).data_dir)
            urdf = export_calibration(get_run(s, run_id), "urdf")
        report = (folder / "report.html").read_text()
        # plotly.js once, beside the run folders; the file loads it from there
        from calstation.storage.report_html import plotly_file_name, plotly_js

        beside = folder.parent / plotly_file_name()
        assert beside.read_text() == plotly_js()
        assert f'<script src="../{plotly_file_name()}"></script>' in report
        assert "SN-0042" in report and len(report.encode()) < 1_500_000
        # served sandboxed, it can load nothing: plotly.js is inlined
        served = client.get(f"/runs/{run_id}/report.html").text
        assert plotly_js() in served and "<script src=" not in served
        assert served.replace("<script>" + plotly_js() + "</script>",
                              f'<script src="../{plotly_file_name()}"></script>') == report
        page = client.get(f"/runs/{run_id}")
        assert page.status_code == 200 and "/static/plotly.min.js" in page.text
        data = client.get(f"/runs/{run_id}.json").json()
        assert data["run"]["id"] == run_id and data["cube_rows"] == result["cube_rows"]
        assert client.get(f"/runs/{run_id}/export.urdf").text == urdf
        ann = client.get("/runs.json", params={"operator": "ann"}).json()["runs"]
        assert ann[0]["id"] == run_id
        assert client.get("/runs.json", params={"operator": "bob"}).json()["runs"] == []
        assert client.get("/runs.json", params={"serial": "SN-0042"}).json()["runs"][0]["id"] == (
            run_id)
        assert client.get("/runs", params={"status": "nonsense"}).status_code == 400
        js = client.get("/static/plotly.min.js")
        assert js.status_code == 200 and len(js.content) > 1_000_000


def test_state_changes_need_the_pages_csrf_value(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    with make_client(tmp_path, db) as client:
        headers = csrf_of(client)
        body = {"recipe": "lean.yaml", "operator": "ann"}
        assert client.post("/api/start", json=body).status_code == 403
        assert client.post("/api/start", json=body,
                           headers={"X-CSRF-Token": "forged"}).status_code == 403
        r = client.post("/api/start", json=body,
                        headers={**headers, "Origin": "http://evil.example"})
        assert r.status_code == 403 and "cross-site" in r.json()["error"]
        # a plain HTML form post (no script) carries the value as a field
        form = {**body, "csrf": "forged"}
        assert client.post("/api/start", data=form).status_code == 403
        with db.session() as s:
            assert s.query(Run).count() == 0
        assert station_plugin.motor_calls == []


def test_a_non_local_station_needs_its_token(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    with pytest.raises(CalstationError, match="needs a station token"):
        make_client(tmp_path, db, host="0.0.0.0")
    with make_client(tmp_path, db, host="0.0.0.0", token=TOKEN) as client:
        headers = csrf_of(client)
        body = {"recipe": "lean.yaml", "operator": "ann"}
        # read-only pages stay open
        assert client.get("/runs").status_code == 200
        assert client.get("/state.json").status_code == 200
        # without the token (even with a valid CSRF value) nothing starts or aborts
        assert client.post("/api/start", json=body, headers=headers).status_code == 401
        assert client.post("/api/abort", headers=headers).status_code == 401
        wrong = {"Authorization": "Bearer not-the-token-at-all"}
        assert client.post("/api/start", json=body, headers=wrong).status_code == 401
        with db.session() as s:
            assert s.query(Run).count() == 0
        assert station_plugin.motor_calls == []
        # the login page gives a browser its session; wrong tokens are refused
        origin = {"Origin": ORIGIN}
        assert client.post("/login", data={"token": "nope", "csrf": headers["X-CSRF-Token"]},
                           headers=origin).status_code == 401
        before = client.cookies["calstation_session"]
        r = client.post("/login", data={"token": TOKEN, "csrf": headers["X-CSRF-Token"]},
                        headers=origin, follow_redirects=False)
        # a new session id at login (the one before could have been planted)
        assert r.status_code == 303 and client.cookies["calstation_session"] != before
        headers = csrf_of(client)  # the new session's CSRF value
        r = client.post("/api/start", json=body, headers=headers)
        assert r.status_code == 201, r.text
        run_id = r.json()["run_id"]
        wait_prompt(client)
        assert client.post("/api/abort", headers=headers).status_code == 200
        wait_live(client, lambda s: not s["busy"])
        assert run_status(db, run_id) == "aborted"
    # a script with the token needs no cookie and no CSRF value
    with make_client(tmp_path, db, host="0.0.0.0", token=TOKEN) as script:
        auth = {"Authorization": f"Bearer {TOKEN}"}
        r = script.post("/api/start", json=body, headers=auth)
        assert r.status_code == 201, r.text
        wait_prompt(script)
        assert script.post("/api/abort", headers=auth).status_code == 200
        wait_live(script, lambda s: not s["busy"])


def test_two_starts_at_once_start_exactly_one_run(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    with make_client(tmp_path, db) as client:
        headers = csrf_of(client)
        barrier = threading.Barrier(2)
        codes: list[int] = []
        messages: list[str] = []

        def start(name: str) -> None:
            barrier.wait()
            r = client.post("/api/start", headers=headers,
                            json={"recipe": "lean.yaml", "operator": name})
            codes.append(r.status_code)
            messages.append(r.text)

        threads = [threading.Thread(target=start, args=(n,)) for n in ("ann", "bob")]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert sorted(codes) == [201, 409], messages
        assert any("in progress on this station" in m for m in messages)
        with db.session() as s:
            assert s.query(Run).count() == 1
        wait_prompt(client)
        client.post("/api/abort", headers=headers)
        wait_live(client, lambda s: not s["busy"])


def test_prompts_answers_and_abort(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    with make_client(tmp_path, db) as client:
        headers = csrf_of(client)
        assert client.post("/api/abort", headers=headers).status_code == 409  # nothing runs
        r = client.post("/api/start", headers=headers,
                        json={"recipe": "missing.yaml", "operator": "ann"})
        assert r.status_code == 400 and "lean.yaml" in r.json()["error"]
        r = client.post("/api/start", headers=headers, json={"recipe": "lean.yaml", "operator": ""})
        assert r.status_code == 422 and "operator" in r.json()["error"]
        run_id = client.post("/api/start", headers=headers,
                             json={"recipe": "lean.yaml", "operator": "ann"}).json()["run_id"]
        prompt = wait_prompt(client)
        stale = client.post("/api/answer", headers=headers,
                            json={"prompt_id": prompt["id"] + 1, "answer": "continue"})
        assert stale.status_code == 409 and "not pending" in stale.json()["error"]
        wrong = client.post("/api/answer", headers=headers,
                            json={"prompt_id": prompt["id"], "answer": "retry"})
        assert wrong.status_code == 409
        # reloading the page shows the same prompt
        page = client.get("/")
        assert "Place the L-shaped static target" in page.text and 'class="placement"' in page.text
        assert client.get("/state.json").json()["prompt"]["id"] == prompt["id"]
        client.post("/api/answer", headers=headers,
                    json={"prompt_id": prompt["id"], "answer": "continue"})
        wait_prompt(client)  # the spin target
        assert client.post("/api/abort", headers=headers).status_code == 200
        st = wait_live(client, lambda s: s if not s["busy"] else None)
        assert st["status"] == "aborted" and st["result"]["verdict"] == "ABORTED"
        assert run_status(db, run_id) == "aborted"
        assert steps_of(db, run_id)[-1] == ("place_spin_target", 1, "aborted")
        assert station_plugin.motor_calls[-2:] == ["emergency_stop", "stop"]


def test_failed_step_offers_retry_and_the_retry_runs_it_again(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    station_plugin.strategy.failures = 1
    with make_client(tmp_path, db) as client:
        headers = csrf_of(client)
        run_id = client.post("/api/start", headers=headers,
                             json={"recipe": "lean.yaml", "operator": "ann"}).json()["run_id"]
        while (p := wait_prompt(client))["kind"] == "fixture" and p["fixture"] != "qa_cube":
            client.post("/api/answer", headers=headers, json={"prompt_id": p["id"],
                                                              "answer": "continue"})
            if p["fixture"] == "spin_target":
                break
        failure = wait_prompt(client, "failure")
        assert failure["step"] == "fine_tune" and "scripted failure" in failure["error"]
        assert failure["answers"] == ["retry", "abort"]
        client.post("/api/answer", headers=headers, json={"prompt_id": failure["id"],
                                                          "answer": "retry"})
        # a fine-tuning is retried from the spin target's placement: re-place, re-scan, re-fit
        again = wait_prompt(client, "fixture")
        assert again["fixture"] == "spin_target"
        client.post("/api/answer", headers=headers, json={"prompt_id": again["id"],
                                                          "answer": "continue"})
        cube = wait_prompt(client, "fixture")
        assert cube["fixture"] == "qa_cube"
        client.post("/api/answer", headers=headers, json={"prompt_id": cube["id"],
                                                          "answer": "abort"})
        wait_live(client, lambda s: not s["busy"])
        steps = steps_of(db, run_id)
        assert ("fine_tune", 1, "failed") in steps and ("fine_tune", 2, "passed") in steps
        assert ("spin_scan", 2, "passed") in steps


def test_trends_and_compare_pages(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    with make_client(tmp_path, db) as client:
        headers = csrf_of(client)
        ids = []
        for _ in range(2):
            r = client.post("/api/start", headers=headers,
                            json={"recipe": "lean.yaml", "operator": "ann"})
            ids.append(r.json()["run_id"])
            finish(client, headers)
        both = client.get("/compare.json", params={"a": ids[0], "b": ids[1]}).json()
        tx = next(r for r in both["rows"] if r["name"] == "tx")
        assert tx["diff"] == pytest.approx(tx["b"] - tx["a"])
        assert client.get("/compare", params={"a": ids[0], "b": ids[1]}).status_code == 200
        assert client.get("/compare", params={"a": "x", "b": "1"}).status_code == 422
        trend = client.get("/trends.json", params={"station": "sim-test", "param": "tx"}).json()
        accepted = [p["run_id"] for p in trend["points"]]
        with db.session() as s:
            passed = [r.id for r in s.query(Run).filter_by(status="passed").order_by(Run.id)]
        assert accepted == passed
        assert client.get("/trends", params={"station": "sim-test", "param": "tz"}
                          ).status_code == 200
        assert client.get("/trends.json", params={"param": "bogus"}).status_code == 400


def test_placement_picture_follows_the_recipe_geometry(tmp_path: Path) -> None:
    from calstation.recipes import CubeGeometry, LTargetGeometry

    svg = placement_svg(0.2925, LTargetGeometry(), "place the static target")
    # seen from above with the lidar at the bottom, +Z_P points left: the tall end (z = −w/2)
    # is drawn right of the centre
    import re

    marks = re.findall(r'<circle cx="([\d.]+)" cy="([\d.]+)" r="4"[^>]*/><text[^>]*'
                       r'data-label="([^"]+)"', svg)
    x = {label.split()[0]: float(cx) for cx, _, label in marks}
    assert x["tall"] > SIZE / 2 > x["short"]
    # the labels sit in the legend under the platter, none over the drawing
    legend = re.findall(r'<text x="6" y="([\d.]+)"[^>]*class="legend">([^<]+)<', svg)
    assert all(float(y) > SIZE for y, _ in legend)
    assert any(re.search(r"\d  tall end \d+ mm", text) for _, text in legend)
    assert len({y for y, _ in legend}) == len(legend)  # one line each: no two overlap
    # an off-centre spin target: its offset from the axis is dimensioned
    from calstation.recipes import FrustumGeometry

    spin = placement_svg(0.2925, FrustumGeometry(offset=(0.0, 0.06)), "spin")
    assert re.search(r'class="offset-label">60 mm<', spin)
    assert 'class="offset-dimension"' in spin and "60 mm from the axis" in spin
    cube = placement_svg(0.2925, CubeGeometry(edge=0.1, offset=(0.0, 0.0), yaw_deg=45.0), "cube")
    pts = re.search(r'<polygon points="([^"]+)" fill="#fff8c5"', cube)
    assert pts is not None
    corners = [tuple(map(float, p.split(","))) for p in pts.group(1).split()]
    # a 45° cube has its corners on the axes: one straight above the centre
    assert min(abs(cx - SIZE / 2) for cx, _ in corners) < 0.2


def test_a_run_left_running_by_a_stopped_server_is_resumed_from_the_page(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    from calstation.recipes import load_recipe
    from calstation.station.runs import create_run

    with make_client(tmp_path, db) as client:
        # a run the server created and then lost (killed before any step finished)
        run_id = create_run(load_recipe(tmp_path / "recipes" / "lean.yaml"), db, operator="ann",
                            unattended=False, data_dir=tmp_path / "data")
        headers = csrf_of(client)
        page = client.get("/")
        assert f'action="/api/resume/{run_id}"' in page.text
        r = client.post(f"/api/resume/{run_id}", headers=headers)
        assert r.status_code == 201, r.text
        assert client.post(f"/api/resume/{run_id}", headers=headers).status_code == 409
        final = finish(client, headers)
        assert final["run_id"] == run_id and final["status"] == run_status(db, run_id)
        assert [s[0] for s in steps_of(db, run_id)][:2] == ["preflight", "place_static_target"]
        assert f'action="/api/resume/{run_id}"' not in client.get("/").text
        with db.session() as s:
            run = s.get(Run, run_id)
            assert run is not None
            run.status = "passed"  # whatever its cube said: a passed run is never resumed
        r = client.post(f"/api/resume/{run_id}", headers=headers)
        assert r.status_code == 400 and "already passed" in r.json()["error"]


def test_calstation_serve_prints_its_address_and_serves(tmp_path: Path) -> None:
    import os
    import signal
    import subprocess
    import sys

    import httpx

    from tests.support.webstation import free_port

    port = free_port()
    (tmp_path / "recipes").mkdir()
    toy_recipe(tmp_path / "recipes")
    env = {**os.environ, "CALSTATION_HOME": str(tmp_path / "home")}
    env.pop("CALSTATION_TOKEN", None)
    proc = subprocess.Popen(
        [sys.executable, "-c", "from calstation.cli import main; main()", "serve",
         "--port", str(port), "--recipes", str(tmp_path / "recipes"),
         "--db", f"sqlite:///{tmp_path / 'serve.db'}"],
        env=env, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()
        assert f"http://127.0.0.1:{port}/" in line
        state = wait_until(lambda: _get(httpx, f"http://127.0.0.1:{port}/state.json"))
        assert state["status"] == "idle" and state["recipes"] == ["lean.yaml"]
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)
    # a network address without a token: refused before listening
    bad = subprocess.run(
        [sys.executable, "-c", "from calstation.cli import main; main()", "serve",
         "--host", "0.0.0.0", "--port", str(port), "--db", f"sqlite:///{tmp_path / 'serve.db'}"],
        env=env, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "needs a station token" in bad.stderr


def _get(httpx: Any, url: str) -> Any:
    try:
        return httpx.get(url, timeout=2).json()
    except httpx.HTTPError:
        return None


def test_a_template_recipe_is_listed_but_cannot_be_started(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin
) -> None:
    import shutil

    recipes = tmp_path / "recipes"
    recipes.mkdir()
    shutil.copy(Path(__file__).resolve().parents[2] / "recipes" / "real-station-template.yaml",
                recipes)
    (recipes / "broken.yaml").write_text("name: broken\nstation: 3\n")
    with make_client(tmp_path, db) as client:
        page = client.get("/").text
        assert re.search(r'<option value="lean.yaml"[^>]* selected>', page)
        assert "real-station-template.yaml</option>" not in page  # not offered
        assert re.search(r"<li><b>real-station-template.yaml</b>: it is a template", page)
        assert re.search(r"<li><b>broken.yaml</b>: it does not validate", page)
        r = client.post("/api/start", headers=csrf_of(client),
                        json={"recipe": "real-station-template.yaml", "operator": "ann"})
        assert r.status_code == 400, r.text
        assert "recipe real-station-template.yaml cannot run: it is a template" in r.json()[
            "error"]
        with db.session() as s:
            assert s.query(Run).count() == 0


def test_the_live_line_is_zoomed_on_the_platter_not_the_room() -> None:
    import numpy as np

    from calstation.web.live import zoom_window

    # a line of the static scan: the target on the platter 1.1–1.4 m away, the floor and a wall
    # 3–4 m behind it
    alpha = np.radians(np.linspace(-30, 30, 400))
    rho = np.where(np.abs(alpha) < np.radians(8), 1250.0 + 150 * np.sin(5 * alpha), 3800.0)
    x, y = rho * np.sin(alpha), rho * np.cos(alpha)
    window = zoom_window(x, y, platter_m=0.585)
    assert window is not None
    assert window["y"][0] < 1150 and 1340 < window["y"][1] < 2000  # the wall is left out
    assert window["x"][1] - window["x"][0] < 800  # not the ±2 m the whole line spans
    assert zoom_window([], [], 0.585) is None
