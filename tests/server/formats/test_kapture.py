"""kapture in and out: a dataset written in the test with kapture's own writer from a sim
run (a rig carrying a camera, a registered depth camera and a LiDAR; depth maps for half
the frames, LiDAR scans for the other half), imported as a mapping run, exported with the
map's keypoints, descriptors and points, read back by kapture and imported again; a
driven trajectory written as kapture."""

from __future__ import annotations

import shutil
from types import SimpleNamespace

import numpy as np
import pytest
from cli_runner import run_monoloc

from monoloc.core.geometry import R_from_quaternion_xyzw, invert_rigid, quaternion_xyzw_from_R
from monoloc.server.formats.kapture_io import read_kapture
from monoloc.server.formats.maps import export_map, import_sources_into_map
from monoloc.server.formats.model import import_sources
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage.db import session_scope

# The rig (vehicle) frame: the camera 1.5 m above it, looking along its +x.
T_CAM_FROM_RIG = np.array(
    [[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 1.5], [1.0, 0.0, 0.0, -0.2], [0.0, 0.0, 0.0, 1.0]]
)


def _pose(kapture, T_a_from_b):
    q = quaternion_xyzw_from_R(T_a_from_b[:3, :3])
    return kapture.PoseTransform(r=[q[3], *q[:3]], t=T_a_from_b[:3, 3].tolist())


@pytest.fixture(scope="module")
def kapture_dir(map_run, sim_city, tmp_path_factory):
    import kapture
    from kapture.io.csv import kapture_to_dir
    from kapture.io.records import depth_map_to_file, get_record_fullpath

    from monoloc.sim.kitti_writer import read_depth

    root = tmp_path_factory.mktemp("kapture")
    c = map_run.intrinsics
    params = [c.width_px, c.height_px, c.fx, c.fy, c.cx + 0.5, c.cy + 0.5]
    sensors = kapture.Sensors()
    sensors["cam0"] = kapture.Camera(kapture.CameraType.PINHOLE, params, name="cam0")
    sensors["depth0"] = kapture.Camera(
        kapture.CameraType.PINHOLE, params, name="depth0", sensor_type="depth"
    )
    sensors["lidar0"] = kapture.create_sensor("lidar", [], name="lidar0")
    T_cam_from_lidar = map_run.load(map_run.frames[0]).source.T_cam_from_lidar
    rigs = kapture.Rigs()
    rigs["car", "cam0"] = _pose(kapture, T_CAM_FROM_RIG)
    rigs["car", "depth0"] = _pose(kapture, T_CAM_FROM_RIG)
    rigs["car", "lidar0"] = _pose(kapture, invert_rigid(T_cam_from_lidar) @ T_CAM_FROM_RIG)
    trajectories, cameras = kapture.Trajectories(), kapture.RecordsCamera()
    depths, lidars = kapture.RecordsDepth(), kapture.RecordsLidar()
    seq = sim_city / "sequences" / "00"
    for frame in map_run.frames:
        ts = 1000 + 100 * frame.index
        T_rig_from_world = invert_rigid(T_CAM_FROM_RIG) @ invert_rigid(frame.T_world_from_cam)
        trajectories[ts, "car"] = _pose(kapture, T_rig_from_world)
        name = f"cam0/{frame.index:06d}.png"
        cameras[ts, "cam0"] = name
        target = get_record_fullpath(str(root), name)
        (root / "sensors" / "records_data" / "cam0").mkdir(parents=True, exist_ok=True)
        shutil.copyfile(frame.image_path, target)
        if frame.index < 4:
            depth = read_depth(seq / "depth" / f"{frame.index:06d}.png")
            depths[ts, "depth0"] = f"depth0/{frame.index:06d}.depth"
            path = get_record_fullpath(str(root), depths[ts, "depth0"])
            (root / "sensors" / "records_data" / "depth0").mkdir(exist_ok=True)
            depth_map_to_file(path, np.where(np.isfinite(depth), depth, 0).astype(np.float32))
        else:
            lidars[ts, "lidar0"] = f"lidar0/{frame.index:06d}.bin"
            (root / "sensors" / "records_data" / "lidar0").mkdir(exist_ok=True)
            shutil.copyfile(
                seq / "velodyne" / f"{frame.index:06d}.bin",
                get_record_fullpath(str(root), lidars[ts, "lidar0"]),
            )
    data = kapture.Kapture(
        sensors=sensors,
        rigs=rigs,
        trajectories=trajectories,
        records_camera=cameras,
        records_depth=depths,
        records_lidar=lidars,
    )
    kapture_to_dir(str(root), data)
    return root


def _entries(factory, map_id):
    with session_scope(factory) as session:
        ids = [s.id for s in entries_repo.list_entries(session, map_id, limit=1000)]
        return entries_repo.get_entry_data(session, ids)


def test_import_depth_and_lidar_records_through_a_rig(factory, kapture_dir, map_run):
    model = read_kapture(kapture_dir)
    assert len(model.images) == 8 and model.default_up == "z"
    assert sum(im.depth is not None for im in model.images) == 4
    assert sum(im.lidar is not None for im in model.images) == 4
    sources = import_sources(model, fmt="kapture", up=None)
    record, summaries, _ = import_sources_into_map(factory, "k", sources)
    assert summaries[0].entries_added == 8
    from monoloc.server.ingest.manage import find_map
    from monoloc.server.storage import runs as runs_repo

    with session_scope(factory) as session:
        assert runs_repo.list_runs(session, record.id)[0].source_format == "kapture"
    assert find_map(factory, "k").camera == map_run.intrinsics
    # The same frames ingested from the KITTI layout (LiDAR) give the same poses, and
    # the LiDAR half gives the same entries exactly.
    from monoloc.server.ingest.manage import create_map, ingest_source

    create_map(factory, "kitti", map_run.intrinsics)
    ingest_source(factory, "kitti", map_run)
    kitti_entries = _entries(factory, find_map(factory, "kitti").id)
    for i, (a, b) in enumerate(zip(_entries(factory, record.id), kitti_entries, strict=True)):
        np.testing.assert_allclose(a.T_world_from_cam, b.T_world_from_cam, atol=1e-6)
        if i >= 4:  # LiDAR records: T_cam_from_lidar recovered through the rig
            np.testing.assert_allclose(a.points_cam, b.points_cam, atol=2e-3)
        else:  # depth maps: points on the keypoints' rays at the rendered depth
            assert len(a.points_cam) >= 20
            common = (a.keypoints_px[:, None] == b.keypoints_px[None]).all(axis=2)
            ia, ib = np.nonzero(common)
            assert len(ia) >= 10
            relative = np.abs(a.points_cam[ia, 2] - b.points_cam[ib, 2]) / b.points_cam[ib, 2]
            assert np.median(relative) < 0.02


def test_export_reads_back_in_kapture_and_imports_again(factory, kapture_dir, tmp_path):
    from kapture.io.csv import kapture_from_dir

    from monoloc.server.formats.maps import TrackMerge

    model = read_kapture(kapture_dir)
    first, _, _ = import_sources_into_map(
        factory, "first", import_sources(model, fmt="kapture", up=None)
    )
    export_map(factory, "first", "kapture", tmp_path / "export")
    data = kapture_from_dir(str(tmp_path / "export"))
    entries = _entries(factory, first.id)
    assert len(data.records_camera) == len(entries) == 8
    n_observations = 0
    for entry in entries:
        pose = data.trajectories[entry.id, "cam0"]  # kapture: cam_from_world
        w, x, y, z = pose.r_raw
        T_cam_from_world = np.eye(4)
        T_cam_from_world[:3, :3] = R_from_quaternion_xyzw(np.array([x, y, z, w]))
        T_cam_from_world[:3, 3] = np.ravel(pose.t_raw)
        np.testing.assert_allclose(
            T_cam_from_world, invert_rigid(entry.T_world_from_cam), atol=1e-9
        )
        n_observations += len(entry.points_cam)
    assert sum(len(data.observations[p, "orb"]) for p in range(len(data.points3d))) == (
        n_observations
    )
    assert len(data.points3d) < n_observations  # points seen by several entries merged
    # The export carries its images (the entries' previews): it imports back as it is.
    again = read_kapture(tmp_path / "export")
    assert again.default_up == "z" and all(len(im.keypoints_px) for im in again.images)
    second, summaries, _ = import_sources_into_map(
        factory, "second", import_sources(again, fmt="kapture", up=None, points="model")
    )
    assert summaries[0].entries_added == 8
    radius = TrackMerge().radius_m
    for a, b in zip(entries, _entries(factory, second.id), strict=True):
        np.testing.assert_allclose(b.T_world_from_cam, a.T_world_from_cam, atol=1e-6)
        np.testing.assert_allclose(b.keypoints_px, a.keypoints_px, atol=1e-4)
        assert np.linalg.norm(b.points_cam - a.points_cam, axis=1).max() <= radius + 1e-4


def test_driven_trajectory_as_kapture_and_cli_errors(tmp_path, map_run, monkeypatch, capsys):
    """A TUM and a KITTI file as `monoloc drive` writes them, exported by the CLI and read
    back by kapture; a folder that is not a kapture dataset is refused in one line."""
    from kapture.io.csv import kapture_from_dir

    from monoloc.client.trajectory import write_trajectory_files
    from monoloc.core.geometry import planar_from_T_world_from_cam

    planar = planar_from_T_world_from_cam(np.stack([f.T_world_from_cam for f in map_run.frames]))
    stamps = np.array([f.timestamp_s for f in map_run.frames])
    tum_path, kitti_path = write_trajectory_files(tmp_path / "track", stamps, planar, 1.65)
    (tmp_path / "times.txt").write_text("".join(f"{t:.6f}\n" for t in stamps))
    monkeypatch.setenv("MONOLOC_DATA_DIR", str(tmp_path / "data"))

    def run(*args):
        code, out, err = run_monoloc(monkeypatch, capsys, *args)
        return SimpleNamespace(returncode=code, stdout=out, stderr=err)

    for path, extra in ((tum_path, ()), (kitti_path, ("--times", str(tmp_path / "times.txt")))):
        out = tmp_path / f"k_{path.name}"
        result = run(
            "map", "export", "--format", "kapture", "--trajectory", str(path), *extra, str(out)
        )
        assert result.returncode == 0, result.stderr
        data = kapture_from_dir(str(out))
        assert len(data.trajectories) == len(stamps)
        for t, (x, y, yaw) in zip(stamps, planar, strict=True):
            pose = data.trajectories[int(round(t * 1e6)), "cam0"]
            centre = np.asarray(pose.inverse().t_raw).ravel()
            np.testing.assert_allclose(centre, [x, y, 1.65], atol=1e-5)
            w, qx, qy, qz = pose.inverse().r_raw
            axis = R_from_quaternion_xyzw(np.array([qx, qy, qz, w]))[:, 2]
            assert abs(np.arctan2(axis[1], axis[0]) - yaw) < 1e-5
    not_kapture = run("map", "import", "--format", "kapture", str(tmp_path), "--map", "k")
    assert not_kapture.returncode != 0
    assert not_kapture.stderr.strip().startswith("error: ")
    assert "not a kapture dataset" in not_kapture.stderr
    kitti_no_times = run(
        "map", "export", "--format", "kapture", "--trajectory", str(kitti_path), str(tmp_path / "x")
    )
    assert kitti_no_times.returncode != 0 and "--times" in kitti_no_times.stderr
