"""Facts about the robot: which joints are the arm and which the fingers, and which link is the tool
centre point (TCP), defined once here and read from the simulator's robot where there is one.

In the simulator they come from the ManiSkill agent (`RobotFacts.from_agent`); `rvt2 record` stores
them in each episode (`EpisodeMeta.extra["robot"]`) and `rvt2 import-rosbag` stores the names it was
given, so code that reads episodes (the keyframe rule, the policy's proprio input) never guesses.
Episodes of format 1.0 written before the facts were stored are Panda episodes: `PANDA` is their
convention (seven arm joints, then two finger joints).
"""

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from rvt2cli.errors import UserError


@dataclass(frozen=True)
class RobotFacts:
    arm_joints: tuple[str, ...]
    finger_joints: tuple[str, ...]
    tcp_link: str

    @staticmethod
    def from_agent(agent) -> "RobotFacts":
        """From a ManiSkill agent (its class attributes name the arm, the gripper and the TCP link)."""
        return RobotFacts(arm_joints=tuple(agent.arm_joint_names), finger_joints=tuple(agent.gripper_joint_names),
                          tcp_link=agent.ee_link_name)

    @staticmethod
    def from_json(obj: dict | None) -> "RobotFacts":
        """As stored in an episode; an episode without them is a Panda episode of format 1.0."""
        if not obj:
            return PANDA
        return RobotFacts(arm_joints=tuple(obj["arm_joints"]), finger_joints=tuple(obj["finger_joints"]),
                          tcp_link=obj["tcp_link"])

    def to_json(self) -> dict:
        d = asdict(self)
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}

    def indices(self, joint_names, which: tuple[str, ...], where: str = "joint state") -> np.ndarray:
        names = list(joint_names)
        missing = [j for j in which if j not in names]
        if missing:
            raise UserError(f"{where}: joint(s) {', '.join(missing)} not among {', '.join(names)}")
        return np.array([names.index(j) for j in which])

    def arm(self, values: np.ndarray, joint_names, where: str = "joint state") -> np.ndarray:
        """The arm joints' columns of per-joint values [..., J]."""
        return np.asarray(values)[..., self.indices(joint_names, self.arm_joints, where)]

    def fingers(self, values: np.ndarray, joint_names, where: str = "joint state") -> np.ndarray:
        """The finger joints' columns of per-joint values [..., J]."""
        return np.asarray(values)[..., self.indices(joint_names, self.finger_joints, where)]


PANDA = RobotFacts(
    arm_joints=tuple(f"panda_joint{i}" for i in range(1, 8)),
    finger_joints=("panda_finger_joint1", "panda_finger_joint2"),
    tcp_link="panda_hand_tcp",
)


def planner_description(agent) -> tuple[str, str]:
    """The URDF and SRDF the motion planner loads for a ManiSkill agent. ManiSkill keeps the SRDF
    next to the URDF under the same name (its own motion-planning examples rely on that too)."""
    urdf = Path(agent.urdf_path)
    srdf = urdf.with_suffix(".srdf")
    if not srdf.is_file():
        raise UserError(f"{urdf}: the motion planner needs {srdf.name} next to it (collision pairs to ignore); "
                        "this robot has none")
    return str(urdf), str(srdf)
