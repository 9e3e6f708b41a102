"""The indoor scenario: rooms with a taped race track for a 1:10 car, in a z-up world.

A room is a box (walls facing inwards, floor, suspended ceiling with light panels):
walls carry sections of shelves, cabinets, doors, posters, whiteboards, windows,
pegboards, lockers and bins, and some long stretches of bare paint (the method's hard
case); furniture stands against the walls (shelving units, cabinets, lockers), a table
and boxes in the infield. Obstacles (cardboard boxes, foam blocks) near the track are
separate from the static scene so that a run can have them moved, as between two
sessions in a lab; chairs, stands and people's legs stand right beside the tape (near
clutter, ``monoloc.sim.indoor.clutter``). The world has a main room (map, query,
off-centre runs) and a training room 60 m away along +x (never seen by them).

World frame: the motion-capture frame, origin on the floor at the centre of the main
room, x along its long side, z up.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from monoloc.sim.indoor.clutter import add_near_clutter
from monoloc.sim.indoor.furniture import add_furniture
from monoloc.sim.indoor.infield import add_infield, obstacle_slots
from monoloc.sim.indoor.room import RoomConfig, lamp_positions, room_bounds
from monoloc.sim.indoor.track import TrackShape, make_track
from monoloc.sim.scene import KIND_GROUND, KIND_LAMP, KIND_WALL, Scene, SceneBuilder
from monoloc.sim.shapes import add_split_quad, add_wall, texture_size_px
from monoloc.sim.textures import TextureSpec, texture_seed

# Section styles of non-plain walls and their weights.
_STYLE_WEIGHTS = {
    "shelf": 3,
    "cabinet": 2,
    "poster": 3,
    "whiteboard": 1,
    "window": 1,
    "pegboard": 1,
    "lockers": 1,
    "storage": 2,
    "brick": 1,
}


_FLOOR_TONES = {
    "concrete": (0.18, 0.35),
    "tiles": (0.2, 0.5),
    "parquet": (0.2, 0.4),
    "carpet": (0.1, 0.25),
}


@dataclass(frozen=True)
class Room:
    """A built room: its config, track, static scene and slots (N, 3) of (x, y, yaw)
    where obstacles may stand."""

    name: str
    config: RoomConfig
    track: TrackShape
    static: Scene
    slots: np.ndarray
    floor_style: str


@dataclass(frozen=True)
class IndoorWorld:
    seed: int
    rooms: dict[str, Room] = field(repr=False)


def build_world(configs: dict[str, RoomConfig], seed: int) -> IndoorWorld:
    """All rooms, deterministic in ``seed``."""
    rooms = {
        name: build_room(name, config, seed * 7919 + k * 104729)
        for k, (name, config) in enumerate(configs.items())
    }
    return IndoorWorld(seed=seed, rooms=rooms)


def build_room(name: str, config: RoomConfig, seed: int) -> Room:
    rng = np.random.default_rng([seed, 1])
    track = make_track(
        config.size_m,
        rng,
        config.clearance_m,
        config.min_turn_radius_m,
        config.centre_xy,
        config.twist,
    )
    b = SceneBuilder()
    floor_style = str(
        rng.choice(["concrete", "tiles", "parquet", "carpet"], p=[0.4, 0.3, 0.2, 0.1])
    )
    _floor_and_ceiling(b, rng, config, track, floor_style)
    walls = _walls(b, rng, config)
    add_furniture(b, rng, config, track, walls)
    add_infield(b, rng, config, track)
    slots = obstacle_slots(rng, config, track, walls)
    # Its own stream: the rest of the room is the same with or without near clutter.
    add_near_clutter(b, np.random.default_rng([seed, 5]), config, track)
    return Room(name, config, track, b.build(), slots, floor_style)


def _floor_and_ceiling(b: SceneBuilder, rng, config: RoomConfig, track, floor_style) -> None:
    x0, y0, x1, y1 = room_bounds(config)
    w, d = x1 - x0, y1 - y0
    ppm = config.floor_ppm
    tone = float(rng.uniform(*_FLOOR_TONES[floor_style]))
    tape = 0.9 if tone < 0.32 or rng.random() < 0.4 else 0.05  # tape stands out
    spec = TextureSpec(
        "indoor_floor",
        *texture_size_px(w, d, ppm),
        seed=texture_seed(rng),
        params=(
            ("ppm", ppm),
            ("style", floor_style),
            ("tone", round(tone, 4)),
            ("x_min", x0),
            ("y_max", y1),
            ("track", tuple(round(v, 9) for v in track.as_params())),
            ("track_width_m", config.track_width_m),
            ("tape_tone", tape),
        ),
        wrap=False,
    )
    # Texture x along +x, y along -y: the front face looks up.
    add_split_quad(b, (x0, y1, 0.0), (1, 0, 0), (0, -1, 0), w, d, spec, ppm, KIND_GROUND, 0.75)
    if config.featureless_end_m > 0:
        _featureless_mat(b, rng, config)
    lamps = lamp_positions(config)
    ceil = TextureSpec(
        "indoor_ceiling",
        *texture_size_px(w, d, config.ceiling_ppm),
        seed=texture_seed(rng),
        params=(
            ("ppm", config.ceiling_ppm),
            ("x_min", x0),
            ("y_min", y0),
            ("lights", tuple((round(x, 6), round(y, 6)) for x, y in lamps)),
        ),
    )
    h = config.height_m
    add_split_quad(
        b, (x0, y0, h), (1, 0, 0), (0, 1, 0), w, d, ceil, config.ceiling_ppm, KIND_WALL, 2.0
    )
    lamp = b.texture(TextureSpec("indoor_lamp", 60, 60, seed=0))
    for x, y in lamps:
        b.add_light((x, y, h - 0.05), 1.0)
        # The panel itself, just below the ceiling, facing down.
        b.add_quad(
            (x - 0.3, y - 0.3, h - 0.01), (1, 0, 0), (0, 1, 0), 0.6, 0.6, lamp, 100.0, KIND_LAMP
        )


def _featureless_mat(b: SceneBuilder, rng, config: RoomConfig) -> None:
    """A plain grey mat over the floor of the room's bare +x end (see RoomConfig)."""
    x0, y0, x1, y1 = room_bounds(config)
    depth = min(config.featureless_end_m, x1 - x0)
    ppm = 60.0
    spec = TextureSpec(
        "indoor_surface",
        *texture_size_px(depth, y1 - y0, ppm),
        seed=texture_seed(rng),
        params=(("ppm", ppm), ("style", "mat")),
    )
    add_split_quad(
        b, (x1 - depth, y1, 0.005), (1, 0, 0), (0, -1, 0), depth, y1 - y0, spec, ppm,
        KIND_GROUND, 0.75,
    )  # fmt: skip


@dataclass(frozen=True)
class WallLayout:
    """One wall: from ``a`` to ``b`` (xy, the room on the left), and its sections
    ((style, x0, x1), ...) with x from b (the wall's left end seen from the room)."""

    a: np.ndarray
    b: np.ndarray
    sections: tuple[tuple[str, float, float], ...]

    @property
    def length_m(self) -> float:
        return float(np.linalg.norm(self.a - self.b))

    def point(self, x_m: float) -> np.ndarray:
        """World xy at ``x_m`` along the wall from its left end (seen from the room)."""
        return self.b + (self.a - self.b) * (x_m / self.length_m)

    @property
    def inward(self) -> np.ndarray:
        d = (self.b - self.a) / self.length_m
        return np.array([-d[1], d[0]])


def _sections(rng, length: float, plain: tuple[float, float] | None, doors: list[int]):
    """Random sections of a wall of ``length`` m; ``plain`` (x0, x1) is kept bare."""
    out: list[tuple[str, float, float]] = []
    x = 0.0
    styles, weights = zip(*_STYLE_WEIGHTS.items(), strict=True)
    p = np.array(weights, float) / sum(weights)
    while x < length - 1e-6:
        if plain is not None and plain[0] <= x + 1e-6 < plain[1]:
            out.append(("plain", x, plain[1]))
            x = plain[1]
            continue
        end = min(length, x + rng.uniform(0.9, 2.2))
        if plain is not None and x < plain[0] < end:
            end = plain[0]
        if length - end < 0.6:
            end = length if plain is None or plain[0] >= length else end
        style = str(rng.choice(styles, p=p))
        if doors[0] > 0 and end - x >= 1.2 and rng.random() < 0.3:
            style, doors[0] = "door", doors[0] - 1
        out.append((style, round(x, 4), round(end, 4)))
        x = end
    return tuple(out)


def _walls(b: SceneBuilder, rng, config: RoomConfig) -> list[WallLayout]:
    x0, y0, x1, y1 = room_bounds(config)
    corners = [np.array(p, float) for p in ((x0, y0), (x1, y0), (x1, y1), (x0, y1))]
    perimeter = 2 * (x1 - x0 + y1 - y0)
    plain_wall = int(rng.integers(4))
    doors = [config.doors]
    walls = []
    paint = rng.uniform(0.55, 0.82)
    for k in range(4):
        a, c = corners[k], corners[(k + 1) % 4]
        length = float(np.linalg.norm(c - a))
        plain = None
        if k == plain_wall:
            span = min(length, config.plain_wall_fraction * perimeter)
            start = rng.uniform(0, length - span)
            plain = (round(start, 4), round(start + span, 4))
        if k == 1 and config.featureless_end_m > 0:  # the +x wall, the bare end
            plain = (0.0, round(length, 4))
        sections = _sections(rng, length, plain, doors)
        layout = WallLayout(a, c, sections)
        spec = TextureSpec(
            "indoor_wall",
            *texture_size_px(length, config.height_m, config.wall_ppm),
            seed=texture_seed(rng),
            params=(
                ("ppm", config.wall_ppm),
                ("paint", round(float(paint * rng.uniform(0.93, 1.07)), 4)),
                ("sections", sections),
                ("skirting_tone", round(float(rng.uniform(0.2, 0.95)), 4)),
            ),
        )
        add_wall(b, a, c, 0.0, config.height_m, spec, config.wall_ppm, KIND_WALL, max_piece_m=0.6)
        walls.append(layout)
    return walls
