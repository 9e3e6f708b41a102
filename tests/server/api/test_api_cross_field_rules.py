"""The OpenAPI description states every cross-field rule the server enforces (issue 50:
ten schema-valid requests were refused, e.g. a geo-reference with both ``origin`` and
``T_ecef_from_world``).

The description is walked for its rules (``x-monoloc-rule`` in request bodies,
``x-monoloc-rules`` among query parameters); every rule found has a violating request
below and every request below names a rule the description states. Each violating body
is invalid against the operation's own request schema (checked with a JSON Schema
validator, so the rule really is in the schema, not only in words) while its valid twin
is valid, and the server answers the violation 422 with a message naming the rule.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

import cv2
import jsonschema_rs
import numpy as np
import pytest
from api_helpers import CALIBRATION, camera_of

CAMERA = camera_of(None)
ORIGIN = {"lat_deg": 48.85837, "lon_deg": 2.294481, "h_m": 35.0, "x_axis_heading_deg": 90.0}
T_ECEF = [1.0, 0.0, 0.0, 4200961.4, 0.0, 1.0, 0.0, 168322.7, 0.0, 0.0, 1.0, 4780237.2]
T_ECEF += [0.0, 0.0, 0.0, 1.0]
POSE = ",".join(str(v) for v in np.eye(4).ravel())
FOCAL = {"fx": 700.0, "fy": 700.0, "cx": 600.0, "cy": 180.0}
LENS = [-0.28, 0.09, 0.0006, -0.0004]
PRIOR = {"prior_x_m": 1.0, "prior_y_m": 2.0, "prior_radius_m": 5.0}


def _png(width: int, height: int, dtype=np.uint8) -> bytes:
    ok, data = cv2.imencode(".png", np.zeros((height, width), dtype))
    assert ok
    return data.tobytes()


IMAGE = _png(CAMERA["width_px"], CAMERA["height_px"])
DEPTH = _png(CAMERA["width_px"], CAMERA["height_px"], np.uint16)
LIDAR = np.zeros((4, 4), np.float32).tobytes()


@dataclass(frozen=True)
class Violation:
    """A request breaking ``rule`` on ``method path``, and its valid twin. ``json``: a JSON
    body; ``form`` / ``files``: a multipart body (its schema instance: the form's fields,
    each file as a string); ``params``: query parameters."""

    rule: str
    method: str
    path: str
    json: dict[str, Any] | None = None
    valid_json: dict[str, Any] | None = None
    form: dict[str, Any] = field(default_factory=dict)
    files: tuple[tuple[str, bytes], ...] = ()
    valid_form: dict[str, Any] | None = None
    params: dict[str, Any] = field(default_factory=dict)

    def instance(self, form: dict[str, Any] | None = None, with_files: bool = True) -> dict:
        values: dict[str, Any] = dict(self.form if form is None else form)
        for name, _ in self.files if with_files else ():
            if name == "files":
                values.setdefault("files", []).append("a file")
            else:
                values[name] = "a file"
        return values


_LOCALIZE = "/v1/maps/{map_id}/localize"
_ENTRIES = "/v1/maps/{map_id}/entries"
_RUNS = "/v1/maps/{map_id}/runs"
_CALIBRATION_JOBS = "/v1/maps/{map_id}/calibration/jobs"
_FILE_SET = (("files", b"a"), ("files", b"b"))
VIOLATIONS = [
    Violation(
        "geo_reference_exactly_one",
        "POST",
        "/v1/maps",
        json={
            "name": "two",
            "camera": CAMERA,
            "geo_reference": {"origin": ORIGIN, "T_ecef_from_world": T_ECEF},
        },
        valid_json={"name": "two", "camera": CAMERA, "geo_reference": {"origin": ORIGIN}},
    ),
    Violation(
        "geo_reference_exactly_one",
        "PUT",
        "/v1/maps/{map_id}/geo-reference",
        json={"origin": ORIGIN, "T_ecef_from_world": T_ECEF},
        valid_json={"T_ecef_from_world": T_ECEF, "origin": None},
    ),
    Violation(
        "admin_key_all_maps",
        "POST",
        "/v1/keys",
        json={"name": "ops", "scopes": ["localize", "admin"], "maps": ["MAP"]},
        valid_json={"name": "car", "scopes": ["localize"], "maps": ["MAP"]},
    ),
    Violation(
        "pnp_covariance_needs_pnp",
        "PUT",
        "/v1/maps/{map_id}/calibration",
        json={**CALIBRATION, "covariance": "pnp"},
        valid_json={**CALIBRATION, "covariance": "paper"},
    ),
    Violation(
        "lens_coefficients_fit_the_model",
        "POST",
        "/v1/cameras",
        json={"name": "fleet", **CAMERA, "distortion_model": "Plumb_Bob", "distortion": [0.1, 0.0]},
        valid_json={"name": "fleet", **CAMERA, "distortion_model": "radtan", "distortion": LENS},
    ),
    Violation(
        "lens_coefficients_need_a_model",
        "POST",
        "/v1/cameras",
        json={"name": "fleet", **CAMERA, "distortion_model": "pinhole", "distortion": LENS},
        valid_json={"name": "fleet", **CAMERA, "distortion": [0.0, 0.0, 0.0, 0.0]},
    ),
    Violation(
        "localize_focal_all_or_none",
        "POST",
        _LOCALIZE,
        form={"fx": 700.0, "cx": 600.0},
        files=(("image", IMAGE),),
        valid_form={"image": "a"} | FOCAL,
    ),
    Violation(
        "localize_prior_all_or_none",
        "POST",
        _LOCALIZE,
        form={"prior_x_m": 1.0, "prior_y_m": 2.0},
        files=(("image", IMAGE),),
        valid_form={"image": "a"} | PRIOR,
    ),
    Violation(
        "localize_yaw_all_or_none",
        "POST",
        _LOCALIZE,
        form={**PRIOR, "prior_yaw_rad": 0.1},
        files=(("image", IMAGE),),
        valid_form={"image": "a"} | {**PRIOR, "prior_yaw_rad": 0.1, "prior_yaw_tolerance_rad": 0.5},
    ),
    Violation(
        "localize_yaw_needs_position",
        "POST",
        _LOCALIZE,
        form={"prior_yaw_rad": 0.1, "prior_yaw_tolerance_rad": 0.5},
        files=(("image", IMAGE),),
        valid_form={"image": "a"} | {**PRIOR, "prior_yaw_rad": 0.1, "prior_yaw_tolerance_rad": 0.5},
    ),
    Violation(
        "localize_distortion_model_needs_focal",
        "POST",
        _LOCALIZE,
        form={"distortion_model": "plumb_bob", "distortion": "-0.2,0.05,0,0"},
        files=(("image", IMAGE),),
        valid_form={"image": "a"}
        | {**FOCAL, "distortion_model": "plumb_bob", "distortion": "-0.2,0.05,0,0"},
    ),
    Violation(
        "localize_distortion_needs_focal",
        "POST",
        _LOCALIZE,
        form={"distortion": "-0.2,0.05,0,0"},
        files=(("image", IMAGE),),
        valid_form={"image": "a"} | {**FOCAL, "distortion": "-0.2,0.05,0,0"},
    ),
    Violation(
        "localize_camera_id_without_intrinsics",
        "POST",
        _LOCALIZE,
        form={"camera_id": 1, **FOCAL},
        files=(("image", IMAGE),),
        valid_form={"image": "a", "camera_id": 1},
    ),
    Violation(
        "entry_exactly_one_3d_source",
        "POST",
        _ENTRIES,
        form={"T_world_from_cam": POSE, "depth_scale": 1000.0, "T_cam_from_lidar": POSE},
        files=(("image", IMAGE), ("depth", DEPTH), ("lidar", LIDAR)),
        valid_form={"T_world_from_cam": POSE, "depth_scale": 1000.0, "image": "a", "depth": "b"},
    ),
    Violation(
        "entry_depth_needs_scale",
        "POST",
        _ENTRIES,
        form={"T_world_from_cam": POSE},
        files=(("image", IMAGE), ("depth", DEPTH)),
        valid_form={"T_world_from_cam": POSE, "depth_scale": 1000.0, "image": "a", "depth": "b"},
    ),
    Violation(
        "entry_lidar_needs_extrinsics",
        "POST",
        _ENTRIES,
        form={"T_world_from_cam": POSE},
        files=(("image", IMAGE), ("lidar", LIDAR)),
        valid_form={"T_world_from_cam": POSE, "T_cam_from_lidar": POSE, "image": "a", "lidar": "b"},
    ),
    Violation(
        "upload_exactly_one_part",
        "POST",
        _RUNS,
        form={"format": "kitti"},
        files=(("archive", b"not read"), *_FILE_SET),
        valid_form={"format": "kitti", "files": ["a", "b"]},
    ),
    Violation(
        "run_stereo_depth_is_kitti",
        "POST",
        _RUNS,
        form={"format": "tum", "depth_from": "stereo"},
        files=(("archive", b"not read"),),
        valid_form={"format": "kitti", "depth_from": "stereo", "archive": "a"},
    ),
    Violation(
        "upload_exactly_one_part",
        "POST",
        _CALIBRATION_JOBS,
        form={"format": "kitti"},
        files=(("archive", b"not read"), *_FILE_SET),
        valid_form={"format": "kitti", "archive": "a"},
    ),
    Violation(
        "entries_area_all_or_none",
        "GET",
        _ENTRIES,
        params={"x_m": 1.0, "y_m": 2.0},
    ),
]


def _resolve(spec: dict, node: dict) -> dict:
    while "$ref" in node:
        target: Any = spec
        for part in node["$ref"].removeprefix("#/").split("/"):
            target = target[part]
        node = target
    return node


def _rules_in(spec: dict, node: Any, seen: set[str]) -> list[dict]:
    """Every ``x-monoloc-rule`` marker under ``node``, following references once."""
    found: list[dict] = []
    if isinstance(node, dict):
        ref = node.get("$ref")
        if ref is not None:
            if ref not in seen:
                seen.add(ref)
                found += _rules_in(spec, _resolve(spec, node), seen)
            return found
        if "x-monoloc-rule" in node:
            found.append(node["x-monoloc-rule"])
        for value in node.values():
            found += _rules_in(spec, value, seen)
    elif isinstance(node, list):
        for value in node:
            found += _rules_in(spec, value, seen)
    return found


def _stated_rules(spec: dict) -> dict[tuple[str, str, str], dict]:
    """(method, path, rule name) -> the rule's statement, for every operation."""
    stated = {}
    for path, operations in spec["paths"].items():
        for method, operation in operations.items():
            for media in operation.get("requestBody", {}).get("content", {}).values():
                for rule in _rules_in(spec, media["schema"], set()):
                    stated[(method.upper(), path, rule["name"])] = rule
            for rule in operation.get("x-monoloc-rules", []):
                stated[(method.upper(), path, rule["name"])] = rule
    return stated


def _body_validator(spec: dict, violation: Violation) -> jsonschema_rs.Validator:
    operation = spec["paths"][violation.path][violation.method.lower()]
    content = operation["requestBody"]["content"]
    media = "application/json" if violation.json is not None else "multipart/form-data"
    return jsonschema_rs.Draft202012Validator(
        {**content[media]["schema"], "components": spec["components"]}
    )


@pytest.fixture(scope="module")
def spec() -> dict:
    from monoloc.server.api.app import create_app
    from monoloc.server.settings import Settings

    return create_app(Settings(data_dir="unused")).openapi()  # no lifespan: nothing written


def test_every_stated_rule_has_a_violation_here_and_every_violation_is_stated(spec):
    stated = set(_stated_rules(spec))
    tried = {(v.method, v.path, v.rule) for v in VIOLATIONS}
    assert stated - tried == set(), "rules stated in the OpenAPI but not tried here"
    assert tried - stated == set(), "rules tried here but not stated in the OpenAPI"
    assert len({name for _, _, name in stated}) >= 15


@pytest.mark.parametrize("violation", VIOLATIONS, ids=lambda v: f"{v.method} {v.path} {v.rule}")
def test_the_schema_itself_refuses_the_violation(spec, violation):
    if violation.params:
        (rule,) = [
            r
            for r in spec["paths"][violation.path]["get"]["x-monoloc-rules"]
            if r["name"] == violation.rule
        ]
        assert rule["kind"] == "all_or_none" and rule["in"] == "query"
        given = [f for f in rule["fields"] if f in violation.params]
        assert 0 < len(given) < len(rule["fields"])
        assert rule["description"] in spec["paths"][violation.path]["get"]["description"]
        return
    validator = _body_validator(spec, violation)
    if violation.json is not None:
        bad = json.loads(json.dumps(violation.json).replace('"MAP"', "1"))
        good = json.loads(json.dumps(violation.valid_json).replace('"MAP"', "1"))
    else:
        bad, good = violation.instance(), violation.instance(violation.valid_form, False)
    assert not validator.is_valid(bad), "the schema lets the violating body through"
    assert validator.is_valid(good), list(validator.iter_errors(good))


@pytest.fixture(scope="module")
def app_with_map(tmp_path_factory):
    from api_helpers import create_keys, make_settings, open_client

    with open_client(make_settings(tmp_path_factory.mktemp("rules") / "data")) as client:
        keys = create_keys(client)
        made = client.post(
            "/v1/maps", json={"name": "rules", "camera": CAMERA}, headers=keys.header("admin")
        )
        assert made.status_code == 201, made.text
        yield client, keys, made.json()["id"]


@pytest.mark.parametrize("violation", VIOLATIONS, ids=lambda v: f"{v.method} {v.path} {v.rule}")
def test_the_server_answers_the_violation_422_naming_the_rule(spec, app_with_map, violation):
    client, keys, map_id = app_with_map
    rule = _stated_rules(spec)[(violation.method, violation.path, violation.rule)]
    path = violation.path.replace("{map_id}", str(map_id))
    kwargs: dict[str, Any] = {"headers": keys.header("admin"), "params": violation.params}
    if violation.json is not None:
        kwargs["content"] = json.dumps(violation.json).replace('"MAP"', str(map_id))
        kwargs["headers"] = {**kwargs["headers"], "Content-Type": "application/json"}
    elif violation.files:
        kwargs["data"] = {k: str(v) for k, v in violation.form.items()}
        kwargs["files"] = [(name, (f"{name}.bin", data)) for name, data in violation.files]
    before = client.get(f"/v1/maps/{map_id}", headers=keys.header("admin")).json()
    answer = client.request(violation.method, path, **kwargs)
    assert answer.status_code == 422, answer.text
    assert rule["message"] in answer.json()["error"]["message"]
    after = client.get(f"/v1/maps/{map_id}", headers=keys.header("admin")).json()
    assert (after["version"], after["n_runs"]) == (before["version"], before["n_runs"])


_NIGHT = {k: v for k, v in CALIBRATION.items() if k != "provenance"}
CALIBRATION_SHAPES = [
    ({**CALIBRATION, "retrieval_frame": "world"}, "retrieval_frame"),
    ({**CALIBRATION, "vlad_evidence": "relative"}, "vlad_evidence"),
    ({**CALIBRATION, "conditions": {"night": {"mu1": _NIGHT["mu1"]}}}, "night"),
    ({**CALIBRATION, "conditions": {"night": {**_NIGHT, "conditions": {"a": _NIGHT}}}}, "night"),
    ({**CALIBRATION, "conditions": {"night": {**_NIGHT, "covariance": "pnp"}}}, "pnp"),
    ({**CALIBRATION, "conditions": {"not a tag!": _NIGHT}}, "not a tag!"),
]


@pytest.mark.parametrize("body, named", CALIBRATION_SHAPES, ids=lambda v: str(v)[-40:])
def test_a_calibration_put_is_refused_only_for_what_its_schema_states(
    spec, app_with_map, body, named
):
    """A calibration's choices and its conditions' shape were free in the schema
    (additional fields, any object per condition) and refused by the server."""
    client, keys, map_id = app_with_map
    schema = spec["paths"]["/v1/maps/{map_id}/calibration"]["put"]["requestBody"]
    validator = jsonschema_rs.Draft202012Validator(
        {**schema["content"]["application/json"]["schema"], "components": spec["components"]}
    )
    good = {**CALIBRATION, "retrieval_frame": "vehicle", "conditions": {"night": _NIGHT}}
    assert validator.is_valid(good), list(validator.iter_errors(good))
    assert not validator.is_valid(body)
    path = f"/v1/maps/{map_id}/calibration"
    answer = client.put(path, json=body, headers=keys.header("write"))
    assert answer.status_code == 422, answer.text
    assert named in answer.json()["error"]["message"]
    assert client.put(path, json=good, headers=keys.header("write")).status_code == 200
    assert client.delete(path, headers=keys.header("write")).status_code == 200
