"""`rvt2 import-rosbag` speed and memory: a 60 s recording of 2 cameras at 30 Hz, 640x480, on the CPU.

    python -m benchmarks.rosbag_bench [--containers mcap,sqlite3,ros1] [--compressed] [--seconds 60] [--json out.json] [--quick]

Writes a synthetic recording as a robot with two realsense cameras would (colour, aligned depth and
camera_info per camera, /joint_states and /tf at the camera rate, /tf_static), once per container,
then times `rvt2 import-rosbag` on it in a fresh process: colour frames imported per second and the
process's peak memory (its maximum resident set), beside the bag's size. The importer streams the bag
twice and holds only the frames it is decoding, so peak memory does not grow with the bag.
`--compressed` records the images as image_transport's `compressed` (JPEG) and `compressedDepth` (PNG).
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from benchmarks.machine import describe
from rvt2cli.robot import PANDA
from rvt2cli.rosbag.bagwriter import BagWriter
from rvt2cli.rosbag.from_episode import OPTICAL_IN_LINK, camera_frames
from rvt2cli.rosbag.messages import CAMERA_INFO, COMPRESSED_IMAGE, IMAGE, JOINT_STATE, TF_MESSAGE

CONTAINERS = {"mcap": ("bag.mcap", "humble"), "sqlite3": ("bag.db3", "humble"), "ros1": ("bag.bag", "noetic")}
START_NS = 1_700_000_000 * 1_000_000_000
CAMERA_MOUNTS = [(0.9, -0.3, 0.6), (0.9, 0.3, 0.6), (0.3, 0.6, 0.7), (0.3, -0.6, 0.7)]
DISTINCT_IMAGES = 16   # the images cycle through this many, so that writing the bag does not dominate


def camera_images(width: int, height: int, count: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(RGB uint8, depth in metres): a textured tabletop with a few boxes, shifting from image to image."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    out = []
    for i in range(count):
        depth = 0.8 + 0.3 * v / height
        for _ in range(3):
            x, y = rng.integers(0, width - 60), rng.integers(0, height - 60)
            depth[y:y + 60, x:x + 60] -= 0.05
        rgb = np.stack([(u + 4 * i) % 256, (v * 2) % 256, 128 + 60 * np.sin(u / 17 + i)], axis=-1)
        rgb = np.clip(rgb + rng.normal(0, 8, rgb.shape), 0, 255).astype(np.uint8)
        out.append((rgb, depth.astype(np.float32)))
    return out


def write_recording(out: Path, distro: str, seconds: float, cameras: int, hz: float, width: int, height: int,
                    compressed: bool) -> Path:
    frames = int(seconds * hz)
    names = [f"cam{i}" for i in range(cameras)]
    pictures = {name: camera_images(width, height, DISTINCT_IMAGES, seed) for seed, name in enumerate(names)}
    K = np.array([[0.9 * width, 0, width / 2], [0, 0.9 * width, height / 2], [0, 0, 1]])
    joint_names = list(PANDA.arm_joints + PANDA.finger_joints)
    with BagWriter(out, distro) as bag:
        msgs = bag.messages
        static = []
        for name, mount in zip(names, CAMERA_MOUNTS):
            look = Rotation.from_euler("xyz", [0, 0.6, np.arctan2(-mount[1], -mount[0] + 0.5)]).as_quat()
            static += [("panda_link0", camera_frames(name)[0], (*mount, *look), START_NS),
                       (camera_frames(name)[0], camera_frames(name)[1], OPTICAL_IN_LINK, START_NS)]
        bag.write("/tf_static", TF_MESSAGE, msgs.transforms(static), START_NS)
        for t in range(frames):
            t_ns = START_NS + round(t * 1e9 / hz)
            phase = 2 * np.pi * t / frames
            arm = 0.3 * np.sin(phase + np.arange(7))
            positions = np.concatenate([arm, [0.04, 0.04]])
            velocities = np.concatenate([0.3 * 2 * np.pi / seconds * np.cos(phase + np.arange(7)), [0.0, 0.0]])
            bag.write("/joint_states", JOINT_STATE, msgs.joint_state(joint_names, positions, velocities, t_ns), t_ns)
            tcp = (0.5 + 0.1 * np.cos(phase), 0.1 * np.sin(phase), 0.3, 1.0, 0.0, 0.0, 0.0)
            bag.write("/tf", TF_MESSAGE, msgs.transforms([("panda_link0", "panda_hand_tcp", tcp, t_ns)]), t_ns)
            for name in names:
                rgb, depth = pictures[name][t % DISTINCT_IMAGES]
                prefix, optical = f"/camera/{name}", camera_frames(name)[1]
                if compressed:
                    bag.write(f"{prefix}/color/image_raw/compressed", COMPRESSED_IMAGE,
                              msgs.compressed_colour(rgb, "jpeg", t_ns, optical), t_ns)
                    bag.write(f"{prefix}/aligned_depth_to_color/image_raw/compressedDepth", COMPRESSED_IMAGE,
                              msgs.compressed_depth(depth, t_ns, optical), t_ns)
                else:
                    bag.write(f"{prefix}/color/image_raw", IMAGE, msgs.image(rgb, "rgb8", t_ns, optical), t_ns)
                    bag.write(f"{prefix}/aligned_depth_to_color/image_raw", IMAGE, msgs.image(depth, "16UC1", t_ns, optical),
                              t_ns)
                bag.write(f"{prefix}/color/camera_info", CAMERA_INFO,
                          msgs.camera_info(K + np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]]), width, height, t_ns, optical),
                          t_ns)
    return out


def size_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*")) if path.is_dir() else path.stat().st_size


def time_import(bag: Path, out: Path, cameras: int) -> dict:
    """`rvt2 import-rosbag` in a fresh process: seconds and its peak resident memory."""
    command = [sys.executable, "-m", "rvt2cli", "import-rosbag", str(bag), "--out", str(out), "--task", "bench",
               "--instruction", "benchmark", "--scene-bounds=0.2,-0.5,-0.1,1.0,0.5,0.7",
               "--joint-states", "/joint_states", "--ee-frame", "panda_hand_tcp"]
    for i in range(cameras):
        command += ["--camera", f"/camera/cam{i}"]
    start = time.perf_counter()
    with tempfile.TemporaryFile("w+") as stdout, tempfile.TemporaryFile("w+") as stderr:
        process = subprocess.Popen(command, stdout=stdout, stderr=stderr, text=True)
        _, status, usage = os.wait4(process.pid, 0)   # this child's own resource usage
        seconds = time.perf_counter() - start
        process.returncode = os.waitstatus_to_exitcode(status)
        stdout.seek(0)
        stderr.seek(0)
        if process.returncode != 0:
            sys.exit(f"import failed: {stderr.read()}")
        output = stdout.read().strip().splitlines()[0]
    return {"seconds": seconds, "peak_rss_mb": usage.ru_maxrss / 1024, "output": output}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--containers", default="mcap,sqlite3,ros1", help=f"comma-separated: {', '.join(CONTAINERS)}")
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--cameras", type=int, default=2)
    parser.add_argument("--hz", type=float, default=30.0)
    parser.add_argument("--size", default="640x480", help="WIDTHxHEIGHT")
    parser.add_argument("--compressed", action="store_true", help="JPEG colour and compressedDepth PNG instead of raw images")
    parser.add_argument("--dir", help="where to write the bags (default: a temporary folder; each is deleted after use)")
    parser.add_argument("--json", help="write results here")
    parser.add_argument("--quick", action="store_true", help="2 s of one 160x120 camera in MCAP: checks that it runs")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    containers, seconds, cameras = args.containers.split(","), args.seconds, args.cameras
    if args.quick:
        containers, seconds, cameras, width, height = ["mcap"], 2.0, 1, 160, 120
    results = {"machine": describe(), "seconds": seconds, "cameras": cameras, "hz": args.hz, "size": [width, height],
               "images": "compressed (JPEG, compressedDepth PNG)" if args.compressed else "raw (rgb8, 16UC1)", "runs": []}
    frames = int(seconds * args.hz)
    print(f"{seconds:.0f} s, {cameras} camera(s) at {args.hz:.0f} Hz, {width}x{height}, {results['images']}; "
          f"{results['machine']['cpu']} ({results['machine']['cores']} cores)")
    print("| container | bag (MB) | write (s) | import (s) | colour frames/s | MB/s | peak memory (MB) |\n|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory(dir=args.dir) as scratch:
        for container in containers:
            name, distro = CONTAINERS[container]
            bag = Path(scratch) / name
            start = time.perf_counter()
            write_recording(bag, distro, seconds, cameras, args.hz, width, height, args.compressed)
            written = time.perf_counter() - start
            megabytes = size_bytes(bag) / 1e6
            run = time_import(bag, Path(scratch) / f"out_{container}", cameras)
            bag.unlink()
            run |= {"container": container, "bag_mb": megabytes, "write_seconds": written, "frames": frames,
                    "frames_per_second": frames / run["seconds"], "mb_per_second": megabytes / run["seconds"]}
            results["runs"].append(run)
            print(f"| {container} | {megabytes:.0f} | {written:.1f} | {run['seconds']:.1f} | {run['frames_per_second']:.0f} | "
                  f"{run['mb_per_second']:.0f} | {run['peak_rss_mb']:.0f} |", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=2)


if __name__ == "__main__":
    main()
