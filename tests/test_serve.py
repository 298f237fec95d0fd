"""`rvt2 serve` and `rvt2_client`: a real server on the loopback, the tiny checkpoint, real clients.

The client answers what `KeyframePolicy.predict` answers in this process (exactly, on the CPU), from Python
3.11 here and from 3.10 and 3.12 where they are found; requests that arrive together share a forward pass
and each gets its own answer; malformed requests are refused naming their field while good ones go on
being answered; the evaluation over the wire, and with one policy shared by its workers, equals the
evaluation with a policy in each worker; SIGTERM answers what is in flight before the server stops.
"""

import hashlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import msgpack
import numpy as np
import pytest
import torch
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from conftest import assert_one_line_error
from rvt2_client import PolicyClient, PolicyError
from rvt2_client.wire import pack, unpack
from rvt2cli.data import read_episode
from rvt2cli.data.fusion import intrinsic_to_opencv
from rvt2cli.deploy import CameraFrame, KeyframePolicy
from rvt2cli.serve.batching import Batcher, at_fixed_size

pytestmark = pytest.mark.sim
ROOT = Path(__file__).resolve().parent.parent
CAMERAS = ("front", "left_shoulder", "right_shoulder")   # the tiny dataset's rig
TOKEN = "correct-horse-battery-staple-42"


class Served:
    """`rvt2 serve` in a process of its own, as a user starts it; its log (stderr) in a file."""

    def __init__(self, checkpoint, folder: Path, *options: str):
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "token").write_text(TOKEN + "\n")
        os.chmod(folder / "token", 0o600)
        self.log = folder / "serve.log"
        self.process = subprocess.Popen(
            [sys.executable, "-m", "rvt2cli", "serve", "--checkpoint", str(checkpoint), "--port", "0",
             "--token-file", str(folder / "token"), *options],
            stdout=subprocess.PIPE, stderr=open(self.log, "w"), text=True, cwd=ROOT)
        line = self.process.stdout.readline()
        assert "serving" in line, self.log.read_text()[-3000:]
        self.url = line.split(" on ", 1)[1].split(";")[0]
        self.http = "http" + self.url[2:]

    def client(self, **kw) -> PolicyClient:
        return PolicyClient(self.url, token=TOKEN, **kw)

    def rss_mib(self) -> float:
        status = Path(f"/proc/{self.process.pid}/status").read_text()
        return int(next(line for line in status.splitlines() if line.startswith("VmRSS")).split()[1]) / 1024

    def stop(self) -> int:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
        return self.process.wait(timeout=60)


@pytest.fixture(scope="module")
def served(tiny_checkpoint, tmp_path_factory):
    run_dir, _ = tiny_checkpoint
    server = Served(run_dir, tmp_path_factory.mktemp("served"), "--max-wait-ms", "30", "--max-message-mb", "4",
                    "--cameras", ",".join(CAMERAS))
    yield server
    assert server.stop() == 0


@pytest.fixture(scope="module")
def in_process(tiny_checkpoint):
    return KeyframePolicy.load(tiny_checkpoint[0])


@pytest.fixture(scope="module")
def observations(tiny_dataset):
    """Robot-side observations from the tiny demos: (frames as a robot has them, instruction, gripper open,
    fingers, keyframes done), at several frames of both episodes."""
    out = []
    for path in sorted(tiny_dataset.glob("*.mcap")):
        episode = read_episode(path)
        for index, frame in enumerate(episode.obs_frames[:12:3]):
            frames = {name: CameraFrame(rgb=cam.rgb, depth=cam.depth, intrinsic=intrinsic_to_opencv(cam.intrinsic),
                                        cam2world=cam.cam2world) for name, cam in episode.cameras(frame).items()}
            fingers = episode.meta.robot.fingers(episode.robot.joint_positions[frame], episode.robot.joint_names)
            out.append((frames, episode.instruction["text"], bool(episode.robot.gripper_command[frame] > 0),
                        tuple(float(f) for f in fingers), index))
    return out


def same(wire, local) -> bool:
    """A client's keyframe is the in-process one, to the bit."""
    return (wire.position, wire.quaternion, wire.gripper_open, wire.ignore_collisions) == \
        (local.position, local.quaternion, local.gripper_open, local.ignore_collisions)


# --- the client answers what the policy answers in this process ---------------------------------------

CLIENT_SCRIPT = """
import json, sys
import numpy as np
from rvt2_client import PolicyClient
data = np.load(sys.argv[2])
frames = {name: {key: data[name + "/" + key] for key in ("rgb", "depth", "intrinsic", "cam2world")}
          for name in json.loads(sys.argv[3])}
with PolicyClient(sys.argv[1], token=sys.argv[4]) as client:
    k = client.predict(frames, sys.argv[5], gripper_open=True, finger_positions=(0.04, 0.04), task="stack_cube")
heavy = sorted(m for m in ("torch", "rvt2cli", "sapien", "mani_skill") if m in sys.modules)
print(json.dumps({"python": sys.version.split()[0], "pose": list(k.position + k.quaternion), "gripper_open": k.gripper_open,
                  "ignore_collisions": k.ignore_collisions, "heavy": heavy}))
"""


def client_pythons() -> dict[str, str]:
    """Interpreters to run the client on, besides this one: RVT2_CLIENT_PYTHONS (paths, space-separated), else
    python3.10 and python3.12 on the PATH; each kept where it has numpy, msgpack and websockets."""
    listed = os.environ.get("RVT2_CLIENT_PYTHONS", "").split() or [p for p in map(shutil.which, ("python3.10", "python3.12")) if p]
    found = {}
    for python in listed:
        probe = subprocess.run([python, "-c", "import sys, numpy, msgpack, websockets; print('%d.%d' % sys.version_info[:2])"],
                               capture_output=True, text=True)
        if probe.returncode == 0:
            found[probe.stdout.strip()] = python
    return found


@pytest.mark.parametrize("version", ["this", "3.10", "3.12"])
def test_the_client_answers_what_the_policy_answers_in_process(served, in_process, observations, version, tmp_path):
    """From the robot's side: no torch and no rvt2 imported, on ROS 2 Humble's Python 3.10 too."""
    python = sys.executable if version == "this" else client_pythons().get(version)
    if python is None:
        pytest.skip(f"no Python {version} with numpy, msgpack and websockets here (set RVT2_CLIENT_PYTHONS)")
    frames, instruction, *_ = observations[0]
    np.savez(tmp_path / "frames.npz", **{f"{name}/{key}": getattr(f, key) for name, f in frames.items()
                                         for key in ("rgb", "depth", "intrinsic", "cam2world")})
    r = subprocess.run([python, "-c", CLIENT_SCRIPT, served.url, str(tmp_path / "frames.npz"), json.dumps(list(frames)),
                        TOKEN, instruction], capture_output=True, text=True, timeout=120, cwd=tmp_path,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, r.stderr[-2000:]
    got = json.loads(r.stdout)
    assert got["heavy"] == [], got
    assert version == "this" or got["python"].startswith(version)
    want = in_process.predict(frames, instruction, gripper_open=True, finger_positions=(0.04, 0.04), task="stack_cube")
    assert tuple(got["pose"]) == want.position + want.quaternion
    assert (got["gripper_open"], got["ignore_collisions"]) == (want.gripper_open, want.ignore_collisions)


def test_frames_in_millimetres_clouds_and_every_state_answer_as_in_process(served, in_process, observations):
    with served.client() as client:
        for frames, instruction, gripper_open, fingers, done in observations[::3]:
            args = (instruction, gripper_open, fingers, done)
            assert same(client.predict(frames, *args), in_process.predict(frames, *args))
            millimetres = {n: CameraFrame(f.rgb, (f.depth * 1000).round().astype(np.uint16), f.intrinsic, f.cam2world)
                           for n, f in frames.items()}
            assert same(client.predict(millimetres, *args, task="stack_cube"), in_process.predict(millimetres, *args, task="stack_cube"))
            cloud = in_process.cloud(frames, in_process.scene_bounds("stack_cube"))
            inputs = in_process.cloud_inputs(cloud, *args, task="stack_cube")
            assert same(client.predict_cloud(cloud.xyz, cloud.rgb, *args, task="stack_cube"), in_process.predict_inputs([inputs])[0])
        info = client.info()
    assert list(info["tasks"]) == ["stack_cube"] and info["cameras"] == list(CAMERAS)


# --- several robots at once ---------------------------------------------------------------------------

def test_a_batched_forward_answers_each_input_as_alone(in_process, observations):
    """The model's batched forward (clouds of different sizes padded) gives each request the keyframe it gets
    alone: exactly, on the CPU."""
    inputs = [in_process.inputs(frames, instruction, gripper_open, fingers, done)
              for frames, instruction, gripper_open, fingers, done in observations]
    assert len({len(i.cloud) for i in inputs}) > 1
    alone = [in_process.predict_inputs([i])[0] for i in inputs]
    assert in_process.predict_inputs(inputs) == alone


def test_a_fixed_batch_answers_a_request_whatever_arrived_with_it(in_process, observations):
    """--fixed-batch: every forward pass has the same number of inputs (padded with copies of the first), and
    a request's answer is the same to the bit whichever requests came with it."""
    inputs = [in_process.inputs(frames, instruction, gripper_open, fingers, done)
              for frames, instruction, gripper_open, fingers, done in observations]
    sizes = []

    def forward(batch):
        sizes.append(len(batch))
        return in_process.predict_inputs(batch)

    fixed = at_fixed_size(forward, 5)
    first = fixed(inputs[:1])[0]
    assert all(fixed([inputs[0], *others])[0] == first for others in (inputs[1:3], inputs[3:7], inputs[-2:]))
    assert [a[0] for a in (fixed(inputs[2:5]), fixed(inputs[2:3]))] == [fixed([inputs[2], inputs[0]])[0]] * 2
    assert set(sizes) == {5}
    with pytest.raises(ValueError, match="6 items for a batch of 5"):
        fixed(inputs[:6])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_on_a_gpu_a_fixed_batch_answers_a_request_whatever_arrived_with_it(tiny_checkpoint, observations):
    """On a GPU, where batches of other sizes may take other kernels: at one fixed size a request's keyframe is
    the same to the bit whichever other requests fill the batch."""
    policy = KeyframePolicy.load(tiny_checkpoint[0], device="cuda")
    inputs = [policy.inputs(frames, instruction, gripper_open, fingers, done)
              for frames, instruction, gripper_open, fingers, done in observations]
    fixed = at_fixed_size(policy.predict_inputs, 6)
    first = fixed(inputs[:1])[0]
    assert all(fixed([inputs[0], *others])[0] == first for others in (inputs[1:3], inputs[3:8], inputs[-2:], inputs[1:6]))


def test_robots_calling_together_share_forward_passes_and_each_gets_its_own_answer(served, in_process, observations):
    clients = 16
    expected = [in_process.predict(frames, *rest) for frames, *rest in observations]
    start = threading.Barrier(clients)
    wrong, errors = [], []

    def robot(index: int) -> None:
        try:
            with served.client() as client:
                client.info()
                for round_ in range(3):
                    start.wait(timeout=60)
                    which = (index + round_) % len(observations)
                    frames, *rest = observations[which]
                    if not same(client.predict(frames, *rest), expected[which]):
                        wrong.append((index, round_))
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(repr(e))

    threads = [threading.Thread(target=robot, args=(i,)) for i in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=300)
    assert not errors and not wrong, (errors, wrong)
    with served.client() as client:
        batching = client.info()["batching"]
    assert batching["largest"] > 1, batching   # requests were answered together


def test_the_batcher_answers_each_request_and_isolates_a_failing_one():
    def run(items):
        if "bad" in items:
            raise ValueError("bad item")
        sizes.append(len(items))
        return [f"answer to {i}" for i in items]

    sizes: list[int] = []
    batcher = Batcher(run, max_batch=4, max_wait_s=0.2)
    futures = [batcher.submit(i) for i in range(10)]
    assert [f.result(timeout=10) for f in futures] == [f"answer to {i}" for i in range(10)]
    assert max(sizes) == 4 and sum(sizes) == 10 and all(f.batch_size <= 4 for f in futures)
    mixed = [batcher.submit(x) for x in ("a", "bad", "c")]
    assert [mixed[0].result(timeout=10), mixed[2].result(timeout=10)] == ["answer to a", "answer to c"]
    with pytest.raises(ValueError, match="bad item"):
        mixed[1].result(timeout=10)
    batcher.close()
    with pytest.raises(RuntimeError, match="closed"):
        batcher.submit(1)


# --- bad input ---------------------------------------------------------------------------------------

def _array(a: np.ndarray) -> dict:
    return {"__ndarray__": True, "dtype": a.dtype.name, "shape": list(a.shape), "data": a.tobytes()}


def malformed_requests(frames, instruction) -> list[tuple[str, object, str | None]]:
    """(what, the message (a dict, or raw bytes or text), the field its refusal names; None: the connection
    closes after the refusal)."""
    cams = {n: {"rgb": f.rgb, "depth": f.depth, "intrinsic": f.intrinsic, "cam2world": f.cam2world} for n, f in frames.items()}
    good = {"type": "predict", "id": 7, "token": TOKEN, "frames": cams, "instruction": instruction, "gripper_open": True,
            "finger_positions": [0.04, 0.04], "keyframes_done": 0, "task": "stack_cube"}

    def with_camera(**change):
        return {**good, "frames": {**cams, "front": {**cams["front"], **change}}}

    depth = cams["front"]["depth"]
    nan_depth, negative_depth = depth.copy(), depth.copy()
    nan_depth[5:9, 5:9] = np.nan
    negative_depth[0, :4] = -0.5
    without_depth = {k: v for k, v in cams["front"].items() if k != "depth"}
    broken_rgb = {**_array(cams["front"]["rgb"]), "data": b"\x00" * 10}
    cloud = {"xyz": np.full((100, 3), np.nan, np.float32), "rgb": np.zeros((100, 3), np.uint8)}
    return [
        ("a wrong token", {**good, "token": "guess"}, "token"),
        ("no token", {k: v for k, v in good.items() if k != "token"}, "token"),
        ("colour as floats", with_camera(rgb=cams["front"]["rgb"].astype(np.float32)), "frames.front.rgb"),
        ("colour without channels", with_camera(rgb=cams["front"]["rgb"][..., 0].copy()), "frames.front.rgb"),
        ("depth of another size", with_camera(depth=depth[:-2]), "frames.front.depth"),
        ("NaN depth", with_camera(depth=nan_depth), "frames.front.depth"),
        ("negative depth", with_camera(depth=negative_depth), "frames.front.depth"),
        ("depth as int32", with_camera(depth=depth.astype(np.int32)), "frames.front.depth"),
        ("a camera missing", {**good, "frames": {n: c for n, c in cams.items() if n != "front"}}, "frames"),
        ("a camera without depth", {**good, "frames": {**cams, "front": without_depth}}, "frames.front.depth"),
        ("neither frames nor cloud", {k: v for k, v in good.items() if k != "frames"}, "frames"),
        ("an unknown task", {**good, "task": "fold_laundry"}, "task"),
        ("an over-long instruction", {**good, "instruction": "stack the cube " * 100}, "instruction"),
        ("no instruction", {k: v for k, v in good.items() if k != "instruction"}, "instruction"),
        ("a 2x3 intrinsic", with_camera(intrinsic=np.eye(3)[:2]), "frames.front.intrinsic"),
        ("a pose without a unit quaternion", with_camera(cam2world=np.array([0, 0, 1, 0, 0, 0, 2.0])), "frames.front.cam2world"),
        ("gripper_open as a string", {**good, "gripper_open": "yes"}, "gripper_open"),
        ("three fingers", {**good, "finger_positions": [0.04, 0.04, 0.04]}, "finger_positions"),
        ("negative keyframes done", {**good, "keyframes_done": -1}, "keyframes_done"),
        ("inverted scene bounds", {**good, "scene_bounds": [1, 1, 1, 0, 0, 0]}, "scene_bounds"),
        ("cameras that see nothing in the bounds", {**good, "scene_bounds": [5, 5, 5, 6, 6, 6]}, "frames"),
        ("an unknown field", {**good, "instrucion": "typo"}, "instrucion"),
        ("an unknown request type", {**good, "type": "train"}, "type"),
        ("array bytes that do not fill its shape", with_camera(rgb=broken_rgb), "frames.front.rgb"),
        ("an array of Python objects", with_camera(rgb={**_array(cams["front"]["rgb"]), "dtype": "object"}), "frames.front.rgb"),
        ("a NaN cloud", {k: v for k, v in {**good, "cloud": cloud}.items() if k != "frames"}, "cloud.xyz"),
        ("a message over the size limit", {**good, "padding": b"\x00" * (5 * 2**20)}, "message"),
        ("garbage bytes", b"\xc1\xff\x00garbage" * 50, None),
        ("a text frame", "hello policy", None),
        ("a msgpack list, not a map", msgpack.packb([1, 2, 3]), None),
    ]


def test_bad_input_is_refused_naming_the_field_and_everyone_else_is_served(served, in_process, observations):
    frames, instruction, gripper_open, fingers, done = observations[1]
    expected = in_process.predict(frames, instruction, gripper_open, fingers, done)
    kinds = malformed_requests(frames, instruction)
    assert len(kinds) >= 20
    raw = connect(served.url, max_size=None, compression=None)
    robot = served.client()
    refused, memory = 0, []
    for round_ in range(8):
        for what, message, field in kinds:
            raw.send(pack(message) if isinstance(message, dict) else message)
            reply = unpack(raw.recv(timeout=60))
            assert reply["ok"] is False, what
            assert reply["field"] == (field or "message"), (what, reply)
            if field is None:  # garbage: refused, then the connection closed
                with pytest.raises(ConnectionClosed):
                    raw.recv(timeout=30)
                raw = connect(served.url, max_size=None, compression=None)
            refused += 1
            if refused % 3 == 0:  # a robot's good request between the bad ones
                assert same(robot.predict(frames, instruction, gripper_open, fingers, done), expected), what
        # a client that leaves mid-request: the server answers into a closed connection and serves on
        leaving = connect(served.url, max_size=None, compression=None)
        leaving.send(pack({"type": "predict", "id": 1, "token": TOKEN, "frames": {n: vars(f) for n, f in frames.items()},
                           "instruction": instruction, "gripper_open": True}))
        leaving.close()
        refused += 1
        memory.append(served.rss_mib())
    assert refused >= 200
    assert same(robot.predict(frames, instruction, gripper_open, fingers, done), expected)
    robot.close()
    print(f"server memory after each round of bad input (MiB): {memory}")
    assert memory[-1] - memory[1] < 25, memory   # flat after the first rounds (allocator pools filled)
    # the client checks the size before sending, against the limit the server gave
    with served.client() as client, pytest.raises(PolicyError, match="over the server's limit") as refused_locally:
        big = {n: CameraFrame(np.zeros((1200, 1600, 3), np.uint8), np.zeros((1200, 1600), np.float32), f.intrinsic, f.cam2world)
               for n, f in frames.items()}
        client.predict(big, instruction, True)
    assert refused_locally.value.field == "message"


# --- operations ----------------------------------------------------------------------------------------

def test_health_needs_the_token_and_names_the_checkpoint_and_each_request_is_logged(served, tiny_checkpoint):
    with pytest.raises(urllib.error.HTTPError) as unauthorised:
        urllib.request.urlopen(served.http + "/healthz", timeout=30)
    assert unauthorised.value.code == 401
    request = urllib.request.Request(served.http + "/healthz", headers={"Authorization": f"Bearer {TOKEN}"})
    info = json.loads(urllib.request.urlopen(request, timeout=30).read())
    weights = Path(info["model"]["weights"])
    assert info["status"] == "ok" and info["device"] == "cpu" and info["model"]["kind"] == "checkpoint"
    assert info["model"]["sha256"] == hashlib.sha256(weights.read_bytes()).hexdigest()
    assert weights.parent == (tiny_checkpoint[0] / (tiny_checkpoint[0] / "last").read_text().strip()).resolve()
    assert info["config"]["name"] == "small" and info["tasks"]["stack_cube"]["scene_bounds"]
    with served.client() as client:
        client.info()
        with pytest.raises(PolicyError, match="instruction"):
            client.predict_cloud(np.zeros((10, 3), np.float32), np.zeros((10, 3), np.uint8), "", True)
    time.sleep(0.5)
    lines = served.log.read_text().splitlines()
    assert any("GET /healthz status=401" in line for line in lines) and any("GET /healthz status=200" in line for line in lines)
    requests = [line for line in lines if " id=" in line]
    assert requests and all("latency_ms=" in line for line in requests)
    assert any("status=refused field=instruction" in line for line in requests)
    assert not any("Traceback" in line for line in lines)


def test_sigterm_answers_the_requests_in_flight_then_stops(tiny_checkpoint, observations, in_process, tmp_path):
    server = Served(tiny_checkpoint[0], tmp_path, "--max-wait-ms", "1000")  # requests wait in the batcher: in flight
    frames, instruction, gripper_open, fingers, done = observations[2]
    expected = in_process.predict(frames, instruction, gripper_open, fingers, done)
    clients = [server.client() for _ in range(3)]
    for client in clients:
        client.info()
    answers = []
    threads = [threading.Thread(target=lambda c=c: answers.append(c.predict(frames, instruction, gripper_open, fingers, done)))
               for c in clients]
    for t in threads:
        t.start()
    time.sleep(0.3)
    server.process.send_signal(signal.SIGTERM)
    for t in threads:
        t.join(timeout=60)
    assert len(answers) == 3 and all(same(a, expected) for a in answers)
    assert server.process.wait(timeout=60) == 0   # it ends by itself (a second signal, as stop() sends, would kill it)
    log = server.log.read_text()
    assert "answering the 3 requests in flight" in log, log[-2000:]
    assert log.count("type=predict status=ok") == 3 and log.strip().splitlines()[-1].endswith("0 refusals"), log[-2000:]
    with pytest.raises(ConnectionError):
        clients[0].predict(frames, instruction, gripper_open, fingers, done)


def test_serve_refuses_unsafe_or_impossible_setups_in_one_line(tiny_checkpoint, tmp_path, cli):
    run_dir, _ = tiny_checkpoint
    assert_one_line_error(cli("serve", "--checkpoint", run_dir, "--host", "0.0.0.0"), "0.0.0.0", "--token-file")
    (tmp_path / "empty").write_text("\n")
    assert_one_line_error(cli("serve", "--checkpoint", run_dir, "--token-file", tmp_path / "empty"), "empty", "token")
    assert_one_line_error(cli("serve", "--checkpoint", tmp_path / "nope"), "nope", "no such checkpoint")
    assert_one_line_error(cli("eval", "--token-file", tmp_path / "empty"), "--token-file", "--policy-url")
    with socket.socket() as s:   # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    assert_one_line_error(cli("eval", "--policy-url", f"ws://127.0.0.1:{port}", "--out", tmp_path / "e"), "cannot connect")
    r = cli("serve", "--help")
    assert r.returncode == 0 and "--token-file" in r.stdout and "--max-wait-ms" in r.stdout


# --- the wire, end to end ------------------------------------------------------------------------------

def test_eval_over_the_wire_equals_a_policy_per_worker_and_a_shared_policy_is_deterministic(served, tiny_checkpoint, tmp_path):
    """The same seeds three ways: two workers each loading the checkpoint (the default), the served policy
    over the wire (`--policy-url`, batch 1 like a worker's), and two workers asking one copy in the main
    process (`--shared-policy`, every forward at batch 2), twice: the same outcomes both times."""
    from rvt2cli.eval.runner import EvalOptions, evaluate

    run_dir, _ = tiny_checkpoint
    options = dict(episodes=2, keyframe_budget=3)
    per_worker = evaluate(EvalOptions(checkpoint=str(run_dir), workers=2, out=str(tmp_path / "per_worker"), **options))
    wire = evaluate(EvalOptions(checkpoint=None, policy_url=served.url, token=TOKEN, out=str(tmp_path / "wire"), **options))
    shared = evaluate(EvalOptions(checkpoint=str(run_dir), workers=2, shared_policy=True, out=str(tmp_path / "shared"), **options))
    again = evaluate(EvalOptions(checkpoint=str(run_dir), workers=2, shared_policy=True, out=str(tmp_path / "again"), **options))

    def outcomes(result) -> dict:
        return {job: (o.success, o.failure, o.control_steps, [(s.keyframe, s.retry, s.reached) for s in o.steps])
                for job, o in result.outcomes}

    assert len(outcomes(per_worker)) == 2 and all(o[3] for o in outcomes(per_worker).values())
    assert outcomes(wire) == outcomes(per_worker)
    assert outcomes(again) == outcomes(shared) and outcomes(shared).keys() == outcomes(per_worker).keys()
    assert "served, sha256 " in wire.report["checkpoint"]
    assert shared.report["checkpoint"] == per_worker.report["checkpoint"] and shared.report["shared_policy"] is True
    assert "shared by the workers" in (tmp_path / "shared" / "eval.md").read_text()


def test_a_shared_policy_needs_a_checkpoint_and_workers(tiny_checkpoint, tmp_path, cli):
    assert_one_line_error(cli("eval", "--checkpoint", tiny_checkpoint[0], "--shared-policy", "--out", tmp_path / "e"),
                          "--shared-policy", "--workers 2")
