"""The QA pages' routes: the dashboard (``/dashboard`` and its JSON twin), the run page
(``/runs/N``, its 3D views fetched after it painted) and the favicon."""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal, Protocol

from fastapi import Depends, FastAPI, Path as PathParam, Query, Request
from fastapi.responses import HTMLResponse, Response
from pydantic import AfterValidator

from calstation.storage.db import Run, RunStatus
from calstation.web.middleware import NONCE_KEY
from calstation.web.payloads import JSONPage, ParamName, printable
from calstation.web.settings import MAX_ID
from calstation.web.status import age

if TYPE_CHECKING:
    from collections.abc import Mapping

    from calstation.storage.dashboard import DashboardQuery
    from calstation.storage.dashboard_types import DashboardData
    from calstation.storage.db import Database
    from calstation.storage.report_types import ViewsData
    from calstation.web.security import Guard
    from calstation.web.status import StationStatus

FAVICON = (
    '<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 32 32">'
    '<circle cx="16" cy="16" r="14" fill="#24292f"/>'
    '<ellipse cx="16" cy="21" rx="10" ry="4" fill="none" stroke="#d0d7de" stroke-width="2"/>'
    '<path d="M16 6 L16 19" stroke="#ffd33d" stroke-width="3" stroke-linecap="round"/>'
    '<circle cx="16" cy="6" r="3" fill="#1a7f37"/></svg>')
"""The station's icon: a lidar above its turntable."""

Text = Annotated[str, AfterValidator(printable)]
RunId = Annotated[int, PathParam(ge=1, le=MAX_ID, description="a run id")]


def _query(
    station: Annotated[Text | None, Query(max_length=100)] = None,
    days: Annotated[int, Query(ge=1, le=366)] = 56,
    group: Literal["day", "week"] = "week",
    param: Annotated[list[ParamName] | None, Query()] = None,
    until: Annotated[Text | None, Query(max_length=10)] = None,
) -> DashboardQuery:
    from calstation.storage.dashboard import DashboardQuery

    q = DashboardQuery(station=station or None, days=days, group=group, until=until or None)
    if param:
        q.params = list(dict.fromkeys(p for p in param if p))[:12]
    return q


Q = Annotated[Any, Depends(_query)]  # Any: a DashboardQuery, imported when asked


class Pages(Protocol):
    """What the QA routes use of the web station's page helpers (``app._Pages``)."""

    db: Database
    guard: Guard
    status: StationStatus

    def page(self, request: Request, template: str, context: Mapping[str, object],
             status: int = 200, headers: dict[str, str] | None = None) -> HTMLResponse: ...

    def require_run(self, run_id: int) -> None: ...


def run_page_routes(app: FastAPI, ctx: Pages) -> None:
    """``/runs/N`` (the run's report under the station's bar) and ``/runs/N/views.json`` (its
    3D views, fetched once the page is shown)."""
    @app.get("/runs/{run_id}", response_class=HTMLResponse)
    def run_page(request: Request, run_id: RunId) -> HTMLResponse:
        """A run's page: its report from the database; the 3D views, reconstructed from the
        recordings, follow from ``/runs/N/views.json`` once the page is shown."""
        from calstation.storage.report_html import render_report, report_data

        ctx.require_run(run_id)
        data = report_data(ctx.db, run_id, views=False)
        logged_in = ctx.guard.logged_in(request)
        return HTMLResponse(render_report(
            data, plotly_src="/static/plotly.min.js", nav=True,
            nonce=request.scope.get(NONCE_KEY), views_src=f"/runs/{run_id}/views.json",
            csrf=ctx.guard.page_session(request).csrf if logged_in else "",
            needs_login=not logged_in,
            logged_in=logged_in and ctx.guard.require_token,
            stations=ctx.status.current(), station_age=age, station_now=time.time))

    views_cache: dict[int, ViewsData] = {}

    @app.get("/runs/{run_id}/views.json", response_model=None)
    def run_views(run_id: RunId) -> ViewsData | Response:
        """The run's 3D views (plotly figures, points in binary) and residual histogram: those
        the report step kept in the run folder, else reconstructed from the recordings."""
        from calstation.storage.report import final_calibration
        from calstation.storage.report_html import stored_views, views_data

        ctx.require_run(run_id)
        with ctx.db.session("reading the runs", read_only=True) as s:
            run = s.get(Run, run_id)
            status = run.status if run is not None else None
            final = (final_calibration(run).id if run is not None and run.calibrations
                     else None)
            folder = Path(run.data_dir) if run is not None else None
        stored = stored_views(folder, [final, status]) if folder is not None else None
        if stored is not None:
            return Response(stored, media_type="application/json")
        cached = views_cache.get(run_id)
        if cached is not None and cached["key"] == [final, status] and status != RunStatus.RUNNING:
            return cached
        got = views_data(ctx.db, run_id)
        if len(views_cache) >= 8:
            views_cache.pop(next(iter(views_cache)))
        views_cache[run_id] = got
        return got



def dashboard_routes(app: FastAPI, ctx: Pages) -> None:
    """``/dashboard``, ``/dashboard.json`` and ``/favicon.ico`` on ``app`` (``ctx``: the
    pages' rendering helpers of :mod:`.app`)."""

    def data(q: DashboardQuery) -> DashboardData:
        from calstation.storage.dashboard import dashboard

        return dashboard(ctx.db, q)

    @app.get("/dashboard.json")
    def dashboard_json(q: Q) -> JSONPage:
        """The dashboard's data: yields, the failure Pareto, control charts, comparison."""
        return dict(data(q))

    @app.get("/dashboard", response_class=HTMLResponse)
    def dashboard_page(request: Request, q: Q) -> HTMLResponse:
        """The QA dashboard: yield and first-pass yield, failures, cycle time, control
        charts with the Western Electric rules, station against station."""
        from calstation.storage.dashboard import CHART_PARAMS
        from calstation.storage.dashboard_figures import figures

        d = data(q)
        page: HTMLResponse = ctx.page(request, "dashboard.html", {
            "d": d, "figures": figures(d), "chart_params": CHART_PARAMS,
            "query": str(request.url.query)})
        return page

    @app.get("/favicon.ico")
    def favicon() -> Response:
        """The station's icon (SVG)."""
        return Response(FAVICON, media_type="image/svg+xml",
                        headers={"Cache-Control": "max-age=86400"})
