"""The web station against hostile pages and a hostile network, through the ASGI app (FastAPI's
test client, and raw ASGI calls where the client cannot say what an attacker would).

One test per finding of the security review (docs/security.md): each attack is refused, with
its reason logged, and nothing starts, answers or aborts a run. The same attacks against a real
uvicorn server are in ``test_web_security_server.py``, and in a real browser in
``test_web_security_browser.py``.
"""

from __future__ import annotations

import asyncio
import html.parser
import json
import re
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient

from calstation.storage.db import Database, Run
from calstation.web.app import create_app
from calstation.web.hosts import HostPolicy, parse_host
from calstation.web.settings import WebLimits
from tests.support.station import StationTestPlugin
from tests.support.webapi import ORIGIN, TOKEN, csrf_of, make_client, wait_prompt
from tests.support.webstation import wait_until

calstation_sim = pytest.importorskip("calstation_sim")

OTHER_PORT = "http://127.0.0.1:9999"


class Clock:
    """A clock the test moves (sessions, throttle)."""

    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def runs(db: Database) -> int:
    with db.session() as s:
        return s.query(Run).count()


def refusals(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if r.name == "calstation.web" and r.getMessage().startswith("refused")]


def assert_refused(caplog: pytest.LogCaptureFixture, status: int, reason: str) -> None:
    """The last refusal logged has ``status`` and a reason containing ``reason``."""
    logged = refusals(caplog)
    assert logged, "no refusal was logged"
    assert f": {status} " in logged[-1] and reason in logged[-1], logged[-1]


def start_body(recipe: str = "lean.yaml", **extra: Any) -> dict[str, Any]:
    return {"recipe": recipe, "operator": "ann", **extra}


# --- CSRF ------------------------------------------------------------------------------------
@pytest.mark.parametrize("token", [None, TOKEN], ids=["default", "token"])
def test_a_post_after_a_cross_origin_redirect_is_refused(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin,
    caplog: pytest.LogCaptureFixture, token: str | None,
) -> None:
    """The review's attack: a page on another port makes the operator's browser post through a
    307 redirect, which arrives with ``Origin: null`` and the browser's cookies, on the default
    server and on a token-protected one with the operator logged in."""
    with make_client(tmp_path, db, token=token) as client:
        headers = csrf_of(client)
        if token:
            assert client.post("/login", data={"token": TOKEN, "csrf": headers["X-CSRF-Token"]},
                               headers={"Origin": ORIGIN}).status_code == 200
            headers = csrf_of(client)
        for origin in ("null", OTHER_PORT, "http://evil.test:8470", "https://127.0.0.1:8470"):
            r = client.post("/api/start", json=start_body(), headers={**headers, "Origin": origin})
            assert r.status_code == 403, (origin, r.text)
            assert_refused(caplog, 403, "Origin: null" if origin == "null" else origin)
        # a plain form, as the redirect re-posts it: the page's field, the browser's cookies
        form = {**start_body(), "csrf": headers["X-CSRF-Token"]}
        r = client.post("/api/start", data=form, headers={"Origin": "null"})
        assert r.status_code == 403
        assert runs(db) == 0 and station_plugin.motor_calls == []


def test_origin_or_referer_is_required_and_must_be_the_station(
    tmp_path: Path, db: Database, caplog: pytest.LogCaptureFixture
) -> None:
    with make_client(tmp_path, db) as client:
        headers = csrf_of(client)
        csrf = {"X-CSRF-Token": headers["X-CSRF-Token"]}
        # neither Origin nor Referer: a cookie-authenticated request that proves nothing
        assert client.post("/api/abort", headers=csrf).status_code == 403
        assert_refused(caplog, 403, "neither Origin nor Referer")
        r = client.post("/api/abort", headers={**csrf, "Referer": OTHER_PORT + "/attack.html"})
        assert r.status_code == 403
        # the station's own Referer, or Origin, passes the check (then: nothing runs, 409)
        r = client.post("/api/abort", headers={**csrf, "Referer": ORIGIN + "/"})
        assert r.status_code == 409
        assert client.post("/api/abort", headers=headers).status_code == 409
        # a browser that says the request is cross-site is believed, whatever its Origin
        for site in ("cross-site", "same-site", "none"):
            r = client.post("/api/abort", headers={**headers, "Sec-Fetch-Site": site})
            assert r.status_code == 403, site
            assert_refused(caplog, 403, f"Sec-Fetch-Site: {site}")
        assert client.post("/api/abort", headers={**headers, "Sec-Fetch-Site": "same-origin"}
                           ).status_code == 409


def test_the_csrf_value_is_bound_to_the_session_not_to_a_readable_cookie(
    tmp_path: Path, db: Database, caplog: pytest.LogCaptureFixture
) -> None:
    with make_client(tmp_path, db) as client, make_client(tmp_path, db) as other:
        headers = csrf_of(client)
        page = client.get("/")
        # the session cookie is the only cookie; no script can read it
        cookies = page.headers.get_list("set-cookie") + client.get("/runs").headers.get_list(
            "set-cookie")
        assert cookies == []  # the browser has its session already
        fresh = TestClient(client.app, base_url=ORIGIN).get("/")
        (cookie,) = fresh.headers.get_list("set-cookie")
        assert cookie.startswith("calstation_session=")
        attrs = {a.strip().lower() for a in cookie.split(";")[1:]}
        assert {"httponly", "samesite=strict", "path=/"} <= attrs
        assert "secure" not in attrs  # plain HTTP here; see the TLS test
        # the value of one session is worthless with another
        theirs = csrf_of(other)
        r = other.post("/api/abort", headers={**theirs, "X-CSRF-Token": headers["X-CSRF-Token"]})
        assert r.status_code == 403
        assert_refused(caplog, 403, "wrong CSRF value")
        # the old scheme: a cookie a page on another port can read and write, echoed back
        forged = TestClient(client.app, base_url=ORIGIN)
        forged.cookies.set("calstation_csrf", "x" * 32)
        r = forged.post("/api/abort", headers={"X-CSRF-Token": "x" * 32, "Origin": ORIGIN})
        assert r.status_code == 403 and "no session" in r.json()["error"]
        # a planted session id (another port can set cookies for this host) gets nowhere
        # without the value derived from it, which only the station's pages carry
        forged.cookies.set("calstation_session", "A" * 43)
        r = forged.post("/api/abort", headers={"X-CSRF-Token": "x" * 32, "Origin": ORIGIN})
        assert r.status_code == 403 and "CSRF" in r.json()["error"]


def test_a_plain_form_needs_the_pages_field_and_other_bodies_are_refused(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin,
    caplog: pytest.LogCaptureFixture,
) -> None:
    with make_client(tmp_path, db) as client:
        headers = csrf_of(client)
        origin = {"Origin": ORIGIN}
        assert client.post("/api/abort", data={"csrf": "nope"}, headers=origin).status_code == 403
        r = client.post("/api/abort", data={"csrf": headers["X-CSRF-Token"]}, headers=origin,
                        follow_redirects=False)
        assert r.status_code == 409  # passed the checks; nothing runs
        # text/plain and multipart are what a cross-site form can send: not taken at all
        for ctype in ("text/plain", "multipart/form-data; boundary=x", "application/xml"):
            r = client.post("/api/start", content=b"recipe=lean.yaml",
                            headers={**headers, "Content-Type": ctype})
            assert r.status_code == 415, ctype
            assert_refused(caplog, 415, "is not taken")
        assert runs(db) == 0


# --- DNS rebinding ---------------------------------------------------------------------------
def test_requests_naming_another_host_are_refused(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The review's attack: a page on a name that resolves to 127.0.0.1 is, for the browser,
    its own origin (it reads the answers and posts with a matching Origin); the Host header
    gives it away."""
    with make_client(tmp_path, db) as client:
        headers = csrf_of(client)
        evil = {"Host": "evil.test:8470", "Origin": "http://evil.test:8470"}
        for method, path in [("GET", "/"), ("GET", "/state.json"), ("GET", "/runs.json"),
                             ("GET", "/events"), ("POST", "/api/start"),
                             ("POST", "/api/answer"), ("POST", "/api/abort")]:
            r = client.request(method, path, headers={**headers, **evil},
                               json=start_body() if method == "POST" else None)
            assert r.status_code == 400, (path, r.status_code)
            assert_refused(caplog, 400, "'evil.test:8470' is not a name of this station")
        assert runs(db) == 0 and station_plugin.motor_calls == []
        # the names of this station pass
        for host in ("127.0.0.1:8470", "localhost:8470", "LOCALHOST", "127.0.0.1"):
            assert client.get("/state.json", headers={"Host": host}).status_code == 200, host
        # look-alikes do not
        for host in ("127.0.0.1.evil.test", "localhost.evil.test", "evil.test", "[::1]:8470",
                     "0.0.0.0:8470", "10.0.0.5", "localhost.", "127.0.0.1:8470 evil",
                     "user@127.0.0.1", "127.0.0.1/x", "999.1.1.1"):
            r = client.get("/state.json", headers={"Host": host})
            assert r.status_code == 400, host


def test_allowed_host_names_and_the_address_a_connection_arrived_at(
    tmp_path: Path, db: Database
) -> None:
    (tmp_path / "recipes").mkdir()
    app = create_app(db, data_dir=tmp_path / "d", recipes_dir=tmp_path / "recipes",
                     host="0.0.0.0", token=TOKEN,
                     allow_hosts=["station.plant.example", "*.cell.plant.example"])
    # served on every address: a connection that arrived at 10.1.2.3 may name it
    client = TestClient(app, base_url="http://10.1.2.3:8470")
    ok = ["10.1.2.3:8470", "station.plant.example", "Station.Plant.Example:8470",
          "a.cell.plant.example", "0.0.0.0:8470"]
    for host in ok:
        assert client.get("/state.json", headers={"Host": host}).status_code == 200, host
    # localhost is only a name of a loopback connection; other addresses are not this one's
    for host in ["localhost", "127.0.0.1", "10.1.2.4", "cell.plant.example", "plant.example",
                 "station.plant.example.evil.test"]:
        assert client.get("/state.json", headers={"Host": host}).status_code == 400, host


def test_host_parsing() -> None:
    import ipaddress

    assert parse_host("LocalHost:8470") == ("localhost", 8470)
    assert parse_host("[::1]:80") == (ipaddress.ip_address("::1"), 80)
    assert parse_host("[::ffff:127.0.0.1]") == (ipaddress.ip_address("127.0.0.1"), None)
    for bad in ("", "a b", "x:99999", "x:", "[zz]", "a@b", "1.2.3.4.5", "é.test", "x\x00"):
        assert parse_host(bad) is None, bad
    policy = HostPolicy("127.0.0.1")
    assert policy.refusal(None, "127.0.0.1") == (400, "no Host header")
    assert policy.refusal("127.0.0.1:1", "127.0.0.1") is None
    assert policy.refusal("localhost", "127.0.0.1") is None
    assert policy.refusal("evil.test", "127.0.0.1") is not None
    with pytest.raises(ValueError):
        HostPolicy("127.0.0.1", ["evil.test/path"])


# --- clickjacking and headers ----------------------------------------------------------------
SECURITY_HEADERS = {
    "x-content-type-options": "nosniff",
    "referrer-policy": "no-referrer",
    "x-frame-options": "DENY",
}


def check_headers(r: httpx.Response) -> str:
    """The response carries the security headers; returns its CSP nonce ('' without one)."""
    for name, value in SECURITY_HEADERS.items():
        assert r.headers.get(name) == value, (r.request.url, name)
    assert "server" not in r.headers
    csp = r.headers["content-security-policy"]
    directives = dict([*d.strip().split(" ", 1), ""][:2] for d in csp.split(";"))
    assert directives["frame-ancestors"] == "'none'"
    assert directives["default-src"] == "'none'"
    for name in ("script-src", "style-src"):
        assert "'unsafe-inline'" not in directives[name] and "'unsafe-eval'" not in directives[name]
        assert "*" not in directives[name] and "http" not in directives[name]
    nonce = re.search(r"'nonce-([^']+)'", directives["script-src"])
    return nonce.group(1) if nonce else ""


class _Inline(html.parser.HTMLParser):
    """Finds what a strict policy would block in a page: inline scripts without the nonce,
    event-handler attributes, style attributes, ``javascript:`` URLs."""

    def __init__(self, nonce: str) -> None:
        super().__init__()
        self.nonce, self.problems = nonce, []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        for name, value in attrs:
            if name.startswith("on"):
                self.problems.append(f"<{tag} {name}=…>")
            if name == "style":
                self.problems.append(f"<{tag} style=…>")
            if name in ("href", "src", "action") and (value or "").strip().lower().startswith(
                    "javascript:"):
                self.problems.append(f"<{tag} {name}=javascript:…>")
        inline = tag in ("script", "style") and "src" not in a
        if inline and a.get("type") != "application/json" and a.get("nonce") != self.nonce:
            self.problems.append(f"<{tag}> without the response's nonce")


def test_every_page_has_the_security_headers_and_no_inline_code_without_the_nonce(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin,
) -> None:
    from tests.support.webapi import finish

    with make_client(tmp_path, db) as client:
        headers = csrf_of(client)
        run_id = client.post("/api/start", json=start_body(), headers=headers).json()["run_id"]
        finish(client, headers)
        pages = ["/", "/runs", f"/runs/{run_id}", "/trends", "/trends?station=sim-test&param=tz",
                 f"/compare?a={run_id}&b={run_id}", "/compare", "/login", "/runs/999"]
        nonces = set()
        for path in pages:
            r = client.get(path)
            assert r.status_code in (200, 404), path
            nonce = check_headers(r)
            assert nonce and nonce not in nonces  # a new nonce for every response
            nonces.add(nonce)
            parser = _Inline(nonce)
            parser.feed(r.text)
            assert parser.problems == [], (path, parser.problems)
        # every other kind of response has them too: JSON, scripts, downloads, errors
        others = [client.get("/state.json"), client.get("/runs.json"),
                  client.get("/static/station.js"), client.get("/static/plotly.min.js"),
                  client.get(f"/runs/{run_id}/export.csv"), client.get("/api/openapi.json"),
                  client.get("/nowhere"), client.put("/api/start"),
                  client.get("/", headers={"Host": "evil.test"}),
                  client.post("/api/start", content=b"x" * 70_000, headers=headers)]
        assert [r.status_code for r in others[-4:]] == [404, 405, 400, 413]
        for r in others:
            check_headers(r)
        assert others[2].headers["content-type"].startswith("text/javascript")
        # the run folder's report.html: its inline scripts run, by their hashes, sandboxed
        r = client.get(f"/runs/{run_id}/report.html")
        csp = r.headers["content-security-policy"]
        assert csp.startswith("sandbox allow-scripts;") and "frame-ancestors 'none'" in csp
        assert "'unsafe-inline'" not in csp and "allow-same-origin" not in csp
        assert len(re.findall(r"'sha256-", csp)) >= 3  # plotly, the drawing, the stylesheet


def test_the_static_scripts_use_no_eval_and_no_webgl_trace() -> None:
    static = Path(__file__).resolve().parents[2] / "calstation" / "web" / "static"
    for js in static.glob("*.js"):
        text = js.read_text()
        for banned in ("eval(", "new Function", "scattergl", "setTimeout(\"", "document.write"):
            assert banned not in text, (js.name, banned)


# --- event streams ---------------------------------------------------------------------------
async def _asgi_stream(app: Any, headers: list[tuple[str, str]], client: str,
                       wait_first: bool = True) -> tuple[int, bytes, asyncio.Event,
                                                         asyncio.Task[None]]:
    """Open ``GET /events`` on ``app`` in this event loop as ``client``; (status, first chunk,
    an event that hangs up when set, the app's task)."""
    hang_up = asyncio.Event()
    messages: asyncio.Queue[dict[str, Any]] = asyncio.Queue()
    sent_request = False

    async def receive() -> dict[str, Any]:
        nonlocal sent_request
        if not sent_request:
            sent_request = True
            return {"type": "http.request", "body": b"", "more_body": False}
        await hang_up.wait()
        return {"type": "http.disconnect"}

    async def send(message: dict[str, Any]) -> None:
        await messages.put(message)

    raw = [(k.lower().encode("latin-1"), v.encode("latin-1"))
           for k, v in [("host", "127.0.0.1:8470"), *headers]]
    scope = {"type": "http", "asgi": {"version": "3.0", "spec_version": "2.4"},
             "http_version": "1.1", "method": "GET", "scheme": "http", "path": "/events",
             "raw_path": b"/events", "query_string": b"", "root_path": "", "headers": raw,
             "client": (client, 40000), "server": ("127.0.0.1", 8470), "state": {}}
    task = asyncio.create_task(app(scope, receive, send))
    start = await asyncio.wait_for(messages.get(), 5)
    body = b""
    if start["status"] == 200 and wait_first:
        body = (await asyncio.wait_for(messages.get(), 5))["body"]
    elif start["status"] != 200:
        while start.get("more_body", True):
            start_body_msg = await asyncio.wait_for(messages.get(), 5)
            body += start_body_msg.get("body", b"")
            if not start_body_msg.get("more_body"):
                break
    return start["status"], body, hang_up, task


def test_event_streams_are_capped_per_client_and_in_total(
    tmp_path: Path, db: Database, caplog: pytest.LogCaptureFixture
) -> None:
    (tmp_path / "recipes").mkdir()
    limits = WebLimits(max_streams=5, max_streams_per_client=2)
    app = create_app(db, data_dir=tmp_path / "d", recipes_dir=tmp_path / "recipes",
                     limits=limits)

    async def main() -> None:
        opened = []
        for _ in range(2):
            status, body, hang_up, task = await _asgi_stream(app, [], "192.0.2.10")
            assert status == 200 and body.startswith(b"event: state\ndata: {")
            opened.append((hang_up, task))
        status, body, _, _ = await _asgi_stream(app, [], "192.0.2.10")
        assert status == 429 and b"2 event streams open" in body
        assert_refused(caplog, 429, "192.0.2.10 has 2 event streams open")
        # another client has its own share; this computer (loopback) shares the total
        for client in ("192.0.2.11", "127.0.0.1", "127.0.0.1"):
            status, _, hang_up, task = await _asgi_stream(app, [], client)
            assert status == 200, client
            opened.append((hang_up, task))
        status, body, _, _ = await _asgi_stream(app, [], "127.0.0.1")
        assert status == 503 and b"5 event streams are open" in body
        assert app.state.slots.count == 5
        # a client that hangs up gives its slot back at once
        for hang_up, task in opened:
            hang_up.set()
            await asyncio.wait_for(task, 5)
        assert app.state.slots.count == 0
        status, _, hang_up, task = await _asgi_stream(app, [], "192.0.2.10")
        assert status == 200
        hang_up.set()
        await asyncio.wait_for(task, 5)

    asyncio.run(main())


def test_a_station_with_a_token_streams_only_to_its_sessions(
    tmp_path: Path, db: Database, caplog: pytest.LogCaptureFixture
) -> None:
    (tmp_path / "recipes").mkdir()
    limits = WebLimits(event_keepalive_s=0.2)
    app = create_app(db, data_dir=tmp_path / "d", recipes_dir=tmp_path / "recipes",
                     host="0.0.0.0", token=TOKEN, limits=limits)
    client = TestClient(app, base_url=ORIGIN)
    page = csrf_of(client)
    sid = client.cookies["calstation_session"]

    async def main() -> None:
        status, body, _, _ = await _asgi_stream(app, [("cookie", f"calstation_session={sid}")],
                                                "192.0.2.10")
        assert status == 401 and b"needs its token" in body
        assert_refused(caplog, 401, "not logged in")
        # a page of another origin cannot open it either
        status, body, _, _ = await _asgi_stream(app, [("origin", OTHER_PORT)], "127.0.0.1")
        assert status == 403
        status, body, hang_up, task = await _asgi_stream(
            app, [("authorization", f"Bearer {TOKEN}")], "192.0.2.10")
        assert status == 200 and body.startswith(b"event: state")
        hang_up.set()
        await task

    asyncio.run(main())
    r = client.post("/login", data={"token": TOKEN, "csrf": page["X-CSRF-Token"]},
                    headers={"Origin": ORIGIN}, follow_redirects=False)
    assert r.status_code == 303
    sid = client.cookies["calstation_session"]
    page = csrf_of(client)

    async def logged_in() -> None:
        messages: list[bytes] = []
        status, body, hang_up, task = await _asgi_stream(
            app, [("cookie", f"calstation_session={sid}")], "192.0.2.10")
        assert status == 200 and body.startswith(b"event: state")
        # logging out ends the stream at its next keep-alive
        transport = httpx.ASGITransport(app=app, client=("192.0.2.10", 1))
        async with httpx.AsyncClient(transport=transport, base_url=ORIGIN) as c:
            r = await c.post("/logout", headers={**page, "Cookie": f"calstation_session={sid}"})
            assert r.status_code == 200
        await asyncio.wait_for(task, 5)
        del messages, hang_up

    asyncio.run(logged_in())
    assert any("event stream ended" in m and "not logged in" in m for m in refusals(caplog))


# --- malformed input: 4xx, never 500 ---------------------------------------------------------
def test_non_ascii_cookies_and_headers_are_refused_not_crashed(
    tmp_path: Path, db: Database, caplog: pytest.LogCaptureFixture
) -> None:
    """hmac.compare_digest raised TypeError on non-ASCII text: every comparison is on bytes."""
    for token in (None, TOKEN):
        with make_client(tmp_path, db, token=token) as client:
            headers = csrf_of(client)
            sid = client.cookies["calstation_session"]
            cases: list[dict[str, Any]] = [
                {"X-CSRF-Token": "é€😀".encode()},
                {"X-CSRF-Token": b"\xff\xfe"},
                {"Cookie": b"calstation_session=\xc3\xa9\xe2\x82\xac"},
                {"Cookie": f"calstation_session={sid}; calstation_csrf=é".encode()},
                {"Authorization": "Bearer é€".encode()},
                {"Authorization": b"Bearer \xff" + TOKEN.encode()},
                {"Origin": "http://é.test".encode()},
            ]
            for extra in cases:
                r = client.post("/api/abort", headers={**headers, **extra})
                # refused (or, with the real session and value beside a stray cookie: nothing
                # to abort), never a crash
                assert 400 <= r.status_code < 500, (extra, r.status_code, r.text)
                assert r.status_code != 409 or b"calstation_csrf" in extra.get("Cookie", b"")
            r = client.post("/login", headers={"Origin": ORIGIN},
                            data={"token": "é€" * 10, "csrf": headers["X-CSRF-Token"]})
            assert r.status_code == (401 if token else 200)


MALFORMED_JSON = [
    b'{"recipe": "lean.yaml", "operator": "ann"',  # truncated
    b"[" * 100_000 + b"]" * 100_000,  # nested past reason (and past the body limit)
    b"[" * 20_000 + b"]" * 20_000,  # nested past reason
    b'{"prompt_id": Infinity, "answer": "abort"}',
    b'{"prompt_id": NaN, "answer": "abort"}',
    b'{"prompt_id": -Infinity, "answer": "abort"}',
    b'{"recipe": "\xff\xfe", "operator": "ann"}',  # not UTF-8
    b'{"prompt_id": ' + b"9" * 5000 + b', "answer": "abort"}',  # past int parsing
    b'{"prompt_id": 1, "prompt_id": 2, "answer": "abort"}',  # a key twice
    b'["prompt_id", 1]', b'"abort"', b"null", b"1", b"\x00\x01\x02", b'{"a": "\\ud800"}',
]


def test_malformed_json_is_a_4xx(
    tmp_path: Path, db: Database, caplog: pytest.LogCaptureFixture
) -> None:
    with make_client(tmp_path, db) as client:
        headers = {**csrf_of(client), "Content-Type": "application/json"}
        for body in MALFORMED_JSON:
            for path in ("/api/start", "/api/answer", "/api/abort", "/login", "/logout"):
                caplog.clear()
                r = client.post(path, content=body, headers=headers)
                assert 400 <= r.status_code < 500, (body[:30], path, r.status_code, r.text)
                assert "error" in r.json() and refusals(caplog), (body[:30], path)


def test_prompt_ids_of_the_wrong_type_answer_nothing(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin,
) -> None:
    """A prompt_id of 1.5 or true answered prompt 1: now only an integer is an id."""
    with make_client(tmp_path, db) as client:
        headers = csrf_of(client)
        client.post("/api/start", json=start_body(), headers=headers)
        prompt = wait_prompt(client)
        assert prompt["id"] == 1
        for value in (1.5, True, "1", 1.0, None, [1], {"id": 1}, 0, -1, 2**53, 2**64, 10**30,
                      "1.5", "", "true", " 1"):
            r = client.post("/api/answer", json={"prompt_id": value, "answer": "continue"},
                            headers=headers)
            assert r.status_code == 422, (value, r.text)
            # the same as a form: digits only (a form's "1" is the id 1)
            if isinstance(value, str | float | int) and value != "1" and value is not True:
                r = client.post("/api/answer", headers={"Origin": ORIGIN}, data={
                    "prompt_id": str(value), "answer": "continue",
                    "csrf": headers["X-CSRF-Token"]})
                assert r.status_code in (409, 422), (value, r.text)
            state = client.get("/state.json").json()
            assert state["prompt"] is not None and state["prompt"]["id"] == 1, value  # pending
        for bad in ({"prompt_id": 1, "answer": "CONTINUE"}, {"prompt_id": 1},
                    {"prompt_id": 1, "answer": "continue", "extra": 1}):
            assert client.post("/api/answer", json=bad, headers=headers).status_code == 422
        assert client.post("/api/abort", headers=headers).status_code == 200
        wait_until(lambda: not client.get("/state.json").json()["busy"])


def test_ids_are_range_checked(tmp_path: Path, db: Database) -> None:
    """Run ids of 2^63 and above gave 500 (the database's integer overflowed)."""
    with make_client(tmp_path, db) as client:
        headers = csrf_of(client)
        for rid in (2**63, 2**63 + 1, 2**64, 10**30, 0, -1, "abc", "1e3", "0x10", " 1", "1.0"):
            for path in (f"/runs/{rid}", f"/runs/{rid}.json", f"/runs/{rid}/report.html",
                         f"/runs/{rid}/export.csv", f"/compare.json?a={rid}&b=1",
                         f"/compare?a=1&b={rid}"):
                r = client.get(path)
                assert r.status_code in (404, 422), (path, r.status_code)
            r = client.post(f"/api/resume/{rid}", headers=headers)
            assert r.status_code in (404, 422), (rid, r.status_code)
        # the largest id a row can have is merely absent
        for path in (f"/runs/{2**63 - 1}", f"/runs/{2**63 - 1}.json", "/runs/1/export.yaml"):
            assert client.get(path).status_code == 404, path
        assert client.post(f"/api/resume/{2**63 - 1}", headers=headers).status_code == 404
        assert client.get("/runs/1/export.exe").status_code == 422


def test_query_parameters_are_bounded(tmp_path: Path, db: Database) -> None:
    with make_client(tmp_path, db) as client:
        for params in ({"since": "9999-12-31", "until": "9999-12-31"}, {"until": "9999-12-31"},
                       {"since": "x" * 33}, {"operator": "a" * 101}, {"station": "\x00"},
                       {"serial": "a\nb"}, {"limit": "0"}, {"limit": "5001"},
                       {"limit": str(2**70)}, {"limit": "1.5"}, {"status": "nonsense"},
                       {"since": "2026-13-45"}):
            for path in ("/runs", "/runs.json"):
                r = client.get(path, params=params)
                assert r.status_code in (400, 422), (path, params, r.status_code)
        for params in ({"param": "bogus"}, {"param": "x" * 33}, {"station": "\u2028"}):
            assert client.get("/trends.json", params=params).status_code in (400, 422)
        assert client.get("/runs.json", params={"since": "2026-01-01", "limit": "5"}
                          ).status_code == 200
        assert client.get("/static/..%2Fapp.py").status_code in (404, 422)
        assert client.get("/static/app.py").status_code == 422


# --- limits ----------------------------------------------------------------------------------
def test_a_large_body_is_refused_before_it_is_read(tmp_path: Path, db: Database) -> None:
    (tmp_path / "recipes").mkdir()
    app = create_app(db, data_dir=tmp_path / "d", recipes_dir=tmp_path / "recipes")

    async def post(headers: list[tuple[bytes, bytes]], chunks: list[bytes]
                   ) -> tuple[int, int, bytes]:
        reads = 0
        out: list[dict[str, Any]] = []

        async def receive() -> dict[str, Any]:
            nonlocal reads
            reads += 1
            if reads <= len(chunks):
                return {"type": "http.request", "body": chunks[reads - 1],
                        "more_body": reads < len(chunks)}
            return {"type": "http.disconnect"}

        async def send(message: dict[str, Any]) -> None:
            out.append(message)

        scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1",
                 "method": "POST", "scheme": "http", "path": "/api/start",
                 "raw_path": b"/api/start", "query_string": b"", "root_path": "",
                 "headers": [(b"host", b"127.0.0.1:8470"), (b"origin", ORIGIN.encode()),
                             (b"content-type", b"application/json"), *headers],
                 "client": ("127.0.0.1", 1), "server": ("127.0.0.1", 8470), "state": {}}
        await app(scope, receive, send)
        body = b"".join(m.get("body", b"") for m in out if m["type"] == "http.response.body")
        return out[0]["status"], reads, body

    # 200 MB announced: refused from the header alone, not a byte read
    status, reads, body = asyncio.run(post([(b"content-length", b"200000000")], [b"{}"]))
    assert (status, reads) == (413, 0) and b"200000000 bytes" in body
    # without a length (chunked): counted as it comes, refused past the limit
    chunk = b" " * 16384
    status, reads, body = asyncio.run(post([], [chunk] * 12_000))
    assert status == 413 and reads == 5  # 5 × 16 KiB > 64 KiB
    for bad in (b"-1", b"1e9", b"\xd9\xa1", b"99999999999999999999999"):
        status, reads, _ = asyncio.run(post([(b"content-length", bad)], [b"{}"]))
        assert (status, reads) == (400, 0), bad


def test_text_fields_have_the_databases_lengths_and_sane_characters(
    tmp_path: Path, db: Database, station_plugin: StationTestPlugin,
) -> None:
    with make_client(tmp_path, db) as client:
        headers = csrf_of(client)

        def start(**fields: Any) -> httpx.Response:
            return client.post("/api/start", json={**start_body("none.yaml"), **fields},
                               headers=headers)

        # within the limits: accepted (then refused for the recipe, which does not exist)
        for fields in ({"operator": "a" * 100}, {"operator": "José Ñúñez-O'Brien"},
                       {"operator": "王小明"}, {"serial": "S" * 100}, {"serial": "LX-1042/3 B"},
                       {"serial": ""}, {"serial": None}, {"operator": "  ann  "}):
            r = start(**fields)
            assert r.status_code == 400 and "no recipe" in r.json()["error"], (fields, r.text)
        for fields in ({"operator": "a" * 101}, {"serial": "S" * 101}, {"operator": ""},
                       {"operator": "   "}, {"operator": "ann\nbob"}, {"operator": "ann\x00"},
                       {"operator": "a\u202eb"}, {"operator": "<script>"},
                       {"serial": "a\tb"}, {"serial": "é"}, {"recipe": "../etc/passwd"},
                       {"recipe": "a" * 300 + ".yaml"}, {"recipe": "x.yml"}, {"operator": 1},
                       {"serial": 42}, {"recipe": ["lean.yaml"]}):
            assert start(**fields).status_code == 422, fields
        # a 1 MB name does not even get read
        r = client.post("/api/start", headers=headers,
                        json=start_body(operator="a" * 1_000_000, serial="b" * 1_000_000))
        assert r.status_code == 413
        assert runs(db) == 0


# --- login and sessions ----------------------------------------------------------------------
def test_wrong_tokens_are_throttled_per_client_with_a_back_off(
    tmp_path: Path, db: Database, caplog: pytest.LogCaptureFixture
) -> None:
    clock = Clock()
    (tmp_path / "recipes").mkdir()
    app = create_app(db, data_dir=tmp_path / "d", recipes_dir=tmp_path / "recipes",
                     host="0.0.0.0", token=TOKEN, limits=WebLimits(clock=clock))
    attacker = TestClient(app, base_url=ORIGIN, client=("192.0.2.66", 1))
    codes = [attacker.post("/api/abort", headers={"Authorization": f"Bearer guess-{i:08d}"}
                           ).status_code for i in range(200)]
    assert codes[:5] == [401] * 5 and codes[5] == 401 and set(codes[6:]) == {429}
    assert_refused(caplog, 429, "too many wrong tokens from 192.0.2.66")
    # locked out: even the right token is not compared
    right = {"Authorization": f"Bearer {TOKEN}"}
    r = attacker.post("/api/abort", headers=right)
    assert r.status_code == 429 and int(r.headers["retry-after"]) >= 1
    # the login form is the same door
    page = csrf_of(attacker)
    r = attacker.post("/login", data={"token": TOKEN, "csrf": page["X-CSRF-Token"]},
                      headers={"Origin": ORIGIN})
    assert r.status_code == 429 and "wait" in r.text
    # another client is not locked out
    other = TestClient(app, base_url=ORIGIN, client=("192.0.2.67", 1))
    assert other.post("/api/abort", headers=right).status_code == 409
    # the back-off doubles with each wrong token after the lock: 1, 2, 4 s ...
    clock.t += 2.0
    assert attacker.post("/api/abort", headers={"Authorization": "Bearer wrong-again-1"}
                         ).status_code == 401
    clock.t += 1.5
    assert attacker.post("/api/abort", headers=right).status_code == 429
    clock.t += 1.0
    assert attacker.post("/api/abort", headers=right).status_code == 409
    # the right token clears the count
    assert attacker.post("/api/abort", headers={"Authorization": "Bearer wrong-again-2"}
                         ).status_code == 401


def test_sessions_are_random_expire_and_end_at_logout(
    tmp_path: Path, db: Database, caplog: pytest.LogCaptureFixture
) -> None:
    clock = Clock()
    (tmp_path / "recipes").mkdir()
    limits = WebLimits(clock=clock, session_idle_s=100.0, session_max_s=1000.0)
    app = create_app(db, data_dir=tmp_path / "d", recipes_dir=tmp_path / "recipes",
                     host="0.0.0.0", token=TOKEN, limits=limits)

    def login() -> tuple[TestClient, dict[str, str]]:
        c = TestClient(app, base_url=ORIGIN)
        page = csrf_of(c)
        r = c.post("/login", data={"token": TOKEN, "csrf": page["X-CSRF-Token"]},
                   headers={"Origin": ORIGIN}, follow_redirects=False)
        assert r.status_code == 303
        cookie = r.headers["set-cookie"]
        assert "max-age=1000" in cookie.lower() and "httponly" in cookie.lower()
        return c, csrf_of(c)

    a, ha = login()
    b, _ = login()
    sa, sb = a.cookies["calstation_session"], b.cookies["calstation_session"]
    assert sa != sb and len(sa) == len(sb) == 43
    assert "log out" in a.get("/").text
    assert a.post("/api/abort", headers=ha).status_code == 409
    # idle too long
    clock.t += 101
    r = a.post("/api/abort", headers=ha)
    assert r.status_code == 401 and "expired" in r.json()["error"]
    assert_refused(caplog, 401, "your session expired")
    # used all along, but older than the longest a session lives
    b2, hb2 = login()
    for _ in range(11):
        clock.t += 90
        assert b2.post("/api/abort", headers=hb2).status_code == 409
    clock.t += 20
    r = b2.post("/api/abort", headers=hb2)
    assert r.status_code == 401 and "expired" in r.json()["error"]
    # logout ends the session on the server, not only in the browser
    c, hc = login()
    sid = c.cookies["calstation_session"]
    r = c.post("/logout", headers=hc, follow_redirects=False)
    assert r.status_code == 200 and 'calstation_session=""' in r.headers["set-cookie"]
    replay = TestClient(app, base_url=ORIGIN)
    replay.cookies.set("calstation_session", sid)
    assert replay.post("/api/abort", headers=hc).status_code == 401


def test_changing_the_token_file_ends_every_session(
    tmp_path: Path, db: Database, caplog: pytest.LogCaptureFixture
) -> None:
    from calstation.web.tokens import TokenSource

    token_file = tmp_path / "token"
    token_file.write_text(TOKEN + "\n")
    (tmp_path / "recipes").mkdir()
    app = create_app(db, data_dir=tmp_path / "d", recipes_dir=tmp_path / "recipes",
                     host="0.0.0.0", token=TokenSource(path=token_file))
    client = TestClient(app, base_url=ORIGIN)
    page = csrf_of(client)
    client.post("/login", data={"token": TOKEN, "csrf": page["X-CSRF-Token"]},
                headers={"Origin": ORIGIN})
    headers = csrf_of(client)
    assert client.post("/api/abort", headers=headers).status_code == 409
    new = "new-station-token-0123"
    token_file.write_text(new + "\n")
    r = client.post("/api/abort", headers=headers)
    assert r.status_code == 401 and "token changed" in r.json()["error"]
    assert any("station token changed: 1 logged-in session(s) ended" in r.getMessage()
               for r in caplog.records)
    assert client.post("/api/abort", headers={"Authorization": f"Bearer {TOKEN}"}
                       ).status_code == 401
    assert client.post("/api/abort", headers={"Authorization": f"Bearer {new}"}
                       ).status_code == 409
    # a token file that can no longer be used locks the station (fail closed)
    token_file.write_text("short\n")
    r = client.post("/api/abort", headers={"Authorization": f"Bearer {new}"})
    assert r.status_code == 503 and "too short" in r.json()["error"]
    token_file.unlink()
    assert client.post("/api/abort", headers={"Authorization": f"Bearer {new}"}
                       ).status_code == 503
    token_file.write_text(new + "\n")
    assert client.post("/api/abort", headers={"Authorization": f"Bearer {new}"}
                       ).status_code == 409


def test_a_local_station_given_a_token_requires_it(tmp_path: Path, db: Database) -> None:
    with make_client(tmp_path, db, token=TOKEN) as client:
        headers = csrf_of(client)
        assert client.post("/api/abort", headers=headers).status_code == 401
        assert client.post("/api/abort", headers={"Authorization": f"Bearer {TOKEN}"}
                           ).status_code == 409
        assert client.post("/api/abort", headers={"Authorization": f"Basic {TOKEN}"}
                           ).status_code == 401
    with make_client(tmp_path, db) as client:
        # a station without a token takes none
        assert client.post("/api/abort", headers={"Authorization": f"Bearer {TOKEN}"}
                           ).status_code == 401


def test_a_cross_site_link_keeps_the_browsers_session(tmp_path: Path, db: Database) -> None:
    """SameSite=Strict leaves the cookie home on a link from another site: the page must not
    hand out a new session over it, but reload itself (which sends the cookie)."""
    with make_client(tmp_path, db, token=TOKEN) as client:
        r = client.get("/", headers={"Sec-Fetch-Site": "cross-site", "Sec-Fetch-Mode": "navigate"})
        assert r.status_code == 200 and 'http-equiv="refresh"' in r.text
        assert "set-cookie" not in r.headers
        r = client.get("/", headers={"Sec-Fetch-Site": "same-origin", "Sec-Fetch-Mode": "navigate"})
        assert "calstation_session=" in r.headers["set-cookie"]
        r = client.get("/runs", headers={"Sec-Fetch-Site": "cross-site"})
        assert "set-cookie" not in r.headers


def test_json_errors_name_the_field_without_echoing_the_input(
    tmp_path: Path, db: Database
) -> None:
    with make_client(tmp_path, db) as client:
        headers = csrf_of(client)
        r = client.post("/api/start", headers=headers,
                        json={"recipe": "lean.yaml", "operator": "<b>" * 30})
        assert r.status_code == 422 and "<b>" not in r.text
        assert json.loads(r.text)["error"].startswith("operator:")
