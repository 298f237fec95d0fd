"""Robot bags (ROS 1 .bag, ROS 2 sqlite3 or MCAP) <-> rvt2 episodes, without a ROS installation.

- `importer`: `rvt2 import-rosbag`, real-robot demonstrations -> episode files (docs/REAL_ROBOT.md);
- `from_episode`: a recorded episode -> the bag a real robot with RealSense cameras would have recorded
  (to test the importer against the simulator's ground truth);
- `bagfile` (opening and reading bags with `rosbags`), `bagwriter` (writing them), `messages` (the
  message types, built for one ROS distribution), `images` (Image and CompressedImage -> numpy),
  `calibration` (CameraInfo -> pinhole intrinsics, undistorting), `tf` (the TF tree and lookups
  through it), `sync` (matching streams by stamp).
"""
