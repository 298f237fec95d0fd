"""Write a recorded rvt2 episode as the ROS 2 bag a real robot would have recorded.

The bag looks like `ros2 bag record -s mcap` with a Franka Panda and realsense-ros 4.x cameras:

    /tf_static            world -> panda_link0 (the robot base in the simulator's world), each camera's
                          mount (its hand-eye calibration: panda_link0 -> NAME_link for a fixed camera,
                          panda_hand_tcp -> NAME_link for one that rides on the hand) and
                          NAME_link -> NAME_color_optical_frame (realsense-ros's optical rotation)
    /tf                   panda_link0 -> panda_hand_tcp at every frame (and a camera that moves otherwise)
    /joint_states         sensor_msgs/JointState: the episode's joints, positions and velocities
    /camera/NAME/color/image_raw, /camera/NAME/aligned_depth_to_color/image_raw, /camera/NAME/color/camera_info

All stamped `start_ns + frame / control_hz`. The episode needs images at every frame (record it with
`RecordOptions(obs_every=1)`, `rvt2 record --obs-every 1`): a camera publishes every frame. Used to
test `rvt2 import-rosbag` against the simulator's ground truth, and to try a ROS 2 pipeline on
simulated demonstrations.
"""

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rvt2cli.atomic import temp_path_for
from rvt2cli.data import Episode, read_episode
from rvt2cli.errors import UserError
from rvt2cli.rosbag import images, msgdefs
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
    camera_prefix: str = "/camera/{name}"   # realsense-ros: camera_namespace/camera_name
    joint_states: str = "/joint_states"
    world_frame: str = "world"
    base_frame: str = "panda_link0"
    ee_frame: str = "panda_hand_tcp"
    base_in_world: tuple = PANDA_BASE_IN_SIM_WORLD
    start_ns: int = 1_700_000_000 * 1_000_000_000   # a plausible wall-clock start


def camera_frames(name: str) -> tuple[str, str]:
    """realsense-ros's frame names for a camera called `name`: its body and its colour optical frame."""
    return f"{name}_link", f"{name}_color_optical_frame"


def _transform(parent: str, child: str, pose, t_ns: int) -> dict:
    x, y, z, qx, qy, qz, qw = (float(v) for v in pose)
    return {"header": {"stamp": images.stamp(t_ns), "frame_id": parent}, "child_frame_id": child,
            "transform": {"translation": {"x": x, "y": y, "z": z}, "rotation": {"x": qx, "y": qy, "z": qz, "w": qw}}}


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
    """Write `episode` as a ROS 2 bag: one `.mcap` file if `out` ends in .mcap, else a rosbag2 folder
    (`metadata.yaml` and `NAME_0.mcap`). Atomic: nothing appears under `out` until it is complete."""
    ep = episode if isinstance(episode, Episode) else read_episode(episode)
    n = ep.num_frames
    if ep.obs_frames != list(range(n)):
        raise UserError(f"{ep.path}: has images at {len(ep.obs_frames)} of its {n} frames; a bag needs them at every "
                        "frame: record with `rvt2 record --obs-every 1` (RecordOptions(obs_every=1))")
    if options.colour_encoding not in images.COLOUR_ENCODINGS or options.depth_encoding not in images.DEPTH_ENCODINGS:
        raise UserError(f"bag encodings {options.colour_encoding}/{options.depth_encoding}: colour must be one of "
                        f"{', '.join(images.COLOUR_ENCODINGS)} and depth one of {', '.join(images.DEPTH_ENCODINGS)}")
    out = Path(out)
    single_file = out.suffix == ".mcap"
    tmp = temp_path_for(out)
    mcap_path = tmp if single_file else tmp / f"{out.name}_0.mcap"
    if not single_file:
        tmp.mkdir(parents=True)
    try:
        counts = _write_mcap(ep, mcap_path, options)
        if not single_file:
            _write_metadata(tmp, mcap_path.name, counts, ep, options)
        os.replace(tmp, out)
    except BaseException:
        _remove(tmp)
        raise
    return out


def _write_mcap(ep: Episode, path: Path, options: BagOptions) -> dict[str, tuple[str, int]]:
    """The bag's messages; returns each topic's type and message count."""
    from mcap_ros2.writer import Writer

    n = ep.num_frames
    stamps = [options.start_ns + round(t * 1e9 / ep.meta.control_hz) for t in range(n)]
    frames = [ep.cameras(t) for t in range(n)]
    world_to_base = Transforms.from_poses(options.base_in_world).inv()
    tcp_in_base = world_to_base * Transforms.from_poses(ep.robot.tcp_pose)
    mounts = _camera_mounts(ep, frames, world_to_base, tcp_in_base, options)
    prefixes = {name: options.camera_prefix.format(name=name) for name in ep.meta.cameras}
    counts: dict[str, tuple[str, int]] = {}

    with open(path, "wb") as stream:
        writer = Writer(stream)
        schemas = {datatype: writer.register_msgdef(datatype, msgdefs.full_definition(datatype))
                   for datatype in (msgdefs.IMAGE, msgdefs.CAMERA_INFO, msgdefs.JOINT_STATE, msgdefs.TF_MESSAGE)}

        def write(topic: str, datatype: str, message: dict, t_ns: int) -> None:
            writer.write_message(topic, schemas[datatype], message, log_time=t_ns, publish_time=t_ns)
            counts[topic] = (datatype, counts.get(topic, (datatype, 0))[1] + 1)

        static = [_transform(options.world_frame, options.base_frame, options.base_in_world, stamps[0])]
        for name, (parent, poses, is_static) in mounts.items():
            link, optical = camera_frames(name)
            static.append(_transform(link, optical, OPTICAL_IN_LINK, stamps[0]))
            if is_static:
                static.append(_transform(parent, link, poses[0], stamps[0]))
        write("/tf_static", msgdefs.TF_MESSAGE, {"transforms": static}, stamps[0])

        tcp_poses = tcp_in_base.poses()
        for t, t_ns in enumerate(stamps):
            dynamic = [_transform(options.base_frame, options.ee_frame, tcp_poses[t], t_ns)]
            dynamic += [_transform(parent, camera_frames(name)[0], poses[t], t_ns)
                        for name, (parent, poses, is_static) in mounts.items() if not is_static]
            write("/tf", msgdefs.TF_MESSAGE, {"transforms": dynamic}, t_ns)
            write(options.joint_states, msgdefs.JOINT_STATE, {
                "header": {"stamp": images.stamp(t_ns), "frame_id": ""}, "name": list(ep.robot.joint_names),
                "position": [float(v) for v in ep.robot.joint_positions[t]],
                "velocity": [float(v) for v in ep.robot.joint_velocities[t]], "effort": []}, t_ns)
            for name, camera in frames[t].items():
                optical = camera_frames(name)[1]
                h, w = camera.depth.shape
                write(f"{prefixes[name]}/color/image_raw", msgdefs.IMAGE,
                      images.image_message(camera.rgb, options.colour_encoding, t_ns, optical), t_ns)
                write(f"{prefixes[name]}/aligned_depth_to_color/image_raw", msgdefs.IMAGE,
                      images.image_message(camera.depth, options.depth_encoding, t_ns, optical), t_ns)
                write(f"{prefixes[name]}/color/camera_info", msgdefs.CAMERA_INFO,
                      images.camera_info_message(camera.intrinsic, w, h, t_ns, optical), t_ns)
        writer.finish()
    return counts


def _write_metadata(folder: Path, file_name: str, counts: dict[str, tuple[str, int]], ep: Episode, options: BagOptions) -> None:
    """rosbag2's metadata.yaml (format version 5, as ROS 2 Humble writes it)."""
    import yaml

    start = options.start_ns
    duration = round((ep.num_frames - 1) * 1e9 / ep.meta.control_hz)
    total = sum(count for _, count in counts.values())
    info = {
        "version": 5,
        "storage_identifier": "mcap",
        "duration": {"nanoseconds": duration},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": total,
        "topics_with_message_count": [
            {"topic_metadata": {"name": topic, "type": datatype, "serialization_format": "cdr", "offered_qos_profiles": ""},
             "message_count": count}
            for topic, (datatype, count) in sorted(counts.items())],
        "compression_format": "",
        "compression_mode": "",
        "relative_file_paths": [file_name],
        "files": [{"path": file_name, "starting_time": {"nanoseconds_since_epoch": start},
                   "duration": {"nanoseconds": duration}, "message_count": total}],
    }
    (folder / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False))


def _remove(path: Path) -> None:
    if path.is_dir():
        for child in path.iterdir():
            child.unlink()
        path.rmdir()
    else:
        path.unlink(missing_ok=True)
