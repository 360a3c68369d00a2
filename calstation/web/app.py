"""The web station's routes: operator, runs, trends, api. Thin: they render and answer.

Every page has a JSON twin at the same path with ``.json`` (``/state.json`` for the operator
page). State-changing requests are POSTs checked by :class:`security.Guard`; everything passes
the front door first (:mod:`.middleware`: host allow-list, body limit, security headers).
Every refusal is logged (logger ``calstation.web``) with the client and the reason.
"""

from __future__ import annotations

import asyncio
import base64
import hashlib
import logging
import re
import time
from collections.abc import AsyncIterator, Mapping, Sequence
from contextlib import asynccontextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal, TypedDict, TypeVar

from fastapi import Depends, FastAPI, Path as PathParam, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import (
    HTMLResponse,
    JSONResponse,
    RedirectResponse,
    Response,
)
from pydantic import AfterValidator, BaseModel, ValidationError
from pydantic_core import ErrorDetails
from starlette.exceptions import HTTPException
from starlette.types import ASGIApp

from calstation.errors import CalstationError
from calstation.station.lock import StationBusy
from calstation.storage.db import Database, Run, RunStatus
from calstation.storage.templating import environment
from calstation.web.events import EventHub, EventStream, StreamSlots
from calstation.web.hosts import HostPolicy, is_local_host
from calstation.web.live import Busy, NoSuchPrompt, Runner
from calstation.web.middleware import NONCE_KEY, FrontDoor, refused
from calstation.web.payloads import (
    AnswerRequest,
    EmptyRequest,
    JSONPage,
    LoginRequest,
    ParamName,
    PlanRequest,
    StartRequest,
    form_to_typed,
    media_type,
    printable,
    read_fields,
    schema_of,
)
from calstation.web.plans import Planner
from calstation.web.qa_routes import dashboard_routes, run_page_routes
from calstation.web.security import AccessError, Guard, client_of
from calstation.web.settings import MAX_ID, WebLimits
from calstation.web.status import StationStatus, age, recipe_stations
from calstation.web.tokens import TokenSource

if TYPE_CHECKING:
    from calstation.storage.qa import HistoryFilter

STATIC = Path(__file__).parent / "static"
StaticFile = Literal["station.css", "station.js", "status.js", "plan.js", "figures.js",
                     "plotly.min.js"]

log = logging.getLogger("calstation.web")

M = TypeVar("M", bound=BaseModel)


class NotFound(CalstationError):
    """No such run (HTTP 404)."""


class FrontDoorSettings(TypedDict):
    """The front door's settings (:class:`~calstation.web.middleware.FrontDoor`)."""

    hosts: HostPolicy
    max_body_bytes: int
    tls: bool


class _StationApp(FastAPI):
    """FastAPI with the front door around its whole stack, error pages included."""

    front_door: FrontDoorSettings | None = None

    def build_middleware_stack(self) -> ASGIApp:
        app = super().build_middleware_stack()
        return FrontDoor(app, **self.front_door) if self.front_door is not None else app


def create_app(
    db: Database,
    *,
    data_dir: Path,
    recipes_dir: Path,
    host: str = "127.0.0.1",
    token: str | TokenSource | None = None,
    allow_hosts: Sequence[str] = (),
    tls: bool = False,
    limits: WebLimits | None = None,
) -> FastAPI:
    """The web station over ``db``; runs go to ``data_dir/runs/N``; recipes offered from
    ``recipes_dir``. ``host`` is the address it is served on: bound to a non-local one it needs
    ``token`` (see :mod:`.security`), and a token given on a local one is required as well.
    Requests must name ``host`` (or, served on a loopback address, ``localhost``), the local
    address they arrived at, or one of ``allow_hosts`` (:mod:`.hosts`). ``tls``: served over
    HTTPS (secure cookies, HSTS)."""
    limits = limits or WebLimits()
    source = TokenSource(token=token) if isinstance(token, str) else token
    guard = Guard(source, require_token=source is not None or not is_local_host(host), tls=tls,
                  limits=limits)
    runner = Runner(db, data_dir, recipes_dir)
    status = StationStatus(db, lambda: recipe_stations(recipes_dir), runner.live.set_stations)
    runner.released = status.refresh
    hub = EventHub(runner.live, tick=status.current)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        yield
        # the server stops: abort a run still in progress, so the motor is stopped
        if runner.abort("the web station was stopped"):
            await asyncio.to_thread(runner.join, 30.0)

    # no Swagger UI: it loads its scripts from a CDN, and the station has no internet
    app = _StationApp(title="calstation station", lifespan=lifespan, docs_url=None,
                      redoc_url=None, openapi_url="/api/openapi.json")
    app.front_door = {"hosts": HostPolicy(host, allow_hosts),
                      "max_body_bytes": limits.max_body_bytes, "tls": tls}
    app.state.runner = runner
    app.state.guard = guard
    app.state.db = db
    app.state.hub = hub
    app.state.slots = StreamSlots(limits)
    app.state.limits = limits
    app.state.status = status
    ctx = _Pages(db, runner, guard, status)
    app.state.pages = ctx
    _error_handlers(app, ctx)
    _operator_routes(app, ctx)
    _run_routes(app, ctx)
    _fleet_routes(app, ctx, recipes_dir)
    _api_routes(app, ctx)
    _plan_routes(app, ctx, Planner(runner))
    run_page_routes(app, ctx)
    dashboard_routes(app, ctx)
    return app


def _wants_json(request: Request) -> bool:
    return (request.url.path.startswith("/api/") or request.url.path.endswith(".json")
            or request.url.path == "/events"
            or "application/json" in request.headers.get("accept", "").split(",")[0]
            or media_type(request)[0] == "application/json")


def _error_handlers(app: FastAPI, ctx: _Pages) -> None:
    def answer(request: Request, status: int, message: str,
               headers: dict[str, str] | None = None) -> Response:
        refused(request.scope, status, message)
        if _wants_json(request) or request.method != "GET":
            return JSONResponse({"error": message}, status_code=status, headers=headers)
        return ctx.page(request, "message.html", {"title": "refused", "message": message},
                        status=status, headers=headers)

    @app.exception_handler(CalstationError)
    async def _calstation_error(request: Request, exc: CalstationError) -> Response:
        status = (exc.status if isinstance(exc, AccessError)
                  else 404 if isinstance(exc, NotFound)
                  else 409 if isinstance(exc, Busy | NoSuchPrompt | StationBusy) else 400)
        headers = exc.headers if isinstance(exc, AccessError) else None
        return answer(request, status, str(exc), headers)

    @app.exception_handler(HTTPException)
    async def _http_error(request: Request, exc: HTTPException) -> Response:
        headers = dict(exc.headers) if exc.headers else None
        return answer(request, exc.status_code, str(exc.detail), headers)

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> Response:
        return answer(request, 422, _describe_errors(exc.errors()))

    @app.exception_handler(Exception)
    async def _crash(request: Request, exc: Exception) -> Response:
        log.exception("internal error in %s %s", request.method, request.url.path[:200])
        return JSONResponse({"error": "internal error (logged by the station)"},
                            status_code=500)


def _describe_errors(errors: Sequence[ErrorDetails]) -> str:
    parts = []
    for e in list(errors)[:5]:
        loc = ".".join(str(p) for p in e.get("loc", ()) if p not in ("body", "query", "path"))
        parts.append(f"{loc}: {e.get('msg', 'invalid')}" if loc else str(e.get("msg")))
    return "; ".join(parts)[:500] or "invalid request"


def _validated(model: type[M], fields: Mapping[str, object], request: Request,
               ints: tuple[str, ...] = ()) -> M:
    """``fields`` as ``model`` (strict; a form's digit fields become numbers first); 422."""
    if media_type(request)[0] == "application/x-www-form-urlencoded":
        fields = form_to_typed(fields, ints)
    try:
        return model.model_validate(fields)
    except ValidationError as exc:
        raise HTTPException(422, _describe_errors(
            exc.errors(include_url=False, include_input=False, include_context=False))) from exc


class _Pages:
    """Rendering helpers shared by the route groups."""

    def __init__(self, db: Database, runner: Runner, guard: Guard,
                 status: StationStatus) -> None:
        self.db, self.runner, self.guard, self.status = db, runner, guard, status


    def page(self, request: Request, template: str, context: Mapping[str, object],
             status: int = 200, headers: dict[str, str] | None = None) -> HTMLResponse:
        """``template`` rendered for ``request``'s session (a new one set when it has none)."""
        session = self.guard.page_session(request)
        site = request.headers.get("sec-fetch-site")
        cross_site = site in ("cross-site", "same-site")
        if session.new and cross_site and request.headers.get("sec-fetch-mode") == "navigate":
            # a link from another site: SameSite=Strict kept the cookie home. Reload from the
            # page itself, which sends it, rather than hand out a session over the real one
            return HTMLResponse('<!doctype html><meta http-equiv="refresh" content="0">',
                                headers={"Cache-Control": "no-store"})
        logged_in = self.guard.logged_in(request)
        html = environment().get_template(template).render(
            request=request, csrf=session.csrf, nonce=request.scope.get(NONCE_KEY, ""),
            needs_login=not logged_in, logged_in=logged_in and self.guard.require_token,
            busy=self.runner.busy, stations=self.status.current(), station_age=age,
            station_now=time.time, **context)
        response = HTMLResponse(html, status_code=status, headers=headers)
        if session.new and not cross_site:
            response.set_cookie(self.guard.cookie_name, session.session_id,
                                **self.guard.cookie_args(logged_in=False))  # type: ignore[arg-type]
        return response

    def require_run(self, run_id: int) -> None:
        """NotFound unless run ``run_id`` exists."""
        with self.db.session("reading the runs", read_only=True) as s:
            if s.get(Run, run_id) is None:
                raise NotFound(f"no run {run_id}")


def _optional_text(value: str | None) -> str | None:
    return None if value is None else printable(value)


OptionalText = Annotated[str | None, AfterValidator(_optional_text)]
RunId = Annotated[int, PathParam(ge=1, le=MAX_ID, description="a run id")]
CampaignId = Annotated[int, PathParam(ge=1, le=MAX_ID, description="a campaign id")]


# --- operator --------------------------------------------------------------------------------
def _operator_routes(app: FastAPI, ctx: _Pages) -> None:
    runner, guard = ctx.runner, ctx.guard

    @app.get("/", response_class=HTMLResponse)
    def operator_page(request: Request) -> HTMLResponse:
        """The operator page: start a run, answer its prompts, follow it live."""
        from calstation.web.offer import judge, offered, start_defaults

        choices = [judge(runner.recipes_dir / name) for name in runner.recipes()]
        runnable = offered(choices)
        return ctx.page(request, "operator.html", {
            "state": runner.live.snapshot(), "runnable": runnable,
            "unrunnable": [c for c in choices if not c.runnable],
            "defaults": start_defaults(ctx.db, runner.recipes_dir, [c.name for c in runnable]),
            "held": {s["station"]: s for s in ctx.status.current() if s["held"]},
            "resumable": _resumable(ctx.db),
        })

    @app.get("/state.json")
    def state_json() -> JSONPage:
        """The operator page's JSON twin: the live state of the current (or last) run."""
        ctx.status.current()
        return {**runner.live.snapshot(), "recipes": runner.recipes()}

    @app.get("/station.json")
    def station_json() -> JSONPage:
        """Who holds each station of this server (every page's status line): ``stations``,
        each with ``held`` and its ``holder`` (run, operator, where from, since when) and
        ``text`` in words; ``now``, the server's time (s since the epoch)."""
        return {"stations": ctx.status.current(), "now": time.time()}

    @app.get("/cloud.json")
    def cloud_json(
        cloud: Annotated[int, Query(ge=0, le=MAX_ID, description="the cloud the page has")] = 0,
        since: Annotated[int, Query(ge=0, le=10_000_000, description="points it has")] = 0,
    ) -> JSONPage:
        """The scan's cloud so far under the current calibration (mm, frame D): the points
        from the ``since``-th of cloud ``cloud`` on (all of them after a new scan began)."""
        return runner.live.cloud_since(cloud, since)

    @app.get("/events", response_class=Response, responses={
        200: {"content": {"text/event-stream": {}},
              "description": "a `state` event with the snapshot whenever it changes"}})
    async def events(request: Request) -> Response:
        """Server-sent events: a ``state`` event with the snapshot whenever it changes. On a
        station with a token it needs the logged-in session; streams are capped in total and
        per client."""
        guard.check_stream(request)
        client = client_of(request)
        slots: StreamSlots = request.app.state.slots
        slots.take(client)

        def still_allowed() -> bool:
            try:
                guard.check_stream(request)
            except AccessError as exc:
                refused(request.scope, exc.status, f"event stream ended: {exc}")
                return False
            return True

        return EventStream(request.app.state.hub, slots, client, request.app.state.limits,
                           still_allowed)

    @app.get("/login", response_class=HTMLResponse)
    def login_page(request: Request) -> HTMLResponse:
        """Enter the station token (only needed on a station with a token)."""
        return ctx.page(request, "login.html", {"error": None})

    @app.post("/login", response_model=None, openapi_extra=schema_of(LoginRequest))
    async def login(request: Request) -> Response:
        """Log in with the station token (a form); wrong tokens are throttled per client."""
        fields = await _authorized(request, guard, login=True)
        body = _validated(LoginRequest, fields, request)
        try:
            sid = guard.login(request, body.token)
        except AccessError as exc:
            if media_type(request)[0] != "application/x-www-form-urlencoded":
                raise
            refused(request.scope, exc.status, str(exc))
            return ctx.page(request, "login.html", {"error": str(exc)}, status=exc.status,
                            headers=exc.headers or None)
        response = _done(request, {"ok": True})
        if sid is not None:
            response.set_cookie(guard.cookie_name, sid,
                                **guard.cookie_args(logged_in=True))  # type: ignore[arg-type]
        return response

    @app.post("/logout", response_model=None, openapi_extra=schema_of(EmptyRequest))
    async def logout(request: Request) -> Response:
        """End the browser's logged-in session."""
        fields = await _authorized(request, guard, login=True)
        _validated(EmptyRequest, fields, request)
        guard.logout(request)
        response = _done(request, {"ok": True})
        response.delete_cookie(guard.cookie_name, path="/", secure=guard.tls, httponly=True,
                               samesite="strict")
        return response

    @app.get("/static/{name}")
    def static(name: StaticFile) -> Response:
        """The pages' scripts and style, and plotly.js from the installed plotly package."""
        if name == "plotly.min.js":
            from calstation.storage.report_html import plotly_js

            return Response(plotly_js(), media_type="text/javascript",
                            headers={"Cache-Control": "max-age=86400"})
        media = {"css": "text/css", "js": "text/javascript"}[name.rsplit(".", 1)[1]]
        return Response((STATIC / name).read_bytes(), media_type=media,
                        headers={"Cache-Control": "no-cache"})


def _resumable(db: Database) -> list[dict[str, object]]:
    """Runs left ``running`` by a process that is gone (a killed server), newest first."""
    import os
    import socket

    from sqlalchemy import select

    from calstation.station.lock import process_alive

    out: list[dict[str, object]] = []
    with db.session("reading the runs", read_only=True) as s:
        for run in s.scalars(select(Run).where(Run.status == RunStatus.RUNNING)
                             .order_by(Run.id.desc()).limit(20)):
            if run.host == socket.gethostname() and run.pid is not None and (
                    run.pid == os.getpid() or process_alive(run.pid)):
                continue
            out.append({"id": run.id, "recipe": run.recipe_name, "operator": run.operator,
                        "started_at": str(run.started_at)[:19]})
    return out


# --- runs, trends, compare -------------------------------------------------------------------
def _history_filter(
    station: Annotated[OptionalText, Query(max_length=100)] = None,
    status: Annotated[OptionalText, Query(max_length=16)] = None,
    operator: Annotated[OptionalText, Query(max_length=100)] = None,
    serial: Annotated[OptionalText, Query(max_length=100)] = None,
    since: Annotated[OptionalText, Query(max_length=32)] = None,
    until: Annotated[OptionalText, Query(max_length=32)] = None,
    failed_step: Annotated[OptionalText, Query(max_length=50)] = None,
    reason: Annotated[OptionalText, Query(max_length=100)] = None,
    limit: Annotated[int, Query(ge=1, le=5000)] = 200,
) -> HistoryFilter:
    from calstation.storage import qa

    # an empty field of the filter form is no filter
    return qa.HistoryFilter(station=station or None, status=status or None,
                            operator=operator or None, serial=serial or None,
                            since=since or None, until=until or None,
                            failed_step=failed_step or None, reason=reason or None,
                            limit=limit)


Filter = Annotated[Any, Depends(_history_filter)]  # Any: a HistoryFilter, imported when asked


def _trend_data(
    request: Request,
    station: Annotated[OptionalText, Query(max_length=100)] = None,
    param: Annotated[list[ParamName] | None, Query()] = None,
) -> JSONPage:
    """The trends of one or more parameters (``param`` repeated); the first one's fields at
    the top (as before several could be asked for), all of them under ``trends``."""
    from calstation.storage import qa
    from calstation.storage.dashboard import LABELS

    offered = qa.TREND_PARAMS + qa.CUBE_TREND_PARAMS
    params = list(dict.fromkeys(p for p in param or [] if p))[:12] or ["tx"]
    for p in params:
        if p not in offered:
            raise qa.QueryError(f"param: {p!r} is not one of {', '.join(offered)}")
    db: Database = request.app.state.db
    with db.session("reading the runs", read_only=True) as s:
        stations = qa.choices(s)["stations"]
        station = station or (stations[0] if stations else "")
        trends = [qa.trend(s, station, p) if station else {
            "station": "", "param": p, "limit_kind": "drift", "points": []} for p in params]
    return {**trends[0], "trends": trends, "stations": stations, "params": list(offered),
            "labels": {p: LABELS.get(p, p) for p in offered}}


Trend = Annotated[JSONPage, Depends(_trend_data)]
RunQuery = Annotated[int | None, Query(ge=1, le=MAX_ID)]


def _compare_data(request: Request, a: RunQuery = None, b: RunQuery = None
                  ) -> JSONPage | None:
    from calstation.storage import qa
    from calstation.storage.report_html import report_data

    if a is None and b is None:
        return None
    if a is None or b is None:
        raise qa.QueryError("compare needs two run ids: ?a=RUN&b=RUN")
    ctx: _Pages = request.app.state.pages
    ctx.require_run(a)
    ctx.require_run(b)
    da, db_ = report_data(ctx.db, a, views=False), report_data(ctx.db, b, views=False)
    return {"a": da, "b": db_, "rows": qa.compare(da, db_)}


Compared = Annotated[JSONPage | None, Depends(_compare_data)]


def _run_routes(app: FastAPI, ctx: _Pages) -> None:
    from calstation.storage import qa

    @app.get("/runs.json")
    def runs_json(f: Filter) -> JSONPage:
        """History as JSON (stored units)."""
        with ctx.db.session("reading the runs", read_only=True) as s:
            return {"filters": f.as_dict(), "runs": qa.history(s, f)}

    @app.get("/runs", response_class=HTMLResponse)
    def runs_page(request: Request, f: Filter) -> HTMLResponse:
        """History, filtered by station, status, operator, serial and date."""
        with ctx.db.session("reading the runs", read_only=True) as s:
            rows, options = qa.history(s, f), qa.choices(s)
        return ctx.page(request, "history.html", {"rows": rows, "f": f, "options": options,
                                                  "query": str(request.url.query)})

    @app.get("/runs/{run_id}.json")
    def run_json(run_id: RunId) -> JSONPage:
        """One run as JSON: what its page shows, without the 3D point clouds."""
        from calstation.storage.report_html import report_data

        ctx.require_run(run_id)
        return dict(report_data(ctx.db, run_id, views=False))

    @app.get("/runs/{run_id}/report.html", response_model=None)
    def run_report_file(run_id: RunId) -> Response:
        """The self-contained ``report.html`` of the run folder (opens offline). Served
        sandboxed: its inline scripts run (those of the file, by their hashes), but as a page
        of no origin, which can neither read nor change the station."""
        ctx.require_run(run_id)
        with ctx.db.session("reading the runs", read_only=True) as s:
            run = s.get(Run, run_id)
            folder = Path(run.data_dir) if run is not None else None
        if folder is None or not (folder / "report.html").is_file():
            raise NotFound(f"run {run_id} has no report.html")
        html = _with_plotly((folder / "report.html").read_text(encoding="utf-8",
                                                               errors="replace"))
        return HTMLResponse(html, headers={"Content-Security-Policy": _file_policy(html)})

    @app.get("/runs/{run_id}/export.{fmt}")
    def export(run_id: RunId, fmt: Literal["yaml", "json", "urdf", "csv"]) -> Response:
        """The run's final calibration as yaml, json, urdf or csv (a download)."""
        from calstation.storage.report import export_calibration, final_calibration, get_run

        ctx.require_run(run_id)
        with ctx.db.session("reading the runs", read_only=True) as s:
            run = get_run(s, run_id)
            text = export_calibration(run, fmt)
            mark = "" if final_calibration(run).accepted else "-NOT-ACCEPTED"
        media = {"json": "application/json", "csv": "text/csv", "urdf": "application/xml"}
        return Response(text, media_type=media.get(fmt, "text/yaml"), headers={
            "Content-Disposition":
                f'attachment; filename="run-{run_id}-calibration{mark}.{fmt}"'})

    @app.get("/trends.json")
    def trends_json(t: Trend) -> JSONPage:
        """Parameters' trends as JSON (stored units)."""
        return t

    @app.get("/trends", response_class=HTMLResponse)
    def trends_page(request: Request, t: Trend) -> HTMLResponse:
        """Trend plots of parameters by date, with 1σ bars and the drift or QA limit."""
        return ctx.page(request, "trends.html", {
            "t": t, "shown": t["trends"], "query": str(request.url.query),
            "figures": {f"trend-{one['param']}": qa.trend_figure(one) for one in t["trends"]}})

    @app.get("/compare.json")
    def compare_json(c: Compared) -> JSONPage:
        """Two runs side by side as JSON."""
        if c is None:
            raise qa.QueryError("compare needs two run ids: ?a=RUN&b=RUN")
        return c

    @app.get("/compare", response_class=HTMLResponse)
    def compare_page(request: Request, c: Compared) -> HTMLResponse:
        """Two runs side by side: calibrations, cube checks, verdicts."""
        if c is None:
            return ctx.page(request, "message.html", {
                "title": "compare", "message": "Pick two runs on the history page."})
        from calstation.storage.dashboard import LABELS

        return ctx.page(request, "compare.html", {**c, "labels": LABELS})


_PLOTLY_BESIDE = re.compile(r'<script src="\.\./plotly-[0-9A-Za-z.+-]+\.min\.js"></script>')


def _with_plotly(html: str) -> str:
    """A report file that loads plotly.js from beside the run folders, with plotly.js inlined
    instead: served sandboxed, it can load nothing, and its inline scripts are allowed by
    their hashes."""
    from calstation.storage.report_html import plotly_js

    return _PLOTLY_BESIDE.sub(lambda _: "<script>" + plotly_js() + "</script>", html, count=1)


_INLINE = re.compile(r"<(script|style)\b([^>]*)>(.*?)</\1\s*>", re.S | re.I)


def _file_policy(html: str) -> str:
    """The Content-Security-Policy of a report file: sandboxed (no origin, so no access to
    the station), its own inline scripts and styles allowed by their hashes, nothing else."""
    hashes: dict[str, set[str]] = {"script": set(), "style": set()}
    for kind, attrs, body in _INLINE.findall(html):
        if kind.lower() == "script" and re.search(r"\bsrc\s*=", attrs, re.I):
            continue
        # the browser hashes the text after its newline normalisation
        text = body.replace("\r\n", "\n").replace("\r", "\n")
        digest = base64.b64encode(hashlib.sha256(text.encode("utf-8")).digest()).decode()
        hashes[kind.lower()].add(f"'sha256-{digest}'")
    scripts = " ".join(sorted(hashes["script"])) or "'none'"
    styles = " ".join(sorted(hashes["style"])) or "'none'"
    return (f"sandbox allow-scripts; default-src 'none'; script-src {scripts} 'report-sample'; "
            f"style-src {styles} 'report-sample'; img-src data: blob:; base-uri 'none'; "
            "form-action 'none'; frame-ancestors 'none'")


# --- campaigns, metrics ----------------------------------------------------------------------
def _fleet_routes(app: FastAPI, ctx: _Pages, recipes_dir: Path) -> None:
    from calstation.fleet.metrics import StationMetrics

    metrics = StationMetrics(ctx.db, lambda: recipe_stations(recipes_dir),
                             lambda: ctx.runner.busy)

    @app.get("/metrics")
    def metrics_page() -> Response:
        """Prometheus metrics of this server's stations (docs/fleet.md)."""
        from prometheus_client import CONTENT_TYPE_LATEST

        return Response(metrics.render(), media_type=CONTENT_TYPE_LATEST)

    def campaigns() -> list[dict[str, object]]:
        from calstation.fleet.view import campaign_list

        with ctx.db.session("reading the campaigns", read_only=True) as s:
            return campaign_list(s)

    @app.get("/campaigns.json")
    def campaigns_json() -> JSONPage:
        """The re-processing campaigns, newest first."""
        return {"campaigns": campaigns()}

    @app.get("/campaigns", response_class=HTMLResponse)
    def campaigns_page(request: Request) -> HTMLResponse:
        """The re-processing campaigns (``calstation reprocess``), newest first."""
        return ctx.page(request, "campaigns.html", {"campaigns": campaigns()})

    def campaign(campaign_id: int) -> dict[str, object]:
        from calstation.fleet.view import campaign_data
        from calstation.storage.db import Campaign

        with ctx.db.session("reading the campaign", read_only=True) as s:
            if s.get(Campaign, campaign_id) is None:
                raise NotFound(f"no campaign {campaign_id}")
            return campaign_data(s, campaign_id)

    @app.get("/campaigns/{campaign_id}.json")
    def campaign_json(campaign_id: CampaignId) -> JSONPage:
        """One campaign as JSON: what ``calstation reprocess --json`` prints."""
        return campaign(campaign_id)

    @app.get("/campaigns/{campaign_id}", response_class=HTMLResponse)
    def campaign_page(request: Request, campaign_id: CampaignId) -> HTMLResponse:
        """One campaign: counts, the histogram of changes, the flagged units, each run linked."""
        return ctx.page(request, "campaign.html", {"data": campaign(campaign_id),
                                                   "link_base": ""})


# --- api (state-changing) --------------------------------------------------------------------
async def _authorized(request: Request, guard: Guard, *, login: bool = False
                      ) -> dict[str, object]:
    """The request's fields, once its body is well-formed (400, 415) and the guard lets it
    through (401, 403, 429; ``login``: no logged-in session needed)."""
    fields = await read_fields(request)
    guard.check_write(request, getattr(request.state, "form_csrf", None), login=login)
    return fields


def _address(request: Request) -> str:
    """The station's address as this request's browser used it (checked by the front door)."""
    return f"{request.url.scheme}://{request.url.netloc}/"[:200]


def _done(request: Request, body: Mapping[str, object], status: int = 200) -> Response:
    """JSON for scripts, a redirect back to the operator page for a plain form post."""
    if media_type(request)[0] == "application/x-www-form-urlencoded":
        return RedirectResponse("/", status_code=303)
    return JSONResponse(body, status_code=status)


def _plan_routes(app: FastAPI, ctx: _Pages, planner: Planner) -> None:
    """The station designer's page: ``calstation plan`` of a recipe (:mod:`.plans`)."""

    @app.get("/plan", response_class=HTMLResponse)
    def plan_page(request: Request) -> HTMLResponse:
        """Plan a recipe: what the station it describes reaches, turns, placement."""
        return ctx.page(request, "plan.html", {"recipes": ctx.runner.recipes(),
                                               "state": planner.snapshot()})

    @app.get("/plan.json")
    def plan_json() -> JSONPage:
        """The plan page's JSON twin: the plan under way or the last one."""
        return dict(planner.snapshot())

    @app.post("/api/plan", response_model=None, openapi_extra=schema_of(PlanRequest))
    async def start_plan(request: Request) -> Response:
        """Start a plan of a recipe of the recipes folder. 409 while one runs or a run is on."""
        body = _validated(PlanRequest, await _authorized(request, ctx.guard), request,
                          ints=("seeds", "turns"))
        planner.start(body.recipe, body.seeds, body.turns)
        if media_type(request)[0] == "application/x-www-form-urlencoded":
            return RedirectResponse("/plan", status_code=303)
        return JSONResponse(planner.snapshot(), status_code=202)


def _api_routes(app: FastAPI, ctx: _Pages) -> None:
    runner, guard = ctx.runner, ctx.guard

    @app.post("/api/start", response_model=None, openapi_extra=schema_of(StartRequest))
    async def start(request: Request) -> Response:
        """Start a run: recipe (a file of the recipes folder), operator, serial. 409 if busy."""
        body = _validated(StartRequest, await _authorized(request, guard), request)
        run_id = await asyncio.to_thread(runner.start, body.recipe, body.operator,
                                         body.serial or None, _address(request))
        return _done(request, {"run_id": run_id, "state": runner.live.snapshot()}, 201)

    @app.post("/api/answer", response_model=None, openapi_extra=schema_of(AnswerRequest))
    async def answer(request: Request) -> Response:
        """Answer the pending prompt: continue / abort (placement), retry / abort (failure)."""
        body = _validated(AnswerRequest, await _authorized(request, guard), request,
                          ints=("prompt_id",))
        runner.live.answer(body.prompt_id, body.answer)
        return _done(request, {"ok": True})

    @app.post("/api/abort", response_model=None, openapi_extra=schema_of(EmptyRequest))
    async def abort(request: Request) -> Response:
        """Abort the running run; the station stops the motor. 409 when nothing runs."""
        _validated(EmptyRequest, await _authorized(request, guard), request)
        if not runner.abort("aborted from the web station"):
            raise NoSuchPrompt("no run is in progress")
        return _done(request, {"ok": True})

    @app.post("/api/resume/{run_id}", response_model=None,
              openapi_extra=schema_of(EmptyRequest))
    async def resume(request: Request, run_id: RunId) -> Response:
        """Continue a run left unfinished (as ``calstation resume``). 409 if busy."""
        _validated(EmptyRequest, await _authorized(request, guard), request)
        ctx.require_run(run_id)
        await asyncio.to_thread(runner.resume, run_id, False, _address(request))
        return _done(request, {"run_id": run_id}, 201)
