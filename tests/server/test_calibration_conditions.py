"""The stored calibration's conditions: a new base keeps the conditions calibrated with
its vocabulary and names the dropped ones; a condition needs a base and replaces its
namesake only; a missing condition cannot be removed."""

from __future__ import annotations

import pytest

from monoloc.core.errors import ConflictError, NotFoundError
from monoloc.core.measurement import MeasurementModel
from monoloc.server.calibration_conditions import (
    condition_entry,
    with_condition,
    with_new_base,
    without_condition,
)


def _entry(vocabulary: str | None, mu_x: float = 0.0) -> dict:
    provenance = {} if vocabulary is None else {"vocabulary_hash": vocabulary}
    return condition_entry(MeasurementModel(mu1=[mu_x, 0.0, 0.0]), provenance, "2024-05-01")


def _base(vocabulary: str, mu_x: float = 0.0) -> dict:
    model = MeasurementModel(mu1=[mu_x, 0.0, 0.0]).to_dict()
    return {**model, "provenance": {"vocabulary_hash": vocabulary}, "updated_at": "t"}


def test_a_new_base_keeps_the_conditions_of_its_vocabulary_only():
    night, rain, fog = _entry("aaaa"), _entry("bbbb"), _entry(None)  # fog: PUT, no hash
    stored = {**_base("aaaa"), "conditions": {"night": night, "rain": rain, "fog": fog}}
    new = with_new_base(stored, _base("aaaa", mu_x=0.3))
    assert new["mu1"] == [0.3, 0.0, 0.0] and new["conditions"] == {"night": night}
    assert new["provenance"]["conditions_dropped"] == ["fog", "rain"]
    first = with_new_base(None, _base("aaaa"))
    assert first["conditions"] == {} and "conditions_dropped" not in first["provenance"]


def test_a_condition_joins_a_base_and_replaces_its_namesake_only():
    with pytest.raises(ConflictError, match="calibrate the map without a condition first"):
        with_condition(None, 7, "night", _entry("aaaa"))
    stored = {**_base("aaaa"), "conditions": {"night": _entry("aaaa"), "rain": _entry("aaaa")}}
    new = with_condition(stored, 7, "night", _entry("aaaa", mu_x=0.5))
    assert new["conditions"]["night"]["mu1"] == [0.5, 0.0, 0.0]
    assert new["conditions"]["rain"] == stored["conditions"]["rain"]
    assert {**new, "conditions": {}} == _base("aaaa")  # the base untouched
    assert list(without_condition(new, 7, "night")["conditions"]) == ["rain"]
    with pytest.raises(NotFoundError, match="no calibration for condition 'fog'"):
        without_condition(new, 7, "fog")
