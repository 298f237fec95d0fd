"""Run an exported rvt2 policy without rvt2: only numpy and onnxruntime (or torch for TorchScript).

    python examples/run_exported_policy.py policy/ [cloud.npz]

The cloud file holds `xyz` [N, 3] (metres, world frame) and `rgb` [N, 3] (uint8); without one, a
random cloud is used. The instruction is the manifest's first training instruction.
"""

import json
import sys
from pathlib import Path

import numpy as np
from safetensors.numpy import load_file

folder = Path(sys.argv[1])
manifest = json.loads((folder / "manifest.json").read_text())
n = manifest["max_points"]
task, info = next(iter(manifest["tasks"].items()))
bounds = np.asarray(info["scene_bounds"], np.float32)

if len(sys.argv) > 2:
    cloud = np.load(sys.argv[2])
    xyz, rgb = cloud["xyz"].astype(np.float32), cloud["rgb"].astype(np.float32) / 255.0
else:
    rng = np.random.default_rng(0)
    xyz = rng.uniform(bounds[:3], bounds[3:], size=(20000, 3)).astype(np.float32)
    rgb = rng.uniform(0, 1, size=(20000, 3)).astype(np.float32)
count = min(len(xyz), n)
inputs = {
    "xyz": np.zeros((1, n, 3), np.float32), "rgb": np.zeros((1, n, 3), np.float32),
    "num_points": np.array([count], np.int64),
    "proprio": np.array([[1.0, 0.04, 0.04, 1.0]], np.float32),  # gripper open, fingers, start of the episode
    "lang": load_file(str(folder / "instructions.safetensors"))["embeddings"][:1].astype(np.float32),
    "scene_bounds": bounds,
    "aim_offset": np.asarray(info.get("aim_offset", [0.0, 0.0, 0.0]), np.float32),  # the task's (rvt2 train --aim-held)
}
inputs["xyz"][0, :count], inputs["rgb"][0, :count] = xyz[:count], rgb[:count]

if manifest["format"] == "onnx":
    import onnxruntime as ort

    session = ort.InferenceSession(str(folder / manifest["file"]), providers=["CPUExecutionProvider"])
    position, quaternion, gripper_open, ignore_collisions, bins = session.run(None, inputs)
else:
    import torch

    policy = torch.jit.load(str(folder / manifest["file"]))
    outputs = policy(*(torch.from_numpy(inputs[k]) for k in manifest["inputs"]))
    position, quaternion, gripper_open, ignore_collisions, bins = (o.numpy() for o in outputs)

instruction = json.loads((folder / "instructions.json").read_text())[0]
print(json.dumps({"task": task, "instruction": instruction, "position": position[0].tolist(),
                  "quaternion_xyzw": quaternion[0].tolist(), "gripper_open": bool(gripper_open[0]),
                  "ignore_collisions": bool(ignore_collisions[0])}))
