"""The web station's routes: operator, runs, trends, api. Thin: they render and answer.

Every page has a JSON twin at the same path with ``.json`` (``/state.json`` for the operator
page). State-changing requests are POSTs under ``/api/`` checked by :class:`security.Guard`.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

from fastapi import Depends, FastAPI, Request
from fastapi.responses import (
    FileResponse,
    HTMLResponse,
    JSONResponse,
    PlainTextResponse,
    RedirectResponse,
    Response,
    StreamingResponse,
)

from calstation.errors import CalstationError
from calstation.storage.db import Database, Run
from calstation.storage.templating import environment
from calstation.web.live import Busy, NoSuchPrompt, Runner
from calstation.web.security import (
    CSRF_COOKIE,
    SESSION_COOKIE,
    AccessError,
    Guard,
    is_local_host,
    new_csrf_value,
)

STATIC = Path(__file__).parent / "static"
EVENT_KEEPALIVE_S = 15.0
EVENT_MIN_PERIOD_S = 0.2


def create_app(
    db: Database,
    *,
    data_dir: Path,
    recipes_dir: Path,
    host: str = "127.0.0.1",
    token: str | None = None,
) -> FastAPI:
    """The web station over ``db``; runs go to ``data_dir/runs/N``; recipes offered from
    ``recipes_dir``. Bound to a non-local ``host`` it needs ``token`` (see :mod:`.security`)."""
    guard = Guard(token, require_token=not is_local_host(host))
    runner = Runner(db, data_dir, recipes_dir)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        yield
        # the server stops: abort a run still in progress, so the motor is stopped
        if runner.abort("the web station was stopped"):
            await asyncio.to_thread(runner.join, 30.0)

    # no Swagger UI: it loads its scripts from a CDN, and the station has no internet
    app = FastAPI(title="calstation station", lifespan=lifespan, docs_url=None,
                  redoc_url=None, openapi_url="/api/openapi.json")
    app.state.runner = runner
    app.state.guard = guard
    app.state.db = db
    ctx = _Pages(db, runner, guard)

    @app.exception_handler(CalstationError)
    async def _calstation_error(request: Request, exc: CalstationError) -> Response:
        status = (exc.status if isinstance(exc, AccessError)
                  else 409 if isinstance(exc, Busy | NoSuchPrompt) else 400)
        if "/api/" in request.url.path or _wants_json(request):
            return JSONResponse({"error": str(exc)}, status_code=status)
        return ctx.page(request, "message.html", {"title": "refused", "message": str(exc)},
                        status=status)

    @app.middleware("http")
    async def _csrf_cookie(request: Request,
                           call_next: Callable[[Request], Awaitable[Response]]) -> Response:
        response = await call_next(request)
        value = getattr(request.state, "csrf", None)
        if value and CSRF_COOKIE not in request.cookies:
            response.set_cookie(CSRF_COOKIE, value, httponly=False, samesite="strict")
        return response

    _operator_routes(app, ctx)
    _run_routes(app, ctx)
    _fleet_routes(app, ctx, recipes_dir)
    _api_routes(app, ctx)
    return app


def _wants_json(request: Request) -> bool:
    return request.url.path.endswith(".json") or "application/json" in request.headers.get(
        "accept", "").split(",")[0]


class _Pages:
    """Rendering helpers shared by the route groups."""

    def __init__(self, db: Database, runner: Runner, guard: Guard) -> None:
        self.db, self.runner, self.guard = db, runner, guard

    def csrf(self, request: Request) -> str:
        value = request.cookies.get(CSRF_COOKIE)
        if not value:
            value = getattr(request.state, "csrf", None) or new_csrf_value()
            request.state.csrf = value
        return value

    def page(self, request: Request, template: str, context: dict[str, Any],
             status: int = 200) -> HTMLResponse:
        html = environment().get_template(template).render(
            request=request, csrf=self.csrf(request), needs_login=self.needs_login(request),
            busy=self.runner.busy, **context)
        return HTMLResponse(html, status_code=status)

    def needs_login(self, request: Request) -> bool:
        if not self.guard.require_token:
            return False
        return request.cookies.get(SESSION_COOKIE) != self.guard.session_value()


# --- operator --------------------------------------------------------------------------------
def _operator_routes(app: FastAPI, ctx: _Pages) -> None:
    runner = ctx.runner

    @app.get("/", response_class=HTMLResponse)
    def operator_page(request: Request) -> HTMLResponse:
        """The operator page: start a run, answer its prompts, follow it live."""
        from calstation.station.operator import default_operator

        return ctx.page(request, "operator.html", {
            "state": runner.live.snapshot(), "recipes": runner.recipes(),
            "default_operator": default_operator(), "resumable": _resumable(ctx.db),
        })

    @app.get("/state.json")
    def state_json() -> dict[str, Any]:
        """The operator page's JSON twin: the live state of the current (or last) run."""
        return {**runner.live.snapshot(), "recipes": runner.recipes()}

    @app.get("/events")
    async def events(request: Request) -> StreamingResponse:
        """Server-sent events: a ``state`` event with the snapshot whenever it changes."""
        async def stream() -> AsyncIterator[str]:
            version = -1
            waited = 0.0
            while not await request.is_disconnected():
                current = await asyncio.to_thread(runner.live.wait_change, version, 1.0)
                if current != version:
                    version = current
                    waited = 0.0
                    yield f"event: state\ndata: {json.dumps(runner.live.snapshot())}\n\n"
                    # coalesce bursts (progress, lidar lines): a page needs a few frames a second
                    await asyncio.sleep(EVENT_MIN_PERIOD_S)
                else:
                    waited += 1.0
                    if waited >= EVENT_KEEPALIVE_S:
                        waited = 0.0
                        yield ": keep-alive\n\n"

        return StreamingResponse(stream(), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-store"})

    @app.get("/login", response_class=HTMLResponse)
    def login_page(request: Request) -> HTMLResponse:
        """Enter the station token (only needed on a non-local address)."""
        return ctx.page(request, "login.html", {"error": None})

    @app.post("/login", response_model=None, dependencies=WRITE)
    async def login(request: Request) -> Response:
        form = await request.form()
        token = str(form.get("token") or "")
        if not ctx.guard.require_token:
            return RedirectResponse("/", status_code=303)
        if not ctx.guard.check_token(token):
            return ctx.page(request, "login.html", {"error": "wrong station token"}, status=401)
        response = RedirectResponse("/", status_code=303)
        response.set_cookie(SESSION_COOKIE, ctx.guard.session_value(), httponly=True,
                            samesite="strict")
        return response

    @app.get("/static/{name}")
    def static(name: str) -> Response:
        """The pages' script and style, and plotly.js from the installed plotly package."""
        if name == "plotly.min.js":
            from calstation.storage.report_html import plotly_js

            return Response(plotly_js(), media_type="text/javascript",
                            headers={"Cache-Control": "max-age=86400"})
        path = STATIC / name
        if "/" in name or not path.is_file():
            return PlainTextResponse("not found", status_code=404)
        return FileResponse(path)


def _resumable(db: Database) -> list[dict[str, Any]]:
    """Runs left ``running`` by a process that is gone (a killed server), newest first."""
    import os
    import socket

    from sqlalchemy import select

    from calstation.station.runs import process_alive

    out = []
    with db.session("reading the runs", read_only=True) as s:
        for run in s.scalars(select(Run).where(Run.status == "running").order_by(Run.id.desc())
                             .limit(20)):
            if run.host == socket.gethostname() and run.pid is not None and (
                    run.pid == os.getpid() or process_alive(run.pid)):
                continue
            out.append({"id": run.id, "recipe": run.recipe_name, "operator": run.operator,
                        "started_at": str(run.started_at)[:19]})
    return out


# --- runs, trends, compare -------------------------------------------------------------------
def _run_routes(app: FastAPI, ctx: _Pages) -> None:
    from calstation.storage import qa

    def history_filter(request: Request) -> qa.HistoryFilter:
        q = request.query_params
        try:
            limit = int(q.get("limit") or 200)
        except ValueError as exc:
            raise qa.QueryError(f"limit: {q.get('limit')!r} is not a number") from exc
        return qa.HistoryFilter(
            station=q.get("station") or None, status=q.get("status") or None,
            operator=q.get("operator") or None, serial=q.get("serial") or None,
            since=q.get("since") or None, until=q.get("until") or None, limit=limit)

    @app.get("/runs.json")
    def runs_json(request: Request) -> dict[str, Any]:
        """History as JSON (stored units)."""
        f = history_filter(request)
        with ctx.db.session("reading the runs", read_only=True) as s:
            return {"filters": f.as_dict(), "runs": qa.history(s, f)}

    @app.get("/runs", response_class=HTMLResponse)
    def runs_page(request: Request) -> HTMLResponse:
        """History, filtered by station, status, operator, serial and date."""
        f = history_filter(request)
        with ctx.db.session("reading the runs", read_only=True) as s:
            rows, options = qa.history(s, f), qa.choices(s)
        return ctx.page(request, "history.html", {"rows": rows, "f": f, "options": options,
                                                  "query": str(request.url.query)})

    @app.get("/runs/{run_id}.json")
    def run_json(run_id: int) -> dict[str, Any]:
        """One run as JSON: what its page shows, without the 3D point clouds."""
        from calstation.storage.report_html import report_data

        return report_data(ctx.db, run_id, views=False)

    @app.get("/runs/{run_id}", response_class=HTMLResponse)
    def run_page(run_id: int) -> HTMLResponse:
        """A run's page: its report, rendered from the database and recordings."""
        from calstation.storage.report_html import render_report, report_data

        data = report_data(ctx.db, run_id)
        return HTMLResponse(render_report(data, plotly_src="/static/plotly.min.js", nav=True))

    @app.get("/runs/{run_id}/report.html", response_model=None)
    def run_report_file(run_id: int) -> Response:
        """The self-contained ``report.html`` of the run folder (opens offline)."""
        with ctx.db.session("reading the runs", read_only=True) as s:
            run = s.get(Run, run_id)
            folder = Path(run.data_dir) if run is not None else None
        if folder is None or not (folder / "report.html").is_file():
            return PlainTextResponse(f"run {run_id} has no report.html", status_code=404)
        return FileResponse(folder / "report.html", media_type="text/html")

    @app.get("/runs/{run_id}/export.{fmt}")
    def export(run_id: int, fmt: str) -> Response:
        """The run's final calibration as yaml, json, urdf or csv (a download)."""
        from calstation.storage.report import export_calibration, get_run

        with ctx.db.session("reading the runs", read_only=True) as s:
            text = export_calibration(get_run(s, run_id), fmt)
        media = {"json": "application/json", "csv": "text/csv", "urdf": "application/xml"}
        return Response(text, media_type=media.get(fmt, "text/yaml"), headers={
            "Content-Disposition": f'attachment; filename="run-{run_id}-calibration.{fmt}"'})

    def trend_data(request: Request) -> dict[str, Any]:
        q = request.query_params
        with ctx.db.session("reading the runs", read_only=True) as s:
            stations = qa.choices(s)["stations"]
            station = q.get("station") or (stations[0] if stations else "")
            param = q.get("param") or "tx"
            t = qa.trend(s, station, param) if station else {
                "station": "", "param": param, "limit_kind": "drift", "points": []}
        return {**t, "stations": stations,
                "params": list(qa.TREND_PARAMS + qa.CUBE_TREND_PARAMS)}

    @app.get("/trends.json")
    def trends_json(request: Request) -> dict[str, Any]:
        """A parameter's trend as JSON (stored units)."""
        return trend_data(request)

    @app.get("/trends", response_class=HTMLResponse)
    def trends_page(request: Request) -> HTMLResponse:
        """Trend plot of one parameter by date, with 1σ bars and the drift limit."""
        t = trend_data(request)
        k, unit = qa.display_scale(t["param"])
        return ctx.page(request, "trends.html", {"t": t, "scale": k, "unit": unit,
                                                 "figure": qa.trend_figure(t)})

    def compare_data(request: Request) -> dict[str, Any]:
        from calstation.storage.report_html import report_data

        q = request.query_params
        try:
            a, b = int(q.get("a", "")), int(q.get("b", ""))
        except ValueError as exc:
            raise qa.QueryError("compare needs two run ids: ?a=RUN&b=RUN") from exc
        da, db_ = report_data(ctx.db, a, views=False), report_data(ctx.db, b, views=False)
        return {"a": da, "b": db_, "rows": qa.compare(da, db_)}

    @app.get("/compare.json")
    def compare_json(request: Request) -> dict[str, Any]:
        """Two runs side by side as JSON."""
        return compare_data(request)

    @app.get("/compare", response_class=HTMLResponse)
    def compare_page(request: Request) -> HTMLResponse:
        """Two runs side by side: calibrations, cube checks, verdicts."""
        if not request.query_params.get("a"):
            return ctx.page(request, "message.html", {
                "title": "compare", "message": "Pick two runs on the history page."})
        return ctx.page(request, "compare.html", compare_data(request))


# --- campaigns, metrics ----------------------------------------------------------------------
def recipe_stations(recipes_dir: Path) -> list[str]:
    """The ``station.id`` of each recipe of the recipes folder (the stations this server runs)."""
    import yaml

    out: set[str] = set()
    for path in sorted(recipes_dir.glob("*.yaml")) if recipes_dir.is_dir() else []:
        try:
            data = yaml.safe_load(path.read_text(encoding="utf-8"))
            out.add(str(data["station"]["id"]))
        except (OSError, yaml.YAMLError, KeyError, TypeError):
            continue
    return sorted(out)


def _fleet_routes(app: FastAPI, ctx: _Pages, recipes_dir: Path) -> None:
    from calstation.fleet.metrics import StationMetrics

    metrics = StationMetrics(ctx.db, lambda: recipe_stations(recipes_dir),
                             lambda: ctx.runner.busy)

    @app.get("/metrics")
    def metrics_page() -> Response:
        """Prometheus metrics of this server's stations (docs/fleet.md)."""
        from prometheus_client import CONTENT_TYPE_LATEST

        return Response(metrics.render(), media_type=CONTENT_TYPE_LATEST)

    def campaigns() -> list[dict[str, Any]]:
        from calstation.fleet.view import campaign_list

        with ctx.db.session("reading the campaigns", read_only=True) as s:
            return campaign_list(s)

    @app.get("/campaigns.json")
    def campaigns_json() -> dict[str, Any]:
        """The re-processing campaigns, newest first."""
        return {"campaigns": campaigns()}

    @app.get("/campaigns", response_class=HTMLResponse)
    def campaigns_page(request: Request) -> HTMLResponse:
        """The re-processing campaigns (``calstation reprocess``), newest first."""
        return ctx.page(request, "campaigns.html", {"campaigns": campaigns()})

    def campaign(campaign_id: int) -> dict[str, Any]:
        from calstation.fleet.view import campaign_data

        with ctx.db.session("reading the campaign", read_only=True) as s:
            return campaign_data(s, campaign_id)

    @app.get("/campaigns/{campaign_id}.json")
    def campaign_json(campaign_id: int) -> dict[str, Any]:
        """One campaign as JSON: what ``calstation reprocess --json`` prints."""
        return campaign(campaign_id)

    @app.get("/campaigns/{campaign_id}", response_class=HTMLResponse)
    def campaign_page(request: Request, campaign_id: int) -> HTMLResponse:
        """One campaign: counts, the histogram of changes, the flagged units, each run linked."""
        return ctx.page(request, "campaign.html", {"data": campaign(campaign_id),
                                                   "link_base": ""})


# --- api (state-changing) --------------------------------------------------------------------
async def _writer(request: Request) -> None:
    """Dependency of every state-changing route: the token and CSRF checks (see ``security``)."""
    form_csrf = None
    if request.headers.get("content-type", "").startswith("application/x-www-form-urlencoded"):
        value = (await request.form()).get("csrf")  # the form is cached for the route
        form_csrf = value if isinstance(value, str) else None
    guard: Guard = request.app.state.guard
    guard.check(method=request.method, headers=dict(request.headers),
                cookies=dict(request.cookies), form_csrf=form_csrf,
                host_url=str(request.base_url), login=request.url.path == "/login")


WRITE = [Depends(_writer)]


async def _payload(request: Request) -> dict[str, Any]:
    if request.headers.get("content-type", "").startswith("application/json"):
        data = await request.json()
        return data if isinstance(data, dict) else {}
    form = await request.form()
    return {k: v for k, v in form.items() if isinstance(v, str)}


def _done(request: Request, body: dict[str, Any], status: int = 200) -> Response:
    """JSON for scripts, a redirect back to the operator page for a plain form post."""
    if request.headers.get("content-type", "").startswith("application/x-www-form-urlencoded"):
        return RedirectResponse("/", status_code=303)
    return JSONResponse(body, status_code=status)


def _api_routes(app: FastAPI, ctx: _Pages) -> None:
    runner = ctx.runner

    @app.post("/api/start", response_model=None, dependencies=WRITE)
    async def start(request: Request) -> Response:
        """Start a run: recipe (a file of the recipes folder), operator, serial. 409 if busy."""
        p = await _payload(request)
        run_id = runner.start(str(p.get("recipe") or ""), str(p.get("operator") or ""),
                              str(p.get("serial") or "") or None)
        return _done(request, {"run_id": run_id, "state": runner.live.snapshot()}, 201)

    @app.post("/api/answer", response_model=None, dependencies=WRITE)
    async def answer(request: Request) -> Response:
        """Answer the pending prompt: continue / abort (placement), retry / abort (failure)."""
        p = await _payload(request)
        try:
            prompt_id = int(p.get("prompt_id") or 0)
        except ValueError as exc:
            raise NoSuchPrompt("prompt_id must be a number") from exc
        runner.live.answer(prompt_id, str(p.get("answer") or ""))
        return _done(request, {"ok": True})

    @app.post("/api/abort", response_model=None, dependencies=WRITE)
    async def abort(request: Request) -> Response:
        """Abort the running run; the station stops the motor. 409 when nothing runs."""
        if not runner.abort("aborted from the web station"):
            raise NoSuchPrompt("no run is in progress")
        return _done(request, {"ok": True})

    @app.post("/api/resume/{run_id}", response_model=None, dependencies=WRITE)
    async def resume(request: Request, run_id: int) -> Response:
        """Continue a run left unfinished (as ``calstation resume``). 409 if busy."""
        runner.resume(run_id)
        return _done(request, {"run_id": run_id}, 201)
