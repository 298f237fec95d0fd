"""`rvt2 eval`: episodes of every task on unseen seeds, for the policy and (optionally) the oracle,
in parallel processes, deterministic per seed, with a report, videos and rollout files.

Every finished episode goes into the journal at once (`rvt2cli.eval.journal`): a crashed simulator
process costs the episodes it was running, not the finished ones, and `--resume` runs the rest.
"""

import contextlib
import itertools
import time
import warnings
from concurrent.futures import FIRST_COMPLETED, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field, replace
from pathlib import Path

from rvt2cli.atomic import ensure_folder
from rvt2cli.errors import UserError
from rvt2cli.eval.journal import NAME as JOURNAL_NAME
from rvt2cli.eval.journal import Journal
from rvt2cli.eval.media import write_rollout, write_video
from rvt2cli.eval.options import EvalOptions
from rvt2cli.eval.report import build_report, episode_record, write_report
from rvt2cli.eval.rollout import Outcome, run_episode
from rvt2cli.eval.search import InsertionSearch
from rvt2cli.record.robot_visuals import DESCRIPTION as ROBOT_VISUALS
from rvt2cli.runtime import torch_device, use_vulkan_driver, worker_pool
from rvt2cli.tasks import episode_variation, get_task


@dataclass(frozen=True)
class Job:
    source: str   # "policy" | "oracle"
    task: str
    seed: int
    variation: int = 0


@dataclass
class EvalResult:
    out_dir: Path
    report: dict
    outcomes: list[tuple[Job, Outcome]] = field(default_factory=list)   # the episodes this call ran


# --- one process's simulator, policy and oracle -------------------------------------------------------

class _Worker:
    def __init__(self, opts: EvalOptions, demos: dict):
        self.opts, self.demos = opts, demos
        self.envs, self.policy, self.oracles, self.rigs = {}, None, {}, {}
        if opts.replay:
            from rvt2cli.eval.journal import read_journal
            from rvt2cli.eval.sources import ReplaySource

            self.policy = ReplaySource(read_journal(Path(opts.replay))[1])
        if opts.checkpoint:
            from rvt2cli.eval.sources import PolicySource
            from rvt2cli.train.checkpoint import load_policy

            policy, ckpt = load_policy(opts.checkpoint, device=opts.device, stage2_min_points=opts.stage2_min_points)
            if opts.cuda_graph:
                from rvt2cli.model.graphed import GraphedPolicy

                policy = GraphedPolicy(policy)
            self.policy = PolicySource(policy, ckpt, opts.device)
            self.rigs = ckpt.info.get("rigs", {})
        if opts.policy_url:
            from rvt2cli.eval.sources import RemotePolicySource

            self.policy = RemotePolicySource(opts.policy_url, opts.token)
            self.rigs = self.policy.info.get("rigs", {})

    def env(self, task):
        """The task's scene, observed with the camera rig the policy's training demos were recorded with."""
        if task.name not in self.envs:
            from rvt2cli.record.scene import make_env

            rig = self.rigs.get(task.name, {})
            self.envs[task.name] = make_env(task, rig.get("cameras"), rig.get("image_size"))
        return self.envs[task.name]

    def run(self, job: Job) -> Outcome:
        from rvt2cli.eval.sources import OracleSource

        task = get_task(job.task)
        env = self.env(task)
        instruction = self.opts.instruction_for(task, job.seed, job.variation)
        if job.source == "policy":
            source = self.policy
        else:
            source = self.oracles.setdefault(task.name, OracleSource(env, self.demos))
        try:
            return run_episode(env, task, job.seed, source, instruction, self.opts.keyframe_budget,
                               step_budget=round(task.max_steps * self.opts.step_budget_scale),
                               video_every=2 if self.opts.video else 0, max_replans=self.opts.max_replans,
                               search=self.opts.insertion_search, variation=job.variation)
        except UserError:
            raise
        except Exception as e:  # noqa: BLE001 - a simulator crash costs this episode, not the run
            return Outcome(task=task.name, seed=job.seed, success=False, failure="error", instruction=instruction,
                           variation=job.variation, error=f"{type(e).__name__}: {e}")


_worker: _Worker | None = None


def _init(opts: EvalOptions, demos: dict) -> None:
    global _worker
    _worker = _Worker(opts, demos)


def _run(job: Job) -> Outcome:
    return _worker.run(job)


# --- the whole evaluation ------------------------------------------------------------------------------

def _demo_seeds(paths) -> dict[tuple[str, int], str]:
    from rvt2cli.data.paths import episode_paths
    from rvt2cli.data.reader import read_episode_overview

    demos = {}
    for path in episode_paths(list(paths)):
        meta = read_episode_overview(path).meta
        demos[(meta.task, meta.seed)] = str(path)
    return demos


def plan_jobs(opts: EvalOptions, checkpoint_tasks: list[str], demos: dict,
              replayed: dict[str, set[int]] | None = None) -> list[Job]:
    """The episodes to run, the tasks taking turns (each task's first episode, then each one's second...): an
    evaluation stopped part way has as many episodes of every task, and the long tasks do not all come last.
    `replayed`: a recorded evaluation's seeds per task (--replay)."""
    tasks = list(opts.tasks) or checkpoint_tasks or sorted({t for t, _ in demos})
    if not tasks:
        raise UserError("no tasks to evaluate: give --tasks (or a checkpoint, whose training tasks are the default)")
    choices = {name: get_task(name).variation_choices(opts.variations) for name in tasks}
    if not any(choices.values()):  # only --variations held-out leaves a task none
        raise UserError(f"--variations {opts.variations}: none of the tasks {', '.join(tasks)} has held_out_variations "
                        "(tasks/*.toml)")
    per_task = []
    for name in [n for n in tasks if choices[n]]:
        jobs = []
        def job(source, seed):  # consecutive seeds take the variations in turn: even, and the same in every run
            return Job(source, name, seed, episode_variation(seed, choices[name]))

        demo_seeds = sorted(seed for task, seed in demos if task == name)
        if opts.policy:
            jobs += [job("policy", s) for s in range(opts.seed, opts.seed + opts.episodes)]
        if replayed is not None:
            jobs += [job("policy", s) for s in sorted(replayed.get(name, ()))
                     if opts.seed <= s < opts.seed + opts.episodes]
        if opts.oracle and demos:  # a demo's keyframes solve the variation it was recorded in
            jobs += [Job("oracle", name, s, _demo_variation(demos[(name, s)])) for s in demo_seeds]
        elif opts.oracle:
            jobs += [job("oracle", s) for s in range(opts.seed, opts.seed + opts.episodes)]
        per_task.append(jobs)
    return [job for turn in itertools.zip_longest(*per_task) for job in turn if job is not None]


def _demo_variation(path: str) -> int:
    from rvt2cli.data.reader import read_episode_overview

    return int(read_episode_overview(path).meta.extra.get("variation", 0))


def untrained_tasks(opts: EvalOptions, checkpoint_tasks: list[str]) -> list[str]:
    """Tasks asked for that the checkpoint never saw (allowed: a generalisation test; said once)."""
    if not opts.policy:
        return []
    return [t for t in opts.tasks if t not in checkpoint_tasks]


def search_grids(task_names) -> dict:
    """{task: its insertion search's grid pitch and probe retract, mm} for the tasks that search."""
    return {name: {"pitch_mm": task.search_pitch_mm, "retract_mm": task.search_retract_mm}
            for name in task_names if InsertionSearch.for_task(task := get_task(name))}


def report_meta(opts: EvalOptions, checkpoint_path: str | None, tasks: list[str], untrained: list[str], seconds: float) -> dict:
    """What an evaluation's report says of how it ran, beside its episodes (`build_report`'s `meta`)."""
    return {"checkpoint": checkpoint_path, "seed": opts.seed, "episodes_per_task": opts.episodes,
            "keyframe_budget": opts.keyframe_budget, "max_replans": opts.max_replans, "instruction": opts.instruction,
            "paraphrases": opts.paraphrases, "first_phrasing": opts.first_phrasing, "variations": opts.variations,
            "step_budget_scale": opts.step_budget_scale, "insertion_search": opts.insertion_search,
            "search_grids": search_grids(tasks) if opts.insertion_search else {},
            "untrained_tasks": untrained, "shared_policy": opts.shared_policy, "cuda_graph": opts.cuda_graph, "seconds": seconds}


def evaluate(opts: EvalOptions, on_outcome=None, on_start=None) -> EvalResult:
    """Run every job not yet in the journal; `on_start(number_of_episodes)` once the inputs are checked,
    `on_outcome(job, outcome, finished)` after each episode (the CLI's progress bar)."""
    if not opts.policy and not opts.oracle and not opts.replay:
        raise UserError("eval needs --checkpoint or --policy-url (and/or --oracle)")
    if opts.checkpoint and opts.policy_url:
        raise UserError("eval takes --checkpoint or --policy-url, not both: --policy-url runs a policy served by `rvt2 serve`")
    if opts.policy and opts.replay:
        raise UserError("eval takes --checkpoint or --replay, not both: --replay runs a recorded evaluation's keyframes")
    if opts.shared_policy and (not opts.checkpoint or opts.workers < 2):
        raise UserError("--shared-policy loads --checkpoint once, in this process, for the --workers processes to share; "
                        "give --checkpoint and --workers 2 or more")
    if opts.cuda_graph and (not opts.checkpoint or opts.shared_policy or not opts.device.startswith("cuda")):
        raise UserError("--cuda-graph replays each worker's policy step as a CUDA graph: give --checkpoint and --device cuda, "
                        "without --shared-policy")
    if opts.policy_url and (opts.device != "cpu" or opts.stage2_min_points is not None):
        raise UserError("--device and --stage2-min-points set up a checkpoint loaded here; a served policy (--policy-url) "
                        "runs as `rvt2 serve` was started")
    if opts.checkpoint:
        torch_device(opts.device)  # refused here, in one line, rather than in every worker
    checkpoint_tasks, checkpoint_path, replayed = [], None, None
    if opts.replay:
        from rvt2cli.eval.journal import read_journal

        journal_path = Path(opts.replay)
        if not journal_path.is_file():
            raise UserError(f"{journal_path}: no such evaluation journal (an episodes.jsonl written by rvt2 eval)")
        replayed = {}
        for record in read_journal(journal_path)[1]:
            if record["source"] == "policy":
                replayed.setdefault(record["task"], set()).add(record["seed"])
        if not replayed:
            raise UserError(f"{journal_path}: no policy episodes to replay")
        checkpoint_tasks, checkpoint_path = sorted(replayed), f"replay of {journal_path}"
    if opts.policy:
        trained = _policy_description(opts)  # refuses missing, foreign or damaged checkpoints, unreachable servers
        checkpoint_tasks, checkpoint_path = trained["tasks"], trained["path"]
    demos = _demo_seeds(opts.demos) if opts.demos else {}
    jobs = plan_jobs(opts, checkpoint_tasks, demos, replayed)
    untrained = untrained_tasks(opts, checkpoint_tasks)
    if untrained:
        warnings.warn(f"task(s) {', '.join(untrained)} not in the checkpoint's training set "
                      f"({', '.join(checkpoint_tasks)}); evaluating anyway (noted in the report)")
    driver = use_vulkan_driver()  # chosen (and probed) once the inputs are checked; worker processes inherit the choice
    if opts.policy:
        rigs = trained["rigs"]
        renderers = sorted({rig["renderer"] for rig in rigs.values() if rig.get("renderer")})
        if renderers and driver.name not in renderers:
            warnings.warn(f"the checkpoint's demos were rendered by {' and '.join(renderers)}, this evaluation renders with "
                          f"{driver.name}: a policy acts differently under another renderer (docs/RESULTS.md, \"Renderer\"); "
                          f"set RVT2_VULKAN={renderers[0]} to evaluate under the demos' renderer")
        if trained["phrasings"] == "first" and not (opts.first_phrasing or opts.instruction):
            warnings.warn("the checkpoint was trained on each variation's first phrasing alone (--phrasings first); "
                          "this evaluation instructs with other phrasings too: give --first-phrasing to evaluate as it was trained")
        drawn = {rig.get("robot_visuals") or "ManiSkill's full meshes" for rig in rigs.values() if rig.get("renderer")}
        if drawn - {ROBOT_VISUALS}:
            warnings.warn(f"the checkpoint's demos drew the Panda with {' and '.join(sorted(drawn))}; this evaluation draws "
                          f"{ROBOT_VISUALS}: the arm's outline differs by a pixel here and there")
    out_dir = ensure_folder(Path(opts.out) if opts.out else (Path(opts.checkpoint) / "eval" if opts.checkpoint else Path("eval")))
    journal = Journal(out_dir, opts.plan(checkpoint_path), opts.resume)
    todo = [job for job in jobs if (job.source, job.task, job.seed) not in journal.finished]
    start = time.perf_counter()
    finished: list[tuple[Job, Outcome]] = []
    if on_start:
        on_start(len(todo))

    def done(job: Job, outcome: Outcome) -> None:
        journal.append(episode_record(job.source, outcome))
        finished.append((job, outcome))
        _save_media(opts, out_dir, job, outcome)
        if on_outcome:
            on_outcome(job, outcome, finished)

    def report() -> dict:
        meta = report_meta(opts, checkpoint_path, sorted({job.task for job in jobs}), untrained, time.perf_counter() - start)
        result = build_report(journal.records, meta)
        write_report(result, out_dir)
        return result

    try:
        _run_jobs(opts, demos, todo, done, driver.name)
    except BrokenProcessPool as e:
        report()
        raise UserError(f"a simulator process died ({e}); the {len(journal.records)} finished episodes are kept in "
                        f"{out_dir / JOURNAL_NAME} (report: {out_dir / 'eval.md'}); run the same command with --resume "
                        "to run the rest") from None
    return EvalResult(out_dir=out_dir, report=report(), outcomes=finished)


def _policy_description(opts: EvalOptions) -> dict:
    """What the evaluated policy was trained on: its tasks, where it is (the journal's "checkpoint"), the camera
    rigs of its demos and its phrasings; from the checkpoint, or from the server (`rvt2 serve`'s health document)."""
    if opts.checkpoint:
        from rvt2cli.train.checkpoint import load_policy

        _, ckpt = load_policy(opts.checkpoint)
        return {"tasks": ckpt.tasks, "path": str(ckpt.path), "rigs": ckpt.info.get("rigs", {}),
                "phrasings": ckpt.training_options.get("phrasings")}
    from rvt2_client import PolicyClient

    from rvt2cli.eval.sources import served_policy

    with PolicyClient(opts.policy_url, token=opts.token) as client:
        info = served_policy(client)
    model = info["model"]
    return {"tasks": list(info["tasks"]), "path": f"{model['path']} (served, sha256 {model['sha256']})",
            "rigs": info.get("rigs", {}), "phrasings": info.get("phrasings")}


def _run_jobs(opts: EvalOptions, demos: dict, jobs: list[Job], done, renderer: str = "lavapipe") -> None:
    if not jobs:
        return
    if opts.workers <= 1:
        import torch

        threads = torch.get_num_threads()
        torch.set_num_threads(1)  # as in each worker process: the same arithmetic whatever --workers
        try:
            worker = _Worker(opts, demos)
            for job in jobs:
                done(job, worker.run(job))
        finally:
            torch.set_num_threads(threads)
        return
    with _policy_for_workers(opts) as worker_opts:
        if worker_opts.policy_url and renderer == "lavapipe":
            gpus = "none"   # the workers render on the CPU and hold no policy: they need no GPU (no CUDA context each)
        else:  # a worker may take whichever GPU it is given unless the policy's device names one ("cuda:1")
            gpus = "all" if opts.device.startswith("cuda:") else "one"
        with worker_pool(opts.workers, _init, (worker_opts, demos), gpus=gpus) as pool:
            pending = {pool.submit(_run, job): job for job in jobs}
            while pending:
                completed, _ = wait(pending, return_when=FIRST_COMPLETED)
                for future in completed:
                    done(pending.pop(future), future.result())


@contextlib.contextmanager
def _policy_for_workers(opts: EvalOptions):
    """The options the worker processes run with. By default each loads the checkpoint itself (on --device:
    a copy of the policy, and a CUDA context, per worker). With --shared-policy the checkpoint is loaded once,
    here, and served to the workers on the loopback by `rvt2 serve`'s server in a thread (a token of this run
    alone); its batcher answers the keyframe requests that arrive together in one forward pass, always at the
    workers' count (`--fixed-batch`), so that an episode does not depend on which requests came together."""
    if not opts.shared_policy:
        yield opts
        return
    import secrets

    from rvt2cli.serve.options import ServeOptions
    from rvt2cli.serve.server import open_server

    token = secrets.token_urlsafe(32)
    # every forward pass at one size: an episode's keyframes do not depend on which workers asked together
    server = open_server(opts.checkpoint, opts.device, ServeOptions(port=0, token=token, max_batch=opts.workers, fixed_batch=True),
                         opts.stage2_min_points).start_in_thread()
    try:
        yield replace(opts, checkpoint=None, policy_url=server.url, token=token, device="cpu", stage2_min_points=None)
    finally:
        server.stop()


def _save_media(opts: EvalOptions, out_dir: Path, job: Job, outcome: Outcome) -> None:
    name = f"{job.source}_{job.task}_{job.seed:05d}"
    if opts.video and outcome.video:
        (out_dir / "videos").mkdir(parents=True, exist_ok=True)
        write_video(outcome.video, out_dir / "videos" / f"{name}.mp4")
    outcome.video = []
    if opts.save_rollouts:
        (out_dir / "rollouts").mkdir(parents=True, exist_ok=True)
        write_rollout(outcome, outcome.control_hz, out_dir / "rollouts" / f"{name}.mcap")
