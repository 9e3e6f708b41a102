"""A map served by shard groups: the vehicle holds the tile table and sends each frame to
the group of its prior's tile (monoloc.core.tiles).

:class:`ShardedLocalizer` is a Localizer like ``HttpLocalizer``: one HTTP request per
frame and group, with the ``X-Monoloc-Tile`` header naming the frame's tile, to the
router (nginx ``map`` on that header, docker/nginx-shards.conf) or straight to the
group's URL. A frame whose prior reaches a neighbour tile of another group goes to both
groups at once and their hypotheses are merged into one answer (each raw hypothesis keeps
its ``shard``), so the one filter of the drive carries on across tiles. A group that
sheds the frame, or fails, leaves the answer to the others; a frame no group answered is
a prediction-only step.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import httpx

from monoloc.client.api import LocalizeAnswer, MonolocClient, ServerError
from monoloc.client.localizer import HttpLocalizer
from monoloc.core.camera import CameraIntrinsics
from monoloc.core.errors import MonolocError
from monoloc.core.geo import GeoReference
from monoloc.core.measurement import Hypotheses, MeasurementModel
from monoloc.core.prior import RetrievalPrior
from monoloc.core.tiles import TILE_HEADER, TileTable


class _TileHeader(httpx.BaseTransport):
    """An HTTP transport that names ``tile`` in every request's tile header (one group's
    client: its requests go one at a time)."""

    def __init__(self, tile: str) -> None:
        self.tile = tile
        self._inner = httpx.HTTPTransport()

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        request.headers[TILE_HEADER] = self.tile
        return self._inner.handle_request(request)

    def close(self) -> None:
        self._inner.close()


class _Group:
    """One shard group as the vehicle sees it: its client, the tile header of its
    requests, and the localizer of its copy of the map. ``failed``: frames it could not
    answer (transport error, a 5xx other than a shed 503)."""

    def __init__(
        self, name: str, client: MonolocClient, transport: _TileHeader, localizer: HttpLocalizer
    ) -> None:
        self.name, self.client, self.transport, self.localizer = name, client, transport, localizer
        self.failed = 0
        self.last_error: str | None = None

    def localize(
        self, tile: str, image: bytes, prior: RetrievalPrior | None, k: int | None
    ) -> LocalizeAnswer:
        self.transport.tile = tile
        try:
            return self.localizer.localize(image, prior, k)
        except ServerError as exc:
            self.failed += 1
            self.last_error = f"{self.name}: {exc}"
            return LocalizeAnswer(Hypotheses.empty(), None, {}, {}, error=self.last_error)


class ShardedLocalizer:
    """Answers a frame from the groups its prior's tiles name (``TileTable.route``).

    ``groups``: connected groups (:meth:`connect` makes them). ``counts[group]`` keeps
    each group's tally; ``routes`` counts the frames sent to one group and to several."""

    def __init__(self, table: TileTable, groups: dict[str, _Group]) -> None:
        self.table = table
        self.groups = groups
        self.routes = {"one_group": 0, "several_groups": 0}
        self._pool = ThreadPoolExecutor(max_workers=max(1, len(groups)))

    @classmethod
    def connect(
        cls,
        table: TileTable,
        api_key: str,
        intrinsics: CameraIntrinsics,
        *,
        timeout_s: float = 10.0,
        deadline_ms: int | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> ShardedLocalizer:
        """Clients of every group of ``table`` (through its router, or at each group's
        URL), the id of the table's map in each group's database (found by name) and the
        camera registered with each (``MonolocClient.camera_id``)."""
        groups: dict[str, _Group] = {}
        try:
            for name, group in sorted(table.groups.items()):
                transport = _TileHeader(table.tiles_of(name)[0])
                url = table.router or group.url or ""  # TileTable checks one is set
                client = MonolocClient(url, api_key, timeout_s=timeout_s, transport=transport)
                try:
                    map_id = client.find_map_id(table.map_name)
                    camera_id = client.camera_id(intrinsics)
                except MonolocError as exc:
                    client.close()
                    raise type(exc)(f"shard group {name} ({url}): {exc}") from exc
                localizer = HttpLocalizer(
                    client, map_id, deadline_ms=deadline_ms, clock=clock, camera_id=camera_id
                )
                groups[name] = _Group(name, client, transport, localizer)
        except BaseException:
            for made in groups.values():
                made.client.close()
            raise
        return cls(table, groups)

    @property
    def last_errors(self) -> dict[str, str]:
        """Per group that failed a frame: its last failure."""
        return {n: g.last_error for n, g in self.groups.items() if g.last_error is not None}

    @property
    def counts(self) -> dict[str, dict[str, int]]:
        """Per group: frames sent, answered, shed, held (``ShedCounts``) and failed."""
        return {
            name: {**dataclasses.asdict(group.localizer.counts), "failed": group.failed}
            for name, group in self.groups.items()
        }

    def first_group(self) -> _Group:
        return self.groups[sorted(self.groups)[0]]

    def measurement_model(self) -> tuple[MeasurementModel, bool]:
        """The measurement model of the map in the first group (the groups' maps are
        calibrated alike: one map, split by tile), and whether it was calibrated."""
        group = self.first_group()
        return group.client.measurement_model(group.localizer.map_id)

    def geo_reference(self) -> GeoReference | None:
        group = self.first_group()
        return group.client.geo_reference(group.localizer.map_id)

    def localize(
        self, image: bytes, prior: RetrievalPrior | None = None, k: int | None = None
    ) -> LocalizeAnswer:
        routes = self.table.route(prior)
        if len(routes) == 1:
            self.routes["one_group"] += 1
            [(name, tile)] = routes.items()
            answers = {name: self.groups[name].localize(tile, image, prior, k)}
        else:
            self.routes["several_groups"] += 1
            futures = {
                name: self._pool.submit(self.groups[name].localize, tile, image, prior, k)
                for name, tile in routes.items()
            }
            answers = {name: future.result() for name, future in futures.items()}
        return merge_answers(answers, routes)

    def close(self) -> None:
        self._pool.shutdown(wait=True)
        for group in self.groups.values():
            group.client.close()

    def __enter__(self) -> ShardedLocalizer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def merge_answers(answers: dict[str, LocalizeAnswer], tiles: dict[str, str]) -> LocalizeAnswer:
    """One answer out of the groups' answers to one frame: the hypotheses of every group
    that answered, in the groups' order, each raw hypothesis with its ``shard``; the raw
    answer's ``shards`` gives each group's tile, map version, count and timings. No group
    answered: an error answer when one failed, else a dropped one."""
    answered = {n: a for n, a in answers.items() if not a.dropped and a.error is None}
    if not answered:
        errors = [a.error for a in answers.values() if a.error is not None]
        if errors:
            return LocalizeAnswer(Hypotheses.empty(), None, {}, {}, error="; ".join(errors))
        return LocalizeAnswer(
            Hypotheses.empty(), None, {}, {"dropped": True, "reason": "shed"}, dropped=True
        )
    hypotheses: list[dict] = []
    shards: dict[str, dict] = {}
    for name, answer in answered.items():
        own = answer.raw.get("hypotheses") or []
        hypotheses.extend({**h, "shard": name} for h in own)
        shards[name] = {
            "tile": tiles[name],
            "map_version": answer.map_version,
            "n_hypotheses": len(own),
            "timings_ms": answer.timings_ms,
        }
    first = next(iter(answered.values()))
    return LocalizeAnswer.from_json(
        {
            "hypotheses": hypotheses,
            "map_version": first.map_version if len(answered) == 1 else None,
            "timings_ms": first.timings_ms,
            "shards": shards,
        }
    )
