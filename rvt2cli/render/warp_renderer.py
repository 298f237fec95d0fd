"""The point renderer as warp kernels, on CPU or CUDA, zero-copy on torch tensors.

Same contract and same arithmetic as `reference.py` (read it first); here it costs one fill and two
launches, with no host synchronisation:

    keys.fill(EMPTY)          torch, on the current stream
    _zbuffer_kernel           one thread per point: project into every view, atomic_min its key
    _resolve_kernel           one thread per pixel: splat (optional), unpack the key, gather

On CUDA both kernels go to torch's current stream, so a render can be captured in a CUDA graph
(after a first call has loaded the kernels).
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import sys
import threading
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

import torch
import warp as wp
from torch import Tensor

from .cameras import CX, CY, FAR, FX, FY, NEAR, ORTHO, TRANSLATION
from .reference import DEPTH_SCALE, EMPTY_KEY, INDEX_BITS, INDEX_MASK, MAX_DEPTH_LEVEL

# No FMA contraction: the kernels then round exactly like the torch reference, pixel for pixel.
wp.set_module_options({"fuse_fp": False, "enable_backward": False})

_EMPTY = wp.constant(wp.int64(EMPTY_KEY))
_INDEX_BITS = wp.constant(wp.int64(INDEX_BITS))
_INDEX_MASK = wp.constant(wp.int64(INDEX_MASK))
_MAX_DEPTH_LEVEL = wp.constant(wp.int64(MAX_DEPTH_LEVEL))
_DEPTH_SCALE = wp.constant(DEPTH_SCALE)
_T = wp.constant(TRANSLATION.start)
_FX, _FY, _CX, _CY = wp.constant(FX), wp.constant(FY), wp.constant(CX), wp.constant(CY)
_NEAR, _FAR, _ORTHO = wp.constant(NEAR), wp.constant(FAR), wp.constant(ORTHO)


@wp.func
def _camera_point(cameras: wp.array3d(dtype=float), b: int, v: int, x: float, y: float, z: float) -> wp.vec3:
    """p_cam = R p + t, summed in the order of `cameras.camera_coordinates`."""
    xc = cameras[b, v, 0] * x + cameras[b, v, 1] * y + cameras[b, v, 2] * z + cameras[b, v, _T]
    yc = cameras[b, v, 3] * x + cameras[b, v, 4] * y + cameras[b, v, 5] * z + cameras[b, v, _T + 1]
    zc = cameras[b, v, 6] * x + cameras[b, v, 7] * y + cameras[b, v, 8] * z + cameras[b, v, _T + 2]
    return wp.vec3(xc, yc, zc)


@wp.func
def _key_depth(key: wp.int64, near: float, far: float) -> float:
    return near + (far - near) * (float(key >> _INDEX_BITS) / _DEPTH_SCALE)


@wp.func
def _draw_point(
    points: wp.array3d(dtype=float),
    cameras: wp.array3d(dtype=float),
    b: int,
    n: int,
    height: int,
    width: int,
    keys: wp.array(dtype=wp.int64),
):
    """atomic_min point n's key into the pixel it lands on in every view where it is visible."""
    x = points[b, n, 0]
    y = points[b, n, 1]
    z = points[b, n, 2]
    if not (wp.isfinite(x) and wp.isfinite(y) and wp.isfinite(z)):
        return
    views = cameras.shape[1]
    for v in range(views):
        p = _camera_point(cameras, b, v, x, y, z)
        near = cameras[b, v, _NEAR]
        far = cameras[b, v, _FAR]
        ortho = cameras[b, v, _ORTHO] > 0.5
        if p[2] >= near and p[2] <= far and (ortho or p[2] > 0.0):
            divisor = 1.0
            if not ortho:
                divisor = p[2]
            u = cameras[b, v, _FX] * p[0] / divisor + cameras[b, v, _CX]
            w = cameras[b, v, _FY] * p[1] / divisor + cameras[b, v, _CY]
            if u >= 0.0 and u < float(width) and w >= 0.0 and w < float(height):
                level = wp.min(wp.int64(wp.floor((p[2] - near) / (far - near) * _DEPTH_SCALE)), _MAX_DEPTH_LEVEL)
                pixel = ((b * views + v) * height + int(w)) * width + int(u)
                wp.atomic_min(keys, pixel, (level << _INDEX_BITS) | wp.int64(n))


@wp.kernel
def _zbuffer_kernel(
    points: wp.array3d(dtype=float),  # [B, N, 3]
    num_points: wp.array(dtype=wp.int64),  # [B], read when use_num_points != 0
    use_num_points: int,
    cameras: wp.array3d(dtype=float),  # [B, V, 19]
    height: int,
    width: int,
    span: int,  # points per thread
    keys: wp.array(dtype=wp.int64),  # [B * V * H * W], filled with EMPTY
):
    b, chunk = wp.tid()
    end = wp.min((chunk + 1) * span, points.shape[1])
    if use_num_points != 0:
        end = int(wp.min(wp.int64(end), num_points[b]))
    for n in range(chunk * span, end):
        _draw_point(points, cameras, b, n, height, width, keys)


@wp.func
def _splat_key(
    keys: wp.array(dtype=wp.int64),
    image_start: int,
    height: int,
    width: int,
    row: int,
    col: int,
    radius: float,
    fx: float,
    near: float,
    far: float,
    ortho: bool,
    reach: float,
    max_px: float,
) -> wp.int64:
    """The smallest key among pixel (row, col) and the neighbours whose disc covers its centre.

    Only neighbours within `reach` (the largest disc of the view) are visited: for each row offset
    dy the columns |dx| <= sqrt(reach^2 - dy^2), a superset of the covering ones (sqrt rounds
    monotonically), each then tested exactly as in the reference."""
    best = keys[image_start + row * width + col]
    steps = int(reach)
    for dy in range(wp.max(-steps, -row), wp.min(steps, height - 1 - row) + 1):
        half = int(wp.sqrt(wp.max(reach * reach - float(dy * dy), 0.0)))
        line = image_start + (row + dy) * width
        for c in range(wp.max(col - half, 0), wp.min(col + half, width - 1) + 1):
            key = keys[line + c]
            if key < best:  # only a nearer key can change the minimum
                disc = radius * fx
                if not ortho:
                    disc = radius * fx / _key_depth(key, near, far)
                disc = wp.min(disc, max_px)
                dx = c - col
                if float(dy * dy + dx * dx) <= disc * disc:
                    best = key
    return best


@wp.kernel
def _resolve_kernel(
    keys: wp.array(dtype=wp.int64),  # [B * V * H * W]
    cameras: wp.array3d(dtype=float),  # [B, V, 19]
    features: wp.array3d(dtype=float),  # [B, N, C]
    height: int,
    width: int,
    span: int,  # pixels per thread: 1 or a whole row (spans never cross a row)
    splat_radius: float,
    max_splat_px: float,
    out_features: wp.array2d(dtype=float),  # [B * V * H * W, C]
    out_depth: wp.array(dtype=float),  # [B * V * H * W]
    out_index: wp.array(dtype=wp.int64),  # [B * V * H * W]
):
    first = wp.tid() * span
    image = first / (height * width)
    b = image / cameras.shape[1]
    v = image % cameras.shape[1]
    row = (first / width) % height
    col0 = first % width
    near = cameras[b, v, _NEAR]
    far = cameras[b, v, _FAR]
    fx = cameras[b, v, _FX]
    ortho = cameras[b, v, _ORTHO] > 0.5
    reach = max_splat_px  # the largest disc of this view (pinhole: at the near plane), capped
    if ortho:
        reach = wp.min(splat_radius * fx, max_splat_px)
    elif near > 0.0:
        reach = wp.min(splat_radius * fx / near, max_splat_px)
    for col in range(col0, col0 + span):
        pixel = first + col - col0
        key = keys[pixel]
        if splat_radius > 0.0:
            key = _splat_key(
                keys, image * height * width, height, width, row, col,
                splat_radius, fx, near, far, ortho, reach, max_splat_px,
            )
        if key == _EMPTY:
            for c in range(features.shape[2]):
                out_features[pixel, c] = 0.0
            out_depth[pixel] = 0.0
            out_index[pixel] = wp.int64(-1)
        else:
            n = int(key & _INDEX_MASK)
            for c in range(features.shape[2]):
                out_features[pixel, c] = features[b, n, c]
            out_depth[pixel] = _key_depth(key, near, far)
            out_index[pixel] = key & _INDEX_MASK


def render_warp(
    points: Tensor,
    features: Tensor,
    params: Tensor,
    height: int,
    width: int,
    num_points: Tensor | None = None,
    splat_radius: float = 0.0,
    max_splat_px: int = 8,
) -> tuple[Tensor, Tensor, Tensor]:
    """Render (validated, contiguous) clouds; same contract as `reference.render_reference`."""
    device = points.device
    _initialise(device)
    batch, n, channels = features.shape
    views = params.shape[1]
    images = (batch, views, height, width)
    keys = _keys_buffer(images, device)
    out_features = torch.empty((*images, channels), dtype=torch.float32, device=device)
    out_depth = torch.empty(images, dtype=torch.float32, device=device)
    out_index = torch.empty(images, dtype=torch.int64, device=device)

    def run(part: tuple[slice, slice], **place) -> None:
        """Both kernels over the scenes and views of `part` (a contiguous block of images)."""
        scenes, view_range = part
        params_part = params[scenes, view_range]
        point_span, pixel_span = (1, 1) if device.type == "cuda" else (64, width)
        block = (params_part.shape[0], params_part.shape[1], height, width)
        keys_part = keys[scenes, view_range]
        if n > 0:
            counts = None if num_points is None else _view(num_points[scenes])
            wp.launch(
                _zbuffer_kernel,
                dim=(block[0], -(-n // point_span)),
                inputs=[
                    _view(points[scenes]), counts, int(num_points is not None), _view(params_part),
                    height, width, point_span, _view(keys_part.view(-1)),
                ],
                **place,
            )
        wp.launch(
            _resolve_kernel,
            dim=math.prod(block) // pixel_span,
            inputs=[
                _view(keys_part.view(-1)), _view(params_part), _view(features[scenes]), height, width,
                pixel_span, splat_radius, float(max_splat_px),
                _view(out_features[scenes, view_range].view(-1, channels)),
                _view(out_depth[scenes, view_range].view(-1)),
                _view(out_index[scenes, view_range].view(-1)),
            ],
            **place,
        )

    if device.type == "cuda":
        run((slice(None), slice(None)), stream=_warp_stream(torch.cuda.current_stream(device)))
    else:
        parts = _cpu_parts(batch, views, torch.get_num_threads())
        list(_cpu_pool(len(parts)).map(functools.partial(run, device="cpu"), parts))
    return out_features, out_depth, out_index


def _view(tensor: Tensor):
    """A zero-copy warp array descriptor of a contiguous tensor (the lightweight ctype form)."""
    return wp.from_torch(tensor, return_ctype=True)


def _keys_buffer(shape: tuple[int, ...], device: torch.device) -> Tensor:
    """The z-buffer, filled with EMPTY_KEY. On the CPU a per-thread buffer is reused: fresh pages cost
    more there than the fill (on CUDA torch's caching allocator makes a new one free)."""
    if device.type == "cuda":
        return torch.full(shape, EMPTY_KEY, dtype=torch.int64, device=device)
    numel = math.prod(shape)
    buffer = getattr(_cpu_scratch, "keys", None)
    if buffer is None or buffer.numel() < numel:
        buffer = _cpu_scratch.keys = torch.empty(numel, dtype=torch.int64)
    return buffer[:numel].view(shape).fill_(EMPTY_KEY)


_cpu_scratch = threading.local()


def _cpu_parts(batch: int, views: int, workers: int) -> list[tuple[slice, slice]]:
    """Split the images into contiguous blocks of (scenes, views) for CPU threads: warp runs a CPU
    launch on one thread, and blocks touch disjoint pixels, so threads need no atomics."""
    if batch == 1 and views > 1:
        bounds = _even_bounds(views, workers)
        return [(slice(0, 1), slice(lo, hi)) for lo, hi in bounds]
    return [(slice(lo, hi), slice(None)) for lo, hi in _even_bounds(batch, workers)]


def _even_bounds(total: int, parts: int) -> list[tuple[int, int]]:
    parts = max(1, min(parts, total))
    edges = [total * i // parts for i in range(parts + 1)]
    return list(zip(edges[:-1], edges[1:]))


@functools.cache
def _cpu_pool(workers: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=workers, thread_name_prefix="rvt2-render")


@functools.lru_cache(maxsize=16)
def _warp_stream(stream: torch.cuda.Stream) -> wp.Stream:
    # Cached: wrapping a stream registers it with warp's runtime, which is not free.
    return wp.stream_from_torch(stream)


_loaded: set[str] = set()


def _initialise(device: torch.device) -> None:
    """Initialise warp silently and load the kernels on `device` (compiled on first use, then cached on
    disk), before any CPU thread or CUDA graph capture needs them."""
    key = str(device)
    if key in _loaded:
        return
    wp.config.log_level = wp.LOG_ERROR  # no "module loaded" chatter
    with contextlib.nullcontext() if torch.cuda.is_available() else _native_stderr_silenced():
        wp.init()
    wp.load_module(sys.modules[__name__], device=wp.device_from_torch(device))
    _loaded.add(key)


@contextlib.contextmanager
def _native_stderr_silenced() -> Iterator[None]:
    """Silence file descriptor 2: without a CUDA driver warp's native library warns there, and on a
    CPU-only machine that is expected, not news."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
