"""Every error the API answers is JSON: ``{"error": {"code": ..., "message": ...}}``.

``MonolocError`` subclasses carry their HTTP status (``http_status``); this module adds
the few that only the API raises (401, 403, 413, 415, 400, 503) and the handlers
that turn them, FastAPI's validation errors and Starlette's HTTP exceptions into that
shape. The code is a short snake_case name a client can switch on.
"""

from __future__ import annotations

import logging
import re
from typing import Any

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.websockets import WebSocket

from monoloc.core.errors import MonolocError

log = logging.getLogger(__name__)

STATUS_CODES = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    408: "request_timeout",
    409: "conflict",
    413: "payload_too_large",
    415: "unsupported_media_type",
    422: "invalid_input",
    429: "too_many_requests",
    500: "internal_error",
    501: "not_implemented",
    503: "unavailable",
    507: "insufficient_storage",
}


class BadRequestError(MonolocError):
    """The request is malformed in a way that is not a validation error (e.g. an archive
    holding a symlink or a path leaving the upload directory)."""

    http_status = 400


class UnauthorizedError(MonolocError):
    """No API key, or an unknown or revoked one."""

    http_status = 401


class ForbiddenError(MonolocError):
    """The API key is valid but lacks the scope the route needs."""

    http_status = 403


class PayloadTooLargeError(MonolocError):
    """A body, image, archive or scan exceeds a configured limit."""

    http_status = 413


class UnsupportedMediaTypeError(MonolocError):
    """An upload is not of an accepted type (only PNG/JPEG images, tar/zip archives)."""

    http_status = 415


class NotReadyError(MonolocError):
    """The server is starting or stopping."""

    http_status = 503


def error_code(exc: MonolocError) -> str:
    """The snake_case code of an error, from its class name (``NotFoundError`` ->
    ``not_found``, ``TooFewPointsError`` -> ``too_few_points``)."""
    name = type(exc).__name__.removesuffix("Error")
    if type(exc) is MonolocError or not name:
        return STATUS_CODES.get(exc.http_status, "error")
    return re.sub(r"(?<!^)(?=[A-Z])", "_", name).lower()


def error_body(code: str, message: str, **extra: Any) -> dict[str, Any]:
    body: dict[str, Any] = {"code": code, "message": message}
    body.update(extra)
    return {"error": body}


def error_response(status: int, code: str, message: str, **extra: Any) -> JSONResponse:
    headers = {"WWW-Authenticate": 'ApiKey header="X-API-Key"'} if status == 401 else None
    return JSONResponse(error_body(code, message, **extra), status_code=status, headers=headers)


# Patterns of the API's fields (server/api/schemas.py) -> the rule in words, so a refusal
# says what is wrong rather than printing a regular expression.
PATTERN_RULES: dict[str, str] = {}


def _message(err: dict[str, Any]) -> str:
    if err.get("type") == "string_pattern_mismatch":
        rule = PATTERN_RULES.get(str((err.get("ctx") or {}).get("pattern", "")))
        if rule:
            return f"invalid value {err.get('input')!r}: {rule}"
    return str(err.get("msg", "invalid"))


def describe_validation(errors: list[dict[str, Any]]) -> str:
    """One line naming the first few invalid fields (pydantic's ``errors()``)."""
    parts = []
    for err in errors[:5]:
        where = ".".join(str(p) for p in err.get("loc", ()) if p not in ("body", "query"))
        parts.append(f"{where or 'request'}: {_message(err)}")
    more = f" (and {len(errors) - 5} more)" if len(errors) > 5 else ""
    return "; ".join(parts) + more


async def _monoloc_error(_conn: Request | WebSocket, exc: Exception) -> JSONResponse:
    assert isinstance(exc, MonolocError)
    status = int(getattr(exc, "http_status", 500) or 500)
    if status >= 500 and status != 507:  # 507: a quota filled by other uploads, no fault
        log.error("request failed: %s", exc, exc_info=exc)
    response = error_response(status, error_code(exc), str(exc) or type(exc).__name__)
    for key, value in (getattr(exc, "headers", None) or {}).items():  # e.g. Retry-After
        response.headers[key] = value
    return response


_HTTP_METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE")


def allowed_methods(app: Any, path: str) -> list[str]:
    """Every method some operation of the OpenAPI description serves at ``path`` (with
    HEAD wherever GET is served): a 405's ``Allow`` header. Starlette's own names only the
    methods of the first route whose path matches."""
    allowed: set[str] = set()
    paths = app.openapi().get("paths", {})
    if path in paths:  # a literal path (/v1/keys/me) is not also its parametrised sibling's
        matching = [paths[path]]
    else:
        matching = []
        for template, operations in paths.items():
            pattern = re.sub(r"\\\{[^/]+?\\\}", "[^/]+", re.escape(template))
            if re.fullmatch(pattern, path):
                matching.append(operations)
    for operations in matching:
        allowed.update(m.upper() for m in operations if m.upper() in _HTTP_METHODS)
    if "GET" in allowed:
        allowed.add("HEAD")
    return [m for m in _HTTP_METHODS if m in allowed]


async def _http_error(conn: Request | WebSocket, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    code = STATUS_CODES.get(exc.status_code, "error")
    message = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
    headers = dict(exc.headers or {})
    if exc.status_code == 405:
        methods = allowed_methods(conn.app, conn.url.path)
        if methods:
            headers["Allow"] = ", ".join(methods)
            message = f"{conn.scope.get('method', 'this method')} is not allowed here; allowed: "
            message += ", ".join(methods)
    response = error_response(exc.status_code, code, message)
    for key, value in headers.items():
        response.headers[key] = value
    return response


async def _validation_error(_conn: Request | WebSocket, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    errors = jsonable_encoder(exc.errors(), exclude={"input", "ctx", "url"})
    return error_response(
        422, "validation_error", describe_validation(list(exc.errors())), details=errors
    )


async def _unexpected_error(_conn: Request, exc: Exception) -> JSONResponse:
    log.exception("unhandled error", exc_info=exc)
    return error_response(500, "internal_error", "internal server error (see the server log)")


def install_error_handlers(app: FastAPI) -> None:
    """Register the JSON error handlers on ``app``."""
    app.add_exception_handler(MonolocError, _monoloc_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(Exception, _unexpected_error)
