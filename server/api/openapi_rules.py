"""The cross-field rules the server enforces, stated in its OpenAPI description (issue 50).

A request body can satisfy every field's own schema and still be refused for how its
fields combine: a geographic reference with both ``origin`` and ``T_ecef_from_world``, a
localize form with ``fx`` but not ``fy``, an entry with both a depth image and a LiDAR
scan. Each such rule is written here once, as JSON Schema (OpenAPI 3.1 is JSON Schema
2020-12): ``oneOf`` for "exactly one of", ``anyOf`` of "all present" / "all absent" for
"all or none", ``anyOf`` of "absent" / "the others present" for "needs". Each rule's
schema carries ``x-monoloc-rule`` (its name, the fields it binds, the words the server's
422 uses), so a client, a fuzzer and the test that walks the description all find it.

"Present" means given and not null: JSON bodies may send null for an optional field,
which the server reads as absent.

Request models carry their rules through ``json_schema_extra`` (``rules_extra``); the
multipart forms FastAPI builds from a route's parameters, and the rules among query
parameters (which JSON Schema cannot bind), are added to the description by
:func:`document_cross_field_rules`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

RULE_EXTRA = "x-monoloc-rule"
OPERATION_RULES_EXTRA = "x-monoloc-rules"
RuleKind = Literal["exactly_one", "all_or_none", "needs", "only_with"]


def _present(name: str, schema: dict[str, Any] | None = None) -> dict[str, Any]:
    value = schema if schema is not None else {"not": {"type": "null"}}
    return {"required": [name], "properties": {name: value}}


def _absent(name: str) -> dict[str, Any]:
    return {"properties": {name: {"type": "null"}}}  # left out, or null


@dataclass(frozen=True)
class CrossFieldRule:
    """One rule among a request's fields.

    ``exactly_one``: exactly one of ``fields`` is present. ``all_or_none``: all or none of
    ``fields``. ``needs``: ``fields[0]``, when present, needs every other field.
    ``only_with``: ``fields[0]`` may be present only when ``when`` (a schema of the whole
    request) holds. ``present`` overrides what "present" means for a field (e.g. a
    non-empty list). ``message`` is what the server's 422 says (a fragment of it)."""

    name: str
    kind: RuleKind
    fields: tuple[str, ...]
    description: str
    message: str
    when: dict[str, Any] | None = None
    present: tuple[tuple[str, dict[str, Any]], ...] = ()

    def _is_present(self, name: str) -> dict[str, Any]:
        return _present(name, dict(self.present).get(name))

    def schema(self) -> dict[str, Any]:
        """This rule as JSON Schema, marked with ``x-monoloc-rule``."""
        if self.kind == "exactly_one":
            body: dict[str, Any] = {"oneOf": [self._is_present(f) for f in self.fields]}
        elif self.kind == "all_or_none":
            body = {
                "anyOf": [
                    {"allOf": [self._is_present(f) for f in self.fields]},
                    {"allOf": [_absent(f) for f in self.fields]},
                ]
            }
        elif self.kind == "needs":
            first, *others = self.fields
            body = {"anyOf": [_absent(first), {"allOf": [self._is_present(f) for f in others]}]}
        else:
            assert self.when is not None, f"rule {self.name}: only_with needs when"
            body = {"anyOf": [_absent(self.fields[0]), self.when]}
        marker = {
            "name": self.name,
            "kind": self.kind,
            "fields": list(self.fields),
            "message": self.message,
        }
        return {"description": self.description, **body, RULE_EXTRA: marker}

    def query_statement(self) -> dict[str, Any]:
        """This rule among query parameters (``x-monoloc-rules`` of the operation)."""
        return {
            "name": self.name,
            "kind": self.kind,
            "fields": list(self.fields),
            "in": "query",
            "description": self.description,
            "message": self.message,
        }


def rules_extra(*rules: CrossFieldRule) -> dict[str, Any]:
    """``json_schema_extra`` entries of a request model bound by ``rules``."""
    return {"allOf": [rule.schema() for rule in rules]}


# --- rules of the JSON request models (server/api/schemas*.py) ---------------------------

GEO_REFERENCE_ONE_OF = CrossFieldRule(
    "geo_reference_exactly_one",
    "exactly_one",
    ("origin", "T_ecef_from_world"),
    "Exactly one of origin and T_ecef_from_world.",
    "exactly one of origin and T_ecef_from_world",
)
ADMIN_KEY_ALL_MAPS = CrossFieldRule(
    "admin_key_all_maps",
    "only_with",
    ("maps", "scopes"),
    "maps only without the admin scope (an admin key sees every map).",
    "an admin key sees every map",
    when={
        "required": ["scopes"],
        "properties": {"scopes": {"not": {"contains": {"const": "admin"}}}},
    },
)
PNP_COVARIANCE_NEEDS_PNP = CrossFieldRule(
    "pnp_covariance_needs_pnp",
    "only_with",
    ("covariance", "pnp"),
    "covariance pnp needs the pnp model's parameters (pnp).",
    "the pnp covariance model needs its fitted parameters",
    when={
        "anyOf": [
            {"properties": {"covariance": {"not": {"const": "pnp"}}}},
            _present("pnp"),
        ]
    },
)
_INTRINSICS = ("fx", "fy", "cx", "cy", "distortion_model", "distortion")
LOCALIZE_FOCAL = CrossFieldRule(
    "localize_focal_all_or_none",
    "all_or_none",
    ("fx", "fy", "cx", "cy"),
    "fx, fy, cx and cy together, or none of them (the map's camera).",
    "give all of fx, fy, cx, cy or none",
)
LOCALIZE_PRIOR = CrossFieldRule(
    "localize_prior_all_or_none",
    "all_or_none",
    ("prior_x_m", "prior_y_m", "prior_radius_m"),
    "A retrieval prior takes prior_x_m, prior_y_m and prior_radius_m together.",
    "a prior needs prior_x_m, prior_y_m and prior_radius_m",
)
LOCALIZE_YAW = CrossFieldRule(
    "localize_yaw_all_or_none",
    "all_or_none",
    ("prior_yaw_rad", "prior_yaw_tolerance_rad"),
    "prior_yaw_rad and prior_yaw_tolerance_rad together.",
    "give prior_yaw_rad and prior_yaw_tolerance_rad together",
)
LOCALIZE_YAW_NEEDS_POSITION = CrossFieldRule(
    "localize_yaw_needs_position",
    "needs",
    ("prior_yaw_rad", "prior_x_m", "prior_y_m", "prior_radius_m"),
    "A heading prior needs the position prior (prior_x_m, prior_y_m, prior_radius_m).",
    "a prior needs prior_x_m, prior_y_m and prior_radius_m",
)
LOCALIZE_DISTORTION_MODEL = CrossFieldRule(
    "localize_distortion_model_needs_focal",
    "needs",
    ("distortion_model", "fx", "fy", "cx", "cy"),
    "A lens distortion needs the camera's fx, fy, cx, cy.",
    "a lens distortion needs the camera's fx, fy, cx, cy",
)
LOCALIZE_DISTORTION = CrossFieldRule(
    "localize_distortion_needs_focal",
    "needs",
    ("distortion", "fx", "fy", "cx", "cy"),
    "Distortion coefficients need the camera's fx, fy, cx, cy.",
    "a lens distortion needs the camera's fx, fy, cx, cy",
)
LOCALIZE_CAMERA_ID = CrossFieldRule(
    "localize_camera_id_without_intrinsics",
    "only_with",
    ("camera_id", "fx", "fy", "cx", "cy", "distortion_model", "distortion"),
    "camera_id (a registered camera) or the camera's intrinsics and lens, not both.",
    "give camera_id or the camera's intrinsics, not both",
    when={"allOf": [_absent(name) for name in _INTRINSICS]},
)
LOCALIZE_RULES = (
    LOCALIZE_FOCAL,
    LOCALIZE_PRIOR,
    LOCALIZE_YAW,
    LOCALIZE_YAW_NEEDS_POSITION,
    LOCALIZE_DISTORTION_MODEL,
    LOCALIZE_DISTORTION,
    LOCALIZE_CAMERA_ID,
)

# --- rules of the multipart forms and query parameters, by operation ---------------------

_A_FILE = {"type": "string"}
ENTRY_ONE_SOURCE = CrossFieldRule(
    "entry_exactly_one_3d_source",
    "exactly_one",
    ("depth", "lidar"),
    "Exactly one 3D source: depth (with depth_scale) or lidar (with T_cam_from_lidar).",
    "send exactly one 3D source",
    present=(("depth", _A_FILE), ("lidar", _A_FILE)),
)
ENTRY_DEPTH_SCALE = CrossFieldRule(
    "entry_depth_needs_scale",
    "needs",
    ("depth", "depth_scale"),
    "depth needs depth_scale.",
    "depth needs a positive depth_scale",
)
ENTRY_LIDAR_EXTRINSICS = CrossFieldRule(
    "entry_lidar_needs_extrinsics",
    "needs",
    ("lidar", "T_cam_from_lidar"),
    "lidar needs T_cam_from_lidar.",
    "lidar needs T_cam_from_lidar",
)
UPLOAD_ONE_PART = CrossFieldRule(
    "upload_exactly_one_part",
    "exactly_one",
    ("archive", "files"),
    "Exactly one of archive (one tar/zip) and files (a non-empty file set).",
    "send either 'archive' (one tar/zip) or 'files', not both",
    present=(("archive", _A_FILE), ("files", {"type": "array", "minItems": 1})),
)
STEREO_IS_KITTI = CrossFieldRule(
    "run_stereo_depth_is_kitti",
    "only_with",
    ("depth_from", "format"),
    "depth_from other than lidar only for KITTI runs (a TUM run has its depth images).",
    "depth is for KITTI runs",
    when={
        "anyOf": [
            {"properties": {"depth_from": {"const": "lidar"}}},
            {"required": ["format"], "properties": {"format": {"const": "kitti"}}},
        ]
    },
)
ENTRY_AREA = CrossFieldRule(
    "entries_area_all_or_none",
    "all_or_none",
    ("x_m", "y_m", "radius_m"),
    "The area filter takes x_m, y_m and radius_m together.",
    "an area filter needs x_m, y_m and radius_m together",
)

FORM_RULES: dict[tuple[str, str], tuple[CrossFieldRule, ...]] = {
    ("post", "/v1/maps/{map_id}/entries"): (
        ENTRY_ONE_SOURCE,
        ENTRY_DEPTH_SCALE,
        ENTRY_LIDAR_EXTRINSICS,
    ),
    ("post", "/v1/maps/{map_id}/runs"): (UPLOAD_ONE_PART, STEREO_IS_KITTI),
    ("post", "/v1/maps/{map_id}/calibration/jobs"): (UPLOAD_ONE_PART,),
}
QUERY_RULES: dict[tuple[str, str], tuple[CrossFieldRule, ...]] = {
    ("get", "/v1/maps/{map_id}/entries"): (ENTRY_AREA,),
}


def _resolve(openapi: dict[str, Any], schema: dict[str, Any]) -> dict[str, Any]:
    ref = schema.get("$ref")
    if not ref:
        return schema
    node: Any = openapi
    for part in ref.removeprefix("#/").split("/"):
        node = node[part]
    return node


def _add_words(operation: dict[str, Any], rules: tuple[CrossFieldRule, ...]) -> None:
    words = " ".join(rule.description for rule in rules)
    text = f"Cross-field rules (422 otherwise): {words}"
    operation["description"] = f"{operation.get('description', '')}\n\n{text}".strip()


def _without_null(schema: dict[str, Any]) -> dict[str, Any]:
    """A form part's schema without its ``null`` branch: ``anyOf: [{file}, {null}]`` (an
    optional part, as FastAPI writes it) becomes the file, so clients see it is a file."""
    options = schema.get("anyOf")
    if not options:
        return schema
    kept = [o for o in options if o.get("type") != "null"]
    if len(kept) != 1 or len(kept) == len(options):
        return schema
    return {**{k: v for k, v in schema.items() if k != "anyOf"}, **kept[0]}


def _form_schemas(openapi: dict[str, Any], schema: dict[str, Any]) -> list[dict[str, Any]]:
    """A form's schema and those it takes its fields from (``allOf``: a form model)."""
    schema = _resolve(openapi, schema)
    found = [schema]
    for part in schema.get("allOf", []):
        if "$ref" in part:
            found += _form_schemas(openapi, part)
    return found


def document_form_parts(openapi: dict[str, Any]) -> None:
    """A multipart form has no null and no empty part: an optional part is left out, and
    an empty one counts as left out. Each form's optional parts are described without
    their null branch, its required text parts with at least one character; optional
    query parameters and headers without their null branch too (in place)."""
    for operations in openapi.get("paths", {}).values():
        for operation in operations.values():
            for parameter in operation.get("parameters", []):
                # a query parameter or header is left out, never null
                if not parameter.get("required") and "schema" in parameter:
                    parameter["schema"] = _without_null(parameter["schema"])
            content = operation.get("requestBody", {}).get("content", {})
            form = content.get("multipart/form-data")
            if form is None:
                continue
            for schema in _form_schemas(openapi, form["schema"]):
                properties = schema.get("properties", {})
                for name, part in properties.items():
                    properties[name] = _without_null(part)
                for name in schema.get("required", []):
                    part = properties.get(name, {})
                    if part.get("type") == "string" and "contentMediaType" not in part:
                        part.setdefault("minLength", 1)


def document_cross_field_rules(openapi: dict[str, Any]) -> dict[str, Any]:
    """Add the forms' rules to their multipart schemas and the query parameters' rules to
    their operations (``x-monoloc-rules``), each in words in the operation's description
    too; optional form parts without null (``document_form_parts``). In place."""
    document_form_parts(openapi)
    paths = openapi.get("paths", {})
    for (method, path), rules in FORM_RULES.items():
        operation = paths[path][method]
        content = operation["requestBody"]["content"]["multipart/form-data"]
        schema = _resolve(openapi, content["schema"])
        schema.setdefault("allOf", []).extend(rule.schema() for rule in rules)
        _add_words(operation, rules)
    for (method, path), rules in QUERY_RULES.items():
        operation = paths[path][method]
        operation[OPERATION_RULES_EXTRA] = [rule.query_statement() for rule in rules]
        _add_words(operation, rules)
    return openapi


# --- a lens: its coefficients by its model (monoloc.core.camera.LensDistortion.parse) ---


def _any_case(words: list[str]) -> str:
    """A regular expression matching one of ``words`` in any case (JSON Schema patterns
    have no flags)."""

    def letters(word: str) -> str:
        return "".join(f"[{c.lower()}{c.upper()}]" if c.isalpha() else c for c in word)

    return "^(?:" + "|".join(letters(w) for w in words) + ")$"


def lens_rules(model: str, coefficients: str) -> dict[str, Any]:
    """``json_schema_extra`` of a body holding a lens as ``model`` (a ROS CameraInfo name)
    and ``coefficients`` (its D, a list): each model's count of coefficients, and
    coefficients only with a model (all zero: a pinhole). The model's own names are
    ``lens_model_pattern``."""
    from monoloc.core.camera import DISTORTION_ALIASES, DISTORTION_MODELS

    branches = []
    for name, counts in DISTORTION_MODELS.items():
        names = [name, *(alias for alias, to in DISTORTION_ALIASES.items() if to == name)]
        branches.append(
            {
                "if": {
                    "required": [model],
                    "properties": {model: {"type": "string", "pattern": _any_case(names)}},
                },
                "then": _present(
                    coefficients,
                    {"type": "array", "minItems": min(counts), "maxItems": max(counts)},
                ),
            }
        )
    counts = {
        "description": "The coefficients' count fits the model: "
        + "; ".join(f"{n} {' or '.join(map(str, c))}" for n, c in DISTORTION_MODELS.items())
        + ".",
        "allOf": branches,
        RULE_EXTRA: {
            "name": "lens_coefficients_fit_the_model",
            "kind": "fits",
            "fields": [model, coefficients],
            "message": "coefficients, got",
        },
    }
    pinhole = {"type": "string", "pattern": _any_case(["", "none", "pinhole"])}
    without_model = {
        "description": f"{coefficients} without {model} (or with none or pinhole) only if "
        "every coefficient is 0.",
        "if": {"anyOf": [_absent(model), {"properties": {model: pinhole}}]},
        "then": {
            "properties": {
                coefficients: {
                    "anyOf": [{"type": "null"}, {"type": "array", "items": {"const": 0}}]
                }
            }
        },
        RULE_EXTRA: {
            "name": "lens_coefficients_need_a_model",
            "kind": "needs",
            "fields": [coefficients, model],
            "message": "distortion coefficients given without their model",
        },
    }
    return {"allOf": [counts, without_model]}


def lens_model_pattern() -> str:
    """The lens model names the server takes, any case (none and pinhole: no lens)."""
    from monoloc.core.camera import DISTORTION_ALIASES, DISTORTION_MODELS

    return _any_case(["", "none", "pinhole", *DISTORTION_MODELS, *DISTORTION_ALIASES])
