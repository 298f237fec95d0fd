"""The point renderer as warp kernels, on CPU or CUDA, zero-copy on torch tensors.

Same contract and same arithmetic as `reference.py` (read it first); here it costs one fill and two
launches, with no host synchronisation:

    keys.fill(EMPTY)    the z-buffer, int64 per pixel
    _zbuffer_kernel     per point: project into every view, atomic_min its key into its pixel
    _resolve_kernel     per pixel: splat (optional), unpack the key, gather features and depth

On CUDA a thread handles one point or one pixel, and both kernels go to torch's current stream, so
a render can be captured in a CUDA graph (after a first call has loaded the kernels). warp runs a
CPU launch on one thread, thread after thread, so there a thread handles 64 points or a whole
image row (amortising its fixed cost), and the images are split into blocks rendered in parallel
by torch.get_num_threads() Python threads (warp releases the GIL while a kernel runs).
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
_MODULE_OPTIONS = {"fuse_fp": False, "enable_backward": False}
wp.set_module_options(_MODULE_OPTIONS)

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
    num_points: wp.array(dtype=wp.int64),  # [B]
    cameras: wp.array3d(dtype=float),  # [B, V, 19]
    height: int,
    width: int,
    span: int,  # points per thread
    keys: wp.array(dtype=wp.int64),  # [B * V * H * W], filled with EMPTY
):
    b, chunk = wp.tid()
    count = int(wp.min(num_points[b], wp.int64(points.shape[1])))  # later points are ignored
    for n in range(chunk * span, wp.min((chunk + 1) * span, count)):
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

    Visits the offsets with dy^2 + dx^2 <= reach^2, reach being the largest disc of the view (for
    each dy the integer square root of reach^2 - dy^2, a difference float32 holds exactly). An
    orthographic view's discs all have radius `reach`, so there that set is exactly the covering
    neighbours and a plain min does (EMPTY is the largest key); a pinhole disc shrinks with depth
    and each nearer key is tested as in the reference."""
    best = keys[image_start + row * width + col]
    reach2 = reach * reach
    steps = int(reach)
    for dy in range(wp.max(-steps, -row), wp.min(steps, height - 1 - row) + 1):
        room = reach2 - float(dy * dy)
        half = int(wp.sqrt(wp.max(room, 0.0)))
        if float(half * half) > room:  # sqrt rounded up to an integer
            half = half - 1
        line = image_start + (row + dy) * width
        first = wp.max(col - half, 0)
        last = wp.min(col + half, width - 1)
        if ortho:
            for c in range(first, last + 1):
                best = wp.min(best, keys[line + c])
        else:
            for c in range(first, last + 1):
                key = keys[line + c]
                if key < best:  # only a nearer key can change the minimum
                    disc = wp.min(radius * fx / _key_depth(key, near, far), max_px)
                    dx = c - col
                    if float(dy * dy + dx * dx) <= disc * disc:
                        best = key
    return best


@functools.cache
def _feature_row(channels: int) -> type:
    return wp.types.vector(length=channels, dtype=float)


@functools.cache
def _resolve_kernel(channels: int) -> wp.Kernel:
    """The per-pixel kernel for feature rows of `channels` floats. Each row moves as one vector, a
    single memory operation instead of `channels` (on CUDA the kernel takes ~40% less time), so the
    kernel is built, and compiled once, per channel count."""
    feature_row = _feature_row(channels)

    @wp.kernel(module="unique", module_options=_MODULE_OPTIONS)
    def resolve(
        keys: wp.array(dtype=wp.int64),  # [B * V * H * W]
        cameras: wp.array3d(dtype=float),  # [B, V, 19]
        features: wp.array2d(dtype=feature_row),  # [B, N]
        height: int,
        width: int,
        span: int,  # pixels per thread: 1 or a whole row (spans never cross a row)
        splat_radius: float,
        max_splat_px: float,
        out_features: wp.array(dtype=feature_row),  # [B * V * H * W]
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
                out_features[pixel] = feature_row()
                out_depth[pixel] = 0.0
                out_index[pixel] = wp.int64(-1)
            else:
                out_features[pixel] = features[b, int(key & _INDEX_MASK)]
                out_depth[pixel] = _key_depth(key, near, far)
                out_index[pixel] = key & _INDEX_MASK

    return resolve


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
    batch, n, channels = features.shape
    resolve = _loaded_kernels(device, channels)
    images = (batch, params.shape[1], height, width)
    out_features = torch.empty((*images, channels), dtype=torch.float32, device=device)
    out_depth = torch.empty(images, dtype=torch.float32, device=device)
    out_index = torch.empty(images, dtype=torch.int64, device=device)
    if batch == 0:
        return out_features, out_depth, out_index
    keys = _keys_buffer(images, device)
    if num_points is None:
        num_points = torch.full((batch,), n, dtype=torch.int64, device=device)
    options = dict(resolve=resolve, splat_radius=splat_radius, max_splat_px=max_splat_px)

    if device.type == "cuda":
        _launch(
            points, num_points, params, features, keys, out_features, out_depth, out_index, **options,
            point_span=1, pixel_span=1, place=dict(stream=_warp_stream(torch.cuda.current_stream(device))),
        )
        return out_features, out_depth, out_index

    def launch_part(part: tuple[slice, slice]) -> None:
        scenes, views = part
        _launch(
            points[scenes], num_points[scenes], params[scenes, views], features[scenes], keys[scenes, views],
            out_features[scenes, views], out_depth[scenes, views], out_index[scenes, views], **options,
            point_span=64, pixel_span=width, place=dict(device="cpu"),
        )

    parts = _cpu_parts(batch, images[1], torch.get_num_threads())
    list(_cpu_pool(len(parts)).map(launch_part, parts))
    return out_features, out_depth, out_index


def _launch(
    points: Tensor,
    num_points: Tensor,
    params: Tensor,
    features: Tensor,
    keys: Tensor,
    out_features: Tensor,
    out_depth: Tensor,
    out_index: Tensor,
    resolve: wp.Kernel,
    splat_radius: float,
    max_splat_px: int,
    point_span: int,
    pixel_span: int,
    place: dict,
) -> None:
    """Both kernels over a contiguous block of images [B, V, H, W]; `place` is wp.launch's device or
    stream."""
    batch, _, height, width = keys.shape
    n, channels = features.shape[1:]
    flat_keys = _view(keys.view(-1))
    cameras = _view(params)
    if n > 0:
        wp.launch(
            _zbuffer_kernel,
            dim=(batch, -(-n // point_span)),
            inputs=[_view(points), _view(num_points), cameras, height, width, point_span, flat_keys],
            **place,
        )
    row = _feature_row(channels)
    wp.launch(
        resolve,
        dim=keys.numel() // pixel_span,
        inputs=[
            flat_keys, cameras, _view(features, row), height, width, pixel_span, splat_radius,
            float(max_splat_px), _view(out_features.view(-1, channels), row), _view(out_depth.view(-1)),
            _view(out_index.view(-1)),
        ],
        **place,
    )


def _view(tensor: Tensor, dtype: type | None = None):
    """A zero-copy warp array descriptor of a contiguous tensor (the lightweight ctype form); with a
    vector dtype the last dimension becomes the vector."""
    return wp.from_torch(tensor, dtype=dtype, return_ctype=True)


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


@functools.cache
def _loaded_kernels(device: torch.device, channels: int) -> wp.Kernel:
    """Initialise warp (silently) and load both kernel modules on `device`, compiling them on first
    use (warp caches the binaries on disk), before CPU threads or a CUDA graph capture need them.
    Returns the resolve kernel for `channels`."""
    wp.config.log_level = wp.LOG_ERROR  # no "module loaded" chatter
    with contextlib.nullcontext() if torch.cuda.is_available() else _native_stderr_silenced():
        wp.init()
    resolve = _resolve_kernel(channels)
    for module in (_zbuffer_kernel.module, resolve.module):
        wp.load_module(module, device=wp.device_from_torch(device))
    return resolve


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
