"""In-memory types of an episode: what the writer takes and the reader gives back."""

from dataclasses import asdict, dataclass, field

import numpy as np

from rvt2cli.robot import RobotFacts


@dataclass
class EpisodeMeta:
    """Episode-level facts; stored as JSON in the `rvt2.episode` metadata record (schema rvt2.Episode)."""

    task: str
    env_id: str
    seed: int
    success: bool
    expert: str
    num_frames: int
    control_hz: float
    scene_bounds: list[float]
    cameras: list[str]
    instruction: str
    versions: dict[str, str]
    obs_frames: list[int] = field(default_factory=list)
    voxel_size: float | None = None
    extra: dict = field(default_factory=dict)

    def to_json_obj(self) -> dict:
        return asdict(self)

    @property
    def robot(self) -> RobotFacts:
        """Which joints are the arm and the fingers (stored in `extra["robot"]`)."""
        return RobotFacts.from_json(self.extra.get("robot"))


@dataclass
class CameraFrame:
    """One camera's RGB-D image with its calibration (OpenCV convention)."""

    rgb: np.ndarray          # uint8 [H, W, 3]
    depth: np.ndarray        # float32 [H, W], metres along the optical axis, 0 = no return
    intrinsic: np.ndarray    # [3, 3]
    cam2world: np.ndarray    # 7: camera pose in the world (x y z qx qy qz qw), OpenCV axes


@dataclass
class Cloud:
    xyz: np.ndarray          # float32 [N, 3], metres, world frame
    rgb: np.ndarray          # uint8 [N, 3]

    def __len__(self) -> int:
        return len(self.xyz)


@dataclass
class RobotTrajectory:
    """Dense robot state, one row per frame."""

    joint_names: list[str]
    joint_positions: np.ndarray   # [T, J]
    joint_velocities: np.ndarray  # [T, J]
    gripper_width: np.ndarray     # [T]
    gripper_command: np.ndarray   # [T]: +1 open, -1 closed
    tcp_pose: np.ndarray          # [T, 7]
    actions: list                 # T entries, list[float] or None (last frame)
    contacts: list[list[str]]     # T entries
    near: list[list[str]] | None = None  # T entries: bodies within 5 mm (None: recorded without it)

    def __len__(self) -> int:
        return len(self.joint_positions)
