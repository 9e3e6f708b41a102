"""The camera registry (``/v1/cameras``) through the real app on a real SQLite file: a
vehicle registers its camera once and names it by id in ``POST .../localize`` and the
stream header; both an id and intrinsics, an unknown id, an image of another size, an
unknown lens model are refused with a message; the cameras outlive the app (stored in
the database); who may delete one."""

from __future__ import annotations

from api_helpers import (
    SIM_SCALE,
    create_keys,
    frame_png,
    make_settings,
    open_client,
)

from monoloc.client.api import encode_frame
from monoloc.core.camera import KITTI_CAM0

CAM = KITTI_CAM0.scaled(SIM_SCALE)
BODY = dict(
    name="car7-front",
    fx=CAM.fx,
    fy=CAM.fy,
    cx=CAM.cx,
    cy=CAM.cy,
    width_px=CAM.width_px,
    height_px=CAM.height_px,
)
FOCAL = dict(fx=repr(CAM.fx), fy=repr(CAM.fy), cx=repr(CAM.cx), cy=repr(CAM.cy))


def _poses(answer: dict) -> list[tuple]:
    return [(h["entry_id"], tuple(h["pose"].values())) for h in answer["hypotheses"]]


def test_a_registered_camera_localizes_like_its_intrinsics(client_on_copy, map_copy, sim_dataset):
    client, keys = client_on_copy, map_copy.keys
    loc = keys.header("localize")
    r = client.post("/v1/cameras", json=BODY, headers=loc)
    assert r.status_code == 201, r.text
    camera = r.json()
    assert camera["name"] == "car7-front" and camera["distortion_model"] is None
    assert camera["fx"] == CAM.fx and camera["width_px"] == CAM.width_px
    # any key reads the registry
    listed = client.get("/v1/cameras", headers=keys.header("write")).json()["items"]
    assert [c["id"] for c in listed] == [camera["id"]]
    assert client.get(f"/v1/cameras/{camera['id']}", headers=loc).json() == camera

    url = f"/v1/maps/{map_copy.map_id}/localize"
    image = {"image": ("f.png", frame_png(sim_dataset, "01", 4), "image/png")}
    by_id = client.post(url, files=image, data={"camera_id": camera["id"], "seed": 7}, headers=loc)
    assert by_id.status_code == 200, by_id.text
    explicit = client.post(url, files=image, data={**FOCAL, "seed": 7}, headers=loc)
    assert by_id.json()["hypotheses"] and _poses(by_id.json()) == _poses(explicit.json())

    both = client.post(url, files=image, data={**FOCAL, "camera_id": camera["id"]}, headers=loc)
    assert both.status_code == 422
    assert "camera_id or the camera's intrinsics, not both" in both.json()["error"]["message"]
    unknown = client.post(url, files=image, data={"camera_id": 999999}, headers=loc)
    assert unknown.status_code == 404
    assert "camera 999999 does not exist" in unknown.json()["error"]["message"]
    half = client.post("/v1/cameras", json={**BODY, "width_px": 620}, headers=loc).json()
    wrong = client.post(url, files=image, data={"camera_id": half["id"]}, headers=loc)
    assert wrong.status_code == 422
    assert f"camera {half['id']}" in wrong.json()["error"]["message"]

    # the stream header names it too
    stream = f"/v1/maps/{map_copy.map_id}/stream"
    png = frame_png(sim_dataset, "01", 4)
    with client.websocket_connect(stream, headers=loc) as ws:
        ws.send_bytes(encode_frame({"seq": 0, "t": 0.0, "camera_id": camera["id"]}, png))
        ws.send_bytes(encode_frame({"seq": 1, "t": 0.1, "camera_id": 999999}, png))
        header = {"seq": 2, "t": 0.2, "camera_id": camera["id"], "intrinsics": dict(fx=1.0)}
        ws.send_bytes(encode_frame(header, png))
        answers = [ws.receive_json() for _ in range(3)]
    assert answers[0]["seq"] == 0 and answers[0]["hypotheses"], answers[0]
    assert answers[1]["error"]["code"] == "not_found", answers[1]
    assert answers[2]["error"]["code"] == "invalid_input", answers[2]


def test_cameras_are_stored_checked_and_deleted_by_their_key(tmp_path):
    data_dir = tmp_path / "data"
    with open_client(make_settings(data_dir)) as client:
        keys = create_keys(client)
        loc = keys.header("localize")
        lens = dict(distortion_model="plumb_bob", distortion=[-0.28, 0.09, 0.0006, -0.0004])
        r = client.post("/v1/cameras", json={**BODY, **lens}, headers=loc)
        assert r.status_code == 201, r.text
        camera_id = r.json()["id"]
        bad = client.post(
            "/v1/cameras",
            json={**BODY, "distortion_model": "ocam", "distortion": [0.1]},
            headers=loc,
        )
        assert bad.status_code == 422 and "'ocam'" in bad.json()["error"]["message"]
        few = client.post(
            "/v1/cameras",
            json={**BODY, "distortion_model": "plumb_bob", "distortion": [0.1]},
            headers=loc,
        )
        assert few.status_code == 422 and "takes 4 or 5" in few.json()["error"]["message"]
        assert client.post("/v1/cameras", json={**BODY, "fx": -1.0}, headers=loc).status_code == 422
        # registering needs the localize scope; a key limited to a map registers too
        assert (
            client.post("/v1/cameras", json=BODY, headers=keys.header("write")).status_code == 403
        )
        admin = keys.header("admin")
        m = client.post(
            "/v1/maps",
            json={"name": "m", "camera": {k: v for k, v in BODY.items() if k != "name"}},
            headers=admin,
        ).json()
        limited = client.post(
            "/v1/keys",
            json={"name": "car8", "scopes": ["localize"], "maps": [m["id"]]},
            headers=admin,
        ).json()["key"]
        mine = client.post("/v1/cameras", json=BODY, headers={"X-API-Key": limited})
        assert mine.status_code == 201
        seen = client.get("/v1/cameras", headers={"X-API-Key": limited}).json()["items"]
        assert [c["id"] for c in seen] == [camera_id, mine.json()["id"]]
        # only the registering key (or an admin) deletes
        other = client.delete(f"/v1/cameras/{camera_id}", headers={"X-API-Key": limited})
        assert other.status_code == 403 and "another key" in other.json()["error"]["message"]
        assert client.delete(f"/v1/cameras/{mine.json()['id']}", headers=admin).status_code == 204
    # a new app on the same database file still knows the camera, lens included
    with open_client(make_settings(data_dir)) as client:
        got = client.get(f"/v1/cameras/{camera_id}", headers=loc)
        assert got.status_code == 200, got.text
        assert got.json()["distortion"] == lens["distortion"]
        assert len(client.get("/v1/cameras", headers=loc).json()["items"]) == 1
        assert client.delete(f"/v1/cameras/{camera_id}", headers=loc).status_code == 204
        gone = client.get(f"/v1/cameras/{camera_id}", headers=loc)
        assert gone.status_code == 404 and "does not exist" in gone.json()["error"]["message"]
