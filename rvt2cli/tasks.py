"""Tasks as data: one TOML file per task in the repository's `tasks/` folder.

A task names a ManiSkill environment, its scripted expert, the language instructions, the scene
bounds the policy sees, and the camera rig. Fields a file leaves out take the defaults below.
"""

import functools
import random
import tomllib
from dataclasses import dataclass, field
from importlib import resources

from rvt2cli.errors import UserError

TCP_AIM = (0.0, 0.0, 0.0)  # the aim offset of a task without one: the position heads aim the TCP itself

# One workspace cube for every task (like RLBench's fixed bounds): 0.8 m on a side, table top at z = 0,
# Panda base at x = -0.615 just outside it. Stage-1 pixels are 3.6 mm, stage-2 (4x zoom) 0.9 mm.
DEFAULT_SCENE_BOUNDS = (-0.4, -0.4, -0.05, 0.4, 0.4, 0.75)
DEFAULT_CAMERAS = ("front", "left_shoulder", "right_shoulder", "wrist")
DEFAULT_IMAGE_SIZE = 128


@dataclass(frozen=True)
class Task:
    name: str
    env_id: str
    expert: str                       # "module:function" taking (env, seed) like ManiSkill's solutions
    instructions: tuple[str, ...]     # templates; {names} are filled from `variables`
    max_steps: int
    scene_bounds: tuple[float, ...] = DEFAULT_SCENE_BOUNDS
    cameras: tuple[str, ...] = DEFAULT_CAMERAS
    image_size: int = DEFAULT_IMAGE_SIZE
    variables: dict = field(default_factory=dict)
    show_hidden: tuple[str, ...] = ()  # objects ManiSkill hides from cameras that the policy must see
    planner_speed: float = 0.9         # fraction of the Panda's joint velocity/acceleration limits (as the expert)
    gripper_close: float = -1.0        # the gripper command that closes it (as the expert; some grip softer)
    insertion: bool = False            # the point is fitting a held object into a close fit (failure reasons say how short)
    aim_offset: tuple[float, ...] = TCP_AIM  # m, TCP frame: what the policy aims once it holds (rvt2 train --aim-held)
    search_pitch_mm: float = 0.0       # > 0: an insertion stopped at a face searches for the hole on this grid (rvt2cli.eval.search)
    search_retract_mm: float = 4.0     # ...each probe backing off this far from the face before it shifts
    env_kwargs: dict = field(default_factory=dict)
    # Variations: each table gives the values of the instruction's placeholders for one variation (over
    # `variables`); the environment learns its index (rvt2cli.record.rlbench18.base). None listed: one.
    variations: tuple[dict, ...] = ()
    paraphrases: tuple[str, ...] = ()          # held-out instruction templates that training never sees
    held_out_variations: tuple[int, ...] = ()  # a compositional split that recording can leave out
    task_sets: tuple[str, ...] = ()            # named sets this task belongs to (e.g. "rlbench18")

    @property
    def num_variations(self) -> int:
        return max(1, len(self.variations))

    def variation_values(self, variation: int = 0) -> dict:
        """The placeholder values of one variation."""
        return {**self.variables, **(self.variations[variation] if self.variations else {})}

    def instruction(self, seed: int, variation: int = 0, paraphrase: bool = False) -> tuple[str, int]:
        """The instruction of the episode with this seed: (text, template index), deterministic. With
        `paraphrase`, one of the held-out paraphrases (a task without them keeps its instructions)."""
        templates = self.paraphrases if paraphrase and self.paraphrases else self.instructions
        index = random.Random(seed).randrange(len(templates))
        return templates[index].format(**self.variation_values(variation)), index

    def first_phrasing(self, variation: int = 0) -> str:
        """The variation's first trained phrasing: RLBench's first description (`init_episode`'s descriptions[0]),
        the one instruction PerAct, RVT and RVT-2 train and evaluate with."""
        return self.instructions[0].format(**self.variation_values(variation))

    def variation_of(self, text: str) -> int | None:
        """The variation one of whose trained phrasings (`instructions` filled in) `text` is, or None (a held-out
        paraphrase, or an instruction written elsewhere)."""
        return next((v for v in range(self.num_variations)
                     if text in (t.format(**self.variation_values(v)) for t in self.instructions)), None)

    def phrasings(self, text: str) -> list[str]:
        """The trained phrasings (`instructions` filled in, each once) of the variation whose instruction `text`
        is; [text] where it is none of them (`variation_of`)."""
        variation = self.variation_of(text)
        if variation is None:
            return [text]
        return list(dict.fromkeys(t.format(**self.variation_values(variation)) for t in self.instructions))

    def all_instructions(self) -> list[str]:
        return [t.format(**self.variation_values(v)) for v in range(self.num_variations) for t in self.instructions]

    def all_paraphrases(self) -> list[str]:
        return [t.format(**self.variation_values(v)) for v in range(self.num_variations) for t in self.paraphrases]

    def variation_choices(self, which: str = "all") -> tuple[int, ...]:
        """The variations episodes are spread over: "all", "seen" (all but the held-out split),
        "held-out" (only that split: none where the task has none), or one index "K"."""
        every = tuple(range(self.num_variations))
        if which == "all":
            return every
        if which == "seen":
            return tuple(v for v in every if v not in self.held_out_variations)
        if which == "held-out":
            return tuple(sorted(set(self.held_out_variations)))
        if which.isdigit() and int(which) < self.num_variations:
            return (int(which),)
        raise UserError(f"task {self.name} has no variation {which}; its variations are 0-{self.num_variations - 1}")


def episode_variation(seed: int, choices: tuple[int, ...]) -> int:
    """The variation of the episode with this seed: consecutive seeds take the choices in turn, so any
    run of seeds spreads its episodes evenly over them, and a seed's variation never depends on where
    the run started."""
    return choices[seed % len(choices)]


_REQUIRED = ("name", "env_id", "expert", "instructions", "max_steps")


def _parse(text: str, source: str) -> Task:
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise UserError(f"{source}: not valid TOML ({e})") from None
    missing = [k for k in _REQUIRED if k not in raw]
    if missing:
        raise UserError(f"{source}: missing {', '.join(missing)}")
    unknown = set(raw) - set(Task.__dataclass_fields__)
    if unknown:
        raise UserError(f"{source}: unknown field(s) {', '.join(sorted(unknown))}")
    for key in ("instructions", "scene_bounds", "cameras", "show_hidden", "aim_offset", "variations", "paraphrases",
                "held_out_variations", "task_sets"):
        if key in raw:
            raw[key] = tuple(raw[key])
    task = Task(**raw)
    if len(task.scene_bounds) != 6:
        raise UserError(f"{source}: scene_bounds needs 6 numbers (xmin ymin zmin xmax ymax zmax)")
    if len(task.aim_offset) != 3:
        raise UserError(f"{source}: aim_offset needs 3 numbers (x y z in metres, in the TCP frame)")
    if not isinstance(task.search_pitch_mm, (int, float)) or task.search_pitch_mm < 0:
        raise UserError(f"{source}: search_pitch_mm must be a number >= 0 (mm; 0: no insertion search)")
    if not isinstance(task.search_retract_mm, (int, float)) or task.search_retract_mm <= 0:
        raise UserError(f"{source}: search_retract_mm must be a number > 0 (mm a probe backs off the face)")
    bad = [v for v in task.held_out_variations if not 0 <= v < task.num_variations]
    if bad:
        raise UserError(f"{source}: held_out_variations {bad} are not variations of this task (0-{task.num_variations - 1})")
    if task.held_out_variations and len(set(task.held_out_variations)) >= task.num_variations:
        raise UserError(f"{source}: held_out_variations leaves no variation to record; hold out fewer")
    try:
        task.all_instructions()
        task.all_paraphrases()
    except KeyError as e:
        raise UserError(f"{source}: instruction uses {{{e.args[0]}}} but [variables] does not define it") from None
    return task


@functools.cache
def all_tasks() -> dict[str, Task]:
    tasks = {}
    for entry in sorted(resources.files("rvt2cli._tasks").iterdir(), key=lambda p: p.name):
        if entry.name.endswith(".toml"):
            task = _parse(entry.read_text(), f"tasks/{entry.name}")
            tasks[task.name] = task
    return tasks


def aim_offsets(names) -> dict[str, list[float]]:
    """The aim offsets that these tasks declare (tasks without one, or unknown here, aim the TCP)."""
    tasks = all_tasks()
    return {n: list(tasks[n].aim_offset) for n in names if n in tasks and any(tasks[n].aim_offset)}


def get_task(name: str) -> Task:
    tasks = all_tasks()
    if name not in tasks:
        raise UserError(f"unknown task {name!r}; known tasks: {', '.join(tasks)}")
    return tasks[name]


def task_sets() -> dict[str, list[str]]:
    """Named task sets (from the tasks' `task_sets`) and their members, in name order."""
    sets: dict[str, list[str]] = {}
    for task in all_tasks().values():
        for name in task.task_sets:
            sets.setdefault(name, []).append(task.name)
    return dict(sorted(sets.items()))


def tasks_of_set(name: str) -> list[str]:
    sets = task_sets()
    if name not in sets:
        raise UserError(f"unknown task set {name!r}; known task sets: {', '.join(sets) or 'none'} "
                        "(a task joins a set through `task_sets` in its tasks/*.toml)")
    return sets[name]
