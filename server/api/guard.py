"""What happens before a route reads its body: the key is checked, then the body is
limited by the route's own size limit.

FastAPI reads and parses a request's body before it resolves the route's dependencies,
so a key checked by a dependency alone is checked only after the whole upload has been
received. :class:`GuardedRoute` (the ``route_class`` of every router with a body)
checks the key first, from the headers: a request without a valid key, or without the
route's scope, gets its 401/403 before one byte of its body is read. The key record is
kept in the request scope for the route's own dependency (no second lookup).

Then the body is limited by the route's kind (``body_limit(kind)`` in the route's
``openapi_extra``, reported in the OpenAPI description with its size): a declared
``Content-Length`` over the limit is refused at once (413), and the bytes are counted as
they arrive (chunked bodies too), failing with 413 as soon as the count passes it:

* ``json``: small JSON bodies (keys, maps, tags, calibration): ``max_json_body_bytes``;
* ``image``: one query frame (localize): ``max_query_body_bytes``, a few MB;
* ``entry``: one reference image with its depth image or LiDAR scan:
  ``max_entry_body_bytes``;
* ``archive``: a recorded run (tar/zip or a file set): ``max_body_bytes``. Multipart
  files are spooled to disk by the form parser, never held in memory whole.

The application-wide :class:`monoloc.server.api.limits.BodySizeLimitMiddleware` stays the
outer bound (``max_body_bytes``) for every request, routed or not.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Coroutine
from typing import Any, Literal

import anyio
from fastapi.dependencies.models import Dependant
from fastapi.routing import APIRoute
from starlette.requests import Request
from starlette.responses import Response
from starlette.types import Message, Receive

from monoloc.server.api.convert import error_responses
from monoloc.server.api.deps import (
    KEY_RECORD_SCOPE,
    authenticate,
    get_state,
    path_map_id,
    presented_key,
)
from monoloc.server.api.errors import PayloadTooLargeError
from monoloc.server.api.limits import BodyTooLargeError

BodyKind = Literal["json", "image", "entry", "archive"]
BODY_LIMIT_EXTRA = "x-monoloc-body-limit"
LIMIT_SETTINGS: dict[str, str] = {
    "json": "max_json_body_bytes",
    "image": "max_query_body_bytes",
    "entry": "max_entry_body_bytes",
    "archive": "max_body_bytes",
}
_BODY_METHODS = frozenset({"POST", "PUT", "PATCH"})


def body_limit(kind: BodyKind) -> dict[str, Any]:
    """``openapi_extra`` of a route whose body is of ``kind`` (see the module docstring)."""
    return {BODY_LIMIT_EXTRA: {"kind": kind}}


def required_scope(dependant: Dependant) -> str | None:
    """The scope of the first key-checking dependency of a route (``require_scope``)."""
    for dependency in dependant.dependencies:
        scope = getattr(dependency.call, "required_scope", None)
        if scope is not None:
            return scope
        found = required_scope(dependency)
        if found is not None:
            return found
    return None


def _counting(receive: Receive, limit: int, setting: str) -> Receive:
    received = 0

    async def counting_receive() -> Message:
        nonlocal received
        message = await receive()
        if message["type"] == "http.request":
            received += len(message.get("body", b""))
            if received > limit:
                raise BodyTooLargeError(limit, f"this route's limit, {setting}")
        return message

    return counting_receive


def _refuse_constant(token: str) -> Any:
    # a JSONDecodeError: FastAPI answers it as a malformed body (422 json_invalid)
    raise json.JSONDecodeError(f"{token} is not JSON (RFC 8259 has no NaN or Infinity)", token, 0)


class StrictJsonRequest(Request):
    """A request whose JSON body is standard JSON: ``NaN``, ``Infinity`` and
    ``-Infinity`` (which Python's parser accepts) are refused like any malformed body."""

    async def json(self) -> Any:
        if not hasattr(self, "_json"):
            self._json = json.loads(await self.body(), parse_constant=_refuse_constant)
        return self._json


def _declared_length(request: Request) -> int | None:
    value = request.headers.get("content-length")
    if value is None:
        return None
    try:
        return int(value)
    except ValueError:
        return None


class GuardedRoute(APIRoute):
    """An APIRoute that authenticates before reading the body, then limits the body."""

    def __init__(self, path: str, endpoint: Callable[..., Any], **kwargs: Any) -> None:
        super().__init__(path, endpoint, **kwargs)
        if self.body_field is not None and BODY_LIMIT_EXTRA not in (self.openapi_extra or {}):
            self.openapi_extra = {**(self.openapi_extra or {}), **body_limit("json")}
        extra = (self.openapi_extra or {}).get(BODY_LIMIT_EXTRA) or {}
        self.body_kind: str = extra.get("kind", "json")
        if self.body_kind not in LIMIT_SETTINGS:
            raise ValueError(f"unknown body kind {self.body_kind!r} of route {path}")
        self.key_scope = required_scope(self.dependant)
        self.limit_setting = f"MONOLOC_{LIMIT_SETTINGS[self.body_kind].upper()}"
        if self.body_field is not None:  # malformed and oversized bodies are answered too
            documented = error_responses(400, 408, 413)
            for status, response in documented.items():
                self.responses.setdefault(status, response)

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def guarded(request: Request) -> Response:
            if request.method not in _BODY_METHODS:
                return await handler(request)
            state = get_state(request)
            if self.key_scope is not None:
                record = await anyio.to_thread.run_sync(
                    authenticate,
                    state,
                    presented_key(request),
                    self.key_scope,
                    path_map_id(request),
                )
                request.scope[KEY_RECORD_SCOPE] = record
            limit = int(getattr(state.settings, LIMIT_SETTINGS[self.body_kind]))
            declared = _declared_length(request)
            if declared is not None and declared > limit:
                raise PayloadTooLargeError(
                    f"request body of {declared} bytes exceeds this route's limit of {limit} "
                    f"bytes ({self.limit_setting})"
                )
            counted = _counting(request.receive, limit, self.limit_setting)
            return await handler(StrictJsonRequest(request.scope, counted))

        return guarded


def document_body_limits(openapi: dict[str, Any], settings: object) -> dict[str, Any]:
    """Write each route's body limit in bytes into its OpenAPI operation (in place), in
    the extension and in words in its description."""
    for operations in openapi.get("paths", {}).values():
        for operation in operations.values():
            extra = operation.get(BODY_LIMIT_EXTRA) if isinstance(operation, dict) else None
            if extra:
                setting = LIMIT_SETTINGS[extra["kind"]]
                extra["max_bytes"] = int(getattr(settings, setting))
                extra["setting"] = f"MONOLOC_{setting.upper()}"
                rule = (
                    f"Body limit: {extra['max_bytes']} bytes (`{extra['setting']}`); "
                    "a larger body is answered 413 naming this limit."
                )
                description = operation.get("description", "")
                operation["description"] = f"{description}\n\n{rule}".strip()
    return openapi
