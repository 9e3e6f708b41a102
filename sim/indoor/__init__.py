"""The indoor scenario: rooms with a taped race track for a 1:10 car with an RGB-D
camera, written in the TUM RGB-D layout.

- ``room``: a room's settings and bounds; ``track``: the race track and laps on it;
  ``world``: the rooms built (floor, ceiling, walls); ``furniture``, ``infield``:
  furniture along the walls, objects inside the loop, movable obstacles.
- ``canvas``, ``units``: drawing in metres on a texture; ``wall_textures``,
  ``floor_textures``, ``surface_textures``: texture generators; ``textures``: their
  registry.
- ``sensors``: the RGB-D camera, motion capture and their errors; ``plan``: settings
  and the runs; ``generate``: the whole dataset; ``info``: its dataset.json;
  ``preview``: a one-page look at it.
"""
