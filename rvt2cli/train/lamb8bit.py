"""8-bit LAMB: the LAMB optimiser with its two moments stored in 8 bits, quantised block-wise.

RVT-2 (Goyal et al., 2024) trains with 8-bit LAMB: LAMB (You et al., 2020) whose Adam moments are kept
in 8 bits as in Dettmers et al., "8-bit Optimizers via Block-wise Quantization" (ICLR 2022). The
arithmetic is that of `rvt2cli.train.lamb.Lamb`; only the storage of the moments differs:

    m = beta1 * m + (1 - beta1) * g                         first moment (signed)
    v = beta2 * v + (1 - beta2) * g^2                       second moment (non-negative)
    u = (m / (1 - beta1^t)) / (sqrt(v / (1 - beta2^t)) + eps) + weight_decay * w
    w = w - lr * (||w|| / ||u||) * u                        per tensor; the ratio is 1 if a norm is 0

Block-wise quantisation. Each moment is cut into blocks of `block_size` consecutive elements. A block
keeps one float32 scale, its largest magnitude (absmax), and one 8-bit code per element: the code of the
value of a quantisation map nearest to element / absmax. An outlier therefore costs precision only in
its own block. Every step dequantises the moments (code -> map value * absmax), updates them in float32,
computes the update from these float32 values and quantises them again for storage.

The dynamic map. Adam's moments span many orders of magnitude, so the map is floating-point-like
(Dettmers' dynamic tree quantisation, with his "dynamic" variant for the second moment): a code reads
E zeros, which give the scale 10^-E, then an indicator bit 1, then the remaining F bits as a linear
fraction. Level E holds the 2^F evenly spaced values 10^-(E+1) * (1 + 9 j / 2^F), j = 1 .. 2^F, that
is (0.1, 1] * 10^-E, and the code of zeros only is 0. With b magnitude bits the levels E = 0 .. b-1 give
2^b - 1 non-zero values from 10^-(b-1) up to 1 exactly. The first moment spends one bit on the sign and
7 on the magnitude (values in [-1, 1], the smallest non-zero magnitude 10^-6; +0 and -0 are both 0). The
second moment is never negative, so all 8 bits go to the magnitude (values in [0, 1], down to 10^-7).
The stored codes are the ranks of these values in ascending order, so a map is a sorted table of 256
float32 values and dequantising is one table look-up.

Rounding to the nearest code is a search over the sorted table. A binary search (torch.bucketize)
costs eight unpredictable branches per element (6x slower on a CPU); we instead index a table by the
top 17 bits of the float32 (sign, exponent and 8 mantissa bits): it gives the code nearest to the low
end of that sliver of floats, and one comparison with the midpoint to the next code finishes the
rounding. This is exact because no sliver holds two midpoints (neighbouring codes are at least 0.9/128
of their value apart, a sliver at most 2^-8), which `NearestCode` checks when it builds its table.

Choices, as measured in tests/test_lamb8bit.py and benchmarks/optim_bench.py:
- block_size 64. The second moment, a square, spans twice the orders of magnitude of the gradient; in a
  large block most of its elements sit far below the block's absmax, where the map is coarse and nearest
  rounding lets an element's v lag its own decay. Training the small config 300 steps on synthetic data
  (benchmarks/optim_bench.py, H200), the smoothed loss stays within 2.5 % / 0.96 % / 0.41 % / 0.28 % /
  0.21 % of 32-bit Lamb's for blocks of 2048 / 256 / 128 / 64 / 32 elements, against 0.21 % between two
  32-bit runs that see the same batches in another order. At 64 the two scales cost 2 x 4/64 = 0.125
  bytes per parameter over the 2 bytes of codes. (The paper used 2048; bitsandbytes now uses 256.)
- min_8bit_size 4096 (as bitsandbytes): smaller tensors (biases, norms: 0.1 % of RVT-2's parameters,
  but 130 of its 232 tensors) keep float32 moments and are updated by `Lamb` itself.
- Flat layout: the 8-bit moments of all large tensors of a parameter group (one device and dtype) live
  in one flat uint8 buffer per moment plus one flat scale buffer, each tensor padded to whole blocks. A
  step is then a few vectorised operations over all of them (about 100 kernels on CUDA for RVT-2's 232
  tensors, whatever their number); per-tensor norms for the trust ratio are `torch._foreach_norm` over
  views of the flat update (multi-tensor kernels, deterministic, unlike a scatter-add's atomics).
  The per-parameter state (`optimizer.state[p]`) holds views of these buffers, so `state_dict()` is the
  usual per-parameter one (tensors only) and loads with `torch.load(..., weights_only=True)`.

As `Lamb.step`, `Lamb8bit.step(skip=...)` takes a boolean device tensor: where it is true, the step
changes nothing (weights, moments, step count) and the host never waits for the device to decide.
"""

import math

import torch
from torch import Tensor
from torch.optim import Optimizer

from rvt2cli.train.lamb import Lamb

BLOCK_SIZE = 64
MIN_8BIT_SIZE = 4096
CODE_STATE_KEYS = ("exp_avg_codes", "exp_avg_absmax", "exp_avg_sq_codes", "exp_avg_sq_absmax")


def dynamic_magnitudes(bits: int) -> Tensor:
    """The 2^bits non-negative values of a dynamic quantisation map with `bits` magnitude bits, ascending
    (float64): 0, then level E = bits-1 down to 0, each with 2^F values in (10^-(E+1), 10^-E], F = bits-1-E."""
    values = [0.0]
    for exponent in reversed(range(bits)):
        fraction_bits = bits - 1 - exponent
        steps = 2**fraction_bits
        values += [10.0 ** -(exponent + 1) * (1 + 9 * j / steps) for j in range(1, steps + 1)]
    return torch.tensor(values, dtype=torch.float64)


def signed_dynamic_map() -> Tensor:
    """256 ascending float32 values in [-1, 1] for the first moment: a sign bit and 7 magnitude bits."""
    magnitudes = dynamic_magnitudes(7)
    values = torch.cat([-magnitudes.flip(0), magnitudes])
    values[127] = 0.0  # -0 is 0
    return values.float()


def unsigned_dynamic_map() -> Tensor:
    """256 ascending float32 values in [0, 1] for the second moment: all 8 bits for the magnitude."""
    return dynamic_magnitudes(8).float()


class NearestCode:
    """Rank of the nearest value in an ascending table (a quantisation map) of each float32 element.

    The float32 bit patterns, cut after their top 17 bits (sign, exponent and 8 mantissa bits; `SHIFT`
    drops the other 15), split the floats into 2^17 slivers, each an interval of values at most 2^-8 of
    its magnitude wide. For each sliver a look-up table holds the code nearest to the sliver's lowest
    value and the midpoint between that code and the next one; the code of x is the table's code, plus
    one if x lies above that midpoint. This is exact when no sliver holds two midpoints, which the
    constructor checks. Every bit pattern has its sliver (infinities and NaNs too), so any input is a
    valid index. Ties round down, as torch.bucketize(x, midpoints) does."""

    SHIFT = 15
    SLIVERS = 2 ** (32 - SHIFT)

    def __init__(self, values: Tensor, device=None):
        midpoints = ((values[:-1] + values[1:]) / 2).float()
        # The index of a float is (bits >> SHIFT) + SLIVERS / 2: the negative floats come first, from -0
        # (index 0) outwards, then the positive ones from +0 (index SLIVERS / 2) outwards. Sliver i of
        # either half spans the magnitudes [start[i], end[i]).
        start = (torch.arange(self.SLIVERS // 2, dtype=torch.int32) << self.SHIFT).view(torch.float32)
        end = torch.cat([start[1:], torch.tensor([math.inf])])
        # Code of x = number of midpoints below x = those at or below the sliver's lowest value, plus
        # the one (if any) inside the sliver that lies below x.
        below = torch.cat([torch.searchsorted(midpoints, -end, right=True), torch.searchsorted(midpoints, start)])
        up_to_highest = torch.cat([torch.searchsorted(midpoints, -start, right=True), torch.searchsorted(midpoints, end)])
        finite = start.isfinite().repeat(2)  # NaN slivers compare as nothing
        if int((up_to_highest - below)[finite].max()) > 1:
            raise ValueError("the quantisation map's codes are too close for a 17-bit look-up")
        self.code = below.to(torch.uint8).to(device)
        self.midpoint_above = torch.cat([midpoints, torch.tensor([math.inf])])[below].to(device)

    def __call__(self, x: Tensor) -> Tensor:
        """uint8 codes of a contiguous float32 tensor (same shape)."""
        sliver = (x.view(torch.int32) >> self.SHIFT).add_(self.SLIVERS // 2).flatten()
        code = self.code.index_select(0, sliver)
        code += x.flatten() > self.midpoint_above.index_select(0, sliver)
        return code.view(x.shape)


class BlockQuantiser:
    """Block-wise dynamic quantisation of a [blocks, block_size] float32 tensor to uint8 codes and one
    float32 absmax per block (signed: the first moment's map; unsigned: the second moment's)."""

    def __init__(self, signed: bool, device=None):
        self.signed = signed
        values = signed_dynamic_map() if signed else unsigned_dynamic_map()
        self.values = values.to(device)
        self.nearest = NearestCode(values, device)
        self.zero_code = int(torch.nonzero(values == 0)[-1])  # 128 signed, 0 unsigned

    def quantise(self, x: Tensor) -> tuple[Tensor, Tensor]:
        if self.signed:
            low, high = torch.aminmax(x, dim=1)
            absmax = torch.maximum(-low, high)
        else:
            absmax = x.amax(dim=1)
        normalised = x / torch.where(absmax > 0, absmax, 1.0)[:, None]
        return self.nearest(normalised), absmax

    def dequantise(self, codes: Tensor, absmax: Tensor) -> Tensor:
        values = self.values.index_select(0, codes.flatten().int()).view(codes.shape)
        return values.mul_(absmax[:, None])


class FlatBlocks:
    """The 8-bit moments of a list of tensors (one device and dtype) as flat [blocks, block_size] buffers,
    each tensor padded with zeros to a whole number of blocks, and their step count (one for all, as
    `Lamb` keeps one per group: a 0-d float32 tensor on the device)."""

    def __init__(self, params: list[Tensor], block_size: int, signed: BlockQuantiser, unsigned: BlockQuantiser):
        device = params[0].device
        self.params, self.block_size = params, block_size
        self.numels = [p.numel() for p in params]
        self.blocks = [math.ceil(n / block_size) for n in self.numels]
        self.padding = [b * block_size - n for b, n in zip(self.blocks, self.numels)]
        self.owner = torch.repeat_interleave(torch.arange(len(params), device=device), torch.tensor(self.blocks, device=device))
        self.zeros = torch.zeros(block_size, dtype=params[0].dtype, device=device)
        total = sum(self.blocks)
        self.step = torch.zeros((), dtype=torch.float32, device=device)
        self.exp_avg_codes = torch.full((total, block_size), signed.zero_code, dtype=torch.uint8, device=device)
        self.exp_avg_absmax = torch.zeros(total, device=device)
        self.exp_avg_sq_codes = torch.full((total, block_size), unsigned.zero_code, dtype=torch.uint8, device=device)
        self.exp_avg_sq_absmax = torch.zeros(total, device=device)

    def views(self, flat: Tensor) -> list[Tensor]:
        """Each tensor's blocks of a [blocks, ...] buffer."""
        return list(flat.split(self.blocks))

    def gather(self, tensors: list[Tensor]) -> Tensor:
        """The tensors, zero-padded to whole blocks, as one float32 [blocks, block_size] tensor."""
        pieces = [piece for t, pad in zip(tensors, self.padding) for piece in (t.reshape(-1), self.zeros[:pad])]
        return torch.cat(pieces).view(-1, self.block_size).float()

    def unpad(self, views: list[Tensor]) -> list[Tensor]:
        """Per-tensor [blocks, block_size] views back in the tensors' shapes (views, no copies)."""
        return [v.view(-1)[:n].view(p.shape) for v, n, p in zip(views, self.numels, self.params)]


class Lamb8bit(Optimizer):
    """LAMB with block-wise 8-bit moments (see the module docstring). Tensors with fewer than
    `min_8bit_size` elements keep float32 moments and are updated by `Lamb` itself (a private instance
    whose state is this optimiser's), so with only such tensors this is exactly `Lamb`.

    `step(skip=...)` behaves as `Lamb.step`: where the boolean device tensor `skip` is true, the step
    changes nothing (weights, moments, step count), without a host synchronisation."""

    def __init__(self, params, lr: float = 1e-3, betas=(0.9, 0.999), eps: float = 1e-6, weight_decay: float = 0.0,
                 block_size: int = BLOCK_SIZE, min_8bit_size: int = MIN_8BIT_SIZE):
        if block_size < 1 or min_8bit_size < 1:
            raise ValueError(f"block_size and min_8bit_size must be positive, not {block_size} and {min_8bit_size}")
        super().__init__(params, dict(lr=lr, betas=tuple(betas), eps=eps, weight_decay=weight_decay,
                                      block_size=block_size, min_8bit_size=min_8bit_size))
        self._quantisers: dict[torch.device, tuple[BlockQuantiser, BlockQuantiser]] = {}
        self._flat: dict[int, tuple[tuple[int, ...], list[FlatBlocks]]] = {}
        self._small: dict[int, tuple[tuple[int, ...], Lamb]] = {}

    def quantisers(self, device: torch.device) -> tuple[BlockQuantiser, BlockQuantiser]:
        """(signed, unsigned) quantisers with their tables on `device`."""
        if device not in self._quantisers:
            self._quantisers[device] = (BlockQuantiser(True, device), BlockQuantiser(False, device))
        return self._quantisers[device]

    @torch.no_grad()
    def step(self, closure=None, skip: Tensor | None = None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for index, group in enumerate(self.param_groups):
            small = self._small_lamb(index, group)
            if small is not None:
                small.step(skip=skip)
            for flat in self._flat_blocks(index, group):
                self._step_8bit(flat, group, skip)
        return loss

    def _small_lamb(self, index: int, group: dict) -> Lamb | None:
        """A `Lamb` over the group's small tensors, with this group's hyperparameters and our state."""
        small = [p for p in group["params"] if p.numel() < group["min_8bit_size"]]
        if not small:
            return None
        ids = tuple(id(p) for p in small)
        if index not in self._small or self._small[index][0] != ids:
            self._small[index] = (ids, Lamb(small))
        lamb = self._small[index][1]
        lamb.param_groups[0].update({k: group[k] for k in ("lr", "betas", "eps", "weight_decay")})
        lamb.state = self.state  # load_state_dict replaces self.state
        return lamb

    def _flat_blocks(self, index: int, group: dict) -> list[FlatBlocks]:
        """The flat 8-bit state of a group's large tensors, one per (device, dtype); made on first use
        from `self.state` (empty, or what `load_state_dict` put there), which then holds views of it."""
        large = [p for p in group["params"] if p.numel() >= group["min_8bit_size"]]
        ids = tuple(id(p) for p in large)
        if index in self._flat and self._flat[index][0] == ids:
            return self._flat[index][1]
        by_kind: dict[tuple, list[Tensor]] = {}
        for p in large:
            by_kind.setdefault((p.device, p.dtype), []).append(p)
        made = []
        for (device, _), params in by_kind.items():
            signed, unsigned = self.quantisers(device)
            flat = FlatBlocks(params, group["block_size"], signed, unsigned)
            buffers = {key: flat.views(getattr(flat, key)) for key in CODE_STATE_KEYS}
            for i, p in enumerate(params):
                old = self.state[p]
                if "step" in old:
                    flat.step.copy_(torch.as_tensor(old["step"]))
                if "exp_avg" in old:  # float32 moments, from `Lamb` or a larger min_8bit_size: quantise them
                    for name, quantiser in (("exp_avg", signed), ("exp_avg_sq", unsigned)):
                        moment = torch.nn.functional.pad(old[name].reshape(-1).float(), (0, flat.padding[i]))
                        codes, absmax = quantiser.quantise(moment.view(-1, flat.block_size))
                        buffers[name + "_codes"][i].copy_(codes)
                        buffers[name + "_absmax"][i].copy_(absmax)
                for key in CODE_STATE_KEYS:
                    if key in old:
                        buffers[key][i].copy_(old[key])
                self.state[p] = {"step": flat.step, **{key: buffers[key][i] for key in CODE_STATE_KEYS}}
            made.append(flat)
        self._flat[index] = (ids, made)
        return made

    def _step_8bit(self, flat: FlatBlocks, group: dict, skip: Tensor | None) -> None:
        params = flat.params
        has_grad = [p.grad is not None for p in params]
        if not any(has_grad):
            return
        if any(p.grad.is_sparse for p in params if p.grad is not None):
            raise RuntimeError("Lamb8bit does not support sparse gradients")
        device = flat.step.device
        beta1, beta2 = group["betas"]
        signed, unsigned = self.quantisers(device)
        keep = torch.ones((), device=device) if skip is None else (~skip).float()  # 0: a skipped step
        flat.step += keep
        # Blocks whose stored moments change: all, unless the step is skipped or a tensor has no gradient.
        tensor_takes = None if all(has_grad) else torch.tensor(has_grad, device=device)
        takes = None if skip is None else keep.bool()
        if tensor_takes is not None:
            takes = tensor_takes[flat.owner] if takes is None else tensor_takes[flat.owner] & takes

        grad = flat.gather([p.grad if p.grad is not None else torch.zeros_like(p) for p in params])
        if skip is not None:  # a skipped step's update is multiplied by 0, and NaN * 0 is NaN
            torch.nan_to_num_(grad, nan=0.0, posinf=0.0, neginf=0.0)
        exp_avg = signed.dequantise(flat.exp_avg_codes, flat.exp_avg_absmax)
        exp_avg_sq = unsigned.dequantise(flat.exp_avg_sq_codes, flat.exp_avg_sq_absmax)
        exp_avg.mul_(beta1).add_(grad, alpha=1 - beta1)
        exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
        del grad
        for name, quantiser, moment in (("exp_avg", signed, exp_avg), ("exp_avg_sq", unsigned, exp_avg_sq)):
            codes, absmax = quantiser.quantise(moment)
            stored_codes, stored_absmax = getattr(flat, name + "_codes"), getattr(flat, name + "_absmax")
            if takes is not None:
                codes = torch.where(takes[:, None] if takes.dim() else takes, codes, stored_codes)
                absmax = torch.where(takes, absmax, stored_absmax)
            stored_codes.copy_(codes)
            stored_absmax.copy_(absmax)

        # The update, from this step's float32 moments, in the order of `Lamb`'s arithmetic.
        t = flat.step.clamp_min(1)
        denom = exp_avg_sq.sqrt_().div_(torch.sqrt(1 - beta2**t)).add_(group["eps"])
        update = exp_avg.div_(denom).div_(1 - beta1**t)
        del denom, exp_avg_sq
        if group["weight_decay"]:
            update.add_(flat.gather(params), alpha=group["weight_decay"])
        per_tensor = flat.views(update)
        w_norm = torch.stack(torch._foreach_norm(params)).float()
        u_norm = torch.stack(torch._foreach_norm(per_tensor))  # the padding is zero in the update
        trust = torch.where((w_norm > 0) & (u_norm > 0), w_norm / u_norm, torch.ones_like(w_norm))
        scale = trust * (-group["lr"] * keep)
        if tensor_takes is not None:
            scale = scale * tensor_takes
        update.mul_(scale[flat.owner][:, None])
        torch._foreach_add_(params, flat.unpad(per_tensor))

    def moments(self, p: Tensor) -> tuple[Tensor, Tensor]:
        """A parameter's (first, second) moment as float32 tensors of its shape, as the next step reads them."""
        state = self.state.get(p, {})
        if "exp_avg" in state:
            return state["exp_avg"].float(), state["exp_avg_sq"].float()
        if "exp_avg_codes" not in state:
            return torch.zeros_like(p, dtype=torch.float32), torch.zeros_like(p, dtype=torch.float32)
        signed, unsigned = self.quantisers(p.device)
        m = signed.dequantise(state["exp_avg_codes"], state["exp_avg_absmax"])
        v = unsigned.dequantise(state["exp_avg_sq_codes"], state["exp_avg_sq_absmax"])
        return m.view(-1)[: p.numel()].view(p.shape), v.view(-1)[: p.numel()].view(p.shape)

    def load_state_dict(self, state_dict: dict) -> None:
        # The base class casts floating-point state to each parameter's dtype; the absmax scales must stay
        # float32 (a bfloat16 parameter would round them), so they bypass it.
        codes = {i: {k: v for k, v in s.items() if k in CODE_STATE_KEYS} for i, s in state_dict["state"].items()}
        rest = {i: {k: v for k, v in s.items() if k not in CODE_STATE_KEYS} for i, s in state_dict["state"].items()}
        current = [dict(group) for group in self.param_groups]
        super().load_state_dict({**state_dict, "state": rest})
        for group, settings in zip(self.param_groups, current):  # a 32-bit Lamb's groups lack block_size, ...
            for key, value in settings.items():
                group.setdefault(key, value)
        saved_ids = [i for g in state_dict["param_groups"] for i in g["params"]]
        params = [p for g in self.param_groups for p in g["params"]]
        for i, p in zip(saved_ids, params):
            for key, value in codes.get(i, {}).items():
                self.state[p][key] = value.to(p.device)
        self._flat = {}  # rebuilt from self.state at the next step

    def state_bytes(self) -> int:
        """Bytes of optimiser state: codes, scales, step counts, float32 moments of small tensors."""
        return optimizer_state_bytes(self)


def optimizer_state_bytes(optimizer: Optimizer) -> int:
    """Bytes held by an optimiser's state tensors, each storage counted once (Lamb8bit's per-parameter
    states are views of shared flat buffers)."""
    storages = {}
    for state in optimizer.state.values():
        for value in state.values():
            if isinstance(value, Tensor):
                storage = value.untyped_storage()
                storages[(storage.device, storage.data_ptr())] = storage.nbytes()
    return sum(storages.values())
