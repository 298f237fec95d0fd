"""The RVT-2 network's parts, one property each (small config, CPU)."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from rvt2cli.model.action_head import ActionHead
from rvt2cli.model.config import RVT, RVT2, SMALL
from rvt2cli.model.heatmap import ConvexUpsampleHeatmap, TransposedConvHeatmap
from rvt2cli.model.locate import gaussian_targets, heatmaps_to_point, window_voxels
from rvt2cli.model.loss import policy_loss
from rvt2cli.model.mvt import MultiViewTransformer
from rvt2cli.model.policy import Observation, RVT2Policy, points_in_box
from rvt2cli.model.rotation import (angle_between, bins_to_quaternion, decode_euler, decode_window, euler_to_quaternion,
                                    quaternion_to_bins, soft_bin_targets)
from rvt2cli.render.cameras import cube_rig, zoom_rig
from rvt2cli.render.channels import NUM_CHANNELS
from rvt2cli.train.lamb import Lamb


def observation(cfg, batch=2, points=2000, seed=0):
    g = torch.Generator().manual_seed(seed)
    return Observation(points=torch.rand(batch, points, 3, generator=g) * 1.8 - 0.9,
                       rgb=torch.rand(batch, points, 3, generator=g),
                       num_points=torch.tensor([points, points // 2] + [points] * (batch - 2))[:batch],
                       proprio=torch.randn(batch, cfg.proprio_dim, generator=g),
                       lang=torch.randn(batch, cfg.lang_tokens, 384, generator=g))


def test_multi_view_transformer_shapes():
    cfg = SMALL
    mvt = MultiViewTransformer(cfg)
    t = cfg.tokens_per_side
    out = mvt(torch.randn(2, 3, NUM_CHANNELS, 64, 64), torch.randn(2, 4), torch.randn(2, cfg.lang_tokens, 384))
    assert out.shape == (2, 3, cfg.width, t, t)


def test_within_view_layers_do_not_mix_views():
    cfg = SMALL  # one within-view layer, then one joint layer
    mvt = MultiViewTransformer(cfg).eval()
    images = torch.randn(1, 3, NUM_CHANNELS, 64, 64)
    proprio, lang = torch.randn(1, 4), torch.randn(1, cfg.lang_tokens, 384)
    x0 = mvt.to_width(torch.cat([mvt.patchify(images[0]).flatten(2).transpose(1, 2),
                                 mvt.proprio(proprio)[:, None].expand(3, 64, -1)], -1) + mvt.position)
    after_first = mvt.blocks[0](x0)
    changed = images.clone()
    changed[0, 2] += 1.0  # only the third view changes
    x1 = mvt.to_width(torch.cat([mvt.patchify(changed[0]).flatten(2).transpose(1, 2),
                                 mvt.proprio(proprio)[:, None].expand(3, 64, -1)], -1) + mvt.position)
    after_first_changed = mvt.blocks[0](x1)
    assert torch.allclose(after_first[:2], after_first_changed[:2], atol=1e-6)
    assert not torch.allclose(after_first[2], after_first_changed[2])
    # the joint layers do mix them
    full, full_changed = mvt(images, proprio, lang), mvt(changed, proprio, lang)
    assert not torch.allclose(full[0, 0], full_changed[0, 0])


@pytest.mark.parametrize("head", [ConvexUpsampleHeatmap, TransposedConvHeatmap])
def test_heatmap_heads_reach_full_resolution(head):
    h = head(width=32, patch=8, hidden=16)
    assert h(torch.randn(5, 32, 8, 8)).shape == (5, 64, 64)


def test_convex_upsampling_is_a_convex_combination_of_neighbour_logits():
    torch.manual_seed(0)
    head = ConvexUpsampleHeatmap(width=16, patch=4, hidden=8)
    features = torch.randn(2, 16, 6, 6)
    weights = head.convex_weights(features)
    assert weights.shape == (2, 9, 4, 4, 6, 6)
    assert torch.all(weights >= 0) and torch.allclose(weights.sum(1), torch.ones(2, 4, 4, 6, 6))
    fine = head(features)
    coarse = head.coarse(features)[:, 0]                                    # [2, 6, 6]
    padded = torch.nn.functional.pad(coarse, (1, 1, 1, 1))                  # the unfold's zero padding
    neighbourhood = padded.unfold(1, 3, 1).unfold(2, 3, 1)                  # [2, 6, 6, 3, 3]
    lo = neighbourhood.amin(dim=(-2, -1)).repeat_interleave(4, 1).repeat_interleave(4, 2)
    hi = neighbourhood.amax(dim=(-2, -1)).repeat_interleave(4, 1).repeat_interleave(4, 2)
    assert torch.all(fine >= lo - 1e-5) and torch.all(fine <= hi + 1e-5)


@pytest.mark.parametrize("views", [RVT2.views, RVT.views])
@pytest.mark.parametrize("zoomed", [False, True])
def test_heatmaps_to_point_recovers_a_planted_point_exactly(views, zoomed):
    size, batch = 56, 3
    g = torch.Generator().manual_seed(1)
    if zoomed:
        center, half = torch.rand(batch, 3, generator=g) - 0.5, 0.25
        cameras = zoom_rig(center, zoom=4.0, views=views, image_size=size)
    else:
        center, half = torch.zeros(batch, 3), 1.0
        cameras = cube_rig(views, size, batch_size=batch)
    ijk = torch.randint(0, size, (batch, 3), generator=g)
    planted = center + (-1 + (ijk + 0.5) * 2 / size) * half                # a voxel centre
    heat = gaussian_targets(planted, cameras, size, sigma=1.5)
    found = heatmaps_to_point(heat, views, center, half, chunk=5)
    assert torch.allclose(found, planted, atol=1e-6)


def test_heatmaps_to_point_looks_only_within_its_window():
    """A sharp peak on the box's face (where stage 2's heatmaps of a 10-demo model put a push's start,
    10 cm below the table) loses to a weaker one near the centre once the window leaves the face out."""
    size, views = 56, RVT2.views
    center = torch.tensor([[0.1, -0.2, 0.3]])
    cameras = zoom_rig(center, zoom=4.0, views=views, image_size=size)
    voxel = lambda ijk: center + (-1 + (torch.tensor([ijk]) + 0.5) * 2 / size) * 0.25  # noqa: E731
    face, near = voxel([33, 25, 0]), voxel([33, 25, 30])  # one column of the scene: only z differs
    heat = 0.7 * gaussian_targets(face, cameras, size, sigma=1.0) + 0.3 * gaussian_targets(near, cameras, size, sigma=1.5)
    assert torch.allclose(heatmaps_to_point(heat, views, center, 0.25), face, atol=1e-6)
    assert torch.allclose(heatmaps_to_point(heat, views, center, 0.25, chunk=3, window=0.5), near, atol=1e-6)


def test_window_voxels_are_centred_and_never_empty():
    assert window_voxels(224, 1.0) == (0, 224)
    assert window_voxels(224, 0.5) == (56, 168)   # voxel centres within +-0.496 of the box's half extent
    assert window_voxels(64, 0.01) == (31, 33)
    with pytest.raises(ValueError, match="window"):
        window_voxels(224, 0.0)


def test_stage_2_finds_its_point_within_the_window_of_stage_1s():
    torch.manual_seed(0)
    cfg = replace(SMALL, stage2_window=0.25)
    pred = RVT2Policy(cfg).predict(observation(cfg, batch=2))
    reach = cfg.search_window() / cfg.zoom  # cube units
    assert ((pred.position - pred.stage1_position).abs() <= reach + 1e-6).all()
    with pytest.raises(ValueError, match="stage2_window"):
        replace(SMALL, stage2_window=1.5).validate()


def test_stage_2s_window_is_where_training_puts_its_targets():
    # U(-5, 5) cm around the target (stage2_noise) in a box of +-10 cm (zoom 4 of the 0.8 m scene cube)
    assert RVT2.search_window() == pytest.approx(0.5)
    assert replace(RVT2, zoom=2.0).search_window() == pytest.approx(0.25)   # `rvt2 train --zoom 2`: +-20 cm
    assert replace(RVT2, stage2_window=1.0).search_window() == 1.0         # the paper: the whole box


def test_gaussian_targets_peak_at_the_projection():
    cameras = cube_rig(RVT2.views, 32)
    heat = gaussian_targets(torch.tensor([[0.0, 0.0, 0.0]]), cameras, 32, sigma=1.5)
    assert torch.allclose(heat.sum(dim=(-2, -1)), torch.ones(1, 3))
    for v in range(3):  # the centre of the cube is at the image centre, between pixels 15 and 16
        peak = divmod(int(heat[0, v].argmax()), 32)
        assert peak[0] in (15, 16) and peak[1] in (15, 16)


def test_rotation_bins_round_trip():
    rng = np.random.default_rng(0)
    bins = rng.integers(0, 72, size=(500, 3))
    bins[:, 1] = rng.integers(19, 53, size=500)  # Euler y within (-90, 90): the canonical range
    assert np.array_equal(quaternion_to_bins(bins_to_quaternion(bins)), bins)
    quats = rng.normal(size=(500, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    error = angle_between(bins_to_quaternion(quaternion_to_bins(quats)), quats)
    assert error.max() <= 7.5 + 1e-6  # half a bin on each axis at most, composed (triangle inequality)


def test_action_head_autoregression_uses_earlier_bins():
    cfg = SMALL
    torch.manual_seed(0)
    head = ActionHead(cfg)
    tokens = torch.randn(2, 3, cfg.width, 8, 8)
    feats = head.features(tokens, torch.full((2, 3, 2), 32.0), None)
    assert feats.shape == (2, 3 * 2 * cfg.rotation_feature_dim)
    a = head(feats, torch.tensor([[0, 10, 20], [0, 10, 20]]))
    b = head(feats, torch.tensor([[5, 10, 20], [5, 10, 20]]))
    assert torch.equal(a["rot_x"], b["rot_x"]) and not torch.allclose(a["rot_y"], b["rot_y"])
    assert {k: v.shape for k, v in a.items()} == {"rot_x": (2, 72), "rot_y": (2, 72), "rot_z": (2, 72),
                                                   "gripper": (2, 2), "collision": (2, 2)}


COARSE = replace(SMALL, coarse_action_features=True)


@pytest.mark.parametrize("cfg", [SMALL, COARSE, RVT2], ids=["small", "small-coarse-action-features", "rvt2"])
def test_policy_forward_backward_and_predict_shapes(cfg):
    torch.manual_seed(0)
    policy = RVT2Policy(cfg, render_backend="torch" if cfg is RVT2 else "warp")
    obs = observation(cfg, batch=1 if cfg is RVT2 else 2)
    b = obs.points.shape[0]
    target = torch.zeros(b, 3)
    bins = torch.zeros(b, 3, dtype=torch.long)
    out = policy(obs, target, bins, target + 0.01)
    assert len(out["stages"]) == 2 and out["stages"][0].logits.shape == (b, 3, cfg.image_size, cfg.image_size)
    losses = policy_loss(out, target, bins, bins[:, 0], bins[:, 0], cfg.image_size, cfg.heatmap_sigma)
    losses["total"].backward()
    assert all(p.grad is not None for p in policy.parameters())
    if cfg is not RVT2:
        pred = policy.predict(obs)
        assert pred.position.shape == (b, 3) and pred.rot_bins.shape == (b, 3) and pred.gripper_open.dtype == torch.bool
        # the decoded rotation lies within its best bins (half a bin per axis at most)
        centres = bins_to_quaternion(pred.rot_bins.numpy(), cfg.rotation_bins)
        assert np.all(angle_between(pred.quaternion.numpy(), centres) <= 2.5 * 3 ** 0.5 + 1e-3)


@pytest.mark.parametrize("coarse", [False, True])
def test_coarse_action_features_let_the_heads_see_what_stage_2_does_not(coarse):
    """A change to the scene outside stage 2's box (+-1/zoom around the point) reaches the rotation heads
    only through stage 1, so only with `coarse_action_features`."""
    torch.manual_seed(0)
    cfg = replace(SMALL, coarse_action_features=coarse)
    policy = RVT2Policy(cfg).eval()
    obs = observation(cfg, batch=1)
    point = torch.tensor([[0.5, 0.5, 0.5]])
    far = (obs.points - point).abs().amax(-1) > 1.5 / cfg.zoom            # outside stage 2's box, with a margin
    moved = Observation(points=torch.where(far[..., None], obs.points.flip(-1), obs.points), rgb=obs.rgb,
                        num_points=obs.num_points, proprio=obs.proprio, lang=obs.lang)

    def rotation_logits(o):
        with torch.no_grad():
            outputs = [policy.run_stage(0, o), policy.run_stage(1, o, point)]
            return policy.action(policy.action_features(outputs, point))["rot_z"]

    assert far.sum() > 1000 and not torch.equal(moved.points, obs.points)
    changed = not torch.allclose(rotation_logits(obs), rotation_logits(moved))
    assert changed == coarse


def test_stage_1s_point_is_kept_where_stage_2s_box_holds_too_few_points():
    """`stage2_min_points`: an observation whose cloud leaves stage 2's box (+-1/zoom around stage 1's point)
    nearly empty keeps stage 1's point; one with enough points there takes stage 2's."""
    torch.manual_seed(0)
    obs = observation(SMALL, batch=2)
    policy = RVT2Policy(replace(SMALL, stage2_min_points=0)).eval()   # stage 2's point everywhere
    first = policy.predict(obs)
    counts = points_in_box(obs, first.stage1_position, 1.0 / SMALL.zoom)
    inside = ((obs.points - first.stage1_position[:, None]).abs() <= 1.0 / SMALL.zoom).all(-1)
    assert counts[1] == inside[1, : obs.num_points[1]].sum() < inside[1].sum()  # padding points do not count
    assert not torch.allclose(first.position, first.stage1_position)          # stage 2 moved the point
    between = int(counts.min()) + 1   # more than the emptier box holds, no more than the fuller one
    kept = replace(SMALL, stage2_min_points=between)
    policy.cfg = kept
    pred = policy.predict(obs)
    blind = counts < between
    assert blind.any() and not blind.all()
    assert torch.equal(pred.position[blind], first.stage1_position[blind])
    assert torch.equal(pred.position[~blind], first.position[~blind])


def test_loss_decreases_on_a_fixed_batch():
    torch.manual_seed(0)
    cfg = SMALL
    policy = RVT2Policy(cfg)
    obs = observation(cfg, batch=2)
    target = torch.tensor([[0.3, -0.2, 0.1], [-0.4, 0.5, -0.3]])
    bins = torch.tensor([[10, 40, 70], [3, 30, 60]])
    grip, coll = torch.tensor([1, 0]), torch.tensor([0, 1])
    optimizer = Lamb(policy.parameters(), lr=1e-2)
    losses = []
    for _ in range(30):
        out = policy(obs, target, bins, target)
        loss = policy_loss(out, target, bins, grip, coll, cfg.image_size, cfg.heatmap_sigma)["total"]
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0], losses


def test_lamb_step_matches_the_formula():
    w0, g = torch.tensor([1.0, -2.0, 3.0]), torch.tensor([0.5, 0.1, -0.2])
    p = torch.nn.Parameter(w0.clone())
    p.grad = g.clone()
    Lamb([p], lr=0.1, betas=(0.9, 0.999), eps=1e-6, weight_decay=0.01).step()
    m_hat, v_hat = (0.1 * g) / 0.1, (0.001 * g * g) / 0.001
    update = m_hat / (v_hat.sqrt() + 1e-6) + 0.01 * w0
    expected = w0 - 0.1 * (w0.norm() / update.norm()) * update
    assert torch.allclose(p.detach(), expected, atol=1e-6)


@pytest.mark.slow
def test_compiled_network_matches_eager():
    torch.manual_seed(0)
    eager = RVT2Policy(SMALL)
    compiled = RVT2Policy(SMALL)
    compiled.load_state_dict(eager.state_dict())
    compiled.compile_network()
    obs = observation(SMALL, batch=2)
    target, bins = torch.tensor([[0.1, 0.2, 0.3], [-0.3, 0.0, 0.2]]), torch.tensor([[1, 2, 3], [4, 5, 6]])
    want, got = eager(obs, target, bins, target), compiled(obs, target, bins, target)
    for a, b in zip(want["stages"], got["stages"]):
        assert torch.allclose(a.logits, b.logits, rtol=1e-4, atol=1e-4)
    for key in want["action"]:
        assert torch.allclose(want["action"][key], got["action"][key], rtol=1e-4, atol=1e-4)
    assert torch.equal(eager.predict(obs).rot_bins, compiled.predict(obs).rot_bins)


def test_soft_rotation_targets_centre_on_the_true_angle_and_decode_back():
    """Gaussian targets around the true angle (not its bin's centre) wrap around +-180 degrees, and
    scores shaped like them decode back to the angle within a tenth of a 1-degree bin; one-bin
    decoding (window 1) would be off by up to half a bin."""
    bins, sigma = 360, 2.0
    window = decode_window(bins, sigma)
    assert window == 4 and decode_window(72, 0.0) == 1
    for true in (10.3, -179.8, 179.6, 0.05, 44.49):
        targets = soft_bin_targets(torch.tensor([[true] * 3]), bins, sigma)
        assert torch.allclose(targets.sum(-1), torch.ones(1, 3))
        nearest = int(np.floor((true + 180.0) % 360.0))   # the bin the angle lies in
        assert targets[0, 0].argmax().item() == nearest
        decoded = torch.rad2deg(decode_euler([torch.log(targets[:, i]) for i in range(3)], window=window))[0].numpy()
        gap = (decoded - true + 180.0) % 360.0 - 180.0
        assert np.all(np.abs(gap) < 0.1)
    edge = soft_bin_targets(torch.tensor([[-179.8, 0.0, 0.0]]), bins, sigma)[0, 0]
    assert edge[359] > 0.1 and edge[0] > edge[359]      # -179.8 is 0.3 degrees from bin 0's centre, 0.7 from 359's


def test_soft_rotation_targets_train_the_heads_towards_the_angle():
    """policy_loss with rotation_sigma_deg: the rotation terms are cross-entropies against the soft
    targets (equal to a hand-computed one), and a few steps on one sample move its decoded angles to
    within half a degree of the target's, between bin centres."""
    torch.manual_seed(0)
    cfg = replace(SMALL, rotation_bins=360, rotation_sigma_deg=2.0)
    policy = RVT2Policy(cfg)
    obs = observation(cfg, batch=1)
    target = torch.zeros(1, 3)
    euler = torch.tensor([[30.4, -12.7, 101.2]])
    bins = torch.from_numpy(np.floor((euler.numpy() + 180.0) % 360.0).astype(np.int64))
    out = policy(obs, target, bins, target)
    losses = policy_loss(out, target, bins, bins[:, 0] % 2, bins[:, 0] % 2, cfg.image_size, cfg.heatmap_sigma,
                         euler, cfg.rotation_sigma_deg)
    soft = soft_bin_targets(euler, 360, 2.0)
    expected = -(soft[:, 0] * torch.log_softmax(out["action"]["rot_x"].float(), -1)).sum()
    assert losses["rot_x"].item() == pytest.approx(expected.item(), rel=1e-5)
    optimizer = torch.optim.Adam(policy.action.parameters(), lr=3e-3)
    for _ in range(60):
        out = policy(obs, target, bins, target)
        loss = policy_loss(out, target, bins, bins[:, 0] % 2, bins[:, 0] % 2, cfg.image_size, cfg.heatmap_sigma,
                           euler, cfg.rotation_sigma_deg)
        optimizer.zero_grad()
        (loss["rot_x"] + loss["rot_y"] + loss["rot_z"]).backward()
        optimizer.step()
    with torch.no_grad():
        action = policy(obs, target, bins, target)["action"]
    decoded = decode_euler([action[k] for k in ("rot_x", "rot_y", "rot_z")], window=decode_window(360, 2.0))
    gap = np.degrees(decoded[0].numpy()) - euler[0].numpy()
    assert np.all(np.abs(gap) < 0.5), gap


def test_rotation_decoding_places_the_angle_within_its_bin():
    """A bin scored alone decodes to its centre; a neighbour scored as high moves the angle to their
    shared edge; neighbours wrap around +-180 degrees; the torch quaternion matches scipy's."""
    bins = 72
    def scores(*pairs):
        s = torch.full((1, bins), -30.0)
        for index, value in pairs:
            s[0, index] = value
        return s
    alone, edge, wrapped = scores((10, 5.0)), scores((10, 5.0), (11, 5.0)), scores((0, 5.0), (71, 5.0))
    angles = torch.rad2deg(decode_euler([alone, edge, wrapped]))[0].numpy()
    assert angles[0] == pytest.approx(-180 + 10.5 * 5, abs=1e-3)          # bin 10's centre
    assert angles[1] == pytest.approx(-180 + 11 * 5, abs=1e-3)            # the edge between bins 10 and 11
    assert angles[2] == pytest.approx(-180, abs=1e-3)                     # bins 0 and 71 share -180 = +180
    rng = np.random.default_rng(0)
    euler = rng.uniform(-170, 170, size=(16, 3))
    from scipy.spatial.transform import Rotation
    expected = Rotation.from_euler("xyz", euler, degrees=True).as_quat()
    ours = euler_to_quaternion(torch.deg2rad(torch.tensor(euler))).numpy()
    assert np.all(angle_between(ours, expected) < 1e-3)


def test_an_aim_puts_the_predicted_tcp_behind_the_aimed_point():
    """With an aim (rvt2 train --aim-held) the heatmaps' point is where the aim goes; the predicted TCP
    is that point less the aim turned by the predicted rotation, and nothing else changes."""
    from scipy.spatial.transform import Rotation

    from rvt2cli.model.observation import aim_vector
    from rvt2cli.model.rotation import rotate_vectors

    torch.manual_seed(0)
    policy = RVT2Policy(SMALL).eval()
    obs = observation(SMALL, batch=2)
    # one observation holds (gripper closed: aimed), the other does not (the TCP itself)
    aim = aim_vector(torch.tensor([0.15, 0.0, 0.0]), torch.tensor([False, True]), torch.tensor([0.4, 0.4]))
    assert torch.allclose(aim, torch.tensor([[0.375, 0.0, 0.0], [0.0, 0.0, 0.0]]))
    plain = policy.predict(obs)
    aimed = policy.predict(replace(obs, aim=aim))
    behind = rotate_vectors(aimed.quaternion, aim)
    assert torch.allclose(aimed.position, plain.position - behind, atol=1e-6)
    assert torch.allclose(aimed.stage1_position, plain.stage1_position - behind, atol=1e-6)
    assert torch.equal(aimed.rot_bins, plain.rot_bins) and torch.equal(aimed.gripper_open, plain.gripper_open)
    assert torch.equal(aimed.position[1], plain.position[1])
    expected = Rotation.from_quat(aimed.quaternion.double().numpy()).apply(aim.double().numpy())
    assert np.allclose(behind.numpy(), expected, atol=1e-6)


def test_an_instruction_cache_pickles_to_the_size_of_its_embeddings():
    """A several-GPU `rvt2 train` pickles the instruction cache to send it to the other processes. Each
    embedding must own its storage: a view into the batch they were embedded in pickles the whole batch,
    once per instruction (rvt2-18's 578 instructions came to 36.8 GiB and ran a GPU out of memory)."""
    import pickle

    from rvt2cli.model.language import InstructionCache
    from rvt2cli.tasks import get_task

    texts = get_task("close_jar").all_paraphrases()
    assert len(texts) >= 20
    tokens = SMALL.lang_tokens
    computed = InstructionCache(tokens)
    lang = computed(texts)
    longer = torch.randn(len(texts), 2 * tokens, 384)   # a sample cache stores a longer prefix than a config uses
    known = InstructionCache(tokens, {text: longer[i, :tokens] for i, text in enumerate(texts)})
    for cache in (computed, known):
        embeddings = cache.as_dict()
        payload = sum(e.nelement() * e.element_size() for e in embeddings.values())
        assert len(pickle.dumps(cache)) < 1.1 * payload + 2**16
        assert pickle.loads(pickle.dumps(cache)).as_dict().keys() == embeddings.keys()
    assert torch.equal(known(texts), longer[:, :tokens]) and torch.equal(computed(texts), lang)
