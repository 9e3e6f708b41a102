"""An indoor room's settings and plain geometry: size, height, where it stands, its
track's width and clearances, how much it holds; the size presets of the main and the
training room; the floor's bounds and where the ceiling lamps hang.

World frame: the motion-capture frame, origin on the floor at the centre of the main
room, x along its long side, z up; metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from monoloc.core.errors import InvalidInputError


@dataclass(frozen=True)
class NearClutterConfig:
    """Things standing right beside the track (issue 51): chairs, light or microphone
    stands and people's legs, ``items`` of them spread along the lap (the bare end left
    out), each on a random side with its near edge ``gap_m`` (uniform range) outside the
    tape. ``kinds`` weighs chair / stand / legs.

    Why: the centre-line camera passes their near edges at 0.38-0.5 m, and their image moves with
    1/depth: 2 cm sideways shifts a leg at 0.5 m by ~25 px (f 615 px) against a wall at
    2.5 m that moves 5 px, so what they hide of the background, and the corners their
    edges make against it, change within a few cm of the mapped views, where a far wall's
    features still match. A real lab floor beside an RC track holds such things; their
    number and distances here are an assumption (the paper names no clutter; its
    conjecture, that an off-line camera sees what the map does not hold, needs it). 0
    items: none."""

    items: int = 30
    gap_m: tuple[float, float] = (0.03, 0.15)
    kinds: tuple[float, float, float] = (0.4, 0.3, 0.3)


@dataclass(frozen=True)
class RoomConfig:
    """One room: size (x, y) and height in metres, centre in the world; the track's
    width, its clearance from the walls, tightest turn and twistiness; how much of the
    wall perimeter is bare paint; numbers of furniture pieces, infield objects and
    movable obstacles; texture resolutions (texels per metre).

    featureless_end_m: the room's +x end is bare over this depth (0: not): its wall plain
    paint, its floor under a plain grey mat (over the tape), nothing standing on it. The
    track's approach to that wall and the start of its turn see nothing to match, so the
    localizer must dead-reckon, as the paper's car did along its featureless wall.

    near_clutter: what stands right beside the tape (NearClutterConfig)."""

    size_m: tuple[float, float] = (8.0, 6.0)
    height_m: float = 2.7
    centre_xy: tuple[float, float] = (0.0, 0.0)
    track_width_m: float = 0.7
    clearance_m: float = 1.15
    min_turn_radius_m: float = 0.8
    twist: float = 1.0
    plain_wall_fraction: float = 0.15
    featureless_end_m: float = 2.2
    doors: int = 2
    furniture: int = 4
    infield_objects: int = 3
    obstacles: int = 6
    wall_ppm: float = 300.0
    floor_ppm: float = 350.0
    ceiling_ppm: float = 60.0
    near_clutter: NearClutterConfig = field(default_factory=NearClutterConfig)


SIZE_PRESETS = {
    "small": ((8.0, 6.0), 1, 1.0),
    "medium": ((10.0, 7.0), 2, 1.2),
    "large": ((12.0, 9.0), 3, 1.5),
}
TRAIN_ROOM_CENTRE_XY = (60.0, 0.0)


def room_configs(size: str) -> dict[str, RoomConfig]:
    """Main and training rooms of a size preset (small 8 x 6 m, medium 10 x 7 m, large
    12 x 9 m; the training room is a little smaller with its own layout)."""
    if size not in SIZE_PRESETS:
        raise InvalidInputError(f"unknown size {size!r}; use one of {sorted(SIZE_PRESETS)}")
    room, _, twist = SIZE_PRESETS[size]
    main = RoomConfig(size_m=room, twist=twist)
    train = replace(
        main,
        size_m=(room[0] - 1.0, room[1]),
        centre_xy=TRAIN_ROOM_CENTRE_XY,
        twist=twist * 1.2,
    )
    return {"main": main, "train": train}


def room_bounds(config: RoomConfig) -> tuple[float, float, float, float]:
    """(x_min, y_min, x_max, y_max) of the room's floor."""
    cx, cy = config.centre_xy
    w, d = config.size_m
    return cx - w / 2, cy - d / 2, cx + w / 2, cy + d / 2


def lamp_positions(config: RoomConfig) -> list[tuple[float, float]]:
    x0, y0, x1, y1 = room_bounds(config)
    nx, ny = max(1, round((x1 - x0) / 2.5)), max(1, round((y1 - y0) / 2.5))
    return [
        (x0 + (i + 0.5) * (x1 - x0) / nx, y0 + (j + 0.5) * (y1 - y0) / ny)
        for i in range(nx)
        for j in range(ny)
    ]
