"""`rvt2 import-rosbag`: real-robot demonstrations (ROS 1 or ROS 2 bags) -> rvt2 episode files.

One bag is one episode, written by `EpisodeWriter` exactly as `rvt2 record` writes a simulated one, so
keyframes, training, rendering and `rvt2 info` work on it unchanged. Its world frame is the robot's
base frame. The first camera's colour stream is the clock (frame t is its t-th image); depth, the
other cameras and the joint states are matched to it by header stamp, and poses are looked up in the
TF tree at those stamps. Images are kept at the frames training uses, as `rvt2 record` keeps them.

Importing is two passes over each bag, each streaming its messages: the first reads everything but
the pixels and checks it all (`plan_import`), the second decodes the images of the observation frames
(raw or compressed, undistorted where the camera has distortion) and writes the episode
(`write_imported_episode`). `import_bags` plans every bag before it writes any, so a bad bag among
several leaves nothing behind.

Options left unset take the defaults of the bag's recorder (`RECORDER_DEFAULTS`): franka_ros2 and
realsense-ros 4.x for a ROS 2 bag, franka_ros and realsense2_camera for a ROS 1 bag.
"""

import re
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from rvt2cli.atomic import check_folder_can_be_made, ensure_folder
from rvt2cli.data import CameraFrame, EpisodeMeta, EpisodeWriter
from rvt2cli.data.provenance import software_versions
from rvt2cli.errors import UserError
from rvt2cli.record.recorder import observation_frames
from rvt2cli.robot import PANDA, RobotFacts
from rvt2cli.rosbag import images
from rvt2cli.rosbag.bagfile import Bag, open_bag
from rvt2cli.rosbag.calibration import Undistortion, camera_matrix, distortion_problem
from rvt2cli.rosbag.messages import CAMERA_INFO, COMPRESSED_IMAGE, IMAGE, JOINT_STATE, TF_MESSAGE
from rvt2cli.rosbag.sync import Stream, common_span, nearest
from rvt2cli.rosbag.tf import StampedTransform, TransformTree

TF, TF_STATIC = "/tf", "/tf_static"
ALIGNED_DEPTH = "aligned_depth_to_color/image_raw"
UNALIGNED_DEPTH = "depth/image_rect_raw"
COMPRESSED, COMPRESSED_DEPTH = "compressed", "compressedDepth"   # image_transport's sub-topics
ENV_ID = "real"
TASK_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]*$")


@dataclass(frozen=True)
class ImportOptions:
    task: str
    instruction: str
    scene_bounds: tuple[float, ...]             # xmin ymin zmin xmax ymax zmax, metres, base frame
    cameras: tuple[str, ...] | None = None      # camera driver topic prefixes; the first is the clock
    colour_topic: str = "color/image_raw"       # relative to each prefix, or absolute (one camera)
    depth_topic: str | None = None              # None: aligned_depth_to_color/image_raw, else depth/image_rect_raw
    camera_info_topic: str = "color/camera_info"
    joint_states: tuple[str, ...] | None = None   # JointState topics, merged joint by joint
    arm_joints: tuple[str, ...] = PANDA.arm_joints
    finger_joints: tuple[str, ...] = PANDA.finger_joints
    base_frame: str = "panda_link0"
    ee_frame: str | None = None
    gripper_threshold: float = 0.07             # m: wider is open (a Panda opens to 0.08)
    sync_tolerance: float = 0.02                # s
    obs_every: int = 10
    voxel_size: float | None = None


@dataclass(frozen=True)
class RecorderDefaults:
    cameras: tuple[str, ...]
    joint_states: tuple[str, ...]
    ee_frame: str


RECORDER_DEFAULTS = {
    2: RecorderDefaults(cameras=("/camera/camera",), joint_states=("/joint_states",), ee_frame="panda_hand_tcp"),
    1: RecorderDefaults(cameras=("/camera",), ee_frame="panda_EE",
                        joint_states=("/franka_state_controller/joint_states", "/franka_gripper/joint_states")),
}


def for_bag(options: ImportOptions, bag: Bag) -> ImportOptions:
    """The options with what was left unset taken from the defaults of the bag's ROS version."""
    defaults = RECORDER_DEFAULTS[bag.ros_version]
    return replace(options, cameras=options.cameras or defaults.cameras,
                   joint_states=options.joint_states or defaults.joint_states, ee_frame=options.ee_frame or defaults.ee_frame)


@dataclass(frozen=True)
class CameraTopics:
    name: str                 # the camera's name in the episode
    prefix: str
    colour: str               # sensor_msgs/Image, or CompressedImage where only that was recorded
    depth: str
    info: str


@dataclass
class ImageStream:
    """The headers of one image topic, by stamp; every image has the stream's frame, size and an
    encoding rvt2 reads (the size of a compressed stream is its first image's)."""

    topic: str
    depth: bool
    stamps: list[int] = field(default_factory=list)
    frame_id: str | None = None
    size: tuple[int, int] | None = None     # width, height


@dataclass
class JointSeries:
    topic: str
    stamps: list[int] = field(default_factory=list)
    positions: list[float] = field(default_factory=list)
    velocities: list[float] = field(default_factory=list)   # NaN where the message had none


@dataclass
class CameraPlan:
    topics: CameraTopics
    size: tuple[int, int]     # width, height
    undistortion: Undistortion   # its intrinsic is rvt2's K of the (undistorted) images
    colour_stamps: np.ndarray  # per observation frame
    depth_stamps: np.ndarray
    cam2world: np.ndarray      # [obs frames, 7], in the base frame


@dataclass
class ImportPlan:
    """Everything about one bag's episode except its pixels, checked."""

    bag: Bag
    options: ImportOptions     # with the bag's recorder defaults filled in
    stamps: np.ndarray         # [T] the clock: the first camera's colour stamps (ns)
    joint_names: list[str]
    joint_positions: np.ndarray   # [T, J]
    joint_velocities: np.ndarray  # [T, J]
    gripper_width: np.ndarray     # [T]
    gripper_command: np.ndarray   # [T] +1 open, -1 closed
    tcp_pose: np.ndarray          # [T, 7] in the base frame
    obs_frames: list[int]
    cameras: list[CameraPlan]
    frames_cut: tuple[int, int]   # colour frames dropped at the start and the end (a stream missing there)

    @property
    def control_hz(self) -> float:
        return (len(self.stamps) - 1) / ((self.stamps[-1] - self.stamps[0]) / 1e9)


# --- options ---------------------------------------------------------------------------------------

def check_options(options: ImportOptions) -> None:
    if not TASK_NAME.match(options.task):
        raise UserError(f"task name {options.task!r} must be letters, digits, '_' or '-' (it names the episode files)")
    if not options.instruction.strip():
        raise UserError("--instruction must say what the robot does, e.g. 'put the red block on the green one'")
    bounds = np.asarray(options.scene_bounds, dtype=np.float64)
    if bounds.shape != (6,) or not np.all(np.isfinite(bounds)) or not np.all(bounds[:3] < bounds[3:]):
        raise UserError(f"--scene-bounds {','.join(map(str, options.scene_bounds))}: need six numbers "
                        "XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX with each minimum below its maximum (metres, base frame)")
    if options.obs_every < 1 or options.sync_tolerance <= 0 or options.gripper_threshold <= 0:
        raise UserError("--obs-every, --sync-tolerance and --gripper-threshold must be positive")
    if options.cameras is not None and len(set(options.cameras)) != len(options.cameras):
        raise UserError(f"--camera lists a prefix twice: {', '.join(options.cameras)}")
    absolute = [t for t in (options.colour_topic, options.depth_topic, options.camera_info_topic) if t and t.startswith("/")]
    if absolute and len(options.cameras or ()) > 1:
        raise UserError(f"absolute topic {absolute[0]} with {len(options.cameras)} cameras: give topics relative to "
                        "the --camera prefixes (e.g. color/image_raw) when importing several cameras")
    overlap = set(options.arm_joints) & set(options.finger_joints)
    if overlap or not options.arm_joints or not options.finger_joints:
        raise UserError("--arm-joints and --finger-joints must each name at least one joint, and no joint twice")


def camera_names(prefixes) -> list[str]:
    """'/camera/camera' -> 'camera'; where two prefixes end alike, the whole prefix ('/a/cam' -> 'a_cam')."""
    last = [p.strip("/").rsplit("/", 1)[-1] for p in prefixes]
    names = last if len(set(last)) == len(last) else [p.strip("/").replace("/", "_") for p in prefixes]
    if any(not n for n in names) or len(set(names)) != len(names):
        raise UserError(f"--camera prefixes {', '.join(prefixes)} do not give distinct camera names; "
                        "use prefixes such as /camera/front and /camera/wrist")
    return names


def _topic(prefix: str, topic: str) -> str:
    return topic if topic.startswith("/") else f"{prefix.rstrip('/')}/{topic}"


def _recorded(bag: Bag, topic: str, compressed: str) -> str:
    """`topic`, or its image_transport sub-topic `compressed` where only that is in the bag: raw wins."""
    return f"{topic}/{compressed}" if not bag.has(topic) and bag.has(f"{topic}/{compressed}") else topic


def _require_images(bag: Bag, topic: str, what: str, hint: str) -> None:
    datatype = COMPRESSED_IMAGE if bag.has(topic) and bag.topics[topic].datatype == COMPRESSED_IMAGE else IMAGE
    bag.require(topic, datatype, what, hint)


def camera_topics(bag: Bag, options: ImportOptions) -> list[CameraTopics]:
    """Each camera's topics in this bag: raw images where recorded, else compressed ones; the depth
    topic falls back to the unaligned one."""
    out = []
    for name, prefix in zip(camera_names(options.cameras), options.cameras):
        depth = _recorded(bag, _topic(prefix, options.depth_topic or ALIGNED_DEPTH), COMPRESSED_DEPTH)
        if options.depth_topic is None and not bag.has(depth):
            depth = _recorded(bag, _topic(prefix, UNALIGNED_DEPTH), COMPRESSED_DEPTH)
            if not bag.has(depth):
                depth = _topic(prefix, ALIGNED_DEPTH)   # for the error message
        topics = CameraTopics(name, prefix, _recorded(bag, _topic(prefix, options.colour_topic), COMPRESSED), depth,
                              _topic(prefix, options.camera_info_topic))
        _require_images(bag, topics.colour, "colour images",
                        "record the camera's colour stream (raw or compressed), or name its prefix with --camera "
                        "(or the topic with --color-topic)")
        _require_images(bag, topics.depth, "depth images",
                        "record depth aligned to colour (realsense: align_depth.enable:=true), or set --depth-topic")
        bag.require(topics.info, CAMERA_INFO, "camera calibration (camera_info)",
                    "record the camera's color/camera_info topic, or set --camera-info-topic")
        out.append(topics)
    return out


# --- pass 1: read and check everything but the pixels ----------------------------------------------

@dataclass
class BagContents:
    """What pass 1 reads: the image streams' headers, the first camera_info of each camera, every
    joint's series and every transform."""

    streams: dict[str, ImageStream]
    camera_info: dict[str, object]
    joints: dict[str, JointSeries]
    transforms: list[StampedTransform]


@dataclass
class Synchronised:
    stamps: np.ndarray                 # the clock after cutting its ends
    matched: dict[str, np.ndarray]     # per image topic and joint name: its message's index at each frame
    image_stamps: dict[str, np.ndarray]  # per image topic: its stamps, sorted (what `matched` indexes)
    frames_cut: tuple[int, int]


def plan_import(path: str | Path, options: ImportOptions) -> ImportPlan:
    """Read and check everything of one bag but its pixels; `options` as given, unset ones are filled
    in from the bag's recorder defaults."""
    bag = open_bag(path)
    options = for_bag(options, bag)
    cameras = camera_topics(bag, options)
    for topic in options.joint_states:
        bag.require(topic, JOINT_STATE, "joint states", "record it, or set --joint-states")
    if not bag.has(TF) and not bag.has(TF_STATIC):
        bag.require(TF, TF_MESSAGE, "transforms", "record /tf and /tf_static")
    for topic in (TF, TF_STATIC):
        if bag.has(topic):
            bag.require(topic, TF_MESSAGE, "transforms", "record /tf and /tf_static")
    contents = read_contents(bag, cameras, options)
    joint_names = list(options.arm_joints) + list(options.finger_joints)
    missing = [j for j in joint_names if j not in contents.joints]
    if missing:
        raise UserError(f"{bag.path}: joint(s) {', '.join(missing)} not found on {', '.join(options.joint_states)} (its joints: "
                        f"{', '.join(contents.joints) or 'none'}); set --arm-joints and --finger-joints to your robot's "
                        "joint names")
    sync = synchronise(bag, contents, cameras[0].colour, joint_names, options)
    clock = sync.stamps

    joints = [contents.joints[j] for j in joint_names]
    positions = np.stack([np.asarray(j.positions)[sync.matched[name]] for j, name in zip(joints, joint_names)], axis=1)
    velocities = np.stack([np.asarray(j.velocities)[sync.matched[name]] for j, name in zip(joints, joint_names)], axis=1)
    seconds = (clock - clock[0]) / 1e9
    for column in range(len(joint_names)):
        if np.isnan(velocities[:, column]).any():   # the messages had no velocities: differentiate
            velocities[:, column] = np.gradient(positions[:, column], seconds)
    arm = len(options.arm_joints)
    width = np.maximum(positions[:, arm:].sum(axis=1), 0.0)
    gripper_open = width > options.gripper_threshold

    tree = TransformTree(contents.transforms, where=str(bag.path), origin_ns=int(clock[0]))
    tcp_pose = tree.lookup(options.base_frame, options.ee_frame, clock, options.sync_tolerance)
    obs = observation_frames(len(clock), gripper_open, velocities[:, :arm], options.obs_every)

    plans = []
    for topics in cameras:
        colour, depth = contents.streams[topics.colour], contents.streams[topics.depth]
        info = contents.camera_info[topics.info]
        _check_camera(bag, topics, colour, depth, info)
        colour_stamps = sync.image_stamps[topics.colour][sync.matched[topics.colour][obs]]
        depth_stamps = sync.image_stamps[topics.depth][sync.matched[topics.depth][obs]]
        cam2world = tree.lookup(options.base_frame, colour.frame_id, colour_stamps, options.sync_tolerance)
        plans.append(CameraPlan(topics, colour.size, Undistortion.of(info, colour.size), colour_stamps, depth_stamps,
                                cam2world))

    return ImportPlan(bag=bag, options=options, stamps=clock, joint_names=joint_names, joint_positions=positions,
                      joint_velocities=velocities, gripper_width=width, gripper_command=np.where(gripper_open, 1.0, -1.0),
                      tcp_pose=tcp_pose, obs_frames=obs, cameras=plans, frames_cut=sync.frames_cut)


def read_contents(bag: Bag, cameras: list[CameraTopics], options: ImportOptions) -> BagContents:
    streams = {c.colour: ImageStream(c.colour, depth=False) for c in cameras}
    streams |= {c.depth: ImageStream(c.depth, depth=True) for c in cameras}
    contents = BagContents(streams=streams, camera_info={}, joints={}, transforms=[])
    topics = set(contents.streams) | {c.info for c in cameras} | set(options.joint_states) | {TF, TF_STATIC}
    for topic, msg, _ in bag.messages(sorted(t for t in topics if bag.has(t))):
        if topic in contents.streams:
            _add_image(bag, contents.streams[topic], msg)
        elif topic in options.joint_states:
            _add_joint_state(bag, contents.joints, msg, topic)
        elif topic in (TF, TF_STATIC):
            contents.transforms.extend(_transforms(msg, static=topic == TF_STATIC))
        else:
            contents.camera_info.setdefault(topic, msg)
    return contents


def synchronise(bag: Bag, contents: BagContents, clock_topic: str, joint_names: list[str],
                options: ImportOptions) -> Synchronised:
    """The clock (the first camera's colour stamps), cut to the time every stream covers, and each
    other stream's message at every frame."""
    image_stamps = {t: np.array(sorted(set(s.stamps)), dtype=np.int64) for t, s in contents.streams.items()}
    clock = image_stamps[clock_topic]
    if len(clock) < 2:
        raise UserError(f"{bag.path}: {clock_topic} has {len(clock)} image(s); a demonstration needs at least two")
    others = {t: Stream(t, stamps) for t, stamps in image_stamps.items() if t != clock_topic}
    others |= {j: Stream(f"{contents.joints[j].topic} ({j})", np.array(contents.joints[j].stamps, dtype=np.int64))
               for j in joint_names}
    tolerance = round(options.sync_tolerance * 1e9)
    first, last = common_span(clock, list(others.values()), tolerance)
    clock = clock[first:last]
    if len(clock) < 2:
        raise UserError(f"{bag.path}: cannot synchronise the streams: fewer than two {clock_topic} images lie within "
                        f"the time every other stream covers (--sync-tolerance {options.sync_tolerance} s)")
    matched = {clock_topic: np.arange(first, last)}   # the clock matches itself
    for key, stream in others.items():
        index, unmatched = nearest(stream, clock, tolerance)
        if unmatched:
            at = (clock[unmatched.frame] - clock[0]) / 1e9
            raise UserError(
                f"{bag.path}: cannot synchronise {stream.name} with {options.cameras[0]}'s colour images: at {at:.3f} s "
                f"(frame {unmatched.frame}) its nearest message is {unmatched.gap_ns / 1e9:.3f} s away (--sync-tolerance "
                f"{options.sync_tolerance} s); raise --sync-tolerance, or record the topic at the camera's rate")
        matched[key] = index
    return Synchronised(clock, matched, image_stamps, (first, len(image_stamps[clock_topic]) - last))


def _add_image(bag: Bag, stream: ImageStream, msg) -> None:
    kind = "depth" if stream.depth else "colour"
    if images.is_compressed(msg):
        problem = images.format_problem(msg, stream.depth)
        if problem:
            raise UserError(f"{bag.path}: {stream.topic} has {problem}: set the camera driver's {kind} format to one of them")
    else:
        allowed = images.DEPTH_ENCODINGS if stream.depth else images.COLOUR_ENCODINGS
        if msg.encoding not in allowed:
            raise UserError(f"{bag.path}: {stream.topic} has image encoding '{msg.encoding}'; rvt2 reads {kind} images as "
                            f"{', '.join(allowed[:-1])} or {allowed[-1]}: set the camera driver's {kind} format to one of them")
        problem = images.layout_problem(msg)
        if problem:
            raise UserError(f"{bag.path}: {stream.topic}: a damaged image ({problem}); record the demonstration again")
    if stream.frame_id is None:
        stream.frame_id, stream.size = msg.header.frame_id, _size(bag, stream, msg)
    size = stream.size if images.is_compressed(msg) else (msg.width, msg.height)   # compressed: checked when decoded
    if (msg.header.frame_id, size) != (stream.frame_id, stream.size):
        raise UserError(f"{bag.path}: {stream.topic} changes frame or size during the recording "
                        f"({stream.frame_id} {stream.size[0]}x{stream.size[1]} -> {msg.header.frame_id} {size[0]}x{size[1]}); "
                        "record one camera configuration per bag")
    stream.stamps.append(images.stamp_ns(msg.header))


def _size(bag: Bag, stream: ImageStream, msg) -> tuple[int, int]:
    try:
        return images.image_size(msg, stream.depth)
    except images.ImageProblem as e:
        raise UserError(f"{bag.path}: {stream.topic}: a damaged image ({e}); record the demonstration again") from None


def _add_joint_state(bag: Bag, joints: dict[str, JointSeries], msg, topic: str) -> None:
    if len(msg.position) != len(msg.name):
        raise UserError(f"{bag.path}: a JointState message names {len(msg.name)} joints but has {len(msg.position)} "
                        "positions; record the joint states again")
    t = images.stamp_ns(msg.header)
    has_velocity = len(msg.velocity) == len(msg.name)
    for i, name in enumerate(msg.name):
        series = joints.setdefault(name, JointSeries(topic))
        if series.stamps and t <= series.stamps[-1]:
            continue   # a repeated or out-of-order stamp
        series.stamps.append(t)
        series.positions.append(float(msg.position[i]))
        series.velocities.append(float(msg.velocity[i]) if has_velocity else float("nan"))


def _transforms(msg, static: bool) -> list[StampedTransform]:
    out = []
    for t in msg.transforms:
        tr, q = t.transform.translation, t.transform.rotation
        out.append(StampedTransform(t.header.frame_id, t.child_frame_id, images.stamp_ns(t.header),
                                    (tr.x, tr.y, tr.z, q.x, q.y, q.z, q.w), static))
    return out


def _check_camera(bag: Bag, topics: CameraTopics, colour: ImageStream, depth: ImageStream, info) -> None:
    if (depth.frame_id, depth.size) != (colour.frame_id, colour.size):
        raise UserError(
            f"{bag.path}: {topics.depth} is in frame '{depth.frame_id}' at {depth.size[0]}x{depth.size[1]}, not in the "
            f"colour camera's '{colour.frame_id}' at {colour.size[0]}x{colour.size[1]}; rvt2 needs depth aligned to colour: "
            f"record with realsense-ros's align_depth.enable:=true ({topics.prefix}/{ALIGNED_DEPTH})")
    K = camera_matrix(info)
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise UserError(f"{bag.path}: {topics.info} has no intrinsics (K is zero: an uncalibrated camera); "
                        "record the camera driver's camera_info")
    problem = distortion_problem(info)
    if problem:
        raise UserError(f"{bag.path}: {topics.info}: {problem}; calibrate the camera with plumb_bob, rational_polynomial or equidistant")
    if (info.width, info.height) not in ((0, 0), colour.size):
        raise UserError(f"{bag.path}: {topics.info} describes a {info.width}x{info.height} camera but {topics.colour} "
                        f"is {colour.size[0]}x{colour.size[1]}; record the camera_info of the same stream")


# --- pass 2: decode the observation frames' images and write the episode --------------------------

def observations(plan: ImportPlan):
    """(frame, the cameras' RGB-D images) at every observation frame, in frame order, as the bag streams
    past: only the frames still waiting for an image are held in memory."""
    wanted: dict[tuple[str, int], list[tuple[int, CameraPlan, str]]] = {}
    for k in range(len(plan.obs_frames)):
        for camera in plan.cameras:
            wanted.setdefault((camera.topics.colour, int(camera.colour_stamps[k])), []).append((k, camera, "rgb"))
            wanted.setdefault((camera.topics.depth, int(camera.depth_stamps[k])), []).append((k, camera, "depth"))
    pending: dict[int, dict[tuple[str, str], np.ndarray]] = {}
    complete = 2 * len(plan.cameras)
    next_k = 0
    topics = sorted({t for c in plan.cameras for t in (c.topics.colour, c.topics.depth)})
    for topic, msg, _ in plan.bag.messages(topics):
        decoded = None
        for k, camera, kind in wanted.pop((topic, images.stamp_ns(msg.header)), []):
            if decoded is None:
                decoded = _decode(plan.bag, topic, msg, camera, kind)
            pending.setdefault(k, {})[(camera.topics.name, kind)] = decoded
        while next_k < len(plan.obs_frames) and len(pending.get(next_k, ())) == complete:
            got = pending.pop(next_k)
            yield plan.obs_frames[next_k], {
                c.topics.name: CameraFrame(rgb=got[(c.topics.name, "rgb")], depth=got[(c.topics.name, "depth")],
                                           intrinsic=c.undistortion.intrinsic, cam2world=c.cam2world[next_k])
                for c in plan.cameras}
            next_k += 1
        if next_k == len(plan.obs_frames):
            return   # the rest of the bag holds no image that is kept
    if next_k < len(plan.obs_frames):
        raise UserError(f"{plan.bag.path}: the images of frame {plan.obs_frames[next_k]} were not found on the second read "
                        "of the bag (did it change meanwhile?); import it again")


def _decode(bag: Bag, topic: str, msg, camera: CameraPlan, kind: str) -> np.ndarray:
    """One image's pixels, undistorted: RGB uint8 or depth in metres."""
    try:
        pixels = images.colour_rgb(msg) if kind == "rgb" else images.depth_metres(msg)
    except images.ImageProblem as e:
        raise UserError(f"{bag.path}: {topic}: a damaged image ({e}); record the demonstration again") from None
    if (pixels.shape[1], pixels.shape[0]) != camera.size:
        raise UserError(f"{bag.path}: {topic} changes size during the recording ({camera.size[0]}x{camera.size[1]} -> "
                        f"{pixels.shape[1]}x{pixels.shape[0]}); record one camera configuration per bag")
    return camera.undistortion.colour(pixels) if kind == "rgb" else camera.undistortion.depth(pixels)



def write_imported_episode(plan: ImportPlan, path: Path, index: int) -> Path:
    options = plan.options
    with EpisodeWriter(path, plan.control_hz) as writer:
        writer.write_instruction(options.instruction, options.task, 0, {})
        for t in range(len(plan.stamps)):
            writer.write_frame(t, joint_names=plan.joint_names, joint_positions=plan.joint_positions[t],
                               joint_velocities=plan.joint_velocities[t], gripper_width=plan.gripper_width[t],
                               gripper_command=plan.gripper_command[t], action=None, contacts=[], tcp_pose=plan.tcp_pose[t])
        for frame, cameras in observations(plan):
            writer.write_observation(frame, cameras)
        width, height = plan.cameras[0].size
        robot = RobotFacts(arm_joints=tuple(options.arm_joints), finger_joints=tuple(options.finger_joints),
                           tcp_link=options.ee_frame)
        meta = EpisodeMeta(
            task=options.task, env_id=ENV_ID, seed=index, success=True, expert=f"rosbag:{plan.bag.name}",
            num_frames=len(plan.stamps), control_hz=plan.control_hz, scene_bounds=[float(v) for v in options.scene_bounds],
            cameras=[c.topics.name for c in plan.cameras], instruction=options.instruction,
            versions=software_versions("rosbags", "opencv-python", "numpy"), obs_frames=writer.obs_frames,
            voxel_size=options.voxel_size,
            extra={"source": "rosbag", "bag": str(plan.bag.path), "image_size": int(width), "image_height": int(height),
                   "robot": robot.to_json(), "base_frame": options.base_frame, "joint_states": list(options.joint_states),
                   "cameras": {c.topics.name: {"colour": c.topics.colour, "depth": c.topics.depth, "camera_info": c.topics.info}
                               for c in plan.cameras},
                   "start_stamp_ns": int(plan.stamps[0]), "frames_cut": list(plan.frames_cut),
                   "gripper_threshold": options.gripper_threshold, "sync_tolerance": options.sync_tolerance},
        )
        return writer.finish(meta)


# --- several bags ---------------------------------------------------------------------------------

def next_episode_paths(out_dir: Path, task: str, count: int) -> list[tuple[int, Path]]:
    """`count` new (index, path) pairs after the task's highest existing index: nothing is overwritten."""
    pattern = re.compile(rf"^{re.escape(task)}_(\d+)\.mcap$")
    taken = [int(m.group(1)) for p in out_dir.iterdir() if (m := pattern.match(p.name))]
    start = max(taken, default=-1) + 1
    return [(i, out_dir / f"{task}_{i:04d}.mcap") for i in range(start, start + count)]


@dataclass
class ImportResult:
    bag: Path
    path: Path
    frames: int
    obs_frames: int
    control_hz: float
    frames_cut: tuple[int, int]


def import_bags(bags, out_dir: str | Path, options: ImportOptions) -> list[ImportResult]:
    """Import every bag (one episode each) into `out_dir`; check all of them before writing any, and
    keep none of this call's files if one fails to write."""
    check_options(options)
    if not bags:
        raise UserError("give at least one bag (a ROS 1 .bag, a rosbag2 folder, or one .db3 or .mcap file)")
    check_folder_can_be_made(out_dir)
    plans = [plan_import(bag, options) for bag in bags]
    out_dir = ensure_folder(out_dir)
    results: list[ImportResult] = []
    try:
        for plan, (index, path) in zip(plans, next_episode_paths(out_dir, options.task, len(plans))):
            write_imported_episode(plan, path, index)
            results.append(ImportResult(plan.bag.path, path, len(plan.stamps), len(plan.obs_frames), plan.control_hz,
                                        plan.frames_cut))
    except BaseException:
        for result in results:
            result.path.unlink(missing_ok=True)
        raise
    return results
