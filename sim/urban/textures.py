"""The city's texture kinds: the registry a ``monoloc.sim.textures.TextureBank`` of an
urban scene is made with."""

from __future__ import annotations

from monoloc.sim.textures import TextureGenerator
from monoloc.sim.urban.facades import facade
from monoloc.sim.urban.street_textures import (
    asphalt,
    car,
    foliage,
    kerb,
    lamp,
    lawn,
    metal,
    road,
    sidewalk,
    sign,
)

URBAN_TEXTURES: dict[str, TextureGenerator] = {
    "facade": facade,
    "road": road,
    "asphalt": asphalt,
    "sidewalk": sidewalk,
    "kerb": kerb,
    "lawn": lawn,
    "car": car,
    "metal": metal,
    "lamp": lamp,
    "sign": sign,
    "foliage": foliage,
}
