"""A campaign as data — what ``calstation reprocess --json`` prints, the web station's QA page
and its JSON twin show — and as the self-contained HTML report of ``--report``.

Values are stored units (metres, radians); the pages show millimetres and degrees. The report
file carries its style and its histogram (inline SVG) and no script, so it opens anywhere and
reads the same under the web station's content policy.
"""

from __future__ import annotations

import math

from sqlalchemy import select
from sqlalchemy.orm import Session, selectinload

from calstation.errors import FleetError
from calstation.fleet.tolerance import Tolerance
from calstation.storage.db import Campaign, CampaignRun, Run
from calstation.storage.report import iso, json_float

HISTOGRAM_BINS = 20
"""Bars of the histogram of changes in the work volume."""


def _serial(run: Run) -> str | None:
    from calstation.storage.report_html import unit_serial

    return unit_serial(run.unit_serial, None, [
        {"name": s.name, "status": s.status, "result": s.result} for s in run.steps])


def run_item(row: CampaignRun, run: Run, serial: str | None) -> dict[str, object]:
    """One run of a campaign: its run (serial, station, status), outcome, flags and every field
    of its comparison (:func:`calstation.fleet.compare.compare`); a run skipped or failed has
    no comparison: its fields are then None (``refused`` empty). ``serial``: the unit's."""
    comparison = dict(row.comparison or {})
    return {
        "run_id": row.run_id, "serial": serial, "station": run.station.name,
        "status": run.status, "started_at": iso(run.started_at), "outcome": row.outcome,
        "flagged": row.flagged, "flags": comparison.pop("flags", []),
        "calibration_id": row.calibration_id, "error": row.error, "seconds": row.seconds,
        "worker": row.worker, "difference": None, "change_in_work_volume_m": None,
        "predicted_error": None, "accepted": None, "refused": [], "cube": None,
        "work_volume": None, **comparison,
    }


def campaign_brief(c: Campaign) -> dict[str, object]:
    """The campaign's own fields."""
    return {"id": c.id, "key": c.key, "selection": c.selection, "strategy": c.strategy,
            "tolerance": c.tolerance, "tolerance_text": Tolerance.from_dict(c.tolerance).describe(),
            "engine": c.engine, "host": c.host, "selected": c.selected,
            "started_at": iso(c.started_at), "finished_at": iso(c.finished_at)}


def campaign_data(
    session: Session, campaign_id: int, run_ids: list[int] | None = None
) -> dict[str, object]:
    """The campaign ``campaign_id``: ``campaign`` (its fields), ``runs`` (one item per row, of
    ``run_ids`` only when given, in run order), ``totals``, ``histogram`` (of the change in the
    work volume), and the ``flagged`` units by serial. :class:`FleetError` when there is none."""
    campaign = session.get(Campaign, campaign_id)
    if campaign is None:
        raise FleetError(f"no campaign with id {campaign_id} in the database")
    stmt = (select(CampaignRun, Run).join(Run, CampaignRun.run_id == Run.id)
            .where(CampaignRun.campaign_id == campaign_id).order_by(CampaignRun.run_id)
            .options(selectinload(Run.steps), selectinload(Run.station)))
    if run_ids is not None:
        stmt = stmt.where(CampaignRun.run_id.in_(run_ids))
    rows = [(row, _serial(run), run) for row, run in session.execute(stmt).all()]
    runs = [run_item(row, run, serial) for row, serial, run in rows]
    selected = len(run_ids) if run_ids is not None else max(campaign.selected, len(runs))
    tolerance = Tolerance.from_dict(campaign.tolerance)
    flagged = sorted(((row.run_id, serial, item) for (row, serial, _), item
                      in zip(rows, runs, strict=True) if row.flagged),
                     key=lambda f: (f[1] or "", f[0]))
    return {
        "campaign": campaign_brief(campaign),
        "totals": totals(runs, selected),
        "runs": runs,
        "histogram": histogram([json_float(r["change_in_work_volume_m"]) for r in runs
                                if r.get("change_in_work_volume_m") is not None],
                               tolerance.volume_m),
        "flagged": [item for _, _, item in flagged],
    }


def totals(runs: list[dict[str, object]], selected: int) -> dict[str, int]:
    """Counts: selected, each outcome, flagged, refused by today's engine, and left (selected
    runs without a row)."""
    out = {"selected": selected, "reprocessed": 0, "skipped": 0, "failed": 0}
    for r in runs:
        outcome = str(r["outcome"])
        out[outcome] = out.get(outcome, 0) + 1
    out["flagged"] = sum(1 for r in runs if r["flagged"])
    out["refused"] = sum(1 for r in runs if r.get("refused"))
    out["left"] = max(0, selected - len(runs))
    return out


def _nice_width(span: float, bins: int) -> float:
    """A round bar width (1, 2 or 5 × 10ⁿ) covering ``span`` in about ``bins`` bars."""
    raw = max(span, 1e-9) / bins
    power = 10 ** math.floor(math.log10(raw))
    return float(next(k * power for k in (1, 2, 5, 10) if k * power >= raw))


def histogram(values_m: list[float], tolerance_m: float | None = None) -> dict[str, object]:
    """Bars of the changes in the work volume (mm): ``bars`` (``x0``, ``x1`` mm, ``count``, and
    where to draw them in a 600 × 200 plot: ``x``, ``y``, ``w``, ``h``), ``ticks`` and the
    tolerance's position when given."""
    mm = [v * 1e3 for v in values_m]
    top = max([*mm, (tolerance_m or 0.0) * 1e3 * 1.1, 1e-3])
    width = _nice_width(top, HISTOGRAM_BINS)
    n = max(1, math.ceil(top / width + 1e-9))
    counts = [0] * n
    for v in mm:
        counts[min(n - 1, int(v // width))] += 1
    peak = max(counts) or 1
    plot_w, plot_h, left, bottom = 600.0, 200.0, 40.0, 220.0
    bar_w = plot_w / n
    bars = [{"x0": k * width, "x1": (k + 1) * width, "count": c,
             "x": left + k * bar_w, "w": max(bar_w - 1.0, 1.0),
             "h": plot_h * c / peak, "y": bottom - plot_h * c / peak}
            for k, c in enumerate(counts)]
    step = max(1, n // 5)
    ticks = [{"x": left + k * bar_w, "label": f"{k * width:g}"} for k in range(0, n + 1, step)]
    tol = None if tolerance_m is None else left + plot_w * min(tolerance_m * 1e3 / (n * width), 1)
    return {"bars": bars, "ticks": ticks, "peak": peak, "count": len(mm), "tolerance_x": tol,
            "tolerance_mm": None if tolerance_m is None else tolerance_m * 1e3}


def render_report(data: dict[str, object], link_base: str | None = None) -> str:
    """The self-contained HTML report of :func:`campaign_data`; each run links to
    ``<link_base>/runs/N`` (its page on ``calstation serve``) when ``link_base`` is given."""
    from calstation.storage.templating import environment

    return environment().get_template("campaign_report.html").render(
        data=data, link_base=None if link_base is None else link_base.rstrip("/"))


def campaign_list(session: Session, limit: int = 100) -> list[dict[str, object]]:
    """The newest campaigns, each with its rows and flagged units counted."""
    from sqlalchemy import func

    counts = dict(session.execute(
        select(CampaignRun.campaign_id, func.count()).group_by(CampaignRun.campaign_id)
    ).tuples().all())
    flagged = dict(session.execute(
        select(CampaignRun.campaign_id, func.count()).where(CampaignRun.flagged)
        .group_by(CampaignRun.campaign_id)
    ).tuples().all())
    return [{**campaign_brief(c), "rows": counts.get(c.id, 0), "flagged": flagged.get(c.id, 0)}
            for c in session.scalars(select(Campaign).order_by(Campaign.id.desc()).limit(limit))]
