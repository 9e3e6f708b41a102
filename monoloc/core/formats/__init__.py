"""Dataset text formats, one module per format family, each a set of read/write pairs:
``kitti`` (poses/NN.txt, times.txt, calib.txt), ``tum`` (groundtruth.txt and other TUM
trajectories, rgb.txt / depth.txt file lists) and ``vehicle`` (vehicle.txt, the measured
speed and yaw rate). Readers take a path or an open text handle and raise
``monoloc.core.errors.InputFileError`` (an ``InvalidInputError``) naming the file and the
line; writers take an open text handle. Numpy only, like the rest of ``monoloc.core``."""
