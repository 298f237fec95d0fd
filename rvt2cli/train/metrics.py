"""How close a policy's predictions are to the keyframes: translation error (mm), rotation error
(degrees), gripper and collision-flag accuracy. Used for validation during training."""

import numpy as np
import torch

from rvt2cli.model.rotation import angle_between, bins_to_quaternion
from rvt2cli.train.batches import PackedSamples, make_batch


@torch.no_grad()
def prediction_errors(policy, packed: PackedSamples, indices=None, batch_size: int = 8, autocast: bool = False) -> dict:
    cfg = policy.cfg
    indices = np.arange(len(packed)) if indices is None else np.asarray(indices)
    trans, rot, grip, coll = [], [], [], []
    was_training = policy.training
    policy.eval()
    for start in range(0, len(indices), batch_size):
        idx = indices[start:start + batch_size]
        batch = make_batch(packed, idx, cfg)
        with torch.autocast(device_type="cuda", dtype=torch.bfloat16, enabled=autocast):
            pred = policy.predict(batch.obs)
        error_cube = (pred.position.float() - batch.position).norm(dim=-1).cpu().numpy()
        trans.append(error_cube * batch.half * 1000.0)
        rot.append(angle_between(bins_to_quaternion(pred.rot_bins.cpu().numpy(), cfg.rotation_bins), batch.quaternion))
        grip.append((pred.gripper_open.long() == batch.gripper).cpu().numpy())
        coll.append((pred.ignore_collisions.long() == batch.collision).cpu().numpy())
    policy.train(was_training)
    trans, rot = np.concatenate(trans), np.concatenate(rot)
    return {"samples": int(len(indices)), "translation_mm": float(trans.mean()), "translation_mm_median": float(np.median(trans)),
            "rotation_deg": float(rot.mean()), "gripper_accuracy": float(np.concatenate(grip).mean()),
            "collision_accuracy": float(np.concatenate(coll).mean())}
