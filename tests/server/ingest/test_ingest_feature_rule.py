"""A map's entries all pick their ORB corners one way: the way the map recorded when it
was created (``maps.features``). A map from before the grid keeps ORB's own rule for the
entries added to it later (night or off-center images), and its queries are described
the same way, so no map ends up with entries described two ways."""

from __future__ import annotations

import numpy as np
from sqlalchemy import update

from monoloc.server.ingest.common import content_hash
from monoloc.server.ingest.pipeline import ingest_run
from monoloc.server.ingest.single import add_single_image
from monoloc.server.ingest.sources import read_kitti_sequence
from monoloc.server.storage import entries as entries_repo
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.models import Map
from monoloc.server.vision.features import OrbConfig, extract_features


def _as_strongest(factory, map_id: int) -> None:
    """The map as revision 0007 stamps one made before the grid."""
    with session_scope(factory) as session:
        session.execute(update(Map).where(Map.id == map_id).values(features={"rule": "strongest"}))


def _keypoints(factory, map_id: int) -> dict[str, np.ndarray]:
    with session_scope(factory) as session:
        ids = [e.id for e in entries_repo.list_entries(session, map_id, limit=1000)]
        data = entries_repo.get_entry_data(session, ids)
    return {d.summary.source_image_hash: d.keypoints_px for d in data}


def _rows(points: np.ndarray) -> set[tuple[float, float]]:
    return {(float(x), float(y)) for x, y in np.round(points, 3)}


def test_entries_pick_their_corners_by_their_maps_rule(kitti_root, factory, make_map, make_run):
    seq = read_kitti_sequence(kitti_root.root)
    frame = seq.frames[3]
    loaded = seq.load(frame)
    rules = {"grid": OrbConfig(), "strongest": OrbConfig(grid_cells=None)}
    picked = {
        rule: _rows(extract_features(loaded.image_gray, c).keypoints_px)
        for rule, c in rules.items()
    }
    assert picked["grid"] != picked["strongest"]
    kept = {}
    for rule in rules:
        map_id = make_map(name=f"m-{rule}")
        if rule == "strongest":
            _as_strongest(factory, map_id)
        summary, created = add_single_image(
            factory, map_id, frame.image_path.read_bytes(), frame.T_world_from_cam, loaded.source
        )
        assert created
        kept[rule] = _rows(_keypoints(factory, map_id)[summary.source_image_hash])
        assert len(kept[rule]) >= 20 and kept[rule] <= picked[rule], rule
    assert kept["grid"] != kept["strongest"]
    # a whole run into a map of ORB's rule: every entry picked the strongest corners
    map_id = make_map(name="run-strongest")
    _as_strongest(factory, map_id)
    ingest_run(factory, map_id, seq, run_id=make_run(map_id, seq))
    stored = _keypoints(factory, map_id)
    assert len(stored) == len(seq.frames)
    for f in seq.frames:
        image = seq.load(f).image_gray
        strongest = _rows(extract_features(image, rules["strongest"]).keypoints_px)
        assert _rows(stored[content_hash(image)]) <= strongest


def _shaded_photograph(width: int, height: int) -> np.ndarray:
    """A real photograph at the camera's size with its left half in the shade (a third of
    the contrast): ORB's strongest corners sit in the sunlit half, the grid's in both."""
    import cv2
    from skimage import data

    image = cv2.resize(data.astronaut()[:, :, 1], (width, height)).astype(np.float64)
    image[:, : width // 2] = 20.0 + image[:, : width // 2] / 3.0
    return image.astype(np.uint8)


def test_queries_are_described_by_their_maps_rule(factory, make_map, settings):
    """A map's own image sent as a query matches every 3D point of its entry when the
    query picks its corners by the map's rule, for a map of either rule; picked by the
    other rule (the grid against ORB's strongest) it would match only part of them."""
    import cv2

    from monoloc.core.camera import KITTI_CAM0
    from monoloc.server.entry_builder import DepthSource
    from monoloc.server.localize import LocalizeConfig
    from monoloc.server.map_registry import MapRegistry

    camera = KITTI_CAM0
    image = _shaded_photograph(camera.width_px, camera.height_px)
    png = cv2.imencode(".png", image)[1].tobytes()
    plane = DepthSource(np.full(image.shape, 8000, dtype=np.uint16), scale_per_m=1000.0)
    registry = MapRegistry(factory, settings.index_dir)
    share = {}
    for rule in ("grid", "strongest"):
        map_id = make_map(camera=camera, name=f"q-{rule}")
        if rule == "strongest":
            _as_strongest(factory, map_id)
        summary, _ = add_single_image(factory, map_id, png, np.eye(4), plane)
        n_points = len(_keypoints(factory, map_id)[summary.source_image_hash])
        result, _ = registry.localize(
            map_id, image, LocalizeConfig(), np.random.default_rng(0), k=1
        )
        share[rule] = result.best.n_inliers / n_points
    assert min(share.values()) > 0.95, share
    # the other rule's query shares visibly fewer of the strongest entry's corners
    grid_query = _rows(extract_features(image).keypoints_px)
    strongest_entry = _rows(extract_features(image, OrbConfig(grid_cells=None)).keypoints_px)
    assert len(strongest_entry & grid_query) < 0.85 * len(strongest_entry)


def test_orb_for_rule_reads_back_what_selection_rule_records():
    import pytest

    from monoloc.core.errors import InvalidInputError
    from monoloc.server.vision.features import orb_for_rule, rule_is_current, selection_rule

    configs = (
        OrbConfig(),
        OrbConfig(grid_cells=None),
        OrbConfig(grid_cells=(4, 3)),
        OrbConfig(min_fast_threshold=None),
        OrbConfig(flat_fast_corners=None),
        OrbConfig(fast_threshold=25, min_fast_threshold=10),
    )
    for config in configs:
        assert orb_for_rule(selection_rule(config)) == config
    assert orb_for_rule(None) == OrbConfig()
    assert rule_is_current(None) and rule_is_current(selection_rule())
    assert not rule_is_current({"rule": "strongest"})
    # a grid map recorded before the second FAST threshold: one pass at 20, not current
    before = {"rule": "grid", "grid_cells": [8, 5], "candidates_factor": 2.0}
    assert orb_for_rule(before) == OrbConfig(min_fast_threshold=None)
    assert not rule_is_current(before)
    bad_thresholds = {**before, "fast_thresholds": [7, 20]}
    for bad in (
        {"rule": "sift"},
        {"rule": "grid", "grid_cells": "8x5"},
        {"rule": "grid"},
        bad_thresholds,
    ):
        with pytest.raises(InvalidInputError):
            orb_for_rule(bad)


def test_a_vocabulary_change_recomputes_vlads_by_the_maps_rule(
    kitti_root, factory, make_map, make_run
):
    """Switching a map of ORB's rule to another vocabulary recomputes each entry's VLAD
    from its image described by that rule, as its queries are."""
    from monoloc.server.ingest.vocab import change_map_vocabulary_detailed
    from monoloc.server.storage.maps import get_or_create_vocabulary
    from monoloc.server.vision.vlad import compute_vlad
    from monoloc.server.vision.vocabulary import Vocabulary

    seq = read_kitti_sequence(kitti_root.root)
    map_id = make_map(name="vocab-strongest")
    _as_strongest(factory, map_id)
    ingest_run(factory, map_id, seq, run_id=make_run(map_id, seq))
    centres = np.random.default_rng(5).uniform(0, 255, (64, 32)).astype(np.float32)
    with session_scope(factory) as session:
        vocab, _ = get_or_create_vocabulary(session, centres, "another vocabulary")
    change = change_map_vocabulary_detailed(factory, map_id, vocab.id)
    assert change.exact == len(seq.frames)
    image = seq.load(seq.frames[3]).image_gray
    with session_scope(factory) as session:
        ids = [e.id for e in entries_repo.list_entries(session, map_id)]
        by_hash = {
            d.summary.source_image_hash: d.vlad for d in entries_repo.get_entry_data(session, ids)
        }
    stored = by_hash[content_hash(image)]
    vocabulary = Vocabulary.from_centres(centres)
    strongest = compute_vlad(
        extract_features(image, OrbConfig(grid_cells=None)).descriptors, vocabulary
    )
    grid = compute_vlad(extract_features(image).descriptors, vocabulary)
    np.testing.assert_allclose(stored, strongest, atol=1e-6)
    assert not np.allclose(stored, grid, atol=1e-6)
