"""Make `panda_visuals.npz`, the lighter Panda the cameras draw (`rvt2cli.record.robot_visuals`), from the meshes
ManiSkill draws: every part over `MIN_PART_TRIANGLES` triangles decimated by open3d's quadric decimation.

    python -m rvt2cli.record.make_robot_visuals

Run it again only when the ManiSkill pin changes (tests/test_record.py checks the shipped file matches). It needs
open3d; recording and evaluating do not.
"""

from pathlib import Path

import numpy as np

from rvt2cli.atomic import atomic_open
from rvt2cli.record.robot_visuals import MAX_PART_TRIANGLES, MESHES, MIN_PART_TRIANGLES, TRIANGLE_SHARE, mesh_parts, part_key
from rvt2cli.record.scene import make_env
from rvt2cli.tasks import get_task


def _decimate(vertices: np.ndarray, triangles: np.ndarray):
    """One part reduced to its share of triangles: (vertices, triangles, normals). Needs open3d (making the file)."""
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices.astype(np.float64)),
                                     o3d.utility.Vector3iVector(triangles.astype(np.int32)))
    # glTF splits vertices along hard edges; unwelded, the decimation would tear the surface open there
    mesh = mesh.merge_close_vertices(1e-6)
    mesh.remove_degenerate_triangles()
    mesh.remove_duplicated_triangles()
    share = min(MAX_PART_TRIANGLES, int(len(triangles) * TRIANGLE_SHARE))
    mesh = mesh.simplify_quadric_decimation(max(MIN_PART_TRIANGLES, share))
    mesh.compute_vertex_normals()
    return (np.asarray(mesh.vertices, np.float32), np.asarray(mesh.triangles, np.uint32),
            np.asarray(mesh.vertex_normals, np.float32))


def make_meshes(path: Path = MESHES) -> dict[str, dict[str, int]]:
    """Decimate the Panda's large visual mesh parts, as ManiSkill draws them, into `path` (needs open3d).
    Returns each robot's triangle counts {name: {"before": ..., "after": ...}}."""
    arrays, counts = {}, {}
    for task in ("push_cube", "insert_peg"):   # ManiSkill's two Pandas: "panda", "panda_wristcam" (a RealSense on the hand)
        env = make_env(get_task(task), lighten=False)
        env.reset(seed=0)
        robot = env.unwrapped.agent.robot
        before = after = 0
        for _, shape, index, part in mesh_parts(robot):
            vertices, triangles = np.asarray(part.vertices, np.float32), np.asarray(part.triangles, np.uint32)
            before += len(triangles)
            if len(triangles) <= MIN_PART_TRIANGLES:
                after += len(triangles)
                continue
            key = part_key(shape.filename, index, vertices, triangles)
            v, t, n = _decimate(vertices, triangles)
            arrays.update({f"{key}/vertices": v, f"{key}/triangles": t, f"{key}/normals": n})
            after += len(t)
        counts[robot.name] = {"before": before, "after": after}
        env.close()
    with atomic_open(path) as f:
        np.savez_compressed(f, **arrays)
    return counts


if __name__ == "__main__":
    print(f"{MESHES}: Panda visual triangles {make_meshes()}")
