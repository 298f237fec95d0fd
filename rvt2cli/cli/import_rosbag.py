"""`rvt2 import-rosbag`: real-robot demonstrations (ROS 1 or ROS 2 bags) -> rvt2 episode files."""

from rvt2cli.cli.args import COUNT, POSITIVE, names, numbers
from rvt2cli.errors import UserError
from rvt2cli.robot import PANDA

BOUNDS_HINT = ("the workspace box in the robot's base frame, in metres, that holds everything the task touches, "
               "e.g. 0.2,-0.4,-0.05,0.9,0.4,0.5 for a tabletop in front of a Panda (docs/REAL_ROBOT.md: choosing scene bounds)")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "import-rosbag", help="turn ROS 1 or ROS 2 bags of real-robot demonstrations into episode files",
        description="Read bags recorded with `ros2 bag record` (sqlite3 or MCAP storage: a rosbag2 folder or one .db3 "
                    "or .mcap file) or ROS 1's `rosbag record` (a .bag file), one bag per demonstration, from a robot "
                    "with RGB-D cameras (raw or compressed images), and write one rvt2 episode per bag into --out, as "
                    "`rvt2 record` writes them: the world frame is the robot's base frame, the first camera's colour "
                    "stream is the clock. Unset topics and frames take the defaults of the bag's ROS version "
                    "(ROS 2: franka_ros2 and realsense-ros; ROS 1: franka_ros and realsense2_camera). Every bag is "
                    "checked before any episode is written. See docs/REAL_ROBOT.md.",
    )
    p.add_argument("bags", nargs="*", metavar="BAG", help="ROS 1 .bag file, rosbag2 folder (with metadata.yaml), or one "
                                                          ".db3 or .mcap file")
    p.add_argument("--out", help="output folder; episodes are named TASK_NNNN.mcap after the ones already there")
    p.add_argument("--task", help="task name (letters, digits, '_', '-')")
    p.add_argument("--instruction", help="the language instruction of the demonstrations")
    p.add_argument("--scene-bounds", type=numbers(6), metavar="XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX", help=f"required: {BOUNDS_HINT}")
    p.add_argument("--camera", action="append", metavar="PREFIX",
                   help="topic prefix of a camera (repeatable; the first is the clock; default /camera/camera for ROS 2 "
                        "(realsense-ros), /camera for ROS 1 (realsense2_camera)); the camera's name in the episode is its "
                        "last part")
    p.add_argument("--color-topic", default="color/image_raw",
                   help="colour image topic, relative to the prefix (default color/image_raw; its /compressed where only "
                        "that was recorded)")
    p.add_argument("--depth-topic", help="depth topic, relative to the prefix (default aligned_depth_to_color/image_raw, "
                                         "else depth/image_rect_raw when it is in the colour camera's frame; their "
                                         "/compressedDepth where only that was recorded)")
    p.add_argument("--camera-info-topic", default="color/camera_info",
                   help="colour camera_info topic, relative to the prefix (default color/camera_info)")
    p.add_argument("--joint-states", action="append", metavar="TOPIC",
                   help="sensor_msgs/JointState topic (repeatable: the topics are merged joint by joint; default "
                        "/joint_states for ROS 2, /franka_state_controller/joint_states and /franka_gripper/joint_states "
                        "for ROS 1)")
    p.add_argument("--arm-joints", type=names, default=PANDA.arm_joints,
                   help="comma-separated arm joint names (default panda_joint1..panda_joint7)")
    p.add_argument("--finger-joints", type=names, default=PANDA.finger_joints,
                   help="comma-separated finger joint names; the gripper width is the sum of their positions")
    p.add_argument("--base-frame", default="panda_link0",
                   help="TF frame of the robot base: the episode's world frame (default panda_link0)")
    p.add_argument("--ee-frame", help="TF frame of the tool centre point (default panda_hand_tcp for ROS 2, panda_EE "
                                      "for ROS 1)")
    p.add_argument("--gripper-threshold", type=POSITIVE, default=0.07,
                   help="gripper width (m) above which the gripper counts as open (default 0.07; a Panda opens to 0.08)")
    p.add_argument("--sync-tolerance", type=POSITIVE, default=0.02,
                   help="how far (s) a matched message or transform may be from a colour frame's stamp (default 0.02)")
    p.add_argument("--obs-every", type=COUNT, default=10, help="keep images every N frames besides keyframes (default 10)")
    p.add_argument("--voxel-size", type=POSITIVE, help="downsample fused clouds to this voxel size in metres (default: no)")
    p.set_defaults(run=run)


def run(args) -> int:
    for option, value in (("BAG", args.bags), ("--out", args.out), ("--task", args.task), ("--instruction", args.instruction)):
        if not value:
            raise UserError(f"import-rosbag needs {option}: rvt2 import-rosbag BAG... --out DIR --task NAME "
                            "--instruction TEXT --scene-bounds XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX")
    if args.scene_bounds is None:
        raise UserError(f"import-rosbag needs --scene-bounds XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX: {BOUNDS_HINT}")

    from rvt2cli.rosbag.importer import ImportOptions, import_bags

    options = ImportOptions(
        task=args.task, instruction=args.instruction, scene_bounds=args.scene_bounds,
        cameras=tuple(args.camera) if args.camera else None, colour_topic=args.color_topic, depth_topic=args.depth_topic,
        camera_info_topic=args.camera_info_topic, joint_states=tuple(args.joint_states) if args.joint_states else None,
        arm_joints=args.arm_joints,
        finger_joints=args.finger_joints, base_frame=args.base_frame, ee_frame=args.ee_frame,
        gripper_threshold=args.gripper_threshold, sync_tolerance=args.sync_tolerance, obs_every=args.obs_every,
        voxel_size=args.voxel_size,
    )
    results = import_bags(args.bags, args.out, options)
    for r in results:
        cut = f"; {r.frames_cut[0]} + {r.frames_cut[1]} colour frames cut at the ends (a stream not yet or no longer there)" \
            if any(r.frames_cut) else ""
        print(f"{r.bag} -> {r.path}: {r.frames} frames at {r.control_hz:.1f} Hz, images at {r.obs_frames} frames{cut}")
    print(f"imported {len(results)} {args.task} episode(s) into {args.out}/; next: rvt2 extract-keyframes {args.out}/")
    return 0
