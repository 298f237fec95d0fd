"""ROS 2 bags (MCAP) <-> rvt2 episodes, without a ROS installation.

- `importer`: `rvt2 import-rosbag`, real-robot demonstrations -> episode files (docs/REAL_ROBOT.md);
- `from_episode`: a recorded episode -> the bag a real robot with realsense cameras would have recorded
  (to test the importer against the simulator's ground truth);
- `bagfile` (opening bags), `msgdefs` (the ROS 2 message definitions), `images` (Image and CameraInfo
  <-> numpy), `tf` (the TF tree and lookups through it), `sync` (matching streams by stamp).
"""
