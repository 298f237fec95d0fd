"""The MCAP episode format: bit-exact round trip, keyframe annotations, and every kind of bad file."""

import json

import numpy as np
import pytest
from mcap.writer import Writer

from conftest import assert_one_line_error
from episode_factory import random_episode
from rvt2cli.data import EpisodeMeta, EpisodeWriter, read_episode, write_keyframes
from rvt2cli.data.keyframes import Keyframe, KeyframeAnnotation, Sample
from rvt2cli.data.fusion import fuse
from rvt2cli.data.writer import McapChannels
from rvt2cli.errors import UserError


def test_round_trip_is_bit_exact(tmp_path):
    path = tmp_path / "ep.mcap"
    truth = random_episode(path, frames=12, obs_every=5)
    ep = read_episode(path)

    assert ep.meta == truth["meta"]
    assert ep.num_frames == 12 and ep.obs_frames == [0, 5, 10]
    assert ep.robot.joint_positions.dtype == np.float32
    assert np.array_equal(ep.robot.joint_positions, np.stack(truth["qpos"]))
    assert np.array_equal(ep.robot.joint_velocities, np.stack(truth["qvel"]))
    assert np.array_equal(ep.robot.tcp_pose.astype(np.float32), np.stack(truth["tcp"]))
    assert ep.robot.gripper_command.tolist() == [1.0] * 6 + [-1.0] * 6
    assert ep.robot.actions[-1] is None and len(ep.robot.actions[0]) == 8
    assert ep.instruction["text"] == "insert the peg into the box"
    for t in ep.obs_frames:
        stored = ep.stored_cloud(t)
        assert stored.xyz.dtype == np.float32 and stored.rgb.dtype == np.uint8
        assert np.array_equal(stored.xyz, truth["clouds"][t].xyz)
        assert np.array_equal(stored.rgb, truth["clouds"][t].rgb)
        fused = fuse(truth["cams"][t], truth["meta"].scene_bounds)
        assert len(fused) > 0
        assert np.array_equal(ep.cloud(t).xyz, fused.xyz) and np.array_equal(ep.cloud(t).rgb, fused.rgb)
        for name, cam in ep.cameras(t).items():
            want = truth["cams"][t][name]
            assert np.array_equal(cam.rgb, want.rgb)
            assert np.array_equal(cam.depth, want.depth) and cam.depth.dtype == np.float32
            assert np.array_equal(cam.intrinsic, want.intrinsic)
            assert np.array_equal(cam.cam2world, want.cam2world)
    assert ep.sim_state(3) == truth["sim"][3]


def test_frames_without_observations_and_out_of_range_are_clear(tmp_path):
    path = tmp_path / "ep.mcap"
    random_episode(path, frames=12, obs_every=5)
    ep = read_episode(path)
    with pytest.raises(UserError, match=r"frame 3 has no observation; frames with observations: 0, 5, 10"):
        ep.cloud(3)
    with pytest.raises(UserError, match=r"frame 40 is out of range; this episode has frames 0..11"):
        ep.cloud(40)


def test_keyframes_are_written_idempotently(tmp_path):
    path = tmp_path / "ep.mcap"
    random_episode(path)
    annotation = KeyframeAnnotation(
        keyframes=(Keyframe.from_pose([0.1, 0.2, 0.3, 0, 0, 0, 1], gripper_open=False, ignore_collisions=False, frame=6,
                                      reasons=("gripper",)),),
        samples=(Sample(obs_frame=0, keyframe=0), Sample(obs_frame=5, keyframe=0)),
        params={"stop_velocity": 0.1},
    )
    before = read_episode(path)
    write_keyframes(path, annotation)
    first = path.read_bytes()
    write_keyframes(path, annotation)
    assert path.read_bytes() == first
    after = read_episode(path)
    assert after.keyframes == annotation
    assert after.keyframes.keyframes[0].position == (0.1, 0.2, 0.3) and after.keyframes.starts == {0, 6}
    # everything else is unchanged
    assert np.array_equal(after.robot.joint_positions, before.robot.joint_positions)
    assert np.array_equal(after.cloud(5).xyz, before.cloud(5).xyz)
    assert after.meta == before.meta
    assert not list(tmp_path.glob(".*tmp*"))


def test_aborted_writer_leaves_no_file(tmp_path):
    path = tmp_path / "ep.mcap"
    with pytest.raises(RuntimeError):
        with EpisodeWriter(path, control_hz=20.0) as w:
            w.write_instruction("x", task="t", template_index=0, variation={})
            raise RuntimeError("simulated crash mid-episode")
    assert list(tmp_path.iterdir()) == []


def test_info_prints_summary_and_json(tmp_path, cli):
    path = tmp_path / "ep.mcap"
    random_episode(path)
    r = cli("info", path)
    assert r.returncode == 0, r.stderr
    assert "insert_peg" in r.stdout and "/points/world" in r.stdout and "keyframes    none" in r.stdout
    r = cli("info", "--json", path)
    info = json.loads(r.stdout)[0]
    assert info["frames"] == 12 and info["cameras"] == ["front", "wrist"] and info["success"] is True
    assert info["channels"]["/robot/state"] == 12 and info["channels"]["/points/world"] == 3
    assert info["size_bytes"] == path.stat().st_size


def test_info_on_missing_file(tmp_path, cli):
    assert_one_line_error(cli("info", tmp_path / "nope.mcap"), "nope.mcap", "no such file")


def test_info_on_a_file_that_is_not_mcap(tmp_path, cli):
    path = tmp_path / "notes.mcap"
    path.write_text("hello, not an mcap file\n")
    assert_one_line_error(cli("info", path), "notes.mcap", "not an MCAP file")


def test_info_on_truncated_file_counts_recoverable_messages(tmp_path, cli):
    path = tmp_path / "ep.mcap"
    random_episode(path)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    r = cli("info", cut)
    assert_one_line_error(r, "cut.mcap", "truncated", "complete messages are recoverable")


def test_info_on_foreign_mcap(tmp_path, cli):
    path = tmp_path / "foreign.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("other.Thing", "jsonschema", b"{}")
        cid = w.register_channel("/thing", "json", sid)
        w.add_message(cid, log_time=0, data=b"{}", publish_time=0)
        w.finish()
    assert_one_line_error(cli("info", path), "foreign.mcap", "not an rvt2 episode")


def test_info_refuses_newer_major_version(tmp_path, cli):
    path = tmp_path / "future.mcap"
    with open(path, "wb") as f:
        out = McapChannels(f)
        out.write_json("/language/instruction", "rvt2.Instruction", {"text": "x", "task": "t", "template_index": 0, "variation": {}}, 0)
        out.writer.add_metadata("rvt2.episode", {"format_version": "2.0", "episode": "{}"})
        out.finish()
    assert_one_line_error(cli("info", path), "future.mcap", "format 2.0 is newer", "upgrade rvt2")


def test_info_with_good_and_bad_files_reports_both(tmp_path, cli):
    good = tmp_path / "good.mcap"
    random_episode(good)
    r = cli("info", good, tmp_path / "missing.mcap")
    assert r.returncode == 2
    assert "insert_peg" in r.stdout and "missing.mcap: no such file" in r.stderr


def test_metadata_must_match_schema(tmp_path):
    meta = EpisodeMeta(task="t", env_id="E", seed=0, success=True, expert="x", num_frames=0, control_hz=20.0,
                       scene_bounds=[0, 0, 0, 1, 1, 1], cameras=[], instruction="i", versions={})
    with pytest.raises(UserError, match="num_frames"):
        with EpisodeWriter(tmp_path / "bad.mcap", control_hz=20.0) as w:
            w.finish(meta)
    assert list(tmp_path.iterdir()) == []


def test_a_folder_of_episodes_leaves_out_an_interrupted_writers_hidden_file(tmp_path, cli):
    """A killed recorder leaves its unfinished episode under a hidden temporary name: reading the folder
    (extract-keyframes, train, pack-samples) uses the finished episodes and never that one."""
    from rvt2cli.atomic import temp_path_for
    from rvt2cli.data.paths import episode_paths

    done = tmp_path / "stack_cube_0000.mcap"
    random_episode(done)
    unfinished = temp_path_for(tmp_path / "stack_cube_0001.mcap")
    unfinished.write_bytes(done.read_bytes()[:1000])  # cut off mid-write
    assert episode_paths([str(tmp_path)]) == [done]
    r = cli("extract-keyframes", tmp_path)
    assert r.returncode == 0, r.stderr
    assert unfinished.exists()  # not ours to delete


def test_episodes_record_rvt2s_version_also_from_a_source_tree():
    """The versions an episode stores come from rvt2 itself and the installed libraries; a library
    without metadata (or rvt2 run from its source tree) is no reason to fail a recording."""
    from rvt2cli import __version__
    from rvt2cli.data.provenance import software_versions

    versions = software_versions("numpy", "no-such-distribution-rvt2-test")
    assert versions["rvt2"] == __version__ and versions["numpy"] == np.__version__
    assert versions["no-such-distribution-rvt2-test"] == "unknown"


def test_the_compiled_schemas_judge_every_message_as_jsonschema_does(tmp_path):
    """The reader checks messages with schemas compiled by fastjsonschema and asks jsonschema only to
    explain a rejection; so the two must agree. Every JSON message of a real episode file, and each of its
    fields deleted, retyped (text, bool, null, -1, an empty list, a list of text) or joined by an unknown one."""
    import jsonschema

    from rvt2cli.data import reader, schemas

    path = tmp_path / "ep.mcap"
    random_episode(path, frames=6, obs_every=5)
    write_keyframes(path, KeyframeAnnotation(
        keyframes=[Keyframe(frame=5, position=[0.1, 0.2, 0.3], quaternion=[0, 0, 0, 1], gripper_open=True,
                            ignore_collisions=False, reasons=["last"])],
        samples=[Sample(obs_frame=0, keyframe=0)], params={}))
    data = path.read_bytes()
    found = {schemas.EPISODE: reader.read_metadata(path, data)[1]}
    for message in reader.iter_raw_messages(path, data):
        if message.topic in reader._JSON_TOPICS:
            found.setdefault(reader._JSON_TOPICS[message.topic], json.loads(message.data))
    assert set(found) == {schemas.EPISODE, schemas.ROBOT_STATE, schemas.SIM_STATE, schemas.INSTRUCTION, schemas.KEYFRAMES}

    def variants(obj):
        yield obj
        yield {**obj, "unknown_field": 1}
        for key in obj:
            yield {k: v for k, v in obj.items() if k != key}
            for value in ("text", True, None, -1, [], ["text"]):
                yield {**obj, key: value}

    checked = 0
    for name, obj in found.items():
        walker = jsonschema.Draft202012Validator(json.loads(schemas.schema_text(name)))
        for variant in variants(obj):
            try:
                schemas._compiled(name)(variant)
                compiled_ok = True
            except Exception:  # noqa: BLE001 - fastjsonschema's JsonSchemaValueException
                compiled_ok = False
            assert compiled_ok == walker.is_valid(variant), (name, variant)
            checked += 1
    assert checked > 100
