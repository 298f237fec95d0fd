"""light_bulb_in: put the bulb from the holder of the named colour into the lamp (RLBench, 20 variations).

Two bulbs (a glass globe and neck on a cylindrical cap) stand in two holders, square cups in two different
colours; the lamp is a post with a square socket on top. The task succeeds when the named holder's bulb
stands in the socket and the gripper has let it go (RLBench's proximity sensor in the lamp, and nothing
grasped); the other bulb there, or in the gripper, is a wrong object. The seed lays everything out; the
variation picks the colours and which holder wears the named one.
"""

import numpy as np
import sapien
import torch
from transforms3d.euler import euler2quat

from mani_skill.utils.registration import register_env
from mani_skill.utils.structs.pose import Pose
from rvt2cli.record.rlbench18.base import VariationEnv
from rvt2cli.record.rlbench18.colors import COLORS, colour_rng, distractor_colours, rgba

# The bulb, upwards from its frame's origin at the bottom of its screw cap: the cap, a glass neck (a cylinder,
# which flat fingers hold without letting the bulb swing, as they would a sphere) and a glass globe.
CAP_RADIUS, CAP_HALF = 0.011, 0.01
NECK_RADIUS, NECK_HALF = 0.014, 0.015
GLOBE_RADIUS = 0.018
NECK_Z = 2 * CAP_HALF + NECK_HALF
GLOBE_Z = 2 * CAP_HALF + 2 * NECK_HALF + 0.008
SOCKET_INNER = 0.016   # m, half the inner side of a holder's or the lamp's square socket
SOCKET_WALL = 0.006
SOCKET_DEPTH = 0.015   # its walls rise this far above its floor
FLOOR = 0.006
LAMP_HEIGHT = 0.08     # the lamp's socket floor stands this high
N_HOLDERS = 2


def _add_socket(builder, floor_z: float, colour, post_half: tuple | None = None):
    """A square cup whose floor's top is at floor_z in the builder's frame (on a post below it, if given)."""
    material = sapien.render.RenderMaterial(base_color=colour)
    outer = SOCKET_INNER + SOCKET_WALL
    boxes = [([0, 0, floor_z - FLOOR / 2], [outer, outer, FLOOR / 2])]
    along = SOCKET_INNER + SOCKET_WALL / 2
    for sign in (-1, 1):
        boxes.append(([sign * along, 0, floor_z + SOCKET_DEPTH / 2], [SOCKET_WALL / 2, outer, SOCKET_DEPTH / 2]))
        boxes.append(([0, sign * along, floor_z + SOCKET_DEPTH / 2], [SOCKET_INNER, SOCKET_WALL / 2, SOCKET_DEPTH / 2]))
    if post_half is not None:
        boxes.append(([0, 0, post_half[2]], list(post_half)))
    for centre, half in boxes:
        builder.add_box_collision(sapien.Pose(centre), half)
        builder.add_box_visual(sapien.Pose(centre), half, material=material)


@register_env("RVT2-LightBulbIn-v1", max_episode_steps=400)
class LightBulbInEnv(VariationEnv):
    num_variations = len(COLORS)

    def _build_task(self, options: dict):
        rng = colour_rng(self)
        named = int(rng.integers(N_HOLDERS))
        others = iter(distractor_colours(rng, self.variation, N_HOLDERS - 1))
        self.holder_colours = [self.variation if i == named else next(others) for i in range(N_HOLDERS)]

        self.holders, self.bulbs = [], []
        for i, colour in enumerate(self.holder_colours):
            holder = self.scene.create_actor_builder()
            _add_socket(holder, FLOOR, rgba(colour))
            holder.initial_pose = sapien.Pose([-0.2, 0.1 * i, 0])
            self.holders.append(holder.build_kinematic(f"bulb_holder{i}"))

            bulb = self.scene.create_actor_builder()
            upright = sapien.Pose(q=[np.cos(np.pi / 4), 0, np.sin(np.pi / 4), 0])  # SAPIEN's cylinders lie along x
            brass = sapien.render.RenderMaterial(base_color=[0.7, 0.6, 0.35, 1.0])
            glass = sapien.render.RenderMaterial(base_color=[0.95, 0.95, 0.9, 1.0])
            for z, radius, half, material in ((CAP_HALF, CAP_RADIUS, CAP_HALF, brass), (NECK_Z, NECK_RADIUS, NECK_HALF, glass)):
                bulb.add_cylinder_collision(sapien.Pose([0, 0, z]) * upright, radius=radius, half_length=half)
                bulb.add_cylinder_visual(sapien.Pose([0, 0, z]) * upright, radius=radius, half_length=half, material=material)
            bulb.add_sphere_collision(sapien.Pose([0, 0, GLOBE_Z]), radius=GLOBE_RADIUS)
            bulb.add_sphere_visual(sapien.Pose([0, 0, GLOBE_Z]), radius=GLOBE_RADIUS, material=glass)
            bulb.initial_pose = sapien.Pose([-0.2, 0.1 * i, FLOOR])
            self.bulbs.append(bulb.build(f"light_bulb{i}"))

        lamp = self.scene.create_actor_builder()
        outer = SOCKET_INNER + SOCKET_WALL
        _add_socket(lamp, LAMP_HEIGHT, [0.3, 0.3, 0.35, 1.0], post_half=(outer, outer, (LAMP_HEIGHT - FLOOR) / 2))
        lamp.initial_pose = sapien.Pose([0.05, 0, 0])
        self.lamp = lamp.build_kinematic("lamp")

    def _place_task(self, env_idx, options: dict):
        rng = self._episode_rng
        self.lamp.set_pose(Pose.create_from_pq(p=[*rng.uniform([0.0, -0.1], [0.1, 0.1]), 0.0],
                                               q=euler2quat(0, 0, rng.uniform(0, np.pi / 2))))
        placed = []
        while len(placed) < N_HOLDERS:  # apart enough for the open gripper between them
            xy = rng.uniform([-0.25, -0.2], [-0.1, 0.2])
            if all(np.linalg.norm(xy - other) >= 0.12 for other in placed):
                placed.append(xy)
        for holder, bulb, xy in zip(self.holders, self.bulbs, placed):
            yaw = euler2quat(0, 0, rng.uniform(0, np.pi / 2))
            holder.set_pose(Pose.create_from_pq(p=[*xy, 0.0], q=yaw))
            bulb.set_pose(Pose.create_from_pq(p=[*xy, FLOOR], q=yaw))

    def socket_floor(self) -> np.ndarray:
        """World position of the centre of the lamp's socket floor."""
        return (self.lamp.pose.sp * sapien.Pose([0, 0, LAMP_HEIGHT])).p

    def named_holders(self) -> list[int]:
        """The holders in the colour the variation names (none, when another variation's colours were built)."""
        return [i for i, colour in enumerate(self.holder_colours) if colour == self.variation]

    def _in_lamp(self, bulb) -> bool:
        offset = bulb.pose.sp.p - self.socket_floor()
        return bool(np.linalg.norm(offset[:2]) < SOCKET_INNER - CAP_RADIUS + 0.002 and -0.005 < offset[2] < 0.01)

    def evaluate(self):
        named = self.named_holders()
        held = self.grasped(self.bulbs)[0]
        released = not held.any()
        success = any(self._in_lamp(self.bulbs[i]) for i in named) and released
        wrong = any(self._in_lamp(b) or bool(held[i])
                    for i, b in enumerate(self.bulbs) if i not in named)
        return {"success": torch.tensor([success]), "wrong_object": torch.tensor([wrong])}


CARRY_M = 0.03     # the bulb's cap passes this far above the lamp's socket walls...
RELEASE_M = 0.004  # ...and is let go this far above the socket's floor


def expert(env, seed=None):
    """Grasp the named holder's bulb by its neck from above, carry it over the lamp, lower its cap into
    the socket, let go and back off upwards. -1 if a motion cannot be planned."""
    from rvt2cli.record.motions import grasp_from_above, place_from_above, solver, top_down_grasp

    env.reset(seed=seed)
    scene = env.unwrapped
    planner = solver(env, speed=0.75)
    bulb = scene.bulbs[scene.named_holders()[0]]

    grasp = top_down_grasp(scene, bulb, at=(bulb.pose.sp * sapien.Pose([0, 0, NECK_Z])).p)
    if not grasp_from_above(planner, grasp):
        return -1

    socket = scene.socket_floor()

    def tcp_for(cap_above_floor: float) -> sapien.Pose:
        """The grasp's hand that holds the bulb, as it now sits in it, with its cap over the socket."""
        tcp, cap = scene.agent.tcp.pose.sp.p, bulb.pose.sp.p
        return sapien.Pose(tcp + socket + [0, 0, cap_above_floor] - cap, grasp.q)

    carry = SOCKET_DEPTH + CARRY_M
    lifted = sapien.Pose(grasp.p + [0, 0, tcp_for(carry).p[2] - grasp.p[2]], grasp.q)
    if planner.move_to_pose_with_screw(lifted) == -1:
        return -1
    return place_from_above(planner, lambda: tcp_for(carry), carry - RELEASE_M)
