"""OpenAPI links between the API's operations (issue 50): which answer names the object
that another operation takes, e.g. ``POST /v1/maps`` answers the new map, whose ``id``
is ``GET /v1/maps/{map_id}``'s ``map_id``. Clients and stateful fuzzers (schemathesis's
state machine) follow them from one call to the next.

Written once here, by (method, path, status) of the answer, and added to the
description by :func:`document_links` with each target's ``operationId``.
"""

from __future__ import annotations

from typing import Any

_MAP = "/v1/maps/{map_id}"
_ENTRY = f"{_MAP}/entries/{{entry_id}}"
_JOB = "/v1/jobs/{job_id}"
_SAME_MAP = {"map_id": "$request.path.map_id"}

# The operations that take one map (by its map_id), and nothing else in their path.
_ON_A_MAP = (
    ("get", _MAP),
    ("delete", _MAP),
    ("post", f"{_MAP}/vocabulary/jobs"),
    ("get", f"{_MAP}/replica"),
    ("get", f"{_MAP}/runs"),
    ("post", f"{_MAP}/runs"),
    ("get", f"{_MAP}/entries"),
    ("post", f"{_MAP}/entries"),
    ("post", f"{_MAP}/localize"),
    ("get", f"{_MAP}/calibration"),
    ("put", f"{_MAP}/calibration"),
    ("delete", f"{_MAP}/calibration"),
    ("post", f"{_MAP}/calibration/jobs"),
    ("get", f"{_MAP}/geo-reference"),
    ("put", f"{_MAP}/geo-reference"),
    ("delete", f"{_MAP}/geo-reference"),
    ("get", f"{_MAP}/poses"),
    ("get", f"{_MAP}/coverage"),
    ("get", f"{_MAP}/vehicles"),
)
_ON_AN_ENTRY = (
    ("get", _ENTRY),
    ("patch", _ENTRY),
    ("delete", _ENTRY),
    ("get", f"{_ENTRY}/keypoints"),
    ("get", f"{_ENTRY}/image"),
)
_ON_A_JOB = (("get", _JOB), ("post", f"{_JOB}/resume"), ("post", f"{_JOB}/cancel"))
_ON_A_CAMERA = (("get", "/v1/cameras/{camera_id}"), ("delete", "/v1/cameras/{camera_id}"))


def _to(targets, parameters: dict[str, str]) -> list[tuple[str, str, dict[str, str]]]:
    return [(method, path, parameters) for method, path in targets]


# (method, path, status) of an answer -> (target method, target path, its parameters)
LINKS: dict[tuple[str, str, str], list[tuple[str, str, dict[str, str]]]] = {
    ("post", "/v1/maps", "201"): _to(_ON_A_MAP, {"map_id": "$response.body#/id"}),
    ("get", "/v1/maps", "200"): _to(_ON_A_MAP, {"map_id": "$response.body#/items/0/id"}),
    ("get", f"{_MAP}/entries", "200"): _to(
        _ON_AN_ENTRY, {**_SAME_MAP, "entry_id": "$response.body#/items/0/id"}
    ),
    ("post", f"{_MAP}/entries", "201"): _to(
        _ON_AN_ENTRY, {**_SAME_MAP, "entry_id": "$response.body#/entry/id"}
    ),
    ("get", f"{_MAP}/runs", "200"): [
        ("get", f"{_MAP}/runs/{{run_id}}", {**_SAME_MAP, "run_id": "$response.body#/0/id"})
    ],
    ("post", f"{_MAP}/runs", "202"): [
        ("get", f"{_MAP}/runs/{{run_id}}", {**_SAME_MAP, "run_id": "$response.body#/run/id"}),
        *_to(_ON_A_JOB, {"job_id": "$response.body#/job/id"}),
    ],
    ("post", f"{_MAP}/vocabulary/jobs", "202"): _to(_ON_A_JOB, {"job_id": "$response.body#/id"}),
    ("post", f"{_MAP}/calibration/jobs", "202"): _to(
        _ON_A_JOB, {"job_id": "$response.body#/job/id"}
    ),
    ("get", "/v1/jobs", "200"): _to(_ON_A_JOB, {"job_id": "$response.body#/items/0/id"}),
    ("put", f"{_MAP}/geo-reference", "200"): _to(
        (("get", f"{_MAP}/geo-reference"), ("delete", f"{_MAP}/geo-reference")), _SAME_MAP
    ),
    ("put", f"{_MAP}/calibration", "200"): _to(
        (("get", f"{_MAP}/calibration"), ("delete", f"{_MAP}/calibration")), _SAME_MAP
    ),
    ("post", "/v1/keys", "201"): [
        ("delete", "/v1/keys/{key_id}", {"key_id": "$response.body#/id"})
    ],
    ("get", "/v1/keys", "200"): [
        ("delete", "/v1/keys/{key_id}", {"key_id": "$response.body#/items/0/id"})
    ],
    ("post", "/v1/cameras", "201"): _to(_ON_A_CAMERA, {"camera_id": "$response.body#/id"}),
    ("get", "/v1/cameras", "200"): _to(_ON_A_CAMERA, {"camera_id": "$response.body#/items/0/id"}),
}


def _link_name(method: str, path: str) -> str:
    words = [w.strip("{}").replace("-", "_") for w in path.split("/") if w and w != "v1"]
    return method.capitalize() + "".join(w[:1].upper() + w[1:] for w in words)


def document_links(openapi: dict[str, Any]) -> dict[str, Any]:
    """Add :data:`LINKS` to the answers of ``openapi`` (in place); each link names its
    target by ``operationId``. KeyError if an operation or answer is missing."""
    paths = openapi["paths"]
    for (method, path, status), targets in LINKS.items():
        response = paths[path][method]["responses"][status]
        links = response.setdefault("links", {})
        for target_method, target_path, parameters in targets:
            target = paths[target_path][target_method]
            links[_link_name(target_method, target_path)] = {
                "operationId": target["operationId"],
                "parameters": dict(parameters),
            }
    return openapi
