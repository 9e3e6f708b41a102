"""The synthetic world monoloc is developed, tested and benchmarked on.

Layers, generic first (reused by every scenario):

- ``monoloc.sim.scene``: a scene is a set of textured planar quads in a z-up world plus lights.
- ``monoloc.sim.textures``: texture specs and the bank that makes their pixels lazily and
  deterministically from a scenario's registry of generators; ``monoloc.sim.texture_tools``:
  the photo library and pixel helpers generators share.
- ``monoloc.sim.shapes``: walls, boxes and billboards made of quads.
- ``monoloc.sim.render``: rasterises a scene for a pinhole camera (texture, depth, quad id).
- ``monoloc.sim.camera`` / ``monoloc.sim.lidar``: photometric camera model and a spinning LiDAR.
- ``monoloc.sim.path`` / ``monoloc.sim.vehicle``: planar paths; kinematic bicycle model,
  pure-pursuit controller, measured signals.
- ``monoloc.sim.recording``: the errors a real recording carries (``RecordingErrors``).
- ``monoloc.sim.kitti_writer`` / ``monoloc.sim.tum_writer``: the two dataset layouts.

Scenarios on top, one package each: ``monoloc.sim.urban`` (a KITTI-like city, KITTI
layout) and ``monoloc.sim.indoor`` (rooms with a 1:10 race track, TUM RGB-D layout).

Orchestration: ``monoloc.sim.generate`` (``GenerateConfig``, ``generate_dataset``) hands a
config to its scenario and gets a ``monoloc.sim.summary.DatasetSummary`` back;
``monoloc.sim.preview`` draws a dataset; the CLI is ``monoloc.sim.cli``.
"""
