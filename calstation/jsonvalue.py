"""JSON-shaped values: what ``json.loads`` returns and ``json.dumps`` accepts.

Use these instead of ``Any`` for payloads that cross a JSON boundary (the web's
JSON pages, ``--json`` output, stored JSON columns, reports). ``JSONObject`` is
for values calstation builds and reads; take ``Mapping[str, object]`` in a
parameter when callers pass narrower dicts (``dict`` is invariant).
"""

from __future__ import annotations

from typing import TypeAlias

JSONScalar: TypeAlias = str | int | float | bool | None
JSONValue: TypeAlias = JSONScalar | list["JSONValue"] | dict[str, "JSONValue"]
JSONObject: TypeAlias = dict[str, JSONValue]

__all__ = ["JSONObject", "JSONScalar", "JSONValue"]
