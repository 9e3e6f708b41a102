"""Geographic tiles and the tile table: which shard group serves which part of a map.

A tile is a square of ``size_m`` in the map's planar world frame, aligned on
(``origin_x_m``, ``origin_y_m``); its id is ``"{ix}_{iy}"`` (column and row indices,
negative west/south of the origin), e.g. ``"-1_0"``. Operators write the tile table (a
JSON file, :func:`read_tile_table`), vehicles load it and send each frame to the group
of its prior's tile; the nginx router maps the same id (the ``X-Monoloc-Tile`` header) to
the group's upstream. The border rule: a prior names every tile its disc reaches
(:meth:`TileScheme.tiles_within`), so a frame near a border goes to both groups.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from pathlib import Path

from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.core.prior import RetrievalPrior

TILE_HEADER = "X-Monoloc-Tile"
DEFAULT_TILE_SIZE_M = 2000.0
_TILE_ID = re.compile(r"^(-?\d+)_(-?\d+)$")
_GROUP_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,62}$")
# The disc of a prior reaches at most this many tiles: a wider prior is a search of
# every group (a cold start's, or a filter long without support).
MAX_PRIOR_TILES = 16


def tile_id(ix: int, iy: int) -> str:
    return f"{ix}_{iy}"


def parse_tile_id(tile: str) -> tuple[int, int]:
    """(ix, iy) of ``"ix_iy"``; InvalidInputError otherwise."""
    match = _TILE_ID.match(tile)
    if match is None:
        raise InvalidInputError(f"a tile id is 'ix_iy' (integers, e.g. '-1_0'), got {tile!r}")
    return int(match.group(1)), int(match.group(2))


@dataclass(frozen=True)
class TileScheme:
    """Square tiles of ``size_m`` whose corner (0, 0) sits at the world point
    (``origin_x_m``, ``origin_y_m``)."""

    size_m: float = DEFAULT_TILE_SIZE_M
    origin_x_m: float = 0.0
    origin_y_m: float = 0.0

    def __post_init__(self) -> None:
        values = (self.size_m, self.origin_x_m, self.origin_y_m)
        if not all(math.isfinite(v) for v in values) or self.size_m <= 0:
            raise InvalidInputError(f"invalid tile scheme {self}")

    def indices(self, x_m: float, y_m: float) -> tuple[int, int]:
        return (
            math.floor((x_m - self.origin_x_m) / self.size_m),
            math.floor((y_m - self.origin_y_m) / self.size_m),
        )

    def tile_of(self, x_m: float, y_m: float) -> str:
        """The id of the tile holding the world point (x_m, y_m); a point on a border
        belongs to the tile east / north of it."""
        return tile_id(*self.indices(x_m, y_m))

    def bounds(self, tile: str) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) in metres of ``tile`` (half-open: max excluded)."""
        ix, iy = parse_tile_id(tile)
        x0 = self.origin_x_m + ix * self.size_m
        y0 = self.origin_y_m + iy * self.size_m
        return x0, y0, x0 + self.size_m, y0 + self.size_m

    def tiles_within(self, x_m: float, y_m: float, radius_m: float) -> list[str]:
        """Every tile the disc of ``radius_m`` around (x_m, y_m) reaches, the disc's
        centre tile first, the others nearest first. None past ``MAX_PRIOR_TILES``:
        InvalidInputError (a prior that wide is a search of the whole map)."""
        cx, cy = self.indices(x_m, y_m)
        ix0, iy0 = self.indices(x_m - radius_m, y_m - radius_m)
        ix1, iy1 = self.indices(x_m + radius_m, y_m + radius_m)
        if (ix1 - ix0 + 1) * (iy1 - iy0 + 1) > MAX_PRIOR_TILES:
            raise InvalidInputError(
                f"a prior of radius {radius_m:.0f} m spans more than {MAX_PRIOR_TILES} tiles "
                f"of {self.size_m:.0f} m"
            )
        reached: list[tuple[float, str]] = []
        for ix in range(ix0, ix1 + 1):
            for iy in range(iy0, iy1 + 1):
                x_min, y_min, x_max, y_max = self.bounds(tile_id(ix, iy))
                # distance from the centre to the square (0 inside it)
                dx = max(x_min - x_m, 0.0, x_m - x_max)
                dy = max(y_min - y_m, 0.0, y_m - y_max)
                distance = math.hypot(dx, dy)
                if (ix, iy) == (cx, cy):
                    distance = -1.0
                if distance <= radius_m:
                    reached.append((distance, tile_id(ix, iy)))
        return [tile for _, tile in sorted(reached)]


@dataclass(frozen=True)
class ShardGroup:
    """A replica group: its ``name`` (the tile table's key), the ``url`` a vehicle reaches
    it at directly (None: only through the router), and its replicas' ``host:port``
    (for the router's config; vehicles ignore them)."""

    name: str
    url: str | None = None
    replicas: tuple[str, ...] = ()


@dataclass(frozen=True)
class TileTable:
    """Which group serves which tile of map ``map_name`` (each group's database holds a
    map of that name with the entries of its tiles). ``router``: the URL of the nginx
    front that routes on the tile header; None: vehicles reach each group at its url."""

    scheme: TileScheme
    map_name: str
    groups: dict[str, ShardGroup]
    tiles: dict[str, str]  # tile id -> group name
    router: str | None = None

    def __post_init__(self) -> None:
        if not self.map_name:
            raise InvalidInputError("a tile table names its map ('map')")
        if not self.tiles:
            raise InvalidInputError("a tile table assigns at least one tile")
        for name in self.groups:
            if not _GROUP_NAME.match(name):
                raise InvalidInputError(
                    f"group name {name!r}: letters, digits, '-' and '_', at most 63"
                )
        for tile, group in self.tiles.items():
            parse_tile_id(tile)
            if group not in self.groups:
                raise InvalidInputError(f"tile {tile} names group {group!r}, which is not listed")
        unused = sorted(set(self.groups) - set(self.tiles.values()))
        if unused:
            raise InvalidInputError(f"groups serve no tile: {', '.join(unused)}")
        if self.router is None:
            missing = sorted(n for n, g in self.groups.items() if not g.url)
            if missing:
                raise InvalidInputError(
                    f"without a 'router', every group needs a 'url': {', '.join(missing)}"
                )

    def group_of(self, tile: str) -> str | None:
        """The group serving ``tile``, None for a tile outside the map."""
        return self.tiles.get(tile)

    def tiles_of(self, group: str) -> list[str]:
        return sorted(t for t, g in self.tiles.items() if g == group)

    def route(self, prior: RetrievalPrior | None) -> dict[str, str]:
        """Group name -> the tile its request names, for a frame with ``prior``: the
        groups of every served tile the prior's disc reaches (the centre's group first),
        each with its nearest tile; every group without a prior, for a prior wider than
        ``MAX_PRIOR_TILES`` tiles, or when the disc reaches no served tile."""
        if prior is not None:
            try:
                reached = self.scheme.tiles_within(prior.x_m, prior.y_m, prior.radius_m)
            except InvalidInputError:
                reached = []
            routes: dict[str, str] = {}
            for tile in reached:
                group = self.tiles.get(tile)
                if group is not None and group not in routes:
                    routes[group] = tile
            if routes:
                return routes
        return {name: self.tiles_of(name)[0] for name in sorted(self.groups)}


def tile_table_from_json(data: object, where: str = "tile table") -> TileTable:
    """A :class:`TileTable` from the parsed JSON of :func:`read_tile_table`."""
    if not isinstance(data, dict):
        raise InvalidInputError(f"{where}: a JSON object is expected")
    unknown = sorted(set(data) - {"tile_size_m", "origin_m", "map", "router", "groups", "tiles"})
    if unknown:
        raise InvalidInputError(f"{where}: unknown keys {', '.join(unknown)}")
    try:
        origin = data.get("origin_m", [0.0, 0.0])
        if not (isinstance(origin, list) and len(origin) == 2):
            raise InvalidInputError("'origin_m' is [x, y] in metres")
        scheme = TileScheme(
            float(data.get("tile_size_m", DEFAULT_TILE_SIZE_M)), float(origin[0]), float(origin[1])
        )
        groups_json = data.get("groups")
        tiles = data.get("tiles")
        if not isinstance(groups_json, dict) or not isinstance(tiles, dict):
            raise InvalidInputError("'groups' and 'tiles' are JSON objects")
        groups = {}
        for name, spec in groups_json.items():
            if not isinstance(spec, dict):
                raise InvalidInputError(f"group {name!r}: an object with 'url' and/or 'replicas'")
            replicas = spec.get("replicas", [])
            if not isinstance(replicas, list) or not all(isinstance(r, str) for r in replicas):
                raise InvalidInputError(f"group {name!r}: 'replicas' is a list of 'host:port'")
            url = spec.get("url")
            groups[str(name)] = ShardGroup(
                str(name), str(url).rstrip("/") if url else None, tuple(replicas)
            )
        router = data.get("router")
        return TileTable(
            scheme,
            str(data.get("map") or ""),
            groups,
            {str(t): str(g) for t, g in tiles.items()},
            str(router).rstrip("/") if router else None,
        )
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{where}: {exc}") from exc
    except InvalidInputError as exc:
        raise InvalidInputError(f"{where}: {exc}") from exc


def tile_table_to_json(table: TileTable) -> dict:
    groups = {}
    for name, group in table.groups.items():
        spec: dict = {}
        if group.url:
            spec["url"] = group.url
        if group.replicas:
            spec["replicas"] = list(group.replicas)
        groups[name] = spec
    data: dict = {
        "map": table.map_name,
        "tile_size_m": table.scheme.size_m,
        "origin_m": [table.scheme.origin_x_m, table.scheme.origin_y_m],
    }
    if table.router:
        data["router"] = table.router
    data.update(groups=groups, tiles=dict(sorted(table.tiles.items())))
    return data


def read_tile_table(path: Path | str) -> TileTable:
    """The tile table of a JSON file::

        {"map": "city", "tile_size_m": 2000, "origin_m": [0, 0],
         "router": "http://shards.example:8080",
         "groups": {"west": {"url": "...", "replicas": ["10.0.0.1:8000", ...]}, ...},
         "tiles": {"-1_0": "west", "0_0": "east"}}

    InputFileError (the path first) for a missing or malformed file."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise InputFileError(path, f"cannot read the tile table: {exc.strerror or exc}") from exc
    except json.JSONDecodeError as exc:
        raise InputFileError(path, f"not JSON: {exc.msg}", exc.lineno) from exc
    try:
        return tile_table_from_json(data, "tile table")
    except InvalidInputError as exc:
        raise InputFileError(path, str(exc).removeprefix("tile table: ")) from exc


def write_tile_table(path: Path | str, table: TileTable) -> Path:
    path = Path(path)
    path.write_text(json.dumps(tile_table_to_json(table), indent=2) + "\n")
    return path
