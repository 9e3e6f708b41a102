"""The synthetic world monoloc is developed, tested and benchmarked on.

Layers, generic first (reused by every scenario):

- ``monoloc.sim.scene``: a scene is a set of textured planar quads in a z-up world plus lights;
  textures are generated lazily and deterministically from small specs.
- ``monoloc.sim.render``: rasterises a scene for a pinhole camera (texture, depth, quad id).
- ``monoloc.sim.camera`` / ``monoloc.sim.lidar``: photometric camera model and a spinning LiDAR.
- ``monoloc.sim.vehicle``: kinematic bicycle model, pure-pursuit controller, measured signals.
- ``monoloc.sim.recording``: the errors a real recording carries (``RecordingErrors``).

Scenario builders on top: ``monoloc.sim.city`` (outdoor, KITTI-like), and the writers
and the orchestration in ``monoloc.sim.kitti_writer`` and ``monoloc.sim.generate``; the
CLI is ``monoloc.sim.cli``.
"""
