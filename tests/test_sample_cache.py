"""`rvt2 pack-samples` and training from the cache: same samples as the episode files, no MCAP needed."""

import subprocess
import sys

import numpy as np
import pytest
import torch

from conftest import TINY_TRAIN, assert_one_line_error
from rvt2cli.data.paths import episode_paths
from rvt2cli.errors import UserError
from rvt2cli.model.config import get_config
from rvt2cli.model.language import InstructionCache
from rvt2cli.train.sample_cache import LEVELS, is_sample_cache, load_sample_cache, pack_sample_cache
from rvt2cli.train.samples import load_samples, select_samples

pytestmark = pytest.mark.sim


@pytest.fixture(scope="module")
def cache(tiny_dataset, tmp_path_factory):
    path = tmp_path_factory.mktemp("cache") / "samples.safetensors"
    pack_sample_cache([str(tiny_dataset)], path, progress=False)
    return path


def test_cache_holds_the_episode_samples(tiny_dataset, cache):
    original = load_samples(episode_paths([str(tiny_dataset)]), progress=False)
    packed, embeddings = load_sample_cache(cache)
    assert is_sample_cache(cache) and len(packed) == len(original) > 0
    assert packed.tasks == original.tasks and packed.instructions == original.instructions
    step = (np.asarray(original.bounds["stack_cube"][3:]) - original.bounds["stack_cube"][:3]) / LEVELS
    for a, b in zip(original.xyz, packed.xyz):
        assert a.shape == b.shape and np.all(np.abs(a - b) <= step / 2 + 1e-6)
    assert all(np.array_equal(a, b) for a, b in zip(original.rgb, packed.rgb))
    for name in ("proprio", "target_position", "target_quaternion"):
        assert np.allclose(np.stack(getattr(original, name)), np.stack(getattr(packed, name)))
    for name in ("target_gripper_open", "target_ignore_collisions", "task_index", "instruction_index", "episode_index",
                 "keyframe_start"):
        assert getattr(original, name) == getattr(packed, name)
    tokens = get_config("small").lang_tokens
    expected = InstructionCache(tokens)(packed.instructions)
    assert torch.allclose(torch.stack([embeddings[t][:tokens] for t in packed.instructions]), expected, atol=1e-6)


def test_selection_by_episode_count_and_keyframe_starts(tiny_dataset):
    samples = load_samples(episode_paths([str(tiny_dataset)]), progress=False)
    first = select_samples(samples, episodes_per_task=1)
    assert first and {samples.episode_index[i] for i in first} == {0}
    starts = select_samples(samples, keyframe_starts_only=True)
    assert 0 < len(starts) < len(samples) and all(samples.keyframe_start[i] for i in starts)
    assert len(load_samples(episode_paths([str(tiny_dataset)]), progress=False, keyframe_starts_only=True)) == len(starts)
    with pytest.raises(UserError, match="stack_cube have fewer episodes"):
        select_samples(samples, episodes_per_task=3)


def test_training_from_the_cache_needs_no_mcap_libraries(cache, tmp_path):
    """As on a GPU machine without the recording stack: the episode-format libraries cannot be imported."""
    blocked = ["mcap", "mcap_protobuf", "foxglove_schemas_protobuf", "jsonschema", "zstandard", "open3d", "sapien",
               "mani_skill", "mplib"]
    code = (f"import sys\nfor m in {blocked!r}: sys.modules[m] = None\n"
            "from rvt2cli.cli import main\nsys.exit(main(sys.argv[1:]))")
    args = ["train", "--data", str(cache), "--out", str(tmp_path / "run"), "--config", "small", "--steps", "3",
            "--batch-size", "4", "--max-points", str(TINY_TRAIN["max_points"]), "--val-episodes", "0",
            "--episodes-per-task", "1", "--keyframe-starts-only", "--no-progress"]
    p = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    assert "trained 3 steps" in p.stdout and "from 1 episodes" in p.stdout
    assert (tmp_path / "run" / "last").is_file()


def test_bad_cache_input_is_one_line(cache, tiny_dataset, tmp_path, cli):
    r = cli("pack-samples", tiny_dataset, "--out", tmp_path / "samples.npz")
    assert_one_line_error(r, "samples.npz", ".safetensors")
    r = cli("train", "--data", cache, tiny_dataset, "--out", tmp_path / "run", "--config", "small")
    assert_one_line_error(r, "one sample cache", "not both")
    assert not (tmp_path / "samples.npz").exists()


def test_reading_episodes_in_worker_processes_gives_the_same_samples(tiny_dataset, monkeypatch, tmp_path):
    """load_samples and extract_files with 2 worker processes (real spawned processes; the files-per-worker
    floor lowered so that two files get two) against one process: the same samples, the same files."""
    import shutil

    from rvt2cli import runtime
    from rvt2cli.keyframes.extract import extract_files
    from rvt2cli.train import cloud_spool

    paths = episode_paths([str(tiny_dataset)])
    one = load_samples(paths, progress=False)
    monkeypatch.setattr(runtime, "FILES_PER_WORKER", 1)
    monkeypatch.setattr(cloud_spool, "SHM", tmp_path / "shm")   # the clouds in flight: where the test can look
    (tmp_path / "shm").mkdir()
    for handover in ("files", "pipe"):   # the workers' clouds through files read in threads, or the result pipe
        two = load_samples(paths, progress=False, workers=2, handover=handover)
        assert (one.tasks, one.instructions, one.episodes, one.bounds, one.rigs) == \
            (two.tasks, two.instructions, two.episodes, two.bounds, two.rigs)
        for name in ("task_index", "instruction_index", "episode_index", "keyframe_start", "keyframe_index",
                     "final_keyframe", "target_gripper_open", "target_ignore_collisions"):
            assert getattr(one, name) == getattr(two, name), name
        for name in ("xyz", "rgb", "proprio", "target_position", "target_quaternion"):
            assert all(np.array_equal(a, b) for a, b in zip(getattr(one, name), getattr(two, name), strict=True)), name
        assert all(a.dtype == b.dtype and a.shape == b.shape for a, b in zip(one.xyz + one.rgb, two.xyz + two.rgb))
    assert list((tmp_path / "shm").iterdir()) == []   # the private folder and its files are gone
    assert cloud_spool.spool_clouds(one.xyz, one.rgb, str(tmp_path / "missing")) is None   # the pipe takes over

    copies = {}
    for workers in (1, 2):
        folder = tmp_path / f"workers{workers}"
        shutil.copytree(tiny_dataset, folder)
        copied = episode_paths([str(folder)])
        results = list(extract_files(copied, workers=workers))
        assert [path for path, _ in results] == copied
        assert all(not isinstance(annotation, UserError) for _, annotation in results)
        copies[workers] = [path.read_bytes() for path in copied]
    assert copies[1] == copies[2]
