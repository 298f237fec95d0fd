"""RGB-D images -> the world-frame cloud a policy sees (`rvt2cli.data.fusion`), on recorded episodes."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rvt2cli.data.episode import Cloud
from rvt2cli.data.fusion import camera_points, crop, fuse
from rvt2cli.data.paths import episode_paths
from rvt2cli.data.reader import read_episode

pytestmark = pytest.mark.sim


def pinhole(cam) -> Cloud:
    """The back-projection as written in a textbook: each pixel (row, col) with a depth return, in row-major order,
    at its centre, through the intrinsics, then rotated and moved into the world (float64, then float32)."""
    rows, cols = np.nonzero(cam.depth > 0)
    z = cam.depth[rows, cols].astype(np.float64)
    K = cam.intrinsic
    x = (cols + 0.5 - K[0, 2]) / K[0, 0] * z
    y = (rows + 0.5 - K[1, 2]) / K[1, 1] * z
    world = np.stack([x, y, z], axis=1) @ Rotation.from_quat(cam.cam2world[3:]).as_matrix().T + cam.cam2world[:3]
    return Cloud(xyz=world.astype(np.float32), rgb=cam.rgb[rows, cols])


def inside(cloud: Cloud, bounds) -> Cloud:
    lo, hi = np.asarray(bounds[:3], np.float32), np.asarray(bounds[3:], np.float32)
    keep = np.all((cloud.xyz >= lo) & (cloud.xyz <= hi), axis=1)
    return Cloud(xyz=cloud.xyz[keep], rgb=cloud.rgb[keep])


def test_fusion_is_the_pinhole_back_projection_of_every_pixel_bit_for_bit(tiny_dataset):
    """Every observed frame of two recorded demos: each camera's points, and the cropped, fused cloud training
    reads (`Episode.cloud`), are the textbook formula's to the bit, in its order; the crop removes some points."""
    frames = cropped = 0
    for path in episode_paths([str(tiny_dataset)]):
        episode = read_episode(path)
        bounds = episode.meta.scene_bounds
        for frame in episode.obs_frames:
            cameras = episode.cameras(frame)
            want = []
            for cam in cameras.values():
                ours, theirs = camera_points(cam), pinhole(cam)
                assert np.array_equal(ours.xyz.view(np.uint32), theirs.xyz.view(np.uint32))
                assert np.array_equal(ours.rgb, theirs.rgb)
                kept = crop(ours, bounds)
                want.append(inside(theirs, bounds))
                assert np.array_equal(kept.xyz, want[-1].xyz)
                cropped += len(ours) - len(kept)
            fused = episode.cloud(frame)
            assert np.array_equal(fused.xyz.view(np.uint32), np.concatenate([w.xyz for w in want]).view(np.uint32))
            assert np.array_equal(fused.rgb, np.concatenate([w.rgb for w in want]))
            assert np.array_equal(fuse(cameras, bounds).xyz, fused.xyz)
            frames += 1
    assert frames >= 6 and cropped > 0
