"""What the vehicle, the server and the sim share: errors, camera, planar geometry, the
measurement model and its fit, dataset formats. Light: numpy only."""
