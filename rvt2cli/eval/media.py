"""Episode videos and replayable rollout files."""

from pathlib import Path

import numpy as np

from rvt2cli.atomic import atomic_path
from rvt2cli.data import schemas
from rvt2cli.data.writer import McapChannels, frame_time_ns

PREDICTIONS_TOPIC = "/eval/predictions"


def write_video(frames: list[np.ndarray], path: Path, fps: int = 10) -> None:
    """mp4 (H.264 through imageio-ffmpeg's bundled binary)."""
    import imageio.v2 as imageio

    with atomic_path(path) as tmp:
        writer = imageio.get_writer(str(tmp), format="FFMPEG", fps=fps, codec="libx264", macro_block_size=1)
        for frame in frames:
            writer.append_data(frame)
        writer.close()


def write_rollout(outcome, control_hz: float, path: Path) -> None:
    """The rollout's predictions (one rvt2.Prediction per keyframe, stamped at the control step it
    was made), for replay next to the video in Foxglove."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        out = McapChannels(f)
        for i, step in enumerate(outcome.steps):
            obj = {"index": i, "frame": step.frame, "position": list(step.keyframe.position),
                   "quaternion": list(step.keyframe.quaternion), "gripper_open": step.keyframe.gripper_open,
                   "ignore_collisions": step.keyframe.ignore_collisions, "reached": step.reached}
            t = frame_time_ns(step.frame, control_hz)
            out.write_json(PREDICTIONS_TOPIC, schemas.PREDICTION, obj, t)
        out.writer.add_metadata("rvt2.rollout", {"task": outcome.task, "seed": str(outcome.seed), "success": str(outcome.success),
                                                 "failure": str(outcome.failure), "instruction": outcome.instruction})
        out.finish()
