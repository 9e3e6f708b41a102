"""A mapping run from a stereo camera uploaded over REST: ``depth_from=stereo`` ingests a
KITTI run that carries image_1 and P1 but no LiDAR scans; without it the same upload is
refused (422 naming the missing scans) and leaves nothing behind."""

from __future__ import annotations

import io
import shutil
import tarfile

from api_helpers import create_keys, make_settings, open_client, wait_job


def _stereo_only_tar(dataset, tmp_path) -> bytes:
    root = tmp_path / "upload"
    shutil.copytree(dataset / "sequences" / "00", root / "sequences" / "00")
    for sub in ("velodyne", "depth"):
        shutil.rmtree(root / "sequences" / "00" / sub)
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        tar.add(root / "sequences" / "00", arcname="run/sequences/00")
        tar.add(dataset / "poses" / "00.txt", arcname="run/poses/00.txt")
    return buffer.getvalue()


def test_stereo_run_upload(stereo_dataset, tmp_path):
    from monoloc.core.camera import KITTI_CAM0

    archive = _stereo_only_tar(stereo_dataset, tmp_path)
    data_dir = tmp_path / "data"
    with open_client(make_settings(data_dir)) as client:
        keys = create_keys(client)
        c = KITTI_CAM0.scaled(0.5)
        camera = {k: getattr(c, k) for k in ("fx", "fy", "cx", "cy", "width_px", "height_px")}
        map_id = client.post(
            "/v1/maps", json={"name": "stereo", "camera": camera}, headers=keys.header("admin")
        ).json()["id"]
        url, h = f"/v1/maps/{map_id}/runs", keys.header("write")

        def upload(**fields):
            files = {"archive": ("run.tar", archive, "application/x-tar")}
            return client.post(url, headers=h, files=files, data={"format": "kitti", **fields})

        refused = upload()
        assert refused.status_code == 422, refused.text
        assert "velodyne" in refused.json()["error"]["message"]
        assert str(data_dir) not in refused.text
        bad = upload(depth_from="sonar")
        assert bad.status_code == 422 and bad.json()["error"]["code"] == "validation_error"
        assert client.get(url, headers=h).json() == []
        assert not [p for p in (data_dir / "uploads").iterdir() if p.name != ".keep"]

        r = upload(depth_from="stereo")
        assert r.status_code == 202, r.text
        job = wait_job(client, r.json()["job"]["id"], h)
        assert job["state"] == "done", job
        assert job["result"]["entries_added"] == 6 and job["result"]["points_min"] >= 100
        assert len(client.get(url, headers=h).json()) == 1
