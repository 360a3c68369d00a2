"""The Jinja2 environment shared by the web pages and the self-contained run report."""

from __future__ import annotations

import json
import math
from functools import cache

from jinja2 import Environment, PackageLoader, select_autoescape
from markupsafe import Markup

from calstation import display


def _num(value: object, digits: int = 3) -> str:
    """A plain count or ratio with ``digits`` decimals (quantities go through ``q``)."""
    if not isinstance(value, int | float) or isinstance(value, bool) \
            or not math.isfinite(float(value)):
        return display.MISSING if value is None or isinstance(value, int | float) else str(value)
    return display.plain(float(value), digits)


def _quantity(value: object, name: str, signed: bool = False, unit: bool = True) -> str:
    """``value`` (stored unit) of quantity ``name`` as :func:`calstation.display.number`."""
    return display.number(name, value, signed=signed, unit=unit)


def _with_sigma(value: object, name: str, sigma: object, unit: bool = True) -> str:
    """:func:`calstation.display.with_sigma`."""
    return display.with_sigma(name, value, sigma, unit=unit)


@cache
def plotly_js() -> str:
    """plotly.js, minified, from the installed ``plotly`` package (no network)."""
    from plotly.offline import get_plotlyjs

    return str(get_plotlyjs())


@cache
def plotly_style_ids() -> tuple[str, ...]:
    """The ids of the ``<style>`` elements plotly.js adds at load time unless an element with
    that id is there already (its map library's rules). A page that puts an empty one of each
    in its head, with the policy's nonce, keeps plotly from adding a style the page's
    Content-Security-Policy would refuse (an error in every page's console); the station draws
    no maps."""
    import re

    return tuple(dict.fromkeys(re.findall(
        r'getElementById\("([0-9a-f]{16,})"\)\)\{var \w+=document\.createElement\("style"\)',
        plotly_js())))


def css_string(text: object) -> Markup:
    """``text`` as a CSS string, for a ``content:`` in a ``<style>``: every character but
    letters, digits and a few marks written as a CSS escape, so no text (a serial, a station's
    name) can end the string or the style."""
    safe = set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789 .,:_-·—()")
    body = "".join(c if c in safe else f"\\{ord(c):x} " for c in str(text))
    return Markup(f'"{body}"')


duration = display.duration
when = display.when


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
    env.filters["q"] = _quantity
    env.filters["qs"] = _with_sigma
    env.filters["sigma"] = lambda v, name, unit=True: display.sigma_text(name, v, unit)
    env.filters["sci"] = display.scientific
    env.filters["percent"] = display.percent
    env.filters["count"] = display.count
    env.filters["megabytes"] = display.megabytes
    env.filters["css_string"] = css_string
    env.filters["duration"] = duration
    env.filters["when"] = when
    env.globals["quantity"] = display.quantity
    env.globals["plotly_style_ids"] = plotly_style_ids
    env.globals["NOT_ESTIMATED"] = display.NOT_ESTIMATED
    env.filters["tojson_compact"] = lambda v: json.dumps(v, separators=(",", ":"))
    return env
