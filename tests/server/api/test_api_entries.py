"""Operator routes on entries: an added entry answers the very next query, a deleted one
is gone from the next; the same image twice is stored once; list filters, get, re-tag;
a depth-PNG entry works like a LiDAR one."""

from __future__ import annotations

import json

import numpy as np
from api_helpers import frame_png, ground_truth

from monoloc.client.api import LocalizeAnswer

QUERY = 12


def _lidar_extrinsics(dataset) -> list[float]:
    for line in (dataset / "sequences" / "01" / "calib.txt").read_text().splitlines():
        if line.startswith("Tr:"):
            return [float(v) for v in line.split()[1:]] + [0.0, 0.0, 0.0, 1.0]
    raise AssertionError("no Tr line")


def _localize(client, m, image):
    r = client.post(
        f"/v1/maps/{m.map_id}/localize",
        headers=m.keys.header("localize"),
        files={"image": ("q.png", image, "image/png")},
        data={"seed": "3"},
    )
    assert r.status_code == 200, r.text
    return r.json()


def _add_lidar_entry(client, m, dataset, frame, tags):
    seq = dataset / "sequences" / "01"
    return client.post(
        f"/v1/maps/{m.map_id}/entries",
        headers=m.keys.header("write"),
        files={
            "image": ("q.png", frame_png(dataset, "01", frame), "image/png"),
            "lidar": (
                "s.bin",
                (seq / "velodyne" / f"{frame:06d}.bin").read_bytes(),
                "application/octet-stream",
            ),
        },
        data={
            "T_world_from_cam": json.dumps(ground_truth(dataset, "01", frame).ravel().tolist()),
            "T_cam_from_lidar": ",".join(map(repr, _lidar_extrinsics(dataset))),
            "tags": tags,
            "timestamp_s": "1.2",
        },
    )


def test_added_entry_answers_the_next_query_and_deleted_one_is_gone(
    sim_dataset, map_copy, client_on_copy
):
    client, m = client_on_copy, map_copy
    image = frame_png(sim_dataset, "01", QUERY)
    before = _localize(client, m, image)

    r = _add_lidar_entry(client, m, sim_dataset, QUERY, "Night")
    assert r.status_code == 201, r.text
    added = r.json()
    entry_id = added["entry"]["id"]
    assert added["created"] and added["map_version"] == before["map_version"] + 1
    assert added["entry"]["tags"] == ["night"] and added["entry"]["n_points"] >= 20
    assert np.allclose(
        added["entry"]["T_world_from_cam"], ground_truth(sim_dataset, "01", QUERY).ravel()
    )

    after_add = _localize(client, m, image)
    assert after_add["map_version"] == added["map_version"]
    assert after_add["retrieved"][0]["entry_id"] == entry_id  # the very image: closest VLAD
    best = after_add["hypotheses"][0]
    assert best["entry_id"] == entry_id
    # each hypothesis names its entry's tags (a condition's calibration weighs it), and the
    # vehicle's library reads them
    assert best["entry_tags"] == ["night"]
    assert all(h["entry_tags"] == [] for h in after_add["hypotheses"] if h["entry_id"] != entry_id)
    parsed = LocalizeAnswer.from_json(after_add).hypotheses
    assert parsed.entry_tags[0] == ("night",) and len(parsed.entry_tags) == len(parsed)
    assert parsed.method == tuple(h["method"] for h in after_add["hypotheses"])
    truth = ground_truth(sim_dataset, "01", QUERY)
    assert np.hypot(best["pose"]["x_m"] - truth[0, 3], best["pose"]["y_m"] - truth[1, 3]) < 0.05

    again = _add_lidar_entry(client, m, sim_dataset, QUERY, "night")
    assert again.status_code == 200 and not again.json()["created"]
    assert again.json()["entry"]["id"] == entry_id

    assert (
        client.delete(
            f"/v1/maps/{m.map_id}/entries/{entry_id}", headers=m.keys.header("write")
        ).status_code
        == 204
    )
    after_delete = _localize(client, m, image)
    assert entry_id not in [e["entry_id"] for e in after_delete["retrieved"]]
    assert after_delete["retrieved"] == before["retrieved"]
    assert after_delete["hypotheses"] == before["hypotheses"]
    assert (
        client.delete(
            f"/v1/maps/{m.map_id}/entries/{entry_id}", headers=m.keys.header("write")
        ).status_code
        == 404
    )


def test_list_filters_get_and_retag(sim_dataset, map_copy, client_on_copy):
    client, m = client_on_copy, map_copy
    h = m.keys.header("write")
    url = f"/v1/maps/{m.map_id}/entries"
    entry_id = _add_lidar_entry(client, m, sim_dataset, 3, "night,off-center").json()["entry"]["id"]
    n_run = m.job["result"]["entries_added"]

    everything = client.get(url, headers=h, params={"limit": 1000}).json()
    assert everything["total"] == n_run + 1 == len(everything["items"])
    page = client.get(url, headers=h, params={"limit": 5, "offset": 5}).json()
    assert [e["id"] for e in page["items"]] == [e["id"] for e in everything["items"][5:10]]
    assert [
        e["id"] for e in client.get(url, headers=h, params={"tag": "night"}).json()["items"]
    ] == [entry_id]
    in_run = client.get(url, headers=h, params={"run_id": 1}).json()
    assert in_run["total"] == n_run and entry_id not in [e["id"] for e in in_run["items"]]
    truth = ground_truth(sim_dataset, "01", 3)
    near = client.get(
        url, headers=h, params={"x_m": truth[0, 3], "y_m": truth[1, 3], "radius_m": 0.5}
    ).json()
    assert entry_id in [e["id"] for e in near["items"]] and near["total"] < everything["total"]
    assert client.get(url, headers=h, params={"x_m": 1.0}).status_code == 422

    r = client.patch(f"{url}/{entry_id}", headers=h, json={"tags": ["Dusk", "dusk", "rain"]})
    assert r.status_code == 200 and sorted(r.json()["tags"]) == ["dusk", "rain"]
    got = client.get(f"{url}/{entry_id}", headers=h).json()
    assert sorted(got["tags"]) == ["dusk", "rain"] and got["timestamp_s"] == 1.2
    # the next localize answer names the new tags (the entry cache follows the re-tag)
    answer = _localize(client, m, frame_png(sim_dataset, "01", 3))
    named = [h["entry_tags"] for h in answer["hypotheses"] if h["entry_id"] == entry_id]
    assert named and all(sorted(t) == ["dusk", "rain"] for t in named)
    assert np.allclose(got["T_world_from_cam"], truth.ravel())
    assert client.get(f"{url}/999999", headers=h).status_code == 404
    detail = client.get(f"/v1/maps/{m.map_id}", headers=m.keys.header("admin")).json()
    assert detail["tag_counts"] == {"dusk": 1, "rain": 1}


def test_depth_png_entry(sim_dataset, map_copy, client_on_copy):
    client, m = client_on_copy, map_copy
    frame = 10
    depth = (sim_dataset / "sequences" / "01" / "depth" / f"{frame:06d}.png").read_bytes()
    r = client.post(
        f"/v1/maps/{m.map_id}/entries",
        headers=m.keys.header("write"),
        files={
            "image": ("i.png", frame_png(sim_dataset, "01", frame), "image/png"),
            "depth": ("d.png", depth, "image/png"),
        },
        data={
            "T_world_from_cam": " ".join(map(str, ground_truth(sim_dataset, "01", frame).ravel())),
            "depth_scale": "256",
        },
    )
    assert r.status_code == 201, r.text
    assert r.json()["entry"]["n_points"] >= 100


def test_an_entry_shows_its_image_and_both_kinds_of_keypoints(
    sim_dataset, map_copy, client_on_copy
):
    import cv2

    client, m = client_on_copy, map_copy
    r = _add_lidar_entry(client, m, sim_dataset, QUERY, "night")
    assert r.status_code == 201, r.text
    entry = r.json()["entry"]
    base = f"/v1/maps/{m.map_id}/entries/{entry['id']}"

    got = client.get(f"{base}/image", headers=m.keys.header("write"))
    assert got.status_code == 200 and got.headers["content-type"] == "image/jpeg"
    jpeg = cv2.imdecode(np.frombuffer(got.content, np.uint8), cv2.IMREAD_GRAYSCALE)
    width, height = entry["image_width_px"], entry["image_height_px"]
    assert (
        jpeg.shape[1] == min(640, width)
        and abs(jpeg.shape[0] / jpeg.shape[1] - height / width) < 0.01
    )
    # the JPEG is the uploaded frame, downscaled
    frame = cv2.imdecode(np.frombuffer(frame_png(sim_dataset, "01", QUERY), np.uint8), 0)
    small = cv2.resize(frame, jpeg.shape[::-1], interpolation=cv2.INTER_AREA)
    assert np.abs(jpeg.astype(float) - small).mean() < 4.0

    kp = client.get(f"{base}/keypoints", headers=m.keys.header("write")).json()
    assert kp["has_image"] and len(kp["x_px"]) == entry["n_points"]
    n_without = len(kp["without_point_x_px"])
    assert n_without == len(kp["without_point_y_px"]) > 0
    # with and without a 3D point are disjoint parts of the image's ORB keypoints
    with_pt = set(zip(kp["x_px"], kp["y_px"], strict=True))
    assert not with_pt & set(zip(kp["without_point_x_px"], kp["without_point_y_px"], strict=True))

    # a vehicle key may not read it; an ingested entry of the same map has its image too
    assert client.get(f"{base}/image", headers=m.keys.header("localize")).status_code == 403
    first = client.get(
        f"/v1/maps/{m.map_id}/entries?limit=1", headers=m.keys.header("write")
    ).json()["items"][0]
    other = client.get(
        f"/v1/maps/{m.map_id}/entries/{first['id']}/image", headers=m.keys.header("write")
    )
    assert other.status_code == 200 and other.content[:3] == b"\xff\xd8\xff"
    # deleted: 404 with a message
    assert client.delete(base, headers=m.keys.header("write")).status_code == 204
    gone = client.get(f"{base}/image", headers=m.keys.header("write"))
    assert gone.status_code == 404 and "does not exist" in gone.json()["error"]["message"]
