"""Predictions of a fixed checkpoint on the first observations of recorded episodes, as JSON, with whichever
rvt2cli is on the path: run it with two checkouts to check that a refactor leaves the policy's outputs
bit-identical.

    PYTHONPATH=OTHER_CHECKOUT python scripts/predictions.py RUN EPISODE... > a.json
    python scripts/predictions.py RUN EPISODE... > b.json && cmp a.json b.json
"""

import json
import sys

import numpy as np
import torch

torch.set_num_threads(1)
from rvt2cli.data import read_episode  # noqa: E402
from rvt2cli.eval.sources import PolicySource  # noqa: E402
from rvt2cli.tasks import get_task  # noqa: E402
from rvt2cli.train.checkpoint import load_policy  # noqa: E402
policy, ckpt = load_policy(sys.argv[1])
src = PolicySource(policy, ckpt)
out = []
for path in sys.argv[2:]:
    ep = read_episode(path)
    src.reset(get_task(ep.meta.task), ep.meta.seed, ep.instruction["text"])
    for frame in ep.obs_frames[:3]:
        cloud = ep.cloud(frame)
        a = src.next(cloud, ep.robot.gripper_command[frame] > 0, ep.robot.joint_positions[frame, -2:], 0)
        out.append([float(v) for v in np.asarray(a.position)] + [float(v) for v in np.asarray(a.quaternion)]
                   + [bool(a.gripper_open), bool(a.ignore_collisions)])
print(json.dumps(out))
