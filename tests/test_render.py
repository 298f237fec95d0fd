"""The point renderer: warp kernels vs the torch reference, and known geometry derived by hand."""

import math

import pytest
import torch

from rvt2cli.render import (
    NUM_CHANNELS,
    RVT1_VIEWS,
    RVT2_VIEWS,
    Cameras,
    channels_from_render,
    cube_rig,
    network_images,
    project,
    render,
    render_scene,
    zoom_rig,
)

BACKENDS = ("warp", "torch")
CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


# ---------------------------------------------------------------------------------------------
# Helpers


def look_at(eye: tuple[float, float, float], target=(0.0, 0.0, 0.0)) -> tuple[torch.Tensor, torch.Tensor]:
    """OpenCV-frame rotation and translation of a camera at `eye` looking at `target`, world z up."""
    eye_t = torch.tensor(eye)
    forward = torch.nn.functional.normalize(torch.tensor(target) - eye_t, dim=0)
    right = torch.nn.functional.normalize(torch.linalg.cross(forward, torch.tensor([0.0, 0.0, 1.0])), dim=0)
    down = torch.linalg.cross(forward, right)
    rotation = torch.stack([right, down, forward])
    return rotation, -rotation @ eye_t


def pinhole_cameras(batch: int, device="cpu") -> Cameras:
    eyes = [(2.5, -2.0, 1.8), (-1.5, -2.5, 2.2), (2.0, 2.0, 1.0)][:batch]
    rotations, translations = zip(*(look_at(e) for e in eyes))
    return Cameras.create(
        torch.stack(rotations)[:, None].to(device), torch.stack(translations)[:, None].to(device),
        fx=80.0, fy=80.0, cx=32.0, cy=24.0, near=0.5, far=6.0, ortho=False,
    )


def random_clouds(seed: int, batch: int = 3, n: int = 2500, channels: int = 5, spread: float = 1.1, centers=None):
    """Uniform clouds (some points outside the view volume) with exact duplicates (depth ties), a few
    non-finite points and different sizes via num_points."""
    g = torch.Generator().manual_seed(seed)
    points = (torch.rand(batch, n, 3, generator=g) * 2 - 1) * spread
    if centers is not None:
        points = points + centers[:, None]
    points[:, n // 2 : n // 2 + 300] = points[:, :300]
    points[0, 7, 1] = math.nan
    points[1, 11, 0] = math.inf
    points[-1, 13, 2] = -math.inf
    features = torch.randn(batch, n, channels, generator=g)
    num_points = torch.tensor([n, 2 * n // 3, n // 3][:batch])
    return points, features, num_points


def scene(rig: str, seed: int, device="cpu"):
    """(points, features, num_points, cameras, image_size, pixel width in world units) for a rig."""
    if rig == "cube3":
        cameras, size, spread, centers = cube_rig(RVT2_VIEWS, 64, batch_size=3), 64, 1.1, None
    elif rig == "cube5":
        cameras, size, spread, centers = cube_rig(RVT1_VIEWS, 48, batch_size=3), 48, 1.1, None
    elif rig == "zoom":
        centers = torch.rand(3, 3, generator=torch.Generator().manual_seed(seed + 100)) - 0.5
        cameras, size, spread = zoom_rig(centers, zoom=4.0, image_size=64), 64, 0.3
    else:
        cameras, size, spread, centers = pinhole_cameras(3), (48, 64), 1.1, None
    points, features, num_points = random_clouds(seed, spread=spread, centers=centers)
    pixel = 2 / cameras.params[0, 0, 12].item()  # world width of a pixel in the orthographic rigs
    on = lambda t: t.to(device)  # noqa: E731
    return on(points), on(features), on(num_points), cameras.to(device), size, pixel


def assert_same_render(a, b, cameras: Cameras) -> None:
    assert torch.equal(a.index, b.index), f"{(a.index != b.index).sum().item()} pixels differ"
    assert torch.equal(a.features, b.features)
    depth_range = (cameras.far - cameras.near)[..., None, None]
    assert ((a.depth - b.depth).abs() <= 1e-6 * depth_range).all()


def render_both(*args, **kwargs):
    return [render(*args, backend=backend, **kwargs) for backend in BACKENDS]


def single_point_render(point, cameras, size, backend, **kwargs):
    points = torch.tensor([[point]], dtype=torch.float32)
    return render(points, points.clone(), cameras, size, backend=backend, **kwargs)


# ---------------------------------------------------------------------------------------------
# warp == torch reference


@pytest.mark.parametrize("splat", ["off", "1.5px", "capped"])
@pytest.mark.parametrize("rig", ["cube3", "cube5", "zoom", "pinhole"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_warp_matches_reference(seed, rig, splat):
    points, features, num_points, cameras, size, pixel = scene(rig, seed)
    radius, cap = {"off": (0.0, 8), "1.5px": (1.5 * pixel, 8), "capped": (5 * pixel, 3)}[splat]
    if rig == "pinhole":
        radius = {"off": 0.0, "1.5px": 0.03, "capped": 0.08}[splat]
    fast, reference = render_both(points, features, cameras, size, num_points, radius, max_splat_px=cap)
    assert_same_render(fast, reference, cameras)
    assert fast.hit.any() and not fast.hit.all()
    assert (fast.index < num_points[:, None, None, None]).all()


def test_depth_ties_go_to_the_lower_index():
    p = [0.375, -0.625, 0.125]
    points = torch.tensor([[[0.9, 0.9, 0.9], p, p, p]])
    for backend in BACKENDS:
        rendered = render(points, points.clone(), cube_rig(image_size=8), 8, backend=backend)
        assert rendered.index[0, 0, 2, 6] == 1  # top view, see test_point_lands_on_hand_derived_pixel


# ---------------------------------------------------------------------------------------------
# Known geometry. Cube rig with W = 8: a pixel is 0.25 wide, pixel i spans [-1 + i/4, -1 + (i+1)/4].
# The point (0.375, -0.625, 0.125) sits at voxel centre (i, j, k) = (5, 1, 4). From the view table
# (image right, image down, camera origin on the face it looks through):
#   top:   right = -y -> u = 4*0.625 + 4 = 6.5,  down = -x -> v = 4*-0.375 + 4 = 2.5, depth = 1 - z
#   front: right = +y -> u = 1.5,                down = -z -> v = 3.5,                depth = 1 - x
#   right: right = +x -> u = 5.5,                v = 3.5,                             depth = y + 1
#   back:  right = -y -> u = 6.5,                v = 3.5,                             depth = x + 1
#   left:  right = -x -> u = 2.5,                v = 3.5,                             depth = 1 - y

POINT = (0.375, -0.625, 0.125)
EXPECTED_PIXEL = {  # view: (row, col, depth)
    "top": (2, 6, 0.875),
    "front": (3, 1, 0.625),
    "right": (3, 5, 0.375),
    "back": (3, 6, 1.375),
    "left": (3, 2, 1.625),
}


@pytest.mark.parametrize("backend", BACKENDS)
def test_point_lands_on_hand_derived_pixel(backend):
    cameras = cube_rig(RVT1_VIEWS, image_size=8)
    rendered = single_point_render(POINT, cameras, 8, backend)
    for v, view in enumerate(RVT1_VIEWS):
        row, col, depth = EXPECTED_PIXEL[view]
        expected = torch.full((8, 8), -1)
        expected[row, col] = 0
        assert torch.equal(rendered.index[0, v], expected), view
        assert rendered.depth[0, v, row, col].item() == pytest.approx(depth, abs=1e-6), view
        assert torch.equal(rendered.features[0, v, row, col], torch.tensor(POINT)), view


def test_project_gives_pixel_centres_and_depth():
    cameras = cube_rig(RVT1_VIEWS, image_size=8)
    uv, depth = project(torch.tensor([[POINT]]), cameras)
    assert uv.shape == (1, 5, 1, 2) and depth.shape == (1, 5, 1)
    for v, view in enumerate(RVT1_VIEWS):
        row, col, expected_depth = EXPECTED_PIXEL[view]
        assert uv[0, v, 0].tolist() == pytest.approx([col + 0.5, row + 0.5], abs=1e-6)
        assert depth[0, v, 0].item() == pytest.approx(expected_depth, abs=1e-6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_nearer_point_occludes_farther(backend):
    low, high = POINT, (POINT[0], POINT[1], 0.625)  # same top pixel (2, 6); high is nearer the top camera
    cameras = cube_rig(image_size=8)
    for order, nearer_index in (([low, high], 1), ([high, low], 0)):
        points = torch.tensor([order])
        rendered = render(points, points.clone(), cameras, 8, backend=backend)
        assert rendered.index[0, 0, 2, 6] == nearer_index
        assert rendered.depth[0, 0, 2, 6].item() == pytest.approx(0.375, abs=1e-6)
        assert rendered.hit[0, 1].sum() == 2  # side by side in the front view


@pytest.mark.parametrize("backend", BACKENDS)
def test_non_finite_points_are_dropped(backend):
    nan, inf = math.nan, math.inf
    points = torch.tensor([[[nan, 0.0, 0.0], [0.0, inf, 0.0], list(POINT), [0.0, 0.0, -inf], [nan, nan, nan]]])
    rendered = render(points, torch.ones(1, 5, 2), cube_rig(RVT1_VIEWS, image_size=8), 8, backend=backend)
    assert (rendered.hit.sum((2, 3)) == 1).all()
    assert set(rendered.index.unique().tolist()) == {-1, 2}


def assert_background(rendered) -> None:
    assert (rendered.index == -1).all()
    assert (rendered.features == 0).all() and (rendered.depth == 0).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_empty_and_invisible_clouds_give_background(backend):
    cameras = cube_rig(image_size=8, batch_size=2)
    empty = torch.zeros(2, 0, 3)
    assert_background(render(empty, torch.zeros(2, 0, 4), cameras, 8, splat_radius=0.3, backend=backend))
    no_scenes = render(
        torch.zeros(0, 5, 3), torch.zeros(0, 5, 4), cube_rig(batch_size=0), 8, splat_radius=0.3, backend=backend
    )
    assert no_scenes.index.shape == (0, 3, 8, 8) and no_scenes.features.shape == (0, 3, 8, 8, 4)
    points = torch.tensor([[[3.0, 3.0, 3.0], [0.0, 0.0, 1.5]], [[-1.5, 0.0, 0.0], [0.2, -1.01, 0.3]]])
    assert_background(render(points, points.clone(), cameras, 8, backend=backend))
    inside = torch.zeros(2, 2, 3)
    assert_background(render(inside, inside.clone(), cameras, 8, torch.zeros(2, dtype=torch.int64), backend=backend))
    behind = torch.tensor([[[-3.0, 3.0, -2.0], [2.5, -2.0, 1.8]]])  # behind / at the pinhole's centre
    assert_background(render(behind, behind.clone(), pinhole_cameras(1), (48, 64), splat_radius=0.05, backend=backend))


@pytest.mark.parametrize("backend", BACKENDS)
def test_zoom_rig_centre_and_culling(backend):
    center = torch.tensor([[0.3, -0.2, 0.1]])
    cameras = zoom_rig(center, zoom=4.0, image_size=8)  # the box center +- 0.25
    rendered = single_point_render(center[0].tolist(), cameras, 8, backend)
    for v in range(3):
        # The centre is the corner shared by the four central pixels; floor puts it in (4, 4).
        assert rendered.index[0, v, 4, 4] == 0 and rendered.hit[0, v].sum() == 1
        assert rendered.depth[0, v, 4, 4].item() == pytest.approx(0.25, abs=1e-6)
    for axis in range(3):
        for sign in (1.0, -1.0):
            offset = torch.zeros(3)
            offset[axis] = sign
            inside = single_point_render((center[0] + 0.24 * offset).tolist(), cameras, 8, backend)
            outside = single_point_render((center[0] + 0.26 * offset).tolist(), cameras, 8, backend)
            assert (inside.hit.sum((2, 3)) == 1).all(), (axis, sign)
            assert not outside.hit.any(), (axis, sign)


def voxel_centres(indices: torch.Tensor, size: int) -> torch.Tensor:
    return -1 + (indices + 0.5) * (2 / size)


@pytest.mark.parametrize("size, zoom", [(224, 1.0), (16, 4.0)])
def test_pixel_centres_line_up_with_voxel_grid(size, zoom):
    g = torch.Generator().manual_seed(0)
    ijk = torch.cat([torch.randint(0, size, (3000, 3), generator=g), torch.tensor([[0, 0, 0], [size - 1] * 3])])
    center = torch.tensor([0.3, -0.2, 0.1]) if zoom != 1 else torch.zeros(3)
    points = center + voxel_centres(ijk, size) / zoom
    cameras = zoom_rig(center[None], zoom=zoom, image_size=size)
    uv, depth = project(points[None], cameras)
    i, j, k = ijk.unbind(-1)
    last = size - 1
    # (col, row, depth slot) of voxel (i, j, k), read off the view table: top (right -y, down -x,
    # looking down -z), front (right +y, down -z, looking along -x), right (right +x, down -z, along +y).
    expected = {"top": (last - j, last - i, last - k), "front": (j, last - k, last - i), "right": (i, last - k, j)}
    for v, view in enumerate(RVT2_VIEWS):
        col, row, slot = expected[view]
        assert torch.allclose(uv[0, v], torch.stack([col, row], -1) + 0.5, atol=1e-3), view
        assert torch.allclose(depth[0, v] * zoom * size / 2, slot + 0.5, atol=1e-3), view


# ---------------------------------------------------------------------------------------------
# Splatting


def disc(row: int, col: int, radius: float, size: int) -> torch.Tensor:
    r, c = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    return (r - row) ** 2 + (c - col) ** 2 <= radius**2


@pytest.mark.parametrize("backend", BACKENDS)
def test_single_point_splats_to_a_disc(backend):
    size, pixel = 16, 2 / 16
    point = voxel_centres(torch.tensor([7, 9, 8]), size).tolist()  # top view: row 15 - 7, col 15 - 9
    rendered = single_point_render(point, cube_rig(image_size=size), size, backend, splat_radius=2.2 * pixel)
    expected = disc(8, 6, 2.2, size)
    assert expected.sum() == 13  # offsets with dy^2 + dx^2 in {0, 1, 2, 4}
    assert torch.equal(rendered.hit[0, 0], expected)
    assert torch.allclose(rendered.depth[0, 0][expected], torch.tensor(1 - point[2]), atol=1e-6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_splat_disc_is_capped(backend):
    size, pixel = 16, 2 / 16
    point = voxel_centres(torch.tensor([7, 9, 8]), size).tolist()
    rendered = single_point_render(
        point, cube_rig(image_size=size), size, backend, splat_radius=10 * pixel, max_splat_px=3
    )
    assert torch.equal(rendered.hit[0, 0], disc(8, 6, 3, size))


@pytest.mark.parametrize("backend", BACKENDS)
def test_splat_prefers_the_nearer_disc(backend):
    size, pixel = 16, 2 / 16
    far_point = voxel_centres(torch.tensor([7, 9, 3]), size)  # top view (8, 6), deep
    near_point = voxel_centres(torch.tensor([7, 8, 12]), size)  # top view (8, 7), near the camera
    points = torch.stack([far_point, near_point])[None]
    cameras = cube_rig(image_size=size)
    rendered = render(points, points.clone(), cameras, size, splat_radius=1.2 * pixel, backend=backend)
    top = rendered.index[0, 0]
    assert top[8, 6] == 1 and top[8, 7] == 1  # the near disc covers the far point's own pixel
    assert top[8, 5] == 0 and top[8, 8] == 1  # beyond the near disc the far point still shows


# ---------------------------------------------------------------------------------------------
# Network channels


@pytest.mark.parametrize("backend", BACKENDS)
def test_network_channels(backend):
    points = torch.tensor([[POINT]])
    rgb = torch.tensor([[[1.0, 0.5, 0.0]]])
    cameras = cube_rig(image_size=8)
    images = network_images(points, rgb, cameras, 8, splat_radius=0.0, backend=backend)
    assert images.shape == (1, 3, NUM_CHANNELS, 8, 8) and NUM_CHANNELS == 10
    top_hit = images[0, 0, :, 2, 6].tolist()
    assert top_hit == pytest.approx([*POINT, 1.0, 0.0, -1.0, 0.875 / 2, 2 * 6.5 / 8 - 1, 2 * 2.5 / 8 - 1, -1.0])
    background = images[0, 0, :, 0, 0].tolist()
    assert background == pytest.approx([0, 0, 0, 0, 0, 0, -1, -0.875, -0.875, -1])
    assert images[0, :, 9, 5, 5].tolist() == [-1.0, 0.0, 1.0]  # view index over 3 views
    rendered = render_scene(points, rgb, cameras, 8, splat_radius=0.0, backend=backend)
    assert rendered.features.shape == (1, 3, 8, 8, 6)
    assert torch.equal(channels_from_render(rendered, cameras), images)


def test_single_view_channel_is_zero():
    points = torch.tensor([[POINT]])
    images = network_images(points, torch.rand(1, 1, 3), cube_rig(("top",), 8), 8)
    assert (images[0, 0, 9] == 0).all()


# ---------------------------------------------------------------------------------------------
# Inputs and cameras


def test_bad_inputs_raise_value_error():
    cameras = cube_rig(image_size=8)
    points = torch.zeros(1, 4, 3)
    with pytest.raises(ValueError, match=r"points must be float32 \[B, N, 3\], got \(1, 4, 2\)"):
        render(torch.zeros(1, 4, 2), points, cameras, 8)
    with pytest.raises(ValueError, match="float32"):
        render(points.double(), points, cameras, 8)
    with pytest.raises(ValueError, match=r"features .* got \(1, 3, 3\)"):
        render(points, torch.zeros(1, 3, 3), cameras, 8)
    with pytest.raises(ValueError, match="batch size"):
        render(torch.zeros(2, 4, 3), torch.zeros(2, 4, 3), cameras, 8)
    with pytest.raises(ValueError, match="num_points"):
        render(points, points, cameras, 8, num_points=torch.tensor([4], dtype=torch.int32))
    with pytest.raises(ValueError, match="image_size"):
        render(points, points, cameras, (8, 0))
    with pytest.raises(ValueError, match="backend"):
        render(points, points, cameras, 8, backend="pytorch3d")
    with pytest.raises(ValueError, match="splat_radius"):
        render(points, points, cameras, 8, splat_radius=-1.0)
    with pytest.raises(ValueError, match=r"Cameras.params must be float32 \[B, V, 19\], got \(1, 3, 18\)"):
        Cameras(torch.zeros(1, 3, 18))
    with pytest.raises(ValueError, match="unknown views"):
        cube_rig(("top", "bottom"))


def test_cameras_helpers():
    cameras = Cameras.cat([cube_rig(batch_size=2), zoom_rig(torch.ones(1, 3))])
    assert cameras.batch_size == len(cameras) == 3 and cameras.num_views == 3
    assert torch.equal(cameras[2].params, zoom_rig(torch.ones(1, 3)).params)
    assert cameras[0:2].batch_size == 2 and cameras[-1].batch_size == 1
    assert cameras.to("cpu").device.type == "cpu"
    assert cameras.rotation.shape == (3, 3, 3, 3) and cameras.translation.shape == (3, 3, 3)
    assert cameras.is_ortho.all() and torch.equal(cameras.far, torch.tensor([[2.0] * 3] * 2 + [[0.5] * 3]))
    for rotation in cube_rig(RVT1_VIEWS).rotation[0]:  # every view is a proper rotation
        assert torch.allclose(rotation @ rotation.T, torch.eye(3)) and torch.det(rotation) == pytest.approx(1.0)


# ---------------------------------------------------------------------------------------------
# CUDA


@CUDA
@pytest.mark.parametrize("splat", [False, True])
@pytest.mark.parametrize("rig", ["cube3", "zoom", "pinhole"])
def test_warp_matches_reference_on_cuda(rig, splat):
    points, features, num_points, cameras, size, pixel = scene(rig, seed=3, device="cuda")
    radius = (0.03 if rig == "pinhole" else 1.5 * pixel) if splat else 0.0
    fast, reference = render_both(points, features, cameras, size, num_points, radius)
    assert fast.index.is_cuda
    assert_same_render(fast, reference, cameras)
    cpu = render(points.cpu(), features.cpu(), cameras.to("cpu"), size, num_points.cpu(), radius)
    assert torch.equal(cpu.index, fast.index.cpu())


@CUDA
def test_render_captures_in_a_cuda_graph():
    points, features, num_points, cameras, size, pixel = scene("cube3", seed=4, device="cuda")
    expected = render(points, features, cameras, size, num_points, 1.5 * pixel)  # also loads the kernels
    stream = torch.cuda.Stream()
    stream.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(stream):
        render(points, features, cameras, size, num_points, 1.5 * pixel)
    torch.cuda.current_stream().wait_stream(stream)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        captured = render(points, features, cameras, size, num_points, 1.5 * pixel)
    points.add_(0.0)
    graph.replay()
    torch.cuda.synchronize()
    assert_same_render(captured, expected, cameras)
