"""The deployment API: RGB-D frames + intrinsics + camera poses -> the next keyframe, from a checkpoint
or an exported folder, equal to what `rvt2 eval` would predict on the same observation."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import AIM
from rvt2cli.data import read_episode
from rvt2cli.data.fusion import intrinsic_to_opencv
from rvt2cli.deploy import CameraFrame, KeyframePolicy
from rvt2cli.errors import UserError
from rvt2cli.eval.sources import PolicySource
from rvt2cli.tasks import get_task
from rvt2cli.train.checkpoint import load_policy

pytestmark = pytest.mark.sim
EXAMPLE = Path(__file__).parent.parent / "examples" / "deploy_from_frames.py"


@pytest.fixture(scope="module")
def episode(tiny_dataset):
    return read_episode(sorted(tiny_dataset.glob("*.mcap"))[0])


def holding(episode) -> int:
    """The first frame at which the gripper is closed (on the cube)."""
    return next(f for f in range(episode.num_frames) if episode.robot.gripper_command[f] < 0)


def frames_of(episode, frame: int, millimetres: bool = False) -> dict[str, CameraFrame]:
    """The episode's cameras as a robot program has them: OpenCV intrinsics, depth in m or mm."""
    out = {}
    for name, cam in episode.cameras(frame).items():
        depth = (cam.depth * 1000).round().astype(np.uint16) if millimetres else cam.depth
        out[name] = CameraFrame(rgb=cam.rgb, depth=depth, intrinsic=intrinsic_to_opencv(cam.intrinsic), cam2world=cam.cam2world)
    return out


def expected(run_dir, episode, frame: int):
    """What the evaluation loop predicts on this observation."""
    policy, ckpt = load_policy(run_dir)
    source = PolicySource(policy, ckpt)
    source.reset(get_task(episode.meta.task), 0, episode.instruction["text"])
    cloud = episode.cloud(frame)
    fingers = episode.meta.robot.fingers(episode.robot.joint_positions[frame], episode.robot.joint_names)
    return source.next(cloud, episode.robot.gripper_command[frame] > 0, fingers, 0)


def test_checkpoint_predicts_what_eval_predicts(tiny_checkpoint, episode):
    run_dir, _ = tiny_checkpoint
    policy = KeyframePolicy.load(run_dir)
    fingers = episode.meta.robot.fingers(episode.robot.joint_positions[0], episode.robot.joint_names)
    got = policy.predict(frames_of(episode, 0), episode.instruction["text"], gripper_open=True, finger_positions=fingers)
    assert got == expected(run_dir, episode, 0)  # same cloud, same observation, same keyframe
    # depth in millimetres (uint16) gives a cloud within half a millimetre: the same keyframe or a neighbouring voxel
    mm = policy.predict(frames_of(episode, 0, millimetres=True), episode.instruction["text"], gripper_open=True,
                        finger_positions=fingers, task="stack_cube")
    assert np.linalg.norm(np.subtract(mm.position, got.position)) < 0.02 and mm.gripper_open == got.gripper_open


def test_exported_folder_predicts_like_the_checkpoint(aimed_checkpoint, onnx_export, episode, tmp_path):
    """Exported with its aim offsets (the manifest's, an input of the ONNX graph), the policy answers as
    the checkpoint does, gripper open (the TCP aimed) and closed (the offset aimed)."""
    run_dir, (result, policy_dir) = aimed_checkpoint, onnx_export
    assert result.returncode == 0, result.stderr[-3000:]
    assert json.loads((policy_dir / "manifest.json").read_text())["tasks"]["stack_cube"]["aim_offset"] == AIM
    for frame, gripper_open in ((0, True), (holding(episode), False)):
        fingers = episode.meta.robot.fingers(episode.robot.joint_positions[frame], episode.robot.joint_names)
        args = (frames_of(episode, frame), episode.instruction["text"], gripper_open, fingers)
        exported, checkpoint = KeyframePolicy.load(policy_dir).predict(*args), KeyframePolicy.load(run_dir).predict(*args)
        assert np.linalg.norm(np.subtract(exported.position, checkpoint.position)) < 0.001
        assert np.allclose(np.abs(np.dot(exported.quaternion, checkpoint.quaternion)), 1.0, atol=1e-5)
        assert (exported.gripper_open, exported.ignore_collisions) == (checkpoint.gripper_open, checkpoint.ignore_collisions)
    # the example runs on it, as a user would (at the last frame above, holding)
    r = subprocess.run([sys.executable, str(EXAMPLE), str(policy_dir), str(episode.path), str(frame)], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert np.allclose(json.loads(r.stdout)["position"], exported.position, atol=0.02)
    # served (rvt2 serve), the export answers a client as it answers here
    from rvt2_client import PolicyClient

    from rvt2cli.serve.server import open_server

    server = open_server(str(policy_dir)).start_in_thread()
    try:
        with PolicyClient(server.url) as client:
            served = client.predict(*args)
            assert client.info()["model"]["kind"] == "export"
    finally:
        server.stop()
    assert (served.position, served.quaternion, served.gripper_open) == (exported.position, exported.quaternion, exported.gripper_open)
    # an export from before the aim_offset input is refused in one line, not run with the wrong inputs
    import shutil

    shutil.copytree(policy_dir, tmp_path / "old")
    manifest = json.loads((tmp_path / "old" / "manifest.json").read_text())
    del manifest["inputs"]["aim_offset"]
    (tmp_path / "old" / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(UserError, match="older rvt2"):
        KeyframePolicy.load(tmp_path / "old")


def test_bad_deployment_input(tiny_checkpoint, episode, tmp_path):
    run_dir, _ = tiny_checkpoint
    policy = KeyframePolicy.load(run_dir)
    with pytest.raises(UserError, match="inside the scene bounds"):
        policy.predict(frames_of(episode, 0), "stack", True, scene_bounds=[5, 5, 5, 6, 6, 6])
    with pytest.raises(UserError, match="give task="):
        policy.predict(frames_of(episode, 0), "stack", True, task="fold_laundry")
    (tmp_path / "fake").mkdir()
    (tmp_path / "fake" / "manifest.json").write_text("{}")
    with pytest.raises(UserError, match="not a policy written by `rvt2 export`"):
        KeyframePolicy.load(tmp_path / "fake")


def test_an_aimed_policy_answers_with_the_tcp_behind_the_aimed_point(tiny_checkpoint, aimed_checkpoint, episode):
    """Trained with an aim offset, a policy holding something answers with the TCP: the point its
    heatmaps found less the offset turned by its rotation; the evaluation loop aims alike; open, it aims
    the TCP itself."""
    from scipy.spatial.transform import Rotation

    run_dir, _ = tiny_checkpoint
    frame = holding(episode)
    fingers = episode.meta.robot.fingers(episode.robot.joint_positions[frame], episode.robot.joint_names)
    args = (frames_of(episode, frame), episode.instruction["text"], False, fingers)
    plain, aimed = KeyframePolicy.load(run_dir).predict(*args), KeyframePolicy.load(aimed_checkpoint).predict(*args)
    assert np.allclose(aimed.quaternion, plain.quaternion)
    behind = Rotation.from_quat(aimed.quaternion).apply(AIM)
    assert np.allclose(aimed.position, np.subtract(plain.position, behind), atol=1e-5)
    assert aimed == expected(aimed_checkpoint, episode, frame)   # rvt2 eval's PolicySource
    opened = (frames_of(episode, 0), episode.instruction["text"], True, fingers)
    assert KeyframePolicy.load(aimed_checkpoint).predict(*opened) == KeyframePolicy.load(run_dir).predict(*opened)
