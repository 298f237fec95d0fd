"""insert_onto_square_peg: put the square ring onto the spoke of the named colour (RLBench, 20 variations).

A square ring lies on the table; a plate carries three square spokes in a row, one of them in the named
colour and the two others in two different colours. The task succeeds when the ring encircles the named
spoke below its top (RLBench's four proximity sensors around the spoke's foot); a ring around another
spoke is a wrong target. The seed lays everything out; the variation picks the colours and which spoke
wears the named one.
"""

import numpy as np
import sapien
import torch
from transforms3d.euler import euler2quat
from scipy.spatial.transform import Rotation

from mani_skill.utils.registration import register_env
from mani_skill.utils.structs.pose import Pose
from rvt2cli.record.rlbench18.base import VariationEnv
from rvt2cli.record.rlbench18.colors import COLORS, colour_rng, distractor_colours, rgba

RING_OUTER = 0.045       # m, half the ring's outer side
RING_WALL = 0.012        # m, the wall's thickness
RING_HALF_HEIGHT = 0.0125
SPOKE_HALF = 0.014       # m, half a spoke's side: 19 mm clear of the ring's inner wall, room for a finger
SPOKE_HEIGHT = 0.045     # m above the plate
SPOKE_SPACING = 0.10     # m between neighbouring spokes
PLATE_HALF = (0.04, 0.17, 0.005)
N_SPOKES = 3
GREY = [0.35, 0.3, 0.25, 1.0]


@register_env("RVT2-InsertOntoSquarePeg-v1", max_episode_steps=400)
class InsertOntoSquarePegEnv(VariationEnv):
    num_variations = len(COLORS)

    def _build_task(self, options: dict):
        rng = colour_rng(self)
        named = int(rng.integers(N_SPOKES))
        others = iter(distractor_colours(rng, self.variation, N_SPOKES - 1))
        self.spoke_colours = [self.variation if i == named else next(others) for i in range(N_SPOKES)]

        ring = self.scene.create_actor_builder()
        along = RING_OUTER - RING_WALL / 2
        for sign in (-1, 1):  # two walls across x, two across y
            for half, centre in (([RING_WALL / 2, RING_OUTER, RING_HALF_HEIGHT], [sign * along, 0, 0]),
                                 ([RING_OUTER - RING_WALL, RING_WALL / 2, RING_HALF_HEIGHT], [0, sign * along, 0])):
                ring.add_box_collision(sapien.Pose(centre), half)
                ring.add_box_visual(sapien.Pose(centre), half,
                                    material=sapien.render.RenderMaterial(base_color=[0.85, 0.85, 0.8, 1]))
        ring.initial_pose = sapien.Pose([-0.2, 0, RING_HALF_HEIGHT])
        self.ring = ring.build("square_ring")

        spokes = self.scene.create_actor_builder()
        spokes.add_box_collision(sapien.Pose(), PLATE_HALF)
        spokes.add_box_visual(sapien.Pose(), PLATE_HALF, material=sapien.render.RenderMaterial(base_color=GREY))
        half = [SPOKE_HALF, SPOKE_HALF, SPOKE_HEIGHT / 2]
        for i, colour in enumerate(self.spoke_colours):
            centre = sapien.Pose([0, self._spoke_offset(i), PLATE_HALF[2] + SPOKE_HEIGHT / 2])
            spokes.add_box_collision(centre, half)
            spokes.add_box_visual(centre, half, material=sapien.render.RenderMaterial(base_color=rgba(colour)))
        spokes.initial_pose = sapien.Pose([0.05, 0, PLATE_HALF[2]])
        self.spokes = spokes.build_kinematic("square_spokes")

    @staticmethod
    def _spoke_offset(i: int) -> float:
        return (i - (N_SPOKES - 1) / 2) * SPOKE_SPACING

    def _place_task(self, env_idx, options: dict):
        rng = self._episode_rng
        plate_xy, plate_yaw = rng.uniform([0.0, -0.1], [0.08, 0.1]), rng.uniform(-np.pi / 8, np.pi / 8)
        ring_xy, ring_yaw = rng.uniform([-0.25, -0.2], [-0.16, 0.2]), rng.uniform(0, np.pi / 2)
        self.spokes.set_pose(Pose.create_from_pq(p=[*plate_xy, PLATE_HALF[2]], q=euler2quat(0, 0, plate_yaw)))
        self.ring.set_pose(Pose.create_from_pq(p=[*ring_xy, RING_HALF_HEIGHT], q=euler2quat(0, 0, ring_yaw)))

    # --- geometry the expert and the success check share ---------------------------------------------

    def spoke_top(self, i: int) -> np.ndarray:
        """World position of the centre of spoke i's top face."""
        return (self.spokes.pose.sp * sapien.Pose([0, self._spoke_offset(i), PLATE_HALF[2] + SPOKE_HEIGHT])).p

    def spoke_yaw(self) -> float:
        return float(Rotation.from_quat(self.spokes.pose.sp.q, scalar_first=True).as_euler("xyz")[2])

    def _encircles(self, i: int) -> torch.Tensor:
        """The ring sits around spoke i, its centre below the spoke's top."""
        ring = self.ring.pose.p[0].cpu().numpy()
        top = self.spoke_top(i)
        around = np.linalg.norm(ring[:2] - top[:2]) <= RING_OUTER - RING_WALL - SPOKE_HALF
        return torch.tensor([bool(around and ring[2] < top[2])])

    def named_spokes(self) -> list[int]:
        """The spokes in the colour the variation names (none, when another variation's colours were built)."""
        return [i for i, colour in enumerate(self.spoke_colours) if colour == self.variation]

    def evaluate(self):
        success, wrong = torch.zeros(1, dtype=torch.bool), torch.zeros(1, dtype=torch.bool)
        named = self.named_spokes()
        for i in range(N_SPOKES):
            if i in named:
                success |= self._encircles(i)
            else:
                wrong |= self._encircles(i)
        return {"success": success, "wrong_target": wrong}


HOVER_M = 0.03      # the ring's bottom passes this far above the spokes' tops
ENGAGE_M = 0.015    # ...and is released this far below the top, around the spoke: it drops onto the plate


def expert(env, seed=None):
    """Grasp the ring's wall nearest the robot from above, carry it over the named spoke turned to the
    spoke's square, lower it onto the spoke's top, let go and back off upwards. -1 if a motion cannot be
    planned."""
    from rvt2cli.record.motions import grasp_from_above, place_from_above, solver, top_down_grasp

    env.reset(seed=seed)
    scene = env.unwrapped
    planner = solver(env, speed=0.75)

    grasp = top_down_grasp(scene, scene.ring)
    closing = grasp.to_transformation_matrix()[:3, 1]
    ring_centre = scene.ring.pose.sp.p
    walls = [ring_centre + sign * (RING_OUTER - RING_WALL / 2) * closing for sign in (-1, 1)]
    wall = min(walls, key=lambda p: p[0])  # the wall nearer the robot's base (which stands at -x)
    grasp = sapien.Pose(wall, grasp.q)

    if not grasp_from_above(planner, grasp):
        return -1

    top = scene.spoke_top(scene.named_spokes()[0])
    ring_pose = scene.ring.pose.sp
    ring_yaw = Rotation.from_quat(ring_pose.q, scalar_first=True).as_euler("xyz")[2]
    quarter = np.pi / 2  # the ring is square: any quarter turn fits, so turn it the least
    yaw = scene.spoke_yaw() + quarter * np.round((ring_yaw - scene.spoke_yaw()) / quarter)

    def tcp_for(ring_centre_z: float) -> sapien.Pose:
        """The TCP pose that puts the ring, as it now sits in the hand, level over the spoke at this height."""
        goal = sapien.Pose([top[0], top[1], ring_centre_z], euler2quat(0, 0, yaw))
        return goal * scene.ring.pose.sp.inv() * scene.agent.tcp.pose.sp

    carry_z = top[2] + HOVER_M + RING_HALF_HEIGHT
    lifted = sapien.Pose(grasp.p + [0, 0, carry_z - ring_pose.p[2]], grasp.q)
    if planner.move_to_pose_with_screw(lifted) == -1:
        return -1
    # re-aimed from where the ring now hangs by a shift only, keeping the first aim's turn: mplib's screw
    # motions can fail on the hair's-breadth turns that the measured orientation would add
    turned = tcp_for(carry_z).q
    return place_from_above(planner, lambda: sapien.Pose(tcp_for(carry_z).p, turned), HOVER_M + ENGAGE_M)
