"""Property-based fuzzing of every route of the web station: no request gets a 5xx.

schemathesis draws requests from the station's OpenAPI description (``/api/openapi.json``),
both valid ones and ones that break it (wrong types, missing and unknown fields, out-of-range
ids, odd strings), with the station token (so that bodies get past the guard to their
validation) and without it (the guard's refusals). Hypothesis adds raw bodies of any bytes and
content type. The number of requests is fixed (``EXAMPLES`` per route and mode), so the run
stays bounded: a few seconds.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings, strategies as st
from hypothesis.errors import Unsatisfiable
from starlette.testclient import TestClient

from calstation import plugins
from calstation.storage.db import Campaign, CampaignRun, Run, open_database
from calstation.web.app import create_app

schemathesis = pytest.importorskip("schemathesis")
calstation_sim = pytest.importorskip("calstation_sim")
from calstation_sim import plugin as sim_plugin  # noqa: E402
from schemathesis import GenerationMode  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
TOKEN = "station-token-0123456789"
ORIGIN = "http://testserver"
EXAMPLES = 20
NOT_FUZZED = {"/events"}  # a stream stays open; test_web_security.py tests it
FUZZ = settings(max_examples=EXAMPLES, deadline=None, database=None,
                suppress_health_check=list(HealthCheck))


@pytest.fixture(scope="module")
def app(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    from calstation.recipes import load_recipe
    from calstation.station.runs import create_run

    folder = tmp_path_factory.mktemp("fuzz")
    (folder / "recipes").mkdir()
    db = open_database(f"sqlite:///{folder / 'fuzz.db'}")
    with plugins.isolated(sim_plugin):
        # one run in the database, so that some ids exist; no recipe to start another
        run_id = create_run(load_recipe(REPO / "recipes" / "sim-periodicity.yaml"), db,
                            operator="ann", unattended=True, data_dir=folder / "data",
                            serial="SN-1")
        with db.session() as s:
            run = s.get(Run, run_id)
            assert run is not None
            run.status = "passed"  # a passed run is never resumed: the fuzz moves no motor
            # a campaign over it, so that the campaign pages have one to show
            campaign = Campaign(key="0" * 64, selection={}, strategy=None, tolerance={},
                                engine="fuzz", selected=1)
            s.add(campaign)
            s.flush()
            s.add(CampaignRun(campaign_id=campaign.id, run_id=run_id, outcome="skipped",
                              error="static.mcap is missing"))
            campaign_id = campaign.id
        app = create_app(db, data_dir=folder / "data", recipes_dir=folder / "recipes",
                         token=TOKEN, allow_hosts=["testserver"])
        app.state.fuzz_ids = {"run_id": run_id, "campaign_id": campaign_id}
        yield app
    db.dispose()


def test_every_route_is_described_and_fuzzed(app: Any) -> None:
    """Every route of the app is in the OpenAPI description (so the fuzz reaches it)."""
    described = set(app.openapi()["paths"])
    routes = {r.path for r in app.routes if getattr(r, "include_in_schema", False)}
    assert routes <= described
    assert {"/api/start", "/api/answer", "/api/abort", "/api/resume/{run_id}", "/login",
            "/logout", "/runs/{run_id}", "/runs.json", "/compare", "/trends", "/metrics",
            "/plan", "/plan.json", "/api/plan", "/campaigns", "/campaigns.json",
            "/campaigns/{campaign_id}", "/campaigns/{campaign_id}.json"} <= described
    methods = {(m.upper(), path) for path, item in app.openapi()["paths"].items() for m in item}
    served = {(m, r.path) for r in app.routes if getattr(r, "include_in_schema", False)
              for m in getattr(r, "methods", ()) if m != "HEAD"}
    assert served == methods  # every method of every route, POST ones included


@pytest.mark.parametrize("mode", [GenerationMode.POSITIVE, GenerationMode.NEGATIVE])
@pytest.mark.parametrize("auth", ["token", "none"])
def test_schemathesis_finds_no_server_error(app: Any, mode: GenerationMode, auth: str,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    schema = schemathesis.openapi.from_asgi("/api/openapi.json", app)
    headers = {"Authorization": f"Bearer {TOKEN}"} if auth == "token" else {"Origin": ORIGIN}
    statuses: Counter[int] = Counter()
    per_route: dict[str, Counter[int]] = {}
    whole: list[str] = []
    operations = [r.ok() for r in schema.get_all_operations()]
    ids = app.state.fuzz_ids
    for operation in operations:
        if operation.path in NOT_FUZZED:
            continue

        @FUZZ
        @given(case=operation.as_strategy(generation_mode=mode), pin=st.booleans())
        def fuzz(case: Any, pin: bool) -> None:
            if pin:  # half the requests name the run and the campaign that exist
                for key in set(case.path_parameters or {}) & set(ids):
                    case.path_parameters[key] = ids[key]
            response = case.call(headers=headers)
            statuses[response.status_code] += 1
            per_route.setdefault(f"{case.method} {case.path}", Counter())[
                response.status_code] += 1
            assert response.status_code < 500, (case.method, case.formatted_path,
                                                response.status_code, response.text[:300])

        try:
            fuzz()
        except Unsatisfiable:  # a route without parameters has no invalid request
            assert mode == GenerationMode.NEGATIVE
            whole.append(f"{operation.method.upper()} {operation.path}")
    with capsys.disabled():
        print(f"\nfuzz ({mode}, {auth}): {sum(statuses.values())} requests over "
              f"{len(operations) - len(NOT_FUZZED)} routes: {dict(sorted(statuses.items()))}"
              + (f"; no invalid request to make of {', '.join(whole)}" if whole else ""))
        for route, counts in sorted(per_route.items()):
            print(f"  {route}: {dict(sorted(counts.items()))}")
    assert sum(statuses.values()) >= EXAMPLES  # it ran
    fuzzed = {f"{o.method.upper()} {o.path}" for o in operations if o.path not in NOT_FUZZED}
    assert set(per_route) == fuzzed - set(whole)  # every route and method got requests
    if mode == GenerationMode.POSITIVE and auth == "token":
        # valid requests reach the pages themselves, the plan and campaign pages included
        for route in ("GET /plan", "GET /plan.json", "GET /campaigns", "GET /campaigns.json",
                      "GET /campaigns/{campaign_id}", "GET /campaigns/{campaign_id}.json",
                      "GET /runs/{run_id}", "GET /runs/{run_id}.json", "GET /metrics"):
            assert per_route[route][200] > 0, (route, per_route[route])


PATHS = ["/api/start", "/api/answer", "/api/abort", "/api/resume/1", "/login", "/logout"]
TYPES = ["application/json", "application/json; charset=latin-1",
         "application/x-www-form-urlencoded", "text/plain", "multipart/form-data; boundary=x",
         "", "application/json; charset=utf-8"]


@settings(max_examples=150, deadline=None, database=None,
          suppress_health_check=list(HealthCheck))
@given(path=st.sampled_from(PATHS), ctype=st.sampled_from(TYPES),
       body=st.one_of(st.binary(max_size=300),
                      st.recursive(st.none() | st.booleans() | st.integers() | st.floats()
                                   | st.text(max_size=20),
                                   lambda c: st.lists(c, max_size=3)
                                   | st.dictionaries(st.sampled_from(
                                       ["prompt_id", "answer", "recipe", "operator", "serial",
                                        "token", "csrf", "x"]), c, max_size=4),
                                   max_leaves=8)),
       auth=st.booleans())
def test_raw_bodies_of_any_bytes_get_a_4xx_or_an_answer(
    app: Any, path: str, ctype: str, body: Any, auth: bool
) -> None:
    import json

    client = TestClient(app, base_url=ORIGIN)
    content = body if isinstance(body, bytes) else json.dumps(body).encode()
    headers = {"Content-Type": ctype, "Origin": ORIGIN}
    if auth:
        headers["Authorization"] = f"Bearer {TOKEN}"
    r = client.post(path, content=content, headers=headers)
    assert r.status_code < 500, (path, ctype, content[:80], r.status_code, r.text[:200])
    assert r.status_code in (200, 303) or 400 <= r.status_code < 500
