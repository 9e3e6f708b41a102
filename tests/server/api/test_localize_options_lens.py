"""A query's lens distortion as the localize form and the stream header carry it."""

from __future__ import annotations

import pytest

from monoloc.core.errors import InvalidInputError
from monoloc.server.api.routes.stream import _option_fields
from monoloc.server.api.schemas_localize import LocalizeOptions

FOCAL = {"fx": 640.0, "fy": 640.0, "cx": 511.5, "cy": 287.5}


def test_the_form_s_distortion_becomes_the_lens_model():
    options = LocalizeOptions.parse(
        {**FOCAL, "distortion_model": "plumb_bob", "distortion": "-0.28, 0.09,0.0006,-0.0004"}
    )
    assert options.lens.model == "plumb_bob"
    assert options.lens.coefficients == (-0.28, 0.09, 0.0006, -0.0004)
    assert LocalizeOptions.parse(FOCAL).lens is None
    assert LocalizeOptions.parse({**FOCAL, "distortion_model": "none"}).lens is None


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"distortion_model": "plumb_bob", "distortion": "0.1,0,0,0"}, "needs the camera's fx"),
        ({**FOCAL, "distortion_model": "ocam", "distortion": "0.1"}, "unknown lens distortion"),
        ({**FOCAL, "distortion_model": "plumb_bob", "distortion": "0.1,x"}, "comma-separated"),
        ({**FOCAL, "distortion_model": "equidistant", "distortion": "0.1"}, "takes 4"),
    ],
)
def test_a_bad_lens_is_refused_naming_what_is_wrong(fields, message):
    with pytest.raises(InvalidInputError, match=message):
        LocalizeOptions.parse(fields)


def test_the_stream_header_carries_the_lens_as_a_list():
    header = {
        "seq": 0,
        "intrinsics": {**FOCAL, "distortion_model": "fisheye", "distortion": [0.05, 0, 0, 0]},
    }
    options = LocalizeOptions.parse(_option_fields(header))
    assert options.lens.model == "equidistant" and options.lens.coefficients[0] == 0.05
    with pytest.raises(InvalidInputError, match="list of numbers"):
        _option_fields({"intrinsics": {**FOCAL, "distortion": "0.05"}})
