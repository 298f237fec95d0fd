"""Camera frames in, the next keyframe out, with rvt2's deployment API (rvt2cli.deploy).

    python examples/deploy_from_frames.py POLICY EPISODE.mcap [FRAME]

POLICY is a run folder, a checkpoint or an `rvt2 export` folder. The RGB-D frames here come from a
recorded episode, to have something to show; on a robot they come from the cameras, with intrinsics as
the camera driver publishes them (OpenCV/ROS convention) and camera-to-base poses from a hand-eye
calibration. Prints the keyframe as JSON.
"""

import json
import sys

from rvt2cli.data import read_episode
from rvt2cli.data.fusion import intrinsic_to_opencv
from rvt2cli.deploy import CameraFrame, KeyframePolicy

policy_path, episode_path = sys.argv[1], sys.argv[2]
frame = int(sys.argv[3]) if len(sys.argv) > 3 else 0

episode = read_episode(episode_path)
cameras = {
    name: CameraFrame(rgb=cam.rgb,                                       # uint8 [H, W, 3]
                      depth=(cam.depth * 1000).round().astype("uint16"),  # millimetres, as RealSense gives them
                      intrinsic=intrinsic_to_opencv(cam.intrinsic),       # K as the camera driver publishes it
                      cam2world=cam.cam2world)                            # camera pose in the base frame, x y z qx qy qz qw
    for name, cam in episode.cameras(frame).items()
}
fingers = episode.meta.robot.fingers(episode.robot.joint_positions[frame], episode.robot.joint_names)

policy = KeyframePolicy.load(policy_path)
keyframe = policy.predict(cameras, instruction=episode.instruction["text"], gripper_open=episode.robot.gripper_command[frame] > 0,
                          finger_positions=fingers, keyframes_done=0, task=episode.meta.task)
print(json.dumps({"position": keyframe.position, "quaternion_xyzw": keyframe.quaternion,
                  "gripper_open": keyframe.gripper_open, "ignore_collisions": keyframe.ignore_collisions}))
