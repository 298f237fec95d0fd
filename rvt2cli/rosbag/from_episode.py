"""Write a recorded rvt2 episode as the bag a real robot would have recorded.

By default the bag looks like `ros2 bag record` with a Franka Panda (franka_ros2) and realsense-ros
4.x cameras; `FRANKA_ROS` makes it look like ROS 1's `rosbag record` with franka_ros and
realsense2_camera. It is written with `rosbags`' writers and the standard messages of ROS 2 Humble
or Jazzy, or ROS 1 Noetic, as a `.bag`, an `.mcap` or `.db3` file, or a rosbag2 folder:

    /tf_static            world -> panda_link0 (the robot base in the simulator's world), each camera's
                          mount (its hand-eye calibration: panda_link0 -> NAME_link for a fixed camera,
                          panda_hand_tcp -> NAME_link for one that rides on the hand) and
                          NAME_link -> NAME_color_optical_frame (realsense-ros's optical rotation)
    /tf                   panda_link0 -> panda_hand_tcp at every frame (and a camera that moves otherwise)
    /joint_states         sensor_msgs/JointState: the episode's joints, positions and velocities (with
                          two topics, as franka_ros: the arm's on the first, the fingers' on the second)
    /camera/NAME/color/image_raw, /camera/NAME/aligned_depth_to_color/image_raw, /camera/NAME/color/camera_info
                          (and, with `compressed`, .../color/image_raw/compressed as JPEG or PNG and
                          .../aligned_depth_to_color/image_raw/compressedDepth as a 16-bit PNG)

All stamped `start_ns + frame / control_hz`. The episode needs images at every frame (record it with
`RecordOptions(obs_every=1)`, `rvt2 record --obs-every 1`): a camera publishes every frame. Used to
test `rvt2 import-rosbag` against the simulator's ground truth, and to try a ROS 2 pipeline on
simulated demonstrations.
"""

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from rvt2cli.data import Episode, read_episode
from rvt2cli.errors import UserError
from rvt2cli.robot import PANDA
from rvt2cli.rosbag import images
from rvt2cli.rosbag.bagwriter import BagWriter
from rvt2cli.rosbag.messages import CAMERA_INFO, COMPRESSED_IMAGE, IMAGE, JOINT_STATE, TF_MESSAGE
from rvt2cli.rosbag.tf import Transforms

# The pose of a realsense optical frame (x right, y down, z forward) in its camera frame (x forward, y left, z up).
OPTICAL_IN_LINK = (0.0, 0.0, 0.0, -0.5, 0.5, -0.5, 0.5)
# ManiSkill's tabletop scenes put the Panda's base at x = -0.615 in the world, unrotated.
PANDA_BASE_IN_SIM_WORLD = (-0.615, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
RIGID = 1e-4   # m / rad: a camera whose mount moves less than this is fixed to it


@dataclass(frozen=True)
class BagOptions:
    colour_encoding: str = "rgb8"        # or bgr8
    depth_encoding: str = "32FC1"        # or 16UC1 (millimetres, as realsense-ros publishes)
    raw: bool = True                     # publish image_raw
    compressed: str | None = None        # also publish image_raw/compressed ("jpeg" or "png") and compressedDepth
    distro: str | None = None            # humble or jazzy (ROS 2), noetic (ROS 1); None: by the file's suffix
    storage: str = "mcap"                # of a rosbag2 folder: mcap or sqlite3
    camera_prefix: str = "/camera/{name}"   # realsense-ros: camera_namespace/camera_name
    joint_states: tuple[str, ...] = ("/joint_states",)
    world_frame: str = "world"
    base_frame: str = "panda_link0"
    ee_frame: str = "panda_hand_tcp"
    base_in_world: tuple = PANDA_BASE_IN_SIM_WORLD
    start_ns: int = 1_700_000_000 * 1_000_000_000   # a plausible wall-clock start


def camera_frames(name: str) -> tuple[str, str]:
    """realsense-ros's frame names for a camera called `name`: its body and its colour optical frame."""
    return f"{name}_link", f"{name}_color_optical_frame"


# ROS 1: franka_ros (the arm's joints from franka_state_controller, the fingers' from franka_gripper, the
# hand's TCP as panda_EE) and realsense2_camera (camera NAME's topics under /NAME).
FRANKA_ROS = BagOptions(distro="noetic", camera_prefix="/{name}", ee_frame="panda_EE",
                        joint_states=("/franka_state_controller/joint_states", "/franka_gripper/joint_states"))


def _is_constant(poses: Transforms) -> bool:
    first = Transforms(poses.rotation[:1], poses.translation[:1])
    moved = first.inv() * poses
    return bool(np.abs(moved.translation).max() < RIGID and moved.rotation.magnitude().max() < RIGID)


def _camera_mounts(ep: Episode, frames: list[dict], world_to_base: Transforms, tcp_in_base: Transforms, options: BagOptions):
    """Per camera: (parent frame, its link's pose in the parent [T, 7], static?)."""
    mounts = {}
    optical_in_link = Transforms.from_poses(OPTICAL_IN_LINK)
    for name in ep.meta.cameras:
        optical_in_base = world_to_base * Transforms.from_poses([f[name].cam2world for f in frames])
        link_in_base = optical_in_base * optical_in_link.inv()
        link_in_tcp = tcp_in_base.inv() * link_in_base
        if _is_constant(link_in_base):
            mounts[name] = (options.base_frame, link_in_base.poses(), True)
        elif _is_constant(link_in_tcp):
            mounts[name] = (options.ee_frame, link_in_tcp.poses(), True)
        else:
            mounts[name] = (options.base_frame, link_in_base.poses(), False)
    return mounts


def write_episode_bag(episode: str | Path | Episode, out: str | Path, options: BagOptions = BagOptions()) -> Path:
    """Write `episode` as a bag: a ROS 1 bag if `out` ends in .bag, one rosbag2 file if it ends in .mcap
    or .db3, else a rosbag2 folder. Atomic: nothing appears under `out` until it is complete."""
    ep = episode if isinstance(episode, Episode) else read_episode(episode)
    n = ep.num_frames
    if ep.obs_frames != list(range(n)):
        raise UserError(f"{ep.path}: has images at {len(ep.obs_frames)} of its {n} frames; a bag needs them at every "
                        "frame: record with `rvt2 record --obs-every 1` (RecordOptions(obs_every=1))")
    if options.colour_encoding not in images.COLOUR_ENCODINGS or options.depth_encoding not in images.DEPTH_ENCODINGS:
        raise UserError(f"bag encodings {options.colour_encoding}/{options.depth_encoding}: colour must be one of "
                        f"{', '.join(images.COLOUR_ENCODINGS)} and depth one of {', '.join(images.DEPTH_ENCODINGS)}")
    out = Path(out)
    distro = options.distro or ("noetic" if out.suffix == ".bag" else "humble")
    with BagWriter(out, distro, options.storage) as bag:
        _write_messages(bag, ep, replace(options, distro=distro))
    return out


def _joint_topics(names: list[str], options: BagOptions) -> list[tuple[str, list[int]]]:
    """(topic, the indices of its joints): all on one topic, or the arm's on the first and the fingers' on the second."""
    if len(options.joint_states) == 1:
        return [(options.joint_states[0], list(range(len(names))))]
    fingers = [i for i, name in enumerate(names) if name in PANDA.finger_joints]
    arm = [i for i in range(len(names)) if i not in fingers]
    return [(options.joint_states[0], arm), (options.joint_states[1], fingers)]


def _write_messages(bag: BagWriter, ep: Episode, options: BagOptions) -> None:
    msgs = bag.messages
    n = ep.num_frames
    stamps = [options.start_ns + round(t * 1e9 / ep.meta.control_hz) for t in range(n)]
    frames = [ep.cameras(t) for t in range(n)]
    world_to_base = Transforms.from_poses(options.base_in_world).inv()
    tcp_in_base = world_to_base * Transforms.from_poses(ep.robot.tcp_pose)
    mounts = _camera_mounts(ep, frames, world_to_base, tcp_in_base, options)
    prefixes = {name: options.camera_prefix.format(name=name) for name in ep.meta.cameras}
    joint_topics = _joint_topics(list(ep.robot.joint_names), options)

    static = [(options.world_frame, options.base_frame, options.base_in_world, stamps[0])]
    for name, (parent, poses, is_static) in mounts.items():
        link, optical = camera_frames(name)
        static.append((link, optical, OPTICAL_IN_LINK, stamps[0]))
        if is_static:
            static.append((parent, link, poses[0], stamps[0]))
    bag.write("/tf_static", TF_MESSAGE, msgs.transforms(static), stamps[0])

    tcp_poses = tcp_in_base.poses()
    for t, t_ns in enumerate(stamps):
        dynamic = [(options.base_frame, options.ee_frame, tcp_poses[t], t_ns)]
        dynamic += [(parent, camera_frames(name)[0], poses[t], t_ns)
                    for name, (parent, poses, is_static) in mounts.items() if not is_static]
        bag.write("/tf", TF_MESSAGE, msgs.transforms(dynamic), t_ns)
        for topic, joints in joint_topics:
            bag.write(topic, JOINT_STATE, msgs.joint_state([ep.robot.joint_names[i] for i in joints],
                                                           ep.robot.joint_positions[t, joints],
                                                           ep.robot.joint_velocities[t, joints], t_ns), t_ns)
        for name, camera in frames[t].items():
            optical = camera_frames(name)[1]
            colour, depth = f"{prefixes[name]}/color/image_raw", f"{prefixes[name]}/aligned_depth_to_color/image_raw"
            h, w = camera.depth.shape
            if options.raw:
                bag.write(colour, IMAGE, msgs.image(camera.rgb, options.colour_encoding, t_ns, optical), t_ns)
                bag.write(depth, IMAGE, msgs.image(camera.depth, options.depth_encoding, t_ns, optical), t_ns)
            if options.compressed:
                bag.write(f"{colour}/compressed", COMPRESSED_IMAGE,
                          msgs.compressed_colour(camera.rgb, options.compressed, t_ns, optical), t_ns)
                bag.write(f"{depth}/compressedDepth", COMPRESSED_IMAGE, msgs.compressed_depth(camera.depth, t_ns, optical), t_ns)
            bag.write(f"{prefixes[name]}/color/camera_info", CAMERA_INFO, msgs.camera_info(camera.intrinsic, w, h, t_ns, optical),
                      t_ns)
