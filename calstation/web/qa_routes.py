"""The QA dashboard's routes (``/dashboard`` and its JSON twin) and the favicon."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Any, Literal

from fastapi import Depends, FastAPI, Query, Request
from fastapi.responses import HTMLResponse, Response
from pydantic import AfterValidator

from calstation.web.payloads import ParamName, printable

if TYPE_CHECKING:
    from calstation.storage.dashboard import DashboardQuery

FAVICON = (
    '<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 32 32">'
    '<circle cx="16" cy="16" r="14" fill="#24292f"/>'
    '<ellipse cx="16" cy="21" rx="10" ry="4" fill="none" stroke="#d0d7de" stroke-width="2"/>'
    '<path d="M16 6 L16 19" stroke="#ffd33d" stroke-width="3" stroke-linecap="round"/>'
    '<circle cx="16" cy="6" r="3" fill="#1a7f37"/></svg>')
"""The station's icon: a lidar above its turntable."""

Text = Annotated[str, AfterValidator(printable)]


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


Q = Annotated[Any, Depends(_query)]


def dashboard_routes(app: FastAPI, ctx: Any) -> None:
    """``/dashboard``, ``/dashboard.json`` and ``/favicon.ico`` on ``app`` (``ctx``: the
    pages' rendering helpers of :mod:`.app`)."""

    def data(q: DashboardQuery) -> dict[str, Any]:
        from calstation.storage.dashboard import dashboard

        with ctx.db.session("reading the runs", read_only=True) as s:
            return dashboard(s, q)

    @app.get("/dashboard.json")
    def dashboard_json(q: Q) -> dict[str, Any]:
        """The dashboard's data: yields, the failure Pareto, control charts, comparison."""
        return data(q)

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
