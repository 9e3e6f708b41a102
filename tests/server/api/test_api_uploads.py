"""Run uploads: archive traversal, links, member and size limits, non-archives and bad
layouts are refused with JSON errors and leave nothing behind (no run, no job, no file
in uploads/ or outside it); a multipart file set is accepted like an archive."""

from __future__ import annotations

import io
import tarfile
import zipfile

import pytest
from api_helpers import camera_of, create_keys, make_settings, open_client, wait_job

CAMERA = dict(fx=300.0, fy=300.0, cx=159.5, cy=119.5, width_px=320, height_px=240)


def _tar(members: list[tarfile.TarInfo | tuple[str, bytes]]) -> bytes:
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        for member in members:
            if isinstance(member, tarfile.TarInfo):
                tar.addfile(member)
            else:
                name, data = member
                info = tarfile.TarInfo(name)
                info.size = len(data)
                tar.addfile(info, io.BytesIO(data))
    return buffer.getvalue()


def _link(name: str, target: str, kind=tarfile.SYMTYPE) -> tarfile.TarInfo:
    info = tarfile.TarInfo(name)
    info.type, info.linkname = kind, target
    return info


def _zip(members: dict[str, bytes], symlink: str | None = None) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name, data in members.items():
            archive.writestr(name, data)
        if symlink is not None:
            info = zipfile.ZipInfo(symlink)
            info.external_attr = 0o120777 << 16
            archive.writestr(info, "/etc/passwd")
    return buffer.getvalue()


@pytest.fixture
def limited(tmp_path):
    settings = make_settings(tmp_path / "data", max_archive_members=20, max_archive_bytes=64 * 1024)
    with open_client(settings) as client:
        keys = create_keys(client)
        map_id = client.post(
            "/v1/maps", json={"name": "m", "camera": CAMERA}, headers=keys.header("admin")
        ).json()["id"]
        yield client, keys, map_id, tmp_path


def test_bad_archives_are_refused_and_leave_nothing(limited):
    client, keys, map_id, tmp_path = limited
    ok = ("sequences/00/calib.txt", b"P0: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    cases = [
        ("traversal", _tar([ok, ("../../evil.txt", b"x")]), 400),
        ("absolute", _tar([("/tmp/evil.txt", b"x")]), 400),
        ("symlink", _tar([ok, _link("sequences/00/poses.txt", "/etc/passwd")]), 400),
        ("hardlink", _tar([ok, _link("h", "/etc/passwd", tarfile.LNKTYPE)]), 400),
        ("zip-traversal", _zip({"a.txt": b"1", "x/../../evil.txt": b"2"}), 400),
        ("zip-symlink", _zip({"a.txt": b"1"}, symlink="link"), 400),
        ("members", _tar([(f"f{i}.txt", b"x") for i in range(21)]), 413),
        ("size", _tar([("big.bin", bytes(65 * 1024))]), 413),
        ("zip-size", _zip({"big.bin": bytes(65 * 1024)}), 413),
        ("not-an-archive", b"just some text, not a tar", 415),
        ("bad-tag", _tar([ok]), 422),
        ("bad-layout", _tar([ok]), 422),
    ]
    for name, blob, status in cases:
        r = client.post(
            f"/v1/maps/{map_id}/runs",
            headers=keys.header("write"),
            files={"archive": (f"{name}.tar", blob, "application/x-tar")},
            data={"format": "kitti", "tags": "bad tag!" if name == "bad-tag" else "ok"},
        )
        assert r.status_code == status, (name, r.text)
        assert r.json()["error"]["message"], name
        assert ("invalid tag" in r.json()["error"]["message"]) == (name == "bad-tag")
        assert str(tmp_path) not in r.json()["error"]["message"], "server paths must not leak"
    assert client.get(f"/v1/maps/{map_id}/runs", headers=keys.header("write")).json() == []
    assert client.get("/v1/jobs", headers=keys.header("write")).json()["items"] == []
    assert list((tmp_path / "data" / "uploads").iterdir()) == []
    assert not list(tmp_path.rglob("evil.txt"))


def test_upload_needs_exactly_one_source_and_a_known_format(limited):
    client, keys, map_id, _ = limited
    url, h = f"/v1/maps/{map_id}/runs", keys.header("write")
    assert client.post(url, headers=h, data={"format": "kitti"}).status_code == 422
    r = client.post(
        url,
        headers=h,
        data={"format": "rosbag"},
        files={"archive": ("a.tar", _tar([("a", b"1")]), "application/x-tar")},
    )
    assert r.status_code == 422 and r.json()["error"]["code"] == "validation_error"
    r = client.post(
        "/v1/maps/999/runs",
        headers=h,
        data={"format": "kitti"},
        files={"archive": ("a.tar", _tar([("a", b"1")]), "application/x-tar")},
    )
    assert r.status_code == 404


def test_file_set_upload_is_ingested(sim_dataset, tmp_path):
    """The multipart-files form of an upload: each file named by its path in the run;
    three frames of the sim map run (a frame range keeps it short)."""
    seq = sim_dataset / "sequences" / "00"
    files = [
        ("files", (f"sequences/00/{p.relative_to(seq)}", p.read_bytes(), "x"))
        for p in sorted(seq.rglob("*"))
        if p.is_file() and "depth" not in p.parts
    ]
    poses = sim_dataset / "poses" / "00.txt"
    files.append(("files", ("poses/00.txt", poses.read_bytes(), "text/plain")))
    with open_client(make_settings(tmp_path / "data")) as client:
        keys = create_keys(client)
        map_id = client.post(
            "/v1/maps",
            json={"name": "s", "camera": camera_of(sim_dataset)},
            headers=keys.header("admin"),
        ).json()["id"]
        r = client.post(
            f"/v1/maps/{map_id}/runs",
            headers=keys.header("write"),
            files=files,
            data={"format": "kitti", "frames": "0:3", "tags": "day,Test", "kind": "offcenter"},
        )
        assert r.status_code == 202, r.text
        assert r.json()["run"]["frames_total"] >= 3
        job = wait_job(client, r.json()["job"]["id"], keys.header("write"))
        assert job["state"] == "done", job
        entries = client.get(
            f"/v1/maps/{map_id}/entries?tag=test", headers=keys.header("write")
        ).json()
        assert entries["total"] == job["result"]["entries_added"] > 0
        # an offcenter run tags its entries off-center, as `monoloc map ingest` does
        assert all(set(e["tags"]) == {"day", "test", "off-center"} for e in entries["items"])
