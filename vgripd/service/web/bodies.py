"""Request bodies of the web view, read so that a malformed one is a 4xx naming what was wrong,
never an internal error: the JSON of the action routes and the ``/login`` form.

- JSON: UTF-8, valid JSON, nested at most ``MAX_JSON_DEPTH`` deep (a 30,000-deep array made
  the parser run out of recursion: a 500); 400 with the reason otherwise.
- The login form: ``application/x-www-form-urlencoded`` in UTF-8 (what a browser's form
  sends); another content type (multipart) is 415, bytes that are no UTF-8 are 400.

The size of every body is bounded before this by the application's ``client_max_size``.

The answer to a config write (``outcome_response``) is here too: every edit route answers the
writer's ``Outcome`` alike, 422 when refused.
"""

from __future__ import annotations

import json
from typing import Any
from urllib.parse import parse_qs

from aiohttp import web

from vgripd.service.host.configtxn import Outcome

#: The deepest nesting of arrays and objects an action's JSON body may have (the pages send 3).
MAX_JSON_DEPTH = 32
FORM_TYPE = "application/x-www-form-urlencoded"


def _text(raw: bytes, what: str) -> str:
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as err:
        raise web.HTTPBadRequest(text=f"{what}: not UTF-8 (byte {err.start}: "
                                      f"{raw[err.start:err.start + 1]!r})") from None


def depth(data: Any, limit: int) -> int:
    """How deep ``data`` nests lists and dicts, counted up to ``limit + 1`` (no recursion)."""
    deepest, level = 0, [data]
    while level and deepest <= limit:
        deepest += 1
        nxt: list[Any] = []
        for item in level:
            if isinstance(item, dict):
                nxt.extend(item.values())
            elif isinstance(item, list):
                nxt.extend(item)
        level = [v for v in nxt if isinstance(v, dict | list)]
    return deepest


async def json_body(request: web.Request) -> Any:
    """The request's JSON body; ``HTTPBadRequest`` naming what is wrong with it."""
    text = _text(await request.read(), "the body")
    try:
        data = json.loads(text)
    except RecursionError:
        raise web.HTTPBadRequest(text=f"the body: JSON nested too deep (at most "
                                      f"{MAX_JSON_DEPTH} levels)") from None
    except ValueError as err:
        raise web.HTTPBadRequest(text=f"the body must be JSON: {err}") from None
    if isinstance(data, dict | list) and depth(data, MAX_JSON_DEPTH) > MAX_JSON_DEPTH:
        raise web.HTTPBadRequest(text=f"the body: JSON nested deeper than {MAX_JSON_DEPTH} "
                                      "levels")
    return data


async def login_form(request: web.Request) -> dict[str, str]:
    """The ``/login`` form's fields (the last value of each); 415 for a body that is no
    URL-encoded form, 400 for one that is no UTF-8."""
    if request.body_exists and request.content_type not in (FORM_TYPE, "application/octet-stream"):
        raise web.HTTPUnsupportedMediaType(
            text=f"the login form is {FORM_TYPE} (the page's form sends it), not "
                 f"{request.content_type}")
    text = _text(await request.read(), "the login form")
    try:
        fields = parse_qs(text, keep_blank_values=True, strict_parsing=False,
                          encoding="utf-8", errors="strict", max_num_fields=16)
    except (ValueError, UnicodeDecodeError) as err:
        raise web.HTTPBadRequest(text=f"the login form: {err}") from None
    return {k: v[-1] for k, v in fields.items()}


def outcome_response(outcome: Outcome, **extra: Any) -> web.Response:
    """A config write's outcome as JSON (``extra`` beside it): 200 applied, 422 refused."""
    return web.json_response({**outcome.as_dict(), **extra},
                             status=200 if outcome.applied else 422)
