"""A LiDAR-built sim map exported as COLMAP and as kapture through the CLI, read with
pycolmap and with kapture's own loader (images written, multi-view tracks, poses, the
cameras scaled to the stored previews), then imported again through the CLI into an equal
map: same entries, poses within 1 mm / 0.01 deg, the same keypoints and their points
within the track merge radius."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from cli_runner import run_monoloc

from monoloc.core.geometry import R_from_quaternion_xyzw, invert_rigid
from monoloc.server.formats.maps import TrackMerge, entry_name, merge_tracks
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage.db import session_scope

RADIUS_M = TrackMerge().radius_m


@pytest.fixture
def cli(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("MONOLOC_DATA_DIR", str(tmp_path / "data"))

    def run(*args: str) -> str:
        code, out, err = run_monoloc(monkeypatch, capsys, *args)
        assert code == 0, err
        return out

    return run


@pytest.fixture
def lidar_map(cli, sim_city):
    cli("map", "create", "city", "--camera", str(sim_city / "sequences" / "00"))
    cli("map", "ingest", "--map", "city", "--format", "kitti", str(sim_city), "--sequence", "00")
    return "city"


def _entries(tmp_path, name):
    from monoloc.server.ingest.manage import find_map
    from monoloc.server.settings import Settings
    from monoloc.server.storage.db import create_engine_for, make_session_factory

    engine = create_engine_for(Settings(data_dir=tmp_path / "data"))
    try:
        factory = make_session_factory(engine)
        record = find_map(factory, name)
        with session_scope(factory) as session:
            ids = [s.id for s in entries_repo.list_entries(session, record.id, limit=1000)]
            return record, entries_repo.get_entry_data(session, ids)
    finally:
        engine.dispose()


def _assert_equal_maps(a_entries, b_entries):
    assert len(b_entries) == len(a_entries) == 8
    for a, b in zip(a_entries, b_entries, strict=True):
        Ta, Tb = a.T_world_from_cam, b.T_world_from_cam
        assert np.linalg.norm(Ta[:3, 3] - Tb[:3, 3]) < 1e-3
        cos = np.clip((np.trace(Ta[:3, :3].T @ Tb[:3, :3]) - 1) / 2, -1, 1)
        assert np.degrees(np.arccos(cos)) < 0.01
        assert len(b.points_cam) == len(a.points_cam)
        np.testing.assert_allclose(b.keypoints_px, a.keypoints_px, atol=1e-3)
        moved = np.linalg.norm(b.points_cam - a.points_cam, axis=1)
        assert moved.max() <= RADIUS_M + 1e-4
        assert np.median(moved) < 1e-4  # most points are seen once and kept as they were


def _T_cam_from_world(pose) -> np.ndarray:
    w, x, y, z = pose.r_raw
    T = np.eye(4)
    T[:3, :3] = R_from_quaternion_xyzw(np.array([x, y, z, w]))
    T[:3, 3] = np.ravel(pose.t_raw)
    return T


def test_colmap_export_has_images_and_tracks_and_imports_back_equal(cli, lidar_map, tmp_path):
    import pycolmap

    record, entries = _entries(tmp_path, lidar_map)
    out = tmp_path / "colmap"
    assert "8 entries" in cli("map", "export", "--format", "colmap", "--map", "city", str(out))
    reconstruction = pycolmap.Reconstruction(str(out))
    assert reconstruction.num_reg_images() == 8
    assert reconstruction.compute_num_observations() == sum(len(e.points_cam) for e in entries)
    lengths = np.array([p.track.length() for p in reconstruction.points3D.values()])
    # Neighbouring frames see the same corners: a share of the points has several views.
    assert lengths.max() >= 3 and np.mean(lengths > 1) > 0.05, np.bincount(lengths)
    for entry in entries:
        image = reconstruction.find_image_with_name(entry_name(entry.id))
        camera = reconstruction.cameras[image.camera_id]
        assert camera.model.name == "PINHOLE"
        pixels = cv2.imread(str(out / "images" / image.name), cv2.IMREAD_GRAYSCALE)
        assert pixels.shape == (camera.height, camera.width) == (188, 620)
        T = np.eye(4)
        T[:3] = image.cam_from_world().matrix()
        np.testing.assert_allclose(invert_rigid(T), entry.T_world_from_cam, atol=1e-9)
        observed = [p for p in image.points2D if p.has_point3D()]
        assert len(observed) == len(entry.points_cam)
        xyz = np.array([reconstruction.points3D[p.point3D_id].xyz for p in observed])
        world = entry.points_cam @ entry.T_world_from_cam[:3, :3].T + entry.T_world_from_cam[:3, 3]
        assert np.linalg.norm(xyz - world, axis=1).max() <= RADIUS_M + 1e-4
    imported = cli(
        "map", "import", "--format", "colmap", str(out), "--map", "again", "--points", "model"
    )
    assert "created map again" in imported
    _, again = _entries(tmp_path, "again")
    _assert_equal_maps(entries, again)
    # The default (ORB features on the exported images) gives the same entries and poses.
    cli("map", "import", "--format", "colmap", str(out), "--map", "orb")
    _, orb = _entries(tmp_path, "orb")
    assert len(orb) == 8
    for a, b in zip(entries, orb, strict=True):
        np.testing.assert_allclose(b.T_world_from_cam, a.T_world_from_cam, atol=1e-6)
        assert len(b.points_cam) >= 0.5 * len(a.points_cam)


def test_kapture_export_reads_in_kapture_and_imports_back_equal(cli, lidar_map, tmp_path):
    from kapture.io.csv import kapture_from_dir
    from kapture.io.records import get_image_fullpath

    _, entries = _entries(tmp_path, lidar_map)
    out = tmp_path / "kapture"
    cli("map", "export", "--format", "kapture", "--map", "city", str(out))
    data = kapture_from_dir(str(out))
    assert len(data.records_camera) == 8 and list(data.sensors) == ["cam0"]
    assert data.sensors["cam0"].camera_type.name == "PINHOLE"
    views_per_point = [
        len({name for name, _ in data.observations[point, "orb"]})
        for point in range(len(data.points3d))
    ]
    assert sum(views_per_point) == sum(len(e.points_cam) for e in entries)
    assert max(views_per_point) >= 3 and np.mean(np.array(views_per_point) > 1) > 0.05
    for entry in entries:
        name = data.records_camera[entry.id, "cam0"]
        assert name == entry_name(entry.id)
        pixels = cv2.imread(get_image_fullpath(str(out), name), cv2.IMREAD_GRAYSCALE)
        assert pixels.shape == (188, 620)
        np.testing.assert_allclose(
            _T_cam_from_world(data.trajectories[entry.id, "cam0"]),
            invert_rigid(entry.T_world_from_cam),
            atol=1e-9,
        )
    cli("map", "import", "--format", "kapture", str(out), "--map", "again", "--points", "model")
    _, again = _entries(tmp_path, "again")
    _assert_equal_maps(entries, again)


def test_previews_smaller_than_the_camera_export_with_scaled_intrinsics(
    cli, sim_city, tmp_path, monkeypatch
):
    """Entries whose stored preview is half the camera's size: the exported camera and
    keypoints are scaled to the preview, so the points project onto their keypoints in
    the exported images through pycolmap's camera."""
    import pycolmap

    from monoloc.server.entry_builder import BuildConfig
    from monoloc.server.formats.maps import export_map
    from monoloc.server.ingest.manage import create_map, ingest_source
    from monoloc.server.ingest.pipeline import IngestConfig
    from monoloc.server.ingest.sources import read_kitti_sequence
    from monoloc.server.settings import Settings
    from monoloc.server.storage.db import create_engine_for, make_session_factory
    from monoloc.server.storage.migrate import upgrade_database

    settings = Settings(data_dir=tmp_path / "small")
    upgrade_database(settings.database_url)
    engine = create_engine_for(settings)
    factory = make_session_factory(engine)
    try:
        run = read_kitti_sequence(sim_city, "00")
        create_map(factory, "small", run.intrinsics)
        ingest_source(
            factory, "small", run, config=IngestConfig(build=BuildConfig(image_max_side_px=310))
        )
        export_map(factory, "small", "colmap", tmp_path / "out")
    finally:
        engine.dispose()
    reconstruction = pycolmap.Reconstruction(str(tmp_path / "out"))
    (camera,) = reconstruction.cameras.values()
    assert (camera.width, camera.height) == (310, 94)
    assert camera.focal_length_x == pytest.approx(run.intrinsics.fx / 2)
    residuals = []
    for image in reconstruction.images.values():
        pixels = cv2.imread(str(tmp_path / "out" / "images" / image.name), cv2.IMREAD_GRAYSCALE)
        assert pixels.shape == (94, 310)
        for p in image.points2D:
            if p.has_point3D():
                xyz = image.cam_from_world() * reconstruction.points3D[p.point3D_id].xyz
                residuals.append(np.linalg.norm(camera.img_from_cam(xyz) - p.xy))
    # merged points move by up to the merge radius: most residuals are ~0
    assert np.median(residuals) < 1e-3 and np.percentile(residuals, 90) < 1.5


def test_merge_tracks_joins_close_matching_points_of_different_entries():
    rng = np.random.default_rng(4)
    desc = rng.integers(0, 256, (3, 32), dtype=np.uint8)
    other = desc.copy()
    other[0, :2] ^= 0xFF  # 16 bits off: still the same corner
    other[2] = 255 - desc[2]  # 256 bits off: another corner at the same place
    a = np.array([[0.0, 0.0, 10.0], [1.0, 0.0, 10.0], [2.0, 0.0, 10.0]])
    b = a + [[0.01, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.0, 0.0]]
    ids_a, ids_b = merge_tracks([a, b], [desc, other])
    assert ids_a[0] == ids_b[0]  # close, descriptors agree
    assert ids_a[1] != ids_b[1]  # 0.5 m apart
    assert ids_a[2] != ids_b[2]  # descriptors disagree
    # two keypoints of one entry are never one track, even at the same place
    (ids,) = merge_tracks([np.zeros((2, 3))], [np.zeros((2, 32), np.uint8)])
    assert ids[0] != ids[1]


def test_merge_tracks_splits_a_chain_through_two_keypoints_of_one_entry():
    """p1 and p2 of entry A, q of entry B between them: q joins the closer one only."""
    same = np.zeros((1, 32), np.uint8)
    a = np.array([[0.0, 0.0, 10.0], [0.02, 0.0, 10.0]])
    b = np.array([[0.008, 0.0, 10.0]])
    c = np.array([[5.0, 0.0, 10.0], [5.01, 0.0, 10.0]])  # a clean pair elsewhere
    ids_a, ids_b, ids_c, ids_d = merge_tracks(
        [a, b, c[:1], c[1:]], [np.repeat(same, 2, 0), same, same, same]
    )
    assert ids_b[0] == ids_a[0] and ids_a[1] != ids_a[0]
    assert ids_c[0] == ids_d[0] and ids_c[0] not in (ids_a[0], ids_a[1])


def test_merge_tracks_keeps_every_member_within_the_radius_of_its_track():
    """A line of points 2.5 cm apart, one per entry: each pair qualifies, the chain
    would span 25 cm; the tracks it becomes keep their members within 3 cm."""
    line = [np.array([[0.025 * k, 0.0, 10.0]]) for k in range(11)]
    ids = np.concatenate(merge_tracks(line, [np.zeros((1, 32), np.uint8)] * 11))
    xyz = np.concatenate(line)
    # four points would put the outer ones 3.75 cm from their mean: at most three a track;
    # every point has a neighbour within the radius, so none is left alone; a track is
    # one stretch of the line (no member skips a neighbour of another track)
    sizes = np.bincount(np.unique(ids, return_inverse=True)[1])
    assert sizes.min() >= 2 and sizes.max() <= 3, ids
    assert np.count_nonzero(np.diff(ids)) == len(sizes) - 1, ids
    for track in np.unique(ids):
        members = xyz[ids == track]
        assert np.linalg.norm(members - members.mean(axis=0), axis=1).max() <= RADIUS_M
