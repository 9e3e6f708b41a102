"""The one options model of a query (form, query parameters, stream header): groups all
or none, ranges, the prior it builds, and the form winning over query parameters."""

from __future__ import annotations

import pytest

from monoloc.core.errors import InvalidInputError
from monoloc.core.prior import RetrievalPrior
from monoloc.server.api.schemas_localize import LocalizeOptions


def test_a_full_set_builds_the_prior_and_the_focal():
    options = LocalizeOptions.parse(
        dict(
            fx="300", fy=300, cx=159.5, cy=119.5, prior_x_m=1, prior_y_m="2", prior_radius_m=3,
            prior_yaw_rad=0.5, prior_yaw_tolerance_rad=0.25, k="7", seed=11, unknown="x",
        )
    )  # fmt: skip
    assert options.focal == (300.0, 300.0, 159.5, 119.5)
    assert options.prior == RetrievalPrior(1.0, 2.0, 3.0, 0.5, 0.25)
    assert (options.k, options.seed) == (7, 11)
    empty = LocalizeOptions.parse({"k": "", "seed": None})
    assert (empty.focal, empty.prior, empty.k, empty.seed) == (None, None, None, None)


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"fx": 300, "fy": 300}, "give all of fx, fy, cx, cy"),
        ({"fx": -1, "fy": 300, "cx": 1, "cy": 1}, "fx and fy must be positive"),
        ({"fx": "nan", "fy": 300, "cx": 1, "cy": 1}, "fx must be finite"),
        ({"prior_x_m": 1, "prior_y_m": 2}, "a prior needs prior_x_m, prior_y_m and prior_r"),
        ({"prior_yaw_rad": 1, "prior_yaw_tolerance_rad": 1}, "a prior needs"),
        ({"prior_x_m": 1, "prior_y_m": 2, "prior_radius_m": 3, "prior_yaw_rad": 1}, "together"),
        ({"prior_x_m": 1, "prior_y_m": 2, "prior_radius_m": 0}, "prior_radius_m must be pos"),
        ({"k": 0}, r"k must be an integer in 1\.\.100"),
        ({"k": 101}, r"k must be an integer in 1\.\.100"),
        ({"seed": -1}, r"seed must be an integer in \[0, 2\^63\)"),
        ({"seed": 2**63}, r"seed must be an integer in \[0, 2\^63\)"),
        ({"k": "ten"}, "k: Input should be a valid integer"),
    ],
)
def test_incomplete_groups_and_out_of_range_values_are_invalid_input(values, message):
    with pytest.raises(InvalidInputError, match=message):
        LocalizeOptions.parse(values)


def test_the_form_wins_field_by_field_over_query_parameters():
    form = LocalizeOptions(k=4, prior_x_m=1.0, prior_y_m=2.0, prior_radius_m=3.0)
    merged = form.over({"k": "2", "seed": "9", "prior_x_m": "50"})
    assert (merged.k, merged.seed, merged.prior) == (4, 9, RetrievalPrior(1.0, 2.0, 3.0))
    with pytest.raises(InvalidInputError, match="k must be"):
        LocalizeOptions().over({"k": "0"})
