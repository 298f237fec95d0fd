"""The Panda's visual meshes, lightened for the cameras.

ManiSkill's Panda draws 136,000 triangles (12,000-22,000 per arm link; `panda_wristcam` 561,000). lavapipe,
the CPU renderer demos and evaluations use, spends most of a 4-camera capture on them (turn_tap: 222 ms per
capture at 128 px on a 2-vCPU Xeon, 79 with the meshes below), and captures are most of an episode's
recording. Every mesh part over `MIN_PART_TRIANGLES` triangles is drawn from `TRIANGLE_SHARE` of them (at
most `MAX_PART_TRIANGLES`), decimated by open3d's quadric decimation, which keeps the silhouette: in 128 px
views of the arm 0.07-0.15% of a fixed camera's depth pixels move by more than 1 mm, all on its outline
(`benchmarks/robot_visuals_bench.py`, tests/test_record.py). Smaller parts, the fingers among them, keep
every triangle: they fill the wrist camera's view.

The decimated parts ship with rvt2 (`panda_visuals.npz`, made by `python -m rvt2cli.record.make_robot_visuals`
from ManiSkill's meshes): every machine draws the same arm, and no machine needs open3d to record. A part
that ManiSkill draws differently from the one decimated (another ManiSkill) is drawn whole.

Only what the cameras draw changes: collision shapes, the planner's model and the robot's facts are ManiSkill's.
"""

import hashlib
import warnings
from functools import lru_cache
from pathlib import Path

import numpy as np

TRIANGLE_SHARE = 0.2
MIN_PART_TRIANGLES = 1000
MAX_PART_TRIANGLES = 5000   # panda_wristcam's RealSense housing has 425,000, a few pixels in a fixed camera's view
MESHES = Path(__file__).with_name("panda_visuals.npz")
DESCRIPTION = (f"visual mesh parts over {MIN_PART_TRIANGLES} triangles decimated to {TRIANGLE_SHARE:.0%}, at most "
               f"{MAX_PART_TRIANGLES} (rvt2cli.record.robot_visuals)")


def part_key(filename: str, index: int, vertices: np.ndarray, triangles: np.ndarray) -> str:
    """A mesh part by its file, its place in it and its geometry: another ManiSkill's mesh gets another key."""
    digest = hashlib.sha1(np.ascontiguousarray(vertices, np.float32).tobytes())
    digest.update(np.ascontiguousarray(triangles, np.uint32).tobytes())
    return f"{Path(filename).name}/{index}/{digest.hexdigest()[:16]}"


@lru_cache(maxsize=1)
def _shipped() -> dict[str, np.ndarray]:
    with np.load(MESHES) as data:
        return {name: data[name] for name in data.files}


def mesh_parts(robot):
    """(render body, shape, part index, part) for every triangle-mesh part of the articulation's links."""
    import sapien

    for link in robot.get_links():
        for obj in link._objs:   # one per sub-scene
            body = obj.entity.find_component_by_type(sapien.render.RenderBodyComponent)
            for shape in body.render_shapes if body is not None else ():
                if isinstance(shape, sapien.render.RenderShapeTriangleMesh):
                    for index, part in enumerate(shape.parts):
                        yield body, shape, index, part


def lighten_robot_visuals(robot) -> None:
    """Draw each link of a ManiSkill articulation with the shipped decimated parts where it has them: its render
    body is replaced by one holding those parts and the rest of its parts as they were."""
    import sapien

    shipped = _shipped()
    bodies: dict[int, tuple] = {}
    for body, shape, index, part in mesh_parts(robot):
        vertices, triangles = np.asarray(part.vertices, np.float32), np.asarray(part.triangles, np.uint32)
        key = part_key(shape.filename, index, vertices, triangles) if len(triangles) > MIN_PART_TRIANGLES else None
        if key is not None and f"{key}/vertices" in shipped:
            v, t, n = (shipped[f"{key}/{name}"] for name in ("vertices", "triangles", "normals"))
            uv = np.zeros((len(v), 2), np.float32)   # untextured: the colour is the material's
        else:
            if key is not None:
                warnings.warn(f"{key}: a Panda mesh part rvt2 has no lighter version of (another ManiSkill than "
                              f"{MESHES.name} was made from?); drawn whole", stacklevel=2)
            v, t = vertices, triangles
            n, uv = np.asarray(part.get_vertex_normal(), np.float32), np.asarray(part.get_vertex_uv(), np.float32)
        light = sapien.render.RenderShapeTriangleMesh(v, t, n, uv, part.material)
        light.local_pose, light.scale, light.front_face = shape.local_pose, shape.scale, shape.front_face
        bodies.setdefault(id(body), (body, []))[1].append(light)
    for old, shapes in bodies.values():
        new = sapien.render.RenderBodyComponent()
        new.name = old.name
        for shape in shapes:
            new.attach(shape)
        entity = old.entity
        entity.remove_component(old)
        entity.add_component(new)
