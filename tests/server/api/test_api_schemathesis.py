"""Schemathesis over the whole OpenAPI description, against the app with its lifespan
(a real SQLite file): no 5xx, every status documented, every body and content type as
described (issue 15, "keep it closed"; issue 50, 6).

Every operation runs on a fresh copy of one prepared data directory (``world``): a map
with entries made through the API, a run and its done ingestion job, a calibration with
a night condition, a geographic reference, a registered camera and a spare key. So no
operation can lock the fuzzer out or starve a later one (a deleted map, a revoked key).
Each operation gets its known-good request first (the objects that exist, a real image,
a real KITTI archive), then generated ones, half of them with the path's ids of objects
that exist; every operation must have answered at least one of them 2xx, its body
checked against its schema. Schemathesis's state machine follows the description's
OpenAPI links (server/api/openapi_links.py), one family at a time on its own fresh
copy (maps: a map listed or created, then read, calibrated, geo-referenced; entries: a
map's entries listed, then one read, re-tagged, its image fetched; keys: a key created,
then revoked; jobs; cameras), and must follow each family's links to a 2xx answer.
``make bench`` runs the slow variant with 200 examples per operation.

Requests carry the admin key (authorization has its own matrix test); the last active
admin key cannot be revoked (409), which the world's fixture checks.
"""

from __future__ import annotations

import io
import shutil
import tarfile
import tempfile
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import schemathesis
from api_helpers import ADMIN_KEY, CALIBRATION, camera_of, create_keys, make_settings, wait_job
from api_helpers import open_client as open_test_client
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from schemathesis import checks
from schemathesis.specs.openapi import checks as openapi_checks

CHECKS = [
    checks.not_a_server_error,
    openapi_checks.status_code_conformance,
    openapi_checks.content_type_conformance,
    openapi_checks.response_schema_conformance,
]
HEADERS = {"X-API-Key": ADMIN_KEY}
CAMERA = camera_of(None)
N_ENTRIES = 3
RUN_FRAMES = 6


def _spec() -> dict:
    from monoloc.server.api.app import create_app
    from monoloc.server.settings import Settings

    return create_app(Settings(data_dir="unused")).openapi()  # no lifespan: nothing written


OPERATIONS = [f"{m.upper()} {p}" for p, ops in _spec()["paths"].items() for m in ops]


# ---- the world every operation starts from -------------------------------------------


def _textured(rng: np.random.Generator) -> np.ndarray:
    """A grey image full of corners: coarse blobs plus fine noise."""
    h, w = CAMERA["height_px"], CAMERA["width_px"]
    coarse = cv2.resize(rng.uniform(0, 255, (h // 8, w // 8)), (w, h), cv2.INTER_NEAREST)
    return np.clip(0.7 * coarse + rng.uniform(0, 76, (h, w)), 0, 255).astype(np.uint8)


def _png(image: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".png", image)
    assert ok
    return data.tobytes()


def _T_world_from_cam(x_m: float) -> np.ndarray:
    """Camera at (x_m, 0, 1.65) looking along +X of the z-up world."""
    T = np.eye(4)
    T[:3, :3] = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]
    T[:3, 3] = [x_m, 0.0, 1.65]
    return T


def _kitti_archive(rng: np.random.Generator, n_frames: int) -> bytes:
    """A tar.gz of a KITTI odometry sequence 00 (images, LiDAR scans of a wall 10 m
    ahead, calib.txt, times, poses) written with monoloc's own KITTI writers."""
    from monoloc.core.formats import kitti

    K = np.array([[CAMERA["fx"], 0, CAMERA["cx"]], [0, CAMERA["fy"], CAMERA["cy"]], [0, 0, 1]])
    T_cam0_from_lidar = np.eye(4)
    T_cam0_from_lidar[:3, :3] = [[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]
    ys, zs = np.meshgrid(np.linspace(-8, 8, 160), np.linspace(-1.5, 2.5, 40))
    wall = np.stack([np.full(ys.size, 10.0), ys.ravel(), zs.ravel(), np.ones(ys.size)], 1)
    poses = np.tile(np.eye(4), (n_frames, 1, 1))
    poses[:, 2, 3] = 0.5 * np.arange(n_frames)  # KITTI's camera frame: z forward
    with tempfile.TemporaryDirectory() as tmp:
        folder = kitti.sequence_dir(tmp, "00")
        (folder / "image_0").mkdir(parents=True)
        (folder / "velodyne").mkdir()
        with open(folder / "calib.txt", "w") as handle:
            kitti.write_calib(handle, kitti.KittiCalib.from_camera(K, T_cam0_from_lidar))
        with open(folder / "times.txt", "w") as handle:
            kitti.write_times(handle, 0.1 * np.arange(n_frames))
        kitti.poses_path(tmp, "00").parent.mkdir()
        with open(kitti.poses_path(tmp, "00"), "w") as handle:
            kitti.write_poses(handle, poses)
        for i in range(n_frames):
            name = kitti.image_name(i)
            (folder / "image_0" / f"{name}.png").write_bytes(_png(_textured(rng)))
            kitti.write_scan(folder / "velodyne" / f"{name}.bin", wall)
        buffer = io.BytesIO()
        with tarfile.open(fileobj=buffer, mode="w:gz", compresslevel=1) as tar:
            tar.add(tmp, arcname="kitti")
    return buffer.getvalue()


@dataclass(frozen=True)
class World:
    data_dir: Path
    map_id: int
    entry_ids: tuple[int, ...]
    run_id: int
    job_id: int
    interrupted_job_id: int
    spare_key_id: int
    camera_id: int
    entry_image: bytes
    entry_depth: bytes
    archive: bytes

    def ids(self) -> dict[str, Any]:
        """An existing object for each path parameter name."""
        return {
            "map_id": self.map_id,
            "entry_id": self.entry_ids[-1],
            "run_id": self.run_id,
            "job_id": self.job_id,
            "key_id": self.spare_key_id,
            "camera_id": self.camera_id,
            "name": "night",
        }


def _entry_form(image: bytes, depth: bytes, x_m: float) -> dict[str, Any]:
    """An entry's form: the image, a depth image 10 m everywhere, the pose at x_m."""
    return {
        "image": image,
        "depth": depth,
        "depth_scale": 1000.0,
        "T_world_from_cam": ",".join(str(v) for v in _T_world_from_cam(x_m).ravel()),
        "tags": "day",
    }


def _interrupted_job(data_dir: Path, map_id: int, vocabulary_id: int) -> int:
    """A vocabulary job left interrupted, as a server stopped in its middle leaves it."""
    from monoloc.server.jobs import store as jobs_repo
    from monoloc.server.jobs.vocabulary import JOB_KIND, VocabularyParams
    from monoloc.server.storage.db import create_engine_for, make_session_factory, session_scope

    params = VocabularyParams.create(vocabulary="default", vocabulary_id=vocabulary_id)
    engine = create_engine_for(make_settings(data_dir))
    with session_scope(make_session_factory(engine)) as session:
        job = jobs_repo.create_job(
            session, JOB_KIND, map_id=map_id, params=params.model_dump(mode="json")
        )
        jobs_repo.update_job(session, job.id, state="interrupted", message="server stopped")
    engine.dispose()
    return job.id


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> World:
    rng = np.random.default_rng(50)
    data_dir = tmp_path_factory.mktemp("schemathesis-world") / "data"
    admin = {"X-API-Key": ADMIN_KEY}
    depth = _png(np.full((CAMERA["height_px"], CAMERA["width_px"]), 10_000, np.uint16))
    archive = _kitti_archive(rng, RUN_FRAMES)
    with open_test_client(make_settings(data_dir)) as client:
        create_keys(client)
        spare = client.post(
            "/v1/keys", json={"name": "spare", "scopes": ["localize"]}, headers=admin
        )
        made = client.post("/v1/maps", json={"name": "street", "camera": CAMERA}, headers=admin)
        assert made.status_code == 201, made.text
        map_id = made.json()["id"]
        images, entry_ids = [], []
        for i in range(N_ENTRIES):
            images.append(_png(_textured(rng)))
            form = _entry_form(images[-1], depth, 0.5 * i)
            files = {k: (f"{k}.png", form.pop(k)) for k in ("image", "depth")}
            added = client.post(f"/v1/maps/{map_id}/entries", data=form, files=files, headers=admin)
            assert added.status_code == 201, added.text
            entry_ids.append(added.json()["entry"]["id"])
        upload = client.post(
            f"/v1/maps/{map_id}/runs",
            data={"format": "kitti"},
            files={"archive": ("run.tar.gz", archive, "application/gzip")},
            headers=admin,
        )
        assert upload.status_code == 202, upload.text
        job = wait_job(client, upload.json()["job"]["id"], admin)
        assert job["state"] == "done", job
        night = {k: v for k, v in CALIBRATION.items() if k != "provenance"}
        calibration = {**CALIBRATION, "conditions": {"night": night}}
        put = client.put(f"/v1/maps/{map_id}/calibration", json=calibration, headers=admin)
        assert put.status_code == 200, put.text
        origin = {"lat_deg": 48.85837, "lon_deg": 2.294481, "x_axis_heading_deg": 90.0}
        geo = client.put(f"/v1/maps/{map_id}/geo-reference", json={"origin": origin}, headers=admin)
        assert geo.status_code == 200, geo.text
        camera = client.post("/v1/cameras", json={"name": "front", **CAMERA}, headers=admin)
        assert camera.status_code == 201, camera.text
        # the fuzzer may revoke any key, its own too: the last active admin key stays
        assert client.delete("/v1/keys/1", headers=admin).status_code == 409
    interrupted = _interrupted_job(data_dir, map_id, made.json()["vocabulary"]["id"])
    return World(
        data_dir=data_dir,
        map_id=map_id,
        entry_ids=tuple(entry_ids),
        run_id=upload.json()["run"]["id"],
        job_id=job["id"],
        interrupted_job_id=interrupted,
        spare_key_id=spare.json()["id"],
        camera_id=camera.json()["id"],
        entry_image=images[0],
        entry_depth=depth,
        archive=archive,
    )


@pytest.fixture(scope="module")
def fuzzed_app(world, tmp_path_factory) -> Iterator[tuple[Any, Path]]:
    """One app and its schemathesis schema, over a data directory that each test gets
    afresh (``fresh_world``). Schemathesis starts the app's lifespan at its first call
    and keeps it until ``shutdown_lifespans``; the description is built once."""
    from schemathesis.python import asgi

    from monoloc.server.api.app import create_app

    data_dir = tmp_path_factory.mktemp("schemathesis-fuzzed") / "data"
    shutil.copytree(world.data_dir, data_dir)
    app = create_app(make_settings(data_dir))
    try:
        yield schemathesis.openapi.from_asgi("/openapi.json", app), data_dir
    finally:
        asgi.shutdown_lifespans()


@pytest.fixture
def fresh_world(world, fuzzed_app) -> tuple[Any, World]:
    """The app stopped, its data replaced by a copy of the world's: the next call starts
    it on the world as prepared, whatever the previous test did to it."""
    from schemathesis.python import asgi

    schema, data_dir = fuzzed_app
    asgi.shutdown_lifespans()
    shutil.rmtree(data_dir)
    shutil.copytree(world.data_dir, data_dir)
    return schema, world


def _call(schema, label: str, **values: Any):
    method, path = label.split(" ", 1)
    return schema[path][method].Case(**values).call(headers=HEADERS)


# ---- one known-good request per operation ---------------------------------------------

# (schema, world) -> the Case's values (path_parameters, query, body, media_type); it may
# make what the request needs first (a running job to cancel)
Prepare = Callable[[Any, World], dict[str, Any]]


def _running_job(schema, world: World) -> int:
    """A new ingestion job, queued or running."""
    upload = _call(
        schema,
        "POST /v1/maps/{map_id}/runs",
        path_parameters={"map_id": world.map_id},
        body={"format": "kitti", "archive": world.archive},
        media_type="multipart/form-data",
    )
    assert upload.status_code == 202, upload.text
    return upload.json()["job"]["id"]


def _good_cases() -> dict[str, Prepare]:
    m, e = "/v1/maps/{map_id}", "/v1/maps/{map_id}/entries/{entry_id}"
    ids: Prepare = lambda c, w: {"path_parameters": w.ids()}  # noqa: E731

    def with_body(body: Any, media: str = "application/json") -> Prepare:
        return lambda c, w: {"path_parameters": w.ids(), "body": body, "media_type": media}

    return {
        "GET /v1/maps": ids,
        "POST /v1/maps": with_body({"name": "second", "camera": CAMERA}),
        f"GET {m}": ids,
        f"DELETE {m}": ids,
        f"POST {m}/vocabulary/jobs": with_body({"vocabulary": "default"}),
        f"GET {m}/replica": ids,
        f"POST {m}/runs": lambda c, w: {
            "path_parameters": w.ids(),
            "body": {"format": "kitti", "archive": w.archive},
            "media_type": "multipart/form-data",
        },
        f"GET {m}/runs": ids,
        f"GET {m}/runs/{{run_id}}": ids,
        "GET /v1/jobs": ids,
        "GET /v1/jobs/{job_id}": ids,
        "POST /v1/jobs/{job_id}/resume": lambda c, w: {
            "path_parameters": {"job_id": w.interrupted_job_id}
        },
        "POST /v1/jobs/{job_id}/cancel": lambda c, w: {
            "path_parameters": {"job_id": _running_job(c, w)}
        },
        f"POST {m}/entries": lambda c, w: {
            "path_parameters": w.ids(),
            "body": _entry_form(_png(_textured(np.random.default_rng(7))), w.entry_depth, 3.0),
            "media_type": "multipart/form-data",
        },
        f"GET {m}/entries": ids,
        f"GET {e}": ids,
        f"DELETE {e}": ids,
        f"PATCH {e}": with_body({"tags": ["night", "off-center"]}),
        f"POST {m}/localize": lambda c, w: {
            "path_parameters": w.ids(),
            "body": {"image": w.entry_image, "k": 3, "seed": 1},
            "media_type": "multipart/form-data",
        },
        f"GET {m}/calibration": ids,
        f"PUT {m}/calibration": with_body(CALIBRATION),
        f"DELETE {m}/calibration": ids,
        f"DELETE {m}/calibration/conditions/{{name}}": ids,
        f"POST {m}/calibration/jobs": lambda c, w: {
            "path_parameters": w.ids(),
            "body": {"format": "kitti", "archive": w.archive, "k": 2},
            "media_type": "multipart/form-data",
        },
        f"GET {m}/geo-reference": ids,
        f"PUT {m}/geo-reference": with_body(
            {"origin": {"lat_deg": 1.0, "lon_deg": 2.0, "x_axis_heading_deg": 0.0}}
        ),
        f"DELETE {m}/geo-reference": ids,
        "POST /v1/keys": with_body({"name": "car", "scopes": ["localize"], "maps": [1]}),
        "GET /v1/keys": ids,
        "GET /v1/keys/me": ids,
        "DELETE /v1/keys/{key_id}": ids,
        "POST /v1/cameras": with_body({"name": "rear", **CAMERA}),
        "GET /v1/cameras": ids,
        "GET /v1/cameras/{camera_id}": ids,
        "DELETE /v1/cameras/{camera_id}": ids,
        "GET /healthz": ids,
        "GET /readyz": ids,
        "GET /metrics": ids,
        f"GET {m}/poses": ids,
        f"GET {m}/coverage": lambda c, w: {"path_parameters": w.ids(), "query": {"radius_m": 1.0}},
        f"GET {e}/keypoints": ids,
        f"GET {e}/image": ids,
        f"GET {m}/vehicles": ids,
    }


GOOD_CASES = _good_cases()


def test_every_operation_has_a_known_good_request():
    assert sorted(set(OPERATIONS) - set(GOOD_CASES)) == []
    assert sorted(set(GOOD_CASES) - set(OPERATIONS)) == []


def _known_good(schema, world: World, label: str) -> Any:
    method, path = label.split(" ", 1)
    operation = schema[path][method]
    values = GOOD_CASES[label](schema, world)
    params = {p.name for p in operation.path_parameters}
    values["path_parameters"] = {
        k: v for k, v in (values.get("path_parameters") or {}).items() if k in params
    }
    return operation.Case(**values)


def _fuzz(schema, world: World, label: str, max_examples: int) -> Counter:
    """The operation's known-good request, then ``max_examples`` generated ones; the
    statuses they were answered with."""
    method, path = label.split(" ", 1)
    operation = schema[path][method]
    statuses: Counter = Counter()
    case = _known_good(schema, world, label)
    response = case.call(headers=HEADERS)
    statuses[response.status_code] += 1
    case.validate_response(response, checks=CHECKS)
    assert 200 <= response.status_code < 300, (label, response.status_code, response.text)

    existing = {p.name: world.ids()[p.name] for p in operation.path_parameters}
    strategy = st.one_of(
        operation.as_strategy(), operation.as_strategy(path_parameters=existing or None)
    )

    @given(case=strategy)
    @settings(
        max_examples=max_examples,
        deadline=None,
        database=None,
        derandomize=True,
        phases=[Phase.explicit, Phase.generate],
        suppress_health_check=list(HealthCheck),
    )
    def run(case) -> None:
        answer = case.call(headers=HEADERS)
        statuses[answer.status_code] += 1
        case.validate_response(answer, checks=CHECKS)

    run()
    return statuses


@pytest.mark.parametrize("label", OPERATIONS)
def test_operation_conforms(fresh_world, label):
    schema, world = fresh_world
    statuses = _fuzz(schema, world, label, max_examples=4)
    assert any(200 <= s < 300 for s in statuses), (label, statuses)


@pytest.mark.slow
@pytest.mark.parametrize("label", OPERATIONS)
def test_operation_conforms_thoroughly(fresh_world, label):
    schema, world = fresh_world
    statuses = _fuzz(schema, world, label, max_examples=200)
    assert any(200 <= s < 300 for s in statuses), (label, statuses)


# ---- the state machine, along the description's links ---------------------------------

_MAPS_TARGETS = {
    "GET /v1/maps/{map_id}",
    "GET /v1/maps/{map_id}/calibration",
    "PUT /v1/maps/{map_id}/calibration",
    "GET /v1/maps/{map_id}/geo-reference",
    "PUT /v1/maps/{map_id}/geo-reference",
    "GET /v1/maps/{map_id}/runs",
}
_ENTRY = "/v1/maps/{map_id}/entries/{entry_id}"
# Family: (the operations its machine runs, the sources one of whose links it must
# follow to a 2xx answer). Uploads and frames are left out: their links are in the
# description, but generated bodies are never valid archives or images.
FAMILIES: dict[str, tuple[set[str], set[str]]] = {
    "maps": ({"POST /v1/maps", "GET /v1/maps"} | _MAPS_TARGETS, {"POST /v1/maps", "GET /v1/maps"}),
    "entries": (
        {
            "GET /v1/maps",
            "GET /v1/maps/{map_id}/entries",
            f"GET {_ENTRY}",
            f"PATCH {_ENTRY}",
            f"GET {_ENTRY}/image",
        },
        {"GET /v1/maps/{map_id}/entries"},
    ),
    "keys": ({"POST /v1/keys", "GET /v1/keys", "DELETE /v1/keys/{key_id}"}, {"POST /v1/keys"}),
    "jobs": (
        {"GET /v1/jobs", "GET /v1/jobs/{job_id}"},
        {"GET /v1/jobs"},
    ),
    "cameras": (
        {"POST /v1/cameras", "GET /v1/cameras", "GET /v1/cameras/{camera_id}"},
        {"POST /v1/cameras", "GET /v1/cameras"},
    ),
}


def _state_machine_run(
    schema,
    labels: set[str],
    spare_key_id: int,
    max_examples: int,
    steps: int,
) -> set:
    """The (source, target) pairs of the description's links that a state machine over
    ``labels`` followed to a 2xx answer (every answer checked as in the fuzzing)."""
    followed: set[tuple[str, str]] = set()

    class Machine(schema.include(name=sorted(labels)).as_state_machine()):  # type: ignore[misc]
        def get_call_kwargs(self, case) -> dict[str, Any]:
            return {"headers": HEADERS}

        def before_call(self, case) -> None:
            # Once the machine made another admin key, the last-admin rule lets its own key
            # (id 1, first in GET /v1/keys) be revoked: it revokes the spare key instead.
            if case.operation.label == "DELETE /v1/keys/{key_id}":
                if case.path_parameters.get("key_id") == 1:
                    case.path_parameters["key_id"] = spare_key_id

        def validate_response(self, response, case, additional_checks=None, **kwargs) -> None:
            case.validate_response(response, checks=CHECKS)

        def step(self, input):
            output = super().step(input)
            link, status = input.transition, output.response.status_code
            if link is not None and not link.is_inferred and input.is_applied:
                if 200 <= status < 300:  # its id: "SOURCE -> [status] name -> TARGET"
                    followed.add((link.id.split(" -> [", 1)[0], input.case.operation.label))
            return output

    Machine.run(
        settings=settings(
            max_examples=max_examples,
            stateful_step_count=steps,
            deadline=None,
            database=None,
            derandomize=True,
            suppress_health_check=list(HealthCheck),
        )
    )
    return followed


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_state_machine_follows_the_links(fresh_world, family):
    schema, world = fresh_world
    labels, sources = FAMILIES[family]
    examples = 16 if family == "entries" else 8  # its links need a list that is not empty
    followed = _state_machine_run(schema, labels, world.spare_key_id, examples, steps=6)
    assert {source for source, _ in followed} & sources, sorted(followed)
