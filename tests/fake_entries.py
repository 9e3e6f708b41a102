"""Valid map entries with random features, for storage and fleet tests that need rows,
not images (shared by the storage suite's ``make_entry`` and the shard suite)."""

from __future__ import annotations

import hashlib

import numpy as np

from monoloc.core.camera import KITTI_CAM0
from monoloc.core.geometry import T_world_from_cam_planar
from monoloc.server.storage.records import NewEntry


def fake_entry(
    name: str,
    x_m: float = 0.0,
    y_m: float = 0.0,
    yaw_rad: float = 0.0,
    n: int = 20,
    tags: tuple[str, ...] = (),
    timestamp_s: float = 0.1,
) -> NewEntry:
    """An entry whose camera stands at (x_m, y_m) heading yaw_rad, n random features drawn
    from a stream seeded by ``name`` (the same name gives the same entry)."""
    rng = np.random.default_rng(
        int.from_bytes(hashlib.sha256(name.encode()).digest()[:4], "little")
    )
    return NewEntry(
        source_image_hash=hashlib.sha256(name.encode()).hexdigest(),
        T_world_from_cam=T_world_from_cam_planar(x_m, y_m, yaw_rad, height_m=1.6),
        vlad=rng.normal(size=2048).astype(np.float32),
        code=rng.integers(0, 256, 256, dtype=np.uint8),
        keypoints_px=rng.uniform(0, 370, (n, 2)).astype(np.float32),
        descriptors=rng.integers(0, 256, (n, 32), dtype=np.uint8),
        points_cam=rng.uniform(1, 40, (n, 3)).astype(np.float32),
        image_width_px=KITTI_CAM0.width_px,
        image_height_px=KITTI_CAM0.height_px,
        tags=tags,
        timestamp_s=timestamp_s,
    )
