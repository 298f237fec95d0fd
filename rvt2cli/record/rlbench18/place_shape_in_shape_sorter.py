"""place_shape_in_shape_sorter: put the named shape into the shape sorter (RLBench, 5 variations).

Five shapes lie on the table: a cube, a cylinder, a triangular prism, a star and a moon, built from boxes
and a cylinder (the prism is a stepped stack of three boxes, the star two squares a quarter turn apart, the
moon a crescent of three boxes). The sorter is a hollow box with five square openings in its top, one per
shape. The task succeeds when the named shape lies inside the sorter (RLBench's proximity sensor in it);
another shape inside it or in the gripper is a wrong object. The variation only names the shape.
"""

import numpy as np
import sapien
import torch
from transforms3d.euler import euler2quat

from mani_skill.utils.registration import register_env
from mani_skill.utils.structs.pose import Pose
from rvt2cli.record.rlbench18.base import VariationEnv, build_fixture

SHAPES = ("cube", "cylinder", "triangular prism", "star", "moon")
SHAPE_COLOURS = ((0.85, 0.2, 0.2), (0.2, 0.45, 0.9), (0.2, 0.75, 0.3), (0.95, 0.8, 0.1), (0.6, 0.3, 0.8))
H = 0.015  # m, every shape's half height

# The sorter, in its own frame (origin at the centre of its footprint, on the table): a hollow box whose top
# plate has two rows of square openings, three in the row at +x and two at -x.
SORTER_HALF = (0.0725, 0.105)
SORTER_HEIGHT = 0.08
WALL = 0.01
PLATE = 0.01
HOLE_HALF = 0.025
HOLES = ((0.0325, -0.065), (0.0325, 0.0), (0.0325, 0.065), (-0.0325, -0.0325), (-0.0325, 0.0325))  # one per shape
SORTER_COLOUR = (0.75, 0.6, 0.4, 1.0)


def _shape_boxes(name: str) -> list[tuple[list[float], list[float], float]]:
    """The shape as boxes: (centre, half sizes, yaw) in its frame, whose origin is its centre."""
    if name == "cube":
        return [([0, 0, 0], [0.013, 0.013, H], 0.0)]
    if name == "triangular prism":  # three layers narrowing to the ridge
        return [([0, 0, -H + (2 * i + 1) * H / 3], [0.014, 0.015 * (3 - i) / 3, H / 3], 0.0) for i in range(3)]
    if name == "star":
        return [([0, 0, 0], [0.011, 0.011, H], 0.0), ([0, 0, 0], [0.011, 0.011, H], np.pi / 4)]
    if name == "moon":
        return [([-0.008, 0, 0], [0.005, 0.01, H], 0.0),
                ([0.001, -0.012, 0], [0.009, 0.004, H], -np.pi / 6), ([0.001, 0.012, 0], [0.009, 0.004, H], np.pi / 6)]
    raise ValueError(name)


def _gaps(holes: list[tuple[float, float]], lo: float, hi: float) -> list[tuple[float, float]]:
    """The intervals of [lo, hi] that the (sorted) holes leave covered."""
    edges = [lo, *[e for h in sorted(holes) for e in h], hi]
    return [(a, b) for a, b in zip(edges[::2], edges[1::2]) if b - a > 1e-9]


@register_env("RVT2-PlaceShapeInShapeSorter-v1", max_episode_steps=400)
class PlaceShapeInShapeSorterEnv(VariationEnv):
    num_variations = len(SHAPES)

    def _build_task(self, options: dict):
        self.shapes = []
        for name, colour in zip(SHAPES, SHAPE_COLOURS):
            builder = self.scene.create_actor_builder()
            material = sapien.render.RenderMaterial(base_color=[*colour, 1.0])
            if name == "cylinder":  # SAPIEN's cylinders lie along x: stand it up
                upright = sapien.Pose(q=[np.cos(np.pi / 4), 0, np.sin(np.pi / 4), 0])
                builder.add_cylinder_collision(upright, radius=0.014, half_length=H)
                builder.add_cylinder_visual(upright, radius=0.014, half_length=H, material=material)
            else:
                for centre, half, yaw in _shape_boxes(name):
                    builder.add_box_collision(sapien.Pose(centre, euler2quat(0, 0, yaw)), half)
                    builder.add_box_visual(sapien.Pose(centre, euler2quat(0, 0, yaw)), half, material=material)
            builder.initial_pose = sapien.Pose([-0.2, 0.1 * len(self.shapes), H])
            self.shapes.append(builder.build(name.replace(" ", "_")))

        hx, hy = SORTER_HALF
        wall_half_z = (SORTER_HEIGHT - PLATE) / 2
        boxes = [([0, 0, WALL / 2], [hx, hy, WALL / 2])]  # the floor
        for sign in (-1, 1):
            boxes.append(([sign * (hx - WALL / 2), 0, wall_half_z], [WALL / 2, hy, wall_half_z]))
            boxes.append(([0, sign * (hy - WALL / 2), wall_half_z], [hx - WALL, WALL / 2, wall_half_z]))
        # the top plate: bands along y between the rows of openings, and the pieces between openings
        rows = sorted({x for x, _ in HOLES})
        row_bands = [(x - HOLE_HALF, x + HOLE_HALF) for x in rows]
        plate_z = SORTER_HEIGHT - PLATE / 2
        for x0, x1 in _gaps(row_bands, -hx, hx):
            boxes.append(([(x0 + x1) / 2, 0, plate_z], [(x1 - x0) / 2, hy, PLATE / 2]))
        for x, (x0, x1) in zip(rows, row_bands):
            for y0, y1 in _gaps([(y - HOLE_HALF, y + HOLE_HALF) for hx_, y in HOLES if hx_ == x], -hy, hy):
                boxes.append(([x, (y0 + y1) / 2, plate_z], [HOLE_HALF, (y1 - y0) / 2, PLATE / 2]))
        self.sorter = build_fixture(self.scene, boxes, SORTER_COLOUR, "shape_sorter", at=(0.1, 0, 0))

    def _place_task(self, env_idx, options: dict):
        rng = self._episode_rng
        self.sorter.set_pose(Pose.create_from_pq(p=[*rng.uniform([0.06, -0.06], [0.12, 0.06]), 0.0],
                                                 q=euler2quat(0, 0, rng.uniform(-np.pi / 8, np.pi / 8))))
        placed = []
        while len(placed) < len(self.shapes):  # apart enough for the open gripper between neighbours
            xy = rng.uniform([-0.26, -0.22], [-0.08, 0.22])
            if all(np.linalg.norm(xy - other) >= 0.08 for other in placed):
                placed.append(xy)
        for shape, xy in zip(self.shapes, placed):
            shape.set_pose(Pose.create_from_pq(p=[*xy, H], q=euler2quat(0, 0, rng.uniform(0, 2 * np.pi))))

    def hole_top(self, i: int) -> np.ndarray:
        """World position of the centre of opening i, level with the sorter's top."""
        return (self.sorter.pose.sp * sapien.Pose([*HOLES[i], SORTER_HEIGHT])).p

    def _inside(self, shape) -> bool:
        local = (self.sorter.pose.sp.inv() * shape.pose.sp).p
        return bool(abs(local[0]) < SORTER_HALF[0] - WALL and abs(local[1]) < SORTER_HALF[1] - WALL
                    and local[2] < SORTER_HEIGHT - PLATE)

    def evaluate(self):
        held = self.grasped(self.shapes)[0]
        wrong = any(self._inside(s) or bool(held[i])
                    for i, s in enumerate(self.shapes) if i != self.variation)
        return {"success": torch.tensor([self._inside(self.shapes[self.variation])]),
                "wrong_object": torch.tensor([wrong])}


CARRY_M = 0.06    # the shape's bottom passes this far above the sorter's top...
RELEASE_M = 0.015  # ...and is let go this far above its opening


def expert(env, seed=None):
    """Grasp the named shape from above, carry it over its opening, let go and back off upwards. -1 if a
    motion cannot be planned."""
    from rvt2cli.record.motions import grasp_from_above, place_from_above, solver, top_down_grasp

    env.reset(seed=seed)
    scene = env.unwrapped
    planner = solver(env, speed=0.75)
    shape = scene.shapes[scene.variation]

    grasp = top_down_grasp(scene, shape, at=shape.pose.sp.p)
    if not grasp_from_above(planner, grasp):
        return -1

    hole = scene.hole_top(scene.variation)

    def tcp_for(bottom_above_top: float) -> sapien.Pose:
        """The grasp's hand that holds the shape, as it now sits in it, centred over its opening. (mplib's
        screw motions can fail on the hair's-breadth turns that a measured orientation would add.)"""
        tcp, held = scene.agent.tcp.pose.sp.p, shape.pose.sp.p
        return sapien.Pose(tcp + [hole[0] - held[0], hole[1] - held[1], hole[2] + bottom_above_top + H - held[2]],
                           grasp.q)

    lifted = sapien.Pose(grasp.p + [0, 0, tcp_for(CARRY_M).p[2] - grasp.p[2]], grasp.q)
    if planner.move_to_pose_with_screw(lifted) == -1:
        return -1
    return place_from_above(planner, lambda: tcp_for(CARRY_M), CARRY_M - RELEASE_M)
