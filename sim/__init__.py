"""The synthetic world monoloc is developed, tested and benchmarked on.

Layers, generic first (reused by every scenario):

- ``sim.scene``: a scene is a set of textured planar quads in a z-up world plus lights;
  textures are generated lazily and deterministically from small specs.
- ``sim.render``: rasterises a scene for a pinhole camera (texture, depth, quad id).
- ``sim.camera`` / ``sim.lidar``: photometric camera model and a spinning LiDAR.
- ``sim.vehicle``: kinematic bicycle model, pure-pursuit controller, measured signals.
- ``sim.recording``: the errors a real recording carries (``RecordingErrors``).

Scenario builders on top: ``sim.city`` (outdoor, KITTI-like), and the writers and the
orchestration in ``sim.kitti_writer`` and ``sim.generate``; the CLI is ``sim.cli``.
"""
