"""Synthetic episodes written through the real episode API (for format tests that need no simulator)."""

import numpy as np

from rvt2cli.data import CameraFrame, Cloud, EpisodeMeta, EpisodeWriter, schemas, topics

JOINTS = [f"panda_joint{i}" for i in range(1, 8)] + ["panda_finger_joint1", "panda_finger_joint2"]


def random_episode(path, seed: int = 0, frames: int = 12, obs_every: int = 5, cameras=("front", "wrist"),
                   variation_index: int | None = 0):
    """`variation_index=None`: the instruction as rvt2 wrote it before format 1.2, without one."""
    rng = np.random.default_rng(seed)
    truth = {"qpos": [], "qvel": [], "tcp": [], "clouds": {}, "cams": {}, "sim": []}
    with EpisodeWriter(path, control_hz=20.0) as w:
        if variation_index is None:
            w._mcap.write_json(topics.INSTRUCTION, schemas.INSTRUCTION, {"text": "insert the peg into the box", "task": "insert_peg",
                                                                         "template_index": 0, "variation": {}}, 0)
        else:
            w.write_instruction("insert the peg into the box", task="insert_peg", template_index=0, variation={},
                                variation_index=variation_index)
        for t in range(frames):
            qpos = rng.normal(size=9).astype(np.float32)
            qvel = rng.normal(size=9).astype(np.float32)
            q = rng.normal(size=4)
            tcp = np.concatenate([rng.normal(size=3), q / np.linalg.norm(q)]).astype(np.float32)
            sim = {"actors": {"peg": rng.normal(size=13).astype(np.float32).tolist()},
                   "articulations": {"panda": rng.normal(size=31).astype(np.float32).tolist()}}
            w.write_frame(t, joint_names=JOINTS, joint_positions=qpos, joint_velocities=qvel,
                          gripper_width=0.04, gripper_command=1.0 if t < frames // 2 else -1.0,
                          action=None if t == frames - 1 else rng.normal(size=8).astype(np.float32),
                          contacts=["peg"] if t > frames // 2 else [], tcp_pose=tcp, sim_state=sim)
            truth["qpos"].append(qpos)
            truth["qvel"].append(qvel)
            truth["tcp"].append(tcp)
            truth["sim"].append(sim)
            if t % obs_every == 0:
                n = int(rng.integers(50, 200))
                cloud = Cloud(xyz=rng.normal(size=(n, 3)).astype(np.float32), rgb=rng.integers(0, 256, (n, 3), dtype=np.uint8))
                cams = {}
                for name in cameras:
                    q = rng.normal(size=4)
                    cams[name] = CameraFrame(
                        rgb=rng.integers(0, 256, (8, 10, 3), dtype=np.uint8),
                        depth=rng.uniform(0, 0.4, (8, 10)).astype(np.float32),
                        intrinsic=np.array([[50.0, 0, 5], [0, 50.0, 4], [0, 0, 1]]),
                        cam2world=np.concatenate([rng.uniform(-0.1, 0.1, size=3), q / np.linalg.norm(q)]),
                    )
                w.write_observation(t, cams, cloud)
                truth["clouds"][t] = cloud
                truth["cams"][t] = cams
        meta = EpisodeMeta(
            task="insert_peg", env_id="PegInsertionSide-v1", seed=seed, success=True, expert="test", num_frames=frames,
            control_hz=20.0, scene_bounds=[-0.5, -0.5, 0.0, 0.5, 0.5, 1.0], cameras=list(cameras),
            instruction="insert the peg into the box", versions={"test": "1"}, obs_frames=w.obs_frames,
        )
        w.finish(meta)
    truth["meta"] = meta
    return truth
