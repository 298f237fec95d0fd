"""Channel (topic) names of an rvt2 episode file. docs/FORMAT.md describes each one."""

ROBOT_STATE = "/robot/state"          # rvt2.RobotState, every frame
TCP_POSE = "/robot/tcp_pose"          # foxglove.PoseInFrame, every frame
TF = "/tf"                            # foxglove.FrameTransform: world->tcp every frame, world->camera at obs frames
SIM_STATE = "/sim/state"              # rvt2.SimState, every frame
INSTRUCTION = "/language/instruction"  # rvt2.Instruction, once
CLOUD = "/points/world"               # foxglove.PointCloud, fused + cropped, at obs frames (optional, for viewing)
KEYFRAMES = "/annotations/keyframes"  # rvt2.Keyframes, once, written by extract-keyframes

METADATA_NAME = "rvt2.episode"        # MCAP metadata record: format_version + episode (JSON)
TCP_FRAME = "tcp"


def camera_frame_id(camera: str) -> str:
    return f"camera_{camera}"


def camera_image(camera: str) -> str:
    return f"/cameras/{camera}/image"        # foxglove.RawImage rgb8


def camera_depth(camera: str) -> str:
    return f"/cameras/{camera}/depth"        # foxglove.RawImage 32FC1, metres


def camera_calibration(camera: str) -> str:
    return f"/cameras/{camera}/calibration"  # foxglove.CameraCalibration


def camera_of_topic(topic: str) -> str | None:
    parts = topic.split("/")
    return parts[2] if len(parts) == 4 and parts[1] == "cameras" else None
