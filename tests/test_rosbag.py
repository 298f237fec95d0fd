"""`rvt2 import-rosbag` against the simulator's ground truth: a recorded episode is written as the bag a
real robot with realsense cameras would have recorded (by `rosbags`' writers: ROS 2 Humble and Jazzy in
MCAP and sqlite3, ROS 1 Noetic), imported back, and compared; and every kind of bad bag is refused in
one line, leaving nothing behind."""

import shutil
import sqlite3
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from conftest import TINY_TRAIN, assert_one_line_error, run_cli
from rvt2cli.data import CameraFrame, read_episode
from rvt2cli.data.fusion import camera_points
from rvt2cli.keyframes.extract import annotate
from rvt2cli.record.recorder import RecordOptions, observation_frames, record
from rvt2cli.rosbag.bagfile import open_bag
from rvt2cli.rosbag.bagwriter import BagWriter
from rvt2cli.rosbag.calibration import Undistortion
from rvt2cli.rosbag.from_episode import FRANKA_ROS, PANDA_BASE_IN_SIM_WORLD, BagOptions, write_episode_bag
from rvt2cli.rosbag.importer import ImportOptions, import_bags
from rvt2cli.rosbag.messages import Messages
from rvt2cli.tasks import get_task

pytestmark = pytest.mark.sim

TASK = "push_cube"
BASE_SHIFT = -np.array(PANDA_BASE_IN_SIM_WORLD[:3])   # sim world -> base frame (panda_link0): x + 0.615
CAMERAS = ("/camera/front", "/camera/wrist")
START = BagOptions().start_ns   # the written bags' first stamp
FRAME_NS = 50_000_000           # push_cube runs at 20 Hz


def base_frame_bounds() -> tuple[float, ...]:
    bounds = np.array(get_task(TASK).scene_bounds, dtype=np.float64)
    return tuple(bounds + np.tile(BASE_SHIFT, 2))


OPTIONS = ImportOptions(task=TASK, instruction="push the cube to the target", scene_bounds=base_frame_bounds(),
                        cameras=CAMERAS)
CLI_ARGS = ["--task", TASK, "--instruction", OPTIONS.instruction, "--scene-bounds", ",".join(map(str, OPTIONS.scene_bounds)),
            "--camera", CAMERAS[0], "--camera", CAMERAS[1]]


@pytest.fixture(scope="module")
def sim_episode(tmp_path_factory):
    """A push_cube demo with images at every frame (two 32 px cameras: a fixed one and the wrist's)."""
    out = tmp_path_factory.mktemp("sim")
    summary = record(TASK, 1, out, seed=0, options=RecordOptions(cameras=("front", "wrist"), image_size=32, obs_every=1))
    assert summary.counts() == {"success": 1}
    return read_episode(summary.results[0].path)


@pytest.fixture(scope="module")
def bag(sim_episode, tmp_path_factory):
    return write_episode_bag(sim_episode, tmp_path_factory.mktemp("bags") / "demo.mcap")


@pytest.fixture(scope="module")
def imported(bag, tmp_path_factory):
    out = tmp_path_factory.mktemp("imported")
    [result] = import_bags([bag], out, OPTIONS)
    return read_episode(result.path)


def assert_same_cameras(original, imported, frame, depth_tolerance):
    for name, cam in original.cameras(frame).items():
        other = imported.cameras(frame)[name]
        assert np.array_equal(cam.rgb, other.rgb)
        np.testing.assert_allclose(other.depth, cam.depth, atol=depth_tolerance)
        np.testing.assert_allclose(other.intrinsic, cam.intrinsic, atol=1e-9)
        np.testing.assert_allclose(other.cam2world[:3], cam.cam2world[:3] + BASE_SHIFT, atol=1e-5)
        assert abs(abs(np.dot(other.cam2world[3:], cam.cam2world[3:])) - 1) < 1e-6
        # every pixel's point, in the base frame
        ours, theirs = camera_points(other), camera_points(cam)
        np.testing.assert_allclose(ours.xyz, theirs.xyz + BASE_SHIFT, atol=depth_tolerance * 1.5 + 1e-5)


def assert_same_cloud(original, imported, frame, tolerance):
    """The fused cloud the policy sees, after the base-frame shift: point for point within `tolerance`
    (a point on the edge of the scene bounds may fall on either side of it)."""
    a, b = original.cloud(frame), imported.cloud(frame)
    a_xyz = a.xyz + BASE_SHIFT.astype(np.float32)
    assert abs(len(a) - len(b)) <= 0.01 * len(a) and len(b) > 500
    distance, index = cKDTree(a_xyz).query(b.xyz)
    assert distance.max() < tolerance
    assert (a.rgb[index] == b.rgb).mean() > 0.99


def test_round_trip_gives_the_same_episode_in_the_base_frame(sim_episode, imported, bag):
    a, b = sim_episode, imported
    n = a.num_frames
    assert b.num_frames == n and b.meta.control_hz == pytest.approx(a.meta.control_hz)
    assert b.meta.cameras == ["front", "wrist"] and b.meta.env_id == "real" and b.meta.success
    assert b.meta.expert == "rosbag:demo.mcap" and b.meta.seed == 0 and b.meta.task == TASK
    assert b.meta.extra["source"] == "rosbag" and b.meta.extra["bag"] == str(bag) and b.meta.extra["image_size"] == 32
    assert b.instruction["text"] == OPTIONS.instruction
    # dense robot state: joints in the options' order, gripper from the finger width, TCP in the base frame
    assert b.robot.joint_names == list(OPTIONS.arm_joints + OPTIONS.finger_joints) == a.robot.joint_names
    np.testing.assert_allclose(b.robot.joint_positions, a.robot.joint_positions, atol=1e-6)
    np.testing.assert_allclose(b.robot.joint_velocities, a.robot.joint_velocities, atol=1e-6)
    np.testing.assert_allclose(b.robot.gripper_width, a.robot.gripper_width, atol=1e-6)
    assert np.array_equal(b.robot.gripper_command, a.robot.gripper_command)   # push_cube closes at frame 1
    np.testing.assert_allclose(b.robot.tcp_pose[:, :3], a.robot.tcp_pose[:, :3] + BASE_SHIFT, atol=1e-5)
    assert np.abs(np.abs((b.robot.tcp_pose[:, 3:] * a.robot.tcp_pose[:, 3:]).sum(axis=1)) - 1).max() < 1e-6
    assert all(c == [] for c in b.robot.contacts) and all(x is None for x in b.robot.actions)
    # images where `rvt2 record` keeps them
    arm = len(OPTIONS.arm_joints)
    assert b.obs_frames == observation_frames(n, b.robot.gripper_command > 0, b.robot.joint_velocities[:, :arm], 10)
    for frame in (0, b.obs_frames[len(b.obs_frames) // 2], n - 1):
        assert_same_cameras(a, b, frame, depth_tolerance=1e-6)
        assert_same_cloud(a, b, frame, tolerance=1e-4)


def test_extract_keyframes_finds_the_same_keyframes(sim_episode, imported, cli):
    r = cli("extract-keyframes", imported.path)
    assert r.returncode == 0, r.stderr
    found = read_episode(imported.path).keyframes.keyframes
    expected = annotate(sim_episode).keyframes.keyframes
    assert [k.frame for k in found] == [k.frame for k in expected] and len(found) >= 3
    for k, e in zip(found, expected):
        np.testing.assert_allclose(k.position, np.array(e.position) + BASE_SHIFT, atol=1e-5)
        assert abs(abs(np.dot(k.quaternion, e.quaternion)) - 1) < 1e-6
        assert k.gripper_open == e.gripper_open and not k.ignore_collisions   # no contacts on a real robot


def test_bgra8_and_millimetre_depth_import_within_a_millimetre(sim_episode, tmp_path):
    bag = write_episode_bag(sim_episode, tmp_path / "bgr.mcap", BagOptions(colour_encoding="bgra8", depth_encoding="16UC1"))
    [result] = import_bags([bag], tmp_path / "out", OPTIONS)
    b = read_episode(result.path)
    for frame in (0, b.obs_frames[-1]):
        assert_same_cameras(sim_episode, b, frame, depth_tolerance=0.0005 + 1e-6)
        assert_same_cloud(sim_episode, b, frame, tolerance=0.001)


def test_rosbag2_folder_imports_after_the_existing_episodes(sim_episode, imported, tmp_path, cli):
    folder = write_episode_bag(sim_episode, tmp_path / "demo_bag")
    assert sorted(p.name for p in folder.iterdir()) == ["demo_bag.mcap", "metadata.yaml"]
    out = tmp_path / "episodes"
    out.mkdir()
    shutil.copy(imported.path, out / f"{TASK}_0003.mcap")   # an earlier import: never overwritten
    r = cli("import-rosbag", folder, "--out", out, *CLI_ARGS)
    assert r.returncode == 0, r.stderr
    assert "1 push_cube episode(s)" in r.stdout
    assert sorted(p.name for p in out.iterdir()) == [f"{TASK}_0003.mcap", f"{TASK}_0004.mcap"]
    b = read_episode(out / f"{TASK}_0004.mcap")
    assert b.meta.seed == 4 and b.meta.expert == "rosbag:demo_bag"
    np.testing.assert_allclose(b.robot.tcp_pose, imported.robot.tcp_pose)
    assert_same_cloud(sim_episode, b, 0, tolerance=1e-4)


def test_training_and_offline_precision_on_imported_episodes(imported, tmp_path):
    from rvt2cli.eval.offline import evaluate_offline
    from rvt2cli.keyframes.extract import extract_file
    from rvt2cli.train.trainer import TrainOptions, train

    data = tmp_path / "data"
    data.mkdir()
    shutil.copy(imported.path, data / imported.path.name)
    extract_file(data / imported.path.name)
    result = train(TrainOptions(data=[str(data)], out=str(tmp_path / "run"), steps=3, save_every=3, **TINY_TRAIN),
                   say=lambda *_: None)
    assert result.steps == 3 and all(np.isfinite(result.losses))
    report = evaluate_offline(str(tmp_path / "run"), [str(data)], tmp_path / "offline", progress=False)
    task = report["tasks"][imported.meta.task]
    assert task["samples"] > 0 and np.isfinite(task["stage2_mm"]["median"]) and (tmp_path / "offline" / "offline.md").is_file()


def same_episode(a, b):
    """Equal in everything but where the bag came from."""
    assert a.num_frames == b.num_frames and a.obs_frames == b.obs_frames
    for field in ("joint_names", "joint_positions", "joint_velocities", "gripper_width", "gripper_command", "tcp_pose"):
        np.testing.assert_array_equal(np.asarray(getattr(a.robot, field)), np.asarray(getattr(b.robot, field)))
    for frame in a.obs_frames:
        for name, cam in a.cameras(frame).items():
            other = b.cameras(frame)[name]
            for field in ("rgb", "depth", "intrinsic", "cam2world"):
                np.testing.assert_array_equal(getattr(cam, field), getattr(other, field))
    ignore = ("bag", "start_stamp_ns")
    assert {k: v for k, v in a.meta.extra.items() if k not in ignore} == {k: v for k, v in b.meta.extra.items() if k not in ignore}


def as_humble_writes_it(db3: Path) -> Path:
    """A .db3 as ROS 2 Humble's rosbag2 writes it: schema version 3, no message definitions stored."""
    with sqlite3.connect(db3) as db:
        db.execute("UPDATE schema SET schema_version = 3")
        db.execute("DROP TABLE message_definitions")
    return db3


def test_every_container_imports_to_identical_episodes(sim_episode, imported, tmp_path):
    """The same recording as ROS 2 Humble sqlite3 (a .db3 file with and without message definitions,
    a folder), Jazzy MCAP and a ROS 1 bag."""
    bags = [write_episode_bag(sim_episode, tmp_path / "humble.db3"),
            as_humble_writes_it(write_episode_bag(sim_episode, tmp_path / "humble_no_definitions.db3")),
            write_episode_bag(sim_episode, tmp_path / "humble_sqlite3", BagOptions(storage="sqlite3")),
            write_episode_bag(sim_episode, tmp_path / "jazzy.mcap", BagOptions(distro="jazzy")),
            write_episode_bag(sim_episode, tmp_path / "noetic.bag")]
    assert [open_bag(b).ros_version for b in bags] == [2, 2, 2, 2, 1]
    assert (tmp_path / "humble_sqlite3" / "humble_sqlite3.db3").is_file()
    # the ROS 1 bag has the ROS 2 topic names here: name them, not the ROS 1 defaults
    options = ImportOptions(**{**OPTIONS.__dict__, "joint_states": ("/joint_states",), "ee_frame": "panda_hand_tcp"})
    results = import_bags(bags, tmp_path / "out", options)
    for result in results:
        same_episode(imported, read_episode(result.path))


def test_franka_ros_bag_imports_with_the_ros1_defaults(sim_episode, imported, tmp_path, cli):
    """franka_ros: the arm's joints and the gripper's on two topics, the TCP as panda_EE; realsense2_camera's
    topics under /NAME. Only the cameras are named."""
    bag = write_episode_bag(sim_episode, tmp_path / "franka.bag", FRANKA_ROS)
    assert {"/franka_state_controller/joint_states", "/franka_gripper/joint_states", "/front/color/image_raw"} \
        <= set(open_bag(bag).topics)
    out = tmp_path / "out"
    r = cli("import-rosbag", bag, "--out", out, *CLI_ARGS[:CLI_ARGS.index("--camera")], "--camera", "/front", "--camera", "/wrist")
    assert r.returncode == 0, r.stderr
    b = read_episode(out / f"{TASK}_0000.mcap")
    assert b.meta.extra["joint_states"] == ["/franka_state_controller/joint_states", "/franka_gripper/joint_states"]
    assert b.robot.joint_names == imported.robot.joint_names
    np.testing.assert_array_equal(b.robot.joint_positions, imported.robot.joint_positions)
    np.testing.assert_allclose(b.robot.tcp_pose, imported.robot.tcp_pose, atol=1e-9)
    assert_same_cloud(sim_episode, b, 0, tolerance=1e-4)


def test_compressed_images_are_read_where_raw_ones_are_missing(sim_episode, imported, tmp_path):
    """PNG colour and compressedDepth (16-bit PNG): colour exact, depth within half a millimetre. With raw
    and compressed (JPEG, lossy) both recorded, the raw images are the ones imported."""
    only_compressed = write_episode_bag(sim_episode, tmp_path / "png.mcap", BagOptions(raw=False, compressed="png"))
    assert not any(t.endswith("image_raw") for t in open_bag(only_compressed).topics)
    both = write_episode_bag(sim_episode, tmp_path / "both.db3", BagOptions(compressed="jpeg"))
    png, raw = (read_episode(r.path) for r in import_bags([only_compressed, both], tmp_path / "out", OPTIONS))
    assert png.meta.extra["cameras"]["front"] == {"colour": "/camera/front/color/image_raw/compressed", "camera_info":
                                                  "/camera/front/color/camera_info",
                                                  "depth": "/camera/front/aligned_depth_to_color/image_raw/compressedDepth"}
    for frame in (0, png.obs_frames[-1]):
        assert_same_cameras(sim_episode, png, frame, depth_tolerance=0.0005 + 1e-6)
    assert raw.meta.extra["cameras"]["front"]["colour"] == "/camera/front/color/image_raw"
    same_episode(imported, raw)


@pytest.mark.parametrize("model, coefficients", [
    ("plumb_bob", [-0.28, 0.09, 0.001, -0.0005, -0.015]),
    ("rational_polynomial", [0.2, -0.1, 0.001, -0.0005, 0.0, 0.5, -0.05, 0.0]),
    ("equidistant", [-0.02, 0.01, -0.008, 0.002]),
])
def test_distorted_camera_sees_a_plane_flat(model, coefficients):
    """A plane seen through a distorted lens, as the camera records it (each recorded pixel sees along
    its distorted ray): undistorted, every pixel's point lies on the plane; taken as pinhole, it does not."""
    messages = Messages("humble")
    width, height = 320, 240
    K = np.array([[220.0, 0, 159.5], [0, 220.0, 119.5], [0, 0, 1]])
    info = messages.camera_info(K + np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]]), width, height, 0, "cam", model, coefficients)
    # the plane n . x = 1 m, tilted; a recorded pixel (u, v) sees along the ray of its undistorted point
    normal = np.array([0.2, -0.1, 1.0])
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1)[:, None, :]
    if model == "equidistant":
        rays = cv2.fisheye.undistortPoints(pixels, K, np.array(coefficients)).reshape(-1, 2)
    else:
        rays = cv2.undistortPoints(pixels, K, np.array(coefficients)).reshape(-1, 2)
    rays = np.concatenate([rays, np.ones((len(rays), 1))], axis=1)
    depth = (1.0 / (rays @ normal)).reshape(height, width).astype(np.float32)   # z of the ray's hit

    def off_plane_mm(frame: CameraFrame) -> np.ndarray:
        xyz = camera_points(frame).xyz.astype(np.float64)
        return np.abs(xyz @ normal - 1.0) / np.linalg.norm(normal) * 1000

    pose = np.array([0, 0, 0, 0, 0, 0, 1.0])
    undistortion = Undistortion.of(info, (width, height))
    undistorted = CameraFrame(rgb=np.zeros((height, width, 3), np.uint8), depth=undistortion.depth(depth),
                              intrinsic=undistortion.intrinsic, cam2world=pose)
    assert (undistorted.depth > 0).mean() > 0.8
    # nearest-neighbour remap: each depth comes from within half a pixel of where it belongs
    error = off_plane_mm(undistorted)
    assert np.median(error) < 0.3 and error.max() < 2.0
    pinhole = CameraFrame(rgb=undistorted.rgb, depth=depth, intrinsic=undistortion.intrinsic, cam2world=pose)
    assert np.median(off_plane_mm(pinhole)) > 5 * np.median(error)


# --- bags edited message by message: what goes wrong in recordings -------------------------------

def rewrite_bag(source: Path, target: Path, edit) -> Path:
    """Copy a bag message by message, into the same kind of bag; `edit(topic, msg, log_time)` returns
    (topic, msg, log_time) to write, or None to drop the message; a message type of the result is
    written in place of the source's when edit returns (topic, msg, log_time, datatype)."""
    source_bag = open_bag(source)
    distro = "noetic" if source_bag.ros_version == 1 else "humble"
    with BagWriter(target, distro) as out:
        for topic, msg, log_time in source_bag.messages(list(source_bag.topics)):
            kept = edit(topic, msg, log_time)
            if kept is not None:
                new_topic, msg, log_time, *datatype = kept
                out.write(new_topic, datatype[0] if datatype else source_bag.topics[topic].datatype, msg, log_time)
    return target


def without(topic):
    return lambda t, msg, log_time: None if t == topic else (t, msg, log_time)


def shift_stamps(topic, ns):
    def edit(t, msg, log_time):
        if t == topic:
            sec, nanosec = divmod(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec + ns, 1_000_000_000)
            msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
        return t, msg, log_time
    return edit


def with_encoding(topic, encoding):
    def edit(t, msg, log_time):
        if t == topic:
            msg.encoding = encoding
        return t, msg, log_time
    return edit


def tf_gap(start_ns, end_ns):
    return lambda t, msg, log_time: None if t == "/tf" and start_ns <= log_time < end_ns else (t, msg, log_time)


def unaligned_depth(t, msg, log_time):
    if t == "/camera/front/aligned_depth_to_color/image_raw":
        msg.header.frame_id = "front_depth_optical_frame"
        return "/camera/front/depth/image_rect_raw", msg, log_time
    return t, msg, log_time


def test_frames_before_and_after_a_stream_are_cut(sim_episode, bag, tmp_path):
    """A recording's topics start and stop at slightly different times: the episode keeps the frames
    every stream covers."""
    n = sim_episode.num_frames
    late_depth = "/camera/wrist/aligned_depth_to_color/image_raw"

    def edit(topic, msg, log_time):
        frame = (log_time - START) // FRAME_NS
        if (topic == late_depth and frame < 3) or (topic == "/joint_states" and frame >= n - 2):
            return None
        return topic, msg, log_time

    [result] = import_bags([rewrite_bag(bag, tmp_path / "ragged.mcap", edit)], tmp_path / "out", OPTIONS)
    assert result.frames_cut == (3, 2) and result.frames == n - 5
    b = read_episode(result.path)
    np.testing.assert_allclose(b.robot.tcp_pose[:, :3], sim_episode.robot.tcp_pose[3:n - 2, :3] + BASE_SHIFT, atol=1e-5)
    assert b.meta.extra["start_stamp_ns"] == START + 3 * FRAME_NS


def empty_bag(path: Path) -> Path:
    with BagWriter(path, "humble") as bag:
        bag.writer.add_connection("/camera/camera/color/image_raw", "sensor_msgs/msg/Image", typestore=bag.messages.store)
    return path


def unknown_storage(folder: Path) -> Path:
    folder.mkdir()
    (folder / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  version: 5\n  storage_identifier: hdf5\n"
                                          "  relative_file_paths:\n  - demo_0.h5\n")
    return folder


def as_string(topic):
    """A bag carrying std_msgs/String on `topic`: a message type rvt2 does not read there."""
    def edit(t, msg, log_time):
        if t == topic:
            return t, Messages("noetic").types["std_msgs/msg/String"](data="hello"), log_time, "std_msgs/msg/String"
        return t, msg, log_time
    return edit


def truncated(path: Path, keep: float) -> Path:
    path.write_bytes(path.read_bytes()[: int(path.stat().st_size * keep)])
    return path


# --- bad input: one line, exit code 2, nothing written ---------------------------------------------

def cli_args(*extra, leave_out: str | None = None) -> list[str]:
    args = list(CLI_ARGS)
    if leave_out:
        del args[args.index(leave_out):args.index(leave_out) + 2]
    return args + list(extra)


def write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


# name: (the bags to give, made from the good bag, the recorded episode and a scratch folder;
#        the other arguments; fragments of the one line)
BAD_INPUTS = {
    "missing file": (lambda bag, ep, d: [d / "nope.mcap"], cli_args(), ["nope.mcap", "no such file"]),
    "not MCAP": (lambda bag, ep, d: [write(d / "notes.mcap", b"just some text")], cli_args(),
                 ["notes.mcap", "cannot open the bag"]),
    "rvt2 episode, not a ROS 2 bag": (lambda bag, ep, d: [ep], cli_args(), ["cannot open the bag", "not a ROS 2 bag"]),
    "truncated MCAP": (lambda bag, ep, d: [write(d / "cut.mcap", bag.read_bytes()[: bag.stat().st_size // 2])], cli_args(),
                       ["cut.mcap", "truncated", "ros2 bag reindex"]),
    "truncated .db3": (lambda bag, ep, d: [truncated(write_episode_bag(ep, d / "cut.db3"), 0.5)], cli_args(),
                       ["cut.db3", "cannot", "truncated"]),
    "unknown storage": (lambda bag, ep, d: [unknown_storage(d / "h5_bag")], cli_args(), ["h5_bag", "unknown bag storage 'hdf5'"]),
    "unknown file": (lambda bag, ep, d: [write(d / "demo.h5", b"HDF")], cli_args(), ["demo.h5", "unknown bag storage '.h5'"]),
    "no images": (lambda bag, ep, d: [rewrite_bag(bag, d / "b.mcap", without("/camera/front/color/image_raw"))], cli_args(),
                  ["no colour images on topic /camera/front/color/image_raw"]),
    "ROS 1 bag of a type rvt2 does not read": (
        lambda bag, ep, d: [rewrite_bag(write_episode_bag(ep, d / "ros1.bag"), d / "b.bag",
                                        as_string("/camera/front/color/image_raw"))],
        cli_args("--joint-states", "/joint_states", "--ee-frame", "panda_hand_tcp"),
        ["b.bag", "carries std_msgs/msg/String", "must be a sensor_msgs/msg/Image"]),
    "empty bag": (lambda bag, ep, d: [empty_bag(d / "empty.mcap")], cli_args(), ["empty.mcap", "no messages"]),
    "missing topic": (lambda bag, ep, d: [rewrite_bag(bag, d / "b.mcap", without("/joint_states"))], cli_args(),
                      ["b.mcap", "no joint states on topic /joint_states", "the bag has: /camera/front/"]),
    "missing camera_info": (lambda bag, ep, d: [rewrite_bag(bag, d / "b.mcap", without("/camera/wrist/color/camera_info"))],
                            cli_args(), ["/camera/wrist/color/camera_info", "camera calibration"]),
    "unknown encoding": (lambda bag, ep, d: [rewrite_bag(bag, d / "b.mcap",
                                                         with_encoding("/camera/front/color/image_raw", "yuv422"))],
                         cli_args(), ["/camera/front/color/image_raw", "'yuv422'", "rgb8, bgr8, rgba8 or bgra8"]),
    "missing transform": (lambda bag, ep, d: [rewrite_bag(bag, d / "b.mcap", without("/tf_static"))], cli_args(),
                          ["no transform panda_link0 -> front_color_optical_frame", "not on /tf or /tf_static"]),
    "stale transform": (lambda bag, ep, d: [rewrite_bag(bag, d / "b.mcap", tf_gap(START + 20 * FRAME_NS, START + 30 * FRAME_NS))],
                        cli_args(), ["stale transform panda_link0 -> panda_hand_tcp", "s away", "--sync-tolerance"]),
    "joint names": (lambda bag, ep, d: [bag], cli_args("--arm-joints", ",".join(f"fr3_joint{i}" for i in range(1, 8))),
                    ["fr3_joint1", "not found on /joint_states", "--arm-joints"]),
    "unsynchronised": (lambda bag, ep, d: [rewrite_bag(bag, d / "b.mcap", shift_stamps(
                           "/camera/wrist/aligned_depth_to_color/image_raw", FRAME_NS // 2))],
                       cli_args(), ["cannot synchronise /camera/wrist/aligned_depth_to_color/image_raw", "0.025 s away"]),
    "depth not aligned": (lambda bag, ep, d: [rewrite_bag(bag, d / "b.mcap", unaligned_depth)], cli_args(),
                          ["/camera/front/depth/image_rect_raw", "front_depth_optical_frame", "align_depth.enable:=true"]),
    "one bad bag among good ones": (lambda bag, ep, d: [bag, rewrite_bag(bag, d / "b.mcap", without("/tf")), bag], cli_args(),
                                    ["b.mcap", "no transform panda_link0 -> panda_hand_tcp"]),
    "no scene bounds": (lambda bag, ep, d: [bag], cli_args(leave_out="--scene-bounds"), ["--scene-bounds", "base frame"]),
}


@pytest.fixture(scope="module")
def bad_input_runs(bag, sim_episode, tmp_path_factory):
    """Every bad input through the command line, four at a time; per case the result and what its
    (empty) output folder holds afterwards."""
    cases = {}
    for name, (make, args, _) in BAD_INPUTS.items():
        folder = tmp_path_factory.mktemp("bad")
        out = folder / "out"
        out.mkdir()
        cases[name] = (["import-rosbag", *make(bag, sim_episode.path, folder), "--out", out, *args], out)
    with ThreadPoolExecutor(4) as pool:
        results = dict(zip(cases, pool.map(lambda args: run_cli(*args), [args for args, _ in cases.values()])))
    return {name: (results[name], sorted(p.name for p in out.iterdir())) for name, (_, out) in cases.items()}


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_bad_input_is_one_line_and_leaves_nothing(case, bad_input_runs):
    result, left_in_out = bad_input_runs[case]
    assert_one_line_error(result, *BAD_INPUTS[case][2])
    assert left_in_out == []
