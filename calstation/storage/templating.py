"""The Jinja2 environment shared by the web pages and the self-contained run report."""

from __future__ import annotations

import datetime as dt
import json
import math
from functools import cache
from typing import Any

from jinja2 import Environment, PackageLoader, select_autoescape


def _num(value: Any, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "—"
    if isinstance(value, int | float):
        return f"{value:.{digits}f}"
    return str(value)


def _mm(value: Any, digits: int = 3) -> str:
    return "—" if value is None else _num(float(value) * 1000.0, digits)


def duration(seconds: Any) -> str:
    """A duration as a person reads it: ``0.4 s``, ``12 s``, ``2 min 05 s``, ``1 h 02 min``."""
    if seconds is None or not math.isfinite(float(seconds)):
        return "—"
    s = float(seconds)
    if s < 10:
        return f"{s:.1f} s"
    whole = round(s)
    if whole < 60:
        return f"{whole} s"
    if whole < 3600:
        return f"{whole // 60} min {whole % 60:02d} s"
    return f"{whole // 3600} h {whole % 3600 // 60:02d} min"


def when(value: Any, seconds: bool = False) -> str:
    """A stored time (ISO-8601 text or datetime, UTC) for people: ``2026-11-23 14:05 UTC``
    (``seconds``: ``14:05:09``); an em dash when absent, the text itself when not a time."""
    if value is None or value == "":
        return "—"
    try:
        t = value if isinstance(value, dt.datetime) else dt.datetime.fromisoformat(str(value))
    except ValueError:
        return str(value)
    if t.tzinfo is not None:
        t = t.astimezone(dt.UTC)
    return t.strftime("%Y-%m-%d %H:%M:%S" if seconds else "%Y-%m-%d %H:%M") + " UTC"


@cache
def environment() -> Environment:
    """Templates from ``calstation/web/templates``, HTML auto-escaped."""
    env = Environment(
        loader=PackageLoader("calstation", "web/templates"),
        autoescape=select_autoescape(["html"]),
        trim_blocks=True,
        lstrip_blocks=True,
    )
    env.filters["num"] = _num
    env.filters["mm"] = _mm
    env.filters["duration"] = duration
    env.filters["when"] = when
    env.filters["tojson_compact"] = lambda v: json.dumps(v, separators=(",", ":"))
    return env
