"""The recording formats, one module per format, each the one home of reading and writing
its files: ``kitti`` (KITTI odometry: poses/NN.txt, times.txt, calib.txt, velodyne scans,
the sequence layout, a sequence opened as a mapping run), ``tum`` (TUM RGB-D:
trajectories, rgb.txt / depth.txt file lists, depth images' encoding, camera.json, the
association of a run's images and ground truth, a run opened as a mapping run),
``rosbag`` (ROS bags' messages, a bag opened as a mapping run, the pose bag a drive
writes), ``vehicle`` (vehicle.txt, the measured speed and yaw rate), ``camera_yaml``
(a run's camera.yaml in ROS's calibration layout: intrinsics, lens, mounting) and
``png`` (an image's size from its header).

The sim writes these layouts, the server ingests them (``monoloc.server.ingest.sources``
adds image decoding and the 3D sources), the vehicle replays them. Readers take a path or
an open text handle and raise ``monoloc.core.errors.InputFileError`` (an
``InvalidInputError``) naming the file and the line; text writers take an open text
handle. Numpy only, like the rest of ``monoloc.core`` (``rosbags`` is imported when a bag
is opened); pixels are decoded and encoded by the callers (OpenCV, Pillow)."""
