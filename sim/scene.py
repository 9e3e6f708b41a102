"""A scene: textured planar quads in a z-up world frame, plus point lights.

A quad is the rectangle ``origin + s * axis_u + t * axis_v`` for ``s`` in [0, size_u] and
``t`` in [0, size_v] metres; ``axis_u`` and ``axis_v`` are orthonormal. Like an image seen
by a camera (x right, y down, looking forward), the front face looks along
``axis_v x axis_u``: seen from the front, ``axis_u`` points right and ``axis_v`` down, so
text in a texture reads correctly. Texture pixel (x, y) (pixel centres at integers) sits
at ``s = (x + 0.5 - tex_offset_px[0]) / texels_per_m`` and likewise ``t`` with y. Several quads may
share one texture with different offsets (a long wall cut into strips).

Textures are ``monoloc.sim.textures.TextureSpec`` records: small, hashable and picklable;
the pixels are made on demand and cached by a ``TextureBank`` (same module), so a large
city costs memory only for what a camera has recently seen, and output does not depend
on the order in which textures are first used.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.sim.textures import TextureSpec

# Surface kinds: used by lighting (lamps glow at night) and by the LiDAR (reflectance).
KIND_GROUND = 0
KIND_ROAD = 1
KIND_WALL = 2
KIND_CAR = 3
KIND_POLE = 4
KIND_SIGN = 5
KIND_FOLIAGE = 6
KIND_LAMP = 7
KIND_GLASS = 8


@dataclass(frozen=True)
class Quads:
    """N quads as arrays (float64 unless said): origin (N,3), axis_u (N,3), axis_v (N,3),
    size_u (N,), size_v (N,), texture (N,) int index into the scene's textures,
    tex_offset_px (N,2), texels_per_m (N,), kind (N,) int, reflectance (N,) in [0,1],
    two_sided (N,) bool."""

    origin: np.ndarray
    axis_u: np.ndarray
    axis_v: np.ndarray
    size_u: np.ndarray
    size_v: np.ndarray
    texture: np.ndarray
    tex_offset_px: np.ndarray
    texels_per_m: np.ndarray
    kind: np.ndarray
    reflectance: np.ndarray
    two_sided: np.ndarray

    def __len__(self) -> int:
        return int(self.origin.shape[0])

    @property
    def normal(self) -> np.ndarray:
        """(N, 3) unit front-face normals (axis_v x axis_u)."""
        return np.cross(self.axis_v, self.axis_u)

    def corners(self) -> np.ndarray:
        """(N, 4, 3) corners in order (0,0), (su,0), (su,sv), (0,sv)."""
        du = self.axis_u * self.size_u[:, None]
        dv = self.axis_v * self.size_v[:, None]
        o = self.origin
        return np.stack([o, o + du, o + du + dv, o + dv], axis=1)


@dataclass(frozen=True)
class Scene:
    """Quads, the textures they reference, and point lights (M, 3) world positions with
    (M,) intensities (used at night) and (M, 3) throw directions: a street lamp's
    horizontal unit vector towards the road (its shield dims the other side), zeros for
    a light that shines the same all round."""

    quads: Quads
    textures: tuple[TextureSpec, ...]
    light_positions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    light_intensities: np.ndarray = field(default_factory=lambda: np.zeros(0))
    light_directions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


def concat_scenes(scenes: list[Scene]) -> Scene:
    """One scene holding all quads, textures and lights of ``scenes``."""
    arrays: dict[str, list[np.ndarray]] = {name: [] for name in Quads.__dataclass_fields__}
    textures: list[TextureSpec] = []
    for scene in scenes:
        for name in arrays:
            value = getattr(scene.quads, name)
            if name == "texture":
                value = value + len(textures)
            arrays[name].append(value)
        textures.extend(scene.textures)
    quads = Quads(**{name: np.concatenate(parts) for name, parts in arrays.items()})
    return Scene(
        quads=quads,
        textures=tuple(textures),
        light_positions=np.concatenate([s.light_positions for s in scenes]).reshape(-1, 3),
        light_intensities=np.concatenate([s.light_intensities for s in scenes]),
        light_directions=np.concatenate([s.light_directions for s in scenes]).reshape(-1, 3),
    )


class SceneBuilder:
    """Accumulates quads and textures; ``build()`` returns an immutable :class:`Scene`."""

    def __init__(self) -> None:
        self._rows: list[tuple] = []
        self._textures: list[TextureSpec] = []
        self._texture_index: dict[TextureSpec, int] = {}
        self._lights: list[tuple[np.ndarray, float, np.ndarray]] = []

    def texture(self, spec: TextureSpec) -> int:
        """Index of ``spec`` in this scene, adding it if new."""
        if spec not in self._texture_index:
            self._texture_index[spec] = len(self._textures)
            self._textures.append(spec)
        return self._texture_index[spec]

    def add_quad(
        self,
        origin,
        axis_u,
        axis_v,
        size_u: float,
        size_v: float,
        texture: int,
        texels_per_m: float,
        kind: int,
        tex_offset_px=(0.0, 0.0),
        reflectance: float = 0.3,
        two_sided: bool = False,
    ) -> None:
        axis_u = np.asarray(axis_u, dtype=np.float64)
        axis_v = np.asarray(axis_v, dtype=np.float64)
        if abs(np.dot(axis_u, axis_v)) > 1e-6 or size_u <= 0 or size_v <= 0:
            raise InvalidInputError(f"degenerate quad at {origin}: axes {axis_u}, {axis_v}")
        self._rows.append(
            (
                origin,
                axis_u / np.linalg.norm(axis_u),
                axis_v / np.linalg.norm(axis_v),
                size_u,
                size_v,
                texture,
                tex_offset_px,
                texels_per_m,
                kind,
                reflectance,
                two_sided,
            )
        )

    def add_light(self, position_world, intensity: float, direction_world=(0.0, 0.0, 0.0)) -> None:
        """A point light; ``direction_world``: horizontal throw direction (see Scene)."""
        self._lights.append(
            (
                np.asarray(position_world, dtype=np.float64),
                intensity,
                np.asarray(direction_world, dtype=np.float64),
            )
        )

    def build(self) -> Scene:
        names = list(Quads.__dataclass_fields__)
        dtypes = [np.float64] * 5 + [np.int32, np.float64, np.float64, np.int16, np.float64, bool]
        columns = list(zip(*self._rows, strict=True)) if self._rows else [[]] * len(names)
        arrays = {}
        for name, dtype, column in zip(names, dtypes, columns, strict=True):
            arr = np.asarray(column, dtype=dtype)
            if name in ("origin", "axis_u", "axis_v"):
                arr = arr.reshape(-1, 3)
            elif name == "tex_offset_px":
                arr = arr.reshape(-1, 2)
            arrays[name] = arr
        lights = self._lights
        return Scene(
            quads=Quads(**arrays),
            textures=tuple(self._textures),
            light_positions=np.array([p for p, _, _ in lights]).reshape(-1, 3),
            light_intensities=np.array([i for _, i, _ in lights], dtype=np.float64),
            light_directions=np.array([d for _, _, d in lights]).reshape(-1, 3),
        )
