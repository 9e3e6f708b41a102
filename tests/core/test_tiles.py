"""monoloc.core.tiles: tile ids of world points, the border rule, the tile table file."""

from __future__ import annotations

import json

import pytest

from monoloc.core.errors import InputFileError, InvalidInputError
from monoloc.core.prior import RetrievalPrior
from monoloc.core.tiles import (
    ShardGroup,
    TileScheme,
    TileTable,
    read_tile_table,
    write_tile_table,
)


def test_tile_of_points_around_the_origin_and_on_borders():
    scheme = TileScheme(2000.0)
    assert scheme.tile_of(0.0, 0.0) == "0_0"
    assert scheme.tile_of(-0.01, 0.0) == "-1_0"
    assert scheme.tile_of(1999.99, -0.5) == "0_-1"
    assert scheme.tile_of(2000.0, 4000.0) == "1_2"  # a border belongs to the east/north tile
    shifted = TileScheme(100.0, origin_x_m=-35.0, origin_y_m=10.0)
    assert shifted.tile_of(-35.0, 10.0) == "0_0"
    assert shifted.tile_of(-35.1, 9.9) == "-1_-1"
    assert shifted.bounds("-1_2") == (-135.0, 210.0, -35.0, 310.0)


def test_a_disc_names_its_tile_first_and_every_neighbour_it_reaches():
    scheme = TileScheme(100.0)
    assert scheme.tiles_within(50.0, 50.0, 10.0) == ["0_0"]
    assert scheme.tiles_within(5.0, 50.0, 10.0) == ["0_0", "-1_0"]
    assert scheme.tiles_within(-5.0, 50.0, 10.0) == ["-1_0", "0_0"]
    # near a corner: the diagonal tile only when the disc reaches the corner itself
    assert set(scheme.tiles_within(3.0, 4.0, 4.9)) == {"0_0", "-1_0", "0_-1"}
    assert set(scheme.tiles_within(3.0, 4.0, 5.0)) == {"0_0", "-1_0", "0_-1", "-1_-1"}
    with pytest.raises(InvalidInputError, match="spans more than"):
        scheme.tiles_within(0.0, 0.0, 500.0)


def _table(**kw) -> TileTable:
    groups = {"west": ShardGroup("west", "http://w:1"), "east": ShardGroup("east", "http://e:1")}
    return TileTable(
        TileScheme(100.0), "city", groups, {"-1_0": "west", "0_0": "east", "1_0": "east"}, **kw
    )


def test_route_sends_a_border_frame_to_both_groups_and_a_cold_start_to_all():
    table = _table()
    assert table.route(RetrievalPrior(50.0, 50.0, 8.0)) == {"east": "0_0"}
    assert table.route(RetrievalPrior(4.0, 50.0, 8.0)) == {"east": "0_0", "west": "-1_0"}
    assert table.route(RetrievalPrior(-4.0, 50.0, 8.0)) == {"west": "-1_0", "east": "0_0"}
    # two tiles of one group: one request, naming the centre's tile
    assert table.route(RetrievalPrior(99.0, 50.0, 8.0)) == {"east": "0_0"}
    assert table.route(None) == {"east": "0_0", "west": "-1_0"}
    # outside every served tile (or too wide a disc): every group searches
    assert set(table.route(RetrievalPrior(50.0, 950.0, 8.0))) == {"east", "west"}
    assert set(table.route(RetrievalPrior(50.0, 50.0, 900.0))) == {"east", "west"}


def test_a_table_round_trips_through_its_file(tmp_path):
    table = _table(router="http://router:8080")
    table = TileTable(
        table.scheme,
        table.map_name,
        {**table.groups, "west": ShardGroup("west", None, ("10.0.0.1:8000", "10.0.0.2:8000"))},
        table.tiles,
        table.router,
    )
    path = write_tile_table(tmp_path / "tiles.json", table)
    assert read_tile_table(path) == table


@pytest.mark.parametrize(
    "data, message",
    [
        ({"map": "c", "groups": {"a": {"url": "u"}}, "tiles": {"0-0": "a"}}, "ix_iy"),
        ({"map": "c", "groups": {"a": {"url": "u"}}, "tiles": {"0_0": "b"}}, "not listed"),
        ({"map": "c", "groups": {"a": {}}, "tiles": {"0_0": "a"}}, "needs a 'url'"),
        (
            {"map": "c", "groups": {"a": {"url": "u"}, "b": {"url": "v"}}, "tiles": {"0_0": "a"}},
            "serve no tile: b",
        ),
        ({"map": "c", "groups": {"a": {"url": "u"}}, "tiles": {"0_0": "a"}, "tile": 1}, "unknown"),
        (
            {"map": "c", "tile_size_m": -2, "groups": {"a": {"url": "u"}}, "tiles": {"0_0": "a"}},
            "invalid tile scheme",
        ),
        ({"groups": {"a": {"url": "u"}}, "tiles": {"0_0": "a"}}, "names its map"),
    ],
)
def test_a_wrong_table_file_is_refused_with_its_path(tmp_path, data, message):
    path = tmp_path / "tiles.json"
    path.write_text(json.dumps(data))
    with pytest.raises(InputFileError, match=message) as caught:
        read_tile_table(path)
    assert str(caught.value).startswith(str(path))


def test_a_file_that_is_not_json_names_its_line(tmp_path):
    path = tmp_path / "tiles.json"
    path.write_text('{\n  "map": "c",\n  oops\n}')
    with pytest.raises(InputFileError, match=r"tiles.json:3: not JSON"):
        read_tile_table(path)
