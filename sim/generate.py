"""Generate a synthetic dataset: what to generate (``GenerateConfig``, both scenarios) and
the entry point that checks it and hands it to its scenario.

- ``urban``: a KITTI-like city in the KITTI odometry layout (``monoloc.sim.urban.generate``;
  its runs in ``monoloc.sim.urban.runs``).
- ``indoor``: rooms with a race track for a 1:10 car, in the TUM RGB-D layout
  (``monoloc.sim.indoor.generate``; its runs in ``monoloc.sim.indoor.plan``).

Generation is deterministic in the seed: the same config gives the same bytes, whatever
the number of worker processes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from monoloc.core.camera import KITTI_CAM0, CameraIntrinsics
from monoloc.core.errors import InvalidInputError
from monoloc.sim.camera import CameraConfig, Lighting
from monoloc.sim.fleet_camera import FleetCameraConfig
from monoloc.sim.indoor.generate import generate_indoor_dataset
from monoloc.sim.indoor.plan import INDOOR_RUN_KINDS, IndoorConfig, indoor_runs
from monoloc.sim.indoor.room import room_configs
from monoloc.sim.lens import lens_remap
from monoloc.sim.lidar import LidarConfig
from monoloc.sim.recording import RecordingErrors
from monoloc.sim.summary import DatasetSummary
from monoloc.sim.urban.city import CityConfig
from monoloc.sim.urban.generate import generate_urban_dataset
from monoloc.sim.urban.runs import DEFAULT_RUNS, RUN_KINDS, TrainRunConfig
from monoloc.sim.vehicle import SensorRig, VehicleConfig

SCENARIOS = ("urban", "indoor")


@dataclass(frozen=True)
class GenerateConfig:
    """What to generate. ``max_frames`` caps each run; ``image_scale`` resizes the camera
    (scaled intrinsics) for quick tests; ``write_depth`` adds sequences/NN/depth/;
    ``write_stereo`` renders the right camera too (sequences/NN/image_1/, baseline
    ``rig.stereo_baseline_m``, P1 in calib.txt; urban only; off by default because it
    doubles the camera's rendering time); ``write_lidar=False`` leaves velodyne/ empty
    (a fleet without LiDAR). ``train_run`` (urban): how the training runs differ from the
    map's street (route shape and length, direction, lighting, exposure, palette, speed,
    frame rate; ``monoloc.sim.urban.runs.TrainRunConfig``); None: as the map's routes.

    Scenario ``indoor`` (TUM RGB-D layout, ``monoloc.sim.indoor.generate``) uses scenario, size,
    seed, runs (from map, query, train, offcenter; the default means all four),
    max_frames, image_scale, workers and ``indoor`` (default: the size preset;
    ``errors=RecordingErrors.none()`` also turns every indoor error off); the
    outdoor-only fields are ignored.

    ``fleet_camera`` (urban): the camera of the ``fleet`` run, the query's drive recorded
    by a fleet car's own camera (size, focal length, lens, mounting;
    ``monoloc.sim.fleet_camera``, issue 48's by default); ``image_scale`` resizes it too."""

    scenario: str = "urban"
    size: str = "small"
    seed: int = 0
    runs: tuple[str, ...] = DEFAULT_RUNS
    max_frames: int | None = None
    image_scale: float = 1.0
    write_depth: bool = False
    write_lidar: bool = True
    write_stereo: bool = False
    query_lighting: str = "day"
    errors: RecordingErrors = field(default_factory=RecordingErrors)
    lidar: LidarConfig = field(default_factory=LidarConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    rig: SensorRig = field(default_factory=SensorRig)
    city: CityConfig | None = None
    query_max_offset_m: float = 1.5
    offcenter_steer_rad: float = 0.05
    workers: int = 1
    indoor: IndoorConfig | None = None
    train_run: TrainRunConfig | None = None
    fleet_camera: FleetCameraConfig = field(default_factory=FleetCameraConfig)

    def city_config(self) -> CityConfig:
        return self.city or CityConfig.preset(self.size)

    def intrinsics(self) -> CameraIntrinsics:
        if self.image_scale == 1.0:
            return KITTI_CAM0
        return KITTI_CAM0.scaled(self.image_scale)

    def validate(self) -> None:
        if self.scenario not in SCENARIOS:
            raise InvalidInputError(f"unknown scenario {self.scenario!r}; use one of {SCENARIOS}")
        kinds, runs = RUN_KINDS, self.runs
        if self.scenario == "indoor":
            kinds, runs = INDOOR_RUN_KINDS, indoor_runs(self.runs)
        bad = [r for r in runs if r not in kinds]
        if bad or not runs or len(set(runs)) != len(runs):
            raise InvalidInputError(
                f"{self.scenario} runs must be distinct names from {kinds}, got {runs}"
            )
        if self.max_frames is not None and self.max_frames < 1:
            raise InvalidInputError(f"max_frames must be >= 1, got {self.max_frames}")
        if not 0.05 <= self.image_scale <= 1.0:
            raise InvalidInputError(f"image_scale must be in [0.05, 1], got {self.image_scale}")
        if self.scenario == "indoor":
            if self.write_stereo:
                raise InvalidInputError(
                    "stereo (image_1) is written for the urban scenario (KITTI layout) only"
                )
            room_configs(self.size) if self.indoor is None else None
            return
        if not self.rig.stereo_baseline_m > 0:
            raise InvalidInputError(
                f"the stereo baseline must be > 0 m, got {self.rig.stereo_baseline_m}"
            )
        CityConfig.preset(self.size) if self.city is None else None
        if self.train_run is not None:
            self.train_run.validate()
        if "fleet" in self.runs:
            self.fleet_camera.validate()
            camera = self.fleet_camera.intrinsics(self.image_scale)
            if camera.distortion is not None:
                lens_remap(camera)  # a lens no pinhole canvas can hold is refused here
        Lighting.preset(self.query_lighting)


def generate_dataset(
    config: GenerateConfig,
    out_dir: Path,
    progress: Callable[[str, int, int], None] | None = None,
) -> DatasetSummary:
    """Write the dataset of ``config`` under ``out_dir``; ``progress(seq_id, done, total)``
    is called as frames are written."""
    config.validate()
    if config.scenario == "indoor":
        return generate_indoor_dataset(config, out_dir, progress)
    return generate_urban_dataset(config, out_dir, progress)
