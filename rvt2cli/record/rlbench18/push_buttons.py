"""push_buttons: press one, two or three coloured buttons in the order the instruction names them.

RLBench's variations (`rlbench/tasks/push_buttons.py`): variation k presses the first 1 + k % 3 colours of
the (k // 3)-th ordered triple of its 18 colours (RLBench's colours without red and lime, which it keeps
for the buttons' caps), 50 variations in all. Button i wears the i-th colour of the triple; a button not
to be pressed wears a colour the instruction does not name. A button counts as pressed once its cap has
gone 3 mm down (RLBench's joint condition).

Here a pressed button latches: its cap stays down, where RLBench turns it green, so that the scene shows
which buttons are done. And success asks for the named buttons in order *and no other*: RLBench ignores
extra presses, which lets a policy that presses every button in a fixed colour order succeed without
reading the instruction.
"""

import itertools

import numpy as np
import sapien
import torch
from transforms3d.euler import euler2quat

from mani_skill.utils.registration import register_env

from rvt2cli.record.rlbench18.base import VariationEnv
from rvt2cli.record.rlbench18.colors import RLBENCH_COLORS, rgba

COLORS = [name for name in RLBENCH_COLORS if name not in ("red", "lime")]
TRIPLES = list(itertools.permutations(COLORS, 3))
MAX_BUTTONS = 3
NUM_VARIATIONS = 50

HOUSING_HALF = (0.035, 0.035, 0.015)  # m: the coloured base the cap sits in
CAP_RADIUS, CAP_HALF_HEIGHT = 0.018, 0.008
TRAVEL = 0.01           # m: how far the cap goes down
PRESSED_DEPTH = 0.003   # m: a cap this far down has been pressed (RLBench's joint condition)
SPRING = 400.0          # N/m: the spring that holds the cap up...
PRELOAD = 0.005         # ...pushing it against its top stop as if this far above it
CAP_TOP = 2 * HOUSING_HALF[2] + 2 * CAP_HALF_HEIGHT  # m above the table, cap up
MIN_SPACING = 0.12      # m between buttons' centres
LAYOUT_X, LAYOUT_Y = (-0.12, 0.12), (-0.2, 0.2)  # m: where buttons stand (world frame)
# the prismatic joint moves along its frame's x axis: turn it to point up
X_TO_UP = sapien.Pose(q=[np.sqrt(0.5), 0, -np.sqrt(0.5), 0])


def variation_colors(variation: int) -> tuple[str, ...]:
    """The colours to press, in order, in this variation."""
    return TRIPLES[variation // MAX_BUTTONS][: 1 + variation % MAX_BUTTONS]


@register_env("RVT2-PushButtons-v1", max_episode_steps=400)
class PushButtonsEnv(VariationEnv):
    num_variations = NUM_VARIATIONS

    def _build_task(self, options: dict):
        targets = variation_colors(self.variation)
        triple = TRIPLES[self.variation // MAX_BUTTONS]
        # the buttons not to press wear colours the instruction does not name, in an order drawn from the seed
        others = [c for c in (COLORS[i] for i in self._episode_rng.permutation(len(COLORS))) if c not in triple]
        self.button_colors = list(targets) + others[: MAX_BUTTONS - len(targets)]
        self.buttons = [self._build_button(f"button{i}", color) for i, color in enumerate(self.button_colors)]

    def _build_button(self, name: str, color: str):
        builder = self.scene.create_articulation_builder()
        housing = builder.create_link_builder()
        housing.set_name(f"{name}_housing")
        centre = sapien.Pose([0, 0, HOUSING_HALF[2]])
        housing.add_box_collision(centre, HOUSING_HALF)
        housing.add_box_visual(centre, HOUSING_HALF, material=sapien.render.RenderMaterial(base_color=rgba(color)))
        cap = builder.create_link_builder(housing)
        cap.set_name(f"{name}_cap")
        cap.set_joint_name(f"{name}_joint")
        upright = sapien.Pose(q=[np.sqrt(0.5), 0, np.sqrt(0.5), 0])  # the cylinder's axis (x) turned up
        cap.add_cylinder_collision(upright, CAP_RADIUS, CAP_HALF_HEIGHT)
        cap.add_cylinder_visual(upright, CAP_RADIUS, CAP_HALF_HEIGHT, material=sapien.render.RenderMaterial(base_color=rgba("red")))
        cap.set_joint_properties("prismatic", limits=[[-TRAVEL, 0.0]],
                                 pose_in_parent=sapien.Pose([0, 0, 2 * HOUSING_HALF[2] + CAP_HALF_HEIGHT]) * X_TO_UP,
                                 pose_in_child=X_TO_UP, friction=0.0, damping=1.0)
        builder.set_initial_pose(sapien.Pose())
        button = builder.build(name=name, fix_root_link=True)
        button.joints_map[f"{name}_joint"].set_drive_properties(stiffness=SPRING, damping=10.0)
        return button

    def _place_task(self, env_idx, options: dict):
        rng = self._episode_rng
        centres = []
        while len(centres) < MAX_BUTTONS:  # rejection sampling, as RLBench's spawn boundary
            xy = np.array([rng.uniform(*LAYOUT_X), rng.uniform(*LAYOUT_Y)])
            if all(np.linalg.norm(xy - c) >= MIN_SPACING for c in centres):
                centres.append(xy)
        yaws = rng.uniform(-np.pi / 4, np.pi / 4, size=MAX_BUTTONS)
        for button, (x, y), yaw in zip(self.buttons, centres, yaws):
            button.set_pose(sapien.Pose([x, y, 0], euler2quat(0, 0, yaw)))
            button.set_qpos(torch.zeros((1, 1)))
            button.set_qvel(torch.zeros((1, 1)))
            button.active_joints[0].set_drive_target(PRELOAD)
        self.pressed: list[int] = []  # buttons in the order they were pressed

    def cap_depths(self) -> np.ndarray:
        """How far each cap is down (m)."""
        return np.array([-float(b.get_qpos()[0, 0]) for b in self.buttons])

    def _after_control_step(self):
        for i, depth in enumerate(self.cap_depths()):
            if i not in self.pressed and depth >= PRESSED_DEPTH:
                self.pressed.append(i)
                self.buttons[i].active_joints[0].set_drive_target(-2 * TRAVEL)  # latched: the cap stays down

    def button_centres(self) -> np.ndarray:
        """[3, 3]: the top centre of each button's cap, up (world frame)."""
        return np.array([[*b.pose.sp.p[:2], CAP_TOP] for b in self.buttons])

    def evaluate(self):
        # the buttons the current variation names, in order (a colour no button wears: none to press)
        wanted = [self.button_colors.index(c) if c in self.button_colors else -1 for c in variation_colors(self.variation)]
        return {"success": torch.tensor([self.pressed == wanted]),
                "wrong_object": torch.tensor([self.pressed != wanted[: len(self.pressed)]]),
                "buttons_pressed": torch.tensor([len(self.pressed)])}


ABOVE_M = 0.05   # the closed fingers stop this far above a cap before pressing it...
PRESS_M = 0.008  # ...and push it this far down (of its 10 mm travel; 3 mm counts)
POINTING_DOWN = [0.0, 1.0, 0.0, 0.0]  # wxyz: the TCP's orientation at rest (turned half round x)


def expert(env, seed=None):
    """Close the gripper, then for each button to press: stop above its cap, push it down, come back up.
    Returns -1 when a motion cannot be planned."""
    from rvt2cli.record.motions import solver

    env.reset(seed=seed)
    scene = env.unwrapped
    planner = solver(env, speed=0.9)
    result = planner.close_gripper()
    for centre in scene.button_centres()[: len(variation_colors(scene.variation))]:
        above = sapien.Pose(centre + [0, 0, ABOVE_M], POINTING_DOWN)
        pressed = sapien.Pose(centre - [0, 0, PRESS_M], POINTING_DOWN)
        for pose in (above, pressed, above):
            result = planner.move_to_pose_with_screw(pose)
            if result == -1:
                return -1
    return result
