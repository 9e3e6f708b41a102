import json

import pytest

from monoloc.sim.generate import GenerateConfig, generate_dataset
from monoloc.sim.lidar import LidarConfig
from monoloc.sim.recording import RecordingErrors

TINY = GenerateConfig(
    seed=3,
    runs=("map", "query"),
    max_frames=4,
    image_scale=0.5,
    write_depth=True,
    errors=RecordingErrors.none(),
    lidar=LidarConfig(azimuth_steps=1000),
)


@pytest.fixture(scope="session")
def tiny_config():
    return TINY


@pytest.fixture(scope="session")
def exact_dataset(tmp_path_factory):
    """A tiny dataset (2 runs x 4 frames, half-size images) with exact geometry."""
    root = tmp_path_factory.mktemp("exact")
    generate_dataset(TINY, root)
    return root, json.loads((root / "dataset.json").read_text())
