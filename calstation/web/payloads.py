"""What the state-changing requests may carry, and how their bodies are read.

Bodies are JSON (scripts, the page's script) or a plain HTML form
(``application/x-www-form-urlencoded``); any other content type is refused (415). A body that
is not what it claims to be (not UTF-8, not JSON, a JSON constant such as ``Infinity``, a key
given twice, nested past reason) is refused with 400; then the fields are validated by strict
pydantic models (422): no unknown field, no type coercion (a ``prompt_id`` of ``1.5``,
``true`` or ``"1"`` is not a prompt id), lengths and characters within what the database
stores: operator and serial by the one check every front end uses
(:mod:`calstation.storage.db.fields`).
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from typing import Annotated, Any, Literal, NoReturn, TypeAlias
from urllib.parse import parse_qsl

from fastapi import Request
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, StringConstraints
from starlette.exceptions import HTTPException

from calstation.storage.db.fields import (
    NAME_LENGTH,
    SERIAL_LENGTH,
    operator_name,
    printable as printable,
    unit_serial,
)
from calstation.web.sessions import CSRF_FIELD
from calstation.web.tokens import TOKEN_MAX_LENGTH

MAX_PROMPT_ID = 2**53 - 1
"""Prompt ids are counted from 1; this is the largest a browser's script holds exactly."""


Text = Annotated[str, AfterValidator(printable)]
OperatorName = Annotated[
    str, StringConstraints(strip_whitespace=True, min_length=1, max_length=NAME_LENGTH),
    AfterValidator(operator_name)]
Serial = Annotated[str, StringConstraints(strip_whitespace=True, max_length=SERIAL_LENGTH),
                   AfterValidator(unit_serial)]
RecipeFile = Annotated[str, StringConstraints(min_length=1, max_length=200,
                                              pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]*\.yaml$")]


class _Strict(BaseModel):
    model_config = ConfigDict(strict=True, extra="forbid", frozen=True)


class StartRequest(_Strict):
    """``POST /api/start``: a recipe file of the recipes folder, the operator, the unit's
    serial (empty: the lidar's own)."""

    recipe: RecipeFile
    operator: OperatorName
    serial: Serial | None = None


class PlanRequest(_Strict):
    """``POST /api/plan``: a recipe file of the recipes folder, the simulated stations per
    figure and the turns of the simulated spin scans."""

    recipe: RecipeFile
    seeds: Annotated[int, Field(ge=1, le=5)] = 2
    turns: Annotated[int, Field(ge=1, le=4)] = 2


class AnswerRequest(_Strict):
    """``POST /api/answer``: the pending prompt's id and one of the answers it offers."""

    prompt_id: Annotated[int, Field(ge=1, le=MAX_PROMPT_ID)]
    answer: Literal["continue", "retry", "abort"]


class EmptyRequest(_Strict):
    """A request that carries nothing (``/api/abort``, ``/api/resume/N``, ``/logout``)."""


class LoginRequest(_Strict):
    """``POST /login``: the station token."""

    token: Annotated[str, StringConstraints(min_length=1, max_length=TOKEN_MAX_LENGTH)]


JSONPage: TypeAlias = dict[str, Any]  # Any: FastAPI's response model of a JSON page: as is
"""What a JSON page returns. FastAPI validates a return value against its annotation; this one
passes any mapping through unchanged (the pages' JSON is typed where it is built)."""


class BadBody(HTTPException):
    """A body that is not what its content type says (400) or of a type not taken (415)."""


def _no_constants(name: str) -> NoReturn:
    raise ValueError(f"{name} is not JSON")


def _no_duplicates(pairs: Iterable[tuple[str, object]]) -> dict[str, object]:
    out: dict[str, object] = {}
    for key, value in pairs:
        if key in out:
            raise ValueError(f"key {key!r} given twice")
        out[key] = value
    return out


def media_type(request: Request) -> tuple[str, dict[str, str]]:
    """The request's content type (lower case) and its parameters."""
    media, *params = request.headers.get("content-type", "").split(";")
    out = {}
    for p in params:
        k, _, v = p.partition("=")
        out[k.strip().lower()] = v.strip().strip('"').lower()
    return media.strip().lower(), out


async def read_fields(request: Request) -> dict[str, object]:
    """The body's fields (JSON object or form), without the form's ``csrf`` field, which is
    kept in ``request.state.form_csrf``. Cached on the request."""
    cached = getattr(request.state, "fields", None)
    if cached is not None:
        return dict(cached)
    media, params = media_type(request)
    body = await request.body()  # bounded by the front door's limit
    form_csrf: str | None = None
    fields: dict[str, object]
    if not body and media in ("", "application/json", "application/x-www-form-urlencoded"):
        fields = {}
    elif media == "application/json":
        if params.get("charset", "utf-8") not in ("utf-8", "utf8"):
            raise BadBody(415, "JSON must be UTF-8")
        try:
            data = json.loads(body.decode("utf-8"), parse_constant=_no_constants,
                              object_pairs_hook=_no_duplicates)
        except (UnicodeDecodeError, ValueError, RecursionError) as exc:
            raise BadBody(400, f"the body is not valid JSON: {str(exc)[:200]}") from exc
        if not isinstance(data, dict):
            raise BadBody(400, "the body must be a JSON object")
        fields = data
    elif media == "application/x-www-form-urlencoded":
        try:
            pairs = parse_qsl(body.decode("ascii"), keep_blank_values=True, strict_parsing=True,
                              max_num_fields=16, encoding="utf-8", errors="strict")
            fields = _no_duplicates(pairs)
        except (UnicodeDecodeError, ValueError) as exc:
            raise BadBody(400, f"the body is not a valid form: {str(exc)[:200]}") from exc
        value = fields.pop(CSRF_FIELD, None)
        form_csrf = value if isinstance(value, str) else None
    else:
        raise BadBody(415, f"content type {media[:60]!r} is not taken: send JSON "
                           "(application/json) or a form (application/x-www-form-urlencoded)")
    request.state.fields = fields
    request.state.form_csrf = form_csrf
    return dict(fields)


def form_to_typed(fields: Mapping[str, object], ints: tuple[str, ...]) -> dict[str, object]:
    """A form's fields with the named ones as integers (a form has only text; digits only,
    so ``1.5`` or ``true`` stay text and are refused by the strict model)."""
    out = dict(fields)
    for name in ints:
        value = out.get(name)
        if isinstance(value, str) and value.isascii() and value.isdigit() and len(value) <= 18:
            out[name] = int(value)
    return out


def schema_of(model: type[BaseModel]) -> dict[str, object]:
    """The OpenAPI ``requestBody`` of a route that takes ``model`` as JSON or as a form."""
    schema = model.model_json_schema()
    form = {**schema, "properties": {**schema.get("properties", {}),
                                     CSRF_FIELD: {"type": "string", "maxLength": 100}}}
    return {"requestBody": {"required": False, "content": {
        "application/json": {"schema": schema},
        "application/x-www-form-urlencoded": {"schema": form},
    }}}


ParamName = Annotated[str, StringConstraints(max_length=32), AfterValidator(printable)]
"""A parameter's name in a query (``param=tx&param=ry``): short, printable."""
