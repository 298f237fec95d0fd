"""Between 3D points and per-view heatmaps: Gaussian heatmap targets, and the 3D point a set of
heatmaps agrees on.

A 3D point's score is the mean of its projections' heatmap values over the views; the prediction is
the highest-scoring point of the W^3 grid of voxel centres the views' pixel centres line up with
(`rvt2cli.render.cameras` guarantees the alignment for the cube and zoom rigs). The reference
implementation materialises a 224^3 grid of projection indices (>1 GB). Here each axis-aligned
orthographic view sees two of the three axes, so the score splits into three pairwise tables,
    S[i, j, k] = A_xy[i, j] + A_xz[i, k] + A_yz[j, k],
each the sum of the views that see that pair of axes. The exact argmax is then found slab by slab
over i, holding O(B * chunk * W^2) numbers instead of O(B * W^3) (at most SLAB_ELEMENTS). At stage 2 a voxel is 1/224 of a
quarter of the scene cube: 0.9 mm for our 0.8 m workspace, so the argmax is exact to half a voxel.
"""

from dataclasses import dataclass

import torch

from rvt2cli.render.cameras import VIEW_AXES, Cameras, project

_PAIRS = ((0, 1), (0, 2), (1, 2))


@dataclass(frozen=True)
class ViewAxes:
    """Which world axis (and direction) an axis-aligned orthographic view's columns and rows follow."""

    col_axis: int
    col_sign: int
    row_axis: int
    row_sign: int


def view_axes(views) -> list[ViewAxes]:
    """From the rig's view names (static: no tensor data, so the argmax traces and exports)."""
    axes = []
    for name in views:
        right, down = VIEW_AXES[name][0], VIEW_AXES[name][1]
        col_axis = max(range(3), key=lambda i: abs(right[i]))
        row_axis = max(range(3), key=lambda i: abs(down[i]))
        axes.append(ViewAxes(col_axis, 1 if right[col_axis] > 0 else -1, row_axis, 1 if down[row_axis] > 0 else -1))
    return axes


def _voxel_table(prob: torch.Tensor, axes: ViewAxes) -> tuple[tuple[int, int], torch.Tensor]:
    """A view's [B, H, W] probabilities re-indexed by voxel index along its two axes (lower axis first)."""
    table = prob
    if axes.row_sign < 0:
        table = table.flip(1)
    if axes.col_sign < 0:
        table = table.flip(2)
    # table is now [B, idx_row_axis, idx_col_axis]
    if axes.row_axis < axes.col_axis:
        return (axes.row_axis, axes.col_axis), table
    return (axes.col_axis, axes.row_axis), table.transpose(1, 2)


SLAB_ELEMENTS = 2**26  # scores held at once (256 MB in float32): one slab for a single 224-px sample


def window_voxels(w: int, window: float) -> tuple[int, int]:
    """The voxel indices [lo, hi) along an axis of W voxels whose centres lie within +-`window` of the
    box's centre (box units: the box spans [-1, 1]); at least the two central voxels."""
    if not 0.0 < window <= 1.0:
        raise ValueError(f"window {window} must be in (0, 1]")
    half = max(1, round(window * w / 2))
    return max(0, w // 2 - half), min(w, w - w // 2 + half)


def heatmaps_to_point(probs: torch.Tensor, views, box_center: torch.Tensor, box_half: float,
                      chunk: int | None = None, window: float = 1.0) -> torch.Tensor:
    """probs [B, V, W, W] (each view sums to 1) of the named axis-aligned orthographic views (a cube or
    zoom rig) -> [B, 3] voxel centre with the best mean score, in cube coordinates; the views cover
    the box `box_center` +- `box_half`. Only voxels within +-`window` of the box's centre (box units)
    are candidates."""
    b, v, h, w = probs.shape
    if h != w:
        raise ValueError("3D argmax needs square views")
    lo, hi = window_voxels(int(w), window)  # int: a traced size is a tensor; the views' size is static
    tables = {pair: probs.new_zeros(b, w, w) for pair in _PAIRS}
    for view, axes in enumerate(view_axes(views)):
        pair, table = _voxel_table(probs[:, view], axes)
        tables[pair] = tables[pair] + table
    a_xy, a_xz, a_yz = (tables[pair][:, lo:hi, lo:hi] for pair in _PAIRS)
    n = hi - lo
    chunk = chunk or max(1, min(n, SLAB_ELEMENTS // (b * n * n)))  # few, large slabs: few kernel launches
    best_score = probs.new_full((b,), -1.0)
    best_index = torch.zeros(b, dtype=torch.long, device=probs.device)
    for start in range(0, n, chunk):
        stop = min(start + chunk, n)
        slab = a_xy[:, start:stop, :, None] + a_xz[:, start:stop, None, :] + a_yz[:, None, :, :]  # [B, c, n, n]
        score, index = slab.flatten(1).max(dim=1)
        better = score > best_score
        best_score = torch.where(better, score, best_score)
        best_index = torch.where(better, index + start * n * n, best_index)
    ijk = torch.stack([best_index // (n * n), (best_index // n) % n, best_index % n], dim=1) + lo
    voxel = -1.0 + (ijk.to(probs.dtype) + 0.5) * (2.0 / w)
    return box_center + voxel * box_half


def gaussian_targets(points: torch.Tensor, cameras: Cameras, size: int, sigma: float) -> torch.Tensor:
    """points [B, 3] (cube coords) -> [B, V, size, size] Gaussian heatmaps centred on their projections,
    each summing to 1 (a probability distribution for the cross-entropy)."""
    uv, _ = project(points[:, None, :], cameras)                  # [B, V, 1, 2]
    u, v = uv[..., 0, 0], uv[..., 0, 1]                           # [B, V]
    centres = torch.arange(size, device=points.device, dtype=points.dtype) + 0.5
    gx = torch.exp(-((centres[None, None, :] - u[..., None]) ** 2) / (2 * sigma**2))   # [B, V, W]
    gy = torch.exp(-((centres[None, None, :] - v[..., None]) ** 2) / (2 * sigma**2))   # [B, V, H]
    heat = gy[..., :, None] * gx[..., None, :]
    return heat / heat.sum(dim=(-2, -1), keepdim=True).clamp_min(1e-12)
