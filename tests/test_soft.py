"""Differentiable silhouettes: hand-computed blends, agreement with the hard raster, pose
gradients against finite differences, and single-view pose recovery."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch
import trimesh

from roboseg.camera import look_at
from roboseg.errors import CameraError, RobotModelError
from roboseg.render.raster import render_hard
from roboseg.render.soft import (
    INSIDE_MIN,
    SilhouetteRenderer,
    contour_edges,
    mesh_edges,
    project_valid,
    render_soft,
    row_pair_weight,
)
from roboseg.robot import RobotModel, load_robot

MED7 = Path(__file__).resolve().parents[2] / "shared" / "robots" / "lbr_med7" / "lbr_med7.urdf"
F64 = torch.float64


def _pinhole(f: float, cx: float, cy: float) -> torch.Tensor:
    return torch.tensor([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]], dtype=F64)


def _square(u0: float, u1: float, v0: float, v1: float, f: float = 10.0) -> torch.Tensor:
    """[1, 4, 3] corners at z = 1 m projecting to the pixel box [u0, u1] × [v0, v1] (K=f, c=0)."""
    corners = [[u0, v0], [u1, v0], [u1, v1], [u0, v1]]
    return torch.tensor([[[u / f, v / f, 1.0] for u, v in corners]], dtype=F64)


SQUARE_FACES = torch.tensor([[0, 1, 2], [0, 2, 3]])


def _hat(xi: torch.Tensor) -> torch.Tensor:
    """4×4 matrix of the twist ``xi = (rho, omega)`` (metres, radians)."""
    X = xi.new_zeros(4, 4)
    X[0, 1], X[0, 2], X[1, 2] = -xi[5], xi[4], -xi[3]
    X[1, 0], X[2, 0], X[2, 1] = xi[5], -xi[4], xi[3]
    X[:3, 3] = xi[:3]
    return X


def _apply(xi: torch.Tensor, T_cam_base: torch.Tensor, verts_base: torch.Tensor) -> torch.Tensor:
    """Vertices ``[B, V, 3]`` in the camera frame after the left twist ``exp(xi) T_cam_base``."""
    T = torch.linalg.matrix_exp(_hat(xi)) @ T_cam_base
    return verts_base @ T[:3, :3].T + T[:3, 3]


@pytest.fixture
def one_thread() -> Iterator[None]:
    """Pin torch to one thread: on a shared machine spinning intra-op threads dominate."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _rotation(w: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of the axis-angle vector ``w`` (radians)."""
    return torch.linalg.matrix_exp(_hat(torch.cat([w.new_zeros(3), w])))[:3, :3]


# --- topology and contour edges -------------------------------------------------------------


def test_mesh_edges_of_two_triangles() -> None:
    topo = mesh_edges(SQUARE_FACES)
    assert topo.edges.tolist() == [[0, 1], [0, 2], [0, 3], [1, 2], [2, 3]]
    assert topo.open.tolist() == [True, False, True, True, True]
    assert topo.opposite[1].tolist() == [1, 3]  # the diagonal: third vertices of both faces
    assert topo.opposite[0].tolist() == [2, -1]


def test_mesh_edges_of_closed_mesh_has_no_open_edges() -> None:
    box = trimesh.creation.box()
    topo = mesh_edges(torch.as_tensor(box.faces))
    assert topo.edges.shape[0] == 18  # 12 triangles × 3 / 2
    assert not bool(topo.open.any())
    assert bool((topo.opposite >= 0).all())


def test_contour_edges_of_tetrahedron_seen_from_a_vertex() -> None:
    # apex straight in front of the base triangle's centroid: the 3 base edges are the outline
    verts = torch.tensor(
        [[[-1.0, -1.0, 3.0], [1.0, -1.0, 3.0], [0.0, 1.0, 3.0], [0.0, -1 / 3, 2.0]]], dtype=F64
    )
    faces = torch.tensor([[0, 1, 2], [0, 1, 3], [1, 2, 3], [2, 0, 3]])
    topo = mesh_edges(faces)
    uv, valid = project_valid(verts, _pinhole(10.0, 0.0, 0.0))
    is_contour, _ = contour_edges(uv, valid, topo)
    outline = {tuple(e) for e in topo.edges[is_contour[0]].tolist()}
    assert outline == {(0, 1), (1, 2), (0, 2)}


def test_row_pair_weight_ramps_around_45_degrees() -> None:
    d = torch.tensor([[0.0, 1.0], [1.0, 0.0], [1.0, 1.0], [-1.0, 3.0], [3.0, -1.0], [1.0, 1.5]])
    # ratio |dv|/(|du|+|dv|) = 1, 0, 0.5, 0.75, 0.25, 0.6 → weight 1, 0, 0.5, 1, 0, 1
    assert row_pair_weight(d).tolist() == pytest.approx([1.0, 0.0, 0.5, 1.0, 0.0, 1.0])


# --- hand-computed blends -------------------------------------------------------------------


def test_axis_aligned_square_gets_box_filter_coverage() -> None:
    # square over u ∈ [2.3, 9.8], v ∈ [1.6, 8.2]: hard columns 3..9, rows 2..8
    verts = _square(2.3, 9.8, 1.6, 8.2).requires_grad_(True)
    K = _pinhole(10.0, 0.0, 0.0)
    hard = render_hard(verts.detach(), SQUARE_FACES, K, 12, 13)
    soft = render_soft(verts, SQUARE_FACES, K, 12, 13, raster=hard)[0]
    expected = torch.zeros(12, 13, dtype=F64)
    expected[2:9, 3:10] = 1.0
    expected[2:9, 2] = 0.2  # left edge at 2.3 covers 0.2 of column 2
    expected[2:9, 10] = 0.3  # right edge at 9.8 covers 0.3 of column 10
    expected[2, 3:10] = 0.9  # top edge at 1.6 leaves 0.9 of row 2
    expected[8, 3:10] = 0.7  # bottom edge at 8.2 leaves 0.7 of row 8
    torch.testing.assert_close(soft, expected, atol=1e-9, rtol=0)
    # moving the square right by δ pixels: Σ soft·u grows by the blended area per row
    # (7 rows × (column 10 gains +1·10, column 2 loses −1·2)) = 56 pixel² per pixel
    (soft * torch.arange(13, dtype=F64)).sum().backward()
    shift = verts.grad[0, :, 0].sum() / 10.0  # d/du = (1/f) d/dx at z = 1
    assert shift.item() == pytest.approx(56.0)


def test_soft_is_continuous_when_an_edge_crosses_a_pixel_centre() -> None:
    K = _pinhole(10.0, 0.0, 0.0)
    before, after = _square(2.999, 9.8, 1.6, 8.2), _square(3.001, 9.8, 1.6, 8.2)
    s0 = render_soft(before, SQUARE_FACES, K, 12, 13)[0]
    s1 = render_soft(after, SQUARE_FACES, K, 12, 13)[0]
    # column 3 flips from inside to outside but its value only moves through 1/2
    assert s0[4, 3].item() == pytest.approx(0.501, abs=2e-3)
    assert s1[4, 3].item() == pytest.approx(0.499, abs=1e-9)
    assert (s1 - s0).abs().max().item() < 3e-3


# --- agreement with the hard raster ---------------------------------------------------------


def _sphere_scene(n_views: int = 3) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.2)
    box = trimesh.creation.box(extents=(0.5, 0.08, 0.08))
    both = trimesh.util.concatenate([mesh, box])
    verts = torch.as_tensor(both.vertices, dtype=F64)
    shift = torch.rand(n_views, 1, 3, generator=g, dtype=F64) * 0.2 - 0.1
    verts = verts.expand(n_views, -1, -1) + shift + torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    return verts, torch.as_tensor(both.faces), _pinhole(90.0, 47.5, 39.5)


def test_soft_thresholds_to_the_hard_silhouette() -> None:
    verts, faces, K = _sphere_scene()
    hard = render_hard(verts, faces, K, 80, 96)
    soft = render_soft(verts, faces, K, 80, 96)
    assert soft.shape == (3, 80, 96) and soft.dtype == F64
    assert soft.min().item() >= 0.0 and soft.max().item() <= 1.0
    assert torch.equal(soft > 0.5, hard)
    assert soft[hard].min().item() >= INSIDE_MIN
    boundary = (soft > 0) & (soft < 1)
    assert 0 < boundary.sum().item() < 0.3 * hard.sum().item()


def test_renderer_matches_functional_api() -> None:
    verts, faces, K = _sphere_scene(2)
    renderer = SilhouetteRenderer(faces, 80, 96, backend="torch")
    assert torch.equal(renderer.hard(verts, K), render_hard(verts, faces, K, 80, 96))
    torch.testing.assert_close(renderer.soft(verts, K), render_soft(verts, faces, K, 80, 96))


def test_input_errors_name_the_value() -> None:
    verts, faces, K = _sphere_scene(1)
    with pytest.raises(CameraError, match="K must be"):
        render_soft(verts, faces, torch.eye(4, dtype=F64), 80, 96)
    with pytest.raises(RobotModelError, match="faces"):
        render_soft(verts, faces[:, :2], K, 80, 96)
    with pytest.raises(RobotModelError, match=r"\[0, \d+\), got 0\.\.99999"):
        render_soft(verts, torch.tensor([[0, 1, 99999]]), K, 80, 96)
    with pytest.raises(ValueError, match="backend 'cuda'"):
        SilhouetteRenderer(faces, 80, 96, backend="cuda")  # type: ignore[arg-type]
    with pytest.raises(CameraError, match="hard raster"):
        render_soft(verts, faces, K, 80, 96, raster=torch.zeros(1, 8, 8, dtype=torch.bool))


def test_per_view_intrinsics_and_near_plane_give_finite_gradients() -> None:
    verts, faces, K = _sphere_scene(2)
    verts = verts.clone()
    verts[1, :40, 2] = -0.5  # part of the second view's mesh behind the camera
    Ks = torch.stack([K, K * torch.tensor([[1.2], [1.2], [1.0]], dtype=F64)])
    verts.requires_grad_(True)
    soft = render_soft(verts, faces, Ks, 80, 96)
    torch.testing.assert_close(soft[0], render_soft(verts[:1], faces, K, 80, 96)[0])
    assert torch.equal(soft > 0.5, render_hard(verts.detach(), faces, Ks, 80, 96))
    (soft * torch.linspace(0, 1, 96, dtype=F64)).sum().backward()
    assert bool(torch.isfinite(verts.grad).all())
    assert verts.grad[1, :40].abs().sum().item() == 0.0  # culled vertices get no gradient
    assert verts.grad[1, 40:].abs().sum().item() > 0.0


# --- gradients --------------------------------------------------------------------------------


def test_disc_translation_gradient_equals_its_area() -> None:
    # d/dδ Σ soft·u for a horizontal shift δ (pixels) is the silhouette's area (pixels²)
    n, r = 96, 12.3
    ang = torch.arange(n, dtype=F64) * (2 * math.pi / n)
    rim = torch.stack([r * ang.cos() + 20.4, r * ang.sin() + 19.7], 1)
    uv = torch.cat([torch.tensor([[20.4, 19.7]], dtype=F64), rim])
    verts = torch.cat([uv / 100.0, torch.ones(n + 1, 1, dtype=F64)], 1)[None]
    verts.requires_grad_(True)
    faces = torch.tensor([[0, 1 + i, 1 + (i + 1) % n] for i in range(n)])
    soft = render_soft(verts, faces, _pinhole(100.0, 0.0, 0.0), 40, 42)
    (soft[0] * torch.arange(42, dtype=F64)).sum().backward()
    moment_rate = verts.grad[0, :, 0].sum().item() / 100.0
    area = 0.5 * n * r * r * math.sin(2 * math.pi / n)
    # the pair blend is an exact box filter only for axis-aligned edges; on a disc the
    # per-row / per-column blends differ from the true area by well under 2 %
    assert moment_rate == pytest.approx(area, rel=0.02)
    assert soft.sum().item() == pytest.approx(area, rel=0.02)


def _scene_med7_or_default(
    size: int, n: int, dtype: torch.dtype = F64
) -> tuple[RobotModel, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Med 7 (default robot when absent) decimated by 95 %: model, ``n`` posed vertex sets
    ``[n, V, 3]`` (base frame), ``T_cam_base`` looking at it and ``K`` for ``size``²."""
    robot = load_robot(MED7 if MED7.exists() else None).decimated(0.95).to(dtype=dtype)
    q = robot.random_joints(n, torch.Generator().manual_seed(3))
    verts = robot.posed_vertices(q)
    eye = torch.tensor([1.2, 0.8, 0.9], dtype=dtype)
    T = look_at(eye, torch.tensor([0.0, 0.0, 0.5], dtype=dtype))
    f = size / (2 * math.tan(math.radians(25)))
    K = torch.tensor([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]], dtype=dtype)
    return robot, verts, T, K


def test_soft_approximates_supersampled_coverage(one_thread: None) -> None:
    # reference: pixel area coverage from an 8×8 supersampled hard render (slow, exact in the
    # limit); the contour-edge blend must be far closer to it than the hard mask is
    size, ss = 128, 8
    robot, verts, T, K = _scene_med7_or_default(size, 3)
    verts_cam = _apply(torch.zeros(6, dtype=F64), T, verts)
    soft = render_soft(verts_cam, robot.faces, K, size, size)
    K_fine = K.clone()
    K_fine[:2] *= ss
    K_fine[:2, 2] += (ss - 1) / 2  # sub-pixel centres at (k + 1/2)/ss - 1/2
    fine = render_hard(verts_cam, robot.faces, K_fine, size * ss, size * ss).to(F64)
    coverage = torch.nn.functional.avg_pool2d(fine[:, None], ss)[:, 0]
    band = ((coverage > 0) & (coverage < 1)) | ((soft > 0) & (soft < 1))
    err_soft = (soft - coverage)[band].abs().mean().item()
    err_hard = ((soft > 0.5).to(F64) - coverage)[band].abs().mean().item()
    assert band.sum().item() > 300
    assert err_soft < 0.25 * err_hard, (err_soft, err_hard)
    assert soft.sum().item() == pytest.approx(coverage.sum().item(), rel=5e-3)


def test_pose_gradient_matches_central_differences(one_thread: None) -> None:
    size = 96
    robot, verts, T, K = _scene_med7_or_default(size, 2)
    g = torch.Generator().manual_seed(1)
    noise = torch.rand(1, 1, size, size, generator=g, dtype=F64)
    weight = torch.nn.functional.avg_pool2d(noise, 15, 1, 7, count_include_pad=False)[0, 0]

    def loss(xi: torch.Tensor) -> torch.Tensor:
        soft = render_soft(_apply(xi, T, verts), robot.faces, K, size, size)
        return (soft * weight).sum()

    xi = torch.zeros(6, dtype=F64, requires_grad=True)
    loss(xi).backward()
    # The soft image is continuous and piecewise linear in the vertices, with kinks where a
    # crossing passes a pair's midpoint. A step of 1e-6 m / 1e-6 rad moves edges by ~1e-4 px,
    # so a central difference stays on one linear piece for all but a handful of pixels.
    h = 1e-6
    fd = torch.zeros(6, dtype=F64)
    with torch.no_grad():
        for i in range(6):
            e = torch.zeros(6, dtype=F64)
            e[i] = h
            fd[i] = (loss(e) - loss(-e)) / (2 * h)
    assert fd.abs().max() > 1.0  # the weight image makes every direction matter
    assert (xi.grad - fd).norm() / fd.norm() < 0.02


# --- pose recovery ----------------------------------------------------------------------------


def test_single_view_descent_recovers_the_pose(one_thread: None) -> None:
    size, dtype = 256, torch.float32
    robot, verts, T, K = _scene_med7_or_default(size, 1, dtype)
    renderer = SilhouetteRenderer(robot.faces, size, size, backend="torch")
    R_true, t_true = T[:3, :3], T[:3, 3]
    target = renderer.hard(verts @ R_true.T + t_true, K).to(dtype)
    g = torch.Generator().manual_seed(5)
    dt, dw = torch.randn(3, generator=g), torch.randn(3, generator=g)
    R0 = _rotation(dw / dw.norm() * math.radians(3.0)) @ R_true  # 3° about the base origin
    t0 = t_true + dt / dt.norm() * 0.02  # 2 cm
    t = torch.zeros(3, dtype=dtype, requires_grad=True)
    w = torch.zeros(3, dtype=dtype, requires_grad=True)
    opt = torch.optim.Adam([t, w], lr=2e-3)
    for _ in range(250):
        opt.zero_grad()
        soft = renderer.soft(verts @ (_rotation(w) @ R0).T + (t0 + t), K)
        loss = ((soft - target) ** 2).sum() / target.sum()
        loss.backward()
        opt.step()
    with torch.no_grad():
        err_t = (t0 + t - t_true).norm().item()
        cos = (((_rotation(w) @ R0 @ R_true.T).trace() - 1) / 2).clamp(-1, 1)
        err_deg = math.degrees(math.acos(cos.item()))
    assert err_t < 2e-3, f"translation error {err_t * 1e3:.2f} mm"
    assert err_deg < 0.2, f"rotation error {err_deg:.3f}°"


# --- nvdiffrast backend -----------------------------------------------------------------------


def test_clip_space_maps_pixel_centres_like_opencv() -> None:
    from roboseg.render.nvdiff import clip_space

    K = torch.tensor([[120.0, 0.5, 40.3], [0.0, 110.0, 30.7], [0.0, 0.0, 1.0]], dtype=F64)
    pts = torch.tensor([[[0.1, -0.2, 1.5], [-0.3, 0.05, 0.8]]], dtype=F64)
    clip = clip_space(pts, K, 60, 80, 0.01)
    ndc = clip[..., :2] / clip[..., 3:]
    # nvdiffrast samples pixel i at NDC (2i + 1) / size - 1, row 0 at NDC y = -1
    pix = torch.stack([(ndc[..., 0] + 1) * 80 / 2 - 0.5, (ndc[..., 1] + 1) * 60 / 2 - 0.5], -1)
    uv, _ = project_valid(pts, K)
    torch.testing.assert_close(pix, uv)
    depth = clip[..., 2] / clip[..., 3]  # near plane at -1, increasing with distance
    assert bool((depth > -1).all()) and depth[0, 0] > depth[0, 1]


def test_nvdiffrast_backend_agrees_with_torch() -> None:
    from roboseg.render import nvdiff

    if not nvdiff.available():
        pytest.skip("nvdiffrast or CUDA not available")
    verts, faces, K = _sphere_scene(2)
    verts, K = verts.float().cuda(), K.float().cuda()
    gpu = SilhouetteRenderer(faces, 80, 96, backend="nvdiffrast")
    cpu = SilhouetteRenderer(faces, 80, 96, backend="torch")
    hard_gpu, hard_cpu = gpu.hard(verts, K), cpu.hard(verts.cpu(), K.cpu())
    inter = (hard_gpu.cpu() & hard_cpu).sum().item()
    assert inter / (hard_gpu.cpu() | hard_cpu).sum().item() > 0.97
    v = verts.clone().requires_grad_(True)
    gpu.soft(v, K).sum().backward()
    assert v.grad is not None and bool(v.grad.abs().sum() > 0)
