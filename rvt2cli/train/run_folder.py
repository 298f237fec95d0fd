"""A run's folder: what a fresh run may train into, the options a resumed run keeps, and what the run
writes there besides its checkpoints (train.csv, validation.csv, TensorBoard, run.json).

    runs/NAME/last, checkpoints/    the checkpoints (rvt2cli.train.checkpoint)
    runs/NAME/run.json              options, episodes trained on, the final validation, time and speed
    runs/NAME/train.csv             one row per logged step
    runs/NAME/validation.csv        precision per task and keyframe at each validation
    runs/NAME/tb/                   the same numbers for TensorBoard
"""

import csv
import json
from dataclasses import replace
from pathlib import Path

from rvt2cli.atomic import atomic_open
from rvt2cli.errors import UserError
from rvt2cli.model.config import ModelConfig, get_config
from rvt2cli.train.checkpoint import Checkpoint, load_checkpoint
from rvt2cli.train.metrics import task_rows
from rvt2cli.train.options import TrainOptions, conflicts

RUN_FILES = {"last", "run.json", "train.csv", "validation.csv", "tb", "checkpoints"}


def _own_files(run_dir: Path) -> list[str]:
    """The names in `run_dir` that `rvt2 train` did not write (its hidden temporary files aside)."""
    return sorted(p.name for p in run_dir.iterdir() if p.name not in RUN_FILES and not
                  (p.name.startswith(".") and ".tmp-" in p.name))


def check_run_folder(run_dir: Path, resume: bool) -> None:
    """A fresh run goes into a new or empty folder, or one of a run stopped before its first checkpoint;
    a resumed run needs a checkpoint. One line otherwise; nothing of the user's is written over."""
    has_checkpoint = (run_dir / "last").exists()
    foreign = _own_files(run_dir) if run_dir.is_dir() and not has_checkpoint else []
    if foreign:
        raise UserError(f"{run_dir}: exists and is not an rvt2 run folder (it holds {foreign[0]}); "
                        "train into a new or empty --out")
    if not resume and has_checkpoint:
        raise UserError(f"{run_dir}: already holds a run; pass --resume to continue it or choose another --out")
    if resume and not has_checkpoint:
        if not run_dir.is_dir():
            raise UserError(f"{run_dir}: no such run folder to resume; start the run without --resume")
        raise UserError(f"{run_dir}: the run has no checkpoint yet (it stopped before its first save); "
                        "start it again without --resume")


def stored_options(run_dir: Path) -> TrainOptions | None:
    """The options a run was started with (from its last checkpoint), or None for a run without them."""
    check_run_folder(run_dir, resume=True)
    options = load_checkpoint(run_dir).training_options
    return TrainOptions.from_json(options) if options else None


def resolve_options(opts: TrainOptions) -> tuple[TrainOptions, Checkpoint | None]:
    """A fresh run needs a fresh folder; a resumed run must keep its run-defining options."""
    run_dir = Path(opts.out)
    check_run_folder(run_dir, opts.resume)
    if not opts.resume:
        return opts, None
    ckpt = load_checkpoint(run_dir)
    stored = stored_options(run_dir)
    if stored is not None:
        changed = conflicts(stored, opts)
        if changed:
            name = changed[0]
            raise UserError(f"--{name.replace('_', '-')} {getattr(opts, name)!r} differs from the run's "
                            f"{getattr(stored, name)!r} in {run_dir}; a resumed run keeps its options: "
                            "leave the flag out, or train into a new --out")
    if ckpt.config.network() != model_config(opts).network():
        raise UserError(f"{run_dir}: was trained with config '{ckpt.config.name}'; resume with --config "
                        f"{ckpt.config.name} or train into a new --out")
    return opts, ckpt


def model_config(opts: TrainOptions) -> ModelConfig:
    """The named config, with the run's own rotation bins and targets, action features, zoom and stage-2
    point minimum where it sets them."""
    cfg = get_config(opts.config)
    if opts.rotation_bins:
        cfg = replace(cfg, rotation_bins=opts.rotation_bins)
    if (opts.coarse_action_features or opts.zoom is not None or opts.stage2_min_points) and cfg.stages == 1:
        raise UserError(f"--config {opts.config} has one stage: --zoom, --coarse-action-features and "
                        "--stage2-min-points need a second stage (--config rvt2 or small)")
    if opts.coarse_action_features:
        cfg = replace(cfg, coarse_action_features=True)
    if opts.zoom is not None:
        cfg = replace(cfg, zoom=opts.zoom)
    if opts.stage2_min_points is not None:
        cfg = replace(cfg, stage2_min_points=opts.stage2_min_points)
    return replace(cfg, rotation_sigma_deg=opts.rotation_sigma) if opts.rotation_sigma is not None else cfg


# --- what the run writes as it trains ------------------------------------------------------------------

class RunLog:
    """train.csv (one row per logged step), validation.csv (precision per task and keyframe at each
    validation) and TensorBoard, written by rank 0 only."""

    FIELDS = ["step", "loss", "heatmap1", "heatmap2", "rot_x", "rot_y", "rot_z", "gripper", "collision",
              "lr", "grad_norm", "samples_per_s", "skipped"]
    VAL_FIELDS = ["step", "task", "keyframe", "samples", "stage1_mm_median", "stage1_mm_p90", "stage2_mm_median",
                  "stage2_mm_p90", "rotation_deg_median", "rotation_deg_p90", "gripper_accuracy", "collision_accuracy"]

    def __init__(self, run_dir: Path, resume_step: int):
        self.train_csv = run_dir / "train.csv"
        self.val_csv = run_dir / "validation.csv"
        for path, fields in ((self.train_csv, self.FIELDS), (self.val_csv, self.VAL_FIELDS)):
            self._restart(path, fields, resume_step)
        from torch.utils.tensorboard import SummaryWriter

        self.tb = SummaryWriter(str(run_dir / "tb"), purge_step=resume_step + 1 if resume_step else None)

    @staticmethod
    def _restart(path: Path, fields: list[str], resume_step: int) -> None:
        """Keep the rows up to the checkpoint a run resumes from (none for a new run)."""
        rows = []
        if resume_step and path.exists():
            with open(path) as f:
                rows = [r for r in csv.DictReader(f) if int(r["step"]) <= resume_step]
        with atomic_open(path, "w") as f:
            writer = csv.DictWriter(f, fieldnames=fields)
            writer.writeheader()
            writer.writerows(rows)

    def log(self, row: dict) -> None:
        with open(self.train_csv, "a", newline="") as f:
            csv.DictWriter(f, fieldnames=self.FIELDS, extrasaction="ignore").writerow(row)
        for key, value in row.items():
            if key != "step" and value is not None and value != "":
                self.tb.add_scalar(f"train/{key}", value, row["step"])

    def log_validation(self, step: int, numbers: dict, report: dict) -> None:
        for key, value in numbers.items():
            if value is not None:
                self.tb.add_scalar(f"val/{key}", value, step)
        rows = []
        for task, entry in report["tasks"].items():
            for keyframe, s in task_rows(entry):
                rows.append({"step": step, "task": task, "keyframe": keyframe, "samples": s["samples"],
                             "stage1_mm_median": s["stage1_mm"]["median"], "stage1_mm_p90": s["stage1_mm"]["p90"],
                             "stage2_mm_median": s["stage2_mm"]["median"], "stage2_mm_p90": s["stage2_mm"]["p90"],
                             "rotation_deg_median": s["rotation_deg"]["median"], "rotation_deg_p90": s["rotation_deg"]["p90"],
                             "gripper_accuracy": s["gripper_accuracy"], "collision_accuracy": s["collision_accuracy"]})
        with open(self.val_csv, "a", newline="") as f:
            csv.DictWriter(f, fieldnames=self.VAL_FIELDS).writerows(rows)
        self.tb.flush()

    def close(self) -> None:
        self.tb.close()


def read_run_json(run_dir: Path) -> dict:
    """What the run has written to run.json so far ({} before its first write)."""
    path = run_dir / "run.json"
    return json.loads(path.read_text()) if path.exists() else {}


def stopped_at_time_limit(run_dir: Path) -> bool:
    """Whether the run stopped at its --time-limit, a checkpoint saved and steps left (run.json's `out_of_time`;
    under torchrun, whose exit code is then 0, the only sign). False for an unreadable run.json."""
    try:
        return bool(read_run_json(run_dir).get("out_of_time"))
    except json.JSONDecodeError:
        return False


def write_run_json(run_dir: Path, update: dict) -> None:
    content = read_run_json(run_dir)
    content.update(update)
    path = run_dir / "run.json"
    with atomic_open(path, "w") as f:
        json.dump(content, f, indent=2)

