"""The robot's collision geometry, as the motion planner sees it, for clearing the planner's cloud.

A planner refuses to start from a configuration that collides with its world ("Invalid start state"),
and refuses a goal that does. Where the cloud comes from cameras, both happen without anything being
wrong: points of the robot itself that segmentation missed, scene points the wrist camera's housing
rests against, the rim of a hole the fingers end beside. So the planner's cloud leaves out every point
inside (or within `pad` of) a robot link as the robot stands at the start of a motion, and every point
near the links that ride with the gripper where the gripper will stand at its goal. Collision
avoidance then guards the way between the two, not its ends.

The geometry is the URDF's own `<collision>` elements (meshes, boxes, cylinders, spheres), each taken
as its convex hull: a point is inside the padded hull where its distance above every face plane is
below `pad` (a slightly larger region than the exact offset surface at the hull's edges and corners,
which errs on the side of clearing). The same code serves a real robot: its URDF and joint state.

A scene cloud has tens of thousands of points and the Panda's hulls 200-300 faces each, so each hull
first keeps the points inside a ball around its padded region (all balls' distances in one matrix product);
only those are tested against its faces.
"""

import functools
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import linprog
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from rvt2cli.errors import UserError


def _origin(element) -> np.ndarray:
    """4x4 transform of a URDF <origin> (fixed-axis roll-pitch-yaw, as URDF defines it)."""
    transform = np.eye(4)
    origin = element.find("origin") if element is not None else None
    if origin is not None:
        transform[:3, :3] = Rotation.from_euler("xyz", [float(v) for v in origin.get("rpy", "0 0 0").split()]).as_matrix()
        transform[:3, 3] = [float(v) for v in origin.get("xyz", "0 0 0").split()]
    return transform


def _shape_vertices(geometry, urdf_dir: Path) -> np.ndarray:
    """Vertices [N, 3] whose convex hull is the shape (in the shape's own frame)."""
    box, cylinder, sphere, mesh = (geometry.find(tag) for tag in ("box", "cylinder", "sphere", "mesh"))
    if box is not None:
        half = np.array([float(v) for v in box.get("size").split()]) / 2
        return np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * half
    if cylinder is not None:
        r, half = float(cylinder.get("radius")), float(cylinder.get("length")) / 2
        angle = np.linspace(0, 2 * np.pi, 16, endpoint=False)
        ring = np.stack([r * np.cos(angle), r * np.sin(angle)], axis=1) / np.cos(np.pi / 16)  # circumscribed
        return np.concatenate([np.hstack([ring, np.full((16, 1), z)]) for z in (-half, half)])
    if sphere is not None:  # the cube around it
        return np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * float(sphere.get("radius"))
    if mesh is not None:
        import trimesh

        name = mesh.get("filename").removeprefix("package://")
        path = urdf_dir / name
        if not path.is_file():
            raise UserError(f"{urdf_dir}: collision mesh {name} not found next to the URDF")
        scale = np.array([float(v) for v in mesh.get("scale", "1 1 1").split()])
        return np.asarray(trimesh.load(path, force="mesh").vertices) * scale
    raise UserError(f"{urdf_dir}: a <collision> geometry of a kind the URDF format does not define")


@dataclass(frozen=True)
class Hull:
    """A convex shape in its link's frame: inside where `planes @ [p, 1] <= 0` for every row."""

    planes: np.ndarray  # [F, 4]: unit outward normal, offset

    @staticmethod
    def of(vertices: np.ndarray) -> "Hull":
        return Hull(ConvexHull(vertices).equations)

    def ball(self, pad: float) -> tuple[np.ndarray, float]:
        """(centre, radius) of a ball, in the hull's frame, that holds its padded region
        {p : planes @ [p, 1] < pad}: around the region's axis-aligned box, found by six linear programs."""
        ends = []
        for direction in np.vstack([np.eye(3), -np.eye(3)]):  # min x, y, z, then -max x, y, z
            solved = linprog(direction, A_ub=self.planes[:, :3], b_ub=pad - self.planes[:, 3], bounds=[(None, None)] * 3,
                             method="highs")
            if solved.status != 0:
                raise ValueError(f"the padded hull has no bounding box (linprog: {solved.message})")
            ends.append(solved.fun)
        low, high = np.array(ends[:3]), -np.array(ends[3:])
        return (low + high) / 2, float(np.linalg.norm(high - low) / 2) + 1e-6  # the solver's tolerance


class RobotGeometry:
    """Each link's collision hulls, and which links ride with the tool centre point."""

    def __init__(self, hulls: dict[str, list[Hull]], rides_with_tcp: frozenset[str]):
        self.hulls, self.rides_with_tcp = hulls, rides_with_tcp
        self._balls: dict[float, dict[str, list[tuple[np.ndarray, float]]]] = {}  # per pad, each link's hulls'

    def balls(self, pad: float) -> dict[str, list[tuple[np.ndarray, float]]]:
        """Each link's hulls' bounding balls (`Hull.ball`) for this pad, computed once."""
        if pad not in self._balls:
            self._balls[pad] = {name: [hull.ball(pad) for hull in hulls] for name, hulls in self.hulls.items()}
        return self._balls[pad]

    @staticmethod
    @functools.cache  # every evaluation episode builds an executor; the meshes load once per process
    def from_urdf(urdf: str | Path, last_arm_joint: str) -> "RobotGeometry":
        """`last_arm_joint`: the links after it (the hand, fingers, a wrist camera) move with the TCP."""
        urdf = Path(urdf)
        root = ET.parse(urdf).getroot()
        hulls: dict[str, list[Hull]] = {}
        for link in root.findall("link"):
            shapes = []
            for collision in link.findall("collision"):
                vertices = _shape_vertices(collision.find("geometry"), urdf.parent)
                placed = vertices @ _origin(collision)[:3, :3].T + _origin(collision)[:3, 3]
                shapes.append(Hull.of(placed))
            if shapes:
                hulls[link.get("name")] = shapes
        children: dict[str, list[str]] = {}
        after = None
        for joint in root.findall("joint"):
            parent, child = joint.find("parent").get("link"), joint.find("child").get("link")
            children.setdefault(parent, []).append(child)
            if joint.get("name") == last_arm_joint:
                after = child
        if after is None:
            raise UserError(f"{urdf}: no joint named {last_arm_joint} (the robot's last arm joint)")
        rides, todo = set(), [after]
        while todo:
            link = todo.pop()
            rides.add(link)
            todo += children.get(link, [])
        return RobotGeometry(hulls, frozenset(rides))

    def near(self, points: np.ndarray, link_poses: dict[str, np.ndarray], pad: float) -> np.ndarray:
        """bool [N]: the points within `pad` of a hull of the given links, each at its 4x4 world pose."""
        hit = np.zeros(len(points), dtype=bool)
        balls = self.balls(pad)
        placed = [(pose, hull, pose[:3, :3] @ centre + pose[:3, 3], radius) for name, pose in link_poses.items()
                  for hull, (centre, radius) in zip(self.hulls.get(name, ()), balls.get(name, ()))]
        if not placed:
            return hit
        # every point's squared distance to every ball's centre as one matrix product, |p|^2 - 2 p.c + |c|^2:
        # five times faster than a pass over the points per ball. Its rounding (~1e-15) is far inside the
        # slack added here, so it keeps a superset of each ball's points, and the faces decide as before.
        centres = np.array([centre for _, _, centre, _ in placed])
        squared = centres @ (-2 * points.T)
        squared += np.einsum("ij,ij->i", points, points)[None, :]
        squared += np.einsum("ij,ij->i", centres, centres)[:, None]
        for (pose, hull, _, radius), distances in zip(placed, squared):
            inside = np.flatnonzero(distances < radius * radius + 1e-9)
            local = (points[inside] - pose[:3, 3]) @ pose[:3, :3]   # world -> link frame
            above = local @ hull.planes[:, :3].T + hull.planes[:, 3]
            hit[inside[above.max(axis=1, initial=-np.inf) < pad]] = True
        return hit
