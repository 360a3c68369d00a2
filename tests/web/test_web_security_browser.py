"""The review's attacks, made by hostile pages in a real browser (Debian's chromium through
Playwright) against the station served by uvicorn on 127.0.0.1:

- a page on another port of the same host, which makes the operator's browser post to the
  station through a 307 redirect (``Origin: null``), with the station's real CSRF value and the
  operator logged in;
- a page that frames the station and lures a click onto its Start button;
- a page on a name that resolves to 127.0.0.1 (DNS rebinding, simulated with chromium's
  ``--host-resolver-rules``), which reads, starts, answers and aborts.

And the station's own pages under their Content-Security-Policy: drawn, with no violation.
Run with ``pytest -m browser``. Every server listens on 127.0.0.1 only.
"""

from __future__ import annotations

import http.server
import json
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import yaml

from calstation.storage.db import Database, Run
from calstation.web.app import create_app
from tests.support.station import StationTestPlugin, toy_recipe
from tests.support.webpage import FAILURES
from tests.support.webstation import CHROMIUM, CHROMIUM_ARGS, HANG_S, free_port, served, wait_until

playwright_api = pytest.importorskip("playwright.sync_api")
calstation_sim = pytest.importorskip("calstation_sim")

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(not Path(CHROMIUM).exists(),
                       reason=f"{CHROMIUM} missing: run scripts/system-deps.sh"),
]

TOKEN = "station-token-0123456789"
EVIL = "evil.test"

# records every Content-Security-Policy violation of a page, from its first script on
VIOLATIONS = """
window.__violations = [];
document.addEventListener("securitypolicyviolation", function (e) {
  window.__violations.push({directive: e.violatedDirective, blocked: e.blockedURI,
                            source: e.sourceFile, page: location.pathname,
                            sample: e.sample, at: e.lineNumber + ":" + e.columnNumber});
});
"""


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    with playwright_api.sync_playwright() as p:
        # evil.test resolves to 127.0.0.1, as after a DNS rebinding; nothing else changes
        b = p.chromium.launch(executable_path=CHROMIUM, args=[
            *CHROMIUM_ARGS, f"--host-resolver-rules=MAP {EVIL} 127.0.0.1"])
        yield b
        b.close()


@pytest.fixture
def page(browser: Any, request: pytest.FixtureRequest) -> Iterator[Any]:
    context = browser.new_context(viewport={"width": 1200, "height": 860})
    context.add_init_script(VIOLATIONS)
    pg = context.new_page()
    pg.set_default_timeout(HANG_S * 1000)  # a hang guard: waits end at their event
    pg.on("dialog", lambda d: d.accept())
    failed_before = request.session.testsfailed
    yield pg
    if request.session.testsfailed > failed_before:
        FAILURES.mkdir(parents=True, exist_ok=True)
        pg.screenshot(path=str(FAILURES / f"{request.node.name}.png"), full_page=True)
    context.close()


@contextmanager
def station(tmp_path: Path, db: Database, port: int | None = None, paced: bool = False,
            **kwargs: Any) -> Iterator[str]:
    """The web station on the lean recipe; ``paced``: the simulator on the host's clock and a
    3 s spin scan, time for the page to draw its live line (unpaced, the scan can end before
    a loaded machine's page has drawn a line)."""
    (tmp_path / "recipes").mkdir(exist_ok=True)
    recipe = toy_recipe(tmp_path / "recipes")
    if paced:
        data = yaml.safe_load(recipe.read_text())
        for device in ("lidar", "turntable", "encoder"):
            data["station"][device]["settings"] = {
                **data["station"][device].get("settings", {}), "real_time": True}
        data["steps"]["spin_scan"]["rpm"] = 20
        recipe.write_text(yaml.safe_dump(data, sort_keys=False))
    app = create_app(db, data_dir=tmp_path / "data", recipes_dir=tmp_path / "recipes", **kwargs)
    with served(app, port=port) as url:
        yield url


Handler = Callable[[http.server.BaseHTTPRequestHandler], None]


@contextmanager
def attacker(routes: dict[str, Handler], port: int = 0) -> Iterator[str]:
    """A web server of the attacker on another port of 127.0.0.1; yields its base URL."""

    class Site(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            self._route()

        def do_POST(self) -> None:
            self.rfile.read(int(self.headers.get("content-length") or 0))
            self._route()

        def _route(self) -> None:
            handler = routes.get(self.path.split("?")[0])
            if handler is None:
                self.send_error(404)
            else:
                handler(self)

        def log_message(self, *args: Any) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", port), Site)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()
        thread.join(10)


def html(body: str) -> Handler:
    def handler(h: http.server.BaseHTTPRequestHandler) -> None:
        data = body.encode()
        h.send_response(200)
        h.send_header("Content-Type", "text/html; charset=utf-8")
        h.send_header("Content-Length", str(len(data)))
        h.end_headers()
        h.wfile.write(data)
    return handler


def redirect(location: str) -> Handler:
    def handler(h: http.server.BaseHTTPRequestHandler) -> None:
        h.send_response(307)
        h.send_header("Location", location)
        h.send_header("Content-Length", "0")
        h.end_headers()
    return handler


def runs(db: Database) -> int:
    with db.session() as s:
        return s.query(Run).count()


def station_log(caplog: pytest.LogCaptureFixture) -> str:
    return "\n".join(r.getMessage() for r in caplog.records if r.name == "calstation.web")


def csrf_value(page: Any) -> str:
    return str(page.locator('meta[name="csrf-token"]').get_attribute("content"))


@pytest.mark.parametrize("token", [None, TOKEN], ids=["default", "token-logged-in"])
def test_a_page_on_another_port_cannot_post_through_a_307_redirect(
    tmp_path: Path, db: Database, page: Any, station_plugin: StationTestPlugin,
    caplog: pytest.LogCaptureFixture, token: str | None,
) -> None:
    caplog.set_level("WARNING", logger="calstation.web")
    with station(tmp_path, db, token=token) as url:
        page.goto(url + "/")
        if token:
            page.goto(url + "/login")
            page.fill('input[name="token"]', TOKEN)
            page.click('button[type="submit"]')
            page.wait_for_url(url + "/")
            assert page.locator("#logout-button").count() == 1
        # the strongest attacker: it even knows this session's CSRF value
        csrf = csrf_value(page)
        attack = f"""<!doctype html><p id="cookies"></p>
<form id="f" method="post" action="/redirect">
  <input name="recipe" value="lean.yaml"><input name="operator" value="mallory">
  <input name="csrf" value="{csrf}"></form>
<script>
  document.getElementById("cookies").textContent = "cookies:" + document.cookie;
  var body = new URLSearchParams({{recipe: "lean.yaml", operator: "mallory", csrf: "{csrf}"}});
  fetch("/redirect", {{method: "POST", body: body, mode: "no-cors", credentials: "include"}})
    .finally(function () {{ document.getElementById("f").submit(); }});
</script>"""
        with attacker({"/attack.html": html(attack),
                       "/redirect": redirect(url + "/api/start")}) as evil:
            page.goto(evil + "/attack.html")
            # the form's redirect lands on the station's refusal
            page.wait_for_url(url + "/api/start")
            answer = json.loads(page.inner_text("body"))
        assert "Origin: null" in answer["error"], answer
        wait_until(lambda: station_log(caplog).count("Origin: null") >= 2)
        # a page of another port shares the cookie jar, but the session cookie is not for
        # scripts
        assert runs(db) == 0 and station_plugin.motor_calls == []
        log = station_log(caplog)
        assert "refused POST /api/start from 127.0.0.1: 403 cross-site request refused " \
               "(Origin: null" in log


def test_a_page_cannot_frame_the_station(
    tmp_path: Path, db: Database, page: Any, station_plugin: StationTestPlugin,
) -> None:
    with station(tmp_path, db) as url:
        page.goto(url + "/")  # the operator has the station open: a session
        messages: list[str] = []
        page.on("console", lambda m: messages.append(m.text))
        frame_page = f"""<!doctype html><h1>Win a prize: click the green button!</h1>
<iframe id="f" src="{url}/" width="1100" height="700" style="opacity:0.01"></iframe>"""
        with attacker({"/frame.html": html(frame_page)}) as evil:
            page.goto(evil + "/frame.html")
            page.wait_for_timeout(1500)
            frame = page.frame_locator("#f")
            # the station is not rendered inside: no Start button to click
            assert frame.locator("#start-button").count() == 0
            page.mouse.click(300, 400)
            page.mouse.click(120, 330)
        # chromium says why it showed nothing
        assert any("frame-ancestors 'none'" in m for m in messages), messages
        assert runs(db) == 0 and station_plugin.motor_calls == []


REBINDING_ATTACK = """<!doctype html><pre id="out">waiting</pre><script>
window.go = async function () {
  var out = {};
  async function call(method, path, body) {
    try {
      var r = await fetch(path, method === "GET" ? {} : {
        method: "POST", headers: {"Content-Type": "application/json"},
        body: JSON.stringify(body)});
      out[method + " " + path] = r.status;
    } catch (e) { out[method + " " + path] = "error " + e; }
  }
  await call("GET", "/state.json");
  await call("GET", "/");
  await call("POST", "/api/start", {recipe: "lean.yaml", operator: "mallory"});
  await call("POST", "/api/answer", {prompt_id: 1, answer: "continue"});
  await call("POST", "/api/abort", {});
  document.getElementById("out").textContent = JSON.stringify(out);
};
</script>"""


def test_a_rebound_name_cannot_read_start_answer_or_abort(
    tmp_path: Path, db: Database, page: Any, station_plugin: StationTestPlugin,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """DNS rebinding: the attacker's page is served from evil.test:PORT; then the name (here:
    the port's server) changes to the station, and the page's requests, same-origin for the
    browser, reach the station."""
    caplog.set_level("WARNING", logger="calstation.web")

    def no_keep_alive(h: http.server.BaseHTTPRequestHandler) -> None:
        h.close_connection = True
        html(REBINDING_ATTACK)(h)

    port = free_port()
    evil_page = page.context.new_page()
    with attacker({"/attack.html": no_keep_alive}, port=port):
        evil_page.goto(f"http://{EVIL}:{port}/attack.html")
        evil_page.wait_for_function("typeof window.go === 'function'")
    with station(tmp_path, db, port=port) as url:
        # the operator's run waits at its first placement, as the review found it
        page.goto(url + "/")
        page.select_option("#recipe", "lean.yaml")
        page.fill("#operator", "ann")  # no default operator before a first run
        page.click("#start-button")
        page.wait_for_selector('#prompt:not([hidden])[data-kind="fixture"]')
        evil_page.evaluate("window.go()")
        evil_page.wait_for_function("document.getElementById('out').textContent !== 'waiting'")
        results = json.loads(evil_page.inner_text("#out"))
        assert results == {"GET /state.json": 400, "GET /": 400, "POST /api/start": 400,
                           "POST /api/answer": 400, "POST /api/abort": 400}, results
        # the run still waits at its prompt; nothing was answered or aborted
        state = json.loads(page.evaluate("fetch('/state.json').then(r => r.text())"))
        assert state["busy"] and state["prompt"]["kind"] == "fixture"
        assert state["prompt"]["id"] == 1 and state["abort_requested"] is None
        assert runs(db) == 1 and "emergency_stop" not in station_plugin.motor_calls
        assert f"Host '{EVIL}:{port}' is not a name of this station" in station_log(caplog)
        page.click("#abort-button")
        page.wait_for_selector("#verdict")


def test_the_stations_pages_draw_under_their_policy(
    tmp_path: Path, db: Database, page: Any, station_plugin: StationTestPlugin,
) -> None:
    """The Content-Security-Policy blocks nothing the station needs: the operator page's live
    plot, the trend plot, the report's 3D views (served and as the sandboxed file), the QA
    dashboard."""
    # a stall names the selector it waited on, well before the suite's hang guard
    page.set_default_timeout(120_000)
    with station(tmp_path, db, paced=True) as url:
        page.goto(url + "/")
        page.select_option("#recipe", "lean.yaml")
        page.fill("#operator", "ann")  # no default operator before a first run
        page.click("#start-button")
        for fixture in ("static_target", "spin_target"):
            page.wait_for_selector(f'#prompt:not([hidden])[data-fixture="{fixture}"]')
            page.click('#prompt button[data-answer="continue"]:not([hidden])')
        # drawn during the spin scan, kept (hidden) once the station waits for the cube
        page.wait_for_selector("#line-plot[data-drawn]", state="attached")
        violations = page.evaluate("window.__violations")
        page.wait_for_selector('#prompt:not([hidden])[data-fixture="qa_cube"]')
        page.click('#prompt button[data-answer="continue"]:not([hidden])')
        # a passed run: the trend plot draws accepted calibrations only
        assert page.wait_for_selector("#verdict").inner_text() == "PASS", \
            page.inner_text("#result")
        run_id = max(int(x) for x in [page.inner_text("#run-id")])
        checks = {f"/runs/{run_id}": ".view3d[data-drawn]",
                  f"/runs/{run_id}/report.html": ".view3d[data-drawn]",
                  "/trends?station=sim-test&param=tx": "#trend-plot[data-drawn]",
                  "/runs": "#history", "/login": "form",
                  "/dashboard": "body[data-figures-drawn]"}
        for path, selector in checks.items():
            page.goto(url + path)
            page.wait_for_selector(selector)
            violations += page.evaluate("window.__violations")
        # what plotly tries and the policy refuses, without loss: its bundle injects MapLibre's
        # stylesheet at load (the station draws no map), and a colour bar clears its cells'
        # style attribute (style="")
        plotly = ("/static/plotly.min.js", "/report.html")
        unexpected = [v for v in violations if not (
            v["source"].endswith(plotly) and (
                v["directive"] == "style-src-elem"
                or (v["directive"] == "style-src-attr" and v["sample"] == "")))]
        assert unexpected == [], json.dumps(unexpected)
        # one stylesheet per page with plotly; the report's colour bars (drawn, then again in
        # the pictures it makes for print) 8 times on each of its two pages
        assert len(violations) <= 22


def test_a_link_from_another_site_keeps_the_operator_logged_in(
    tmp_path: Path, db: Database, page: Any, station_plugin: StationTestPlugin,
) -> None:
    """SameSite=Strict keeps the session cookie home on a link from another site: the page
    reloads itself rather than hand out a new session over the operator's."""
    with station(tmp_path, db, token=TOKEN) as url:
        page.goto(url + "/login")
        page.fill('input[name="token"]', TOKEN)
        page.click('button[type="submit"]')
        page.wait_for_url(url + "/")
        link = f'<!doctype html><a id="go" href="{url}/">the station</a>'
        # another site, not another port of this one: evil.test
        with attacker({"/link.html": html(link)}) as evil:
            page.goto(evil.replace("127.0.0.1", EVIL) + "/link.html")
            page.click("#go")
            page.wait_for_selector("#start-button")
        assert page.locator("#logout-button").count() == 1
        page.select_option("#recipe", "lean.yaml")
        page.fill("#operator", "ann")  # no default operator before a first run
        page.click("#start-button")
        page.wait_for_selector('#prompt:not([hidden])[data-kind="fixture"]')
        page.click("#abort-button")
        page.wait_for_selector("#verdict")
        assert runs(db) == 1
