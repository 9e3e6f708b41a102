"""The indoor texture kinds: the registry a ``monoloc.sim.textures.TextureBank`` of an
indoor scene is made with."""

from __future__ import annotations

from monoloc.sim.indoor.floor_textures import floor
from monoloc.sim.indoor.surface_textures import ceiling, lamp_panel, surface
from monoloc.sim.indoor.wall_textures import wall
from monoloc.sim.textures import TextureGenerator

INDOOR_TEXTURES: dict[str, TextureGenerator] = {
    "indoor_wall": wall,
    "indoor_floor": floor,
    "indoor_ceiling": ceiling,
    "indoor_surface": surface,
    "indoor_lamp": lamp_panel,
}
