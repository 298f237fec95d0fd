"""8-bit LAMB (`rvt2cli.train.lamb8bit`): the quantisation maps, block-wise quantisation, one step
against 32-bit `Lamb`, training curves, skipped steps, exact resume, and the state's size."""

import copy
import math

import pytest
import torch

from rvt2cli.train.lamb8bit import (BLOCK_SIZE, BlockQuantiser, Lamb8bit, NearestCode, optimizer_state_bytes,
                                    signed_dynamic_map, unsigned_dynamic_map)
from rvt2cli.train.lamb import Lamb


@pytest.fixture(autouse=True)
def one_thread():
    """Small tensors: a second OpenMP thread only contends for the shared cores (10x slower under load)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def midpoints(values: torch.Tensor) -> torch.Tensor:
    return (values[:-1] + values[1:]) / 2


# --- the maps ------------------------------------------------------------------------------------

def test_signed_map_covers_minus_one_to_one_symmetrically():
    values = signed_dynamic_map()
    assert values.shape == (256,) and values.dtype == torch.float32
    assert values[0] == -1.0 and values[-1] == 1.0
    assert bool((values.diff() >= 0).all())
    assert int((values.diff() == 0).sum()) == 1 and values[127] == values[128] == 0.0  # +0 and -0
    assert torch.equal(values, -values.flip(0))
    assert float(values[129]) == pytest.approx(1e-6)  # the smallest non-zero magnitude, 10^-6


def test_unsigned_map_covers_zero_to_one_with_finer_steps():
    values = unsigned_dynamic_map()
    assert values.shape == (256,) and values[0] == 0.0 and values[-1] == 1.0
    assert bool((values.diff() > 0).all())
    assert float(values[1]) == pytest.approx(1e-7)
    # the top level: 128 evenly spaced values in (0.1, 1], twice as many as the signed map's 64
    top = values[128:].double()
    assert torch.allclose(top.diff(), torch.full((127,), 0.9 / 128, dtype=torch.float64), atol=1e-7)
    assert float(values[127]) == pytest.approx(0.1)
    assert int((signed_dynamic_map() > 0.1).sum()) == 64


def test_each_decade_has_its_share_of_codes():
    """Dynamic: codes in every decade down to 10^-7, halving per decade, where a linear grid of 256 has
    none below 1/255."""
    values = unsigned_dynamic_map()
    per_decade = [int(((values > 10.0 ** -(e + 1)) & (values <= 10.0 ** -e)).sum()) for e in range(7)]
    assert per_decade == [128, 64, 32, 16, 8, 4, 2]


# --- rounding and block-wise quantisation --------------------------------------------------------

@pytest.mark.parametrize("signed", [True, False])
def test_nearest_code_is_the_binary_search_result(signed):
    values = signed_dynamic_map() if signed else unsigned_dynamic_map()
    mids = midpoints(values)
    g = torch.Generator().manual_seed(0)
    n = 200_000
    x = torch.cat([
        torch.rand(n, generator=g) * 2 - 1,
        (torch.rand(n, generator=g) * 2 - 1) * torch.exp(-25 * torch.rand(n, generator=g)),  # down to 1e-11
        values, mids, mids.nextafter(torch.tensor(2.0)), mids.nextafter(torch.tensor(-2.0)),
        torch.tensor([0.0, -0.0, 1e-30, -1e-30, 1e-45, 1.0, -1.0]),
    ])
    if not signed:
        x = x.abs()
    codes = NearestCode(values)(x)
    assert codes.dtype == torch.uint8
    assert torch.equal(codes.long(), torch.bucketize(x, mids))


@pytest.mark.parametrize("signed", [True, False])
def test_quantisation_error_is_half_a_code_gap_of_the_block_absmax(signed):
    quantiser = BlockQuantiser(signed)
    g = torch.Generator().manual_seed(1)
    scales = torch.exp(torch.randn(500, 1, generator=g) * 4)  # blocks of very different sizes
    x = torch.randn(500, 256, generator=g) * scales
    if not signed:
        x = x * x
    without_outlier, _ = quantiser.quantise(x)
    x[7, 3] = 1e4 * x[7].abs().max()  # an outlier costs resolution in its own block only
    codes, absmax = quantiser.quantise(x)
    assert torch.equal(codes[:7], without_outlier[:7]) and torch.equal(codes[8:], without_outlier[8:])
    assert not torch.equal(codes[7], without_outlier[7])
    assert codes.dtype == torch.uint8 and codes.shape == x.shape and absmax.shape == (500,)
    assert torch.equal(absmax, x.abs().amax(dim=1))
    restored = quantiser.dequantise(codes, absmax)
    # each element lands on the map value nearest to x / absmax: at most half the gap around it
    values = quantiser.values
    normalised = x / absmax[:, None]
    above = torch.searchsorted(values, normalised.contiguous()).clamp(1, 255)
    gap = values[above] - values[above - 1]
    assert bool(((restored - x).abs() <= (0.5 * gap + 1e-6) * absmax[:, None]).all())
    # which is 0.70 % (signed) or 0.35 % (unsigned) of the block's absmax at most, and exact at the absmax
    worst = float(((restored - x).abs() / absmax[:, None]).max())
    assert worst <= (0.9 / 64 if signed else 0.9 / 128) / 2 + 1e-6
    top = x.abs().argmax(dim=1)
    assert torch.equal(restored.gather(1, top[:, None]), x.gather(1, top[:, None]))
    # the top decade, [0.1, 1] of the absmax, has the finest codes: a few percent relative error at most
    # (half a code gap, 0.9/64 or 0.9/128 of the absmax, over 0.1 of it); smaller values get fewer codes
    top_decade = normalised.abs() >= 0.1
    relative = (restored - x).abs() / x.abs()
    assert float(relative[top_decade].max()) <= (4.5 / 64 if signed else 4.5 / 128) + 1e-6
    assert float(relative[normalised.abs() >= 1e-3].median()) < 0.02


def test_an_all_zero_block_stays_zero():
    quantiser = BlockQuantiser(True)
    codes, absmax = quantiser.quantise(torch.zeros(3, 256))
    assert torch.equal(absmax, torch.zeros(3))
    assert torch.equal(quantiser.dequantise(codes, absmax), torch.zeros(3, 256))


# --- the optimiser -------------------------------------------------------------------------------

SHAPES = [(64, 96), (300,), (48, 100), (7,), (5000,), (16, 16)]  # three above min_8bit_size=4096


def make_params(shapes=SHAPES, seed=0, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    return [torch.nn.Parameter(torch.randn(s, generator=g).to(dtype)) for s in shapes]


def grads_for(params, seed):
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(p.shape, generator=g).to(p.dtype) for p in params]


def run(optimizer, params, steps, first_seed=100, skip_at=()):
    for i in range(steps):
        for p, grad in zip(params, grads_for(params, first_seed + i)):
            p.grad = grad
        optimizer.step(skip=torch.tensor(i in skip_at))


def test_first_step_equals_lamb():
    """From zero moments, the first step's moments are exact: the update is Lamb's up to rounding."""
    a, b = make_params(), make_params()
    run(Lamb(a, lr=1e-2, weight_decay=0.01), a, 1)
    run(Lamb8bit(b, lr=1e-2, weight_decay=0.01), b, 1)
    for x, y, w in zip(a, b, make_params()):
        assert not torch.equal(x, w)
        assert torch.allclose(x, y, rtol=0, atol=1e-6)


def test_one_step_is_the_lamb_formula_on_the_stored_moments():
    """After a few steps, give 32-bit Lamb the 8-bit optimiser's (dequantised) moments: one more step
    moves the weights the same way, and Lamb's new moments are the 8-bit ones up to quantisation."""
    params = make_params()
    eight = Lamb8bit(params, lr=1e-2, weight_decay=0.01)
    run(eight, params, 5)
    twin = [torch.nn.Parameter(p.detach().clone()) for p in params]
    lamb = Lamb(twin, lr=1e-2, weight_decay=0.01)
    for p, q in zip(params, twin):
        m, v = eight.moments(p)
        lamb.state[q] = {"step": torch.tensor(5.0), "exp_avg": m.clone(), "exp_avg_sq": v.clone()}
    before = [p.detach().clone() for p in params]
    grads = grads_for(params, 999)
    for p, q, grad in zip(params, twin, grads):
        p.grad, q.grad = grad.clone(), grad.clone()
    eight.step()
    lamb.step()
    for p, q, w in zip(params, twin, before):
        assert float((p - w).abs().max().detach()) > 1e-4
        assert torch.allclose(p, q, rtol=0, atol=1e-6), float((p - q).abs().max())
    for p, q in zip(params, twin):
        m, v = eight.moments(p)
        m32, v32 = lamb.state[q]["exp_avg"], lamb.state[q]["exp_avg_sq"]
        if p.numel() < 4096:  # float32 moments: exactly Lamb's
            assert torch.equal(m, m32) and torch.equal(v, v32)
        else:  # within 0.7 % (first) and 0.35 % (second moment) of the largest magnitude of their block
            for ours, exact, bound in ((m, m32, 0.9 / 64 / 2), (v, v32, 0.9 / 128 / 2)):
                padding = (0, -exact.numel() % BLOCK_SIZE)
                flat = torch.nn.functional.pad(exact.flatten(), padding).view(-1, BLOCK_SIZE)
                err = torch.nn.functional.pad((ours - exact).flatten(), padding).view(-1, BLOCK_SIZE)
                assert bool((err.abs() <= bound * 1.001 * flat.abs().amax(dim=1, keepdim=True)).all())


def test_trajectories_stay_close_to_lamb():
    """20 steps on the same gradients: the 8-bit weights follow the 32-bit ones to 2 % of the distance
    travelled (the trust ratio makes each step lr * ||w||: the distances are alike)."""
    a, b = make_params(), make_params()
    start = [p.detach().clone() for p in a]
    run(Lamb(a, lr=1e-2, weight_decay=0.01), a, 20)
    run(Lamb8bit(b, lr=1e-2, weight_decay=0.01), b, 20)
    for x, y, w in zip(a, b, start):
        travelled = float((x - w).detach().norm())
        assert travelled > 0.3
        if x.numel() < 4096:  # float32 moments: Lamb's own trajectory
            assert torch.equal(x, y)
        else:
            assert float((x - y).detach().norm()) < 0.04 * travelled


def test_only_small_tensors_is_exactly_lamb():
    shapes = [(40, 50), (300,), (7,), (64, 63)]
    a, b = make_params(shapes), make_params(shapes)
    lamb, eight = Lamb(a, lr=1e-2, weight_decay=0.01), Lamb8bit(b, lr=1e-2, weight_decay=0.01)
    run(lamb, a, 8, skip_at=(3,))
    run(eight, b, 8, skip_at=(3,))
    assert all(torch.equal(x, y) for x, y in zip(a, b))
    assert all(torch.equal(eight.state[y]["exp_avg_sq"], lamb.state[x]["exp_avg_sq"]) for x, y in zip(a, b))


def regression_losses(optimizer_class, steps=150, batch_seed=0) -> list[float]:
    """A 3-layer MLP (two of its weights 8-bit) fitted to a fixed random teacher network, from fixed
    initial weights, on minibatches of 64 drawn in the order `batch_seed` gives."""
    g = torch.Generator().manual_seed(0)
    teacher = [torch.randn(32, 64, generator=g) / 32**0.5, torch.randn(64, 1, generator=g) / 8]
    x = torch.randn(2048, 32, generator=g)
    y = torch.tanh(x @ teacher[0]) @ teacher[1]
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(32, 256), torch.nn.Tanh(), torch.nn.Linear(256, 256), torch.nn.Tanh(),
                                torch.nn.Linear(256, 1))
    optimizer = optimizer_class(model.parameters(), lr=5e-3, weight_decay=1e-4)
    batches = torch.Generator().manual_seed(batch_seed)
    losses = []
    for step in range(steps):
        rows = torch.randint(0, len(x), (64,), generator=batches)
        loss = torch.nn.functional.mse_loss(model(x[rows]), y[rows])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    return losses


def smoothed(values, window=15):
    return [sum(values[max(0, i - window + 1): i + 1]) / len(values[max(0, i - window + 1): i + 1]) for i in range(len(values))]


def largest_relative_difference(a, b):
    return max(abs(x - y) / x for x, y in zip(smoothed(a), smoothed(b)))


def test_regression_loss_curves_agree_within_noise():
    """The 8-bit curve is closer to the 32-bit one than two 32-bit runs on other minibatch orders."""
    lamb, eight, other_order = regression_losses(Lamb), regression_losses(Lamb8bit), regression_losses(Lamb, batch_seed=1)
    assert lamb[0] == eight[0]
    assert smoothed(lamb)[-1] < 0.15 * lamb[0] and smoothed(eight)[-1] < 0.15 * eight[0]  # both learn
    noise = largest_relative_difference(lamb, other_order)  # 0.22 here
    assert largest_relative_difference(lamb, eight) < min(0.02, 0.1 * noise)  # 0.0045 here


def test_skipped_step_changes_nothing():
    params = make_params()
    optimizer = Lamb8bit(params, lr=1e-2, weight_decay=0.01)
    run(optimizer, params, 3)
    weights = [p.detach().clone() for p in params]
    state = {i: {k: v.clone() for k, v in optimizer.state[p].items()} for i, p in enumerate(params)}
    for p in params:
        p.grad = torch.full_like(p, math.nan)
    optimizer.step(skip=torch.tensor(True))
    assert all(torch.equal(p, w) for p, w in zip(params, weights))
    for i, p in enumerate(params):
        for key, value in state[i].items():
            assert torch.equal(optimizer.state[p][key], value), key
    assert float(optimizer.state[params[0]]["step"]) == 3.0


def test_a_tensor_without_gradient_keeps_weights_and_moments():
    params = make_params()
    optimizer = Lamb8bit(params, lr=1e-2)
    run(optimizer, params, 2)
    frozen = params[0]  # 6144 elements: 8-bit moments
    weight, codes = frozen.detach().clone(), optimizer.state[frozen]["exp_avg_codes"].clone()
    others = [p.detach().clone() for p in params[1:]]
    for p, grad in zip(params, grads_for(params, 5)):
        p.grad = None if p is frozen else grad
    optimizer.step()
    assert torch.equal(frozen, weight) and torch.equal(optimizer.state[frozen]["exp_avg_codes"], codes)
    assert all(not torch.equal(p, w) for p, w in zip(params[1:], others))


def test_resume_from_a_file_is_exact(tmp_path):
    straight_params = make_params()
    straight = Lamb8bit(straight_params, lr=1e-2, weight_decay=0.01)
    run(straight, straight_params, 6)

    first_params = make_params()
    first = Lamb8bit(first_params, lr=1e-2, weight_decay=0.01)
    run(first, first_params, 3)
    torch.save({"optimizer": first.state_dict(), "weights": [p.detach() for p in first_params]}, tmp_path / "state.pt")

    saved = torch.load(tmp_path / "state.pt", weights_only=True)
    resumed_params = [torch.nn.Parameter(w.clone()) for w in saved["weights"]]
    resumed = Lamb8bit(resumed_params, lr=0.5, weight_decay=0.0)  # hyperparameters come from the file
    resumed.load_state_dict(saved["optimizer"])
    assert resumed.param_groups[0]["lr"] == 1e-2
    run(resumed, resumed_params, 3, first_seed=103)
    assert all(torch.equal(x, y) for x, y in zip(straight_params, resumed_params))
    for x, y in zip(straight_params, resumed_params):
        for key, value in straight.state[x].items():
            assert torch.equal(resumed.state[y][key], value), key


def test_state_dict_holds_per_parameter_codes_and_scales():
    params = make_params()
    optimizer = Lamb8bit(params, block_size=256)
    run(optimizer, params, 1)
    state = optimizer.state_dict()["state"]
    big = state[0]  # (64, 96): 6144 elements, 24 blocks of 256
    assert big["exp_avg_codes"].dtype == torch.uint8 and big["exp_avg_codes"].shape == (24, 256)
    assert big["exp_avg_absmax"].dtype == torch.float32 and big["exp_avg_absmax"].shape == (24,)
    assert big["exp_avg_sq_codes"].shape == (24, 256) and big["exp_avg_sq_absmax"].shape == (24,)
    assert set(state[1]) == {"step", "exp_avg", "exp_avg_sq"}  # (300,): float32 moments


def test_bfloat16_parameters_keep_float32_scales_through_a_reload():
    params = make_params(dtype=torch.bfloat16)
    optimizer = Lamb8bit(params, lr=1e-2)
    run(optimizer, params, 2)
    scales = optimizer.state[params[0]]["exp_avg_absmax"].clone()
    reloaded = Lamb8bit(params, lr=1e-2)
    reloaded.load_state_dict(optimizer.state_dict())
    run(reloaded, params, 1)
    assert reloaded.state[params[0]]["exp_avg_absmax"].dtype == torch.float32
    assert not torch.equal(reloaded.state[params[0]]["exp_avg_absmax"], scales)  # it stepped from them


def test_state_bytes_are_two_per_parameter_plus_scales():
    shapes = [(64 * 160,), (100, 100), (1000,)]  # 160 blocks of 64; 157 blocks (48 elements padding); small
    params = make_params(shapes)
    eight, lamb = Lamb8bit(params, block_size=64), Lamb([torch.nn.Parameter(p.detach().clone()) for p in params])
    run(eight, params, 1)
    run(lamb, lamb.param_groups[0]["params"], 1)
    codes = 2 * 317 * 64           # two moments, one byte per element of 317 blocks
    scales = 2 * 317 * 4           # two float32 absmax per block
    small = 2 * 1000 * 4 + 4       # float32 moments and step of the small tensor
    assert eight.state_bytes() == optimizer_state_bytes(eight) == codes + scales + 4 + small
    assert optimizer_state_bytes(lamb) == 8 * sum(p.numel() for p in params) + 3 * 4
    # 2 bytes, 0.125 for the scales, 0.005 for the padding of the 10000-element tensor
    assert (codes + scales) / (64 * 160 + 100 * 100) == pytest.approx(2.13, abs=0.001)


def test_a_32_bit_lamb_state_loads_with_its_moments_quantised():
    """Resuming a run of 32-bit `Lamb` (one trained on a CPU, say) with `Lamb8bit`: the step count and
    the moments carry over, the latter within quantisation error."""
    params = make_params()
    lamb = Lamb(params, lr=1e-2, weight_decay=0.01)
    run(lamb, params, 4)
    twin = [torch.nn.Parameter(p.detach().clone()) for p in params]
    eight = Lamb8bit(twin, lr=1e-2, weight_decay=0.01)
    eight.load_state_dict(copy.deepcopy(lamb.state_dict()))
    run(lamb, params, 1, first_seed=104)
    run(eight, twin, 1, first_seed=104)
    for p, q in zip(params, twin):
        assert float(eight.state[q]["step"]) == 5.0
        m, v = eight.moments(q)
        m32, v32 = lamb.state[p]["exp_avg"], lamb.state[p]["exp_avg_sq"]
        if p.numel() < 4096:
            assert torch.equal(m, m32) and torch.equal(v, v32) and torch.equal(p, q)
            continue
        # two roundings (at loading, after the step), each at most half a code gap of the absmax
        assert torch.allclose(m, m32, rtol=0, atol=2 * 0.9 / 64 / 2 * float(m32.abs().max()))
        assert torch.allclose(v, v32, rtol=0, atol=2 * 0.9 / 128 / 2 * float(v32.abs().max()))
        assert 0 < float((p - q).detach().abs().max()) < 1e-3  # of a step of lr * ||w||, 1e-2 of the weights
