"""Several GPUs: how a `rvt2 train` run's first process sends the training data to the others, at rvt2-18's size.

    python -m torch.distributed.run --standalone --nproc-per-node 2 -m benchmarks.share_bench [--scale 1] [--json out.json]

`rvt2cli.train.data_sharing.share_data`, the function `rvt2 train` runs, on data of the shape rvt2-18's 1,800 demos
give: 61,885 training and 617 validation samples packed at 50,000 points (43.2 GiB on the first GPU), the
per-sample columns the other processes need, and the embeddings of 578 instructions, kept as views into
one batch as the language model returns them. The contents are random: what is measured is the sending.
Reported: the pickled part's size (everything but the packed tensors), the first process's GPU memory before,
each process's time and peak GPU memory, and whether every process ends with the same data (checksums).
`--scale` shrinks every count (e.g. 0.002 runs on two CPU processes over gloo in seconds).
"""

import argparse
import json
import os
import pickle
import time
import numpy as np
import torch
import torch.distributed as dist

from rvt2cli.model.language import InstructionCache
from rvt2cli.train.packed import PackedSamples
from rvt2cli.train.samples import SampleSet
from rvt2cli.train.data_sharing import pickled_part, share_data
from rvt2cli.train.training_data import TrainingData

TRAIN, VALIDATION, POINTS, INSTRUCTIONS, TASKS, EPISODES = 61_885, 617, 50_000, 578, 18, 1_800  # rvt2-18, 100 demos per task
LANG_TOKENS, LANG_DIM = 77, 384


def packed_samples(n: int, points: int, instructions: int, device) -> PackedSamples:
    g = torch.Generator(device=device).manual_seed(n)
    r = np.random.default_rng(n)
    return PackedSamples(
        xyz=torch.rand(n, points, 3, device=device, generator=g),
        rgb=torch.randint(0, 255, (n, points, 3), dtype=torch.uint8, device=device, generator=g),
        count=torch.full((n,), points, device=device), proprio=torch.rand(n, 4, device=device, generator=g),
        instruction=torch.randint(0, instructions, (n,), device=device, generator=g),
        lang=torch.rand(instructions, LANG_TOKENS, LANG_DIM, device=device, generator=g),
        task=np.arange(n) % TASKS, keyframe_index=np.arange(n) % 9, final_keyframe=np.zeros(n, bool),
        keyframe_start=np.ones(n, bool), target_position=r.random((n, 3)), target_quaternion=r.random((n, 4)),
        target_gripper=np.ones(n, np.int64), target_collision=np.zeros(n, np.int64), center=r.random((TASKS, 3)),
        half=r.random(TASKS), lo=r.random((TASKS, 3)), hi=r.random((TASKS, 3)), gripper_open=np.ones(n, bool))


def training_data(scale: float, device) -> TrainingData:
    """What `read_data` gives the first process, less the clouds' sources (the samples' own clouds are not sent)."""
    train, validation = max(2, int(TRAIN * scale)), max(1, int(VALIDATION * scale))
    points, instructions = max(16, int(POINTS * scale)), max(2, int(INSTRUCTIONS * scale))
    samples = SampleSet(tasks=[f"task {t}" for t in range(TASKS)], instructions=[f"instruction {i}" for i in range(instructions)],
                        episodes=[f"episode {e}.mcap" for e in range(EPISODES)])
    rng = np.random.default_rng(0)
    for i in range(train + validation):
        samples.proprio.append(rng.random(4, np.float32))
        samples.target_position.append(rng.random(3, np.float32))
        samples.target_quaternion.append(rng.random(4))
        for column, value in (("target_gripper_open", True), ("target_ignore_collisions", False), ("keyframe_start", True),
                              ("keyframe_index", 1), ("final_keyframe", False), ("task_index", i % TASKS),
                              ("instruction_index", i % instructions), ("episode_index", i % EPISODES)):
            getattr(samples, column).append(value)
    batch = torch.rand(instructions, LANG_TOKENS, LANG_DIM)   # embed_instructions' one batch: each embedding a view into it
    cache = InstructionCache(LANG_TOKENS, {text: batch[i] for i, text in enumerate(samples.instructions)})
    return TrainingData(samples, list(range(train + validation)), packed_samples(train, points, instructions, device),
                        packed_samples(validation, points, instructions, device), cache)


def checksums(data: TrainingData) -> list[float]:
    packed, val = data.packed, data.packed_val
    return [float(packed.xyz[:, ::97].double().sum()), float(packed.rgb[::13].double().sum()), float(val.xyz.double().sum()),
            float(packed.lang.double().sum()), float(len(data.instructions.as_dict())), float(len(data.selected))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", type=float, default=1.0, help="every count times this (default 1: rvt2-18's size)")
    parser.add_argument("--json", help="write the results here (first process)")
    args = parser.parse_args()
    cuda = torch.cuda.is_available()
    dist.init_process_group("nccl" if cuda else "gloo")
    rank = dist.get_rank()
    device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", 0))) if cuda else torch.device("cpu")
    if cuda:
        torch.cuda.set_device(device)
    data, before = None, {}
    if rank == 0:
        data = training_data(args.scale, device)
        before = {"pickled_mib": len(pickle.dumps(pickled_part(data))) / 2**20,
                  "instruction_cache_mib": len(pickle.dumps(data.instructions)) / 2**20,
                  "first_process_gib": torch.cuda.memory_allocated() / 2**30 if cuda else 0.0,
                  "train_samples": len(data.packed), "points": data.packed.xyz.shape[1]}
    dist.barrier()
    start = time.perf_counter()
    received = share_data(data, None, device)
    if cuda:
        torch.cuda.synchronize()
    seconds = time.perf_counter() - start
    peak = torch.cuda.max_memory_allocated() / 2**30 if cuda else 0.0   # the checksums' temporaries come after
    processes = [None] * dist.get_world_size()
    dist.all_gather_object(processes, {"rank": rank, "seconds": seconds, "peak_gpu_gib": peak, "checksums": checksums(received)})
    if rank == 0:
        from benchmarks.machine import describe

        same = all(p["checksums"] == processes[0]["checksums"] for p in processes)
        print(f"{before['train_samples']:,} training samples of {before['points']:,} points; the first GPU holds "
              f"{before['first_process_gib']:.1f} GiB; pickled part {before['pickled_mib']:.1f} MiB "
              f"(instruction embeddings {before['instruction_cache_mib']:.1f} MiB)")
        print("| process | seconds | peak GPU memory, GiB |\n|---|---|---|")
        for p in processes:
            print(f"| {p['rank']} | {p['seconds']:.1f} | {p['peak_gpu_gib']:.1f} |")
        print("every process holds the same data" if same else "the processes' copies differ")
        if args.json:
            with open(args.json, "w") as f:
                json.dump({"machine": describe(), "scale": args.scale, **before, "processes": processes, "same": same}, f, indent=1)
        if not same:
            raise SystemExit(1)
    dist.destroy_process_group()


if __name__ == "__main__":
    main()
