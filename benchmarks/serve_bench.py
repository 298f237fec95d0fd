"""`rvt2 serve` under load: requests per second and latency for 1, 4 and 16 robots calling at once.

    python -m benchmarks.serve_bench [--device cuda] [--config rvt2] [--clients 1,4,16] [--max-batch 16,1]
                                     [--seconds 20] [--cameras 4] [--image-size 128] [--json out.json] [--quick]

What a robot does, end to end: each client is a process of its own with `rvt2_client.PolicyClient` (no torch),
sending the same RGB-D frames again and again (4 cameras of 128 x 128 by default, rvt2-18's rig) and waiting
for each keyframe before the next. The server is `rvt2 serve` in a process of its own, as a user starts it,
on a checkpoint of the config's shape with random weights (speed depends on sizes, not on the weights).
Latency is the client's, from sending the frames to holding the keyframe: the message, the checks, the
fusion of the cameras, the wait for a batch, the forward pass and the reply. Each setting runs `--seconds`
after a warm-up; `--max-batch 1` is the server without dynamic batching, for comparison. --quick: a tiny
CPU configuration (CI).

Only numpy and rvt2_client are imported at the top: the client processes (spawned) import this module.
"""

import argparse
import json
import multiprocessing
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from rvt2_client import PolicyClient

TASK = "bench_task"
INSTRUCTION = "put the block on the plate"
TOKEN = "serve-bench-token-not-secret"


# --- what a robot sends --------------------------------------------------------------------------------

def look_at_pose(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """x y z qx qy qz qw of a camera at `eye` looking at `target`, OpenCV axes (x right, y down, z forward)."""
    from scipy.spatial.transform import Rotation

    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.concatenate([eye, Rotation.from_matrix(np.stack([x, y, z], axis=1)).as_quat()])


def synthetic_frames(bounds, cameras: int, size: int, seed: int = 0) -> dict[str, dict]:
    """RGB-D frames of cameras around the scene, 1 m from its centre, looking down at a table 2 cm above the
    bounds' floor (depth: where each pixel's ray meets it, a tenth of the pixels without a return), random
    colours."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(bounds[:3]), np.asarray(bounds[3:])
    centre = (lo + hi) / 2
    table = lo[2] + 0.02
    focal = size / (2 * np.tan(np.radians(30)))   # 60 degrees across
    K = np.array([[focal, 0, size / 2 - 0.5], [0, focal, size / 2 - 0.5], [0, 0, 1]])
    v, u = np.mgrid[0:size, 0:size]
    rays = np.stack([(u - K[0, 2]) / focal, (v - K[1, 2]) / focal, np.ones_like(u, float)], axis=-1)
    frames = {}
    for i in range(cameras):
        angle = 2 * np.pi * i / cameras
        eye = centre + np.array([np.cos(angle), np.sin(angle), 0.6])
        pose = look_at_pose(eye, np.array([centre[0], centre[1], table]))
        from scipy.spatial.transform import Rotation

        down = rays @ Rotation.from_quat(pose[3:]).as_matrix().T    # world direction of each pixel (z along the axis = 1)
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = np.where(down[..., 2] < 0, (table - eye[2]) / down[..., 2], 0.0)
        depth = np.clip(depth, 0, 5).astype(np.float32)
        depth[rng.random(depth.shape) < 0.1] = 0.0   # a real camera's holes: each seed's cloud has its own size
        frames[f"camera{i}"] = {"rgb": rng.integers(0, 256, (size, size, 3), dtype=np.uint8), "depth": depth,
                                "intrinsic": K, "cam2world": pose}
    return frames


# --- a robot ------------------------------------------------------------------------------------------

def robot(url: str, frames: dict, start_at: float, stop_at: float, results) -> None:
    """One client process: requests back to back until `stop_at`; the latencies of those sent after `start_at`."""
    latencies = []
    with PolicyClient(url, token=TOKEN, timeout=600) as client:
        while (now := time.time()) < stop_at:
            sent = time.perf_counter()
            client.predict(frames, INSTRUCTION, gripper_open=True, task=TASK)
            if now >= start_at:
                latencies.append(time.perf_counter() - sent)
    results.put(latencies)


# --- the server and the measurement -------------------------------------------------------------------

def random_checkpoint(config: str, folder: Path, tasks: dict[str, list[float]] | None = None) -> Path:
    """A checkpoint of `config`'s shape with random weights, for `tasks` (name -> scene bounds; default: one task
    in the default bounds, with one instruction's embedding; other instructions are embedded when asked)."""
    import torch

    from rvt2cli.model.config import get_config
    from rvt2cli.model.observation import LANG_DIM
    from rvt2cli.model.policy import RVT2Policy
    from rvt2cli.tasks import DEFAULT_SCENE_BOUNDS
    from rvt2cli.train.checkpoint import save_checkpoint

    cfg = get_config(config)
    torch.manual_seed(0)
    instructions = {} if tasks else {INSTRUCTION: torch.randn(cfg.lang_tokens, LANG_DIM)}
    tasks = tasks or {TASK: list(DEFAULT_SCENE_BOUNDS)}
    save_checkpoint(folder, 0, RVT2Policy(cfg), cfg, {"tasks": list(tasks), "bounds": tasks}, instructions, {})
    return folder


def batch_parity(checkpoint: Path, device: str, cameras: int, size: int, requests: int = 16) -> dict:
    """The model's batched forward against one request at a time, on this device: inputs of different
    clouds (sizes too) and gripper states, answered together and alone."""
    import torch
    from scipy.spatial.transform import Rotation

    from rvt2cli.deploy import CameraFrame, KeyframePolicy
    from rvt2cli.tasks import DEFAULT_SCENE_BOUNDS

    policy = KeyframePolicy.load(checkpoint, device)
    inputs = [policy.inputs({n: CameraFrame(**f) for n, f in synthetic_frames(DEFAULT_SCENE_BOUNDS, cameras, size, seed).items()},
                            INSTRUCTION, gripper_open=seed % 2 == 0, keyframes_done=seed % 5, task=TASK)
              for seed in range(requests)]
    alone = [policy.predict_inputs([i])[0] for i in inputs]
    together = policy.predict_inputs(inputs)
    positions = [1000 * float(np.linalg.norm(np.subtract(a.position, b.position))) for a, b in zip(alone, together)]
    angles = [float(np.degrees((Rotation.from_quat(a.quaternion).inv() * Rotation.from_quat(b.quaternion)).magnitude()))
              for a, b in zip(alone, together)]
    del policy
    if device.startswith("cuda"):
        torch.cuda.empty_cache()
    return {"requests": requests, "cloud_points": sorted({len(i.cloud) for i in inputs}), "identical": alone == together,
            "max_position_mm": max(positions), "max_rotation_deg": max(angles),
            "same_flags": all((a.gripper_open, a.ignore_collisions) == (b.gripper_open, b.ignore_collisions)
                              for a, b in zip(alone, together))}


class Server:
    def __init__(self, checkpoint: Path, device: str, max_batch: int, max_wait_ms: float, log: Path):
        token = log.parent / "token"
        token.write_text(TOKEN)
        token.chmod(0o600)
        self.process = subprocess.Popen([sys.executable, "-m", "rvt2cli", "serve", "--checkpoint", str(checkpoint), "--port", "0",
                                         "--device", device, "--token-file", str(token), "--max-batch", str(max_batch),
                                         "--max-wait-ms", str(max_wait_ms)],
                                        stdout=subprocess.PIPE, stderr=open(log, "w"), text=True)
        line = self.process.stdout.readline()
        if " on ws://" not in line:
            raise SystemExit(f"rvt2 serve did not start: {log.read_text()[-2000:]}")
        self.url = line.split(" on ", 1)[1].split(";")[0]

    def batching(self) -> dict:
        with PolicyClient(self.url, token=TOKEN) as client:
            return client.info()["batching"]

    def gpu_memory(self) -> dict | None:
        with PolicyClient(self.url, token=TOKEN) as client:
            return client.info().get("gpu_memory_mib")

    def stop(self) -> None:
        self.process.terminate()
        self.process.wait(timeout=120)


def measure(server: Server, frames: dict, clients: int, seconds: float, warmup: float) -> dict:
    context = multiprocessing.get_context("spawn")
    results = context.Queue()
    start_at = time.time() + warmup + 2.0   # the processes' start (imports) comes first
    stop_at = start_at + seconds
    processes = [context.Process(target=robot, args=(server.url, frames, start_at, stop_at, results)) for _ in range(clients)]
    for p in processes:
        p.start()
    while time.time() < start_at:
        time.sleep(0.05)
    before = server.batching()
    latencies = [x for _ in processes for x in results.get(timeout=seconds + warmup + 900)]
    after = server.batching()
    for p in processes:
        p.join()
    answered, batches = after["requests"] - before["requests"], after["batches"] - before["batches"]
    ms = sorted(1000 * x for x in latencies)
    return {"clients": clients, "requests": len(ms), "seconds": seconds, "requests_per_s": len(ms) / seconds,
            "p50_ms": statistics.median(ms), "p99_ms": ms[min(len(ms) - 1, int(0.99 * len(ms)))],
            "mean_batch": answered / batches if batches else None}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--config", default="rvt2", help="model config (rvt2, rvt, small)")
    parser.add_argument("--clients", default="1,4,16", help="robots calling at once, comma-separated")
    parser.add_argument("--max-batch", default="16,1", help="server settings to compare, comma-separated (1: no batching)")
    parser.add_argument("--max-wait-ms", type=float, default=5.0)
    parser.add_argument("--seconds", type=float, default=20.0, help="measured time per setting")
    parser.add_argument("--warmup", type=float, default=5.0, help="seconds of requests before the measurement")
    parser.add_argument("--cameras", type=int, default=4)
    parser.add_argument("--image-size", type=int, default=128)
    parser.add_argument("--quick", action="store_true", help="the small config, 2 and 1 clients, 3 s each (CI)")
    parser.add_argument("--json", type=Path, help="write the results and the machine description here")
    args = parser.parse_args()
    if args.quick:
        args.config, args.clients, args.max_batch, args.seconds, args.warmup, args.cameras, args.image_size = \
            "small", "1,2", "4", 3.0, 1.0, 2, 64
    from benchmarks.machine import describe
    from rvt2cli.deploy import CameraFrame, KeyframePolicy
    from rvt2cli.tasks import DEFAULT_SCENE_BOUNDS

    frames = synthetic_frames(DEFAULT_SCENE_BOUNDS, args.cameras, args.image_size)
    with tempfile.TemporaryDirectory() as tmp:
        checkpoint = random_checkpoint(args.config, Path(tmp) / "run")
        points = len(KeyframePolicy.cloud({n: CameraFrame(**f) for n, f in frames.items()}, list(DEFAULT_SCENE_BOUNDS)))
        parity = batch_parity(checkpoint, args.device, args.cameras, args.image_size)
        print(f"batched forward against one at a time ({parity['requests']} requests, clouds of {parity['cloud_points'][0]:,} to "
              f"{parity['cloud_points'][-1]:,} points): identical {parity['identical']}, positions within "
              f"{parity['max_position_mm']:.3g} mm, rotations within {parity['max_rotation_deg']:.3g} degrees")
        runs, memory = [], {}
        print(f"{args.config} on {args.device}: {args.cameras} cameras of {args.image_size} px, {points:,} points a request")
        print(f"{'max batch':>9} {'clients':>7} {'requests/s':>10} {'p50 ms':>8} {'p99 ms':>8} {'mean batch':>10}")
        for max_batch in (int(b) for b in args.max_batch.split(",")):
            server = Server(checkpoint, args.device, max_batch, args.max_wait_ms, Path(tmp) / f"serve_{max_batch}.log")
            try:
                for clients in (int(c) for c in args.clients.split(",")):
                    run = {"max_batch": max_batch, "max_wait_ms": args.max_wait_ms,
                           **measure(server, frames, clients, args.seconds, args.warmup)}
                    runs.append(run)
                    print(f"{max_batch:>9} {clients:>7} {run['requests_per_s']:>10.1f} {run['p50_ms']:>8.1f} {run['p99_ms']:>8.1f} "
                          f"{run['mean_batch'] or 0:>10.2f}", flush=True)
                memory[max_batch] = server.gpu_memory()
            finally:
                server.stop()
    result = {"benchmark": "serve", "machine": describe(), "device": args.device, "config": args.config,
              "cameras": args.cameras, "image_size": args.image_size, "points_per_request": points, "batch_parity": parity, "server_gpu_memory_mib": memory, "runs": runs}
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
