"""benchmarks/gemm_bench.py finds the matrix products the policy's forward really runs."""

import pytest
import torch

from benchmarks import gemm_bench
from benchmarks.policy_bench import forward_flops
from rvt2cli.model.config import get_config


def test_the_products_of_a_forward_are_the_transformers_and_the_heads():
    cfg, batch, points = get_config("small"), 2, 2000
    shapes = gemm_bench.product_shapes(cfg, batch, points, torch.device("cpu"))
    by_kn = {}
    for (m, k, n), count in shapes.items():
        by_kn.setdefault((k, n), []).append((m, count))
    layers = cfg.depth * cfg.stages
    qkv = by_kn[(cfg.width, 3 * cfg.heads * cfg.head_dim)]
    assert sum(count for _, count in qkv) == layers   # one attention input product per layer and stage
    assert all(m % batch == 0 and m >= batch * cfg.tokens_per_side ** 2 for m, _ in qkv)   # every token of a batch
    # GEGLU's two products over the halves of one weight (F.linear, no module of their own) are found too
    assert sum(count for _, count in by_kn[(cfg.width, cfg.mlp_ratio * cfg.width)]) == 2 * layers
    assert sum(count for _, count in by_kn[(cfg.mlp_ratio * cfg.width, cfg.width)]) == layers
    products = sum(2 * m * k * n * count for (m, k, n), count in shapes.items())
    assert 0.3 < products / (batch * forward_flops(cfg, torch.device("cpu"), points)) < 1   # convolutions and attention are the rest


def test_the_bench_times_every_shape_and_sums_a_step(tmp_path):
    results = gemm_bench.main(["--quick", "--device", "cpu", "--json", str(tmp_path / "g.json")])
    assert results["per_step"]["bf16_ms"] > 0 and all(r["bf16_ms"] > 0 and r["count"] >= 1 for r in results["shapes"])
    assert "fp8_ms" not in results["per_step"]   # FP8 products need a Hopper GPU
    assert (tmp_path / "g.json").exists()


def test_the_fp8_operands_it_times_compute_the_bf16_product():
    """The casts, scales and layouts handed to `torch._scaled_mm` give the product in bf16, within what
    e4m3 and e5m2 keep (3 and 2 mantissa bits); a wrong scale or layout would be far off."""
    for a, b, left, right in gemm_bench._three_products(64, 32, 48, torch.device("cpu")):
        (qa, sa), (qb, sb) = gemm_bench._to_float8(a, left), gemm_bench._to_float8(b.t().contiguous(), right)
        try:
            got = torch._scaled_mm(qa, qb.t(), scale_a=sa, scale_b=sb, out_dtype=torch.bfloat16).float()
        except (RuntimeError, NotImplementedError):
            pytest.skip("this torch has no FP8 products on the CPU")
        want = a.float() @ b.float()
        assert got.shape == want.shape
        assert (got - want).abs().max() < 0.15 * want.abs().max()
        assert torch.corrcoef(torch.stack([got.flatten(), want.flatten()]))[0, 1] > 0.99
