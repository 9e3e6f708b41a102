"""The urban scenario: a seeded, KITTI-like city driven by a car, written in the KITTI
odometry layout.

- ``street_grid``, ``city``: districts of streets and the city made of them; ``district``,
  ``buildings``, ``street_props``: one district's static scene (ground, roads,
  buildings, lamps, trees, signs, parked cars).
- ``facades``, ``street_textures``: texture generators; ``textures``: their registry.
- ``routes``: walks over a street grid and the lane-centre paths along them.
- ``runs``: the runs of a dataset (map, query, train, night, off-centre); ``record``:
  recording one run; ``info``: dataset.json and the world frame; ``generate``: the
  whole dataset; ``preview``: a one-page look at it.
"""
