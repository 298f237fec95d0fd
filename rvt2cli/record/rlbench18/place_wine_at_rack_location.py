"""place_wine_at_rack_location: put the wine bottle in the named slot of the rack (RLBench, 3 variations:
middle, left, right, in RLBench's order; left is the robot's left, +y).

The bottle (a square-sided body with a cylinder for its neck) lies on its side on the table, its neck
pointing away from the robot within 60 degrees; the rack is a plate with three cradles side by side, each
two rails along the rack's x on which a bottle lies lengthwise. The task succeeds when the bottle lies in
the named cradle and the gripper has let it go (RLBench's proximity sensor at that location, and nothing
grasped); a bottle in another cradle is a wrong target. The variation only names the slot.
"""

import numpy as np
import sapien
import torch
from transforms3d.euler import euler2quat
from scipy.spatial.transform import Rotation

from mani_skill.utils.registration import register_env
from mani_skill.utils.structs.pose import Pose
from rvt2cli.record.rlbench18.base import VariationEnv, build_fixture

LOCATIONS = ("middle", "left", "right")
SLOT_Y = {"middle": 0.0, "left": 0.09, "right": -0.09}  # in the rack's frame
BODY_HALF_WIDTH, BODY_HALF = 0.024, 0.06
NECK_RADIUS, NECK_HALF = 0.011, 0.03
BOTTLE_DENSITY = 400  # kg/m^3: a 0.12 kg bottle
NECK_ALONG_X = [np.cos(np.pi / 4), 0, np.sin(np.pi / 4), 0]  # the bottle's frame lying down: its z (the neck) along x
RACK_PLATE = (0.08, 0.14, 0.005)   # half sizes
RAIL_HALF = (0.07, 0.005, 0.0125)  # rails along x
RAIL_GAP = 0.032                   # m between a cradle's two rails (inner faces): the body rests on them
RAIL_TOP = 2 * RACK_PLATE[2] + 2 * RAIL_HALF[2]
WOOD_COLOUR = (0.55, 0.35, 0.2, 1.0)    # the rack
LYING_Z = RAIL_TOP + BODY_HALF_WIDTH  # where a bottle's axis lies in a cradle


@register_env("RVT2-PlaceWineAtRackLocation-v1", max_episode_steps=400)
class PlaceWineAtRackLocationEnv(VariationEnv):
    num_variations = len(LOCATIONS)

    def _build_task(self, options: dict):
        glass = sapien.render.RenderMaterial(base_color=[0.1, 0.35, 0.15, 1.0])
        bottle = self.scene.create_actor_builder()
        # a square-sided body: the fingers' contacts with a round one (cylinder or capsule, whatever its
        # friction) jitter the wrist faster than the keyframe rule's rest, so no motion holding it would end
        # in a keyframe. It lies on a side, so it does not roll either.
        body = [BODY_HALF_WIDTH, BODY_HALF_WIDTH, BODY_HALF]
        bottle.add_box_collision(sapien.Pose(), body, density=BOTTLE_DENSITY)
        bottle.add_box_visual(sapien.Pose(), body, material=glass)
        neck = sapien.Pose([0, 0, BODY_HALF + NECK_HALF], [np.cos(np.pi / 4), 0, -np.sin(np.pi / 4), 0])  # cylinders lie along x
        bottle.add_cylinder_collision(neck, radius=NECK_RADIUS, half_length=NECK_HALF, density=BOTTLE_DENSITY)
        bottle.add_cylinder_visual(neck, radius=NECK_RADIUS, half_length=NECK_HALF, material=glass)
        bottle.initial_pose = sapien.Pose([-0.2, 0, BODY_HALF_WIDTH], NECK_ALONG_X)
        self.bottle = bottle.build("wine_bottle")  # its frame: the body's centre, z along the neck

        boxes = [([0, 0, RACK_PLATE[2]], RACK_PLATE)]
        for y in SLOT_Y.values():
            for side in (-1, 1):
                boxes.append(([0, y + side * (RAIL_GAP / 2 + RAIL_HALF[1]), 2 * RACK_PLATE[2] + RAIL_HALF[2]], RAIL_HALF))
        self.rack = build_fixture(self.scene, boxes, WOOD_COLOUR, "wine_rack", at=(0.1, 0, 0))

    def _place_task(self, env_idx, options: dict):
        rng = self._episode_rng
        self.rack.set_pose(Pose.create_from_pq(p=[*rng.uniform([0.06, -0.05], [0.12, 0.05]), 0.0],
                                               q=euler2quat(0, 0, rng.uniform(-np.pi / 12, np.pi / 12))))
        lying = sapien.Pose(q=euler2quat(0, 0, rng.uniform(-np.pi / 3, np.pi / 3))) * sapien.Pose(q=NECK_ALONG_X)
        self.bottle.set_pose(Pose.create_from_pq(p=[*rng.uniform([-0.22, -0.15], [-0.12, 0.15]), BODY_HALF_WIDTH],
                                                 q=lying.q))

    def slot_centre(self, location: str) -> np.ndarray:
        """World position of a bottle's centre lying in this cradle."""
        return (self.rack.pose.sp * sapien.Pose([0, SLOT_Y[location], LYING_Z])).p

    def rack_axes(self) -> np.ndarray:
        """The rack's x, y, z axes in the world (columns)."""
        return self.rack.pose.sp.to_transformation_matrix()[:3, :3]

    def _lies_in(self, location: str) -> bool:
        local = (self.rack.pose.sp.inv() * self.bottle.pose.sp)
        axis = Rotation.from_quat(local.q, scalar_first=True).apply([0, 0, 1])
        return bool(abs(local.p[1] - SLOT_Y[location]) < RAIL_GAP / 2 and abs(local.p[0]) < RAIL_HALF[0]
                    and local.p[2] < LYING_Z + 0.01 and abs(axis[0]) > np.cos(np.radians(20)))

    def evaluate(self):
        named = LOCATIONS[self.variation]
        released = not bool(self.grasped([self.bottle])[0, 0])
        return {"success": torch.tensor([self._lies_in(named) and released]),
                "wrong_target": torch.tensor([any(self._lies_in(o) for o in LOCATIONS if o != named)])}


CARRY_M = 0.06     # the bottle passes this far above where it rests in its cradle...
RELEASE_M = 0.005  # ...and is let go this far above where it rests


def expert(env, seed=None):
    """Grasp the bottle's body from above, carry it over the named cradle turned along the rack, lower it
    onto the rails, let go and back off upwards. -1 if a motion cannot be planned."""
    from rvt2cli.record.motions import grasp_from_above, place_from_above, solver, top_down_grasp

    env.reset(seed=seed)
    scene = env.unwrapped
    planner = solver(env, speed=0.75)
    location = LOCATIONS[scene.variation]

    grasp = top_down_grasp(scene, scene.bottle, at=scene.bottle.pose.sp.p)  # at the body's centre
    if not grasp_from_above(planner, grasp):
        return -1

    # over the cradle the fingers close across the rack (along its y), whichever way turns the hand least
    rack_y = scene.rack_axes()[:, 1]
    closing = grasp.to_transformation_matrix()[:3, 1]
    placing = scene.agent.build_grasp_pose(np.array([0.0, 0.0, -1.0]), rack_y * np.sign(rack_y @ closing), [0, 0, 0]).q

    def tcp_for(above: float) -> sapien.Pose:
        """The placing hand's pose that lays the bottle, as it now sits in it, over its cradle this much higher."""
        in_hand = scene.agent.tcp.pose.sp.inv() * scene.bottle.pose.sp
        return sapien.Pose(scene.slot_centre(location) + [0, 0, above] - (sapien.Pose(q=placing) * in_hand).p, placing)

    lifted = sapien.Pose(grasp.p + [0, 0, 0.06], grasp.q)  # clear of the rails (higher, the arm nears a singularity)
    if planner.move_to_pose_with_screw(lifted) == -1:
        return -1
    return place_from_above(planner, lambda: tcp_for(CARRY_M), CARRY_M - RELEASE_M)
