"""The outdoor scenario: a seeded city of street grids ("districts") in a z-up world.

A district is a grid of streets with loops; its blocks are lined with buildings of
varied footprints, heights and set-backs, sidewalks, kerbs, lamps, trees and signs;
an outer ring of buildings faces the perimeter streets. The city has a main district
(driven by the map, query, night and off-centre runs) and a training district far away
(never seen by them). Parked cars are separate from the static scene so that each run
can have its own arrangement (some moved or removed between runs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from monoloc.core.errors import InvalidInputError
from monoloc.sim.scene import Scene, SceneBuilder, concat_scenes
from monoloc.sim.urban.district import build_district_scene
from monoloc.sim.urban.street_grid import StreetGrid, make_grid
from monoloc.sim.urban.street_props import add_car

SIZE_PRESETS = {"small": (2, 2), "medium": (3, 3), "large": (5, 4)}


@dataclass(frozen=True)
class CityConfig:
    """Layout and style of a city. Lengths in metres; ranges are (min, max).

    Aliasing: each district has ``building_designs`` recurring buildings; a lot starts a
    row of ``terrace_copies`` identical copies of one of them with probability
    ``repeated_building_fraction`` (see ``monoloc.sim.urban.buildings``).

    ``train_seed``: the training district drawn from its own seed (its streets,
    buildings and textures another draw than the one the city's seed gives; None: the
    city's), so a training run can see another street than any drawn with the map. The
    main district's streets and buildings stay; its parked cars, one draw over all the
    city's parking spots, are re-arranged."""

    blocks_x: int = 2
    blocks_y: int = 2
    train_blocks: tuple[int, int] = (2, 2)
    train_offset_m: tuple[float, float] = (3000.0, 0.0)
    block_length_m: tuple[float, float] = (55.0, 90.0)
    lane_width_m: float = 3.5
    parking_lane_width_m: float = 2.5
    parking_street_fraction: float = 0.6
    parking_occupancy: float = 0.55
    sidewalk_width_m: tuple[float, float] = (2.5, 4.5)
    lot_width_m: tuple[float, float] = (8.0, 26.0)
    lot_depth_m: tuple[float, float] = (10.0, 20.0)
    building_height_m: tuple[float, float] = (6.0, 26.0)
    setback_m: tuple[float, float] = (0.0, 2.0)
    deep_setback_fraction: float = 0.1
    plain_facade_fraction: float = 0.15
    shop_fraction: float = 0.45
    empty_lot_fraction: float = 0.06
    tree_street_fraction: float = 0.5
    lamp_spacing_m: tuple[float, float] = (22.0, 32.0)
    building_designs: int = 4
    repeated_building_fraction: float = 0.25
    terrace_copies: tuple[int, int] = (2, 4)
    facade_texels_per_m: float = 40.0
    ground_texels_per_m: float = 40.0
    train_seed: int | None = None

    @classmethod
    def preset(cls, size: str) -> CityConfig:
        """small (a few hundred metres of road), medium, large (a few kilometres)."""
        if size not in SIZE_PRESETS:
            raise InvalidInputError(f"unknown size {size!r}; use one of {sorted(SIZE_PRESETS)}")
        bx, by = SIZE_PRESETS[size]
        return cls(blocks_x=bx, blocks_y=by)


@dataclass(frozen=True)
class ParkingSpots:
    """Where cars may park: (N, 3) array of (x, y, yaw_rad) car centres, z-up world."""

    poses: np.ndarray


@dataclass(frozen=True)
class City:
    """The static scene of all districts, their street grids and parking spots."""

    config: CityConfig
    seed: int
    static: Scene
    grids: dict[str, StreetGrid]
    parking: ParkingSpots


def build_city(config: CityConfig, seed: int) -> City:
    """The whole city, deterministic in ``seed``: main district at the origin and the
    training district at ``config.train_offset_m``."""
    rng = np.random.default_rng([seed, 1])
    main = make_grid(config, rng, "main", (config.blocks_x, config.blocks_y), (0.0, 0.0))
    train_seed = seed if config.train_seed is None else config.train_seed
    train_rng = rng if config.train_seed is None else np.random.default_rng([train_seed, 1])
    grids = {
        "main": main,
        "train": make_grid(config, train_rng, "train", config.train_blocks, config.train_offset_m),
    }
    scenes, spots = [], []
    for k, (grid, district_seed) in enumerate(zip(grids.values(), (seed, train_seed), strict=True)):
        scene, grid_spots = build_district_scene(grid, config, district_seed * 7919 + k * 104729)
        scenes.append(scene)
        spots.append(grid_spots)
    return City(
        config=config,
        seed=seed,
        static=concat_scenes(scenes),
        grids=grids,
        parking=ParkingSpots(poses=np.concatenate(spots).reshape(-1, 3)),
    )


def parked_cars(city: City, variant: int, change_fraction: float = 0.3) -> Scene:
    """The parked cars of one run. ``variant`` 0 is the reference arrangement; another
    variant re-draws each spot with probability ``change_fraction`` (moved, removed, a
    different car, or a new one), as happens between two drives of the same street."""
    poses = city.parking.poses
    n = len(poses)
    base = np.random.default_rng([city.seed, 2])
    occupied = base.random(n) < city.config.parking_occupancy
    car_seed = base.integers(0, 2**31, size=n)
    shift = base.uniform(-0.6, 0.6, size=n)
    if variant:
        rng = np.random.default_rng([city.seed, 3, variant])
        change = rng.random(n) < change_fraction
        occupied = np.where(change, rng.random(n) < city.config.parking_occupancy, occupied)
        car_seed = np.where(change, rng.integers(0, 2**31, size=n), car_seed)
        shift = np.where(change, rng.uniform(-1.0, 1.0, size=n), shift)
    builder = SceneBuilder()
    for k in np.flatnonzero(occupied):
        x, y, yaw = poses[k]
        xy = np.array([x, y]) + shift[k] * np.array([math.cos(yaw), math.sin(yaw)])
        add_car(builder, xy, yaw, int(car_seed[k]))
    return builder.build()
