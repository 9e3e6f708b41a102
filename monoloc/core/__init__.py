"""What the vehicle, the server and the sim share: errors, camera, planar geometry, the
measurement model and its fit, dataset formats, the geographic reference of a map (geo).
Light: numpy (and pymap3d, pure Python, for geo)."""
