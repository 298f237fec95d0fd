"""Where a non-finite training step on several GPUs comes from.

    python -m torch.distributed.run --standalone --nproc-per-node 2 -m benchmarks.ddp_nonfinite \
        --data CACHE_OR_DEMOS [--steps 200] [--batch-size 96] [--ddp-graphs split|whole] [--no-compile] \
        [--no-amp] [--train-args "OPTIONS"] [--json out.json]

It runs `rvt2 train`'s own step (`rvt2cli.train.step.TrainStep`: the policy under DistributedDataParallel,
compiled and in bf16 as `rvt2 train` sets them up, `rvt2cli.train.training_setup.setup_training`) and reads every
step back. Where a process's own loss is not finite, it runs the same batch's forward again with the same
weights (a skipped step changes none): through the model exactly as the step did, through the compiled
network outside DDP, and eagerly, and records which loss terms are finite in each. A fault that appears
only inside DDP's forward and goes away outside it is in how the compiled graphs run under DDP; one that
repeats eagerly is in the data or the weights.

`--ddp-graphs whole` (the default) compiles as `rvt2 train` does, one graph per compiled module; `split`
as torch does by default under DDP (Dynamo's DDPOptimizer cuts each compiled graph at DDP's gradient
buckets). On 2 x H200 with experiments/ddp_2tasks.toml's data, split skipped 27 of 300 steps and whole
none (docs/BENCHMARKS.md).
Per process, in the JSON: the steps, the non-finite steps with their terms and the reruns.
"""

import argparse
import contextlib
import json
import os
import shlex
import time

import numpy as np
import torch

from rvt2cli.model.loss import policy_loss


def forward_terms(model, batch, cfg, amp: bool) -> dict[str, bool]:
    """Which loss terms of this batch's forward are finite (no backward, no weight change). With gradients
    on, as in the step: the compiled graphs are the training ones (no_grad would compile others), and
    DDP's model runs under no_sync, so that it expects no backward."""
    sync = model.no_sync() if isinstance(model, torch.nn.parallel.DistributedDataParallel) else contextlib.nullcontext()
    with sync, torch.autocast(device_type="cuda", dtype=torch.bfloat16, enabled=amp):
        outputs = model(batch.obs, batch.position, batch.rot_bins, batch.stage2_center)
    losses = policy_loss(outputs, batch.position, batch.rot_bins, batch.gripper, batch.collision, cfg.image_size,
                         cfg.heatmap_sigma, batch.euler_deg, cfg.rotation_sigma_deg)
    return {name: bool(torch.isfinite(value).item()) for name, value in losses.items()}


def main() -> None:
    from rvt2cli.cli.train import options_from, register

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", nargs="+", required=True)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--batch-size", type=int, default=96)
    parser.add_argument("--ddp-graphs", choices=("split", "whole"), default="whole",
                        help="whole: as rvt2 train compiles under DDP (default); split: torch's default, which the fault needs")
    parser.add_argument("--no-compile", action="store_true")
    parser.add_argument("--no-amp", action="store_true")
    parser.add_argument("--train-args", default="", help="more `rvt2 train` options, e.g. \"--aim-held\"")
    parser.add_argument("--probe-step", type=int, default=0,
                        help="also run the three reruns at this step, finite or not (a control)")
    parser.add_argument("--out", default="/tmp/ddp_nonfinite_run")
    parser.add_argument("--json")
    args = parser.parse_args()

    train_parser = argparse.ArgumentParser()
    register(train_parser.add_subparsers(dest="command"))
    cli = ["train", "--data", *args.data, "--out", args.out, "--steps", str(args.steps), "--batch-size",
           str(args.batch_size), "--val-episodes", "0", "--warmup", str(max(1, args.steps // 10)), "--no-progress",
           *([] if args.no_compile else ["--compile"]), *(["--no-amp"] if args.no_amp else []), *shlex.split(args.train_args)]
    opts = options_from(train_parser.parse_args(cli))

    from rvt2cli.train.training_setup import setup_training

    setup = setup_training(opts, say=print, ddp_graph_split=args.ddp_graphs == "split")
    rank, world, policy, model, step_fn, batches = (setup.rank, setup.world, setup.policy, setup.model,
                                                    setup.train_step, setup.batches)
    cfg = policy.cfg
    amp = step_fn.amp
    bad, started = [], time.perf_counter()
    for step in range(1, args.steps + 1):
        batch = next(batches)
        result = step_fn(batch)
        if bool(result.finite.item()) and step != args.probe_step:
            continue
        own = {name: bool(torch.isfinite(value).item()) for name, value in result.losses.items()}
        entry = {"step": step, "terms": own, "probe": step == args.probe_step}
        if not all(own.values()) or entry["probe"]:   # run this process's forward again three ways
            entry["again_as_stepped"] = forward_terms(model, batch, cfg, amp)
            entry["compiled_outside_ddp"] = forward_terms(policy, batch, cfg, amp)
            with policy.eager():
                entry["eager"] = forward_terms(policy, batch, cfg, amp)
        bad.append(entry)
        print(f"rank {rank} step {step}: {'probe' if entry['probe'] else 'not finite'} {json.dumps(entry)}", flush=True)
    seconds = time.perf_counter() - started
    report = {"rank": rank, "world": world, "steps": args.steps, "batch_size": args.batch_size,
              "ddp_graphs": args.ddp_graphs, "compile": not args.no_compile, "amp": amp, "seconds": seconds,
              "non_finite_steps": sum(1 for b in bad if not b["probe"]),
              "own_forward_non_finite": sum(1 for b in bad if not all(b["terms"].values())),
              "reruns_finite": {k: int(np.sum([all(b[k].values()) for b in bad if k in b and not b["probe"]]))
                                for k in ("again_as_stepped", "compiled_outside_ddp", "eager")},
              "bad_steps": bad, "torch": torch.__version__, "gpu": torch.cuda.get_device_name() if torch.cuda.is_available() else None}
    print(f"rank {rank}: {report['non_finite_steps']} of {args.steps} steps not finite ({report['own_forward_non_finite']} in its own "
          f"forward; finite again: {report['reruns_finite']}); {seconds:.0f} s", flush=True)
    if args.json:
        root, ext = os.path.splitext(args.json)
        with open(f"{root}.rank{rank}{ext}", "w") as f:
            json.dump(report, f, indent=1)


if __name__ == "__main__":
    main()
