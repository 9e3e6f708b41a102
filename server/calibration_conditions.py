"""A map's calibration conditions as stored: the base calibration's dict holds, under
``"conditions"``, one dict per condition, keyed by the entry tag that names it (e.g.
``night``): the parameters of a model calibrated on a training run recorded in that
condition (a night run against its own night map), with the provenance and updated_at
of that calibration. A hypothesis from an entry carrying the tag is weighed by that
model (``monoloc.core.measurement.MeasurementModel.conditions``).

A condition needs a base calibration to hang on; calibrating the base again keeps the
conditions calibrated with the same vocabulary (their e_vlad statistics still hold) and
drops the others. Pure: stored dicts in, dicts to store out.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from monoloc.core.errors import ConflictError, InvalidInputError, NotFoundError
from monoloc.core.measurement import DEFAULT_RETRIEVAL_FRAME, MeasurementModel
from monoloc.server.storage.entry_checks import normalise_tag


def condition_name(name: str) -> str:
    """A condition's name: an entry tag, lower-cased (InvalidInputError if not a tag)."""
    return normalise_tag(name, "condition name")


def require_base(calibration: Mapping[str, Any] | None, map_id: int, condition: str) -> None:
    """ConflictError unless the map has a base calibration for ``condition`` to join."""
    if not calibration:
        raise ConflictError(
            f"map {map_id} has no calibration to add condition {condition!r} to: calibrate "
            "the map without a condition first"
        )


def condition_entry(
    model: MeasurementModel, provenance: Mapping[str, Any], updated_at: str | None
) -> dict[str, Any]:
    """What a condition stores: its model's parameters (no conditions of its own), its
    provenance and when it was set."""
    if model.conditions:
        raise InvalidInputError(
            f"a condition's model cannot have conditions of its own, got {sorted(model.conditions)}"
        )
    values = model.to_dict()
    del values["conditions"]
    return {**values, "provenance": dict(provenance), "updated_at": updated_at}


def _vocabulary_of(calibration: Mapping[str, Any]) -> str | None:
    provenance = calibration.get("provenance")
    return provenance.get("vocabulary_hash") if isinstance(provenance, Mapping) else None


def with_new_base(stored: Mapping[str, Any] | None, base: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` (a freshly fitted calibration, its provenance naming its vocabulary) with
    the stored conditions calibrated with the same vocabulary; the names of the others,
    dropped, go to ``provenance["conditions_dropped"]``."""
    previous = dict((stored or {}).get("conditions") or {})
    vocabulary = _vocabulary_of(base)
    kept = {
        name: condition
        for name, condition in previous.items()
        if vocabulary is not None and _vocabulary_of(condition) == vocabulary
    }
    provenance = dict(base.get("provenance") or {})
    dropped = sorted(set(previous) - set(kept))
    if dropped:
        provenance["conditions_dropped"] = dropped
    return checked({**base, "provenance": provenance, "conditions": kept})


def with_condition(
    stored: Mapping[str, Any] | None, map_id: int, name: str, entry: Mapping[str, Any]
) -> dict[str, Any]:
    """The stored calibration with condition ``name`` set to ``entry`` (replacing an
    older one of that name), the base untouched. ConflictError without a base."""
    require_base(stored, map_id, name)
    conditions = {**(stored.get("conditions") or {}), name: dict(entry)}
    return checked({**stored, "conditions": conditions})


def without_condition(stored: Mapping[str, Any] | None, map_id: int, name: str) -> dict[str, Any]:
    """The stored calibration without condition ``name``; NotFoundError if it has none."""
    conditions = dict((stored or {}).get("conditions") or {})
    if name not in conditions:
        have = ", ".join(sorted(conditions)) or "none"
        raise NotFoundError(
            f"map {map_id} has no calibration for condition {name!r} (conditions: {have})"
        )
    del conditions[name]
    return {**stored, "conditions": conditions}


def put_conditions(
    conditions: Mapping[str, Mapping[str, Any]], updated_at: str
) -> dict[str, dict[str, Any]]:
    """The conditions of a calibration PUT as stored: names normalised as tags, each
    model checked (``MeasurementModel.from_dict``; InvalidInputError) and stored with
    source "put", its provenance (an object, default empty) and ``updated_at``; a model
    that leaves its retrieval frame out is in the product's (a stored calibration that
    leaves it out was fitted before the choice existed: world axes)."""
    out: dict[str, dict[str, Any]] = {}
    for given, values in conditions.items():
        name = condition_name(given)
        if name in out:
            raise InvalidInputError(f"condition {name!r} is given twice")
        provenance = values.get("provenance") or {}
        if not isinstance(provenance, Mapping):
            raise InvalidInputError(f"condition {name!r}: provenance must be an object")
        try:
            frame = values.get("retrieval_frame") or DEFAULT_RETRIEVAL_FRAME
            given = {**values, "retrieval_frame": frame}
            model = dataclasses.replace(MeasurementModel.from_dict(given), source="put")
            out[name] = condition_entry(model, provenance, updated_at)
        except InvalidInputError as exc:
            raise InvalidInputError(f"condition {name!r}: {exc}") from exc
    return out


def public_conditions(stored: Mapping[str, Any] | None) -> dict[str, dict[str, Any]]:
    """Each stored condition's parameters (as its model reads them), provenance and
    updated_at, by name."""
    conditions = (stored or {}).get("conditions") or {}
    return {
        name: condition_entry(
            MeasurementModel.from_dict(values),
            values.get("provenance") or {},
            values.get("updated_at"),
        )
        for name, values in sorted(conditions.items())
    }


def checked(calibration: dict[str, Any]) -> dict[str, Any]:
    """``calibration`` if a vehicle can load it, conditions included (InvalidInputError
    otherwise), with the pose-error model it selects spelled out (a PUT may leave it to
    the default)."""
    return {**calibration, "covariance": MeasurementModel.from_dict(calibration).covariance}
